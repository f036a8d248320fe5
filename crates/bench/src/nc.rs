//! `compgate-bench nc`: NC job latency per target kind against its peer on loopback, a
//! job being what the gateway counts as written: the write and the guard's read-back.
//!
//! Peers: the simulated NC axis module (`modbus`, in process), the SINUMERIK-like
//! asyncua server (`opcua`, `tests/peers/opcua_server.py`), python-snap7's server with
//! the PLC program's handshake (`s7`, `tests/peers/s7_plc.py`) and pyads' test server
//! (`ads`, `tests/peers/ads_server.py`), the Python ones run by the peers'
//! interpreter. A kind whose peer is missing is reported as skipped, with the reason.
//!
//! The S7 peer scans every `--plc-cycle-ms` (default 1) and stays BUSY for one scan, as
//! FB3 takes a PLC cycle or more: an S7 job spans about three scans plus the gateway's
//! S7 requests, not a real PLC's FB3 time (several PLC cycles of a few ms each).

use std::fmt::Write as _;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use compgate_core::comp::CompParams;
use compgate_gateway::config::TargetConfig;
use compgate_gateway::nc::guard::THERMAL_VARS;
use compgate_gateway::nc::{Guarded, Job, NcWriter};
use compgate_plc::nc::{NcAxis, NcAxisModule};
use tokio::time::Instant;

/// A target kind to measure.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Kind {
    /// The simulated NC axis module over Modbus/TCP.
    Modbus,
    /// The asyncua server.
    Opcua,
    /// python-snap7's server with the PLC program's handshake.
    S7,
    /// pyads' test server.
    Ads,
}

/// The float type of the S7 data block.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum S7Type {
    /// 32-bit REAL.
    Real,
    /// 64-bit LREAL.
    Lreal,
}

impl S7Type {
    /// The name in the target config and the peer's `--value-type`.
    fn name(self) -> &'static str {
        match self {
            Self::Real => "real",
            Self::Lreal => "lreal",
        }
    }
}

/// What one `nc` run measures.
#[derive(Debug, Clone)]
pub struct Options {
    /// Measured jobs per kind (and S7 value type).
    pub jobs: usize,
    /// Interpreter of the Python peers.
    pub python: PathBuf,
    /// The kinds, in this order.
    pub kinds: Vec<Kind>,
    /// The S7 block's value types, each measured on its own.
    pub s7_types: Vec<S7Type>,
    /// Scan cycle of the S7 peer's PLC program, ms.
    pub plc_cycle_ms: f64,
}

impl Options {
    /// Every kind, S7 with LREAL at a 1 ms scan; `python` by default the workspace's
    /// `target/peers-venv/bin/python`.
    pub fn new(jobs: usize, python: Option<PathBuf>) -> Self {
        Self {
            jobs,
            python: python.unwrap_or_else(|| root().join("target/peers-venv/bin/python")),
            kinds: vec![Kind::Modbus, Kind::Opcua, Kind::S7, Kind::Ads],
            s7_types: vec![S7Type::Lreal],
            plc_cycle_ms: 1.0,
        }
    }
}

/// Latency figures of one kind.
#[derive(Debug, Clone, PartialEq)]
pub struct KindLatency {
    /// `kind` value (for S7 with the value type).
    pub kind: String,
    /// Jobs measured.
    pub jobs: usize,
    /// Median, ms.
    pub p50_ms: f64,
    /// 99th percentile, ms.
    pub p99_ms: f64,
    /// Slowest, ms.
    pub max_ms: f64,
}

/// One kind's outcome.
#[derive(Debug)]
pub enum Outcome {
    /// Measured.
    Measured(KindLatency),
    /// Not measured (kind), and why.
    Skipped(String, String),
}

/// The value of percentile `p` (0..=1) of sorted `v`, nearest rank.
fn percentile(v: &[f64], p: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let rank = (p * v.len() as f64).ceil() as usize;
    v[rank.clamp(1, v.len()) - 1]
}

