//! What the journal (the gateway's log) records with real processes: under systemd
//! the per-update status line is off, so the log is the operator's running record.

// Test helpers: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

mod common;

use std::time::Duration;

use common::process::Gateway;
use common::proxy::Proxy;
use compgate_plc::field::SensorFault;

/// The log lines so far that contain `needle`.
fn count(gw: &Gateway, needle: &str) -> usize {
    gw.stderr
        .lock()
        .unwrap()
        .iter()
        .filter(|l| l.contains(needle))
        .count()
}

/// Asserts that exactly one log line contains `needle`; that line.
fn once(gw: &Gateway, needle: &str) -> String {
    let n = count(gw, needle);
    assert_eq!(n, 1, "{n} lines with `{needle}`\n{}", gw.stderr_text());
    gw.wait_log(1.0, needle)
}

// An open sensor (NE43 low) is logged once when it happens, naming the channel, its
// device and the reason, and so is the axis' change to ramp to zero, naming the input;
// its recovery likewise. Not once per sample: the poll is 50 ms, the update 100 ms.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sensor_fault_and_its_recovery_are_logged_once() {
    let dir = tempfile::tempdir().unwrap();
    let toml = common::config("ramp_to_zero", "", "");
    let (plant, path) = common::plant_and_file(dir.path(), &toml, "").await;
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| {
        gw.wait_notify(10.0, "a verified write", |m| m.contains("jobs 1 ok"))
    });
    assert_eq!(count(&gw, "channel T_bed"), 0, "{}", gw.stderr_text());
    assert_eq!(count(&gw, "axis X"), 0, "{}", gw.stderr_text());

    let field = plant.field["ain1"].clone();
    let t_bed = plant.transmitter["T_bed"];
    field.set_sensor_fault(t_bed, SensorFault::Open).unwrap();
    tokio::task::block_in_place(|| {
        gw.wait_log(5.0, "channel T_bed bad");
        gw.wait_log(5.0, "axis X no longer follows its model");
    });
    // Ramped to zero and holding there: many samples and decisions later.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let line = once(&gw, "channel T_bed bad");
    assert!(line.contains("WARN"), "{line}");
    assert!(line.contains("NE43 low"), "{line}");
    assert!(line.contains("device=\"ain1\""), "{line}");
    let line = once(&gw, "axis X no longer follows its model");
    assert!(line.contains("WARN"), "{line}");
    assert!(line.contains("ramp to zero: bad input T_bed"), "{line}");
    assert_eq!(plant.nc["nc_x"].state().sd43900_mm, 0.0);

    field.set_sensor_fault(t_bed, SensorFault::None).unwrap();
    tokio::task::block_in_place(|| {
        gw.wait_log(5.0, "channel T_bed usable again");
        gw.wait_log(5.0, "axis X follows its model again");
    });
    tokio::time::sleep(Duration::from_millis(1000)).await;
    let line = once(&gw, "channel T_bed usable again");
    assert!(line.contains("INFO"), "{line}");
    assert!(line.contains("device=\"ain1\""), "{line}");
    let line = once(&gw, "axis X follows its model again");
    assert!(line.contains("INFO"), "{line}");
    // Nothing more of either, and nothing of the channels that stayed good.
    assert_eq!(count(&gw, "channel T_bed"), 2, "{}", gw.stderr_text());
    assert_eq!(count(&gw, "axis X "), 2, "{}", gw.stderr_text());
    assert_eq!(count(&gw, "channel T_screw"), 0, "{}", gw.stderr_text());
    assert!(tokio::task::block_in_place(|| gw.stop()));
    drop(plant);
}

