//! Python protocol peers (tests/peers/*.py) from `target/peers-venv`, installed by
//! `tests/peers/install.sh`. Each prints `PORT <n>` once listening on 127.0.0.1 and
//! serves until its standard input closes; dropping a [`Peer`] closes it and kills
//! the process.
#![allow(dead_code)]
#![allow(clippy::unwrap_used)]

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};

/// A running peer.
pub struct Peer {
    child: Child,
    /// The port it listens on (127.0.0.1).
    pub port: u16,
}

impl Peer {
    /// `127.0.0.1:port`.
    pub fn address(&self) -> String {
        format!("127.0.0.1:{}", self.port)
    }
}

impl Drop for Peer {
    fn drop(&mut self) {
        drop(self.child.stdin.take());
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The peers' interpreter, or `None` (after saying why) when it is not installed; with
/// `CI` set a missing peer fails the test.
pub fn python() -> Option<PathBuf> {
    let py = root().join("target/peers-venv/bin/python");
    if py.exists() {
        return Some(py);
    }
    let why = "the Python test peers are not installed: run tests/peers/install.sh";
    assert!(std::env::var_os("CI").is_none(), "{why} (CI is set)");
    eprintln!("skipped: {why}");
    None
}

/// Starts `tests/peers/<script>` with `args`; `None` when the peers are not installed.
pub fn start(script: &str, args: &[String]) -> Option<Peer> {
    let py = python()?;
    let mut child = Command::new(py)
        .arg(root().join("tests/peers").join(script))
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("peer starts");
    let out = child.stdout.take().expect("stdout");
    let mut line = String::new();
    BufReader::new(out)
        .read_line(&mut line)
        .expect("peer prints its port");
    let port = line
        .trim()
        .strip_prefix("PORT ")
        .and_then(|p| p.parse().ok())
        .unwrap_or_else(|| panic!("{script}: expected `PORT <n>`, got {line:?}"));
    Some(Peer { child, port })
}
