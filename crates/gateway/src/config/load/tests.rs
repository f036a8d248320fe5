use super::*;
use crate::config::*;

const EXAMPLE: &str = include_str!("../../../../../config/example.toml");
const DEMO: &str = include_str!("../../../../../config/demo.toml");

fn env(vars: &[(&str, &str)]) -> Vec<(String, String)> {
    vars.iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect()
}

/// The problems of a text that must not load.
fn problems(text: &str) -> Vec<ConfigProblem> {
    problems_env(text, &[])
}

fn problems_env(text: &str, vars: &[(&str, &str)]) -> Vec<ConfigProblem> {
    match load_str_with_env(text, "t.toml", env(vars)) {
        Ok(_) => panic!("expected problems"),
        Err(ConfigError::Invalid(p)) => p,
        Err(e) => panic!("unexpected {e}"),
    }
}

fn keys(p: &[ConfigProblem]) -> Vec<&str> {
    p.iter().map(|p| p.key.as_str()).collect()
}

/// The example with `from` replaced by `to` (which must occur exactly once).
fn edit(from: &str, to: &str) -> String {
    assert_eq!(EXAMPLE.matches(from).count(), 1, "{from}");
    EXAMPLE.replace(from, to)
}

#[test]
fn example_loads_with_the_documented_values() {
    let cfg = load_str(EXAMPLE, "example.toml").expect("example is valid");
    assert_eq!(cfg.gateway.status_interval_s, 1.0);
    assert_eq!(cfg.devices["ain1"].transport(), Transport::Tcp);
    let ain1 = cfg.devices["ain1"].tcp().expect("tcp");
    assert_eq!(ain1.address, "127.0.0.1:5020");
    assert_eq!(ain1.connect_timeout(), std::time::Duration::from_secs(2));
    let ain2 = cfg.devices["ain2"].rtu().expect("rtu");
    assert_eq!(
        (ain2.baud(), ain2.parity(), ain2.stop_bits()),
        (19200, Parity::Even, 1)
    );
    let screw = &cfg.channels["T_screw"];
    assert_eq!(screw.byte_order, ByteOrder::Abcd, "default byte order");
    assert_eq!(
        screw.scaling,
        Scaling::Transmitter(TransmitterScaling {
            adc_full_scale_counts: 4095,
            adc_full_scale_ma: 24.0,
            current_range: CurrentRange::Ma4To20,
            range_min_degc: -50.0,
            range_max_degc: 150.0,
        })
    );
    let amb = &cfg.channels["T_ambient"];
    assert_eq!(
        (amb.data_type, amb.byte_order),
        (DataType::F32, ByteOrder::Cdab)
    );
    assert_eq!(amb.registers(), 2);
    assert_eq!(
        amb.scaling,
        Scaling::Direct(DirectScaling {
            gain: 1.0,
            offset_degc: 0.0
        })
    );
    let x = &cfg.axes["X"];
    assert_eq!(x.on_bad_input, OnBadInput::RampToZero);
    assert_eq!(x.k0.terms.len(), 2);
    assert_eq!(x.tan_beta.terms[0].coeff_per_degc, 0.0000115);
    assert!(cfg.sim.is_none());
}

#[test]
fn demo_loads_and_simulates_every_axis_input() {
    let cfg = load_str(DEMO, "demo.toml").expect("demo is valid");
    // The first thing a new user runs: no warning at its start.
    let warnings = crate::config::warnings(&cfg, "demo.toml");
    assert!(warnings.is_empty(), "{warnings:#?}");
    let sim = cfg.sim.as_ref().expect("demo has [sim]");
    let x = &cfg.axes["X"];
    assert_eq!(x.md32750, 3);
    assert_eq!(sim.nc_module(&x.nc_module).md32750, Some(3));
    for t in &x.k0.terms {
        assert!(sim.channels.contains_key(&t.channel), "{}", t.channel);
    }
    for t in &x.tan_beta.terms {
        assert!(sim.channels.contains_key(&t.channel), "{}", t.channel);
    }
}

#[test]
fn serialized_config_loads_back_equal() {
    for text in [EXAMPLE, DEMO] {
        let cfg = load_str(text, "x.toml").expect("valid");
        let again = toml::to_string(&cfg).expect("serializes");
        assert_eq!(
            load_str(&again, "again.toml").expect("reloads"),
            cfg,
            "{again}"
        );
    }
}

#[test]
fn minimal_config_takes_the_documented_defaults() {
    let text = r#"
        [devices.d]
        transport = "tcp"
        address = "10.0.0.5:502"
        unit_id = 1
        [channels.c]
        device = "d"
        register = "input"
        address = 0
        data_type = "u16"
        scaling = { kind = "direct" }
        [nc_modules.n]
        address = "10.0.0.6:502"
        unit_id = 1
        [axes.X]
        nc_module = "n"
        md32750 = 3
    "#;
    let cfg = load_str(text, "m.toml").expect("valid");
    assert_eq!(cfg.gateway, GatewayConfig::default());
    let d = cfg.devices["d"].tcp().expect("tcp");
    assert_eq!(d.common.timeout_s, 1.0);
    assert_eq!(d.modbus.retries, 1);
    assert_eq!(
        (d.common.backoff_initial_s, d.common.backoff_max_s),
        (0.5, 30.0)
    );
    assert_eq!(cfg.channels["c"].filter, FilterConfig::default());
    assert_eq!(cfg.channels["c"].filter.median_samples, 3);
    let x = &cfg.axes["X"];
    assert_eq!(x.max_abs_tan_beta, 0.01);
    assert_eq!(x.on_bad_input, OnBadInput::Hold);
    assert_eq!(x.k0, K0Model::default());
    assert_eq!(cfg.nc_modules["n"].job_timeout_s, 2.0);
}

