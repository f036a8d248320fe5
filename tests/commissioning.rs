//! What a commissioning engineer meets first (issue 23): a monitoring-only config
//! before the NC is connected, a silent device, ADC noise on the default filter, a
//! float in the wrong word order. Each test runs the real gateway against the
//! simulated plant on loopback.

mod common;

use std::time::Duration;

use common::metrics::{scrape, value};
use common::process::{assert_success, Gateway};
use rusqlite::Connection;

/// One TCP field device with two PT100 channels and nothing else: no NC module, no
/// axis. `device_extra` and `filter` go into the device and channel tables.
fn monitoring_config(device_extra: &str, filter: &str) -> String {
    let scaling = common::SCALING;
    format!(
        r#"
[gateway]
status_interval_s = 0.1

[devices.ain1]
transport = "tcp"
address = "127.0.0.1:0"
unit_id = 1
timeout_s = 0.2
connect_timeout_s = 0.5
poll_interval_s = 0.05
backoff_initial_s = 0.05
backoff_max_s = 0.2
{device_extra}

[channels.T_bed]
device = "ain1"
register = "input"
address = 0
data_type = "u16"
scaling = {scaling}
{filter}

[channels.T_screw]
device = "ain1"
register = "input"
address = 1
data_type = "u16"
scaling = {scaling}
{filter}

[sim]
seed = 3

[sim.channels.T_bed]
profile = "constant"
mean_degc = 30.0

[sim.channels.T_screw]
profile = "constant"
mean_degc = 25.0
"#
    )
}

