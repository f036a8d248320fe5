//! `compgate sim` on the shop-floor PC: it never takes a real adapter's serial link,
//! and a CAN interface that is not there gets a hint; `run` on a missing CAN interface
//! logs the SYNC producer's fault once, not at every retry.

mod common;

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use common::process::{signal, BIN};

/// An RTU line at `serial_path` with one channel, nothing else: what `sim` makes of it.
fn rtu_config(serial_path: &std::path::Path) -> String {
    format!(
        r#"
[devices.line]
transport = "rtu"
serial_path = "{}"
unit_id = 7

[channels.T_amb]
device = "line"
register = "input"
address = 0
data_type = "u16"
scaling = {}

[sim]
seed = 1
"#,
        serial_path.display(),
        common::SCALING
    )
}

/// A child with its stdout and stderr lines collected by threads.
struct Running {
    child: Child,
    lines: Arc<Mutex<Vec<String>>>,
}

impl Running {
    fn start(args: &[&str], config: &std::path::Path) -> Self {
        let mut child = Command::new(BIN)
            .args(args)
            .arg(config)
            .env_remove("JOURNAL_STREAM")
            .env_remove("RUST_LOG")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn compgate");
        let lines = Arc::new(Mutex::new(Vec::new()));
        let out = child.stdout.take().expect("stdout");
        let err = child.stderr.take().expect("stderr");
        for pipe in [
            Box::new(out) as Box<dyn std::io::Read + Send>,
            Box::new(err) as Box<dyn std::io::Read + Send>,
        ] {
            let sink = lines.clone();
            std::thread::spawn(move || {
                for l in BufReader::new(pipe).lines().map_while(Result::ok) {
                    sink.lock().expect("lines").push(l);
                }
            });
        }
        Running { child, lines }
    }

    /// Waits until `pred` holds for the lines so far; panics after `secs`.
    fn wait(&self, secs: u64, what: &str, pred: impl Fn(&[String]) -> bool) {
        let deadline = Instant::now() + Duration::from_secs(secs);
        while Instant::now() < deadline {
            if pred(&self.lines.lock().expect("lines")) {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        panic!("timed out waiting for {what}:\n{}", self.text());
    }

    fn text(&self) -> String {
        self.lines.lock().expect("lines").join("\n")
    }

    /// Waits for the exit, which is expected before the plant runs: its exit code
    /// and everything it said. Panics when the plant runs or after `secs`.
    fn exit(mut self, secs: u64) -> (Option<i32>, String) {
        let deadline = Instant::now() + Duration::from_secs(secs);
        while Instant::now() < deadline {
            if let Some(st) = self.child.try_wait().expect("try_wait") {
                // The reader threads end with the pipes: give them a moment.
                std::thread::sleep(Duration::from_millis(100));
                return (st.code(), self.text());
            }
            let text = self.text();
            assert!(
                !text.contains("simulated plant running"),
                "the plant runs:\n{text}"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        panic!("did not exit within {secs} s:\n{}", self.text());
    }

    /// SIGTERM, then waits for the exit.
    fn stop(mut self) {
        signal(self.child.id(), "TERM");
        let deadline = Instant::now() + Duration::from_secs(10);
        while Instant::now() < deadline {
            if self.child.try_wait().expect("try_wait").is_some() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        panic!("did not stop within 10 s after SIGTERM:\n{}", self.text());
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

// A udev-style link to something else (here a regular file standing in for the
// adapter) is refused with the key, the path and why, and is left as it was.
#[test]
fn sim_refuses_a_serial_link_it_did_not_make() {
    let dir = tempfile::tempdir().unwrap();
    let adapter = dir.path().join("ttyUSB-real");
    std::fs::write(&adapter, "").unwrap();
    let link = dir.path().join("usb-FTDI-by-id");
    std::os::unix::fs::symlink("ttyUSB-real", &link).unwrap();
    let cfg = dir.path().join("sim.toml");
    std::fs::write(&cfg, rtu_config(&link)).unwrap();

    let (code, err) = Running::start(&["sim", "--config"], &cfg).exit(20);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains(&format!(
            "devices.line.serial_path: {}: is a link to ttyUSB-real, not one `compgate sim` made",
            link.display()
        )),
        "{err}"
    );
    assert_eq!(
        std::fs::read_link(&link).unwrap(),
        std::path::Path::new("ttyUSB-real")
    );

    // A regular file at the path is no link of sim's either.
    let cfg_file = dir.path().join("sim-file.toml");
    std::fs::write(&cfg_file, rtu_config(&adapter)).unwrap();
    let (code, err) = Running::start(&["sim", "--config"], &cfg_file).exit(20);
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("exists and is not a link"), "{err}");
    assert!(std::fs::symlink_metadata(&adapter).unwrap().is_file());
}

// A link into /dev/pts left by an earlier sim (killed before it removed it) is
// replaced, and removed at exit.
#[test]
fn sim_replaces_its_own_stale_pty_link_and_removes_it_at_exit() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("line");
    std::os::unix::fs::symlink("/dev/pts/999999", &link).unwrap();
    let cfg = dir.path().join("sim.toml");
    std::fs::write(&cfg, rtu_config(&link)).unwrap();

    let sim = Running::start(&["sim", "--config"], &cfg);
    sim.wait(20, "the plant running", |l| {
        l.iter().any(|l| l.contains("simulated plant running"))
    });
    let target = std::fs::read_link(&link).unwrap();
    assert!(
        target.starts_with("/dev/pts/") && target != std::path::Path::new("/dev/pts/999999"),
        "{}",
        target.display()
    );
    sim.stop();
    assert!(
        std::fs::symlink_metadata(&link).is_err(),
        "the link is still there"
    );
}

/// A CAN interface name no machine has.
const NO_INTERFACE: &str = "vcannone0";

fn can_config_without_interface() -> String {
    std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/can-example.toml"
    ))
    .expect("can-example.toml")
    .replace(
        "interface = \"vcan0\"",
        &format!("interface = \"{NO_INTERFACE}\""),
    )
}

#[test]
fn sim_on_a_missing_can_interface_says_how_to_bring_it_up() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("can.toml");
    std::fs::write(&cfg, can_config_without_interface()).unwrap();
    let out = Command::new(BIN)
        .args(["sim", "--config"])
        .arg(&cfg)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains(&format!("devices.can_ain: CAN interface {NO_INTERFACE}: "))
            && err.contains(&format!(
                "bring it up first: sudo deploy/can/can-up.sh {NO_INTERFACE}"
            )),
        "{err}"
    );
}

// The SYNC producer retries a missing interface with its backoff for ever: one WARN
// line for the fault, the retries at DEBUG.
#[test]
fn a_missing_can_interface_is_logged_once_not_per_retry() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("can.toml");
    let text = can_config_without_interface().replace(
        "degrade_after_cycles = 3\n",
        "degrade_after_cycles = 3\nbackoff_initial_s = 0.02\nbackoff_max_s = 0.05\n",
    );
    std::fs::write(&cfg, text).unwrap();
    let gw = Running::start(&["--log", "debug", "run", "--config"], &cfg);
    let open_failed = |l: &String| l.contains("cannot open the interface");
    gw.wait(30, "five failed opens of the interface", |l| {
        l.iter().filter(|l| open_failed(l)).count() >= 5
    });
    let text = gw.text();
    let warned: Vec<&str> = text
        .lines()
        .filter(|l| l.contains("WARN") && l.contains("SYNC producer"))
        .collect();
    assert_eq!(warned.len(), 1, "{text}");
    assert!(warned[0].contains(NO_INTERFACE), "{text}");
    gw.stop();
}