// An axis that writes only SD43910 and SD43920 (`nc_write`): the job line names those
// and their values, not the SD43900 of the parameter set, which was not written.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_job_line_names_only_the_variables_written() {
    let dir = tempfile::tempdir().unwrap();
    let base = common::config("hold", "", "");
    let k0 = base.lines().find(|l| l.starts_with("k0 = ")).unwrap();
    // The NC runs the position-dependent part only, as the axis expects.
    let toml = base
        .replace(&format!("{k0}\n"), "")
        .replace(
            "md32750 = 3\np0_mm",
            "md32750 = 2\nnc_write = [\"sd43910\", \"sd43920\"]\np0_mm",
        )
        .replace(
            "referenced = true\nmd32750 = 3",
            "referenced = true\nmd32750 = 2",
        );
    assert!(toml.contains("nc_write"), "{toml}");
    assert!(!toml.contains("md32750 = 3"), "{toml}");
    let (plant, path) = common::plant_and_file(dir.path(), &toml, "").await;
    let gw = Gateway::start(dir.path(), &path, &[]);
    let line = tokio::task::block_in_place(|| gw.wait_log(10.0, "NC job done"));
    // Two axes on one target must be told apart: the line names the axis.
    assert!(line.contains("axis=X"), "{line}");
    assert!(line.contains("target_name=nc_x"), "{line}");
    assert!(line.contains("written=\"SD43910="), "{line}");
    assert!(line.contains(", SD43920=100 mm\""), "{line}");
    assert!(!line.to_lowercase().contains("sd43900"), "{line}");
    drop(gw);
    drop(plant);
}

// A wrong MD32750 holds the axis: one WARN when it is seen, one INFO when it matches
// again and the writes resume. An axis not referenced is warned of on its own line,
// not hidden behind the MD32750 one.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_md32750_and_an_unreferenced_axis_are_logged_once_per_change() {
    let dir = tempfile::tempdir().unwrap();
    let toml = common::config("hold", "", "").replace(
        "referenced = true\nmd32750 = 3",
        "referenced = false\nmd32750 = 1",
    );
    let (plant, path) = common::plant_and_file(dir.path(), &toml, "").await;
    let gw = Gateway::start(dir.path(), &path, &[]);
    let nc = plant.nc["nc_x"].clone();
    tokio::task::block_in_place(|| {
        gw.wait_log(10.0, "MD32750 is 1 on the NC");
        gw.wait_log(10.0, "axis X is not referenced");
    });
    // Several snapshots (one a second) and many updates later: no job, no more lines.
    tokio::time::sleep(Duration::from_millis(2500)).await;
    assert_eq!(nc.jobs_executed(), 0);
    let line = once(&gw, "MD32750 is 1 on the NC");
    assert!(line.contains("WARN"), "{line}");
    assert!(line.contains("the axis holds"), "{line}");
    assert!(once(&gw, "axis X is not referenced").contains("WARN"));

    nc.with_state(|a| a.md32750 = 3);
    tokio::task::block_in_place(|| {
        gw.wait_log(10.0, "matches the config again");
        gw.wait_log(10.0, "NC job done");
    });
    assert!(once(&gw, "matches the config again").contains("INFO"));
    nc.with_state(|a| a.referenced = true);
    let line = tokio::task::block_in_place(|| gw.wait_log(10.0, "axis X is referenced again"));
    assert!(line.contains("INFO"), "{line}");
    assert_eq!(count(&gw, "MD32750 is 1 on the NC"), 1);
    assert_eq!(count(&gw, "axis X is not referenced"), 1);
    drop(gw);
    drop(plant);
}

// A model asking for more than `max_abs_k0_mm` gets the limit: the journal says so
// once, with the model's value and the key, the metric is 1 while it lasts, and the
// return within the limit is logged once too. It used to be silent: the status read
// "write (limited)", as for a step limit, then "within deadband".
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_model_held_at_its_absolute_limit_is_logged_and_exported() {
    let dir = tempfile::tempdir().unwrap();
    // The model's K0: 0.004 mm/K x (30 - 20) K = 0.04 mm.
    let toml =
        common::config("hold", "", "").replace("max_abs_k0_mm = 0.5", "max_abs_k0_mm = 0.015");
    let (plant, path) =
        common::plant_and_file(dir.path(), &toml, "\n[metrics]\nbind = \"127.0.0.1:0\"\n").await;
    let gw = Gateway::start(dir.path(), &path, &[]);
    let port = tokio::task::block_in_place(|| gw.metrics_port(10.0));
    let nc = plant.nc["nc_x"].clone();
    tokio::task::block_in_place(|| gw.wait_log(10.0, "axis X is held at its limit"));
    // Many updates (100 ms) later, within the deadband at the limit: no more lines.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert_eq!(nc.state().sd43900_mm, 0.015);
    let line = once(&gw, "axis X is held at its limit");
    assert!(line.contains("WARN"), "{line}");
    assert!(line.contains("at the limit (the model's K0 0.04"), "{line}");
    assert!(
        line.contains("mm is beyond max_abs_k0_mm = 0.015 mm)"),
        "{line}"
    );
    let at_limit = || {
        let (text, _) = common::metrics::scrape(port, Duration::from_secs(2)).unwrap();
        common::metrics::value(&text, "compgate_axis_at_limit{axis=\"X\"}")
    };
    assert_eq!(tokio::task::block_in_place(at_limit), Some(1.0));

    // T_bed at 22 degC: K0 0.008 mm, within the limit.
    let t_bed = plant.transmitter["T_bed"];
    plant.field["ain1"]
        .set_temperature_override(t_bed, Some(22.0))
        .unwrap();
    tokio::task::block_in_place(|| gw.wait_log(10.0, "axis X follows its model again"));
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert!((nc.state().sd43900_mm - 0.008).abs() < 0.0005);
    assert!(once(&gw, "axis X follows its model again").contains("INFO"));
    assert_eq!(count(&gw, "axis X "), 2, "{}", gw.stderr_text());
    assert_eq!(tokio::task::block_in_place(at_limit), Some(0.0));
    drop(gw);
    drop(plant);
}