#[test]
fn two_typos_are_both_reported_with_file_and_path() {
    let text = edit("timeout_s = 0.3", "timeout = 0.3")
        .replace("lowpass_tau_s = 10.0", "lowpas_tau_s = 10.0");
    let p = problems(&text);
    assert_eq!(
        keys(&p),
        ["channels.T_bed.filter.lowpas_tau_s", "devices.ain2.timeout"],
        "{p:#?}"
    );
    assert!(p.iter().all(|p| p.file == "t.toml"));
    assert_eq!(
        p[0].to_string(),
        "t.toml: channels.T_bed.filter.lowpas_tau_s: unknown key; did you mean `lowpass_tau_s`?"
    );
    assert!(p[1].message.contains("`timeout_s`"), "{}", p[1]);
}

#[test]
fn unknown_keys_everywhere_are_reported() {
    let text = format!(
        "colour = \"red\"\n{}",
        edit("offset = 0.0", "offset = 0.0\nbogus = 1")
            .replace(
                "{ channel = \"T_bed\", ref_degc = 20.0, coeff_mm_per_degc = 0.004 }",
                "{ channel = \"T_bed\", ref_degc = 20.0, coef_mm_per_degc = 0.004 }",
            )
            .replace(
                "kind = \"direct\", gain",
                "kind = \"direct\", range_min_degc = 0.0, gain"
            )
    );
    let p = problems(&text);
    assert_eq!(
        keys(&p),
        [
            "axes.X.k0.terms[0].coef_mm_per_degc",
            "axes.X.tan_beta.bogus",
            "channels.T_ambient.scaling.range_min_degc",
            "colour",
        ],
        "{p:#?}"
    );
    assert!(
        p[2].message.contains("not used by kind = \"direct\""),
        "{}",
        p[2]
    );
}

#[test]
fn missing_required_key_is_reported_with_its_path() {
    let p = problems(&edit("device = \"ain2\"\n", ""));
    assert_eq!(keys(&p), ["channels.T_ambient.device"], "{p:#?}");
    assert_eq!(p[0].message, "required key is missing");

    let p = problems(&edit("range_max_degc = 150.0\n", ""));
    assert_eq!(
        keys(&p),
        ["channels.T_bed.scaling.range_max_degc"],
        "{p:#?}"
    );

    let text: String = EXAMPLE
        .split("# ---------------------------------------------------------------- field")
        .next()
        .unwrap_or_default()
        .to_string();
    let p = problems(&text);
    assert_eq!(
        keys(&p),
        // `[targets]` / `[nc_modules]` and `[axes]` are optional (a monitoring-only
        // config).
        ["devices", "channels"],
        "missing sections: {p:#?}"
    );
}

// Issue 23, trap 4: reading and recording temperatures before an NC is connected is
// the first commissioning step. Without `[nc_modules]` and `[axes]` the file used to be
// refused with "required key is missing" twice.
#[test]
fn a_monitoring_only_config_without_nc_modules_and_axes_is_valid() {
    let text: String = EXAMPLE
        .split("# ----------------------------------------------------------------- NC modules")
        .next()
        .unwrap_or_default()
        .to_string();
    let cfg = load_str(&text, "monitor.toml").expect("monitoring-only config loads");
    assert!(cfg.nc_modules.is_empty() && cfg.axes.is_empty());
    assert_eq!(cfg.channels.len(), 3);
    // An axis still needs its NC module: no section is assumed to exist.
    let axis = "[axes.X]\nnc_module = \"nc_x\"\nmd32750 = 2\n\
                [axes.X.tan_beta]\nterms = [{ channel = \"T_screw\", coeff_per_degc = 0.00001 }]\n";
    let p = problems(&format!("{text}\n{axis}"));
    assert_eq!(keys(&p), ["axes.X.nc_module"], "{p:#?}");
}

#[test]
fn type_errors_and_typos_together() {
    let text = edit("timeout_s = 0.3", "timeout_s = \"fast\"")
        .replace("unit_id = 7", "unit_id = 300")
        .replace("transport = \"tcp\"", "transport = \"tpc\"")
        .replace(
            "max_gap_registers = 8\n\n[devices.ain2]",
            "max_gap_register = 8\n\n[devices.ain2]",
        );
    let p = problems(&text);
    assert_eq!(
        keys(&p),
        [
            "devices.ain1.max_gap_register",
            "devices.ain1.transport",
            "devices.ain2.timeout_s",
            "devices.ain2.unit_id",
        ],
        "{p:#?}"
    );
    assert_eq!(
        p[1].message,
        "unknown value `tpc`, expected one of `tcp`, `rtu`, `can`"
    );
    assert!(
        p[2].message.ends_with("expected a number 0.001..=3600"),
        "{}",
        p[2]
    );
    assert!(p[3].message.contains("0..=247"), "{}", p[3]);
}

#[test]
fn broken_entries_do_not_cause_follow_up_reference_problems() {
    // ain2 loses a required key: its channel T_ambient still refers to it, and that
    // must not be reported as an unknown device. A real broken reference is.
    let text = edit("transport = \"rtu\"\n", "").replace(
        "{ channel = \"T_screw\", ref_degc",
        "{ channel = \"T_srew\", ref_degc",
    );
    let p = problems(&text);
    assert_eq!(
        keys(&p),
        ["devices.ain2.transport", "axes.X.tan_beta.terms[0].channel"],
        "{p:#?}"
    );
    assert!(
        p[1].message.contains("unknown channel `T_srew`"),
        "{}",
        p[0]
    );
}

#[test]
fn errors_in_array_elements_keep_the_file_indices() {
    let text = edit(
        "    { channel = \"T_ambient\", ref_degc = 20.0, coeff_mm_per_degc = 0.001 },\n",
        "    { channel = 5, ref_degc = 20.0, coeff_mm_per_degc = 0.001 },\n    \
         { channel = \"T_bed\", ref_degc = \"x\", coeff_mm_per_degc = 0.001 },\n    \
         { channel = \"T_bed\", ref_degc = 20.0, coeff_mm_per_degc = 0.001, extra = 1 },\n",
    );
    let p = problems(&text);
    assert_eq!(
        keys(&p),
        [
            "axes.X.k0.terms[1].channel",
            "axes.X.k0.terms[2].ref_degc",
            "axes.X.k0.terms[3].extra",
        ],
        "{p:#?}"
    );
}

