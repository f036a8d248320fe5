//! The axis gauges of `/metrics` before the first NC job: what the NC held at start.

mod common;

use std::time::{Duration, Instant};

use common::metrics::{scrape, value};
use common::process::Gateway;

// Temperatures steady and the NC already holding values within the deadbands of what
// the model computes: no job is written, and the gauges show what the NC held at
// start, as /api/status does.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn axis_gauges_show_what_the_nc_held_at_start_before_any_job() {
    let dir = tempfile::tempdir().unwrap();
    let toml = common::config("hold", "", "")
        .replace("deadband_k0_mm = 0.00001", "deadband_k0_mm = 0.1")
        .replace(
            "deadband_tan_beta = 0.0000000001",
            "deadband_tan_beta = 0.001",
        );
    let (plant, path) =
        common::plant_and_file(dir.path(), &toml, "\n[metrics]\nbind = \"127.0.0.1:0\"\n").await;
    // The model gives about 0.04 mm and 5.75e-5 at the test's 30 and 25 degC.
    plant.nc["nc_x"].with_state(|a| {
        a.sd43900_mm = 0.03;
        a.sd43910 = 0.00005;
        a.sd43920_mm = 100.0;
    });
    let mut gw = Gateway::start(dir.path(), &path, &[]);
    let port = tokio::task::block_in_place(|| gw.metrics_port(10.0));
    // The status shows what the NC held once the gateway read it.
    tokio::task::block_in_place(|| {
        gw.wait_notify(20.0, "the NC's values read at start", |m| {
            m.contains("SD43900=0.0300mm")
        })
    });
    let series = |name: &str| format!("{name}{{axis=\"X\"}}");
    let deadline = Instant::now() + Duration::from_secs(20);
    let body = loop {
        let (body, _) =
            tokio::task::block_in_place(|| scrape(port, Duration::from_secs(2))).expect("scrape");
        if value(&body, &series("compgate_axis_sd43920_mm")).is_some() {
            break body;
        }
        assert!(
            Instant::now() < deadline,
            "no axis gauges 20 s after the status showed the NC's values:\n{body}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert_eq!(plant.nc["nc_x"].jobs_executed(), 0, "a job was written");
    assert_eq!(
        value(&body, &series("compgate_axis_sd43900_mm")),
        Some(0.03),
        "{body}"
    );
    assert_eq!(
        value(&body, &series("compgate_axis_sd43910")),
        Some(0.00005),
        "{body}"
    );
    assert_eq!(
        value(&body, &series("compgate_axis_sd43920_mm")),
        Some(100.0),
        "{body}"
    );
    assert!(tokio::task::block_in_place(|| gw.stop()));
    drop(plant);
}
