//! Warnings: settings that are valid but most likely not what was meant. They do not
//! stop `validate` or the service; `validate` prints them and the service logs them.

use std::collections::BTreeMap;
use std::path::Path;

use compgate_core::comp::{MAX_TAN_BETA_PER_K, STEEL_EXPANSION_PER_K};

use super::keys::field;
use super::problem::{check_host_port, peer_identity, ConfigProblem, Problems};
use super::{Config, DeviceConfig};
use crate::channel::RegisterKind;
use crate::source::config::DeviceCommon;
use crate::source::modbus::config::{ModbusCommon, RtuDeviceConfig};

/// Every warning of a valid configuration, with `file` as the origin.
///
/// - A Modbus `address` of 30001..=39999 or 40001..=49999 is most likely a 1-based
///   register number from a device manual ("30013" = input register 13 = PDU address
///   12): a device without that many registers answers exception 2 at run time.
/// - Two TCP devices with the same `address` and `unit_id` are one device polled
///   twice: most likely a copied entry whose address or unit id was not changed. (On
///   one RTU line the same unit id twice is an error.)
/// - Devices sharing a serial line whose `timeout_s` add up to more than their
///   smallest `poll_interval_s`: a silent one holds up the others. Not for units at
///   one TCP address: behind a TCP-to-RTU gateway each `timeout_s` must stay above the
///   gateway's own response timeout, so lowering them is no advice.
/// - A TCP device at the address and unit id of a Modbus NC module: its channels
///   would read the module's registers as temperatures (a copied address).
/// - A tan(beta) `coeff_per_degc` beyond [`MAX_TAN_BETA_PER_K`].
/// - An OPC UA target's or MQTT's `credentials_file` readable by group or others.
pub fn warnings(cfg: &Config, file: &str) -> Vec<ConfigProblem> {
    let mut out = Problems::new(file);
    let mut tcp: BTreeMap<(String, u8), &String> = BTreeMap::new();
    for (name, dev) in &cfg.devices {
        let DeviceConfig::Tcp(d) = dev else {
            continue;
        };
        let at = (peer_identity(&d.address), d.unit_id);
        if let Some(other) = tcp.insert(at, name) {
            out.push(
                field("devices", name, "unit_id"),
                format!(
                    "unit id {} at {} is also device `{other}`: the same device polled \
                     twice; give one of them its own address or unit_id, or move its \
                     channels to `{other}`",
                    d.unit_id, d.address
                ),
            );
        }
    }
    for (module, m) in cfg.modbus_targets() {
        // Port 0 is the simulated plant's to give each its own free port.
        if check_host_port(&m.address).is_err() {
            continue;
        }
        if let Some(name) = tcp.get(&(peer_identity(&m.address), m.unit_id)) {
            out.push(
                field("devices", name, "address"),
                format!(
                    "{} unit id {} is also NC module `{module}`: the device's channels would \
                     read the NC module's registers as temperatures; give the device the \
                     temperature module's address",
                    m.address, m.unit_id
                ),
            );
        }
    }
    for (name, dev) in &cfg.devices {
        let (modbus, common) = match dev {
            DeviceConfig::Tcp(d) => (&d.modbus, &d.common),
            DeviceConfig::Rtu(d) => (&d.modbus, &d.common),
            DeviceConfig::Can(_) => continue,
        };
        if let Some(message) = retries_that_cannot_run(modbus.retries, common) {
            out.push(field("devices", name, "retries"), message);
        }
    }
    let mut lines: BTreeMap<&str, Vec<(&String, &RtuDeviceConfig)>> = BTreeMap::new();
    for (name, dev) in &cfg.devices {
        if let DeviceConfig::Rtu(d) = dev {
            lines.entry(&d.serial_path).or_default().push((name, d));
        }
    }
    for (path, devs) in &lines {
        let Some(&(first, _)) = devs.first() else {
            continue;
        };
        let key = field("devices", first, "serial_path");
        let timed: Vec<_> = devs.iter().map(|(n, d)| (*n, &d.common)).collect();
        if let Some(message) = slow_line(&format!("serial line {path}"), &timed) {
            out.push(key.clone(), message);
        }
        if !path.trim().is_empty() && !Path::new(path).exists() {
            out.push(key, missing_serial_path(path, devs));
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
    for (name, axis) in &cfg.axes {
        for (i, t) in axis.tan_beta.terms.iter().enumerate() {
            if let Some(message) = implausible_slope(t.coeff_per_degc) {
                out.push(
                    format!("axes.{name}.tan_beta.terms[{i}].coeff_per_degc"),
                    message,
                );
            }
        }
    }
    // A model fitted over temperatures its channel never reads as valid (a CSV in
    // kelvin) is never within its fitted range, and compensates with what it never saw.
    for (name, axis) in &cfg.axes {
        for (channel, &[min, max]) in &axis.fitted_degc {
            let Some(ch) = cfg.channels.get(channel) else {
                continue;
            };
            let (lo, hi) = (ch.filter.valid_min_degc, ch.filter.valid_max_degc);
            if max < lo || min > hi {
                out.push(
                    format!("axes.{name}.fitted_degc.{channel}"),
                    format!(
                        "the model was fitted over {min}..{max} degC, but channel `{channel}` \
                         takes only {lo}..{hi} degC as valid: it never meets the temperatures it \
                         was fitted over; a measurement CSV in kelvin (fit the model again from \
                         degC), or a valid range narrower than the machine's temperatures (widen \
                         channels.{channel}.filter.valid_min_degc or valid_max_degc)"
                    ),
                );
            }
        }
    }
    for (name, axis) in &cfg.axes {
        if !axis.accepted_doubts.is_empty() {
            out.push(
                format!("axes.{name}.accepted_doubts"),
                format!(
                    "the model was written although its fit is in doubt: {}; \
                     measure the machine again and fit anew, or remove the key once the \
                     doubt is settled",
                    axis.accepted_doubts.join("; ")
                ),
            );
        }
    }
    // `run` logs it at start; validate (and so `systemctl reload`) said nothing.
    let logins = cfg
        .targets
        .iter()
        .filter_map(|(name, t)| match t {
            crate::nc::config::TargetConfig::Opcua(o) => {
                Some((format!("targets.{name}"), o.login()))
            }
            _ => None,
        })
        .chain(cfg.mqtt.as_ref().map(|m| ("mqtt".to_string(), m.login())));
    for (table, login) in logins {
        if let Some(path) = login.readable_by_others() {
            out.push(
                format!("{table}.credentials_file"),
                format!(
                    "{} is readable by group or others, and holds a password; chmod 600 it",
                    path.display()
                ),
            );
        }
    }
    if let Some(m) = &cfg.metrics {
        if let Some(message) = exposed(&m.bind) {
            out.push("metrics.bind", message);
        }
    }
    out.into_vec()
}

/// A tan(beta) coefficient no machine structure has: a model calibrated on positions
/// in inches, or a mistyped exponent, compensates millimetres wrong (a coefficient
/// 100 times too large gave 4.6 mm at 700 mm) while every limit but the NC's holds.
fn implausible_slope(coeff_per_degc: f64) -> Option<String> {
    (coeff_per_degc.abs() > MAX_TAN_BETA_PER_K).then(|| {
        format!(
            "{coeff_per_degc:e} /K is {:.0} times steel's expansion ({STEEL_EXPANSION_PER_K:e} \
             /K), beyond {MAX_TAN_BETA_PER_K:e} /K: no machine structure expands so; check the \
             model (calibrated on positions in inches? a mistyped exponent?)",
            coeff_per_degc.abs() / STEEL_EXPANSION_PER_K
        )
    })
}

/// A listener beyond this PC (`0.0.0.0`, a LAN address): it has no authentication and
/// no TLS, which a plant's IT asks about first.
fn exposed(bind: &str) -> Option<String> {
    let ip = bind.parse::<std::net::SocketAddr>().ok()?.ip();
    (!ip.is_loopback()).then(|| {
        format!(
            "`{bind}` serves /metrics and the status page beyond this PC, to anyone who \
             reaches the port, without authentication or TLS (read only: nothing there \
             changes the gateway); keep the port behind the plant firewall, or bind \
             127.0.0.1 and put a reverse proxy with authentication in front"
        )
    })
}

/// Seconds as written in a message: to the millisecond, without trailing zeros
/// (`0.1 * 3` is "0.3", not "0.30000000000000004").
fn s(v: f64) -> f64 {
    (v * 1000.0).round() / 1000.0
}

/// The shortest `timeout_s` a warning advises: a reply at 9600 baud takes tens of ms.
const MIN_ADVISED_TIMEOUT_S: f64 = 0.05;

/// Why not all of `retries` can run after timeouts in one poll cycle of `common`.
fn retries_that_cannot_run(retries: u32, common: &DeviceCommon) -> Option<String> {
    let (t, p) = (common.timeout_s, common.poll_interval_s);
    let defaults = DeviceCommon::default();
    let all_default = retries == ModbusCommon::DEFAULT_RETRIES
        && t == defaults.timeout_s
        && p == defaults.poll_interval_s;
    if retries == 0 || all_default || !(t > 0.0 && p > 0.0) {
        return None;
    }
    let deadline = p.max(t);
    let attempts = f64::from(retries) + 1.0;
    // A margin for rounding: 3 * 0.1 s fits a cycle of 0.3 s.
    if attempts * t <= deadline * (1.0 + 1e-9) {
        return None;
    }
    // Attempts that fit: at least the first, which always gets its whole timeout.
    let fit = ((deadline / t) * (1.0 + 1e-9)).floor().max(1.0);
    // `fit - 1` < `retries` here, so it fits a u32.
    let runs = (fit - 1.0) as u32;
    let head = if runs == 0 {
        format!("retries = {retries} never runs after a timeout")
    } else {
        format!("only {runs} of retries = {retries} can run after timeouts")
    };
    // A timeout_s a device cannot answer within is no advice.
    let lower = if p / attempts >= MIN_ADVISED_TIMEOUT_S {
        format!("Lower timeout_s to {} s, raise", s(p / attempts))
    } else {
        "Raise".to_string()
    };
    Some(format!(
        "{head} (a retry still follows a fast fault, such as a bad CRC): one poll cycle \
         ends after max(poll_interval_s, timeout_s) = {} s (the cycle deadline), and an \
         attempt that times out takes timeout_s = {} s of it, so (retries + 1) * \
         timeout_s = {} s does not fit. {lower} poll_interval_s to {} s, or set retries = \
         {runs}",
        s(deadline),
        s(t),
        s(attempts * t),
        s(attempts * t),
    ))
}

/// `devs` are polled one at a time on `line` (a serial line, or the one connection at
/// a TCP address): why a silent one holds up the others, when their timeouts add up to
/// more than the smallest poll interval.
fn slow_line(line: &str, devs: &[(&String, &DeviceCommon)]) -> Option<String> {
    if devs.len() < 2 {
        return None;
    }
    let total: f64 = devs.iter().map(|(_, d)| d.timeout_s).sum();
    let (fastest, poll) = devs
        .iter()
        .map(|(name, d)| (name, d.poll_interval_s))
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
    if total <= poll * (1.0 + 1e-9) {
        return None;
    }
    let timeouts: Vec<String> = devs
        .iter()
        .map(|(name, d)| format!("`{name}` {} s", s(d.timeout_s)))
        .collect();
    Some(format!(
        "{line}: a silent device on this line holds up the others: its \
         devices are polled one at a time, and their timeout_s ({}) add up to {} s, more \
         than the smallest poll_interval_s on the line ({} s, `{fastest}`), so while one \
         does not answer the others are polled late. Lower timeout_s (a device answers \
         within tens of milliseconds at 9600 baud and more), or raise poll_interval_s to \
         {} s or more",
        timeouts.join(", "),
        s(total),
        s(poll),
        s(total),
    ))
}

/// The serial device at `path`, shared by `devs`, does not exist.
fn missing_serial_path(path: &str, devs: &[(&String, &RtuDeviceConfig)]) -> String {
    let others: Vec<String> = devs
        .iter()
        .skip(1)
        .map(|(name, _)| format!("`{name}`"))
        .collect();
    let also = if others.is_empty() {
        String::new()
    } else {
        format!(" (also the line of {})", others.join(", "))
    };
    format!(
        "serial device {path}{also} does not exist (yet): `run` keeps trying to open it; \
         check the adapter is plugged in and the path (ls /dev/serial/by-id gives stable \
         names)"
    )
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
                 timeout_s = 0.1\n[channels.t_{name}]\ndevice = \"{name}\"\nregister = \"input\"\naddress = 0\n\
                 data_type = \"u16\"\nscaling = {{ kind = \"direct\", gain = 0.1, offset_degc = 0.0 }}\n"
            )
        };
        let text = [
            device("good", "127.0.0.1:502", 1),
            device("bad", "127.0.0.1:502", 1),
            device("other_unit", "127.0.0.1:502", 2),
            device("spelled", "LocalHost:502", 2),
        ]
        .concat();
        let cfg = crate::config::load_str(&text, "dup.toml").expect("valid");
        let w: Vec<String> = warnings(&cfg, "dup.toml")
            .iter()
            .map(ToString::to_string)
            .collect();
        assert_eq!(w.len(), 2, "{w:#?}");
        // One address spelled two ways is one device.
        assert!(
            w[1].starts_with("dup.toml: devices.spelled.unit_id: unit id 2 at LocalHost:502 is also device `other_unit`"),
            "{}",
            w[1]
        );
        // Devices are checked in name order: `good` comes after `bad`.
        assert!(
            w[0].starts_with(
                "dup.toml: devices.good.unit_id: unit id 1 at 127.0.0.1:502 is also device `bad`"
            ),
            "{}",
            w[0]
        );
    }

    // A temperature module given the NC module's address (a copied entry) read the
    // module's registers as temperatures without a word.
    #[test]
    fn a_device_at_the_nc_modules_address_and_unit_gets_a_warning() {
        let text = include_str!("../../../../config/example.toml");
        let mut cfg = crate::config::load_str(text, "plant.toml").expect("valid");
        let nc = cfg.modbus_targets()[0].1.clone();
        let w = |cfg: &Config| -> Vec<String> {
            // The example's RTU line is not plugged in here: not this warning.
            warnings(cfg, "plant.toml")
                .iter()
                .map(ToString::to_string)
                .filter(|w| !w.contains("serial_path"))
                .collect()
        };
        assert_eq!(w(&cfg), Vec::<String>::new());
        let Some(DeviceConfig::Tcp(d)) = cfg.devices.get_mut("ain1") else {
            panic!("ain1 is a TCP device in the example");
        };
        d.address.clone_from(&nc.address);
        d.unit_id = nc.unit_id + 1;
        assert_eq!(
            w(&cfg),
            Vec::<String>::new(),
            "another unit id is another device"
        );
        let Some(DeviceConfig::Tcp(d)) = cfg.devices.get_mut("ain1") else {
            unreachable!()
        };
        d.unit_id = nc.unit_id;
        let w = w(&cfg);
        assert_eq!(w.len(), 1, "{w:#?}");
        assert!(
            w[0].starts_with(&format!(
                "plant.toml: devices.ain1.address: {} unit id {} is also NC module `nc_x`",
                nc.address, nc.unit_id
            )),
            "{}",
            w[0]
        );
    }

    // `bind = "0.0.0.0:9464"` passed `validate` silently; nothing said the listener has
    // no authentication.
    #[test]
    fn a_listener_beyond_this_pc_gets_a_warning() {
        for bind in ["0.0.0.0:9464", "[::]:9464", "192.168.0.10:9464"] {
            let m = exposed(bind).unwrap_or_else(|| panic!("{bind}: no warning"));
            assert!(m.contains("without authentication or TLS"), "{m}");
        }
        for bind in ["127.0.0.1:9464", "[::1]:0"] {
            assert_eq!(exposed(bind), None, "{bind}");
        }
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

    // Review V: a screw coefficient typed 100 times too large (0.0011445 /K) passed
    // validate with OK and was compensated as 4.6 mm at 700 mm, nothing said.
    #[test]
    fn a_slope_coefficient_no_structure_has_gets_a_warning() {
        let example = include_str!("../../../../config/example.toml");
        let at = "coeff_per_degc = 0.0000115";
        assert!(example.contains(at));
        let slopes = |text: &str| -> Vec<String> {
            let cfg = crate::config::load_str(text, "plant.toml").expect("valid");
            warnings(&cfg, "plant.toml")
                .iter()
                .map(ToString::to_string)
                .filter(|w| w.contains("tan_beta"))
                .collect()
        };
        assert!(slopes(example).is_empty());
        let w = slopes(&example.replacen(at, "coeff_per_degc = 0.0011445", 1));
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(
            w[0].starts_with(
                "plant.toml: axes.X.tan_beta.terms[0].coeff_per_degc: 1.1445e-3 /K is 100 \
                 times steel's expansion"
            ),
            "{}",
            w[0]
        );
        // Eight times steel's (a sensor that warms less than the screw) is no warning.
        assert_eq!(implausible_slope(8.0 * STEEL_EXPANSION_PER_K), None);
    }

    /// A model fitted on temperatures in kelvin passed validate with OK (field review).
    #[test]
    fn a_model_fitted_beyond_its_channels_valid_range_gets_a_warning() {
        let example = include_str!("../../../../config/example.toml");
        let fitted = "fitted_degc = { T_bed = [16.9, 23.5], T_screw = [17.0, 27.1] }";
        let axis = "[axes.X]\n";
        assert!(example.contains(axis));
        let ok = example.replacen(axis, &format!("{axis}{fitted}\n"), 1);
        assert!(
            !warned(&ok).iter().any(|w| w.contains("fitted_degc")),
            "{:?}",
            warned(&ok)
        );
        let kelvin = ok.replacen("T_screw = [17.0, 27.1]", "T_screw = [290.15, 300.25]", 1);
        let w: Vec<String> = warned(&kelvin)
            .into_iter()
            .filter(|w| w.contains("fitted_degc"))
            .collect();
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(
            w[0].starts_with(
                "rtu.toml: axes.X.fitted_degc.T_screw: the model was fitted over 290.15..300.25 \
                 degC, but channel `T_screw` takes only"
            ),
            "{}",
            w[0]
        );
    }

    /// A model forced past its doubts said so only in a comment, which nothing
    /// read after the day it was written.
    #[test]
    fn a_model_written_over_its_doubts_is_warned_of() {
        let example = include_str!("../../../../config/example.toml");
        let axis = "[axes.X]\n";
        assert!(example.contains(axis));
        assert!(!warned(example)
            .iter()
            .any(|w| w.contains("accepted_doubts")));
        let forced = example.replacen(
            axis,
            &format!("{axis}accepted_doubts = [\"T_bed spans only 0.2 K\", \"kelvin?\"]\n"),
            1,
        );
        let w: Vec<String> = warned(&forced)
            .into_iter()
            .filter(|w| w.contains("accepted_doubts"))
            .collect();
        assert_eq!(
            w,
            [
                "rtu.toml: axes.X.accepted_doubts: the model was written although its \
              fit is in doubt: T_bed spans only 0.2 K; kelvin?; measure the machine \
              again and fit anew, or remove the key once the doubt is settled"
            ]
        );
    }

    /// The warnings of `text`, as `validate` prints them (without "warning: ").
    fn warned(text: &str) -> Vec<String> {
        let cfg = crate::config::load_str(text, "rtu.toml").expect("valid");
        warnings(&cfg, "rtu.toml")
            .iter()
            .map(ToString::to_string)
            .collect()
    }

    /// A Modbus device `name` with one channel; `keys` go into its table.
    fn modbus_device(name: &str, keys: &str) -> String {
        format!(
            "[devices.{name}]\n{keys}\n\
             [channels.t_{name}]\ndevice = \"{name}\"\nregister = \"input\"\naddress = 0\n\
             data_type = \"u16\"\nscaling = {{ kind = \"direct\", gain = 0.1, offset_degc = 0.0 }}\n"
        )
    }

    // Field review: `timeout_s = 1.0`, `poll_interval_s = 0.5`, `retries = 1` on an RTU
    // line passed silently, and the retry never ran: a first attempt that times out
    // uses the whole cycle deadline max(0.5, 1.0) = 1 s.
    #[test]
    fn retries_that_cannot_run_after_a_timeout_get_a_warning_with_what_to_change() {
        let rtu = |name: &str, unit: u8, t: f64, p: f64, r: u32| {
            modbus_device(
                name,
                &format!(
                    "transport = \"rtu\"\nserial_path = \"/dev/null\"\nunit_id = {unit}\n\
                     timeout_s = {t}\npoll_interval_s = {p}\nretries = {r}"
                ),
            )
        };
        let tcp = |name: &str, t: f64, p: f64, r: u32| {
            modbus_device(
                name,
                &format!(
                    "transport = \"tcp\"\naddress = \"127.0.0.1:502\"\nunit_id = 1\n\
                     timeout_s = {t}\npoll_interval_s = {p}\nretries = {r}"
                ),
            )
        };
        // Each RTU device on its own line: /dev/null is one path, so one line; the
        // line's own warning is tested below, so it is left out here.
        let w = warned(&rtu("field", 1, 1.0, 0.5, 1));
        assert_eq!(
            w,
            ["rtu.toml: devices.field.retries: retries = 1 never runs after a timeout (a \
              retry still follows a fast fault, such as a bad CRC): one poll cycle ends after max(poll_interval_s, timeout_s) = 1 s (the cycle \
              deadline), and an attempt that times out takes timeout_s = 1 s of it, so \
              (retries + 1) * timeout_s = 2 s does not fit. Lower timeout_s to 0.25 s, \
              raise poll_interval_s to 2 s, or set retries = 0"]
        );
        let w = warned(&tcp("plc", 0.2, 0.5, 3));
        assert_eq!(w.len(), 1, "{w:#?}");
        assert!(
            w[0].starts_with(
                "rtu.toml: devices.plc.retries: only 1 of retries = 3 can run after timeouts (a "
            ) && w[0].contains("(retries + 1) * timeout_s = 0.8 s does not fit")
                && w[0].ends_with("Lower timeout_s to 0.125 s, raise poll_interval_s to 0.8 s, or set retries = 1"),
            "{}",
            w[0]
        );
        // A fast poll: no timeout_s a device answers within would fit, none is advised.
        let w = warned(&tcp("fast", 0.5, 0.01, 1));
        assert_eq!(w.len(), 1, "{w:#?}");
        assert!(
            w[0].ends_with("does not fit. Raise poll_interval_s to 1 s, or set retries = 0"),
            "{}",
            w[0]
        );
        // Retries that fit, exactly or with rounding (3 * 0.1 s in 0.3 s), none, and
        // the defaults (their retry is for fast faults).
        for fits in [
            tcp("defaults", 1.0, 1.0, 1),
            tcp("a", 0.5, 1.0, 1),
            tcp("b", 0.1, 0.3, 2),
            tcp("c", 1.0, 0.5, 0),
            rtu("d", 1, 0.3, 2.0, 1),
        ] {
            assert_eq!(warned(&fits), Vec::<String>::new(), "{fits}");
        }
    }

    // Devices on one RTU line are polled one at a time: with timeouts adding up to
    // more than the line's smallest poll interval, one silent device made the others
    // late every cycle, silently.
    #[test]
    fn an_rtu_line_whose_timeouts_add_up_past_its_poll_interval_gets_a_warning() {
        let rtu = |name: &str, unit: u8, t: f64, p: f64| {
            modbus_device(
                name,
                &format!(
                    "transport = \"rtu\"\nserial_path = \"/dev/null\"\nunit_id = {unit}\n\
                     timeout_s = {t}\npoll_interval_s = {p}\nretries = 0"
                ),
            )
        };
        let text = [rtu("a", 1, 0.3, 1.0), rtu("b", 2, 0.4, 0.5)].concat();
        assert_eq!(
            warned(&text),
            [
                "rtu.toml: devices.a.serial_path: serial line /dev/null: a silent device on \
              this line holds up the others: its devices are polled one at a time, and \
              their timeout_s (`a` 0.3 s, `b` 0.4 s) add up to 0.7 s, more than the \
              smallest poll_interval_s on the line (0.5 s, `b`), so while one does not \
              answer the others are polled late. Lower timeout_s (a device answers within \
              tens of milliseconds at 9600 baud and more), or raise poll_interval_s to \
              0.7 s or more"
            ]
        );
        // Within the interval; and one device alone has no others to hold up.
        let text = [rtu("a", 1, 0.2, 1.0), rtu("b", 2, 0.3, 0.5)].concat();
        assert_eq!(warned(&text), Vec::<String>::new());
        assert_eq!(warned(&rtu("a", 1, 0.4, 0.5)), Vec::<String>::new());
        // Units at one TCP address (behind a TCP-to-RTU gateway) get none: their
        // timeout_s must stay above the gateway's, whatever they add up to.
        let tcp = |name: &str, unit: u8| {
            modbus_device(
                name,
                &format!("transport = \"tcp\"\naddress = \"127.0.0.1:502\"\nunit_id = {unit}"),
            )
        };
        let text: String = (1..=4).map(|u| tcp(&format!("u{u}"), u)).collect();
        assert_eq!(warned(&text), Vec::<String>::new());
    }

    // A serial path that does not exist failed only at `run`, as a connect error; a
    // USB adapter may be plugged in later, so `validate` warns and does not refuse.
    #[test]
    fn a_serial_path_that_does_not_exist_gets_a_warning_naming_the_key() {
        let rtu = |name: &str, unit: u8, path: &str| {
            modbus_device(
                name,
                &format!(
                    "transport = \"rtu\"\nserial_path = \"{path}\"\nunit_id = {unit}\n\
                     timeout_s = 0.1\npoll_interval_s = 1.0"
                ),
            )
        };
        let missing = "/dev/compgate-test-no-such-tty";
        let text = [
            rtu("a", 1, missing),
            rtu("b", 2, missing),
            rtu("c", 3, "/dev/null"),
        ]
        .concat();
        assert_eq!(
            warned(&text),
            [format!(
                "rtu.toml: devices.a.serial_path: serial device {missing} (also the line of \
                 `b`) does not exist (yet): `run` keeps trying to open it; check the adapter \
                 is plugged in and the path (ls /dev/serial/by-id gives stable names)"
            )]
        );
    }
}
