use super::*;
use crate::config::schema::*;
use crate::config::{load_str, ConfigError};

fn example() -> Config {
    match load_str(
        include_str!("../../../../../config/example.toml"),
        "example.toml",
    ) {
        Ok(cfg) => cfg,
        Err(e) => panic!("{e}"),
    }
}

/// Keys of the problems after `change` was applied to the example.
fn problems_after(change: impl FnOnce(&mut Config)) -> Vec<String> {
    let mut cfg = example();
    change(&mut cfg);
    validate(&cfg, "v.toml")
        .into_iter()
        .map(|p| {
            assert_eq!(p.file, "v.toml");
            assert!(!p.message.is_empty());
            p.key
        })
        .collect()
}

fn tcp<'a>(cfg: &'a mut Config, name: &str) -> &'a mut TcpDeviceConfig {
    cfg.devices
        .get_mut(name)
        .and_then(DeviceConfig::tcp_mut)
        .expect("tcp device in example")
}
fn rtu<'a>(cfg: &'a mut Config, name: &str) -> &'a mut RtuDeviceConfig {
    cfg.devices
        .get_mut(name)
        .and_then(DeviceConfig::rtu_mut)
        .expect("rtu device in example")
}

/// Keys of the problems of the example text with `from` replaced by `to`.
fn text_problems(from: &str, to: &str) -> Vec<String> {
    let text = include_str!("../../../../../config/example.toml");
    assert_eq!(text.matches(from).count(), 1, "{from}");
    match load_str(&text.replace(from, to), "v.toml") {
        Ok(_) => Vec::new(),
        Err(ConfigError::Invalid(p)) => p.into_iter().map(|p| p.key).collect(),
        Err(e) => panic!("{e}"),
    }
}
fn ch<'a>(cfg: &'a mut Config, name: &str) -> &'a mut ChannelConfig {
    cfg.channels.get_mut(name).expect("channel in example")
}
fn x(cfg: &mut Config) -> &mut AxisConfig {
    cfg.axes.get_mut("X").expect("axis in example")
}
/// Adds a channel `T_<device>` reading `device`, so that the device is not unread.
fn read_by_channel(cfg: &mut Config, device: &str) {
    let mut t = cfg.channels["T_ambient"].clone();
    t.device = device.into();
    cfg.channels.insert(format!("T_{device}"), t);
}

#[test]
fn example_is_clean() {
    assert_eq!(problems_after(|_| {}), Vec::<String>::new());
}

#[test]
fn tcp_and_rtu_fields() {
    // A TCP device cannot hold serial keys nor lack its address: the schema
    // refuses such a file (keys in the order of the table).
    assert_eq!(
        text_problems(
            "address = \"127.0.0.1:5020\"\n",
            "serial_path = \"/dev/ttyS0\"\nbaud = 9600\n"
        ),
        [
            "devices.ain1.baud",
            "devices.ain1.serial_path",
            "devices.ain1.address",
        ]
    );
    assert_eq!(
        text_problems(
            "serial_path = \"/dev/ttyUSB0\"\n",
            "address = \"10.0.0.1:502\"\nconnect_timeout_s = 1.0\n"
        ),
        [
            "devices.ain2.address",
            "devices.ain2.connect_timeout_s",
            "devices.ain2.serial_path",
        ]
    );
    assert_eq!(
        problems_after(|c| {
            let d = rtu(c, "ain2");
            d.baud = Some(300);
            d.stop_bits = Some(3);
        }),
        ["devices.ain2.baud", "devices.ain2.stop_bits"]
    );
    assert_eq!(
        problems_after(|c| tcp(c, "ain1").address = "plc:5o2".into()),
        ["devices.ain1.address"]
    );
}