#[test]
fn broken_reference_is_reported() {
    let p = problems(&edit("nc_module = \"nc_x\"", "nc_module = \"nc_y\""));
    assert_eq!(keys(&p), ["axes.X.nc_module"], "{p:#?}");
    assert_eq!(
        p[0].to_string(),
        "t.toml: axes.X.nc_module: unknown target `nc_y`; expected one of the names in [targets] or \
         [nc_modules]: `nc_x`"
    );
    let p = problems(&edit("device = \"ain2\"", "device = \"ain3\""));
    assert_eq!(keys(&p), ["channels.T_ambient.device"], "{p:#?}");
}

#[test]
fn syntax_error_names_line_and_column() {
    let text = EXAMPLE.replacen("[devices.ain1]", "[devices.ain1", 1);
    let line = EXAMPLE
        .lines()
        .position(|l| l == "[devices.ain1]")
        .map(|i| i + 1)
        .unwrap_or_default();
    let p = problems(&text);
    assert_eq!(p.len(), 1);
    assert!(
        p[0].key.starts_with(&format!("line {line}, column")),
        "{p:?}"
    );
    assert!(p[0].message.starts_with("TOML syntax error"), "{p:?}");
    assert!(!p[0].message.contains("given twice"), "{p:?}");
}

/// `cat example.toml model.toml > plant.toml` said "duplicate key" alone (field
/// review R7-B).
#[test]
fn a_model_pasted_beside_the_axis_table_says_where_it_goes() {
    let axis = EXAMPLE
        .split("\n[")
        .find(|t| t.starts_with("axes.X]"))
        .expect("the example has [axes.X]");
    let text = format!("{EXAMPLE}\n[{axis}");
    let p = problems(&text);
    assert_eq!(p.len(), 1, "{p:?}");
    assert!(
        p[0].message.starts_with("TOML syntax error: duplicate key")
            && p[0]
                .message
                .ends_with("goes in place of the axis' table, not beside it)"),
        "{p:?}"
    );
}

#[test]
fn env_override_changes_a_value() {
    let vars = [
        ("COMPGATE__DEVICES__AIN1__TIMEOUT_S", "0.25"),
        ("COMPGATE__AXES__X__UPDATE_INTERVAL_S", "3"),
        ("COMPGATE__AXES__X__ON_BAD_INPUT", "hold"),
        ("COMPGATE__DEVICES__AIN2__TIMEOUT_S", ""),
        ("UNRELATED", "1"),
        ("COMPGATE_SINGLE_UNDERSCORE", "1"),
    ];
    // An empty variable is what a template with an undefined value renders: an error,
    // not the file's value.
    let p = problems_env(EXAMPLE, &vars);
    assert_eq!(
        p.iter().map(ToString::to_string).collect::<Vec<_>>(),
        ["t.toml: devices.ain2.timeout_s: the environment variable \
             COMPGATE__DEVICES__AIN2__TIMEOUT_S is empty: unset it to keep the file's \
             value, or give one"]
    );
    let set: Vec<(&str, &str)> = vars.into_iter().filter(|(_, v)| !v.is_empty()).collect();
    let cfg = load_str_with_env(EXAMPLE, "e.toml", env(&set)).expect("valid");
    assert_eq!(cfg.devices["ain1"].common().timeout_s, 0.25);
    assert_eq!(cfg.axes["X"].update_interval_s, 3.0);
    assert_eq!(cfg.axes["X"].on_bad_input, OnBadInput::Hold);
    assert_eq!(cfg.devices["ain2"].common().timeout_s, 0.3, "the file's");
}

// The field case: an Ansible template with an undefined variable ran with the base
// file's NC address, another machine's NC.
#[test]
fn an_empty_override_is_a_problem_naming_the_variable_and_the_key() {
    let p = problems_env(EXAMPLE, &[("COMPGATE__NC_MODULES__NC_X__ADDRESS", "")]);
    assert_eq!(
        p.iter().map(ToString::to_string).collect::<Vec<_>>(),
        ["t.toml: nc_modules.nc_x.address: the environment variable \
             COMPGATE__NC_MODULES__NC_X__ADDRESS is empty: unset it to keep the file's \
             value, or give one"]
    );
    // In the file's spelling; a key the file lacks has no value to keep.
    let p = problems_env(
        EXAMPLE,
        &[
            ("COMPGATE__CHANNELS__T_BED__ADDRESS", ""),
            ("COMPGATE__RECORDER__PATH", ""),
        ],
    );
    assert_eq!(
        p.iter().map(ToString::to_string).collect::<Vec<_>>(),
        [
            "t.toml: channels.T_bed.address: the environment variable \
             COMPGATE__CHANNELS__T_BED__ADDRESS is empty: unset it to keep the file's \
             value, or give one",
            "t.toml: recorder.path: the environment variable COMPGATE__RECORDER__PATH is \
             empty: unset it or give a value",
        ],
        "{p:#?}"
    );
}

