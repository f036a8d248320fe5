//! Warnings: settings that are valid but most likely not what was meant. They do not
//! stop `validate` or the service; `validate` prints them and the service logs them.

use std::collections::BTreeMap;

use super::keys::field;
use super::problem::{ConfigProblem, Problems};
use super::{Config, DeviceConfig};
use crate::channel::RegisterKind;

/// Every warning of a valid configuration, with `file` as the origin.
///
/// - A Modbus `address` of 30001..=39999 or 40001..=49999 is most likely a 1-based
///   register number from a device manual ("30013" = input register 13 = PDU address
///   12): a device without that many registers answers exception 2 at run time.
/// - Two TCP devices with the same `address` and `unit_id` are one device polled
///   twice, each over its own connection: most likely a copied entry whose address or
///   unit id was not changed. (On one RTU line the same unit id twice is an error.)
pub fn warnings(cfg: &Config, file: &str) -> Vec<ConfigProblem> {
    let mut out = Problems::new(file);
    let mut tcp: BTreeMap<(String, u8), &String> = BTreeMap::new();
    for (name, dev) in &cfg.devices {
        let DeviceConfig::Tcp(d) = dev else {
            continue;
        };
        let at = (d.address.trim().to_ascii_lowercase(), d.unit_id);
        if let Some(other) = tcp.insert(at, name) {
            out.push(
                field("devices", name, "unit_id"),
                format!(
                    "unit id {} at {} is also device `{other}`: the same device polled \
                     twice, over two connections; give one of them its own address or \
                     unit_id, or move its channels to `{other}`",
                    d.unit_id, d.address
                ),
            );
        }
    }
    for (name, ch) in &cfg.channels {
        let (Some(kind), Some(address)) = (ch.register, ch.address) else {
            continue;
        };
        if let Some(message) = one_based(kind, address) {
            out.push(field("channels", name, "address"), message);
        }
    }
    out.into_vec()
}

/// Why `address` looks like a 1-based register number, with the likely PDU address.
fn one_based(kind: RegisterKind, address: u16) -> Option<String> {
    let (base, named) = match address {
        30_001..=39_999 => (30_001, RegisterKind::Input),
        40_001..=49_999 => (40_001, RegisterKind::Holding),
        _ => return None,
    };
    let pdu = address - base;
    let table = |k: RegisterKind| match k {
        RegisterKind::Input => "input",
        RegisterKind::Holding => "holding",
    };
    let register = if kind == named {
        String::new()
    } else {
        format!(" and register = \"{}\"", table(named))
    };
    Some(format!(
        "{address} looks like the 1-based register number of a device manual ({} register \
         {}); addresses here are 0-based PDU addresses, so that register is address = \
         {pdu}{register}. A device without {address} registers answers exception 2 \
         (illegal data address) at run time.",
        table(named),
        pdu + 1
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    // Two TCP devices at one address and unit id passed `validate` silently; two RTU
    // devices with one unit id on a line are an error.
    #[test]
    fn two_tcp_devices_at_one_address_and_unit_get_a_warning_naming_both() {
        let device = |name: &str, address: &str, unit: u8| {
            format!(
                "[devices.{name}]\ntransport = \"tcp\"\naddress = \"{address}\"\nunit_id = {unit}\n\
                 [channels.t_{name}]\ndevice = \"{name}\"\nregister = \"input\"\naddress = 0\n\
                 data_type = \"u16\"\nscaling = {{ kind = \"direct\", gain = 0.1, offset_degc = 0.0 }}\n"
            )
        };
        let text = [
            device("good", "127.0.0.1:502", 1),
            device("bad", "127.0.0.1:502", 1),
            device("other_unit", "127.0.0.1:502", 2),
        ]
        .concat();
        let cfg = crate::config::load_str(&text, "dup.toml").expect("valid");
        let w: Vec<String> = warnings(&cfg, "dup.toml")
            .iter()
            .map(ToString::to_string)
            .collect();
        assert_eq!(w.len(), 1, "{w:#?}");
        // Devices are checked in name order: `good` comes after `bad`.
        assert!(
            w[0].starts_with(
                "dup.toml: devices.good.unit_id: unit id 1 at 127.0.0.1:502 is also device `bad`"
            ),
            "{}",
            w[0]
        );
    }

    // Issue 23, trap 5: `address = 30013` passed `validate` and failed at run time with
    // exception 2.
    #[test]
    fn a_1_based_address_gets_a_warning_with_the_0_based_one() {
        let m = one_based(RegisterKind::Input, 30_013).expect("warned");
        assert!(
            m.contains("input register 13") && m.contains("address = 12."),
            "{m}"
        );
        let m = one_based(RegisterKind::Input, 40_001).expect("warned");
        assert!(m.contains("address = 0 and register = \"holding\""), "{m}");
        assert_eq!(one_based(RegisterKind::Input, 30_000), None);
        assert_eq!(one_based(RegisterKind::Holding, 1_004), None);
        assert_eq!(one_based(RegisterKind::Holding, 50_000), None);
    }
}
