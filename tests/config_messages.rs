//! What `validate` says of values that came from the environment.

mod common;

use std::process::Command;

use common::process::BIN;

// recorder.path is checked on the file system after loading: its problem names the
// variable that set it, as every problem of loading does.
#[test]
fn a_recorder_path_from_the_environment_is_named_with_its_variable() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("plant.toml");
    let text = std::fs::read_to_string("config/example.toml").unwrap() + "\n[recorder]\n";
    std::fs::write(&path, text).unwrap();
    let missing = dir.path().join("nonexistent").join("x.db");
    let out = Command::new(BIN)
        .args(["validate", "--config"])
        .arg(&path)
        .env("COMPGATE__RECORDER__PATH", &missing)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains(&format!(
            "{}: recorder.path: {}: the directory",
            path.display(),
            missing.display()
        )) && err
            .trim_end()
            .ends_with("(environment: COMPGATE__RECORDER__PATH)"),
        "{err}"
    );
}

// Nothing in the file shows that a value came from the environment: validate lists
// the overrides after OK, variable and key, never the value (a password may be one).
// An empty override and one with a single `_` after COMPGATE, which ran the file's
// value instead (another machine's NC address), are problems.
#[test]
fn validate_lists_the_overrides_and_refuses_empty_and_mistyped_ones() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("plant.toml");
    std::fs::copy("config/example.toml", &path).unwrap();
    let validate = |vars: &[(&str, &str)]| {
        let mut cmd = Command::new(BIN);
        cmd.args(["validate", "--config"]).arg(&path);
        for (k, v) in vars {
            cmd.env(k, v);
        }
        let out = cmd.output().unwrap();
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stdout).into_owned(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let (code, stdout, stderr) = validate(&[
        ("COMPGATE__NC_MODULES__NC_X__ADDRESS", "127.0.0.1:5099"),
        ("COMPGATE__DEVICES__AIN1__TIMEOUT_S", "0.25"),
        ("COMPGATE_OPCUA_USER", "operator"),
    ]);
    assert_eq!(code, Some(0), "{stderr}");
    assert_eq!(
        stdout,
        format!(
            "{}: OK\n\
             environment override: COMPGATE__DEVICES__AIN1__TIMEOUT_S -> devices.ain1.timeout_s\n\
             environment override: COMPGATE__NC_MODULES__NC_X__ADDRESS -> nc_modules.nc_x.address\n",
            path.display()
        )
    );
    assert!(
        !(stdout.clone() + &stderr).contains("5099"),
        "{stdout}{stderr}"
    );

    let (code, _, stderr) = validate(&[("COMPGATE__NC_MODULES__NC_X__ADDRESS", "")]);
    assert_eq!(code, Some(1), "{stderr}");
    assert!(
        stderr.contains(&format!(
            "{}: nc_modules.nc_x.address: the environment variable \
             COMPGATE__NC_MODULES__NC_X__ADDRESS is empty: unset it to keep the file's value, \
             or give one",
            path.display()
        )),
        "{stderr}"
    );
    let (code, _, stderr) = validate(&[("COMPGATE_NC_MODULES__NC_X__ADDRESS", "127.0.0.1:5099")]);
    assert_eq!(code, Some(1), "{stderr}");
    assert!(
        stderr.contains("write COMPGATE__NC_MODULES__NC_X__ADDRESS"),
        "{stderr}"
    );
}

/// example.toml with its NC module replaced by an OPC UA target whose credentials are
/// given by `credentials` (`credentials_file = ...` or `user_env`/`password_env`).
fn opcua_config(dir: &std::path::Path, credentials: &str) -> std::path::PathBuf {
    let text = std::fs::read_to_string("config/example.toml").expect("example.toml");
    let start = text.find("[nc_modules.nc_x]").expect("its NC module");
    let end = text.find("[axes.X]").expect("its axis");
    let target = format!(
        "[targets.nc_x]\nkind = \"opcua\"\nendpoint_url = \"opc.tcp://127.0.0.1:4840\"\n\
         {credentials}\n\n"
    );
    let text = format!("{}{target}{}", &text[..start], &text[end..]).replace(
        "nc_module = \"nc_x\"\n",
        "nc_module = \"nc_x\"\naxis_number = 1\n",
    );
    let path = dir.join("opcua.toml");
    std::fs::write(&path, text).expect("config written");
    path
}