// `COMPGATE_NC_MODULES__NC_X__ADDRESS` was ignored and the file's address ran.
#[test]
fn a_variable_with_one_underscore_after_the_prefix_is_a_problem_naming_it() {
    let p = problems_env(
        EXAMPLE,
        &[
            ("COMPGATE_NC_MODULES__NC_X__ADDRESS", "10.0.0.2:502"),
            ("compgate_channels__t_bed__address", "3"),
            // A user_env's variable and other COMPGATE_ names without `__` are not
            // overrides.
            ("COMPGATE_OPCUA_USER", "operator"),
            ("COMPGATE_SINGLE_UNDERSCORE", "1"),
            ("COMPGATE_TRAILING_", "1"),
        ],
    );
    assert_eq!(
        p.iter().map(ToString::to_string).collect::<Vec<_>>(),
        [
            "t.toml: nc_modules.nc_x.address: the environment variable \
             COMPGATE_NC_MODULES__NC_X__ADDRESS looks like an override but has one `_` \
             after COMPGATE: write COMPGATE__NC_MODULES__NC_X__ADDRESS",
            "t.toml: channels.T_bed.address: the environment variable \
             compgate_channels__t_bed__address looks like an override but has one `_` \
             after COMPGATE: write COMPGATE__channels__t_bed__address",
        ],
        "{p:#?}"
    );
    assert_eq!(mistyped_prefix("COMPGATE__X__Y"), None);
    assert_eq!(mistyped_prefix("COMPGATE"), None);
    assert_eq!(mistyped_prefix("COMPGATEX__Y"), None);
    assert_eq!(
        mistyped_prefix("COMPGATé_X__Y"),
        None,
        "not cut inside a character"
    );
}

// An MQTT login whose variables the config names `COMPGATE_MQTT__USER` (a `__` in a
// variable name is the integrator's choice) was refused as a mistyped override, with
// advice that would have put the password into the config (review X).
#[test]
fn the_variables_the_config_names_are_no_overrides_whatever_their_spelling() {
    let text = format!(
        "{EXAMPLE}\n[mqtt]\nbroker = \"127.0.0.1:1883\"\nmachine = \"m1\"\nuser_env = \"COMPGATE_MQTT__USER\"\n\
         password_env = \"COMPGATE_MQTT__PASSWORD\"\n"
    );
    let vars = env(&[
        ("COMPGATE_MQTT__USER", "gw"),
        ("COMPGATE_MQTT__PASSWORD", "secret"),
    ]);
    // (The login's own checks look for the variables in this process' environment.)
    let problems = match load_str_with_env(&text, "t.toml", vars) {
        Ok(_) => Vec::new(),
        Err(ConfigError::Invalid(p)) => p,
        Err(e) => panic!("unexpected {e}"),
    };
    assert!(
        !problems
            .iter()
            .any(|p| p.message.contains("looks like an override")),
        "{problems:#?}"
    );
}

// `validate` and `run` list the overrides from what the loader used, without values.
#[test]
fn the_loader_returns_the_overrides_it_applied_shown_without_their_values() {
    let (cfg, overrides) = load_text(
        EXAMPLE,
        "e.toml",
        env(&[
            ("COMPGATE__NC_MODULES__NC_X__ADDRESS", "10.0.0.2:502"),
            ("COMPGATE__CHANNELS__T_BED__ADDRESS", "9"),
            (
                "COMPGATE__AXES__X__K0__TERMS__1__COEFF_MM_PER_DEGC",
                "0.002",
            ),
            ("COMPGATE_OPCUA_USER", "operator"),
        ]),
        true,
    )
    .expect("valid");
    assert_eq!(cfg.channels["T_bed"].address, Some(9));
    let shown: Vec<String> = overrides.iter().map(ToString::to_string).collect();
    assert_eq!(
        shown,
        [
            "COMPGATE__AXES__X__K0__TERMS__1__COEFF_MM_PER_DEGC -> axes.X.k0.terms[1].coeff_mm_per_degc",
            "COMPGATE__CHANNELS__T_BED__ADDRESS -> channels.T_bed.address",
            "COMPGATE__NC_MODULES__NC_X__ADDRESS -> nc_modules.nc_x.address",
        ]
    );
    let debug = format!("{overrides:?}");
    assert!(
        !debug.contains("10.0.0.2") && !debug.contains("0.002"),
        "{debug}"
    );
}

#[test]
fn env_override_keeps_mixed_case_names() {
    let cfg = load_str_with_env(
        EXAMPLE,
        "e.toml",
        env(&[
            ("COMPGATE__CHANNELS__T_BED__ADDRESS", "9"),
            ("COMPGATE__CHANNELS__T_BED__FILTER__LOWPASS_TAU_S", "20"),
            (
                "COMPGATE__AXES__X__K0__TERMS__1__COEFF_MM_PER_DEGC",
                "0.002",
            ),
            ("COMPGATE__DEVICES__AIN2__SERIAL_PATH", "1"),
        ]),
    )
    .expect("valid");
    assert_eq!(cfg.channels["T_bed"].address, Some(9));
    assert_eq!(cfg.channels["T_bed"].filter.lowpass_tau_s, 20.0);
    assert!(!cfg.channels.contains_key("t_bed"));
    assert_eq!(cfg.axes["X"].k0.terms[1].coeff_mm_per_degc, 0.002);
    assert_eq!(cfg.axes["X"].k0.terms[0].coeff_mm_per_degc, 0.004);
    assert_eq!(
        cfg.devices["ain2"].rtu().map(|d| d.serial_path.as_str()),
        Some("1"),
        "a number set for a text key stays text"
    );
}

#[test]
fn env_problems_name_the_variable() {
    let p = problems_env(
        EXAMPLE,
        &[
            ("COMPGATE__DEVICES__AIN1__TIMEOUTS", "1"),
            ("COMPGATE__DEVICES__AIN1__BACKOFF_MAX_S", "0.1"),
        ],
    );
    assert_eq!(
        keys(&p),
        ["devices.ain1.timeouts", "devices.ain1.backoff_max_s"],
        "{p:#?}"
    );
    assert!(
        p[0].message
            .ends_with("(environment: COMPGATE__DEVICES__AIN1__TIMEOUTS)"),
        "{}",
        p[0]
    );
    assert!(p[1].message.contains("backoff_initial_s"), "{}", p[1]);
    assert!(p[1]
        .message
        .contains("COMPGATE__DEVICES__AIN1__BACKOFF_MAX_S"));

    let p = problems_env(
        EXAMPLE,
        &[("COMPGATE__AXES__X__K0__TERMS__5__REF_DEGC", "1")],
    );
    assert_eq!(p.len(), 1, "{p:#?}");
    assert!(p[0].message.contains("beyond the 2 elements"), "{}", p[0]);
}

