//! The service when the machine is not there yet: READY=1 for systemd with every device
//! dead, and a refused reload told in STATUS=.

// Test helpers: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

mod common;

use std::path::{Path, PathBuf};

use common::process::Gateway;

/// The test config with its field device and NC module on ports nothing listens on,
/// a recorder in `dir` and the HTTP listener on port 0; written to `dir`.
fn dead_plant_file(dir: &Path) -> PathBuf {
    let toml = common::config("hold", "", "")
        .replacen(
            "127.0.0.1:0",
            &format!("127.0.0.1:{}", common::free_port()),
            1,
        )
        .replacen(
            "127.0.0.1:0",
            &format!("127.0.0.1:{}", common::free_port()),
            1,
        );
    let extra = format!(
        "\n[recorder]\npath = {:?}\n\n[metrics]\nbind = \"127.0.0.1:0\"\n",
        dir.join("rec.db").display().to_string()
    );
    let path = dir.join("compgate.toml");
    std::fs::write(&path, toml + &extra).unwrap();
    path
}

// A PC that boots before the machine's I/O is powered: no device answers. The service
// is up (recorder open, HTTP bound, tasks polling) and says so at once; under
// `Type=notify` a READY=1 that waited for a device would time the start out and put
// the service in a restart loop. STATUS= names the devices that are down.
#[test]
fn ready_at_start_with_every_device_dead_and_status_names_them() {
    let dir = tempfile::tempdir().unwrap();
    let path = dead_plant_file(dir.path());
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    let ready = gw.wait_notify(10.0, "READY=1", |m| m.lines().any(|l| l == "READY=1"));
    assert!(ready.contains("STATUS=ain1 "), "{ready}");
    // The listener was bound before READY.
    let port = gw.metrics_port(1.0);
    assert!(std::net::TcpStream::connect(("127.0.0.1", port)).is_ok());
    gw.wait_notify(10.0, "STATUS with ain1 down", |m| m.contains("ain1 down"));
    assert!(
        !gw.stderr_text().contains("device link up"),
        "{}",
        gw.stderr_text()
    );
    assert!(gw.stop());
}

// A file that does not load on SIGHUP: the log and systemd's STATUS= both say the
// reload was refused, naming the problem; the old configuration runs on.
#[test]
fn a_config_that_does_not_load_on_sighup_is_told_to_systemd() {
    let dir = tempfile::tempdir().unwrap();
    let path = dead_plant_file(dir.path());
    let good = std::fs::read_to_string(&path).unwrap();
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    gw.wait_notify(10.0, "READY=1", |m| m.lines().any(|l| l == "READY=1"));
    std::fs::write(&path, good.replace("timeout_s = 0.2", "timeot_s = 0.2")).unwrap();
    gw.signal("HUP");
    let status = gw.wait_notify(10.0, "STATUS reload refused", |m| {
        m.contains("STATUS=reload refused")
    });
    assert!(
        status.contains("old configuration running")
            && status.contains("devices.ain1.timeot_s: unknown key"),
        "{status}"
    );
    // One line: a newline would end the STATUS= assignment.
    assert_eq!(status.lines().count(), 1, "{status:?}");
    gw.wait_log(10.0, "reload refused");
    // Still running on the old config: the status line comes back.
    gw.wait_notify(10.0, "the status line again", |m| {
        m.contains("STATUS=ain1 ")
    });
    assert!(gw.stop());
}
