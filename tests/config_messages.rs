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