#[test]
fn env_cannot_tell_names_apart_that_differ_in_case() {
    let text = format!(
        "{EXAMPLE}\n[channels.t_BED]\ndevice = \"ain1\"\nregister = \"input\"\naddress = 5\n\
         data_type = \"u16\"\nscaling = {{ kind = \"direct\" }}\n"
    );
    let p = problems(&text);
    assert_eq!(keys(&p), ["channels.t_BED"], "{p:#?}");
    let p = problems_env(&text, &[("COMPGATE__CHANNELS__T_BED__ADDRESS", "3")]);
    assert!(
        p.iter().any(|p| p.key == "channels.t_bed.address" && p.message.contains("`T_bed` and `t_BED`")),
        "{p:#?}"
    );
}

// Some TCP modules answer only unit 255, the Modbus TCP guide's id for a device
// addressed by its IP; RTU keeps 1..=247.
#[test]
fn tcp_unit_id_255_is_valid_and_rtu_248_is_not() {
    let text = edit(
        "unit_id = 1\n# Per-request timeout.\ntimeout_s = 0.5\n# Connect",
        "unit_id = 255\n# Per-request timeout.\ntimeout_s = 0.5\n# Connect",
    );
    let cfg = load_str(&text, "t.toml").expect("unit 255 on TCP is valid");
    assert_eq!(cfg.devices["ain1"].tcp().map(|d| d.unit_id), Some(255));
    let p = problems(&edit("unit_id = 7", "unit_id = 248"));
    assert_eq!(keys(&p), ["devices.ain2.unit_id"], "{p:#?}");
}

#[test]
fn error_display_lists_every_problem() {
    let err = load_str(&edit("unit_id = 7", "unit_id = 0"), "x.toml").expect_err("invalid");
    assert_eq!(
        err.to_string(),
        "1 configuration problem:\n  x.toml: devices.ain2.unit_id: must be 1..=247 on RTU: \
         0 is the broadcast address, which never answers"
    );
    assert_eq!(err.problems().len(), 1);
    let missing = load(Path::new("surely/not/here.toml")).expect_err("no file");
    assert!(matches!(missing, ConfigError::Read { .. }), "{missing}");
}

// `address = 400002` said only "expected an integer 0..=65535".
#[test]
fn a_six_digit_register_number_is_named_as_one() {
    let p = problems(&edit("address = 1000\n", "address = 400002\n"));
    assert_eq!(keys(&p), ["channels.T_ambient.address"], "{p:#?}");
    assert!(
        p[0].message.ends_with(
            "expected an integer 0..=65535; 400002 looks like a 6-digit register number of \
             a device manual (holding register 2): addresses here are 0-based PDU \
             addresses, so that register is address = 1 with register = \"holding\""
        ),
        "{}",
        p[0]
    );
}

#[test]
fn humanized_messages() {
    assert_eq!(
        humanize("unknown field `baudrate`, expected one of `baud`, `parity`"),
        "unknown key; did you mean `baud`?"
    );
    assert_eq!(
        humanize("unknown field `speed`, expected one of `baud`, `parity`"),
        "unknown key; expected one of `baud`, `parity`"
    );
    assert_eq!(
        humanize("unknown field `x`, there are no fields"),
        "unknown key; this table takes no keys"
    );
    assert_eq!(
        humanize("invalid type: integer `5`, expected struct DeviceConfig"),
        "invalid type: integer `5`, expected a table"
    );
    assert_eq!(
        closest("stopbits", &["stop_bits", "baud"]),
        Some("stop_bits")
    );
    assert_eq!(closest("retry", &["retries", "unit_id"]), Some("retries"));
    assert_eq!(closest("colour", &["address", "unit_id"]), None);
    assert_eq!(closest("axis", &["axes", "devices"]), Some("axes"));
    assert_eq!(edit_distance("kitten", "sitting"), 3);
}

#[test]
fn secs_saturates() {
    use std::time::Duration;
    assert_eq!(secs(0.5), Duration::from_millis(500));
    assert_eq!(secs(-1.0), Duration::ZERO);
    assert_eq!(secs(f64::NAN), Duration::ZERO);
    assert_eq!(secs(f64::INFINITY), Duration::MAX);
}

#[test]
fn every_missing_key_of_a_table_is_reported() {
    let text = format!(
        "{EXAMPLE}\n[channels.T_new]\nfilter = {{ median_samples = 2 }}\n\n\
         [channels.T_new2]\ndevice = \"ain1\"\nregister = \"input\"\naddress = 7\n\
         data_type = \"u16\"\nscaling = {{ kind = \"transmitter\", adc_full_scale_ma = 24.0 }}\n"
    );
    let p = problems(&text);
    assert_eq!(
        keys(&p),
        [
            // register and address depend on the device's transport: validation
            // reports them once the device is known.
            "channels.T_new.device",
            "channels.T_new.data_type",
            "channels.T_new.scaling",
            "channels.T_new2.scaling.adc_full_scale_counts",
            "channels.T_new2.scaling.range_min_degc",
            "channels.T_new2.scaling.range_max_degc",
        ],
        "the even median of T_new is not judged on stand-ins: {p:#?}"
    );
}

#[test]
fn a_key_of_another_transport_is_an_unknown_key() {
    let p = problems(&edit(
        "address = \"127.0.0.1:5020\"\n",
        "address = \"127.0.0.1:5020\"\nbaud_rate = 9600\nbaud = 9600\n",
    ));
    assert_eq!(
        keys(&p),
        ["devices.ain1.baud", "devices.ain1.baud_rate"],
        "{p:#?}"
    );
    assert!(
        p[0].message.contains("not used by transport = \"tcp\"")
            && p[0].message.contains("only for transport = \"rtu\""),
        "{}",
        p[0]
    );
    assert!(p[1].message.starts_with("unknown key"), "{}", p[1]);
    assert!(p[1].message.contains("`baud`"), "{}", p[1]);
}

