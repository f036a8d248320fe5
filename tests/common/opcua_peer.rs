//! The SINUMERIK-like OPC UA peer (`tests/peers/opcua_server.py`, asyncua) as a child
//! process on 127.0.0.1. Include it with `#[path = "common/opcua_peer.rs"] mod opcua_peer;`.
#![allow(dead_code)]
// Test harness: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Write};
use std::path::PathBuf;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

/// The peers' interpreter (installed by `tests/peers/install.sh`), or `None` with the
/// reason printed; with `CI` set a missing peer fails the test instead.
pub fn python() -> Option<PathBuf> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let py = root.join("target/peers-venv/bin/python");
    let ok = py.is_file()
        && Command::new(&py)
            .args(["-c", "import asyncua"])
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
    if ok {
        return Some(py);
    }
    let why =
        "the OPC UA peer (asyncua in target/peers-venv) is missing; run tests/peers/install.sh";
    if std::env::var_os("CI").is_some() {
        panic!("{why}");
    }
    eprintln!("SKIP: {why}");
    None
}

/// Writes a client certificate and key for `urn:compgate` into `pki_dir` (`own/`,
/// `private/`), made by the peer's Python (a key made by a debug build would be slow).
pub fn make_client_cert(pki_dir: &std::path::Path) {
    let py = python().expect("checked by the caller");
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/peers/opcua_server.py");
    let status = Command::new(py)
        .arg(script)
        .arg("--make-client-cert")
        .arg(pki_dir)
        .stdout(Stdio::null())
        .status()
        .unwrap();
    assert!(status.success(), "making the client certificate failed");
}

/// A running peer; dropping it kills it.
pub struct OpcuaPeer {
    child: Child,
    stdin: ChildStdin,
    lines: mpsc::Receiver<String>,
    /// `opc.tcp://127.0.0.1:PORT/`.
    pub endpoint: String,
    /// The port it listens on.
    pub port: u16,
    /// Index of its SinumerikVarProvider namespace.
    pub ns: u16,
}

impl OpcuaPeer {
    /// Starts the peer on a free port with extra command-line `args`; `None` (after
    /// printing why) when the peer is not installed and `CI` is unset.
    pub fn start(args: &[&str]) -> Option<Self> {
        Self::start_on(0, args)
    }

    /// Starts the peer on `port` (0: any free one).
    pub fn start_on(port: u16, args: &[&str]) -> Option<Self> {
        let py = python()?;
        let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/peers/opcua_server.py");
        let mut child = Command::new(py)
            .arg(script)
            .args(["--port", &port.to_string()])
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("spawn the OPC UA peer");
        let stdin = child.stdin.take().unwrap();
        let stdout = child.stdout.take().unwrap();
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let mut peer = OpcuaPeer {
            child,
            stdin,
            lines,
            endpoint: String::new(),
            port: 0,
            ns: 0,
        };
        let endpoint = peer.expect_line("ENDPOINT ");
        let ns = peer.expect_line("NS ");
        peer.port = endpoint
            .trim_end_matches('/')
            .rsplit(':')
            .next()
            .and_then(|p| p.parse().ok())
            .unwrap_or_else(|| panic!("no port in {endpoint}"));
        peer.endpoint = endpoint;
        peer.ns = ns.parse().unwrap();
        Some(peer)
    }

    /// The next stdout line, which must start with `prefix`; returns the rest.
    fn expect_line(&mut self, prefix: &str) -> String {
        let line = self
            .lines
            .recv_timeout(Duration::from_secs(30))
            .unwrap_or_else(|e| panic!("OPC UA peer: no `{prefix}` line: {e}"));
        line.strip_prefix(prefix)
            .unwrap_or_else(|| panic!("OPC UA peer: expected `{prefix}...`, got `{line}`"))
            .to_string()
    }

    fn command(&mut self, cmd: &str, answer: &str) -> String {
        writeln!(self.stdin, "{cmd}").unwrap();
        self.stdin.flush().unwrap();
        self.expect_line(answer)
    }

    /// The bits of every setting datum the peer holds, by node id, read from its own
    /// address space (not through the client under test).
    pub fn dump(&mut self) -> BTreeMap<String, u64> {
        let json = self.command("dump", "VALUES ");
        let map: BTreeMap<String, String> = serde_json::from_str(&json).unwrap();
        map.into_iter()
            .map(|(k, v)| (k, u64::from_str_radix(&v, 16).unwrap()))
            .collect()
    }

    /// Delays every later Write answer by `s` seconds.
    pub fn set_write_delay(&mut self, s: f64) {
        self.command(&format!("delay {s}"), "OK");
    }

    /// Closes every client session on the server side, as its session timeout would;
    /// returns how many there were.
    pub fn expire_sessions(&mut self) -> usize {
        self.command("expire", "OK ").parse().unwrap()
    }

    /// The node id of setting datum `name` (e.g. `$SA_TEMP_COMP_SLOPE`) of `axis`.
    pub fn node(&self, name: &str, axis: u16) -> String {
        format!("ns={};s=/NC/_N_AX_SEA_ACX/{name}[u{axis}]", self.ns)
    }

    /// Kills the peer at once, as a crash or power loss would.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for OpcuaPeer {
    fn drop(&mut self) {
        self.kill();
    }
}