// Trap 4: a config without `[nc_modules]` and `[axes]` used to be refused ("required
// key is missing"). It runs: the device is polled, the values filtered, recorded and
// served as metrics.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_monitoring_only_config_polls_filters_records_and_serves_metrics() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("rec.db");
    let extra = format!(
        "\n[recorder]\npath = {:?}\ncommit_interval_s = 0.2\n\n[metrics]\nbind = \"127.0.0.1:0\"\n",
        db.display().to_string()
    );
    let (_plant, path) =
        common::plant_and_file(dir.path(), &monitoring_config("", ""), &extra).await;
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| gw.wait_notify(10.0, "READY=1", |m| m.contains("READY=1")));
    let port = gw.metrics_port(1.0);

    let series = "compgate_channel_value_degc{channel=\"T_bed\"}";
    let mut last = None;
    for _ in 0..100 {
        let body = tokio::task::block_in_place(|| scrape(port, Duration::from_secs(2)))
            .map(|(body, _)| body)
            .unwrap_or_default();
        last = value(&body, series);
        if last.is_some_and(|v| (v - 30.0).abs() < 0.5) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let v = last.unwrap_or_else(|| panic!("no {series}\nlog:\n{}", gw.stderr_text()));
    assert!((v - 30.0).abs() < 0.5, "T_bed = {v} degC, expected 30");
    // Recording: wait for 40 rows (1 s of polling both channels at 20 Hz).
    let mut readings = 0;
    for _ in 0..100 {
        let conn = Connection::open(&db).unwrap();
        readings = compgate_service::record::counts(&conn).map_or(0, |c| c.0);
        if readings >= 40 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(tokio::task::block_in_place(|| gw.stop()));
    assert!(readings >= 40, "{readings} readings recorded");

    let conn = Connection::open(&db).unwrap();
    let (_, jobs, _nc) = compgate_service::record::counts(&conn).unwrap();
    assert_eq!(jobs, 0, "no NC, no job");
    let good: i64 = conn
        .query_row(
            "SELECT count(*) FROM readings r JOIN channels c ON c.id = r.channel \
             WHERE c.name = 'T_screw' AND quality = 0",
            [],
            |r| r.get(0),
        )
        .unwrap();
    assert!(good > 10, "{good} good T_screw readings recorded");
}

/// A monitoring config with a float channel `T_amb` the plant serves in word order
/// CDAB at 23.45 degC (no noise), plus a counts channel `T_bed`; a running plant for
/// it and a config file in `dir` that reads `T_amb` as ABCD, `extra` appended.
async fn plant_with_swapped_float(
    dir: &std::path::Path,
    extra: &str,
) -> (compgate::plant::Plant, std::path::PathBuf) {
    let float = r#"
[channels.T_amb]
device = "ain1"
register = "holding"
address = 1004
data_type = "f32"
byte_order = "CDAB"
scaling = { kind = "direct" }

[sim.channels.T_amb]
profile = "constant"
mean_degc = 23.45
"#;
    let text = monitoring_config("", "") + float;
    let (plant, path) = common::plant_and_file(dir, &text, extra).await;
    let written = std::fs::read_to_string(&path).expect("config file");
    assert_eq!(
        written.matches("byte_order = \"CDAB\"").count(),
        1,
        "{written}"
    );
    std::fs::write(
        &path,
        written.replace("byte_order = \"CDAB\"", "byte_order = \"ABCD\""),
    )
    .expect("config file written");
    (plant, path)
}

// Trap 2: a CDAB float configured as ABCD read -1.6e-23 degC with quality good, and an
// axis was written from it. It is bad now, and the log names the word order.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_float_in_the_wrong_word_order_is_bad_and_the_log_names_the_order() {
    let dir = tempfile::tempdir().unwrap();
    let metrics = "\n[metrics]\nbind = \"127.0.0.1:0\"\n";
    let (_plant, path) = plant_with_swapped_float(dir.path(), metrics).await;
    let gw = Gateway::start(dir.path(), &path, &[]);
    let port = tokio::task::block_in_place(|| gw.metrics_port(10.0));
    let line = tokio::task::block_in_place(|| gw.wait_log(10.0, "check `byte_order`"));
    assert!(
        line.contains("T_amb") && line.contains("as ABCD; as CDAB it would read 23.4"),
        "{line}"
    );
    let quality = "compgate_channel_quality{channel=\"T_amb\"}";
    let good = "compgate_channel_quality{channel=\"T_bed\"}";
    let mut seen = (None, None);
    for _ in 0..50 {
        let body = tokio::task::block_in_place(|| scrape(port, Duration::from_secs(2)))
            .map(|(body, _)| body)
            .unwrap_or_default();
        seen = (value(&body, quality), value(&body, good));
        if seen.0.is_some() && seen.1 == Some(0.0) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(seen, (Some(2.0), Some(0.0)), "T_amb bad, T_bed good");
    // Logged once, not once per poll.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let hints = gw.stderr_text().matches("check `byte_order`").count();
    assert_eq!(hints, 1, "{}", gw.stderr_text());
    println!("{line}");
}

// Trap 5: `address = 30013` passed `validate` and failed at run time with exception 2.
// `validate` still accepts it (a device may have that many registers) but warns with
// the likely 0-based address.
#[test]
fn validate_warns_about_a_1_based_address_and_names_the_0_based_one() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("plant.toml");
    // Port 0 is for the simulated plant only: `validate` checks for `run`.
    let text = monitoring_config("", "")
        .replacen("address = 1\n", "address = 30013\n", 1)
        .replace("127.0.0.1:0", "127.0.0.1:1");
    assert!(text.contains("address = 30013"));
    std::fs::write(&path, text).unwrap();
    let out = std::process::Command::new(common::process::BIN)
        .args(["validate", "--config"])
        .arg(&path)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    let file = path.display().to_string();
    assert!(
        err.contains(&format!(
            "warning: {file}: channels.T_screw.address: 30013 looks like"
        )),
        "{err}"
    );
    assert!(
        err.contains("input register 13") && err.contains("address = 12."),
        "{err}"
    );
}

// Trap 3: a silent device took blocks x (timeout + retry) to be noticed: each read
// block waited its full timeout and reconnected before the cycle counted as failed.
// Here the device is read in 3 blocks (counts, a CDAB float, an ABCD float) with
// timeout_s = 0.2, one retry and poll_interval_s = 0.05: a cycle used to take
// 3 x 2 x 0.2 = 1.2 s, so uncertain came after 1.2 s and bad after 3.6 s. With the
// cycle deadline D = max(poll_interval_s, timeout_s) = 0.2 s the documented bounds are
// P + D = 0.25 s to uncertain and P + 3 D = 0.65 s to bad (plus one status interval).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_device_is_bad_after_degrade_after_cycles_deadlines_not_blocks_x_timeouts() {
    use compgate_core::channel::{Quality, Reason};
    let floats = r#"
[channels.T_cdab]
device = "ain1"
register = "holding"
address = 1004
data_type = "f32"
byte_order = "CDAB"
scaling = { kind = "direct" }