#[test]
fn unit_ids_and_times() {
    assert_eq!(
        problems_after(|c| {
            // 248..=255 are valid on TCP (some modules answer only 255).
            let d = tcp(c, "ain1");
            d.unit_id = 255;
            d.common.timeout_s = 0.0;
            d.common.poll_interval_s = -1.0;
            d.common.backoff_initial_s = 5.0;
            d.common.backoff_max_s = 1.0;
            d.common.degrade_after_cycles = 0;
            rtu(c, "ain2").unit_id = 0;
            c.gateway.status_interval_s = f64::NAN;
            c.nc_modules.get_mut("nc_x").expect("nc").job_timeout_s = 0.0;
        }),
        [
            "gateway.status_interval_s",
            "devices.ain1.timeout_s",
            "devices.ain1.poll_interval_s",
            "devices.ain1.backoff_max_s",
            "devices.ain1.degrade_after_cycles",
            "devices.ain2.unit_id",
            "nc_modules.nc_x.job_timeout_s",
        ]
    );
    assert_eq!(
        problems_after(|c| rtu(c, "ain2").unit_id = 248),
        ["devices.ain2.unit_id"]
    );
}

#[test]
fn shared_serial_line() {
    let keys = problems_after(|c| {
        let mut other = rtu(c, "ain2").clone();
        other.baud = Some(9600);
        other.parity = Some(Parity::None);
        other.stop_bits = None; // 2 without parity
        c.devices.insert("ain3".into(), DeviceConfig::Rtu(other));
        read_by_channel(c, "ain3");
    });
    assert_eq!(
        keys,
        [
            "devices.ain3.baud",
            "devices.ain3.parity",
            "devices.ain3.stop_bits",
            "devices.ain3.unit_id",
        ]
    );
    // Defaults count: an explicit 19200/even/1 equals the defaults.
    assert_eq!(
        problems_after(|c| {
            let mut other = rtu(c, "ain2").clone();
            other.baud = None;
            other.parity = None;
            other.stop_bits = None;
            other.unit_id = 8;
            c.devices.insert("ain3".into(), DeviceConfig::Rtu(other));
            read_by_channel(c, "ain3");
        }),
        Vec::<String>::new()
    );
}

#[test]
fn registers_and_scaling() {
    assert_eq!(
        problems_after(|c| {
            let t = ch(c, "T_ambient");
            t.address = Some(65535);
            t.scaling = Scaling::Direct(DirectScaling {
                gain: 0.0,
                offset_degc: f64::INFINITY,
            });
        }),
        [
            "channels.T_ambient.address",
            "channels.T_ambient.scaling.gain",
            "channels.T_ambient.scaling.offset_degc",
        ]
    );
    assert_eq!(
        problems_after(|c| {
            let t = ch(c, "T_bed");
            t.data_type = DataType::I16;
            t.scaling = Scaling::Transmitter(TransmitterScaling {
                adc_full_scale_counts: 40_000,
                adc_full_scale_ma: 16.0,
                current_range: CurrentRange::Ma4To20,
                range_min_degc: 100.0,
                range_max_degc: 0.0,
            });
            ch(c, "T_screw").data_type = DataType::F32;
        }),
        [
            "channels.T_bed.scaling.adc_full_scale_counts",
            "channels.T_bed.scaling.adc_full_scale_ma",
            "channels.T_bed.scaling.range_max_degc",
        ],
        "f32 counts are fine"
    );
    // The same register read twice is fine.
    assert_eq!(
        problems_after(|c| ch(c, "T_screw").address = Some(0)),
        Vec::<String>::new()
    );
}

#[test]
fn filter_ranges() {
    assert_eq!(
        problems_after(|c| {
            let f = &mut ch(c, "T_bed").filter;
            f.median_samples = 4;
            f.lowpass_tau_s = -1.0;
            f.max_rate_degc_per_s = -0.1;
            f.max_rejected_samples = 0;
            f.stale_after_s = -5.0;
            f.valid_min_degc = 50.0;
            f.valid_max_degc = 50.0;
            ch(c, "T_screw").filter.median_samples = 0;
        }),
        [
            "channels.T_bed.filter.median_samples",
            "channels.T_bed.filter.lowpass_tau_s",
            "channels.T_bed.filter.max_rate_degc_per_s",
            "channels.T_bed.filter.max_rejected_samples",
            "channels.T_bed.filter.stale_after_s",
            "channels.T_bed.filter.valid_max_degc",
            "channels.T_screw.filter.median_samples",
        ]
    );
}

