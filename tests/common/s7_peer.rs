//! The S7 test peer (`tests/peers/s7_plc.py`: python-snap7's server plus a scan loop
//! playing the PLC program) as a child process on 127.0.0.1.
#![allow(dead_code)]
// Test harness: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};

/// The peers' interpreter, installed by `tests/peers/install.sh`.
pub fn python() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("target/peers-venv/bin/python")
}

/// Whether the peer can run; with `CI` set a missing peer fails the test, otherwise
/// the test skips with the reason printed.
pub fn available() -> bool {
    let ok = Command::new(python())
        .args(["-c", "import snap7.server"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !ok {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI is set and the S7 peer is missing: python-snap7 in target/peers-venv (run tests/peers/install.sh)"
        );
        println!(
            "SKIPPED: python-snap7 not installed in target/peers-venv (run tests/peers/install.sh)"
        );
    }
    ok
}

/// A running `s7_plc.py`; dropping it kills it.
pub struct S7Peer {
    child: Child,
    pub port: u16,
    args: Vec<String>,
}

impl S7Peer {
    /// Starts the peer on port 0 with `args` (e.g. `["--mode", "done"]`).
    pub fn start(args: &[&str]) -> Self {
        Self::start_on(0, args.iter().map(|s| s.to_string()).collect())
    }

    fn start_on(port: u16, args: Vec<String>) -> Self {
        let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/peers/s7_plc.py");
        let mut child = Command::new(python())
            .arg(script)
            .args(["--port", &port.to_string()])
            .args(&args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("start tests/peers/s7_plc.py");
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .expect("read the peer's PORT line");
        let port = line
            .trim()
            .strip_prefix("PORT ")
            .and_then(|p| p.parse().ok())
            .unwrap_or_else(|| panic!("s7_plc.py printed {line:?}, expected \"PORT <n>\""));
        Self { child, port, args }
    }

    /// `127.0.0.1:<port>`.
    pub fn address(&self) -> String {
        format!("127.0.0.1:{}", self.port)
    }

    /// Kills the peer (a PLC switched off: every connection drops).
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// Starts the peer again on the same port with the same arguments.
    pub fn restart(&mut self) {
        self.kill();
        *self = Self::start_on(self.port, self.args.clone());
    }
}

impl Drop for S7Peer {
    fn drop(&mut self) {
        self.kill();
    }
}
