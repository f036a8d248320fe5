//! The service when the machine is not there yet: READY=1 for systemd with every device
//! dead, a refused reload told in STATUS=, and how the log is written when stderr is
//! the journal and when `JOURNAL_STREAM` is inherited but stderr is not the journal.

// Test helpers: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

mod common;

use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::process::{Gateway, BIN};

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

// Which values came from the environment is in the log once at start, variable and
// key; the value is not (a password may be one).
#[test]
fn the_environment_overrides_are_logged_at_start_without_their_values() {
    let dir = tempfile::tempdir().unwrap();
    let path = dead_plant_file(dir.path());
    let mut gw = Gateway::start(
        dir.path(),
        &path,
        &[("COMPGATE__DEVICES__AIN1__TIMEOUT_S", "0.375")],
    );
    gw.wait_notify(10.0, "READY=1", |m| m.lines().any(|l| l == "READY=1"));
    let log = gw.stderr_text();
    let line = "environment override: COMPGATE__DEVICES__AIN1__TIMEOUT_S -> devices.ain1.timeout_s";
    assert_eq!(
        log.lines()
            .filter(|l| l.contains(line) && l.contains("INFO"))
            .count(),
        1,
        "{log}"
    );
    assert!(!log.contains("0.375"), "{log}");
    assert!(gw.stop());
}

// A file that does not load on SIGHUP: the log and systemd's STATUS= both say the
// reload was refused, naming the problem, and STATUS= keeps saying it until a reload
// succeeds; the old configuration runs on.
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
    // Still running on the old config: the status line comes back, and keeps the
    // refusal (it used to be gone a second later) until a reload succeeds.
    let status = gw.wait_notify(10.0, "the status line again", |m| {
        m.contains("STATUS=ain1 ")
    });
    assert!(
        status.contains("; reload refused, old configuration running: ")
            && status.contains("timeot_s"),
        "{status}"
    );
    std::fs::write(&path, &good).unwrap();
    gw.signal("HUP");
    gw.wait_notify(10.0, "the status line without the refusal", |m| {
        m.contains("STATUS=ain1 ") && !m.contains("reload refused")
    });
    assert!(gw.stop());
}

/// Runs the gateway on `config` with stderr on `stderr` and
/// `JOURNAL_STREAM=journal_stream` until its log holds "device link down" or 15 s
/// pass; returns the log.
fn run_with_journal_stream(config: &Path, stderr: &Path, journal_stream: &str) -> String {
    let mut child = Command::new(BIN)
        .args(["run", "--config"])
        .arg(config)
        .env("JOURNAL_STREAM", journal_stream)
        .env_remove("NOTIFY_SOCKET")
        .env_remove("RUST_LOG")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(stderr).unwrap())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(15);
    let log = || std::fs::read_to_string(stderr).unwrap_or_default();
    while Instant::now() < deadline && !log().contains("device link down") {
        if let Some(st) = child.try_wait().unwrap() {
            panic!("the gateway exited ({st}):\n{}", log());
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let _ = child.kill();
    let _ = child.wait();
    log()
}

// `JOURNAL_STREAM` is inherited by every process of a systemd (user) session, a
// terminal's too: only a stderr that is the very stream it names (device and inode)
// is the journal. There each line starts with its syslog priority, which journald
// takes as its level, and holds the event's fields, which `journalctl -u compgate`
// shows (tests/systemd/ checks that under a real systemd). Elsewhere the line is
// stamped with its time, for the person who looks at the terminal or the file.
#[test]
fn log_lines_carry_their_level_for_the_journal_only_when_stderr_is_the_journal_stream() {
    let dir = tempfile::tempdir().unwrap();
    let config = dead_plant_file(dir.path());
    let down = |log: &str| {
        log.lines()
            .find(|l| l.contains("device link down"))
            .map(str::to_string)
            .unwrap_or_else(|| panic!("no device link down in:\n{log}"))
    };

    // stderr on a file, JOURNAL_STREAM naming another one (the config).
    let other = std::fs::metadata(&config).unwrap();
    let stderr = dir.path().join("stderr-1.txt");
    let line = down(&run_with_journal_stream(
        &config,
        &stderr,
        &format!("{}:{}", other.dev(), other.ino()),
    ));
    assert!(
        !line.starts_with('<')
            && line.starts_with(char::is_numeric)
            && line.contains("device=ain1"),
        "{line}"
    );

    // JOURNAL_STREAM naming stderr itself: the journal's stream.
    let stderr = dir.path().join("stderr-2.txt");
    std::fs::write(&stderr, "").unwrap();
    let me = std::fs::metadata(&stderr).unwrap();
    let log = run_with_journal_stream(&config, &stderr, &format!("{}:{}", me.dev(), me.ino()));
    let line = down(&log);
    assert!(
        line.starts_with("<4> WARN") && line.contains("device=ain1") && line.contains("error="),
        "{line}"
    );
    assert!(
        log.lines().all(|l| l.starts_with("<3>")
            || l.starts_with("<4>")
            || l.starts_with("<6>")
            || l.starts_with("<7>")),
        "{log}"
    );
}
