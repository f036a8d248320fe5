//! Python protocol peers (tests/peers/*.py) from `target/peers-venv`, installed by
//! `tests/peers/install.sh`: the one way the tests find the interpreter, start a peer
//! on 127.0.0.1 and stop it. A peer serves until its standard input closes; dropping a
//! [`Peer`] closes it and kills the process.
#![allow(dead_code)]
#![allow(clippy::unwrap_used)]

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};

/// A running peer.
pub struct Peer {
    child: Child,
    /// The port it listens on (127.0.0.1); 0 until known.
    pub port: u16,
}

impl Peer {
    /// Starts `tests/peers/<script>` under `python` with `args`, its standard input and
    /// output piped; `port` stays 0 (see [`start`] for peers that print `PORT <n>`).
    pub fn spawn(python: &Path, script: &str, args: &[String]) -> Self {
        let child = Command::new(python)
            .arg(script_path(script))
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap_or_else(|e| panic!("starting tests/peers/{script}: {e}"));
        Self { child, port: 0 }
    }

    /// Starts `script` as [`Peer::spawn`] does and reads the `PORT <n>` line it prints
    /// once it listens.
    pub fn start_with(python: &Path, script: &str, args: &[String]) -> Self {
        let (mut peer, port) = Self::start_reading(python, script, args, "PORT");
        peer.port = port
            .parse()
            .unwrap_or_else(|_| panic!("{script}: expected `PORT <n>`, got {port:?}"));
        peer
    }

    /// Starts `script` as [`Peer::spawn`] does and reads the `<key> <value>` line it
    /// prints once it serves (e.g. `PATH /dev/pts/3`); returns the value.
    pub fn start_reading(
        python: &Path,
        script: &str,
        args: &[String],
        key: &str,
    ) -> (Self, String) {
        let mut peer = Self::spawn(python, script, args);
        let mut line = String::new();
        BufReader::new(peer.child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap_or_else(|e| panic!("{script}: reading its {key} line: {e}"));
        let value = line
            .trim()
            .strip_prefix(key)
            .and_then(|v| v.strip_prefix(' '))
            .unwrap_or_else(|| panic!("{script}: expected `{key} <value>`, got {line:?}"))
            .to_string();
        (peer, value)
    }

    /// Its standard input and output, for peers that take commands.
    pub fn take_stdio(&mut self) -> (ChildStdin, ChildStdout) {
        (
            self.child.stdin.take().unwrap(),
            self.child.stdout.take().unwrap(),
        )
    }

    /// `127.0.0.1:port`.
    pub fn address(&self) -> String {
        format!("127.0.0.1:{}", self.port)
    }

    /// Kills the peer at once, as a crash or power loss would.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Peer {
    fn drop(&mut self) {
        drop(self.child.stdin.take());
        self.kill();
    }
}

/// `tests/peers/<script>`.
pub fn script_path(script: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/peers")
        .join(script)
}

/// Where `tests/peers/install.sh` puts the peers' interpreter.
pub fn interpreter() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("target/peers-venv/bin/python")
}

/// The peers' interpreter if it can import `module`, or `None` after printing why;
/// with `CI` set a missing peer fails the test instead.
pub fn python(module: &str) -> Option<PathBuf> {
    let py = interpreter();
    let ok = py.is_file()
        && Command::new(&py)
            .args(["-c", &format!("import {module}")])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
    if ok {
        return Some(py);
    }
    let why = format!(
        "the Python test peer ({module} in target/peers-venv) is missing: run tests/peers/install.sh"
    );
    assert!(std::env::var_os("CI").is_none(), "{why} (CI is set)");
    eprintln!("skipped: {why}");
    None
}

/// Starts `tests/peers/<script>`, which needs `module`, with `args` and reads its
/// port; `None` when the peer is not installed.
pub fn start(script: &str, module: &str, args: &[String]) -> Option<Peer> {
    Some(Peer::start_with(&python(module)?, script, args))
}