// A model applied beyond the temperatures it was fitted over extrapolates: with a
// summer's 35 degC after a winter's fit it wrote its values without a word (review V).
// The journal says so once, with the channel and the range, the metric is 1 while it
// lasts, and the return within the range is logged once too.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_model_applied_beyond_its_fitted_temperatures_is_logged_and_exported() {
    let dir = tempfile::tempdir().unwrap();
    // T_bed reads 30 degC, 6 K above its range, and T_screw 25 degC, 3 K above: both
    // are named, farthest first.
    let toml = common::config("hold", "", "").replace(
        "tan_beta = {",
        "fitted_degc = { T_bed = [18.0, 24.0], T_screw = [18.0, 22.0] }\ntan_beta = {",
    );
    let (plant, path) =
        common::plant_and_file(dir.path(), &toml, "\n[metrics]\nbind = \"127.0.0.1:0\"\n").await;
    let gw = Gateway::start(dir.path(), &path, &[]);
    let port = tokio::task::block_in_place(|| gw.metrics_port(10.0));
    let warned = "axis X: T_bed reads 30.0 degC, 6.0 K above the 18.0..24.0 degC; T_screw reads \
                  25.0 degC, 3.0 K above the 18.0..22.0 degC the model was fitted over";
    tokio::task::block_in_place(|| gw.wait_log(10.0, warned));
    // Many updates (100 ms) later: no more lines, and the axis still compensates.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert!(once(&gw, warned).contains("WARN"));
    let nc = plant.nc["nc_x"].clone();
    assert!((nc.state().sd43900_mm - 0.04).abs() < 0.0005);
    let outside = || {
        let (text, _) = common::metrics::scrape(port, Duration::from_secs(2)).unwrap();
        common::metrics::value(&text, "compgate_axis_outside_fit{axis=\"X\"}")
    };
    assert_eq!(tokio::task::block_in_place(outside), Some(1.0));
    let back = "axis X: its inputs are within the temperatures the model was fitted over again";
    // The flag holds through what says nothing of the temperatures (review X): T_screw
    // back within (23.4 degC: 1.4 K above, within the margin once flagged less the
    // hysteresis) and T_bed's sensor broken, then a reload of a tuning key. Each had
    // cleared it ("within ... again", the metric at 0), and the WARN came again.
    let field = &plant.field["ain1"];
    let (t_bed, t_screw) = (plant.transmitter["T_bed"], plant.transmitter["T_screw"]);
    field.set_temperature_override(t_screw, Some(23.4)).unwrap();
    field.set_sensor_fault(t_bed, SensorFault::Open).unwrap();
    tokio::task::block_in_place(|| gw.wait_log(10.0, "channel T_bed bad"));
    let text = std::fs::read_to_string(&path).unwrap();
    std::fs::write(
        &path,
        text.replace("deadband_k0_mm = 0.00001", "deadband_k0_mm = 0.00002"),
    )
    .unwrap();
    gw.signal("HUP");
    tokio::task::block_in_place(|| gw.wait_log(10.0, "configuration reloaded"));
    for _ in 0..10 {
        assert_eq!(tokio::task::block_in_place(outside), Some(1.0));
        tokio::time::sleep(Duration::from_millis(150)).await;
    }
    assert_eq!(count(&gw, back), 0, "{}", gw.stderr_text());
    assert_eq!(count(&gw, "model was fitted over: it extrapolates"), 1);

    // T_bed mended at 25.4 degC: within the margin, and the flag clears, once.
    field.set_sensor_fault(t_bed, SensorFault::None).unwrap();
    field.set_temperature_override(t_bed, Some(25.4)).unwrap();
    tokio::task::block_in_place(|| gw.wait_log(10.0, back));
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert!(once(&gw, back).contains("INFO"));
    assert_eq!(tokio::task::block_in_place(outside), Some(0.0));
    drop(gw);
    drop(plant);
}