#[test]
fn a_type_error_does_not_hide_an_unknown_device_of_the_same_entry() {
    let p = problems(
        &edit("device = \"ain2\"", "device = \"ain9\"")
            .replace("address = 1000\n", "address = \"x\"\n"),
    );
    assert_eq!(
        keys(&p),
        ["channels.T_ambient.address", "channels.T_ambient.device"],
        "{p:#?}"
    );
    assert!(
        p[0].message.ends_with("expected an integer 0..=65535"),
        "{}",
        p[0]
    );
    assert!(
        p[1].message.starts_with("unknown device `ain9`"),
        "{}",
        p[1]
    );
}

#[test]
fn type_errors_in_two_entries_are_both_reported() {
    let text = edit("timeout_s = 0.3", "timeout_s = \"slow\"")
        .replace("md32750 = 3", "md32750 = \"three\"");
    let p = problems(&text);
    assert_eq!(
        keys(&p),
        ["axes.X.md32750", "devices.ain2.timeout_s"],
        "{p:#?}"
    );
}

// ------------------------------------------------------------- hostile values --

/// The one problem of the example with `from` replaced by `to`.
fn only_problem(from: &str, to: &str) -> ConfigProblem {
    let p = problems(&edit(from, to));
    assert_eq!(p.len(), 1, "{p:#?}");
    p.into_iter().next().unwrap()
}

#[test]
fn a_tiny_timeout_names_the_key_and_the_range() {
    let p = only_problem(
        "timeout_s = 0.5\n# Connect",
        "timeout_s = 1e-320\n# Connect",
    );
    assert_eq!(p.key, "devices.ain1.timeout_s", "{p}");
    assert_eq!(
        p.message,
        "invalid value: floating point `1e-320`, expected a number 0.001..=3600"
    );
}

#[test]
fn a_huge_interval_names_the_key_and_the_range() {
    let p = only_problem("status_interval_s = 1.0", "status_interval_s = 1e308");
    assert_eq!(p.key, "gateway.status_interval_s", "{p}");
    assert_eq!(
        p.message,
        "invalid value: floating point `1e308`, expected a number 0.001..=3600"
    );
}

#[test]
fn huge_retries_name_the_key_and_the_range() {
    let p = only_problem("retries = 1\n# Seconds", "retries = 4000000000\n# Seconds");
    assert_eq!(p.key, "devices.ain1.retries", "{p}");
    assert_eq!(
        p.message,
        "invalid value: integer `4000000000`, expected an integer 0..=100"
    );
}

#[test]
fn a_huge_coefficient_names_the_key_and_the_range() {
    let p = problems(&edit(
        "coeff_mm_per_degc = 0.004",
        "coeff_mm_per_degc = -1e308",
    ));
    assert_eq!(p.len(), 1, "{p:#?}");
    assert_eq!(p[0].key, "axes.X.k0.terms[0].coeff_mm_per_degc", "{}", p[0]);
    assert_eq!(
        p[0].message,
        "invalid value: floating point `-1e308`, expected a number -1..=1"
    );
}

#[test]
fn a_huge_limit_names_the_key_and_the_range() {
    let p = only_problem("max_abs_k0_mm = 0.5", "max_abs_k0_mm = 1e308");
    assert_eq!(p.key, "axes.X.max_abs_k0_mm", "{p}");
    assert!(
        p.message.ends_with("expected a number > 0 and <= 10"),
        "{p}"
    );
}

// A limit that must be > 0: the JSON Schema says `exclusiveMinimum` (an editor
// checking against it accepted 0, which validate refused), and the structural check
// and a type error state the range validation states: > 0 and <= 10.
#[test]
fn a_limit_that_must_be_positive_says_so_in_the_schema_and_every_message() {
    let schema = crate::config::json_schema();
    let axis = &schema["$defs"]["AxisConfig"]["properties"];
    for (key, max) in [
        ("max_abs_k0_mm", 10.0),
        ("max_step_k0_mm", 10.0),
        ("max_abs_tan_beta", 0.1),
        ("max_step_tan_beta", 0.1),
    ] {
        assert_eq!(axis[key]["exclusiveMinimum"], 0.0, "{key}: {}", axis[key]);
        assert!(axis[key].get("minimum").is_none(), "{key}: {}", axis[key]);
        assert_eq!(axis[key]["maximum"], max, "{key}");
    }
    let p = only_problem("max_step_k0_mm = 0.02", "max_step_k0_mm = 0");
    assert_eq!(p.key, "axes.X.max_step_k0_mm", "{p}");
    assert_eq!(
        p.message,
        "invalid value: integer `0`, expected a number > 0 and <= 10"
    );
    let p = only_problem("max_step_k0_mm = 0.02", "max_step_k0_mm = \"abc\"");
    assert_eq!(
        p.message,
        "invalid type: string \"abc\", expected a number > 0 and <= 10"
    );
    let p = only_problem("max_abs_tan_beta = 0.01", "max_abs_tan_beta = -0.0");
    assert!(
        p.message.ends_with("expected a number > 0 and <= 0.1"),
        "{p}"
    );
}

// metrics.max_connections had no range in the schema (an editor accepted 0 and 10^9;
// a type error said ">= 0").
#[test]
fn metrics_max_connections_has_its_range_in_the_schema() {
    let p = problems(&format!("{EXAMPLE}\n[metrics]\nmax_connections = 0\n"));
    assert_eq!(p.len(), 1, "{p:#?}");
    assert_eq!(p[0].key, "metrics.max_connections");
    assert_eq!(
        p[0].message,
        "invalid value: integer `0`, expected an integer 1..=256"
    );
}

