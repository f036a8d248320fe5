//! Every shipped configuration loads and validates, and the loader's promises hold
//! for real files on disk: every typo reported with its path and file, environment
//! overrides applied, broken references and missing keys named.

use std::path::{Path, PathBuf};

use compgate_gateway::config::{self, ConfigError, ConfigProblem};

fn config_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("config")
}

/// Every `*.toml` in `config/`, so a new example file is covered without a new test.
fn shipped_files() -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(config_dir())
        .expect("config/ exists")
        .map(|e| e.expect("readable entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    files.sort();
    files
}

fn no_env() -> std::iter::Empty<(String, String)> {
    std::iter::empty()
}

/// Writes `text` to a temporary file named `name` and loads it without environment.
fn load_text(
    name: &str,
    text: &str,
) -> (
    PathBuf,
    Result<config::Config, ConfigError>,
    tempfile::TempDir,
) {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join(name);
    std::fs::write(&path, text).expect("write");
    let result = config::load_with_env(&path, no_env());
    (path, result, dir)
}

fn problems(result: Result<config::Config, ConfigError>) -> Vec<ConfigProblem> {
    match result {
        Ok(_) => panic!("expected problems"),
        Err(ConfigError::Invalid(p)) => p,
        Err(e) => panic!("unexpected error {e}"),
    }
}

fn example_text() -> String {
    std::fs::read_to_string(config_dir().join("example.toml")).expect("example.toml")
}

#[test]
fn every_shipped_config_loads_and_validates_cleanly() {
    let files = shipped_files();
    for name in ["example.toml", "demo.toml", "minimal.toml"] {
        assert!(
            files.iter().any(|f| f.ends_with(name)),
            "{name} missing from {files:?}"
        );
    }
    for file in &files {
        // demo.toml's port 0 is for the simulated plant only (`compgate demo`, `sim`).
        let demo = file.ends_with("demo.toml");
        let loaded = if demo {
            config::load_for_sim(file)
        } else {
            config::load_with_env(file, no_env())
        };
        let cfg = match loaded {
            Ok(cfg) => cfg,
            Err(e) => panic!("{}: {e}", file.display()),
        };
        if !demo {
            let again = config::validate(&cfg, &file.display().to_string());
            assert!(again.is_empty(), "{again:#?}");
        }
    }
}

/// `compgate run --config config/demo.toml` connected to port 0 for ever: the file
/// loads for `run` no more, naming each address and where port 0 belongs.
#[test]
fn port_0_is_refused_for_run_and_left_to_the_simulated_plant() {
    let file = config_dir().join("demo.toml");
    let p = problems(config::load_with_env(&file, no_env()));
    let keys: Vec<&str> = p.iter().map(|p| p.key.as_str()).collect();
    assert_eq!(keys, ["devices.ain1.address", "nc_modules.nc_x.address"]);
    for p in &p {
        assert_eq!(p.file, file.display().to_string());
        assert!(
            p.message.contains("port 0 cannot be connected to")
                && p.message.contains("`compgate demo` and `compgate sim`"),
            "{p}"
        );
    }
    // Without [sim] no hint about the simulator.
    let text = example_text().replace("127.0.0.1:5020", "127.0.0.1:0");
    let (_path, result, _dir) = load_text("zero.toml", &text);
    let p = problems(result);
    assert_eq!(p.len(), 1, "{p:#?}");
    assert_eq!(p[0].key, "devices.ain1.address");
    assert!(!p[0].message.contains("compgate sim"), "{}", p[0]);
    // The demo's path: the text loads and the plant picks the ports.
    let text = std::fs::read_to_string(&file).expect("demo.toml");
    config::load_str(&text, "demo.toml").expect("the demo's embedded config loads");
}

/// A deadband no change can pass held the axis silently: refused, naming the limit.
#[test]
fn a_deadband_no_change_can_pass_is_refused() {
    let text = example_text()
        .replace("deadband_k0_mm = 0.001", "deadband_k0_mm = 5")
        .replace("deadband_tan_beta = 0.000001", "deadband_tan_beta = 0.05");
    let (_path, result, _dir) = load_text("deadband.toml", &text);
    let p = problems(result);
    let lines: Vec<String> = p
        .iter()
        .map(|p| format!("{}: {}", p.key, p.message))
        .collect();
    assert_eq!(lines.len(), 2, "{lines:#?}");
    assert!(
        lines[0].starts_with("axes.X.deadband_k0_mm: 5 is above max_step_k0_mm = 0.02"),
        "{lines:#?}"
    );
    assert!(
        lines[1].starts_with("axes.X.deadband_tan_beta: 0.05 is above max_step_tan_beta"),
        "{lines:#?}"
    );
    // Below the step limit but not below the whole span of the limit.
    let text = example_text()
        .replace("deadband_k0_mm = 0.001", "deadband_k0_mm = 0.01")
        .replace("max_abs_k0_mm = 0.5", "max_abs_k0_mm = 0.005");
    let (_path, result, _dir) = load_text("deadband.toml", &text);
    let p = problems(result);
    assert_eq!(p.len(), 1, "{p:#?}");
    assert_eq!(p[0].key, "axes.X.deadband_k0_mm");
    assert!(
        p[0].message
            .starts_with("0.01 is not below 2 x max_abs_k0_mm = 0.01"),
        "{}",
        p[0]
    );
}

#[test]
fn a_value_listed_twice_in_nc_write_is_refused() {
    let text = example_text().replace(
        "nc_module = \"nc_x\"\n",
        "nc_module = \"nc_x\"\nnc_write = [\"sd43900\", \"sd43910\", \"sd43900\", \"sd43920\"]\n",
    );
    let (_path, result, _dir) = load_text("dup.toml", &text);
    let p = problems(result);
    assert_eq!(p.len(), 1, "{p:#?}");
    assert_eq!(p[0].key, "axes.X.nc_write");
    assert!(
        p[0].message
            .starts_with("\"sd43900\" is listed more than once"),
        "{}",
        p[0]
    );
}

/// A URL's scheme and an IPv6 zone by name got "write an IPv6 address in brackets".
#[test]
fn a_scheme_and_a_zone_name_in_an_address_get_their_own_reason() {
    let text = example_text()
        .replace("127.0.0.1:5020", "tcp://127.0.0.1:502")
        .replace("127.0.0.1:5021", "[fe80::1%eth0]:502");
    let (_path, result, _dir) = load_text("scheme.toml", &text);
    let lines: Vec<String> = problems(result)
        .iter()
        .map(|p| format!("{}: {}", p.key, p.message))
        .collect();
    assert_eq!(
        lines,
        [
            "devices.ain1.address: `tcp://127.0.0.1:502`: no scheme: write host:port, e.g. \
             \"192.168.0.10:502\"",
            "nc_modules.nc_x.address: `[fe80::1%eth0]:502`: give the zone of the IPv6 address \
             as the interface's index, e.g. \"[fe80::1%2]:502\" (`ip link` lists it), not its name",
        ]
    );
    // The zone by index is what the socket code takes.
    let text = example_text().replace("127.0.0.1:5021", "[fe80::1%2]:502");
    let (_path, result, _dir) = load_text("zone.toml", &text);
    result.expect("a zone index is accepted");
}

/// The broker got only a `rsplit_once(':')`: run then retried "failed to lookup address"
/// for ever. It gets the check of every other address now.
#[test]
fn the_mqtt_broker_is_checked_as_every_address() {
    let dir = tempfile::tempdir().expect("temp dir");
    let with = |broker: &str| {
        format!(
            "{}\n[recorder]\npath = {:?}\n\n[mqtt]\nbroker = {broker:?}\nmachine = \"m1\"\n",
            example_text(),
            dir.path().join("r.db").display().to_string()
        )
    };
    for (broker, why) in [
        ("mqtt://127.0.0.1:43883", "no scheme"),
        ("192.168.0.300:1883", "is not an IPv4 address"),
        (" broker:1883", "is not a valid host name"),
        ("a b:1883", "is not a valid host name"),
        ("[::1:1883", "is not an IPv6 address in brackets"),
        ("broker:0", "port 0 cannot be connected to"),
    ] {
        let (_path, result, _dir) = load_text("mqtt.toml", &with(broker));
        let p = problems(result);
        assert_eq!(p.len(), 1, "{broker}: {p:#?}");
        assert_eq!(p[0].key, "mqtt.broker", "{broker}");
        assert!(
            p[0].message.contains(why) && p[0].message.contains("broker.plant.local:1883"),
            "{broker}: {}",
            p[0]
        );
    }
    for ok in ["broker.plant.local:1883", "127.0.0.1:1883", "[::1]:1883"] {
        let (_path, result, _dir) = load_text("mqtt.toml", &with(ok));
        result.unwrap_or_else(|e| panic!("{ok}: {e}"));
    }
}

/// The broker's login comes from a file or two variables, as the OPC UA target's: a
/// problem names the `mqtt.` key and never what the file holds.
#[test]
fn the_mqtt_login_is_checked_at_load() {
    let dir = tempfile::tempdir().expect("temp dir");
    let with = |keys: &str| {
        format!(
            "{}\n[recorder]\npath = {:?}\n\n[mqtt]\nbroker = \"127.0.0.1:1883\"\nmachine = \"m1\"\n{keys}\n",
            example_text(),
            dir.path().join("r.db").display().to_string()
        )
    };
    let file = dir.path().join("mqtt.login");
    let missing = dir.path().join("nowhere.login");
    std::fs::write(&file, "compgate\nsecret\n").expect("write");
    for (keys, key, why) in [
        (
            format!(
                "credentials_file = {:?}\nuser_env = \"U\"\npassword_env = \"P\"",
                file.display().to_string()
            ),
            "mqtt.credentials_file",
            "not both",
        ),
        (
            "user_env = \"U\"".into(),
            "mqtt.password_env",
            "required with user_env",
        ),
        (
            "user_env = \"COMPGATE_TEST_NO_SUCH_USER\"\npassword_env = \"P\"".into(),
            "mqtt.user_env",
            "COMPGATE_TEST_NO_SUCH_USER is not set",
        ),
        (
            format!("credentials_file = {:?}", missing.display().to_string()),
            "mqtt.credentials_file",
            "nowhere.login: No such file",
        ),
    ] {
        let (_path, result, _dir) = load_text("mqtt.toml", &with(&keys));
        let p = problems(result);
        assert_eq!(p.len(), 1, "{keys}: {p:#?}");
        assert_eq!(p[0].key, key, "{keys}");
        assert!(p[0].message.contains(why), "{keys}: {}", p[0]);
    }
    let (_path, result, _dir) = load_text(
        "mqtt.toml",
        &with(&format!(
            "credentials_file = {:?}",
            file.display().to_string()
        )),
    );
    result.expect("a readable credentials file is accepted");
}

/// `T_` could not be reached by an override: `COMPGATE__CHANNELS__T___ADDRESS` split as
/// `T` and `_ADDRESS`. A name starting with `_` is still fine: the split reads from the
/// left.
#[test]
fn a_name_ending_in_an_underscore_is_refused() {
    let text = example_text()
        .replace("[channels.T_screw]", "[channels.T_screw_]")
        .replace("channel = \"T_screw\"", "channel = \"T_screw_\"");
    let (_path, result, _dir) = load_text("names.toml", &text);
    let p = problems(result);
    assert_eq!(p.len(), 1, "{p:#?}");
    assert_eq!(p[0].key, "channels.T_screw_");
    assert!(
        p[0].message.starts_with("name must not end in `_`"),
        "{}",
        p[0]
    );

    let text = example_text()
        .replace("[channels.T_screw]", "[channels._T_screw]")
        .replace("channel = \"T_screw\"", "channel = \"_T_screw\"");
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("lead.toml");
    std::fs::write(&path, text).expect("write");
    let env = [(
        "COMPGATE__CHANNELS___T_SCREW__ADDRESS".to_string(),
        "5".to_string(),
    )];
    let cfg = config::load_with_env(&path, env).expect("a leading `_` is reachable");
    assert_eq!(cfg.channels["_T_screw"].address, Some(5));
}

/// A UTF-16 file (Notepad's "Unicode") said only "stream did not contain valid UTF-8";
/// `--config /dev/zero` read until memory ran out.
#[test]
fn a_utf16_or_endless_file_gets_a_read_error_that_says_why() {
    let dir = tempfile::tempdir().expect("temp dir");
    let read_error = |path: &Path| match config::load_with_env(path, no_env()) {
        Err(ConfigError::Read { file, message }) => {
            assert_eq!(file, path.display().to_string());
            message
        }
        other => panic!("expected a read error, got {other:?}"),
    };
    let utf16 = dir.path().join("utf16.toml");
    let mut bytes = vec![0xff, 0xfe];
    bytes.extend(example_text().encode_utf16().flat_map(u16::to_le_bytes));
    std::fs::write(&utf16, bytes).expect("write");
    let m = read_error(&utf16);
    assert!(
        m.contains("UTF-16") && m.contains("save it as UTF-8"),
        "{m}"
    );

    let latin1 = dir.path().join("latin1.toml");
    let mut bytes = b"[gateway]\n# 20 \xb0C\n".to_vec();
    bytes.extend(example_text().bytes());
    std::fs::write(&latin1, bytes).expect("write");
    let m = read_error(&latin1);
    assert!(
        m.starts_with("line 2 is not UTF-8") && m.contains("save the file as UTF-8"),
        "{m}"
    );

    let big = dir.path().join("big.toml");
    let padding = "#".repeat(config::MAX_FILE_BYTES as usize);
    std::fs::write(&big, example_text() + &padding).expect("write");
    let m = read_error(&big);
    assert!(m.contains("larger than 64 MB"), "{m}");
    #[cfg(unix)]
    {
        let m = read_error(Path::new("/dev/zero"));
        assert!(m.contains("larger than 64 MB"), "{m}");
    }
}

#[test]
fn two_typos_are_both_reported_with_path_and_file() {
    let text = example_text()
        .replacen("retries = 1", "retry = 1", 1)
        .replace("valid_min_degc = -20.0\n", "valid_minimum_degc = -20.0\n");
    let (path, result, _dir) = load_text("typos.toml", &text);
    let p = problems(result);
    let file = path.display().to_string();
    let lines: Vec<String> = p.iter().map(|p| p.to_string()).collect();
    assert_eq!(
        lines,
        [
            format!("{file}: channels.T_bed.filter.valid_minimum_degc: unknown key; did you mean `valid_min_degc`?"),
            format!("{file}: devices.ain1.retry: unknown key; did you mean `retries`?"),
        ]
    );
}

#[test]
fn env_override_changes_a_value() {
    let file = config_dir().join("example.toml");
    let env = [
        ("COMPGATE__DEVICES__AIN1__TIMEOUT_S", "0.125"),
        ("COMPGATE__CHANNELS__T_SCREW__FILTER__VALID_MAX_DEGC", "60"),
        (
            "COMPGATE__AXES__X__TAN_BETA__TERMS__0__COEFF_PER_DEGC",
            "0.000012",
        ),
    ]
    .map(|(k, v)| (k.to_string(), v.to_string()));
    let cfg = config::load_with_env(&file, env).expect("valid with overrides");
    assert_eq!(cfg.devices["ain1"].common().timeout_s, 0.125);
    assert_eq!(cfg.channels["T_screw"].filter.valid_max_degc, 60.0);
    assert_eq!(cfg.axes["X"].tan_beta.terms[0].coeff_per_degc, 0.000012);
    assert_eq!(cfg.channels.len(), 3, "no lowercase twin of T_screw");

    let plain = config::load_with_env(&file, no_env()).expect("valid");
    assert_eq!(plain.devices["ain1"].common().timeout_s, 0.5);
}

#[test]
fn broken_reference_is_reported() {
    let text = example_text().replace(
        "{ channel = \"T_bed\", ref_degc = 20.0, coeff_mm_per_degc = 0.004 }",
        "{ channel = \"T_bedd\", ref_degc = 20.0, coeff_mm_per_degc = 0.004 }",
    );
    let (path, result, _dir) = load_text("ref.toml", &text);
    let p = problems(result);
    assert_eq!(p.len(), 1, "{p:#?}");
    assert_eq!(p[0].file, path.display().to_string());
    assert_eq!(p[0].key, "axes.X.k0.terms[0].channel");
    assert!(
        p[0].message.starts_with("unknown channel `T_bedd`"),
        "{}",
        p[0]
    );
}

#[test]
fn missing_required_key_is_reported_with_path() {
    let text = example_text().replace("unit_id = 7\n", "");
    let (_path, result, _dir) = load_text("missing.toml", &text);
    let p = problems(result);
    assert_eq!(p.len(), 1, "{p:#?}");
    assert_eq!(p[0].key, "devices.ain2.unit_id");
    // Required for Modbus transports only, so validation (not the parser) reports it.
    assert!(
        p[0].message
            .starts_with("required with transport = \"rtu\""),
        "{}",
        p[0]
    );
}

#[test]
fn unreadable_file_is_a_read_error() {
    let dir = tempfile::tempdir().expect("temp dir");
    let err =
        config::load_with_env(&dir.path().join("absent.toml"), no_env()).expect_err("no such file");
    assert!(matches!(err, ConfigError::Read { .. }), "{err}");
}

/// `compgate sim` on a shipped config sets its simulated NC up as the axis expects
/// (minimal.toml's axis has MD32750 = 2): a dry-run must not hold on an MD32750 the
/// simulator made up. An explicit `[sim.nc_modules]` value still wins.
#[tokio::test]
async fn the_simulated_nc_takes_the_axis_md32750_unless_told_otherwise() {
    use compgate::plant::{Bind, Plant};
    let cfg = config::load_with_env(&config_dir().join("minimal.toml"), no_env())
        .expect("minimal.toml loads");
    let plant = Plant::start(&cfg, Bind::Ephemeral).await.expect("plant");
    assert_eq!(plant.nc["nc_x"].state().md32750, 2);
    plant.stop();

    let text = std::fs::read_to_string(config_dir().join("minimal.toml")).expect("read")
        + "\n[sim.nc_modules.nc_x]\nmd32750 = 1\n";
    let (_, cfg, _dir) = load_text("m.toml", &text);
    let plant = Plant::start(&cfg.expect("loads"), Bind::Ephemeral)
        .await
        .expect("plant");
    assert_eq!(plant.nc["nc_x"].state().md32750, 1);
    plant.stop();
}
