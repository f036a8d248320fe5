//! The service when the machine is not there yet: READY=1 for systemd with every device
//! dead, a refused reload told in STATUS=, and where the log goes when `JOURNAL_STREAM`
//! is inherited but stderr is not the journal.

// Test helpers: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

mod common;

use std::os::unix::fs::MetadataExt;
use std::os::unix::net::UnixDatagram;
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

/// Runs the gateway on `config` in a private mount namespace whose
/// /run/systemd/journal is `journal` (with a datagram socket the test reads, as
/// journald's), stderr on `stderr` and `JOURNAL_STREAM=journal_stream`, until its log
/// holds "device link down" in either place or 15 s pass; returns the datagrams.
fn run_with_journal(
    journal: &Path,
    config: &Path,
    stderr: &Path,
    journal_stream: &str,
) -> Vec<String> {
    let socket = UnixDatagram::bind(journal.join("socket")).unwrap();
    socket
        .set_read_timeout(Some(Duration::from_millis(100)))
        .unwrap();
    // A tmpfs over /run: /run/systemd may not exist, and nothing of it is needed.
    let script = "mount -t tmpfs tmpfs /run && mkdir -p /run/systemd/journal \
                  && mount --bind \"$0\" /run/systemd/journal && exec \"$@\"";
    let mut child = Command::new("unshare")
        .args(["--mount", "--propagation", "private", "sh", "-c", script])
        .arg(journal)
        .args([BIN, "run", "--config"])
        .arg(config)
        .env("JOURNAL_STREAM", journal_stream)
        .env_remove("NOTIFY_SOCKET")
        .env_remove("RUST_LOG")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(stderr).unwrap())
        .spawn()
        .expect("unshare runs (util-linux; a mount namespace needs root)");
    let mut got = Vec::new();
    let mut buf = vec![0u8; 1 << 16];
    let deadline = Instant::now() + Duration::from_secs(15);
    let seen = |got: &[String]| {
        got.iter().any(|d| d.contains("device link down"))
            || std::fs::read_to_string(stderr)
                .unwrap_or_default()
                .contains("device link down")
    };
    while Instant::now() < deadline && !seen(&got) {
        if let Some(st) = child.try_wait().unwrap() {
            panic!(
                "the gateway exited ({st}):\n{}",
                std::fs::read_to_string(stderr).unwrap_or_default()
            );
        }
        if let Ok(n) = socket.recv(&mut buf) {
            got.push(String::from_utf8_lossy(&buf[..n]).into_owned());
        }
    }
    let _ = child.kill();
    let _ = child.wait();
    got
}

// `JOURNAL_STREAM` is inherited by every process of a systemd (user) session, a
// terminal's too: only a stderr that is the very stream it names (device and inode)
// is the journal. Otherwise the log goes to stderr, where the person looks.
#[test]
fn the_log_goes_to_the_journal_only_when_stderr_is_the_journal_stream() {
    let dir = tempfile::tempdir().unwrap();
    let config = dead_plant_file(dir.path());
    let journal = dir.path().join("journal");
    std::fs::create_dir(&journal).unwrap();

    // stderr on a file, JOURNAL_STREAM naming another one (the config).
    let other = std::fs::metadata(&config).unwrap();
    let stderr = dir.path().join("stderr-1.txt");
    let got = run_with_journal(
        &journal,
        &config,
        &stderr,
        &format!("{}:{}", other.dev(), other.ino()),
    );
    let log = std::fs::read_to_string(&stderr).unwrap();
    assert!(log.contains("device link down"), "{log}\njournal: {got:?}");
    assert!(
        got.iter().all(|d| !d.contains("device link down")),
        "{got:?}"
    );

    // JOURNAL_STREAM naming stderr itself: the journal, with the event's fields.
    std::fs::remove_file(journal.join("socket")).unwrap();
    let stderr = dir.path().join("stderr-2.txt");
    std::fs::write(&stderr, "").unwrap();
    let me = std::fs::metadata(&stderr).unwrap();
    let got = run_with_journal(
        &journal,
        &config,
        &stderr,
        &format!("{}:{}", me.dev(), me.ino()),
    );
    assert!(
        got.iter()
            .any(|d| d.contains("device link down") && d.contains("F_DEVICE")),
        "{got:?}"
    );
    let log = std::fs::read_to_string(&stderr).unwrap();
    assert!(!log.contains("device link down"), "{log}");
}