/// Runs `jobs` thermal jobs (after `warmup` unmeasured ones) through the guarded
/// writer of `target`, each value different from the last so none is skipped.
async fn measure(kind: &str, target: &TargetConfig, jobs: usize) -> Result<KindLatency, String> {
    let writer = target.build("X", 1).map_err(|e| format!("{kind}: {e}"))?;
    let mut w = Guarded::new(writer, THERMAL_VARS.to_vec(), target.job_timeout());
    let mut held = w
        .read_snapshot()
        .await
        .map_err(|e| format!("{kind}: first read: {e}"))?
        .thermal();
    let warmup = 20;
    let mut ms = Vec::with_capacity(jobs);
    for i in 0..warmup + jobs {
        let k0 = 0.001 * (i % 100) as f64;
        let next = CompParams {
            k0_mm: k0,
            tan_beta: k0 * 1e-3,
            p0_mm: 100.0,
        };
        let job = Job::thermal(&next);
        let t = Instant::now();
        // As the running gateway writes: checked first against what the NC holds.
        w.write_job_from(&job, Some(&held))
            .await
            .map_err(|e| format!("{kind}: job {i}: {e}"))?;
        held = next;
        if i >= warmup {
            ms.push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    ms.sort_by(f64::total_cmp);
    Ok(KindLatency {
        kind: kind.to_string(),
        jobs,
        p50_ms: percentile(&ms, 0.5),
        p99_ms: percentile(&ms, 0.99),
        max_ms: ms.last().copied().unwrap_or(f64::NAN),
    })
}

fn toml_target(text: &str) -> Result<TargetConfig, String> {
    toml::from_str(text).map_err(|e| format!("bench target config: {e}"))
}

/// A peer process, killed on drop.
struct PeerProcess(Child);

impl Drop for PeerProcess {
    fn drop(&mut self) {
        drop(self.0.stdin.take());
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts `script` under `python`; returns the process and its port (from its first
/// line, `PORT <n>`).
fn start_peer(python: &Path, script: &Path, args: &[&str]) -> Result<(PeerProcess, u16), String> {
    let (peer, lines) = start_peer_lines(python, script, args, 1)?;
    let line = &lines[0];
    let port = line
        .trim()
        .strip_prefix("PORT ")
        .and_then(|p| p.parse().ok())
        .ok_or_else(|| format!("{}: expected `PORT <n>`, got {line:?}", script.display()))?;
    Ok((peer, port))
}

/// Starts `script` under `python` and returns its first `n` lines.
fn start_peer_lines(
    python: &Path,
    script: &Path,
    args: &[&str],
    n: usize,
) -> Result<(PeerProcess, Vec<String>), String> {
    let mut child = Command::new(python)
        .arg(script)
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .map_err(|e| format!("{}: {e}", python.display()))?;
    let out = child.stdout.take().ok_or("peer stdout")?;
    let peer = PeerProcess(child);
    let mut reader = BufReader::new(out);
    let mut lines = Vec::with_capacity(n);
    for _ in 0..n {
        let mut line = String::new();
        reader
            .read_line(&mut line)
            .map_err(|e| format!("peer: {e}"))?;
        lines.push(line.trim().to_string());
    }
    Ok((peer, lines))
}

/// The workspace root (the peers' scripts and interpreter live under it).
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

async fn modbus(jobs: usize) -> Result<KindLatency, String> {
    let module = NcAxisModule::new(NcAxis {
        referenced: true,
        md32750: 3,
        ..NcAxis::default()
    });
    let (address, stop) = module
        .serve_loopback()
        .await
        .map_err(|e| format!("modbus: NC module: {e}"))?;
    let target = toml_target(&format!(
        "kind = \"modbus\"\naddress = \"{address}\"\nunit_id = 1\n"
    ))?;
    let r = measure("modbus", &target, jobs).await;
    stop.cancel();
    r
}

/// `Some(skipped)` when the peers' interpreter is missing.
fn no_python(kind: &str, python: &Path) -> Option<Outcome> {
    (!python.exists()).then(|| {
        Outcome::Skipped(
            kind.to_string(),
            format!(
                "no peer interpreter at {} (run tests/peers/install.sh)",
                python.display()
            ),
        )
    })
}

async fn opcua(jobs: usize, python: &Path) -> Result<Outcome, String> {
    if let Some(skip) = no_python("opcua", python) {
        return Ok(skip);
    }
    let script = root().join("tests/peers/opcua_server.py");
    // ENDPOINT, then NS once it serves.
    let (_peer, lines) = start_peer_lines(python, &script, &["--port", "0"], 2)?;
    let endpoint = lines[0]
        .strip_prefix("ENDPOINT ")
        .ok_or_else(|| format!("opcua peer: expected `ENDPOINT <url>`, got {:?}", lines[0]))?
        .to_string();
    let dir = tempfile::tempdir().map_err(|e| format!("opcua: temp dir: {e}"))?;
    let cred = dir.path().join("cred");
    std::fs::write(&cred, "writer\nwriter-pw\n").map_err(|e| format!("opcua: {e}"))?;
    let target = toml_target(&format!(
        "kind = \"opcua\"\nendpoint_url = \"{endpoint}\"\nsecurity_policy = \"None\"\n\
         security_mode = \"None\"\npki_dir = \"{}\"\ncredentials_file = \"{}\"\n",
        dir.path().join("pki").display(),
        cred.display()
    ))?;
    measure("opcua", &target, jobs).await.map(Outcome::Measured)
}

async fn s7(
    jobs: usize,
    python: &Path,
    value_type: S7Type,
    cycle_ms: f64,
) -> Result<Outcome, String> {
    let kind = format!("s7 {}", value_type.name());
    if let Some(skip) = no_python(&kind, python) {
        return Ok(skip);
    }
    let script = root().join("tests/peers/s7_plc.py");
    let cycle_ms = cycle_ms.to_string();
    let (_peer, port) = start_peer(
        python,
        &script,
        &[
            "--port",
            "0",
            "--mode",
            "done",
            "--value-type",
            value_type.name(),
            "--cycle-ms",
            &cycle_ms,
        ],
    )?;
    let target = toml_target(&format!(
        "kind = \"s7\"\naddress = \"127.0.0.1:{port}\"\ndb_number = 100\nvalue_type = \"{}\"\n",
        value_type.name()
    ))?;
    measure(&kind, &target, jobs).await.map(Outcome::Measured)
}

async fn ads(jobs: usize, python: &Path) -> Result<Outcome, String> {
    if let Some(skip) = no_python("ads", python) {
        return Ok(skip);
    }
    let script = root().join("tests/peers/ads_server.py");
    let (_peer, port) = start_peer(
        python,
        &script,
        &[
            "--lreal",
            "0x5001:0=0",
            "--lreal",
            "0x5001:8=0",
            "--lreal",
            "0x5001:16=0",
        ],
    )?;
    let at = |o: u32| format!("{{ index_group = 0x5000, index_offset = {o}, group_per_axis = 1 }}");
    let target = toml_target(&format!(
        "kind = \"ads\"\naddress = \"127.0.0.1:{port}\"\nams_net_id = \"127.0.0.1.1.1\"\n\
         sd43900 = {}\nsd43910 = {}\nsd43920 = {}\n",
        at(0),
        at(8),
        at(16)
    ))?;
    // The peer answers from Python threads: give it a moment on a loaded machine.
    tokio::time::sleep(Duration::from_millis(50)).await;
    measure("ads", &target, jobs).await.map(Outcome::Measured)
}

/// Measures the kinds of `opts`, one after the other.
pub async fn run(opts: &Options) -> Result<Vec<Outcome>, String> {
    if !(opts.plc_cycle_ms > 0.0 && opts.plc_cycle_ms <= 1000.0) {
        return Err(format!(
            "--plc-cycle-ms {}: not in 0 (exclusive) ..= 1000",
            opts.plc_cycle_ms
        ));
    }
    let (jobs, python) = (opts.jobs, opts.python.as_path());
    let mut outcomes = Vec::new();
    for kind in &opts.kinds {
        match kind {
            Kind::Modbus => outcomes.push(Outcome::Measured(modbus(jobs).await?)),
            Kind::Opcua => outcomes.push(opcua(jobs, python).await?),
            Kind::S7 => {
                for &t in &opts.s7_types {
                    outcomes.push(s7(jobs, python, t, opts.plc_cycle_ms).await?);
                }
            }
            Kind::Ads => outcomes.push(ads(jobs, python).await?),
        }
    }
    Ok(outcomes)
}

/// The report table; `plc_cycle_ms` is the S7 peer's scan cycle.
pub fn table(outcomes: &[Outcome], plc_cycle_ms: f64) -> String {
    let mut s = String::from(
        "NC job latency per target kind, loopback (a job = the check of what the NC holds, the write and its verified read-back)\n\
         kind      jobs    p50 ms   p99 ms   max ms\n",
    );
    for o in outcomes {
        let _ = match o {
            Outcome::Measured(k) => writeln!(
                s,
                "{:<8} {:>5} {:>9.3} {:>8.3} {:>8.3}",
                k.kind, k.jobs, k.p50_ms, k.p99_ms, k.max_ms
            ),
            Outcome::Skipped(kind, why) => writeln!(s, "{kind:<8} skipped: {why}"),
        };
    }
    if outcomes.iter().any(|o| match o {
        Outcome::Measured(k) => k.kind.starts_with("s7"),
        Outcome::Skipped(..) => false,
    }) {
        let _ = writeln!(
            s,
            "s7: the peer's PLC program scans every {plc_cycle_ms} ms"
        );
    }
    s.push_str(
        "anchors (vendor figures): Neuron 3.2.1 API write 523 ms average, NG Gateway 75.6 ms average\n",
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_by_nearest_rank() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&v, 0.5), 50.0);
        assert_eq!(percentile(&v, 0.99), 99.0);
        assert_eq!(percentile(&[3.0], 0.99), 3.0);
        assert!(percentile(&[], 0.5).is_nan());
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn modbus_jobs_are_measured() {
        let k = modbus(30).await.expect("modbus bench");
        assert_eq!(k.jobs, 30);
        assert!(
            k.p50_ms > 0.0 && k.p50_ms <= k.p99_ms && k.p99_ms <= k.max_ms,
            "{k:?}"
        );
    }
}