/// `compgate <command> --config path` with the credentials variables unset.
fn compgate(command: &str, path: &std::path::Path) -> (Option<i32>, String) {
    let out = Command::new(BIN)
        .args([command, "--config"])
        .arg(path)
        .env_remove("CG_TEST_OPCUA_USER")
        .env_remove("CG_TEST_OPCUA_PW")
        .output()
        .expect("compgate runs");
    let text =
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    (out.status.code(), text)
}

// validate passed an OPC UA target whose credentials could not be read while run
// refused to start: under the unit ExecStartPre= passed and the service restart-looped.
#[test]
fn validate_reads_the_opcua_credentials_as_run_does() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("absent-creds");
    let path = opcua_config(
        dir.path(),
        &format!("credentials_file = {:?}", missing.display().to_string()),
    );
    let want = format!(
        "{}: targets.nc_x.credentials_file: {}: No such file",
        path.display(),
        missing.display()
    );
    for command in ["validate", "run"] {
        let (code, text) = compgate(command, &path);
        assert_eq!(code, Some(1), "{command}: {text}");
        assert!(text.contains(&want), "{command}: {text}");
    }

    // A file without a user name on its first line: refused, the password not shown.
    let creds = dir.path().join("creds");
    std::fs::write(&creds, "\nsecret-pw-4711\n").unwrap();
    let path = opcua_config(
        dir.path(),
        &format!("credentials_file = {:?}", creds.display().to_string()),
    );
    let (code, text) = compgate("validate", &path);
    assert_eq!(code, Some(1), "{text}");
    assert!(
        text.contains("targets.nc_x.credentials_file:")
            && text.contains("first line (user name) is empty"),
        "{text}"
    );
    assert!(!text.contains("secret-pw-4711"), "{text}");
    // The user without a password line (a file caught half written): refused.
    std::fs::write(&creds, "operator\n").unwrap();
    let (code, text) = compgate("validate", &path);
    assert_eq!(code, Some(1), "{text}");
    assert!(text.contains("second line (password) is missing"), "{text}");
    std::fs::write(&creds, "operator\nsecret-pw-4711\n").unwrap();
    let (code, text) = compgate("validate", &path);
    assert_eq!(code, Some(0), "{text}");

    let path = opcua_config(
        dir.path(),
        "user_env = \"CG_TEST_OPCUA_USER\"\npassword_env = \"CG_TEST_OPCUA_PW\"",
    );
    let (code, text) = compgate("validate", &path);
    assert_eq!(code, Some(1), "{text}");
    assert!(
        text.contains(&format!(
            "{}: targets.nc_x.user_env: environment variable CG_TEST_OPCUA_USER is not set",
            path.display()
        )),
        "{text}"
    );
    let out = Command::new(BIN)
        .args(["validate", "--config"])
        .arg(&path)
        .env("CG_TEST_OPCUA_USER", "operator")
        .env("CG_TEST_OPCUA_PW", "secret-pw-4711")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

// `run` warned of a credentials file others may read; validate, which
// `systemctl reload` runs, said nothing.
#[test]
fn validate_warns_of_a_credentials_file_others_may_read() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let cred = dir.path().join("cred");
    std::fs::write(&cred, "writer\nwriter-pw\n").unwrap();
    let path = opcua_config(
        dir.path(),
        &format!("credentials_file = {:?}", cred.display().to_string()),
    );
    for (mode, warned) in [(0o644, true), (0o600, false)] {
        std::fs::set_permissions(&cred, std::fs::Permissions::from_mode(mode)).unwrap();
        let (code, text) = compgate("validate", &path);
        assert_eq!(code, Some(0), "{text}");
        assert_eq!(
            text.contains(&format!(
                "targets.nc_x.credentials_file: {} is readable by group or others",
                cred.display()
            )),
            warned,
            "mode {mode:o}: {text}"
        );
    }
}