// A name over 64 characters (perhaps megabytes) is reported by its length and first
// characters, in its key path too, never echoed.
#[test]
fn a_name_too_long_is_reported_by_its_length_not_echoed() {
    let long = format!("T_{}", "t".repeat(1 << 20));
    let text = EXAMPLE.replace("T_bed", &long);
    let p = problems(&text);
    assert!(!p.is_empty());
    for problem in &p {
        let shown = problem.to_string();
        assert!(
            shown.len() < 300,
            "{} bytes: {}",
            shown.len(),
            &shown[..300]
        );
    }
    let name = p
        .iter()
        .find(|p| p.key.starts_with("channels."))
        .expect("the channel's own problem");
    assert_eq!(
        name.key,
        format!("channels.<T_tttttttttttttt…, {} characters>", (1 << 20) + 2)
    );
    assert_eq!(
        name.message,
        format!("name of {} characters, longer than 64", (1 << 20) + 2)
    );
}

#[test]
fn a_megabyte_serial_path_names_the_key_and_the_length() {
    let long = "x".repeat(1 << 20);
    let p = only_problem(
        "serial_path = \"/dev/ttyUSB0\"",
        &format!("serial_path = \"/dev/{long}\""),
    );
    assert_eq!(p.key, "devices.ain2.serial_path", "{p}");
    assert_eq!(
        p.message,
        format!(
            "invalid value: a string of {} characters, expected a string of at most 1024 \
             characters",
            (1 << 20) + 5
        )
    );
}

#[test]
fn transport_true_says_which_transports_there_are() {
    let p = only_problem("transport = \"tcp\"", "transport = true");
    assert_eq!(p.key, "devices.ain1.transport", "{p}");
    assert_eq!(
        p.message,
        "invalid type: boolean `true`, expected one of `tcp`, `rtu`, `can`"
    );
}

/// The example with its `[nc_modules.nc_x]` table replaced by `target` (a `[targets]`
/// entry named `nc_x`) and `axis` appended to `[axes.X]`.
fn with_target(target: &str, axis: &str) -> String {
    let start = EXAMPLE.find("[nc_modules.nc_x]").expect("nc_x in example");
    let end = start + EXAMPLE[start..].find("\n\n").expect("end of the table");
    let text = format!("{}{target}{}", &EXAMPLE[..start], &EXAMPLE[end..]);
    text.replace(
        "nc_module = \"nc_x\"\n",
        &format!("nc_module = \"nc_x\"\n{axis}"),
    )
}

const ADS: &str = "[targets.nc_x]\nkind = \"ads\"\naddress = \"127.0.0.1:48898\"\n\
                   ams_net_id = \"127.0.0.1.1.1\"\nsd43900 = { index_group = 0x4020, index_offset = 0 }";

#[test]
fn a_target_table_takes_only_its_kinds_keys() {
    // The same module as a `[targets]` entry loads and names the same writer.
    let modbus = with_target(
        "[targets.nc_x]\nkind = \"modbus\"\naddress = \"127.0.0.1:1502\"\nunit_id = 1",
        "",
    );
    let cfg = load_str(&modbus, "t.toml").expect("modbus target loads");
    assert_eq!(
        cfg.target("nc_x").map(|t| t.kind()),
        Some(TargetKind::Modbus)
    );
    assert!(cfg.nc_modules.is_empty());

    // An ADS key on a Modbus target is named as such.
    let p = problems(&with_target(
        "[targets.nc_x]\nkind = \"modbus\"\naddress = \"127.0.0.1:1502\"\nunit_id = 1\nams_port = 851",
        "",
    ));
    assert_eq!(keys(&p), ["targets.nc_x.ams_port"], "{p:#?}");
    assert!(p[0].message.contains("ads"), "{}", p[0].message);

    // An unknown kind names the kinds there are.
    let p = problems(&modbus.replace("kind = \"modbus\"", "kind = \"fanuc\""));
    assert_eq!(keys(&p), ["targets.nc_x.kind"], "{p:#?}");
    assert!(p[0].message.contains("modbus"), "{}", p[0].message);
}

#[test]
fn an_axis_on_a_several_axis_target_needs_its_number_and_a_place_for_each_value() {
    let p = problems(&with_target(ADS, ""));
    let k = keys(&p);
    assert!(k.contains(&"axes.X.axis_number"), "{p:#?}");
    // The example's X writes all three; this ADS target has a place for SD43900 only.
    let p = problems(&with_target(ADS, "axis_number = 1\n"));
    assert_eq!(keys(&p), ["axes.X.nc_write", "axes.X.nc_write"], "{p:#?}");
    assert!(p[0].message.contains("SD43910"), "{}", p[0].message);
    // Leaving them out is right for a K0-only axis, and not for X's slope model.
    let only_k0 = "axis_number = 1\nnc_write = [\"sd43900\"]\n";
    let p = problems(&with_target(ADS, only_k0));
    assert_eq!(keys(&p), ["axes.X.nc_write", "axes.X.nc_write"], "{p:#?}");
    assert!(p[0].message.starts_with("leaves out SD43910"), "{}", p[0]);
    let cfg = load_str(&without_slope(&with_target(ADS, only_k0)), "t.toml")
        .expect("a K0-only axis loads with an allow-list of SD43900");
    assert_eq!(cfg.axes["X"].nc_write_ids(), [43900]);
    let p = problems(&without_slope(&with_target(
        &ADS.replace("127.0.0.1.1.1", "1.2.3"),
        only_k0,
    )));
    assert_eq!(keys(&p), ["targets.nc_x.ams_net_id"], "{p:#?}");
}

/// `text` (the example) without axis X's tan(beta) model.
fn without_slope(text: &str) -> String {
    let start = text.find("[axes.X.tan_beta]").expect("X has a slope");
    let end = start + text[start..].find("]\n").expect("end of the terms") + 2;
    let end = end + text[end..].find("]\n").expect("end of the table") + 2;
    format!("{}{}", &text[..start], &text[end..])
}

const MINIMAL: &str = include_str!("../../../../../config/minimal.toml");

