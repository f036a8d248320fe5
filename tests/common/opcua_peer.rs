//! The SINUMERIK-like OPC UA peer (`tests/peers/opcua_server.py`, asyncua) on
//! 127.0.0.1, with the commands it takes on its standard input.
// Test harness: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Write};
use std::path::PathBuf;
use std::process::{ChildStdin, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use super::peer::{self, Peer};

const SCRIPT: &str = "opcua_server.py";

/// The peers' interpreter, or `None` with the reason printed; with `CI` set a missing
/// peer fails the test instead.
pub fn python() -> Option<PathBuf> {
    peer::python("asyncua")
}

/// Writes a client certificate and key for `urn:compgate` into `pki_dir` (`own/`,
/// `private/`), made by the peer's Python (a key made by a debug build would be slow).
pub fn make_client_cert(pki_dir: &std::path::Path) {
    let py = python().expect("checked by the caller");
    let status = Command::new(py)
        .arg(peer::script_path(SCRIPT))
        .arg("--make-client-cert")
        .arg(pki_dir)
        .stdout(Stdio::null())
        .status()
        .unwrap();
    assert!(status.success(), "making the client certificate failed");
}

/// A running peer; dropping it kills it.
pub struct OpcuaPeer {
    process: Peer,
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
        let mut all = vec!["--port".to_string(), port.to_string()];
        all.extend(args.iter().map(|s| s.to_string()));
        let mut process = Peer::spawn(&py, SCRIPT, &all);
        let (stdin, stdout) = process.take_stdio();
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let mut peer = OpcuaPeer {
            process,
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
        peer.process.port = peer.port;
        peer.endpoint = endpoint;
        peer.ns = ns.parse().unwrap();
        Some(peer)
    }

    /// The next stdout line, which must start with `prefix`; returns the rest.
    fn expect_line(&mut self, prefix: &str) -> String {
        let line = self
            .lines
            // Eleven Python servers starting two at a time beside the VM stages took
            // more than 30 s on CI; a peer that died closes the channel at once.
            .recv_timeout(Duration::from_secs(120))
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

    /// A `[targets.nc_x]` table for this peer without security, logging in as `user`
    /// (password `<user>-pw`, as the peer knows it) from a credentials file written
    /// into `dir`.
    pub fn target_table(&self, dir: &std::path::Path, user: &str) -> String {
        let cred = dir.join(format!("cred-{user}"));
        std::fs::write(&cred, format!("{user}\n{user}-pw\n")).unwrap();
        format!(
            "[targets.nc_x]\nkind = \"opcua\"\nendpoint_url = \"{}\"\nsecurity_policy = \"None\"\n\
             security_mode = \"None\"\npki_dir = \"{}\"\ncredentials_file = \"{}\"\n",
            self.endpoint,
            dir.join("pki").display(),
            cred.display()
        )
    }

    /// The node id of setting datum `name` (e.g. `$SA_TEMP_COMP_SLOPE`) of `axis`.
    pub fn node(&self, name: &str, axis: u16) -> String {
        format!("ns={};s=/NC/_N_AX_SEA_ACX/{name}[u{axis}]", self.ns)
    }

    /// Kills the peer at once, as a crash or power loss would.
    pub fn kill(&mut self) {
        self.process.kill();
    }
}
