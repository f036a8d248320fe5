//! The fault catalogue with real processes and sockets (the README's fault table).
//! Timeouts, exception responses, dropped connections and rejected NC jobs are in
//! `tests/gateway.rs`; a bad config on SIGHUP in `tests/service.rs`; a full disk in
//! `tests/record.rs`; the broker down in `tests/mqtt.rs`.

// Test helpers: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

mod common;

use std::sync::{Arc, Mutex};
use std::time::Duration;

use common::process::Gateway;
use common::proxy::Proxy;
use common::{config, COUNT_DEGC};
use compgate::plant::{Bind, Plant};
use compgate_core::channel::{Quality, Reading, Reason};
use compgate_gateway::config as cfgmod;
use compgate_gateway::runtime::{self, Status};
use compgate_plc::field::CommFault;
use compgate_plc::nc::NcAxisModule;
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;

fn reading<'a>(s: &'a Status, ch: &str) -> &'a Reading {
    &s.channels
        .iter()
        .find(|c| &*c.name == ch)
        .expect("channel")
        .reading
}

fn q(s: &Status, ch: &str) -> Quality {
    reading(s, ch).quality
}

/// The gateway in-process on `cfg`; returns its status and a stopper.
fn run_gateway(
    cfg: cfgmod::Config,
) -> (
    watch::Receiver<Status>,
    CancellationToken,
    tokio::task::JoinHandle<()>,
) {
    let (tx, rx) = watch::channel(Status::default());
    let shutdown = CancellationToken::new();
    let sd = shutdown.clone();
    let h = tokio::spawn(async move {
        runtime::run(&cfg, sd, tx).await.expect("gateway runs");
    });
    (rx, shutdown, h)
}

async fn wait(
    rx: &watch::Receiver<Status>,
    secs: f64,
    what: &str,
    pred: impl Fn(&Status) -> bool,
) -> Status {
    let mut rx2 = rx.clone();
    let got = tokio::time::timeout(
        Duration::from_secs_f64(secs),
        rx2.wait_for(|s| !s.channels.is_empty() && pred(s)),
    )
    .await
    .map(|s| s.expect("status").clone());
    match got {
        Ok(s) => s,
        Err(_) => panic!(
            "timed out waiting for {what}: {}",
            compgate_service::status::render(&rx.borrow())
        ),
    }
}

