//! `compgate bench --soak SECONDS`: the gateway as a real process against 8 simulated
//! field modules x 64 channels at 10 Hz, with recording, MQTT (when a `mosquitto`
//! binary is installed) and metrics on. Samples the gateway process' CPU time and RSS
//! from `/proc` once a second and reports CPU % of one core, RSS and its growth. The
//! simulator and the broker run as processes of their own and are not counted.

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
struct Sample {
    at: Instant,
    cpu_ticks: u64,
    rss_kb: u64,
}

fn free_port() -> Result<u16, String> {
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

fn sample(pid: u32) -> Option<Sample> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the command name (which may hold spaces) start at field 3.
    let rest = stat.rsplit_once(')')?.1;
    let f: Vec<&str> = rest.split_whitespace().collect();
    let utime: u64 = f.get(11)?.parse().ok()?;
    let stime: u64 = f.get(12)?.parse().ok()?;
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let rss_kb = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())?;
    Some(Sample {
        at: Instant::now(),
        cpu_ticks: utime + stime,
        rss_kb,
    })
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
            "[devices.ain{}]\ntransport = \"tcp\"\naddress = \"127.0.0.1:{port}\"\nunit_id = 1\ntimeout_s = 0.5\npoll_interval_s = 0.1\n\n",
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
pub fn run(seconds: f64) -> Result<String, String> {
    if !(seconds.is_finite() && seconds >= 10.0) {
        return Err(format!("--soak {seconds}: at least 10 seconds"));
    }
    let exe = std::env::current_exe().map_err(|e| format!("own binary: {e}"))?;
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
        Command::new(&exe)
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
        Command::new(&exe)
            .args(["--log", "warn", "run", "--config"])
            .arg(&cfg_path)
            .env_remove("NOTIFY_SOCKET")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| format!("compgate run: {e}"))?,
    );
    let pid = gw.0.id();
    let warmup = Duration::from_secs_f64((seconds * 0.2).min(30.0));
    let end = Instant::now() + Duration::from_secs_f64(seconds);
    std::thread::sleep(warmup);
    let mut samples = Vec::new();
    while Instant::now() < end {
        samples.push(sample(pid).ok_or("the gateway process ended during the soak")?);
        std::thread::sleep(Duration::from_secs(1));
    }
    let rows = rusqlite::Connection::open(dir.path().join("soak.db"))
        .and_then(|c| c.query_row("SELECT count(*) FROM readings", [], |r| r.get::<_, i64>(0)))
        .unwrap_or(-1);
    drop(gw);
    drop(sim);
    let mqtt_on = broker.is_some();
    drop(broker);

    let (first, last) = match (samples.first(), samples.last()) {
        (Some(f), Some(l)) if samples.len() >= 2 => (*f, *l),
        _ => return Err("too few samples".into()),
    };
    let hz = clock_ticks_per_s() as f64;
    let span_s = last.at.duration_since(first.at).as_secs_f64();
    let cpu_pct = (last.cpu_ticks - first.cpu_ticks) as f64 / hz / span_s * 100.0;
    let max_rss = samples.iter().map(|s| s.rss_kb).max().unwrap_or(0);
    // Growth: mean of the last quarter against the mean of the first quarter.
    let q = (samples.len() / 4).max(1);
    let mean = |s: &[Sample]| s.iter().map(|x| x.rss_kb as f64).sum::<f64>() / s.len() as f64;
    let early = mean(&samples[..q]);
    let late = mean(&samples[samples.len() - q..]);
    let growth_kb = late - early;
    let per_hour = growth_kb / span_s * 3600.0;
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
    let _ = writeln!(
        out,
        "RSS      {:.1} MB at start, {:.1} MB at end, {:.1} MB max (target < 30 MB)",
        first.rss_kb as f64 / 1024.0,
        last.rss_kb as f64 / 1024.0,
        max_rss as f64 / 1024.0
    );
    let _ = writeln!(
        out,
        "growth   {:+.2} MB (last quarter vs first quarter), {:+.2} MB/h",
        growth_kb / 1024.0,
        per_hour / 1024.0
    );
    Ok(out)
}