[channels.T_abcd]
device = "ain1"
register = "holding"
address = 2006
data_type = "f32"
byte_order = "ABCD"
scaling = { kind = "direct" }
"#;
    let mut rig = common::start(&(monitoring_config("", "") + floats)).await;
    let quality =
        |s: &compgate_gateway::runtime::Status| common::Rig::channel(s, "T_bed").reading.quality;
    rig.wait_for(10.0, "all good", |s| {
        s.channels
            .iter()
            .all(|c| c.reading.quality == Quality::Good)
    })
    .await;
    let started = std::time::Instant::now();
    rig.plant.field["ain1"].set_comm_fault(compgate_plc::field::CommFault::Silent);
    rig.wait_for(5.0, "uncertain", |s| {
        quality(s) == Quality::Uncertain(Reason::Comm)
    })
    .await;
    let to_uncertain = started.elapsed();
    let s = rig
        .wait_for(10.0, "bad", |s| {
            quality(s) == Quality::Bad(Reason::DeviceDegraded)
        })
        .await;
    let to_bad = started.elapsed();
    let d = &s.devices[0];
    println!(
        "3 blocks, D = 0.2 s: uncertain after {:.3} s, bad after {:.3} s, last cycle {:.3} s, error: {:?}",
        to_uncertain.as_secs_f64(),
        to_bad.as_secs_f64(),
        d.last_cycle.as_secs_f64(),
        d.last_error
    );
    assert!(
        d.last_cycle < Duration::from_millis(300),
        "{:?}",
        d.last_cycle
    );
    assert!(
        to_uncertain < Duration::from_millis(700),
        "{to_uncertain:?}"
    );
    assert!(to_bad < Duration::from_millis(1200), "{to_bad:?}");
    // Every channel of the device went bad together, and it recovers.
    assert!(s
        .channels
        .iter()
        .all(|c| c.reading.quality == Quality::Bad(Reason::DeviceDegraded)));
    rig.plant.field["ain1"].set_comm_fault(compgate_plc::field::CommFault::None);
    rig.wait_for(10.0, "good again", |s| {
        s.channels
            .iter()
            .all(|c| c.reading.quality == Quality::Good)
    })
    .await;
    rig.stop().await;
}

/// `compgate probe ARGS --config CONFIG`, off the runtime's threads.
fn probe(args: &[&str], config: &std::path::Path) -> std::process::Output {
    tokio::task::block_in_place(|| {
        std::process::Command::new(common::process::BIN)
            .arg("probe")
            .args(args)
            .arg("--config")
            .arg(config)
            .output()
            .expect("compgate probe runs")
    })
}

// `--device D --channel C` with C on another device would probe nothing: refused,
// naming where C is, before anything is polled.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn probe_refuses_a_channel_that_is_not_on_the_device_given() {
    let dir = tempfile::tempdir().unwrap();
    let spare = r#"
[devices.spare]
transport = "tcp"
address = "127.0.0.1:0"
unit_id = 2

[channels.T_spare]
device = "spare"
register = "input"
address = 0
data_type = "u16"
scaling = { kind = "direct" }
"#;
    let path = dir.path().join("probe.toml");
    // Port 0 is refused outside the simulated plant; nothing is polled here.
    let text = (monitoring_config("", "") + spare).replace("127.0.0.1:0", "127.0.0.1:1");
    std::fs::write(&path, text).unwrap();
    let out = probe(&["--device", "spare", "--channel", "T_bed"], &path);
    let text = String::from_utf8_lossy(&out.stdout);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{text}{err}");
    assert!(
        err.contains("--channel T_bed is on device `ain1`, not on --device spare"),
        "{err}"
    );
    assert!(!text.contains("device "), "{text}");
}

