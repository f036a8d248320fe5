//! The shop-floor service: the systemd unit's hardening, sd_notify readiness, watchdog
//! and status from the real binary, stopping and SIGHUP reload.

// Test helpers: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

mod common;

use std::time::Duration;

use common::metrics::value;
use common::process::Gateway;
use compgate::plant::{Bind, Plant};
use compgate_gateway::config;
use compgate_gateway::runtime::{self, Hooks, Status};
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;

const UNIT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/deploy/compgate.service");

#[test]
fn unit_file_exposure_is_at_most_2_0() {
    let out = std::process::Command::new("systemd-analyze")
        .args(["security", "--offline=true", "--no-pager", UNIT])
        .output()
        .expect("systemd-analyze runs (./test.sh installs the systemd package)");
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    let line = text
        .lines()
        .find(|l| l.contains("Overall exposure level"))
        .unwrap_or_else(|| panic!("no exposure figure in:\n{text}"));
    let figure: f64 = line
        .split(':')
        .nth(1)
        .and_then(|r| r.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("cannot parse: {line}"));
    println!("{line}");
    assert!(figure <= 2.0, "{line}");
    let unit = std::fs::read_to_string(UNIT).unwrap();
    for needle in [
        "Type=notify",
        "WatchdogSec=",
        "ExecStartPre=/usr/local/bin/compgate validate",
        "Restart=on-failure",
        "ProtectSystem=strict",
        "StateDirectory=compgate",
        "ConfigurationDirectory=compgate",
        "NoNewPrivileges=yes",
        "RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6 AF_CAN AF_NETLINK",
        "User=compgate",
    ] {
        assert!(unit.contains(needle), "unit lacks {needle}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn notify_ready_watchdog_and_status_from_the_real_binary() {
    let dir = tempfile::tempdir().unwrap();
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), "").await;
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    let ready =
        tokio::task::block_in_place(|| gw.wait_notify(10.0, "READY=1", |m| m.contains("READY=1")));
    assert!(ready.lines().any(|l| l == "READY=1"), "{ready}");
    // Watchdog pings keep coming from the control loop, with the status line.
    let status = tokio::task::block_in_place(|| {
        gw.wait_notify(10.0, "STATUS with a verified write", |m| {
            m.contains("WATCHDOG=1")
                && m.contains("ain1 up")
                && m.contains("X: SD43900=")
                && m.contains("jobs 1 ok")
        })
    });
    assert!(status.contains("STATUS="), "{status}");
    let before = gw
        .messages
        .iter()
        .filter(|m| m.contains("WATCHDOG=1"))
        .count();
    tokio::task::block_in_place(|| std::thread::sleep(Duration::from_millis(400)));
    tokio::task::block_in_place(|| {
        gw.wait_notify(2.0, "more WATCHDOG=1", |m| m.contains("WATCHDOG=1"))
    });
    assert!(
        gw.messages
            .iter()
            .filter(|m| m.contains("WATCHDOG=1"))
            .count()
            > before
    );

    // The field module stops answering: the status line says so.
    plant.field["ain1"].set_comm_fault(compgate_plc::field::CommFault::Silent);
    tokio::task::block_in_place(|| {
        gw.wait_notify(10.0, "STATUS link down", |m| m.contains("ain1 down"))
    });
    let stopping = tokio::task::block_in_place(|| {
        gw.signal("TERM");
        gw.wait_notify(10.0, "STOPPING=1", |m| m.contains("STOPPING=1"))
    });
    assert!(stopping.contains("STOPPING=1"));
    drop(plant);
}