#[test]
fn references() {
    assert_eq!(
        problems_after(|c| {
            ch(c, "T_bed").device = "nope".into();
            x(c).tan_beta.terms[0].channel = "T_nope".into();
            let dup = x(c).k0.terms[0].clone();
            x(c).k0.terms.push(dup);
            let mut y = c.axes["X"].clone();
            y.k0 = K0Model::default();
            y.tan_beta = TanBetaModel::default();
            c.axes.insert("Y".into(), y);
        }),
        [
            "channels.T_bed.device",
            "axes.X.k0.terms[2].channel",
            "axes.X.tan_beta.terms[0].channel",
            "axes.Y.nc_module",
        ]
    );
    assert_eq!(
        problems_after(|c| x(c).nc_module = "nc_y".into()),
        ["axes.X.nc_module"]
    );
}

#[test]
fn axis_limits_and_md32750() {
    assert_eq!(
        problems_after(|c| {
            let a = x(c);
            a.max_abs_tan_beta = 0.2;
            a.max_abs_k0_mm = 0.0;
            a.deadband_k0_mm = -0.1;
            a.max_step_tan_beta = 0.0;
            a.ramp_k0_mm_per_s = 0.0;
            a.update_interval_s = 0.0;
        }),
        [
            "axes.X.update_interval_s",
            "axes.X.deadband_k0_mm",
            "axes.X.max_abs_k0_mm",
            "axes.X.max_abs_tan_beta",
            "axes.X.max_step_tan_beta",
            "axes.X.ramp_k0_mm_per_s",
        ]
    );
    assert_eq!(problems_after(|c| x(c).md32750 = 8), ["axes.X.md32750"]);
    assert_eq!(problems_after(|c| x(c).md32750 = 2), ["axes.X.k0"]);
    assert_eq!(problems_after(|c| x(c).md32750 = 1), ["axes.X.tan_beta"]);
    assert_eq!(
        problems_after(|c| {
            x(c).on_bad_input = OnBadInput::Hold;
            x(c).ramp_k0_mm_per_s = 0.0;
        }),
        Vec::<String>::new(),
        "ramp rates may be 0 with hold"
    );
}

#[test]
fn names() {
    assert_eq!(
        problems_after(|c| {
            let t = c.channels["T_bed"].clone();
            c.channels.insert("t_bed".into(), t.clone());
            c.channels.insert("T bed".into(), t.clone());
            c.channels.insert("T__bed".into(), t.clone());
            c.channels.insert("".into(), t.clone());
            c.channels.insert("T".repeat(65), t);
        }),
        [
            "channels.\"\"",
            "channels.\"T bed\"",
            "channels.<TTTTTTTTTTTTTTTT…, 65 characters>",
            "channels.T__bed",
            "channels.t_bed",
        ]
    );
}

#[test]
fn sim_section() {
    assert_eq!(
        problems_after(|c| {
            let mut sim = SimConfig::default();
            sim.channels.insert(
                "T_bed".into(),
                SimChannelConfig {
                    profile: SimProfile::Sine,
                    amplitude_degc: -1.0,
                    period_s: 0.0,
                    noise_degc: -0.1,
                    ..SimChannelConfig::default()
                },
            );
            sim.channels
                .insert("T_nope".into(), SimChannelConfig::default());
            sim.nc_modules.insert(
                "nc_x".into(),
                SimNcModuleConfig {
                    md32750: Some(9),
                    motion_min_mm: 10.0,
                    motion_max_mm: 0.0,
                    motion_speed_mm_per_s: -1.0,
                    ..SimNcModuleConfig::default()
                },
            );
            sim.nc_modules
                .insert("nc_nope".into(), SimNcModuleConfig::default());
            c.sim = Some(sim);
        }),
        [
            "sim.channels.T_bed.amplitude_degc",
            "sim.channels.T_bed.period_s",
            "sim.channels.T_bed.noise_degc",
            "sim.channels.T_nope",
            "sim.nc_modules.nc_nope",
            "sim.nc_modules.nc_x.md32750",
            "sim.nc_modules.nc_x.motion_max_mm",
            "sim.nc_modules.nc_x.motion_speed_mm_per_s",
        ]
    );
}