/// Watches the NC's SD43900 every 2 ms and keeps every distinct value, in order.
fn watch_nc(nc: NcAxisModule, stop: CancellationToken) -> Arc<Mutex<Vec<f64>>> {
    let seen = Arc::new(Mutex::new(vec![nc.state().sd43900_mm]));
    let s = seen.clone();
    tokio::spawn(async move {
        while !stop.is_cancelled() {
            let v = nc.state().sd43900_mm;
            {
                let mut s = s.lock().unwrap();
                if s.last() != Some(&v) {
                    s.push(v);
                }
            }
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    });
    seen
}

fn max_jump(values: &[f64]) -> f64 {
    values
        .windows(2)
        .map(|w| (w[1] - w[0]).abs())
        .fold(0.0, f64::max)
}

/// Waits (10 s at most) until the NC holds an SD43900 of at least `mm`; panics with
/// `what` and the NC's state if it does not.
async fn ramped_to(nc: &NcAxisModule, mm: f64, what: &str) {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    while nc.state().sd43900_mm < mm {
        assert!(
            tokio::time::Instant::now() < deadline,
            "{what}: {:?}",
            nc.state()
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// Stops [`watch_nc`]'s watch and returns what the NC held, checked to have moved by at
/// most `max_step_mm` at a time.
fn stepped(seen: &Mutex<Vec<f64>>, stop: &CancellationToken, max_step_mm: f64) -> Vec<f64> {
    stop.cancel();
    let seen = seen.lock().unwrap().clone();
    assert!(
        max_jump(&seen) <= max_step_mm + 1e-9,
        "jump {} in {seen:?}",
        max_jump(&seen)
    );
    seen
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn modbus_server_process_killed_and_restarted() {
    // The field module runs as its own process (`compgate sim`) on a fixed port.
    let dir = tempfile::tempdir().unwrap();
    let port = common::free_port();
    let mut field_cfg = cfgmod::load_str(&config("hold", "", ""), "test.toml").unwrap();
    field_cfg.nc_modules.clear();
    field_cfg.axes.clear();
    if let Some(sim) = field_cfg.sim.as_mut() {
        sim.nc_modules.clear();
    }
    field_cfg
        .devices
        .get_mut("ain1")
        .and_then(|d| d.tcp_mut())
        .unwrap()
        .address = format!("127.0.0.1:{port}");
    let field_path = dir.path().join("field.toml");
    std::fs::write(&field_path, toml::to_string(&field_cfg).unwrap()).unwrap();
    let start_sim = || {
        let mut child = std::process::Command::new(common::process::BIN)
            .args(["sim", "--config"])
            .arg(&field_path)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        common::process::wait_listening(&mut child, port, 4.0, "compgate sim");
        child
    };
    let mut sim = tokio::task::block_in_place(start_sim);

    // The NC from an in-process plant; the gateway reads the field module process.
    let plant = Plant::start(
        &cfgmod::load_str(&config("hold", "", ""), "t.toml").unwrap(),
        Bind::Ephemeral,
    )
    .await
    .unwrap();
    let mut cfg = plant.config.clone();
    cfg.devices
        .get_mut("ain1")
        .and_then(|d| d.tcp_mut())
        .unwrap()
        .address = format!("127.0.0.1:{port}");
    let (rx, shutdown, h) = run_gateway(cfg);
    wait(&rx, 10.0, "first job", |s| s.axes[0].jobs_ok >= 1).await;
    let jobs = plant.nc["nc_x"].jobs_executed();
    let sd = plant.nc["nc_x"].state().sd43900_mm;

    sim.kill().unwrap();
    sim.wait().unwrap();
    let s = wait(&rx, 10.0, "channels bad, axis holding", |s| {
        matches!(q(s, "T_bed"), Quality::Bad(_)) && s.axes[0].decision.starts_with("hold")
    })
    .await;
    assert!(
        s.devices[0]
            .errors
            .keys()
            .any(|k| *k == "connect" || *k == "transport" || *k == "backoff"),
        "{:?}",
        s.devices[0].errors
    );
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(
        plant.nc["nc_x"].jobs_executed(),
        jobs,
        "no job from dead inputs"
    );
    assert_eq!(plant.nc["nc_x"].state().sd43900_mm, sd);

    let mut sim = tokio::task::block_in_place(start_sim);
    let s = wait(&rx, 10.0, "reconnected and good", |s| {
        q(s, "T_bed") == Quality::Good && s.devices[0].connects >= 2
    })
    .await;
    let v = reading(&s, "T_bed").value_degc.expect("a value");
    assert!((v - 30.0).abs() <= COUNT_DEGC, "{v}");
    shutdown.cancel();
    h.await.unwrap();
    let _ = sim.kill();
    let _ = sim.wait();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nc_unreachable_while_temperatures_change() {
    let toml = config("hold", "", "").replace("max_step_k0_mm = 0.5", "max_step_k0_mm = 0.01");
    let plant = Plant::start(&cfgmod::load_str(&toml, "t.toml").unwrap(), Bind::Ephemeral)
        .await
        .unwrap();
    let nc = plant.nc["nc_x"].clone();
    let proxy = Proxy::start(plant.config.nc_modules["nc_x"].address.clone()).await;
    let mut cfg = plant.config.clone();
    cfg.nc_modules.get_mut("nc_x").unwrap().address = proxy.addr.to_string();
    let stop_watch = CancellationToken::new();
    let seen = watch_nc(nc.clone(), stop_watch.clone());
    let (rx, shutdown, h) = run_gateway(cfg);
    wait(&rx, 10.0, "ramped to 0.04", |s| {
        s.axes[0]
            .written
            .is_some_and(|p| (p.k0_mm - 0.04).abs() < 0.001)
    })
    .await;

    proxy.cut();
    let jobs = nc.jobs_executed();
    plant.field["ain1"]
        .set_temperature_override(plant.transmitter["T_bed"], Some(40.0))
        .unwrap();
    // Jobs may fail before the first failed read; after it none is tried.
    let s = wait(&rx, 10.0, "NC unreachable shown, 40 degC read", |s| {
        s.axes[0]
            .warning
            .as_deref()
            .is_some_and(|w| w.contains("NC unreachable"))
            && reading(s, "T_bed")
                .value_degc
                .is_some_and(|v| (v - 40.0).abs() <= COUNT_DEGC)
    })
    .await;
    // The last position read is not shown as if it were live, nor the last decision.
    assert!(s.axes[0].nc.is_none(), "{:?}", s.axes[0].nc);
    assert_eq!(s.axes[0].decision, "hold: NC unreachable");
    // The temperatures are still followed; nothing reaches the NC; nothing is taken as written.
    let v = reading(&s, "T_bed").value_degc.expect("a value");
    assert!((v - 40.0).abs() <= COUNT_DEGC);
    assert_eq!(nc.jobs_executed(), jobs);
    assert!((s.axes[0].written.unwrap().k0_mm - nc.state().sd43900_mm).abs() < 1e-12);

    proxy.restore();
    wait(&rx, 15.0, "caught up with 40 degC", |s| {
        s.axes[0]
            .written
            .is_some_and(|p| (p.k0_mm - 0.08).abs() < 0.001)
            && s.axes[0].warning.is_none()
    })
    .await;
    let seen = stepped(&seen, &stop_watch, 0.01);
    assert!(seen.len() >= 8, "ramped in steps: {seen:?}");
    shutdown.cancel();
    h.await.unwrap();
}

// The NC restarts and comes back holding 0 (or someone changes SD43900 at the HMI)
// while the temperatures hold still: the gateway must see that the NC no longer holds
// what it confirmed and ramp from what it does hold. It used to keep its old
// baseline: within the deadband, it never wrote again, and the NC ran uncompensated.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_nc_that_lost_its_values_is_ramped_again_from_what_it_holds() {
    let toml = config("hold", "", "").replace("max_step_k0_mm = 0.5", "max_step_k0_mm = 0.01");
    let plant = Plant::start(&cfgmod::load_str(&toml, "t.toml").unwrap(), Bind::Ephemeral)
        .await
        .unwrap();
    let nc = plant.nc["nc_x"].clone();
    let (rx, shutdown, h) = run_gateway(plant.config.clone());
    // Done ramping: no job is on its way when the NC loses its values (one decided
    // from the old baseline before the next snapshot would still land in one step).
    wait(&rx, 10.0, "ramped to 0.04 and within the deadband", |s| {
        s.axes[0]
            .written
            .is_some_and(|p| (p.k0_mm - 0.04).abs() < 0.001)
            && s.axes[0].decision == "within deadband"
    })
    .await;
    let jobs = nc.jobs_executed();
    nc.with_state(|a| a.sd43900_mm = 0.0);
    let stop_watch = CancellationToken::new();
    let seen = watch_nc(nc.clone(), stop_watch.clone());
    let deadline = tokio::time::Instant::now() + Duration::from_secs(15);
    while (nc.state().sd43900_mm - 0.04).abs() > 0.001 {
        assert!(
            tokio::time::Instant::now() < deadline,
            "the NC still holds {} mm after 15 s ({} jobs since)",
            nc.state().sd43900_mm,
            nc.jobs_executed() - jobs
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let seen = stepped(&seen, &stop_watch, 0.01);
    assert!(seen.len() >= 4, "ramped in steps: {seen:?}");
    shutdown.cancel();
    h.await.unwrap();
}

// The NC's values change (here: cleared at the HMI) between two reads of the NC while
// the gateway ramps: the next job was limited from what the NC held before, and would
// have jumped from 0 to the ramp's next value in one step. Each job now goes out only
// while the NC holds what its step was limited from; here the NC is read once a minute
// (status interval 60 s), so only that check can see the change.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_value_changed_between_reads_of_the_nc_is_never_stepped_over() {
    let toml = config("hold", "", "")
        .replace("max_step_k0_mm = 0.5", "max_step_k0_mm = 0.005")
        .replace("status_interval_s = 0.05", "status_interval_s = 60.0");
    let plant = Plant::start(&cfgmod::load_str(&toml, "t.toml").unwrap(), Bind::Ephemeral)
        .await
        .unwrap();
    plant.field["ain1"]
        .set_temperature_override(plant.transmitter["T_bed"], Some(60.0))
        .unwrap();
    let nc = plant.nc["nc_x"].clone();
    let (rx, shutdown, h) = run_gateway(plant.config.clone());
    ramped_to(&nc, 0.02, "no ramp").await;
    nc.with_state(|a| a.sd43900_mm = 0.0);
    let stop_watch = CancellationToken::new();
    let seen = watch_nc(nc.clone(), stop_watch.clone());
    ramped_to(&nc, 0.02, "no ramp again").await;
    let seen = stepped(&seen, &stop_watch, 0.005);
    assert!(seen.len() >= 4, "ramped again from 0 in steps: {seen:?}");
    drop(rx);
    shutdown.cancel();
    h.await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn gateway_sigkill_and_restart_reads_the_nc_first_and_never_jumps() {
    let dir = tempfile::tempdir().unwrap();
    let toml = config("hold", "", "").replace("max_step_k0_mm = 0.5", "max_step_k0_mm = 0.005");
    let plant = Plant::start(&cfgmod::load_str(&toml, "t.toml").unwrap(), Bind::Ephemeral)
        .await
        .unwrap();
    plant.field["ain1"]
        .set_temperature_override(plant.transmitter["T_bed"], Some(60.0))
        .unwrap();
    let path = dir.path().join("compgate.toml");
    std::fs::write(&path, toml::to_string(&plant.config).unwrap()).unwrap();
    let nc = plant.nc["nc_x"].clone();
    let stop_watch = CancellationToken::new();
    let seen = watch_nc(nc.clone(), stop_watch.clone());

    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| {
        gw.wait_notify(10.0, "a few steps", |m| m.contains("jobs 5 ok"))
    });
    gw.signal("KILL");
    let _ = gw.child.wait();
    let held = nc.state().sd43900_mm;
    assert!(held > 0.02 && held < 0.1, "mid-ramp: {held}");
    drop(gw);

    let mut gw = Gateway::start(dir.path(), &path, &[]);
    let line = tokio::task::block_in_place(|| gw.wait_log(10.0, "NC parameters read at start"));
    assert!(line.contains(&format!("sd43900_mm={held}")), "{line}");
    tokio::task::block_in_place(|| {
        gw.wait_notify(20.0, "the ramp completed", |m| m.contains("SD43900=0.160"))
    });
    let seen = stepped(&seen, &stop_watch, 0.005);
    assert!(seen.contains(&held));
    assert!(tokio::task::block_in_place(|| gw.stop()));
}

/// CRC-16/MODBUS, as it goes on the wire (low byte first).
fn crc16(bytes: &[u8]) -> [u8; 2] {
    crc::Crc::<u16>::new(&crc::CRC_16_MODBUS)
        .checksum(bytes)
        .to_le_bytes()
}

fn response(unit: u8, fc: u8, regs: &[u16]) -> Vec<u8> {
    let mut f = vec![unit, fc, (regs.len() * 2) as u8];
    for r in regs {
        f.extend_from_slice(&r.to_be_bytes());
    }
    let c = crc16(&f);
    f.extend_from_slice(&c);
    f
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn garbage_and_malformed_rtu_frames_never_become_values() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let (mut master, _slave, pty) = compgate_plc::field::pty_pair().unwrap();
    let toml = config("hold", "", "")
        .replace(
            "transport = \"tcp\"\naddress = \"127.0.0.1:0\"",
            &format!("transport = \"rtu\"\nserial_path = \"{pty}\"\nbaud = 115200\nparity = \"even\"\nstop_bits = 1"),
        )
        .replace("connect_timeout_s = 0.5\n", "")
        .replace("unit_id = 1\ntimeout_s = 0.2", "unit_id = 9\ntimeout_s = 0.2");
    let cfg = cfgmod::load_str(&toml, "t.toml").unwrap();
    // The NC from a plant of the TCP variant; the RTU line is served by this test.
    let plant = Plant::start(
        &cfgmod::load_str(&config("hold", "", ""), "t.toml").unwrap(),
        Bind::Ephemeral,
    )
    .await
    .unwrap();
    let mut cfg = cfg;
    cfg.nc_modules = plant.config.nc_modules.clone();

    // 1775 counts = 30.04 degC on every channel; the garbage carries 3000 counts (111 degC).
    const GOOD: u16 = 1775;
    let mode = Arc::new(std::sync::atomic::AtomicU8::new(0));
    let m = mode.clone();
    let server = tokio::spawn(async move {
        let mut n: u32 = 0;
        let mut req = [0u8; 8];
        loop {
            if master.read_exact(&mut req).await.is_err() {
                break;
            }
            // Resynchronise on a request for our unit (a previous garbage reply may
            // have left the client mid-frame; requests are always 8 bytes).
            if req[0] != 9 || crc16(&req[..6]) != [req[6], req[7]] {
                continue;
            }
            let count = usize::from(u16::from_be_bytes([req[4], req[5]]));
            n += 1;
            let good = response(9, req[1], &vec![GOOD; count]);
            let reply = if m.load(std::sync::atomic::Ordering::SeqCst) == 0 {
                good
            } else {
                match n % 5 {
                    // Bytes that are no frame at all.
                    0 => vec![0x55, 0xAA, 0x00, 0xFF, 0x13, 0x37, 0x42],
                    // A frame with a wrong CRC.
                    1 => {
                        let mut f = response(9, req[1], &vec![3000; count]);
                        let l = f.len();
                        f[l - 1] ^= 0xFF;
                        f
                    }
                    // A truncated frame.
                    2 => response(9, req[1], &vec![3000; count])[..4].to_vec(),
                    // A valid frame from another unit.
                    3 => response(7, req[1], &vec![3000; count]),
                    // A byte count that does not match the request.
                    _ => response(9, req[1], &vec![3000; count + 1]),
                }
            };
            if master.write_all(&reply).await.is_err() {
                break;
            }
        }
    });
    let (rx, shutdown, h) = run_gateway(cfg);
    wait(&rx, 10.0, "good over RTU", |s| {
        q(s, "T_bed") == Quality::Good
    })
    .await;

    mode.store(1, std::sync::atomic::Ordering::SeqCst);
    // Every status during the garbage: any value shown is the true one.
    let mut watch_rx = rx.clone();
    let check = tokio::spawn(async move {
        let mut worst: f64 = 0.0;
        let deadline = tokio::time::Instant::now() + Duration::from_secs(3);
        while tokio::time::timeout_at(deadline, watch_rx.changed())
            .await
            .is_ok()
        {
            let s = watch_rx.borrow_and_update().clone();
            for c in &s.channels {
                for v in [c.reading.unfiltered_degc, c.reading.value_degc]
                    .into_iter()
                    .flatten()
                {
                    worst = worst.max((v - 30.04).abs());
                }
            }
        }
        worst
    });
    let s = wait(&rx, 10.0, "channels no longer good", |s| {
        !q(s, "T_bed").is_good()
    })
    .await;
    let errors: u64 = s.devices[0].errors.values().sum();
    assert!(errors >= 1, "{:?}", s.devices[0].errors);
    let worst = check.await.unwrap();
    assert!(
        worst < 0.05,
        "a garbage value reached a channel: off by {worst} degC"
    );

    mode.store(0, std::sync::atomic::Ordering::SeqCst);
    wait(&rx, 10.0, "good again", |s| {
        q(s, "T_bed") == Quality::Good && q(s, "T_col") == Quality::Good
    })
    .await;
    shutdown.cancel();
    h.await.unwrap();
    server.abort();
}

/// The test plant on two RTU modules sharing the line at `path`: `ain1` (T_bed,
/// T_screw; `timeout_s = 0.2`, polled every 0.05 s) and `ain2` (T_col) with `ain2_keys`.
fn two_modules_on_a_line(path: &str, ain2_keys: &str) -> String {
    let rtu = format!("transport = \"rtu\"\nserial_path = \"{path}\"\nbaud = 115200");
    config("hold", "", "")
        .replace("transport = \"tcp\"\naddress = \"127.0.0.1:0\"", &rtu)
        .replace("connect_timeout_s = 0.5\n", "")
        .replace(
            "[channels.T_col]\ndevice = \"ain1\"",
            "[channels.T_col]\ndevice = \"ain2\"",
        )
        .replace(
            "[nc_modules.nc_x]",
            &format!("[devices.ain2]\n{rtu}\nunit_id = 2\n{ain2_keys}\n\n[nc_modules.nc_x]"),
        )
}

// An RS-485 line shared by two modules, one of which stops answering: its timeouts
// (each followed by the wait for a quiet line) held the healthy one's cycles up,
// 0.05 s became more than 0.4 s. Once degraded the silent module is asked only when
// its backoff allows, the healthy one keeps its interval, and the silent one is good
// again soon after it answers.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_module_on_a_shared_rtu_line_does_not_hold_up_the_others() {
    let toml = two_modules_on_a_line(
        "/dev/compgate-test-line",
        "timeout_s = 0.2\nretries = 0\npoll_interval_s = 0.05\nbackoff_initial_s = 0.1\n\
         backoff_max_s = 0.8\ndegrade_after_cycles = 3",
    );
    let plant = Plant::start(&cfgmod::load_str(&toml, "t.toml").unwrap(), Bind::Ephemeral)
        .await
        .unwrap();
    let (healthy, silent) = (plant.field["ain1"].clone(), plant.field["ain2"].clone());
    let (rx, shutdown, h) = run_gateway(plant.config.clone());
    wait(&rx, 10.0, "both modules read", |s| {
        q(s, "T_bed") == Quality::Good && q(s, "T_col") == Quality::Good
    })
    .await;

    silent.set_comm_fault(CommFault::Silent);
    wait(&rx, 10.0, "the silent module degraded", |s| {
        q(s, "T_col") == Quality::Bad(Reason::DeviceDegraded)
    })
    .await;
    // Its first waits are short: measure once they have doubled to the longest.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    healthy.log_requests(true);
    let asked_before = silent.requests_received();
    tokio::time::sleep(Duration::from_secs(2)).await;
    let arrivals = healthy.take_request_log();
    let asked = silent.requests_received() - asked_before;
    println!(
        "in 2 s: the healthy module asked {} times, the silent one {asked}",
        arrivals.len()
    );
    // 2 s at 0.05 s: 40 cycles, less the line time of the silent module's asks
    // (every 0.8 s, each one timeout and one quiet wait: 0.4 s): about 25. Without the
    // backoff, 5.
    assert!(
        arrivals.len() >= 15,
        "the healthy module was asked {} times in 2 s",
        arrivals.len()
    );
    assert!(
        (1..=4).contains(&asked),
        "the silent module was asked {asked} times in 2 s"
    );
    let s = rx.borrow().clone();
    let ain2 = s.devices.iter().find(|d| d.name == "ain2").unwrap();
    assert!(ain2.errors.contains_key("backoff"), "{:?}", ain2.errors);
    assert!(
        ain2.last_error
            .as_deref()
            .is_some_and(|e| e.contains("no reply within") && e.contains("next attempt in")),
        "{:?}",
        ain2.last_error
    );
    assert_eq!(q(&s, "T_bed"), Quality::Good);

    silent.set_comm_fault(CommFault::None);
    wait(
        &rx,
        5.0,
        "the module good again within its longest wait",
        |s| q(s, "T_col") == Quality::Good,
    )
    .await;
    shutdown.cancel();
    h.await.unwrap();
}

// Two modules on one RS-485 line, the second one slow: its own `timeout_s` must hold
// for its requests. The line's connection was built from the first device's settings
// (by name), so the slow module timed out after the fast one's 0.05 s on every
// request, whatever its own key said.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_module_on_a_shared_rtu_line_gets_its_own_timeout() {
    let toml = two_modules_on_a_line(
        "/dev/compgate-test-timeouts",
        "timeout_s = 0.8\nretries = 0\npoll_interval_s = 0.2",
    )
    .replace("timeout_s = 0.2\n", "timeout_s = 0.05\n");
    let plant = Plant::start(&cfgmod::load_str(&toml, "t.toml").unwrap(), Bind::Ephemeral)
        .await
        .unwrap();
    // Slow enough that a wait for the line shows in the fast module's cycle beside
    // what a loaded machine adds to its round trips.
    plant.field["ain2"].set_comm_fault(CommFault::Delay(Duration::from_millis(300)));
    let (mut rx, shutdown, h) = run_gateway(plant.config.clone());
    // The fast module's cycles, as the status shows them, while it takes turns with
    // the slow one: its own round trips (and the quiet wait of 0.05 s when it opens
    // the port), not its wait for the line (that made it look as slow as the other in
    // its metrics and on the status page).
    let mut fast_cycle = Duration::ZERO;
    let s = loop {
        let s = rx.borrow_and_update().clone();
        if let Some(d) = s.devices.iter().find(|d| d.name == "ain1") {
            fast_cycle = fast_cycle.max(d.last_cycle);
        }
        if s.devices.iter().any(|d| d.name == "ain2" && d.cycles >= 10) {
            break s;
        }
        tokio::time::timeout(Duration::from_secs(10), rx.changed())
            .await
            .expect("a status within 10 s")
            .unwrap();
    };
    shutdown.cancel();
    h.await.unwrap();
    assert!(
        fast_cycle < Duration::from_millis(200),
        "the fast module's cycle took {fast_cycle:?}"
    );
    let slow = s.devices.iter().find(|d| d.name == "ain2").unwrap();
    assert!(
        slow.errors.is_empty(),
        "the slow module's requests failed: {:?}, {:?}",
        slow.errors,
        slow.last_error
    );
    assert_eq!(q(&s, "T_col"), Quality::Good);
    assert_eq!(q(&s, "T_bed"), Quality::Good);
}

// The same line, the slow module's replies coming after its own timeout_s (0.2 s) but
// within it plus the quiet wait: the wait before the next request must be the timed-out
// request's, not that of the next device on the line (0.05 s), or the late reply
// answers the fast module's request (a frame error naming the other unit).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_late_reply_on_a_shared_rtu_line_never_reaches_the_next_module() {
    let toml = two_modules_on_a_line(
        "/dev/compgate-test-late",
        "timeout_s = 0.2\nretries = 0\npoll_interval_s = 0.2\nbackoff_initial_s = 0.1\n\
         backoff_max_s = 0.2",
    )
    // ain1's (the first in the file).
    .replacen("timeout_s = 0.2\n", "timeout_s = 0.05\n", 1);
    let plant = Plant::start(&cfgmod::load_str(&toml, "t.toml").unwrap(), Bind::Ephemeral)
        .await
        .unwrap();
    plant.field["ain2"].set_comm_fault(CommFault::Delay(Duration::from_millis(300)));
    let (rx, shutdown, h) = run_gateway(plant.config.clone());
    let s = wait(&rx, 20.0, "8 timeouts of the slow module", |s| {
        s.devices
            .iter()
            .any(|d| d.name == "ain2" && d.errors.get("timeout").copied().unwrap_or(0) >= 8)
    })
    .await;
    shutdown.cancel();
    h.await.unwrap();
    let fast = s.devices.iter().find(|d| d.name == "ain1").unwrap();
    // A late reply reaching the fast module is a frame error naming unit 2. A timeout
    // of its own 0.05 s is what a loaded machine may cause (CI saw one).
    assert!(
        fast.errors.keys().all(|k| *k == "timeout"),
        "the fast module's requests failed: {:?}, {:?}",
        fast.errors,
        fast.last_error
    );
}
