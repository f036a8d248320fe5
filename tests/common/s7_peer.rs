//! The S7 test peer (`tests/peers/s7_plc.py`: python-snap7's server plus a scan loop
//! playing the PLC program) on 127.0.0.1, with a restart on the same port.

use super::peer::{self, Peer};

const SCRIPT: &str = "s7_plc.py";
const MODULE: &str = "snap7.server";

/// Whether the peer can run; with `CI` set a missing peer fails the test, otherwise
/// the test skips with the reason printed.
pub fn available() -> bool {
    peer::python(MODULE).is_some()
}

/// A running `s7_plc.py`; dropping it kills it.
pub struct S7Peer {
    peer: Peer,
    args: Vec<String>,
}

impl S7Peer {
    /// Starts the peer on port 0 with `args` (e.g. `["--mode", "done"]`), after
    /// [`available`] said it can.
    pub fn start(args: &[&str]) -> Self {
        Self::start_on(0, args.iter().map(|s| s.to_string()).collect())
    }

    fn start_on(port: u16, args: Vec<String>) -> Self {
        let mut all = vec!["--port".to_string(), port.to_string()];
        all.extend(args.iter().cloned());
        Self {
            peer: Peer::start_with(&peer::interpreter(), SCRIPT, &all),
            args,
        }
    }

    /// `127.0.0.1:<port>`.
    pub fn address(&self) -> String {
        self.peer.address()
    }

    /// Kills the peer (a PLC switched off: every connection drops).
    pub fn kill(&mut self) {
        self.peer.kill();
    }

    /// Starts the peer again on the same port with the same arguments.
    pub fn restart(&mut self) {
        self.kill();
        *self = Self::start_on(self.peer.port, self.args.clone());
    }
}
