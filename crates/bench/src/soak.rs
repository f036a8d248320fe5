//! `compgate-bench soak --seconds SECONDS`: the gateway as a real process against 8 simulated
//! field modules x 64 channels at 10 Hz, with recording, MQTT (when a `mosquitto`
//! binary is installed) and metrics on. Samples the gateway process' CPU time and RSS
//! from `/proc` once a second after a warm-up and reports CPU % of one core (in total
//! and by thread), RSS at the end of the warm-up and at the end, and the trend of RSS
//! as the least-squares slope over the samples after the warm-up. Once a minute it
//! also reads the gateway's live heap (`compgate_process_heap_bytes`, glibc's
//! figure) from the metrics endpoint, so that a rising RSS can be told apart: a
//! growing heap is a leak, a flat heap under a rising RSS is the allocator. The
//! simulator and the broker run as processes of their own and are not counted.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Field modules.
pub const DEVICES: usize = 8;
/// Channels per field module.
pub const CHANNELS: usize = 64;

/// One `/proc` sample of the gateway.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Sample {
    pub(crate) at: Instant,
    pub(crate) cpu_ticks: u64,
    pub(crate) rss_kb: u64,
}

pub(crate) fn free_port() -> Result<u16, String> {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .map_err(|e| format!("no free port: {e}"))
}

fn clock_ticks_per_s() -> u64 {
    Command::new("getconf")
        .arg("CLK_TCK")
        .output()
        .ok()
        .and_then(|o| String::from_utf8_lossy(&o.stdout).trim().parse().ok())
        .unwrap_or(100)
}

/// The command name and the CPU ticks (user + system) of a `/proc/.../stat` line.
fn stat_name_ticks(stat: &str) -> Option<(&str, u64)> {
    // The name sits in parentheses and may hold spaces; fields resume after the last
    // `)`, at field 3.
    let (head, rest) = stat.rsplit_once(')')?;
    let name = head.get(head.find('(')? + 1..)?;
    let f: Vec<&str> = rest.split_whitespace().collect();
    let utime: u64 = f.get(11)?.parse().ok()?;
    let stime: u64 = f.get(12)?.parse().ok()?;
    Some((name, utime + stime))
}

pub(crate) fn sample(pid: u32) -> Option<Sample> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let (_, cpu_ticks) = stat_name_ticks(&stat)?;
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let rss_kb = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())?;
    Some(Sample {
        at: Instant::now(),
        cpu_ticks,
        rss_kb,
    })
}

/// CPU ticks of every live thread of `pid`: thread id -> (name, ticks).
fn thread_ticks(pid: u32) -> BTreeMap<u32, (String, u64)> {
    let mut out = BTreeMap::new();
    let Ok(dir) = std::fs::read_dir(format!("/proc/{pid}/task")) else {
        return out;
    };
    for entry in dir.flatten() {
        let Some(tid) = entry.file_name().to_str().and_then(|t| t.parse().ok()) else {
            continue;
        };
        let Ok(stat) = std::fs::read_to_string(entry.path().join("stat")) else {
            continue;
        };
        if let Some((name, ticks)) = stat_name_ticks(&stat) {
            out.insert(tid, (name.to_string(), ticks));
        }
    }
    out
}

/// CPU ticks spent between `before` and `after` by thread name; a thread that
/// started in between counts from zero, one that ended is missing (its time is in
/// the process total only).
fn ticks_by_name(
    before: &BTreeMap<u32, (String, u64)>,
    after: &BTreeMap<u32, (String, u64)>,
) -> BTreeMap<String, u64> {
    let mut by_name: BTreeMap<String, u64> = BTreeMap::new();
    for (tid, (name, ticks)) in after {
        let start = before.get(tid).map_or(0, |b| b.1);
        *by_name.entry(name.clone()).or_default() += ticks.saturating_sub(start);
    }
    by_name
}

/// Least-squares slope of RSS over time, kB per hour.
fn rss_slope_kb_per_h(samples: &[Sample]) -> Option<f64> {
    let points: Vec<(Instant, u64)> = samples.iter().map(|s| (s.at, s.rss_kb)).collect();
    slope_kb_per_h(&points)
}

/// Least-squares slope of `(time, kB)` points, kB per hour; `None` under 3 points.
fn slope_kb_per_h(points: &[(Instant, u64)]) -> Option<f64> {
    let t0 = points.first()?.0;
    let n = points.len() as f64;
    if points.len() < 3 {
        return None;
    }
    let xs: Vec<f64> = points
        .iter()
        .map(|p| p.0.duration_since(t0).as_secs_f64())
        .collect();
    let mx = xs.iter().sum::<f64>() / n;
    let my = points.iter().map(|p| p.1 as f64).sum::<f64>() / n;
    let (mut sxy, mut sxx) = (0.0, 0.0);
    for (x, p) in xs.iter().zip(points) {
        sxy += (x - mx) * (p.1 as f64 - my);
        sxx += (x - mx) * (x - mx);
    }
    (sxx > 0.0).then(|| sxy / sxx * 3600.0)
}