// minimal.toml's X models tan(beta) only; `nc_write = ["sd43900"]` validated, and the
// NC never received SD43910 while the log said every job was written and verified.
#[test]
fn nc_write_leaving_out_the_modelled_slope_is_refused() {
    let text = MINIMAL.replace("md32750 = 2\n", "md32750 = 2\nnc_write = [\"sd43900\"]\n");
    let p = problems(&text);
    assert_eq!(keys(&p), ["axes.X.nc_write", "axes.X.nc_write"], "{p:#?}");
    assert_eq!(
        p[0].to_string(),
        "t.toml: axes.X.nc_write: leaves out SD43910, but the axis models tan(beta): the NC \
         would never receive it; add \"sd43910\" to nc_write or take tan(beta) out of the model"
    );
    assert!(p[1].message.starts_with("leaves out SD43920"), "{}", p[1]);
    let text = MINIMAL.replace(
        "md32750 = 2\n",
        "md32750 = 2\nnc_write = [\"sd43910\", \"sd43920\"]\n",
    );
    load_str(&text, "t.toml").expect("K0 is not modelled: leaving out SD43900 is fine");
}

// A channel left out for a type error still reads its device.
#[test]
fn a_broken_channel_still_reads_its_device() {
    let text = EXAMPLE.replace("address = 1000\n", "address = \"x\"\n");
    let p = problems(&text);
    assert_eq!(keys(&p), ["channels.T_ambient.address"], "{p:#?}");
    let p = problems(&edit("device = \"ain2\"\n", ""));
    assert_eq!(
        keys(&p),
        ["channels.T_ambient.device"],
        "the device the broken channel reads is unknown: no device counts as unread"
    );
}

#[test]
fn empty_device_and_channel_tables_are_refused() {
    let p = problems("[devices]\n[channels]\n");
    assert_eq!(keys(&p), ["devices", "channels"], "{p:#?}");
    assert!(p[0].message.starts_with("no device defined"), "{}", p[0]);
}

// `COMPGATE__DEVICES__AIN2__TIMEOUT_S` with no `[devices.ain2]` in the file: the
// missing transport was blamed on the file.
#[test]
fn an_entry_created_by_the_environment_says_so() {
    let p = problems_env(MINIMAL, &[("COMPGATE__DEVICES__AIN2__TIMEOUT_S", "1")]);
    assert_eq!(keys(&p), ["devices.ain2.transport"], "{p:#?}");
    assert_eq!(
        p[0].to_string(),
        "t.toml: devices.ain2.transport: required key is missing (environment: \
         COMPGATE__DEVICES__AIN2__TIMEOUT_S creates `devices.ain2` which the file lacks)"
    );
    // An override of an entry the file has keeps the plain note.
    let p = problems_env(MINIMAL, &[("COMPGATE__DEVICES__AIN1__TIMEOUT_S", "-1")]);
    assert_eq!(keys(&p), ["devices.ain1.timeout_s"], "{p:#?}");
    assert!(
        p[0].message
            .ends_with("(environment: COMPGATE__DEVICES__AIN1__TIMEOUT_S)"),
        "{}",
        p[0]
    );
}

#[test]
fn a_trend_span_out_of_range_names_the_key() {
    let p = problems(&format!("{EXAMPLE}\n[metrics]\ntrend_s = 5.0\n"));
    assert_eq!(keys(&p), vec!["metrics.trend_s"], "{p:#?}");
    let cfg = load_str(
        &format!("{EXAMPLE}\n[metrics]\nstatus_page = false\n"),
        "t.toml",
    )
    .expect("valid");
    let m = cfg.metrics.expect("metrics");
    assert!(!m.status_page);
    assert_eq!((m.bind.as_str(), m.trend_s), ("127.0.0.1:9464", 300.0));
}

// A CAN node without channels is still started (NMT) and its heartbeat watched.
#[test]
fn a_can_node_without_channels_may_stand_alone() {
    let text = format!(
        "{}\n[devices.can_b]\ntransport = \"can\"\ninterface = \"vcan1\"\nnode_id = 5\n",
        include_str!("../../../../../config/can-example.toml")
    );
    load_str(&text, "can.toml").expect("a lone CAN node loads");
}

// A check after loading (the recorder's path) names the variable that set its key,
// matched ignoring case as overrides are; an empty one sets nothing.
#[test]
fn the_variable_that_set_a_key_is_found_again() {
    let vars = |pairs: &[(&str, &str)]| env_vars_setting(env(pairs), "recorder.path");
    assert_eq!(
        vars(&[
            ("COMPGATE__RECORDER__PATH", "/x.db"),
            ("COMPGATE__RECORDER__COMMIT_INTERVAL_S", "1"),
            ("OTHER__RECORDER__PATH", "/y.db"),
        ]),
        ["COMPGATE__RECORDER__PATH"]
    );
    assert_eq!(
        vars(&[("compgate__Recorder__path", "/x.db")]),
        ["compgate__Recorder__path"]
    );
    assert!(vars(&[("COMPGATE__RECORDER__PATH", "")]).is_empty());
    assert_eq!(
        env_suffix(&["COMPGATE__RECORDER__PATH".into()]),
        " (environment: COMPGATE__RECORDER__PATH)"
    );
    assert_eq!(env_suffix(&[]), "");
}

// Three axes with one axis_number on a several-axis target: the third names both.
#[test]
fn an_axis_number_taken_twice_names_every_axis_that_has_it() {
    let axis = |name: &str| {
        format!("\n[axes.{name}]\nnc_module = \"nc_x\"\naxis_number = 1\nmd32750 = 3\n")
    };
    let text = with_target(ADS, "axis_number = 1\n") + &axis("Y") + &axis("Z");
    let p = problems(&text);
    let at = |key: &str| {
        p.iter()
            .find(|p| p.key == key)
            .map(|p| p.message.as_str())
            .unwrap_or_else(|| panic!("no problem at {key}: {p:#?}"))
    };
    assert_eq!(
        at("axes.Y.nc_module"),
        "axis `X` already has axis_number 1 on target `nc_x`"
    );
    assert_eq!(
        at("axes.Z.nc_module"),
        "axes `X`, `Y` already have axis_number 1 on target `nc_x`"
    );
}