/// The problems (key, message) after `change` was applied to the example.
fn messages_after(change: impl FnOnce(&mut Config)) -> Vec<(String, String)> {
    let mut cfg = example();
    change(&mut cfg);
    validate(&cfg, "v.toml")
        .into_iter()
        .map(|p| (p.key, p.message))
        .collect()
}

// A config without devices or channels passed `validate`, and `run` then stopped at
// once with exit code 0 and no reason.
#[test]
fn a_config_needs_a_device_and_a_channel() {
    let p = messages_after(|c| {
        c.devices.clear();
        c.channels.clear();
        c.axes.clear();
    });
    let keys: Vec<&str> = p.iter().map(|(k, _)| k.as_str()).collect();
    assert_eq!(keys, ["devices", "channels"], "{p:#?}");
    assert!(p[0].1.contains("at least one [devices.NAME]"), "{}", p[0].1);
    assert!(
        p[1].1.contains("at least one [channels.NAME]"),
        "{}",
        p[1].1
    );
    assert_eq!(
        problems_after(|c| {
            c.channels.clear();
            c.axes.clear();
        }),
        ["channels"],
        "no channel: one problem, not one per device"
    );
}

// A device no channel reads gets a poller and a link, and nothing is ever read.
#[test]
fn a_device_no_channel_reads_is_a_problem() {
    let p = messages_after(|c| {
        c.channels.retain(|_, ch| ch.device != "ain2");
        c.axes.clear();
    });
    assert_eq!(p.len(), 1, "{p:#?}");
    assert_eq!(p[0].0, "devices.ain2");
    assert!(
        p[0].1.starts_with("no channel reads device `ain2`"),
        "{}",
        p[0].1
    );
    // A channel naming an unknown device most likely meant the unread one: only the
    // reference is reported.
    assert_eq!(
        problems_after(|c| {
            for ch in c.channels.values_mut().filter(|ch| ch.device == "ain2") {
                ch.device = "ain3".into();
            }
        }),
        ["channels.T_ambient.device"]
    );
}

fn nc_write_messages(change: impl FnOnce(&mut AxisConfig)) -> Vec<String> {
    messages_after(|c| change(x(c)))
        .into_iter()
        .map(|(k, m)| {
            assert_eq!(k, "axes.X.nc_write", "{m}");
            m
        })
        .collect()
}

// nc_write cuts every job down to its values: one the model sets but nc_write leaves
// out never reached the NC, while the job was logged as written and verified.
#[test]
fn nc_write_must_hold_every_value_the_model_sets() {
    // The example's X models K0 and tan(beta), about p0_mm = 0.
    let m = nc_write_messages(|a| a.nc_write = vec![NcVar::Sd43900]);
    assert_eq!(m.len(), 2, "{m:#?}");
    assert!(m[0].starts_with("leaves out SD43910") && m[0].contains("\"sd43910\""));
    assert!(
        m[1].starts_with("leaves out SD43920") && m[1].contains("P0"),
        "{}",
        m[1]
    );
    let m = nc_write_messages(|a| a.nc_write = vec![NcVar::Sd43910, NcVar::Sd43920]);
    assert_eq!(m.len(), 1, "{m:#?}");
    assert!(m[0].starts_with("leaves out SD43900"), "{}", m[0]);
    // Motion heat adds to the model it names.
    let m = nc_write_messages(|a| {
        a.k0 = K0Model::default();
        a.tan_beta = TanBetaModel::default();
        a.md32750 = 1;
        a.motion_heat = Some(MotionHeatModel {
            tau_s: 600.0,
            ref_mm_per_s: 0.0,
            k0_mm_per_mm_per_s: 0.001,
            tan_beta_per_mm_per_s: 0.0,
        });
        a.nc_write = vec![NcVar::Sd43910, NcVar::Sd43920];
    });
    assert_eq!(m.len(), 1, "{m:#?}");
    assert!(m[0].starts_with("leaves out SD43900"), "{}", m[0]);
    // A set P0 without a slope still has to reach the NC.
    let m = nc_write_messages(|a| {
        a.tan_beta = TanBetaModel::default();
        a.p0_mm = 100.0;
        a.nc_write = vec![NcVar::Sd43900];
    });
    assert_eq!(m.len(), 1, "{m:#?}");
    assert!(m[0].contains("p0_mm = 100"), "{}", m[0]);
}