// `compgate probe` against the plant with the CDAB float misconfigured as ABCD: it
// shows the registers, names CDAB as the plausible order, and exits non-zero because
// the channel is bad; the counts channel shows its mA and degC.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn probe_names_the_word_order_of_a_misconfigured_float_and_exits_1() {
    let dir = tempfile::tempdir().unwrap();
    let (plant, path) = plant_with_swapped_float(dir.path(), "").await;
    let out = probe(&[], &path);
    let text = String::from_utf8_lossy(&out.stdout);
    let err = String::from_utf8_lossy(&out.stderr);
    println!("{text}{err}");
    assert_eq!(out.status.code(), Some(1), "{text}{err}");
    assert!(err.contains("1 channel bad: T_amb"), "{err}");
    let amb = text
        .split("  T_amb:")
        .nth(1)
        .unwrap_or_else(|| panic!("no T_amb section:\n{text}"));
    let amb = amb.split("\n  T_").next().unwrap_or_default();
    assert!(amb.contains("holding register 1004, f32 ABCD"), "{amb}");
    // About 23.44 degC after the ADC (0x41BB....), published as f32 CDAB: the low
    // word first.
    assert!(
        amb.contains("registers  0x") && amb.contains(" 0x41BB\n"),
        "{amb}"
    );
    let marked: Vec<&str> = amb.lines().filter(|l| l.contains("<- plausible")).collect();
    assert_eq!(marked.len(), 1, "{amb}");
    assert!(
        marked[0].trim_start().starts_with("as CDAB") && marked[0].contains("23.4"),
        "{amb}"
    );
    assert!(amb.contains("set byte_order = \"CDAB\""), "{amb}");
    assert!(amb.contains("quality    bad"), "{amb}");
    // The counts channel: good, with its loop current.
    let bed = text.split("  T_bed:").nth(1).unwrap_or_default();
    let bed = bed.split("\n  T_").next().unwrap_or_default();
    assert!(
        bed.contains("quality    good") && bed.contains(" mA"),
        "{bed}"
    );
    assert!(bed.contains("30.0") || bed.contains("29.9"), "{bed}");

    // One channel, configured right: exit 0.
    let fixed = dir.path().join("fixed.toml");
    let text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("byte_order = \"ABCD\"", "byte_order = \"CDAB\"");
    std::fs::write(&fixed, text).unwrap();
    let out = probe(&["--channel", "T_amb"], &fixed);
    let text = assert_success(&out);
    assert!(
        !text.contains("T_bed") && text.contains("quality    good"),
        "{text}"
    );

    // A silent device: the first read times out, the others are not tried; exit 1.
    plant.field["ain1"].set_comm_fault(compgate_plc::field::CommFault::Silent);
    let out = probe(&[], &fixed);
    let text = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{text}");
    assert!(text.contains("error      no reply within 200ms"), "{text}");
    assert_eq!(
        text.matches("not read, the device did not answer").count(),
        2,
        "{text}"
    );
}

// Field review: an RTU port the gateway's user may not open said "Permission denied"
// and not what to do. Root opens every file, so the probe runs as `nobody` here (and
// is skipped when the test does not run as root, which cannot change its user).
#[test]
fn probe_of_a_serial_port_the_user_may_not_open_names_the_group_it_needs() {
    use std::os::unix::fs::{MetadataExt, PermissionsExt};
    use std::os::unix::process::CommandExt;
    if std::fs::metadata("/proc/self").map(|m| m.uid()).ok() != Some(0) {
        println!("skipped: only root can run the probe as another user");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
    // A "tty" only its owner may open: the open fails before any ioctl.
    let tty = dir.path().join("ttyS9");
    std::fs::write(&tty, b"").unwrap();
    std::fs::set_permissions(&tty, std::fs::Permissions::from_mode(0o600)).unwrap();
    let path = dir.path().join("rtu.toml");
    let text = format!(
        "[devices.ain]\ntransport = \"rtu\"\nserial_path = \"{}\"\nunit_id = 1\n\
         timeout_s = 0.1\nretries = 0\n\
         [channels.T]\ndevice = \"ain\"\nregister = \"input\"\naddress = 0\n\
         data_type = \"u16\"\nscaling = {{ kind = \"direct\", gain = 0.1 }}\n",
        tty.display()
    );
    std::fs::write(&path, text).unwrap();
    std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o644)).unwrap();
    let out = std::process::Command::new(common::process::BIN)
        .args(["probe", "--config"])
        .arg(&path)
        .uid(65534)
        .gid(65534)
        .output()
        .expect("compgate probe runs");
    let text = String::from_utf8_lossy(&out.stdout);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{text}{err}");
    assert!(
        text.contains(&format!(
            "{}: permission denied: the gateway's user needs the tty's group (usually dialout)",
            tty.display()
        )),
        "{text}{err}"
    );
}

/// CRC-16/MODBUS, as it goes on the wire (low byte first).
fn crc16(bytes: &[u8]) -> [u8; 2] {
    crc::Crc::<u16>::new(&crc::CRC_16_MODBUS)
        .checksum(bytes)
        .to_le_bytes()
}