// With WatchdogSec=4s (WATCHDOG_USEC=2000000) and a status tick every 5 s, the control
// loop still pings every second (half of WATCHDOG_USEC): systemd would not kill it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn watchdog_pings_follow_watchdog_usec_not_the_status_interval() {
    let dir = tempfile::tempdir().unwrap();
    let toml = common::config("hold", "", "")
        .replace("status_interval_s = 0.05", "status_interval_s = 5.0");
    let (plant, path) = common::plant_and_file(dir.path(), &toml, "").await;
    let mut gw = Gateway::start(dir.path(), &path, &[("WATCHDOG_USEC", "2000000")]);
    tokio::task::block_in_place(|| gw.wait_notify(10.0, "READY=1", |m| m.contains("READY=1")));
    let from = std::time::Instant::now();
    tokio::task::block_in_place(|| std::thread::sleep(Duration::from_millis(5500)));
    let to = std::time::Instant::now();
    let pings: Vec<std::time::Instant> = {
        let msgs = gw.notified.lock().unwrap();
        let times = gw.notified_at.lock().unwrap();
        msgs.iter()
            .zip(times.iter())
            .filter(|(m, t)| m.lines().any(|l| l == "WATCHDOG=1") && **t >= from)
            .map(|(_, t)| *t)
            .collect()
    };
    let mut gaps: Vec<Duration> = pings.windows(2).map(|w| w[1] - w[0]).collect();
    if let (Some(first), Some(last)) = (pings.first(), pings.last()) {
        gaps.push(*first - from);
        gaps.push(to - *last);
    }
    let max = gaps.iter().max().copied().unwrap_or(to - from);
    println!(
        "{} WATCHDOG=1 in {:?}, largest gap {max:?}",
        pings.len(),
        to - from
    );
    assert!(pings.len() >= 5, "{} pings in {:?}", pings.len(), to - from);
    assert!(
        max <= Duration::from_millis(1100),
        "a gap of {max:?} between pings"
    );
    assert!(tokio::task::block_in_place(|| gw.stop()));
    drop(plant);
}