#[test]
fn nc_write_may_leave_out_what_the_model_does_not_set() {
    // A K0-only axis on a control without a slope (documented for ADS).
    assert_eq!(
        nc_write_messages(|a| {
            a.tan_beta = TanBetaModel::default();
            a.md32750 = 1;
            a.nc_write = vec![NcVar::Sd43900];
        }),
        Vec::<String>::new()
    );
    // A slope-only axis (config/minimal.toml) need not write K0.
    assert_eq!(
        nc_write_messages(|a| {
            a.k0 = K0Model::default();
            a.md32750 = 2;
            a.nc_write = vec![NcVar::Sd43910, NcVar::Sd43920];
        }),
        Vec::<String>::new()
    );
}

#[test]
fn port_0_is_left_to_the_simulated_plant() {
    let zero = |c: &mut Config| {
        tcp(c, "ain1").address = "127.0.0.1:0".into();
        c.nc_modules.get_mut("nc_x").expect("nc").address = "127.0.0.1:0".into();
    };
    assert_eq!(
        problems_after(zero),
        ["devices.ain1.address", "nc_modules.nc_x.address"]
    );
    // `run` connects to what the file names, [sim] or not.
    assert_eq!(
        problems_after(|c| {
            zero(c);
            c.sim = Some(SimConfig::default());
        }),
        ["devices.ain1.address", "nc_modules.nc_x.address"]
    );
    let mut cfg = example();
    zero(&mut cfg);
    cfg.sim = Some(SimConfig::default());
    assert_eq!(
        validate_assuming(&cfg, "v.toml", &Assumed::default(), true),
        Vec::<ConfigProblem>::new(),
        "for the simulated plant, which binds a free port and writes it in"
    );
    assert_eq!(
        problems_after(|c| tcp(c, "ain1").address = "192.168.0.300:502".into()),
        ["devices.ain1.address"]
    );
}

// With three axes on one NC module the third one's message names both others, not
// only the one before it.
#[test]
fn an_axis_on_a_taken_module_names_every_axis_already_on_it() {
    let m = messages_after(|c| {
        let x = c.axes["X"].clone();
        c.axes.insert("Y".into(), x.clone());
        c.axes.insert("Z".into(), x);
    });
    let on = |key: &str| {
        m.iter()
            .find(|(k, _)| k == key)
            .map(|(_, msg)| msg.as_str())
            .unwrap_or_else(|| panic!("no problem at {key}: {m:#?}"))
    };
    assert_eq!(
        on("axes.Y.nc_module"),
        "NC module `nc_x` already carries axis `X`; one axis per module"
    );
    assert_eq!(
        on("axes.Z.nc_module"),
        "NC module `nc_x` already carries axes `X`, `Y`; one axis per module"
    );
    assert!(!m.iter().any(|(k, _)| k == "axes.X.nc_module"), "{m:#?}");
}

/// `change` applied to the example with axis X copied to a second axis `Y` on the
/// target `y_target`, built from `target` (TOML); X keeps its NC module `nc_x`, unit 1.
/// The problems at `axes.Y.nc_module`.
fn second_target_problems(target: &str, change: impl FnOnce(&mut Config)) -> Vec<String> {
    messages_after(|c| {
        let t: TargetConfig = toml::from_str(target).expect("target");
        c.targets.insert("y_target".into(), t);
        let mut y = c.axes["X"].clone();
        y.nc_module = "y_target".into();
        y.axis_number = Some(1);
        c.axes.insert("Y".into(), y);
        change(c);
    })
    .into_iter()
    .filter(|(k, _)| k == "axes.Y.nc_module")
    .map(|(_, m)| m)
    .collect()
}

