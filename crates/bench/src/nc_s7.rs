//! `compgate-bench nc-s7`: job latency of the S7 data-block target against its test
//! peer (`tests/peers/s7_plc.py`: python-snap7's server plus a scan loop playing the
//! PLC program), from REQ to the verified read-back.
//!
//! The peer scans every `--plc-cycle-ms` (default 1) and stays BUSY for one scan, as
//! FB3 takes a PLC cycle or more: a job spans about three scans plus the gateway's
//! five S7 requests. The figure is the gateway's side plus that, not a real PLC's FB3
//! time (several PLC cycles of a few ms each).

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use compgate_core::comp::CompParams;
use compgate_gateway::nc::s7::{S7TargetConfig, S7ValueType};
use compgate_gateway::nc::{Job, NcWriter};

/// Latencies of one run, sorted.
#[derive(Debug, Clone)]
pub struct Report {
    /// `real` or `lreal`.
    pub value_type: String,
    /// The peer's scan cycle, ms.
    pub plc_cycle_ms: f64,
    /// Every job's latency, ascending.
    pub latencies: Vec<Duration>,
}

impl Report {
    /// Latency percentile (0..=100).
    pub fn percentile(&self, p: f64) -> Duration {
        let l = &self.latencies;
        if l.is_empty() {
            return Duration::ZERO;
        }
        let i = ((p / 100.0) * (l.len() - 1) as f64).round() as usize;
        l[i.min(l.len() - 1)]
    }

    /// One table line: jobs, p50, p99, max in ms.
    pub fn line(&self) -> String {
        let ms = |d: Duration| d.as_secs_f64() * 1e3;
        format!(
            "s7 ({}, PLC cycle {} ms) jobs {}: p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms",
            self.value_type,
            self.plc_cycle_ms,
            self.latencies.len(),
            ms(self.percentile(50.0)),
            ms(self.percentile(99.0)),
            ms(self.latencies.last().copied().unwrap_or_default()),
        )
    }
}

/// The peer as a child process; killed on drop.
struct Peer(Child);

impl Drop for Peer {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn start_peer(value_type: &str, plc_cycle_ms: f64) -> Result<(Peer, u16), String> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let python = root.join("target/peers-venv/bin/python");
    let script = root.join("tests/peers/s7_plc.py");
    let mut child = Command::new(&python)
        .arg(&script)
        .args(["--port", "0", "--mode", "done", "--value-type", value_type])
        .args(["--cycle-ms", &plc_cycle_ms.to_string()])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .map_err(|e| {
            format!(
                "cannot start the S7 peer with {} ({e}); run tests/peers/install.sh",
                python.display()
            )
        })?;
    let out = child.stdout.take().ok_or("the S7 peer has no stdout")?;
    let peer = Peer(child);
    let mut line = String::new();
    BufReader::new(out)
        .read_line(&mut line)
        .map_err(|e| format!("reading the S7 peer's port: {e}"))?;
    let port = line
        .trim()
        .strip_prefix("PORT ")
        .and_then(|p| p.parse().ok())
        .ok_or_else(|| format!("the S7 peer printed {line:?}, expected \"PORT <n>\""))?;
    Ok((peer, port))
}

/// Runs `jobs` thermal jobs (after 10 unmeasured ones) with `value_type` values
/// against a peer scanning every `plc_cycle_ms`.
pub async fn run(jobs: u32, value_type: &str, plc_cycle_ms: f64) -> Result<Report, String> {
    let (_peer, port) = start_peer(value_type, plc_cycle_ms)?;
    let cfg = S7TargetConfig {
        address: format!("127.0.0.1:{port}"),
        rack: None,
        slot: None,
        remote_tsap: None,
        local_tsap: 0x0100,
        db_number: 100,
        start_byte: 0,
        block_stride_bytes: None,
        value_type: match value_type {
            "lreal" => S7ValueType::Lreal,
            _ => S7ValueType::Real,
        },
        timeout_s: 1.0,
        connect_timeout_s: 2.0,
        job_timeout_s: 2.0,
    };
    let mut w = cfg.build("X1", 1).map_err(|e| e.to_string())?;
    let mut latencies = Vec::with_capacity(jobs as usize);
    for i in 0..jobs + 10 {
        // A new value each time, as the gateway only writes changes.
        let p = CompParams {
            k0_mm: 0.001 * f64::from(i % 500),
            tan_beta: 1e-6 * f64::from(i % 100),
            p0_mm: 0.0,
        };
        let r = w
            .write_job(&Job::thermal(&p))
            .await
            .map_err(|e| format!("job {i}: {e}"))?;
        if i >= 10 {
            latencies.push(r.elapsed);
        }
    }
    latencies.sort();
    Ok(Report {
        value_type: value_type.into(),
        plc_cycle_ms,
        latencies,
    })
}