// A device that goes silent for many polls logs one warning, and one line when it is
// back: transitions, never one line per poll.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_device_logs_one_warning_and_one_recovery() {
    let dir = tempfile::tempdir().unwrap();
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), "").await;
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| gw.wait_notify(10.0, "READY=1", |m| m.contains("READY=1")));
    plant.field["ain1"].set_comm_fault(compgate_plc::field::CommFault::Silent);
    tokio::task::block_in_place(|| {
        gw.wait_notify(10.0, "6 failed cycles", |m| {
            m.contains("ain1 down (6 failed)") || m.contains("ain1 down (7 failed)")
        })
    });
    plant.field["ain1"].set_comm_fault(compgate_plc::field::CommFault::None);
    tokio::task::block_in_place(|| gw.wait_log(10.0, "device link up again"));
    tokio::task::block_in_place(|| std::thread::sleep(Duration::from_millis(300)));
    let log = gw.stderr_text();
    let down: Vec<&str> = log
        .lines()
        .filter(|l| l.contains("device link down"))
        .collect();
    let up: Vec<&str> = log
        .lines()
        .filter(|l| l.contains("device link up again"))
        .collect();
    assert_eq!(down.len(), 1, "{log}");
    assert!(
        down[0].contains("WARN") && down[0].contains("ain1"),
        "{log}"
    );
    assert_eq!(up.len(), 1, "{log}");
    assert!(up[0].contains("INFO") && up[0].contains("ain1"), "{log}");
    let warnings = log.lines().filter(|l| l.contains("WARN")).count();
    assert_eq!(warnings, 1, "one warning for the whole outage:\n{log}");
    assert!(tokio::task::block_in_place(|| gw.stop()));
    drop(plant);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sighup_with_a_bad_config_keeps_the_old_one_running() {
    let dir = tempfile::tempdir().unwrap();
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), "").await;
    let good = std::fs::read_to_string(&path).unwrap();
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| gw.wait_notify(10.0, "READY=1", |m| m.contains("READY=1")));

    // A typo and a dangling reference: refused, every problem logged with its key.
    std::fs::write(
        &path,
        good.replace("timeout_s = 0.2", "timeot_s = 0.2")
            .replace("channel = \"T_bed\"", "channel = \"T_nope\""),
    )
    .unwrap();
    gw.signal("HUP");
    let line = tokio::task::block_in_place(|| gw.wait_log(10.0, "reload refused"));
    let err = gw.stderr_text();
    assert!(err.contains("devices.ain1.timeot_s: unknown key"), "{err}");
    assert!(err.contains("T_nope"), "{err}");
    assert!(line.contains("ERROR"), "{line}");
    // Still polling and writing with the old config.
    let jobs_before = plant.nc["nc_x"].jobs_executed();
    plant.field["ain1"]
        .set_temperature_override(0, Some(40.0))
        .unwrap();
    tokio::task::block_in_place(|| {
        gw.wait_notify(10.0, "still running", |m| {
            m.contains("ain1 up") && m.contains("SD43900=0.0800mm")
        })
    });
    assert!(plant.nc["nc_x"].jobs_executed() > jobs_before);

    // A good config takes effect.
    std::fs::write(
        &path,
        good.replace("coeff_mm_per_degc = 0.004", "coeff_mm_per_degc = 0.002"),
    )
    .unwrap();
    gw.signal("HUP");
    tokio::task::block_in_place(|| gw.wait_log(10.0, "configuration reloaded"));
    tokio::task::block_in_place(|| {
        gw.wait_notify(10.0, "new coefficient written", |m| {
            m.contains("SD43900=0.0400mm")
        })
    });
    assert!(tokio::task::block_in_place(|| gw.stop()));
    drop(plant);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reload_keeps_the_state_of_unchanged_channels_and_devices() {
    // A slow low-pass shows whether a channel's filter state survived: a fresh
    // processor starts at the first sample, a kept one is still near the old value.
    let filter = "{ median_samples = 1, lowpass_tau_s = 1000.0, max_rate_degc_per_s = 0.0, max_rejected_samples = 5, stale_after_s = 0.0, valid_min_degc = -20.0, valid_max_degc = 100.0 }";
    let toml = common::config("hold", "", filter);
    let cfg = config::load_str(&toml, "test.toml").unwrap();
    let plant = Plant::start(&cfg, Bind::Ephemeral).await.unwrap();
    let cfg = plant.config.clone();
    let (tx, mut rx) = watch::channel(Status::default());
    let (reload_tx, reload_rx) = mpsc::channel(1);
    let shutdown = CancellationToken::new();
    let sd = shutdown.clone();
    let run_cfg = cfg.clone();
    let gw = tokio::spawn(async move {
        let hooks = Hooks {
            reload: Some(reload_rx),
            ..Hooks::default()
        };
        runtime::run_with(&run_cfg, sd, tx, hooks).await.unwrap();
    });
    let wait = |rx: &mut watch::Receiver<Status>,
                what: &'static str,
                pred: Box<dyn Fn(&Status) -> bool + Send>| {
        let mut rx = rx.clone();
        async move {
            tokio::time::timeout(
                Duration::from_secs(10),
                rx.wait_for(|s| !s.channels.is_empty() && pred(s)),
            )
            .await
            .unwrap_or_else(|_| panic!("timed out waiting for {what}"))
            .unwrap()
            .clone()
        }
    };
    wait(&mut rx, "first job", Box::new(|s| s.axes[0].jobs_ok >= 1)).await;
    let field = plant.field["ain1"].clone();
    field
        .set_temperature_override(plant.transmitter["T_bed"], Some(40.0))
        .unwrap();
    field
        .set_temperature_override(plant.transmitter["T_col"], Some(40.0))
        .unwrap();
    let bed = cfg.channels.keys().position(|c| c == "T_bed").unwrap();
    let col = cfg.channels.keys().position(|c| c == "T_col").unwrap();
    let before = wait(
        &mut rx,
        "new samples",
        Box::new(move |s| {
            s.channels[bed]
                .reading
                .unfiltered_degc
                .is_some_and(|v| (v - 40.0).abs() < 0.1)
                && s.channels[col]
                    .reading
                    .unfiltered_degc
                    .is_some_and(|v| (v - 40.0).abs() < 0.1)
        }),
    )
    .await;
    assert!(before.channels[bed].reading.value_degc.unwrap() < 31.0);
    assert!(before.channels[col].reading.value_degc.unwrap() > 59.0);
    let jobs_before = before.axes[0].jobs_ok;

    // Change only T_col (its plausible range): T_bed, the device and the axis keep state.
    let mut new_cfg = cfg.clone();
    new_cfg
        .channels
        .get_mut("T_col")
        .unwrap()
        .filter
        .valid_max_degc = 110.0;
    reload_tx.send(new_cfg).await.unwrap();
    let after = wait(
        &mut rx,
        "T_col restarted",
        Box::new(move |s| {
            s.channels[col]
                .reading
                .value_degc
                .is_some_and(|v| (v - 40.0).abs() < 0.1)
        }),
    )
    .await;
    let bed_after = after.channels[bed].reading.value_degc.unwrap();
    assert!(bed_after < 31.0, "T_bed's low-pass was reset: {bed_after}");
    assert_eq!(
        after.devices[0].connects, 1,
        "the device kept its connection"
    );
    assert!(after.axes[0].jobs_ok >= jobs_before, "axis status kept");
    assert!(after.axes[0].written.is_some());
    shutdown.cancel();
    tokio::time::timeout(Duration::from_secs(10), gw)
        .await
        .unwrap()
        .unwrap();
}