// Two entries for one NC (a copied entry, an address spelled two ways) pass every
// per-target check, and at run time their axes overwrite each other's values.
#[test]
fn one_control_under_two_target_names_is_refused() {
    let x_at = example().nc_modules["nc_x"].address.clone();
    let modbus =
        |addr: &str, unit: u8| format!("kind = \"modbus\"\naddress = \"{addr}\"\nunit_id = {unit}");
    let spelled = x_at.replace("127.0.0.1", "LocalHost");
    assert_ne!(spelled, x_at, "the example's NC module is on 127.0.0.1");
    let m = second_target_problems(&modbus(&spelled, 1), |_| {});
    assert_eq!(m.len(), 1, "{m:#?}");
    assert!(
        m[0].contains(&format!("the Modbus NC module at {x_at}, unit 1"))
            && m[0].contains("target `nc_x` does for axis X")
            && m[0].contains("overwrite"),
        "{}",
        m[0]
    );
    // Another unit behind the same address is another module; port 0 is the
    // simulated plant's to give, a port to each.
    assert_eq!(
        second_target_problems(&modbus(&x_at, 2), |_| {}),
        Vec::<String>::new()
    );
    let m = messages_after(|c| {
        c.nc_modules.get_mut("nc_x").expect("nc_x").address = "127.0.0.1:0".into();
        c.sim = Some(SimConfig::default());
        let nc_y = c.nc_modules["nc_x"].clone();
        c.nc_modules.insert("nc_y".into(), nc_y);
        let mut y = c.axes["X"].clone();
        y.nc_module = "nc_y".into();
        c.axes.insert("Y".into(), y);
    });
    assert!(!m.iter().any(|(k, _)| k == "axes.Y.nc_module"), "{m:#?}");

    // Two S7 targets on one PLC's data block: blocks that overlap clash, blocks side
    // by side (or another data block) do not.
    let s7 = |addr: &str, db: u16, start: u16| {
        format!("kind = \"s7\"\naddress = \"{addr}\"\ndb_number = {db}\nstart_byte = {start}")
    };
    let on_plc = |c: &mut Config| {
        c.targets.insert(
            "plc".into(),
            toml::from_str(&s7("10.0.0.5:102", 100, 0)).expect("s7"),
        );
        let x = c.axes.get_mut("X").expect("X");
        x.nc_module = "plc".into();
        x.axis_number = Some(1);
    };
    let m = second_target_problems(&s7("10.0.0.5:102", 100, 8), on_plc);
    assert_eq!(m.len(), 1, "{m:#?}");
    assert!(
        m[0].contains("DB100 of the S7 PLC at 10.0.0.5:102"),
        "{}",
        m[0]
    );
    let block = match toml::from_str(&s7("10.0.0.5:102", 100, 0)).expect("s7") {
        TargetConfig::S7(t) => t.layout().block_len(),
        other => panic!("{other:?}"),
    };
    for other in [
        s7("10.0.0.5:102", 100, block),
        s7("10.0.0.5:102", 101, 0),
        s7("10.0.0.6:102", 100, 0),
    ] {
        assert_eq!(
            second_target_problems(&other, on_plc),
            Vec::<String>::new(),
            "{other}"
        );
    }
}

// An OPC UA or ADS target reports no position: the motion heat term read 0 mm for
// a standing axis and kept its reference offset on the NC whatever the axis did.
#[test]
fn motion_heat_needs_a_target_that_reports_the_position() {
    let heat = || crate::axis::MotionHeatModel {
        tau_s: 600.0,
        ref_mm_per_s: 5.0,
        k0_mm_per_mm_per_s: 0.001,
        tan_beta_per_mm_per_s: 0.0,
    };
    let on_opcua = |with_heat: bool| {
        problems_after(|c| {
            c.nc_modules.remove("nc_x");
            let t: TargetConfig =
                toml::from_str("kind = \"opcua\"\nendpoint_url = \"opc.tcp://127.0.0.1:4840\"")
                    .expect("opcua target");
            c.targets.insert("nc_x".into(), t);
            x(c).axis_number = Some(1);
            if with_heat {
                x(c).motion_heat = Some(heat());
            }
        })
    };
    assert_eq!(on_opcua(false), Vec::<String>::new());
    assert_eq!(on_opcua(true), ["axes.X.motion_heat"]);
    // The NC module reports it.
    assert_eq!(
        problems_after(|c| x(c).motion_heat = Some(heat())),
        Vec::<String>::new()
    );
}