// A reload keeps what the journal was told of each axis: the axis held while a reload
// had pointed its device at a dead port, and the reload back says it follows its
// model again. The journal's last word used to be the hold: the reload started the
// axis' log afresh, as if it had always followed its model.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reload_that_ends_a_hold_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), "").await;
    let good = std::fs::read_to_string(&path).unwrap();
    let device = good.find("[devices.ain1]").unwrap();
    let start = device + good[device..].find("address = \"").unwrap() + "address = \"".len();
    let end = start + good[start..].find('"').unwrap();
    let dead = format!("127.0.0.1:{}", common::free_port());
    let bad = format!("{}{dead}{}", &good[..start], &good[end..]);
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| {
        gw.wait_notify(10.0, "a verified write", |m| m.contains("jobs 1 ok"))
    });

    std::fs::write(&path, &bad).unwrap();
    gw.signal("HUP");
    let line = tokio::task::block_in_place(|| {
        gw.wait_log(10.0, "axis X no longer follows its model");
        gw.wait_log(10.0, "device link down")
    });
    // Named with where it is: a timeout's error says no address.
    assert!(line.contains(&format!("link=tcp://{dead}")), "{line}");
    std::fs::write(&path, &good).unwrap();
    gw.signal("HUP");
    let line = tokio::task::block_in_place(|| gw.wait_log(10.0, "axis X follows its model again"));
    assert!(line.contains("INFO"), "{line}");
    assert_eq!(count(&gw, "axis X "), 2, "{}", gw.stderr_text());
    assert!(tokio::task::block_in_place(|| gw.stop()));
    drop(plant);
}

// An NC back from an outage without the compensation it confirmed (it restarted) is
// told at WARN with both values: it runs uncompensated until the steps catch up. It
// was an INFO like any reconnect. One back with its values stays an INFO. The
// unreachable line names the target's address (a timeout's error does not).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_nc_back_without_its_values_is_a_warning() {
    let dir = tempfile::tempdir().unwrap();
    let (plant, path) =
        common::plant_and_file(dir.path(), &common::config("hold", "", ""), "").await;
    let nc_address = plant.config.nc_modules["nc_x"].address.clone();
    let proxy = Proxy::start(nc_address.clone()).await;
    let text = std::fs::read_to_string(&path).unwrap();
    std::fs::write(&path, text.replace(&nc_address, &proxy.addr.to_string())).unwrap();
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    tokio::task::block_in_place(|| {
        gw.wait_notify(10.0, "a verified write", |m| m.contains("jobs 1 ok"))
    });
    let nc = plant.nc["nc_x"].clone();

    proxy.cut();
    let line = tokio::task::block_in_place(|| gw.wait_log(10.0, "NC target unreachable"));
    assert!(line.contains(&format!("address={}", proxy.addr)), "{line}");
    proxy.restore();
    let line = tokio::task::block_in_place(|| gw.wait_log(10.0, "read again after the outage"));
    assert!(line.contains("INFO"), "{line}");

    proxy.cut();
    // Two lines per 10 s at most: the second outage may wait for the next window.
    tokio::task::block_in_place(|| gw.wait_log_nth(20.0, "NC target unreachable", 2));
    nc.with_state(|a| a.sd43900_mm = 0.0);
    proxy.restore();
    let line = tokio::task::block_in_place(|| {
        gw.wait_log(10.0, "the NC holds other values than it confirmed")
    });
    assert!(line.contains("WARN"), "{line}");
    assert!(
        line.contains("sd43900_mm=0.0") && line.contains("confirmed_sd43900_mm=0.04"),
        "{line}"
    );
    assert_eq!(count(&gw, "read again after the outage"), 1);
    assert!(tokio::task::block_in_place(|| gw.stop()));
    drop(proxy);
    drop(plant);
}