/// A TCP peer that accepts connections and never answers, as a hung NC or a half-open
/// link does; counts the connections it accepted.
struct SilentPeer {
    addr: String,
    accepted: std::sync::Arc<std::sync::atomic::AtomicUsize>,
    stop: CancellationToken,
}

impl SilentPeer {
    async fn start() -> Self {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap().to_string();
        let accepted = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let stop = CancellationToken::new();
        let (n, s) = (accepted.clone(), stop.clone());
        tokio::spawn(async move {
            let mut held = Vec::new();
            loop {
                tokio::select! {
                    () = s.cancelled() => break,
                    a = listener.accept() => {
                        if let Ok((stream, _)) = a {
                            held.push(stream);
                            n.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                        }
                    }
                }
            }
        });
        SilentPeer {
            addr,
            accepted,
            stop,
        }
    }

    /// Waits until the gateway has connected (its snapshot read is then outstanding).
    async fn wait_connected(&self) {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
        while self.accepted.load(std::sync::atomic::Ordering::SeqCst) == 0 {
            assert!(
                tokio::time::Instant::now() < deadline,
                "the gateway never connected to the NC"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}

impl Drop for SilentPeer {
    fn drop(&mut self) {
        self.stop.cancel();
    }
}

/// [`common::config`] with the NC's request and job timeouts at `timeout_s`.
fn config_with_nc_timeouts(timeout_s: f64) -> String {
    let toml = common::config("hold", "", "").replace(
        "timeout_s = 0.5\njob_timeout_s = 0.5",
        &format!("timeout_s = {timeout_s:?}\njob_timeout_s = {timeout_s:?}"),
    );
    assert!(toml.contains(&format!("job_timeout_s = {timeout_s:?}")));
    toml
}

/// A plant for `toml` and a config file naming its addresses, the NC at `nc_address`.
async fn plant_with_nc_at(
    dir: &std::path::Path,
    toml: &str,
    nc_address: &str,
) -> (Plant, std::path::PathBuf) {
    let plant = Plant::start(&config::load_str(toml, "t.toml").unwrap(), Bind::Ephemeral)
        .await
        .unwrap();
    let mut cfg = plant.config.clone();
    cfg.nc_modules.get_mut("nc_x").unwrap().address = nc_address.to_string();
    let path = dir.join("compgate.toml");
    std::fs::write(&path, toml::to_string(&cfg).unwrap()).unwrap();
    (plant, path)
}

/// Waits up to 10 s for the gateway process to exit; whether it exited successfully.
fn wait_exit(gw: &mut Gateway) -> bool {
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while std::time::Instant::now() < deadline {
        if let Some(st) = gw.child.try_wait().unwrap() {
            return st.success();
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    panic!(
        "the gateway did not exit within 10 s:\n{}",
        gw.stderr_text()
    );
}

// An NC that accepts the connection and never answers, with a 60 s request timeout:
// SIGTERM stops the gateway at once, abandoning the outstanding read. It used to wait
// out the timeout (up to an hour), and systemd would have killed it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_stops_at_once_with_an_nc_read_outstanding() {
    let dir = tempfile::tempdir().unwrap();
    let nc = SilentPeer::start().await;
    let (plant, path) =
        plant_with_nc_at(dir.path(), &config_with_nc_timeouts(60.0), &nc.addr).await;
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| gw.wait_notify(10.0, "READY=1", |m| m.contains("READY=1")));
    nc.wait_connected().await;
    assert!(tokio::task::block_in_place(|| gw.stop()));
    drop(plant);
}

/// Starts the gateway against an NC whose jobs never finish (job timeout 60 s) and
/// waits until a job is in flight.
async fn gateway_with_a_job_in_flight(dir: &std::path::Path) -> (Plant, Gateway) {
    let toml = config_with_nc_timeouts(60.0);
    let (plant, path) = common::plant_and_file(dir, &toml, "").await;
    let nc = plant.nc["nc_x"].clone();
    nc.set_job_fault(compgate_plc::nc::JobFault::NeverFinish);
    let gw = Gateway::start(dir, &path, &[]);
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    while nc.job_state() != compgate_ncproto::JobState::Busy {
        assert!(
            tokio::time::Instant::now() < deadline,
            "no job in flight:\n{}",
            gw.stderr_text()
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    (plant, gw)
}

// A job in flight on SIGTERM gets a short grace, not its whole job timeout; then it is
// abandoned and the log says its outcome is unknown.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_abandons_a_job_in_flight_after_a_short_grace() {
    let dir = tempfile::tempdir().unwrap();
    let (plant, mut gw) = gateway_with_a_job_in_flight(dir.path()).await;
    gw.signal("TERM");
    assert!(tokio::task::block_in_place(|| wait_exit(&mut gw)));
    let line = gw.wait_log(1.0, "NC job abandoned at stop");
    assert!(line.contains("WARN"), "{line}");
    assert!(line.contains("whether it landed is unknown"), "{line}");
    assert!(line.contains("axis=X"), "{line}");
    drop(plant);
}

// A second stop signal does not wait for the job's grace: the gateway stops at once
// (after the recorder's final commit). It used to be ignored.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_stop_signal_stops_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let (plant, mut gw) = gateway_with_a_job_in_flight(dir.path()).await;
    gw.signal("TERM");
    tokio::task::block_in_place(|| gw.wait_log(10.0, "SIGTERM: stopping"));
    // The first signal's grace is 2 s: a machine stalled longer than that lets the
    // gateway stop before the second signal, and there is nothing to check.
    let running = gw.child.try_wait().unwrap().is_none();
    gw.signal("INT");
    assert!(tokio::task::block_in_place(|| wait_exit(&mut gw)));
    if running {
        let line = gw.wait_log(1.0, "Ctrl-C again: stopping now");
        assert!(line.contains("WARN"), "{line}");
    }
    drop(plant);
}

/// Counts the reloads that took effect.
struct Reloads(std::sync::Arc<std::sync::atomic::AtomicUsize>);

impl runtime::Observer for Reloads {
    fn on_reload(&mut self, result: &Result<(), runtime::GatewayError>) {
        if result.is_ok() {
            self.0.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        }
    }
}

// A reload while an NC read is outstanding (the NC never answers, 60 s timeout) takes
// effect between two polls, and the polls go on. It used to freeze polling, recording,
// the status and the watchdog until the read timed out.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reload_does_not_wait_for_an_outstanding_nc_read() {
    let nc = SilentPeer::start().await;
    let toml = config_with_nc_timeouts(60.0);
    let plant = Plant::start(&config::load_str(&toml, "t.toml").unwrap(), Bind::Ephemeral)
        .await
        .unwrap();
    let mut cfg = plant.config.clone();
    cfg.nc_modules.get_mut("nc_x").unwrap().address = nc.addr.clone();
    let (tx, rx) = watch::channel(Status::default());
    let (reload_tx, reload_rx) = mpsc::channel(1);
    let reloads = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let shutdown = CancellationToken::new();
    let (sd, run_cfg, counter) = (shutdown.clone(), cfg.clone(), reloads.clone());
    let gw = tokio::spawn(async move {
        let hooks = Hooks {
            observer: Box::new(Reloads(counter)),
            reload: Some(reload_rx),
            ..Hooks::default()
        };
        runtime::run_with(&run_cfg, sd, tx, hooks).await.unwrap();
    });
    let mut rx2 = rx.clone();
    let wait_samples = |at_least: u64| {
        let mut rx = rx.clone();
        async move {
            tokio::time::timeout(
                Duration::from_secs(10),
                rx.wait_for(|s| s.samples >= at_least),
            )
            .await
            .unwrap_or_else(|_| panic!("fewer than {at_least} samples after 10 s"))
            .unwrap()
            .samples
        }
    };
    wait_samples(2).await;
    nc.wait_connected().await;
    reload_tx.send(cfg).await.unwrap();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    while reloads.load(std::sync::atomic::Ordering::SeqCst) == 0 {
        assert!(
            tokio::time::Instant::now() < deadline,
            "the reload did not take effect within 10 s"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let samples = rx2.borrow_and_update().samples;
    wait_samples(samples + 10).await;
    shutdown.cancel();
    tokio::time::timeout(Duration::from_secs(10), gw)
        .await
        .expect("the gateway stops within 10 s")
        .unwrap();
}

// A reload that changes [recorder] or [metrics] says they take effect at the next
// restart, naming them; it used to keep the old ones in silence.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reload_names_the_sections_that_wait_for_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let extra = format!(
        "\n[recorder]\npath = \"{}\"\n\n[metrics]\nbind = \"127.0.0.1:0\"\n",
        dir.path().join("a.db").display()
    );
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), &extra).await;
    let text = std::fs::read_to_string(&path).unwrap();
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| gw.wait_notify(10.0, "READY=1", |m| m.contains("READY=1")));
    std::fs::write(
        &path,
        text.replace("a.db", "b.db")
            .replace("bind = \"127.0.0.1:0\"", "bind = \"127.0.0.1:1\""),
    )
    .unwrap();
    gw.signal("HUP");
    let line = tokio::task::block_in_place(|| gw.wait_log(10.0, "take effect at the next restart"));
    assert!(line.contains("WARN"), "{line}");
    assert!(line.contains("[recorder], [metrics]"), "{line}");
    assert!(!line.contains("[mqtt]"), "{line}");
    tokio::task::block_in_place(|| gw.wait_log(10.0, "configuration reloaded"));
    assert!(!dir.path().join("b.db").exists());
    // The file put back as the service runs: nothing waits for a restart any more. It
    // used to be compared with the file loaded last and warned again.
    std::fs::write(&path, &text).unwrap();
    gw.signal("HUP");
    tokio::task::block_in_place(|| gw.wait_log_nth(10.0, "configuration reloaded", 2));
    let warned = gw
        .stderr_text()
        .matches("take effect at the next restart")
        .count();
    assert_eq!(warned, 1, "{}", gw.stderr_text());
    assert!(tokio::task::block_in_place(|| gw.stop()));
    drop(plant);
}