// Field review: `compgate probe` hinted only at a 32-bit word order. A module counting
// 0.1 degC read with gain 1 (234 -> 234 degC), an i16 read as u16 (-5.0 degC as 65486
// counts), a transmitter register of zeros (NE43 low, or no transmitter there) and a
// silent RTU unit got no hint; the RTU header did not show parity and stop bits. An RTU
// line on a pty, served by this test: unit 1 answers registers 0, 1, 2 with 234,
// 0xFFCE, 0; unit 2 never answers.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn probe_hints_at_tenths_a_signed_type_zeros_and_a_silent_rtu_unit() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let (mut master, _slave, pty) = compgate_plc::field::pty_pair().unwrap();
    let slave = tokio::spawn(async move {
        let mut req = [0u8; 8];
        while master.read_exact(&mut req).await.is_ok() {
            if req[0] != 1 || crc16(&req[..6]) != [req[6], req[7]] {
                continue;
            }
            let start = u16::from_be_bytes([req[2], req[3]]);
            let value = [234u16, 0xFFCE, 0][usize::from(start.min(2))];
            let mut reply = vec![1, req[1], 2];
            reply.extend_from_slice(&value.to_be_bytes());
            let crc = crc16(&reply);
            reply.extend_from_slice(&crc);
            if master.write_all(&reply).await.is_err() {
                break;
            }
        }
    });
    let device = |name: &str, unit: u8| {
        format!(
            "[devices.{name}]\ntransport = \"rtu\"\nserial_path = \"{pty}\"\nbaud = 19200\n\
             parity = \"even\"\nunit_id = {unit}\ntimeout_s = 0.2\n"
        )
    };
    let channel = |name: &str, dev: &str, address: u16, scaling: &str| {
        format!(
            "[channels.{name}]\ndevice = \"{dev}\"\nregister = \"holding\"\n\
             address = {address}\ndata_type = \"u16\"\nscaling = {scaling}\n"
        )
    };
    let text = [
        device("ain", 1),
        device("off", 2),
        channel("T_a_tenths", "ain", 0, "{ kind = \"direct\", gain = 1.0 }"),
        channel("T_b_signed", "ain", 1, "{ kind = \"direct\", gain = 0.1 }"),
        channel("T_c_zero", "ain", 2, common::SCALING),
        channel("T_d_off", "off", 0, "{ kind = \"direct\", gain = 0.1 }"),
    ]
    .concat();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rtu.toml");
    std::fs::write(&path, text).unwrap();
    let out = probe(&[], &path);
    slave.abort();
    let text = String::from_utf8_lossy(&out.stdout);
    let err = String::from_utf8_lossy(&out.stderr);
    println!("{text}{err}");
    assert_eq!(out.status.code(), Some(1), "{text}{err}");
    let section = |name: &str| {
        let s = text
            .split(&format!("  {name}:"))
            .nth(1)
            .unwrap_or_else(|| panic!("no {name} section:\n{text}"));
        s.split("\n  T_").next().unwrap_or_default().to_string()
    };
    assert!(
        text.contains(&format!(
            "device ain: rtu://{pty}@19200, 8E1 (parity even, 1 stop bit), unit 1\n"
        )),
        "{text}"
    );
    let a = section("T_a_tenths");
    assert!(a.contains("quality    bad (out of range)"), "{a}");
    assert!(
        a.lines()
            .any(|l| l
                == "    hint       as 0.1 degC counts it reads 23.4 degC: set scaling gain = 0.1"),
        "{a}"
    );
    let b = section("T_b_signed");
    assert!(
        b.lines()
            .any(|l| l == "    hint       as i16 it reads -5.0 degC: set data_type = \"i16\""),
        "{b}"
    );
    let c = section("T_c_zero");
    assert!(
        c.lines().any(|l| l
            == "    quality    bad (NE43 low) (a register that reads 0 may also be the wrong \
                address or register table)"),
        "{c}"
    );
    // Two channels and the silent unit; the zeros are told on the quality line.
    assert_eq!(text.matches("    hint ").count(), 3, "{text}");
    let d = section("T_d_off");
    assert!(
        d.contains("error      no reply within 200ms")
            && d.lines().any(|l| l
                == "    hint       no reply: check unit_id, baud and parity against the \
                    module's switches, the A/B wiring, termination and the module's power"),
        "{d}"
    );
}
