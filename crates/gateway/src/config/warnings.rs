//! Warnings: settings that are valid but most likely not what was meant. They do not
//! stop `validate` or the service; `validate` prints them and the service logs them.

use super::keys::field;
use super::problem::{ConfigProblem, Problems};
use super::Config;
use crate::channel::RegisterKind;

/// Every warning of a valid configuration, with `file` as the origin.
///
/// - A Modbus `address` of 30001..=39999 or 40001..=49999 is most likely a 1-based
///   register number from a device manual ("30013" = input register 13 = PDU address
///   12): a device without that many registers answers exception 2 at run time.
pub fn warnings(cfg: &Config, file: &str) -> Vec<ConfigProblem> {
    let mut out = Problems::new(file);
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