/// GET /metrics; the body.
fn scrape(port: u16) -> String {
    common::metrics::scrape(port, Duration::from_secs(2))
        .expect("metrics endpoint")
        .0
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn prometheus_endpoint_shows_links_channels_jobs_and_cycle_times() {
    let dir = tempfile::tempdir().unwrap();
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), "").await;
    let mut text = std::fs::read_to_string(&path).unwrap();
    text.push_str("\n[metrics]\nbind = \"127.0.0.1:0\"\n");
    std::fs::write(&path, text).unwrap();
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| gw.wait_notify(10.0, "first job", |m| m.contains("jobs 1 ok")));
    let port = gw.metrics_port(1.0);
    tokio::time::sleep(Duration::from_millis(300)).await;
    let m = tokio::task::block_in_place(|| scrape(port));
    assert_eq!(
        value(&m, r#"compgate_device_link_up{device="ain1"}"#),
        Some(1.0),
        "{m:?}"
    );
    let bed = value(&m, r#"compgate_channel_value_degc{channel="T_bed"}"#).unwrap();
    assert!((bed - 30.0).abs() < 0.1, "{bed}");
    assert_eq!(
        value(&m, r#"compgate_channel_quality{channel="T_bed"}"#),
        Some(0.0)
    );
    assert!(value(&m, r#"compgate_nc_jobs_total{axis="X",result="ok"}"#).unwrap() >= 1.0);
    let k0 = value(&m, r#"compgate_axis_sd43900_mm{axis="X"}"#).unwrap();
    assert!((k0 - 0.04).abs() < 0.001, "{k0}");
    assert!(value(&m, r#"compgate_cycle_seconds_count"#).unwrap() > 0.0);
    // glibc's figures: the gateway's live heap is megabytes, not zero.
    if cfg!(all(target_os = "linux", target_env = "gnu")) {
        let in_use = value(&m, r#"compgate_process_heap_bytes{state="in_use"}"#).unwrap();
        assert!(in_use > 100_000.0, "{in_use}");
        assert!(value(&m, r#"compgate_process_heap_bytes{state="free"}"#).is_some());
    }
    assert!(m
        .lines()
        .any(|l| l.starts_with("compgate_device_poll_seconds_bucket{device=\"ain1\"")));

    // The device stops answering: link down, timeouts counted, channels bad.
    plant.field["ain1"].set_comm_fault(compgate_plc::field::CommFault::Silent);
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let m = tokio::task::block_in_place(|| scrape(port));
    assert_eq!(
        value(&m, r#"compgate_device_link_up{device="ain1"}"#),
        Some(0.0)
    );
    assert!(
        value(
            &m,
            r#"compgate_device_errors_total{device="ain1",kind="timeout"}"#
        )
        .unwrap()
            >= 3.0
    );
    assert_eq!(
        value(&m, r#"compgate_channel_quality{channel="T_bed"}"#),
        Some(2.0)
    );
    // A bad channel's held value is no measurement: a dashboard plotting the value
    // alone drew a normal flat line through a wire break. NaN leaves a gap.
    let bed = value(&m, r#"compgate_channel_value_degc{channel="T_bed"}"#).unwrap();
    assert!(bed.is_nan(), "{bed}");
    assert!(tokio::task::block_in_place(|| gw.stop()));
    drop(plant);
}

// Under systemd, stdout is the journal (`JOURNAL_STREAM` names it): a line of every
// channel per status update would bury the journal's events, so none is printed
// there. On a file or a pipe there is one per update.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_status_line_per_update_when_stdout_is_the_journal() {
    use std::os::unix::fs::MetadataExt;
    let dir = tempfile::tempdir().unwrap();
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), "").await;
    let field = &plant.field["ain1"];
    // Runs the gateway 1.5 s with stdout on a file, `JOURNAL_STREAM` naming that file
    // (`journal`) or another inode; its stdout, and the polls it made meanwhile.
    let run = |journal: bool| {
        let out = dir.path().join(format!("stdout-{journal}.txt"));
        let file = std::fs::File::create(&out).unwrap();
        let m = file.metadata().unwrap();
        let ino = if journal { m.ino() } else { m.ino() + 1 };
        let polls_before = field.requests_served();
        let mut child = std::process::Command::new(common::process::BIN)
            .args(["--log", "warn", "run", "--config"])
            .arg(&path)
            .env("JOURNAL_STREAM", format!("{}:{ino}", m.dev()))
            .env_remove("NOTIFY_SOCKET")
            .env_remove("RUST_LOG")
            .stdout(file)
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(Duration::from_millis(1500));
        common::process::signal(child.id(), "TERM");
        let exit = child.wait().unwrap();
        assert!(exit.success(), "journal {journal}: {exit}");
        let polls = field.requests_served() - polls_before;
        (std::fs::read_to_string(&out).unwrap(), polls)
    };
    let (text, polls) = tokio::task::block_in_place(|| run(false));
    assert!(polls >= 5, "{polls} polls in 1.5 s");
    let lines = text.lines().filter(|l| l.contains("T_bed=")).count();
    assert!(lines >= 5, "{lines} status lines on a file:\n{text}");
    let (text, polls) = tokio::task::block_in_place(|| run(true));
    assert!(polls >= 5, "{polls} polls in 1.5 s with stdout the journal");
    assert_eq!(text, "", "stdout is the journal");
}

// Nobody reads `/dev/null`: the line is not rendered there (at 1000 channels it was a
// seventh of the gateway's instructions at 10k points/s). The test above shows a file
// still gets it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_status_line_rendered_when_stdout_is_dev_null() {
    let dir = tempfile::tempdir().unwrap();
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), "").await;
    let field = &plant.field["ain1"];
    let log = dir.path().join("stderr.txt");
    let polls_before = field.requests_served();
    let (exit, polls) = tokio::task::block_in_place(|| {
        let mut child = std::process::Command::new(common::process::BIN)
            .args(["--log", "info", "run", "--config"])
            .arg(&path)
            .env_remove("JOURNAL_STREAM")
            .env_remove("NOTIFY_SOCKET")
            .env_remove("RUST_LOG")
            .stdout(std::process::Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap();
        std::thread::sleep(Duration::from_millis(1500));
        common::process::signal(child.id(), "TERM");
        (
            child.wait().unwrap(),
            field.requests_served() - polls_before,
        )
    });
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(exit.success(), "{exit}:\n{text}");
    assert!(polls >= 5, "{polls} polls in 1.5 s with stdout /dev/null");
    assert!(
        text.contains("stdout is /dev/null: no status line per update"),
        "{text}"
    );
}