/// How often the soak reads the gateway's heap figure: a scrape renders every
/// metric, so not every second.
const HEAP_EVERY: Duration = Duration::from_secs(60);

/// The gateway's live heap in kB, from `compgate_process_heap_bytes{state="in_use"}`
/// on its metrics endpoint; `None` when it cannot be read (or off glibc).
fn heap_in_use_kb(metrics_port: u16) -> Option<u64> {
    metric_sum(
        &scrape(metrics_port)?,
        "compgate_process_heap_bytes{state=\"in_use\"} ",
    )
    .map(|b| (b / 1024.0) as u64)
}

/// The text of the metrics endpoint; `None` when it cannot be read.
pub fn scrape(metrics_port: u16) -> Option<String> {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(("127.0.0.1", metrics_port)).ok()?;
    s.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    s.write_all(b"GET /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        .ok()?;
    let mut body = String::new();
    s.read_to_string(&mut body).ok()?;
    Some(body)
}

/// A number of a scrape: the sum over the lines starting with `prefix`; `None` when no
/// line has a value.
pub fn metric_sum(scrape: &str, prefix: &str) -> Option<f64> {
    scrape
        .lines()
        .filter(|l| l.starts_with(prefix))
        .filter_map(|l| l.rsplit_once(' ')?.1.trim().parse::<f64>().ok())
        .reduce(|a, b| a + b)
}

fn mosquitto() -> Option<PathBuf> {
    ["/usr/sbin/mosquitto", "/usr/bin/mosquitto"]
        .iter()
        .map(PathBuf::from)
        .find(|p| p.exists())
}

/// The soak configuration: devices `ain1..ain8` with channels `T_<d>_<c>`.
fn config_text(
    dir: &Path,
    ports: &[u16],
    nc_port: u16,
    broker: Option<u16>,
    metrics_port: u16,
) -> String {
    let mut t = String::from("[gateway]\nstatus_interval_s = 1.0\n\n");
    let scaling = r#"{ kind = "transmitter", adc_full_scale_counts = 4095, adc_full_scale_ma = 24.0, current_range = "4-20", range_min_degc = -50.0, range_max_degc = 150.0 }"#;
    let filter = r#"{ median_samples = 3, lowpass_tau_s = 5.0, max_rate_degc_per_s = 2.0, max_rejected_samples = 5, stale_after_s = 0.0, valid_min_degc = -20.0, valid_max_degc = 100.0 }"#;
    for (d, port) in ports.iter().enumerate() {
        let _ = write!(
            t,
            "[devices.ain{}]\ntransport = \"tcp\"\naddress = \"127.0.0.1:{port}\"\nunit_id = 1\ntimeout_s = 0.5\nretries = 0\npoll_interval_s = 0.1\n\n",
            d + 1
        );
        for c in 0..CHANNELS {
            let _ = write!(
                t,
                "[channels.T_{}_{c}]\ndevice = \"ain{}\"\nregister = \"input\"\naddress = {c}\ndata_type = \"u16\"\nscaling = {scaling}\nfilter = {filter}\n\n",
                d + 1,
                d + 1
            );
        }
    }
    let _ = write!(
        t,
        "[nc_modules.nc_x]\naddress = \"127.0.0.1:{nc_port}\"\nunit_id = 1\n\n[axes.X]\nnc_module = \"nc_x\"\nmd32750 = 3\np0_mm = 100.0\nupdate_interval_s = 1.0\nk0 = {{ offset_mm = 0.0, terms = [{{ channel = \"T_1_0\", ref_degc = 20.0, coeff_mm_per_degc = 0.004 }}] }}\ntan_beta = {{ offset = 0.0, terms = [{{ channel = \"T_1_1\", ref_degc = 20.0, coeff_per_degc = 0.0000115 }}] }}\n\n"
    );
    let _ = write!(
        t,
        "[recorder]\npath = {:?}\n\n[metrics]\nbind = \"127.0.0.1:{metrics_port}\"\n\n",
        dir.join("soak.db").display().to_string()
    );
    if let Some(p) = broker {
        let _ = write!(
            t,
            "[mqtt]\nbroker = \"127.0.0.1:{p}\"\nmachine = \"soak\"\npublish_interval_s = 1.0\n\n"
        );
    }
    t.push_str("[sim]\nseed = 1\n\n");
    for d in 1..=DEVICES {
        for c in 0..CHANNELS {
            let _ = write!(
                t,
                "[sim.channels.T_{d}_{c}]\nprofile = \"sine\"\nmean_degc = {}\namplitude_degc = 2.0\nperiod_s = 600.0\nnoise_degc = 0.02\n\n",
                20 + (c % 10)
            );
        }
    }
    t.push_str("[sim.nc_modules.nc_x]\nreferenced = true\nmd32750 = 3\nmotion_min_mm = 0.0\nmotion_max_mm = 1000.0\nmotion_speed_mm_per_s = 50.0\n");
    t
}

struct Kill(Child);

impl Drop for Kill {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn wait_port(port: u16, what: &str) -> Result<(), String> {
    for _ in 0..250 {
        if std::net::TcpStream::connect(("127.0.0.1", port)).is_ok() {
            return Ok(());
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Err(format!("{what} did not listen on port {port}"))
}

/// Runs the soak for `seconds` and returns the report.
pub fn run(seconds: f64, exe: &Path) -> Result<String, String> {
    if !(seconds.is_finite() && seconds >= 10.0) {
        return Err(format!("--seconds {seconds}: at least 10 seconds"));
    }
    let dir = tempfile::tempdir().map_err(|e| format!("temporary directory: {e}"))?;
    let ports = (0..DEVICES)
        .map(|_| free_port())
        .collect::<Result<Vec<_>, _>>()?;
    let nc_port = free_port()?;
    let metrics_port = free_port()?;

    let broker = match mosquitto() {
        Some(bin) => {
            let port = free_port()?;
            let conf = dir.path().join("mosquitto.conf");
            std::fs::write(
                &conf,
                format!("listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n"),
            )
            .map_err(|e| e.to_string())?;
            let child = Command::new(bin)
                .arg("-c")
                .arg(&conf)
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .map_err(|e| format!("mosquitto: {e}"))?;
            let k = Kill(child);
            wait_port(port, "mosquitto")?;
            Some((port, k))
        }
        None => None,
    };
    let cfg_path = dir.path().join("soak.toml");
    std::fs::write(
        &cfg_path,
        config_text(
            dir.path(),
            &ports,
            nc_port,
            broker.as_ref().map(|b| b.0),
            metrics_port,
        ),
    )
    .map_err(|e| e.to_string())?;

    let sim = Kill(
        Command::new(exe)
            .args(["--log", "warn", "sim", "--config"])
            .arg(&cfg_path)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| format!("compgate sim: {e}"))?,
    );
    for p in ports.iter().chain([&nc_port]) {
        wait_port(*p, "compgate sim")?;
    }
    let gw = Kill(
        Command::new(exe)
            .args(["--log", "warn", "run", "--config"])
            .arg(&cfg_path)
            .env_remove("NOTIFY_SOCKET")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| format!("compgate run: {e}"))?,
    );
    let pid = gw.0.id();
    // Caches (SQLite's page cache, the MQTT outbox, allocator arenas) fill during the
    // warm-up; what RSS does after it is the trend.
    let warmup = Duration::from_secs_f64((seconds * 0.2).min(60.0));
    let end = Instant::now() + Duration::from_secs_f64(seconds);
    std::thread::sleep(warmup);
    let threads_before = thread_ticks(pid);
    let mut samples = Vec::new();
    let mut heap: Vec<(Instant, u64)> = Vec::new();
    let mut next_heap = Instant::now();
    while Instant::now() < end {
        samples.push(sample(pid).ok_or("the gateway process ended during the soak")?);
        if Instant::now() >= next_heap || Instant::now() + Duration::from_secs(1) >= end {
            if let Some(kb) = heap_in_use_kb(metrics_port) {
                heap.push((Instant::now(), kb));
            }
            next_heap += HEAP_EVERY;
        }
        std::thread::sleep(Duration::from_secs(1));
    }
    let threads_after = thread_ticks(pid);
    let rows = rusqlite::Connection::open(dir.path().join("soak.db"))
        .and_then(|c| c.query_row("SELECT count(*) FROM readings", [], |r| r.get::<_, i64>(0)))
        .unwrap_or(-1);
    drop(gw);
    drop(sim);
    let mqtt_on = broker.is_some();
    drop(broker);

    let (first, last) = match (samples.first(), samples.last()) {
        (Some(f), Some(l)) if samples.len() >= 3 => (*f, *l),
        _ => return Err("too few samples".into()),
    };
    let hz = clock_ticks_per_s() as f64;
    let span_s = last.at.duration_since(first.at).as_secs_f64();
    let pct = |ticks: u64| ticks as f64 / hz / span_s * 100.0;
    let cpu_pct = pct(last.cpu_ticks - first.cpu_ticks);
    let max_rss = samples.iter().map(|s| s.rss_kb).max().unwrap_or(0);
    let slope_all = rss_slope_kb_per_h(&samples);
    let slope_half = rss_slope_kb_per_h(&samples[samples.len() / 2..]);
    let mut out = String::new();
    let _ = writeln!(
        out,
        "soak: {DEVICES} devices x {CHANNELS} channels at 10 Hz, recording on, metrics on, MQTT {}",
        if mqtt_on {
            "on (local mosquitto)"
        } else {
            "OFF (no mosquitto binary)"
        }
    );
    let _ = writeln!(
        out,
        "measured {span_s:.0} s after {:.0} s warm-up; {rows} readings recorded",
        warmup.as_secs_f64()
    );
    let _ = writeln!(out, "CPU      {cpu_pct:.2} % of one core (target < 2 %)");
    let by_name = ticks_by_name(&threads_before, &threads_after);
    let mut threads: Vec<(&String, &u64)> = by_name.iter().collect();
    threads.sort_by(|a, b| b.1.cmp(a.1));
    let _ = writeln!(
        out,
        "  by thread: {}",
        threads
            .iter()
            .map(|(n, t)| format!("{n} {:.2} %", pct(**t)))
            .collect::<Vec<_>>()
            .join(", ")
    );
    let _ = writeln!(
        out,
        "RSS      {:.1} MB after warm-up, {:.1} MB at the end, {:.1} MB max (target < 30 MB)",
        first.rss_kb as f64 / 1024.0,
        last.rss_kb as f64 / 1024.0,
        max_rss as f64 / 1024.0
    );
    let slope = |s: Option<f64>| s.map_or("n/a".to_string(), |v| format!("{v:+.0} kB/h"));
    let _ = writeln!(
        out,
        "trend    {} (least squares over {} samples after warm-up), {} over the second half; end - start {:+.2} MB",
        slope(slope_all),
        samples.len(),
        slope(slope_half),
        (last.rss_kb as f64 - first.rss_kb as f64) / 1024.0
    );
    match (heap.first(), heap.last()) {
        (Some(f), Some(l)) => {
            let _ = writeln!(
                out,
                "heap     {:.1} MB in use after warm-up, {:.1} MB at the end; trend {} ({} readings, one a minute), {} over the second half",
                f.1 as f64 / 1024.0,
                l.1 as f64 / 1024.0,
                slope(slope_kb_per_h(&heap)),
                heap.len(),
                slope(slope_kb_per_h(&heap[heap.len() / 2..])),
            );
        }
        _ => {
            let _ = writeln!(
                out,
                "heap     n/a (no glibc heap figure on the metrics endpoint)"
            );
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(t0: Instant, s: f64, rss_kb: u64) -> Sample {
        Sample {
            at: t0 + Duration::from_secs_f64(s),
            cpu_ticks: 0,
            rss_kb,
        }
    }

    #[test]
    fn rss_slope_is_the_least_squares_line_in_kb_per_hour() {
        let t0 = Instant::now();
        // 1 kB every 10 s is 360 kB/h, whatever the noise around the line.
        let rising: Vec<Sample> = (0..100u32)
            .map(|i| {
                at(
                    t0,
                    f64::from(i),
                    20_000 + u64::from(i) / 10 + u64::from(i % 2),
                )
            })
            .collect();
        let slope = rss_slope_kb_per_h(&rising).expect("slope");
        assert!((slope - 360.0).abs() < 10.0, "{slope}");
        let flat: Vec<Sample> = (0..100u32).map(|i| at(t0, f64::from(i), 20_000)).collect();
        assert_eq!(rss_slope_kb_per_h(&flat), Some(0.0));
        assert_eq!(rss_slope_kb_per_h(&flat[..2]), None);
    }

    #[test]
    fn stat_line_gives_name_with_spaces_and_user_plus_system_ticks() {
        let stat = "4242 (tokio rt) worker) S 1 2 3 4 5 6 7 8 9 10 120 30 0 0 20 0 4";
        assert_eq!(stat_name_ticks(stat), Some(("tokio rt) worker", 150)));
        assert_eq!(stat_name_ticks("4242 no parentheses"), None);
    }

    #[test]
    fn thread_time_is_summed_by_name_and_new_threads_count_from_zero() {
        let before = BTreeMap::from([(1, ("recorder".to_string(), 10)), (2, ("w".to_string(), 5))]);
        let after = BTreeMap::from([
            (1, ("recorder".to_string(), 15)),
            (2, ("w".to_string(), 9)),
            (3, ("w".to_string(), 2)),
        ]);
        let by = ticks_by_name(&before, &after);
        assert_eq!(by["recorder"], 5);
        assert_eq!(by["w"], 6);
    }
}
