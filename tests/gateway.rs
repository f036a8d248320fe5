//! The full chain over real loopback sockets and ptys: simulated transmitters ->
//! Modbus -> channel processing -> thermal model -> FB3 job -> the value the NC applies.
//! Then one test per field fault, each asserting what the gateway does about it.

mod common;

use std::time::Duration;

use common::{config, start, Rig, COUNT_DEGC};
use compgate_core::channel::{Quality, Reason};
use compgate_ncproto::JobStatus;
use compgate_plc::field::{CommFault, SensorFault};
use compgate_plc::nc::JobFault;
use tokio_modbus::ExceptionCode;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn full_chain_tcp_transmitters_to_applied_nc_compensation() {
    let mut rig = start(&config("hold", "", "")).await;
    let s = rig
        .wait_for(10.0, "a verified job and the NC applying it", |s| {
            s.axes[0].jobs_ok >= 1
                && s.axes[0].nc.is_some_and(|nc| {
                    nc.sd43900_mm != 0.0
                        && nc
                            .applied_comp_mm
                            .zip(nc.target_comp_mm)
                            .is_some_and(|(a, t)| (a - t).abs() < 1e-12)
                })
        })
        .await;

    // Temperatures read through the 12-bit ADC within one count of the truth.
    let t_bed = Rig::value(&s, "T_bed");
    let t_screw = Rig::value(&s, "T_screw");
    assert!((t_bed - 30.0).abs() <= COUNT_DEGC, "T_bed {t_bed}");
    assert!((t_screw - 25.0).abs() <= COUNT_DEGC, "T_screw {t_screw}");
    assert!((Rig::value(&s, "T_col") - 60.0).abs() <= COUNT_DEGC);
    assert_eq!(Rig::quality(&s, "T_bed"), Quality::Good);

    // What the NC holds is the model evaluated on those readings, bit for bit through
    // the f64 job encoding.
    let nc = rig.plant.nc["nc_x"].state();
    let k0 = 0.004 * (t_bed - 20.0);
    let tan = 0.0000115 * (t_screw - 20.0);
    let written = s.axes[0].written.expect("written");
    assert!(
        (nc.sd43900_mm - k0).abs() < 1e-12,
        "SD43900 {} vs {k0}",
        nc.sd43900_mm
    );
    assert!(
        (nc.sd43910 - tan).abs() < 1e-15,
        "SD43910 {} vs {tan}",
        nc.sd43910
    );
    assert_eq!(nc.sd43920_mm, 100.0);
    assert_eq!(written.k0_mm.to_bits(), nc.sd43900_mm.to_bits());

    // The NC applies dKx = K0 + tan(beta) * (Px - P0) at Px = 500 mm, MD32750 = 3.
    let expect = k0 + tan * (500.0 - 100.0);
    assert!(
        (nc.applied_comp_mm - expect).abs() < 1e-12,
        "applied {} vs {expect}",
        nc.applied_comp_mm
    );
    assert!((expect - 0.063).abs() < 0.001, "sanity: {expect}");

    // A temperature change reaches the NC.
    let field = rig.plant.field["ain1"].clone();
    field.set_temperature_override(0, Some(35.0)).unwrap();
    rig.wait_for(10.0, "SD43900 follows T_bed to 35 degC", |s| {
        s.axes[0]
            .written
            .is_some_and(|p| (p.k0_mm - 0.06).abs() <= 0.004 * COUNT_DEGC)
    })
    .await;
    let fin = rig.stop().await;
    assert!(
        fin.axes[0].jobs_failed == 0,
        "{:?}",
        fin.axes[0].last_job_error
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn full_chain_over_modbus_rtu_on_a_pty_pair() {
    let toml = config("hold", "", "")
        .replace(
            "transport = \"tcp\"\naddress = \"127.0.0.1:0\"",
            "transport = \"rtu\"\nserial_path = \"/dev/compgate-test-rtu\"\nbaud = 115200\nparity = \"even\"\nstop_bits = 1",
        )
        .replace("connect_timeout_s = 0.5\n", "")
        .replace("unit_id = 1\ntimeout_s = 0.2", "unit_id = 9\ntimeout_s = 0.3");
    let mut rig = start(&toml).await;
    let path = rig.plant.config.devices["ain1"]
        .rtu()
        .map(|d| d.serial_path.clone())
        .unwrap();
    assert!(path.starts_with("/dev/pts/"), "served on a pty: {path}");
    let s = rig
        .wait_for(15.0, "a verified job from RTU readings", |s| {
            s.axes[0].jobs_ok >= 1
        })
        .await;
    assert!((Rig::value(&s, "T_bed") - 30.0).abs() <= COUNT_DEGC);
    assert!((Rig::value(&s, "T_col") - 60.0).abs() <= COUNT_DEGC);
    let nc = rig.plant.nc["nc_x"].state();
    assert!((nc.sd43900_mm - 0.004 * (Rig::value(&s, "T_bed") - 20.0)).abs() < 1e-12);
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn timeout_holds_uncertain_then_bad_and_holds_compensation() {
    let mut rig = start(&config("hold", "", "")).await;
    rig.wait_for(10.0, "first job", |s| s.axes[0].jobs_ok >= 1)
        .await;
    let jobs_before = rig.plant.nc["nc_x"].jobs_executed();
    let sd_before = rig.plant.nc["nc_x"].state().sd43900_mm;

    let field = rig.plant.field["ain1"].clone();
    field.set_comm_fault(CommFault::Silent);
    // Meanwhile the temperature moves: the gateway must not follow what it cannot read.
    field.set_temperature_override(0, Some(45.0)).unwrap();
    let s = rig
        .wait_for(
            10.0,
            "channels bad after degrade_after_cycles timeouts",
            |s| Rig::quality(s, "T_bed") == Quality::Bad(Reason::DeviceDegraded),
        )
        .await;
    assert!(
        s.devices[0].errors.get("timeout").copied().unwrap_or(0) >= 3,
        "{:?}",
        s.devices[0].errors
    );
    // The held value is the last good one.
    assert!((Rig::value(&s, "T_bed") - 30.0).abs() <= COUNT_DEGC);
    let s = rig
        .wait_for(5.0, "axis holds", |s| {
            s.axes[0].decision.starts_with("hold: bad input")
        })
        .await;
    assert!(
        s.axes[0].decision.contains("T_bed"),
        "{}",
        s.axes[0].decision
    );
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(
        rig.plant.nc["nc_x"].jobs_executed(),
        jobs_before,
        "no job while inputs are bad"
    );
    assert_eq!(rig.plant.nc["nc_x"].state().sd43900_mm, sd_before);

    field.set_comm_fault(CommFault::None);
    rig.wait_for(10.0, "recovered and following 45 degC", |s| {
        Rig::quality(s, "T_bed") == Quality::Good
            && s.axes[0]
                .written
                .is_some_and(|p| (p.k0_mm - 0.1).abs() <= 0.004 * COUNT_DEGC)
    })
    .await;
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn exception_is_not_a_transport_fault() {
    let mut rig = start(&config("hold", "", "")).await;
    let s = rig
        .wait_for(10.0, "polling", |s| s.devices[0].cycles >= 3)
        .await;
    let connects = s.devices[0].connects;
    assert_eq!(connects, 1);
    let field = rig.plant.field["ain1"].clone();
    field.set_comm_fault(CommFault::Exception(ExceptionCode::ServerDeviceBusy));
    let s = rig
        .wait_for(10.0, "exception leads to degraded channels", |s| {
            Rig::quality(s, "T_screw") == Quality::Bad(Reason::DeviceDegraded)
                && s.devices[0].errors.get("exception").copied().unwrap_or(0) >= 3
        })
        .await;
    assert!(s.devices[0]
        .last_error
        .as_deref()
        .unwrap_or("")
        .contains("0x06 server device busy"));
    field.set_comm_fault(CommFault::None);
    let s = rig
        .wait_for(10.0, "good again", |s| {
            Rig::quality(s, "T_screw") == Quality::Good
        })
        .await;
    // The device answered every time: the connection was never rebuilt.
    assert_eq!(s.devices[0].connects, connects);
    assert!(!s.devices[0].errors.contains_key("timeout"));
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dropped_connection_reconnects_with_backoff() {
    let mut rig = start(&config("hold", "", "")).await;
    rig.wait_for(10.0, "polling", |s| s.devices[0].cycles >= 3)
        .await;
    let field = rig.plant.field["ain1"].clone();
    field.set_comm_fault(CommFault::DropConnections);
    let s = rig
        .wait_for(10.0, "transport faults seen", |s| {
            s.devices[0].errors.get("transport").copied().unwrap_or(0)
                + s.devices[0].errors.get("connect").copied().unwrap_or(0)
                >= 2
                && !Rig::quality(s, "T_bed").is_good()
        })
        .await;
    assert_eq!(
        Rig::quality(&s, "T_bed").is_usable(),
        !matches!(Rig::quality(&s, "T_bed"), Quality::Bad(_))
    );
    field.set_comm_fault(CommFault::None);
    let s = rig
        .wait_for(10.0, "reconnected and good", |s| {
            s.devices[0].connects >= 2 && Rig::quality(s, "T_bed") == Quality::Good
        })
        .await;
    assert!((Rig::value(&s, "T_bed") - 30.0).abs() <= COUNT_DEGC);
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn late_reply_is_never_taken_for_the_next_answer() {
    // Two reads per cycle (counts at 0..3 and f32 at 2000..2001), distinct temperatures:
    // a late reply read as the next answer would put one channel's value on another.
    let toml = config("hold", "max_gap_registers = 0", "").replace(
        "[nc_modules.nc_x]",
        "[channels.T_f32]\ndevice = \"ain1\"\nregister = \"input\"\naddress = 2004\ndata_type = \"f32\"\nbyte_order = \"ABCD\"\nscaling = { kind = \"direct\", gain = 1.0, offset_degc = 0.0 }\nfilter = { median_samples = 1, lowpass_tau_s = 0.0, max_rate_degc_per_s = 0.0, max_rejected_samples = 5, stale_after_s = 0.0, valid_min_degc = -20.0, valid_max_degc = 100.0 }\n\n[nc_modules.nc_x]",
    );
    let mut rig = start(&toml).await;
    rig.wait_for(10.0, "polling", |s| s.devices[0].cycles >= 3)
        .await;
    let field = rig.plant.field["ain1"].clone();
    // Replies arrive 0.3 s late against a 0.2 s timeout.
    field.set_comm_fault(CommFault::Delay(Duration::from_millis(300)));
    let truth = [
        ("T_bed", 30.0),
        ("T_screw", 25.0),
        ("T_col", 60.0),
        ("T_f32", 60.0),
    ];
    let deadline = tokio::time::Instant::now() + Duration::from_secs(2);
    let mut timeouts_seen = false;
    while tokio::time::Instant::now() < deadline {
        rig.status.changed().await.unwrap();
        let s = rig.status.borrow_and_update().clone();
        timeouts_seen |= s.devices[0].errors.get("timeout").copied().unwrap_or(0) > 0;
        for (ch, t) in truth {
            let r = &Rig::channel(&s, ch).reading;
            if let Some(v) = r.unfiltered_degc.filter(|_| r.quality.is_good()) {
                assert!(
                    (v - t).abs() <= 2.0 * COUNT_DEGC,
                    "{ch} read {v}, truth {t}"
                );
            }
        }
    }
    assert!(timeouts_seen);
    field.set_comm_fault(CommFault::None);
    let s = rig
        .wait_for(10.0, "all good again", |s| {
            truth
                .iter()
                .all(|(c, _)| Rig::quality(s, c) == Quality::Good)
        })
        .await;
    for (ch, t) in truth {
        assert!((Rig::value(&s, ch) - t).abs() <= 2.0 * COUNT_DEGC, "{ch}");
    }
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ne43_open_sensor_makes_channel_bad_and_ramps_to_zero() {
    let mut rig = start(&config("ramp_to_zero", "", "")).await;
    rig.wait_for(10.0, "first job", |s| s.axes[0].jobs_ok >= 1)
        .await;
    let field = rig.plant.field["ain1"].clone();
    field.set_sensor_fault(0, SensorFault::Open).unwrap();
    let s = rig
        .wait_for(5.0, "NE43 low", |s| {
            Rig::quality(s, "T_bed") == Quality::Bad(Reason::Ne43Low)
        })
        .await;
    assert!(Rig::channel(&s, "T_bed").reading.current_ma.unwrap() < 3.6);
    // Ramp policy: K0 and tan(beta) go to zero at the configured rate, P0 stays.
    let s = rig
        .wait_for(10.0, "ramped to zero", |s| {
            s.axes[0]
                .written
                .is_some_and(|p| p.k0_mm == 0.0 && p.tan_beta == 0.0)
        })
        .await;
    assert!(
        s.axes[0].decision.contains("T_bed"),
        "{}",
        s.axes[0].decision
    );
    assert_eq!(rig.plant.nc["nc_x"].state().sd43900_mm, 0.0);
    assert_eq!(rig.plant.nc["nc_x"].state().sd43920_mm, 100.0);
    // The unaffected channel stays good.
    assert_eq!(Rig::quality(&s, "T_screw"), Quality::Good);
    field.set_sensor_fault(0, SensorFault::None).unwrap();
    rig.wait_for(10.0, "compensation back", |s| {
        s.axes[0]
            .written
            .is_some_and(|p| (p.k0_mm - 0.04).abs() <= 0.004 * COUNT_DEGC)
    })
    .await;
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stale_sensor_is_detected() {
    let filter = "{ median_samples = 1, lowpass_tau_s = 0.0, max_rate_degc_per_s = 0.0, max_rejected_samples = 5, stale_after_s = 0.5, valid_min_degc = -20.0, valid_max_degc = 100.0 }";
    let mut toml = config("hold", "", filter);
    // Noise keeps healthy counts moving, as on a real ADC.
    toml = toml.replace("mean_degc = 30.0", "mean_degc = 30.0\nnoise_degc = 0.5");
    let mut rig = start(&toml).await;
    rig.wait_for(10.0, "first job", |s| s.axes[0].jobs_ok >= 1)
        .await;
    let field = rig.plant.field["ain1"].clone();
    field.set_sensor_fault(0, SensorFault::Frozen).unwrap();
    let s = rig
        .wait_for(5.0, "stale", |s| {
            Rig::quality(s, "T_bed") == Quality::Bad(Reason::Stale)
        })
        .await;
    assert!(s.axes[0].decision.starts_with("hold") || s.axes[0].decision.starts_with("within"));
    rig.wait_for(5.0, "axis holds", |s| s.axes[0].decision.contains("T_bed"))
        .await;
    field.set_sensor_fault(0, SensorFault::None).unwrap();
    rig.wait_for(5.0, "fresh again", |s| Rig::quality(s, "T_bed").is_usable())
        .await;
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rejected_nc_job_is_reported_retried_and_not_confirmed() {
    let mut rig = start(&config("hold", "", "")).await;
    let nc = rig.plant.nc["nc_x"].clone();
    nc.set_job_fault(JobFault::Refuse(JobStatus::AccessDenied));
    let s = rig
        .wait_for(10.0, "refused jobs", |s| s.axes[0].jobs_failed >= 2)
        .await;
    let err = s.axes[0].last_job_error.clone().unwrap();
    assert!(err.contains("error 3 (access denied)"), "{err}");
    assert_eq!(s.axes[0].jobs_ok, 0);
    // Nothing was confirmed: the gateway still shows what the NC held at start.
    assert_eq!(s.axes[0].written.unwrap().k0_mm, 0.0);
    assert_eq!(nc.state().sd43900_mm, 0.0);

    // A job that never finishes times out instead of hanging the writer.
    nc.set_job_fault(JobFault::NeverFinish);
    let s = rig
        .wait_for(10.0, "job timeout", |s| {
            s.axes[0]
                .last_job_error
                .as_deref()
                .is_some_and(|e| e.contains("did not finish"))
        })
        .await;
    assert_eq!(s.axes[0].jobs_ok, 0);

    nc.set_job_fault(JobFault::None);
    // The job that timed out may have taken effect on the NC: the gateway then takes
    // it from there, and may have nothing left to write. A new temperature calls for
    // a new value.
    rig.plant.field["ain1"]
        .set_temperature_override(0, Some(35.0))
        .unwrap();
    let s = rig
        .wait_for(10.0, "job accepted once the NC allows it", |s| {
            s.axes[0].jobs_ok >= 1
        })
        .await;
    assert!((nc.state().sd43900_mm - s.axes[0].written.unwrap().k0_mm).abs() < 1e-15);
    // The failure is kept beside the counters once jobs succeed again.
    let (_, why) = s.axes[0].last_failure.clone().expect("last failure kept");
    assert!(why.contains("did not finish"), "{why}");
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_dead_device_does_not_stop_the_other() {
    let toml = config("hold", "", "").replace(
        "[channels.T_col]\ndevice = \"ain1\"",
        "[devices.ain2]\ntransport = \"tcp\"\naddress = \"127.0.0.1:0\"\nunit_id = 1\ntimeout_s = 0.2\npoll_interval_s = 0.05\nbackoff_initial_s = 0.05\nbackoff_max_s = 0.2\n\n[channels.T_col]\ndevice = \"ain2\"",
    );
    let mut rig = start(&toml).await;
    rig.wait_for(10.0, "both polling", |s| {
        s.devices.iter().all(|d| d.cycles >= 2)
    })
    .await;
    rig.plant.field["ain2"].set_comm_fault(CommFault::Silent);
    let s = rig
        .wait_for(10.0, "ain2 degraded", |s| {
            Rig::quality(s, "T_col") == Quality::Bad(Reason::DeviceDegraded)
        })
        .await;
    let ain1_cycles = s.devices.iter().find(|d| d.name == "ain1").unwrap().cycles;
    let s = rig
        .wait_for(5.0, "ain1 keeps polling", |s| {
            s.devices.iter().find(|d| d.name == "ain1").unwrap().cycles >= ain1_cycles + 10
        })
        .await;
    assert_eq!(Rig::quality(&s, "T_bed"), Quality::Good);
    // The axis uses only ain1's channels: it keeps writing.
    let jobs = s.axes[0].jobs_ok;
    rig.plant.field["ain1"]
        .set_temperature_override(0, Some(33.0))
        .unwrap();
    rig.wait_for(5.0, "a new job despite ain2", |s| s.axes[0].jobs_ok > jobs)
        .await;
    rig.stop().await;
}

// An NC whose MD32750 is not the config's runs another compensation type: the axis
// holds and says why. An axis not referenced still gets its setting data (the NC
// applies them once referenced), with a warning of its own next to the MD32750 one.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn md32750_mismatch_and_unreferenced_axis_are_shown() {
    let toml = config("hold", "", "").replace(
        "referenced = true\nmd32750 = 3",
        "referenced = false\nmd32750 = 1",
    );
    let mut rig = start(&toml).await;
    let s = rig
        .wait_for(10.0, "the axis holding for MD32750", |s| {
            s.axes[0].decision.contains("MD32750")
        })
        .await;
    assert_eq!(
        s.axes[0].decision,
        "hold: MD32750 is 1 on the NC, the config expects 3"
    );
    let w = s.axes[0].warning.clone().unwrap();
    assert!(
        w.contains("MD32750 is 1 on the NC, the config expects 3"),
        "{w}"
    );
    assert!(w.contains("axis not referenced"), "{w}");
    // Many updates later (polls are 50 ms, updates 100 ms): still nothing written.
    let samples = s.samples;
    let s = rig
        .wait_for(10.0, "40 more samples", |s| s.samples >= samples + 40)
        .await;
    assert_eq!(rig.plant.nc["nc_x"].jobs_executed(), 0);
    assert_eq!(s.axes[0].jobs_ok + s.axes[0].jobs_failed, 0);
    assert_eq!(rig.plant.nc["nc_x"].state().sd43900_mm, 0.0);

    // MD32750 put right, the axis still not referenced: the settings are written; the
    // NC applies nothing until referenced.
    rig.plant.nc["nc_x"].with_state(|a| a.md32750 = 3);
    let s = rig
        .wait_for(10.0, "a job once MD32750 matches", |s| {
            s.axes[0].jobs_ok >= 1
        })
        .await;
    let w = s.axes[0].warning.clone().unwrap_or_default();
    assert!(w.contains("axis not referenced"), "{w}");
    assert!(!w.contains("MD32750"), "{w}");
    assert_eq!(s.axes[0].nc.and_then(|nc| nc.applied_comp_mm), Some(0.0));
    rig.plant.nc["nc_x"].with_state(|a| a.referenced = true);
    let s = rig
        .wait_for(10.0, "warnings clear once the NC is right", |s| {
            s.axes[0].warning.is_none()
                && s.axes[0]
                    .nc
                    .and_then(|nc| nc.applied_comp_mm)
                    .is_some_and(|c| c > 0.0)
        })
        .await;
    assert!(render_has_no_warning(&s));
    rig.stop().await;
}

// `gateway.status_interval_s` is a display setting: at 1 ms it must not read the NC
// once per millisecond. Over a stretch of at least 2 s (40 polls of 50 ms) the NC
// serves a snapshot (2 requests) at most once a second, plus what the jobs cost.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fast_status_interval_does_not_flood_the_nc() {
    let toml =
        config("hold", "", "").replace("status_interval_s = 0.05", "status_interval_s = 0.001");
    assert!(toml.contains("status_interval_s = 0.001"));
    let mut rig = start(&toml).await;
    let s = rig
        .wait_for(10.0, "a verified job", |s| s.axes[0].jobs_ok >= 1)
        .await;
    let nc = rig.plant.nc["nc_x"].clone();
    let (requests, jobs, samples) = (nc.requests_served(), nc.jobs_executed(), s.samples);
    let started = std::time::Instant::now();
    // A new temperature: a job must get through at once, not behind snapshot reads.
    rig.plant.field["ain1"]
        .set_temperature_override(0, Some(35.0))
        .unwrap();
    rig.wait_for(10.0, "the new temperature written", |s| {
        s.axes[0]
            .written
            .is_some_and(|p| (p.k0_mm - 0.06).abs() <= 0.004 * COUNT_DEGC)
    })
    .await;
    rig.wait_for(20.0, "40 more samples", |s| s.samples >= samples + 40)
        .await;
    let served = nc.requests_served() - requests;
    let jobs = nc.jobs_executed() - jobs;
    let elapsed_s = started.elapsed().as_secs_f64();
    // A job: the idle check, the pairs, REQ, at least one wait read, the acknowledge
    // and the read-back (2): at most 20 with waits, generously.
    let bound = 2.0 * (elapsed_s + 2.0) + 20.0 * jobs as f64;
    assert!(
        (served as f64) <= bound,
        "{served} NC requests in {elapsed_s:.1} s with {jobs} jobs (bound {bound:.0})"
    );
    rig.stop().await;
}

fn render_has_no_warning(s: &compgate_gateway::runtime::Status) -> bool {
    !compgate_service::status::render(s).contains("WARNING")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn monitoring_only_config_without_axes_runs_and_stops() {
    let full = config("hold", "", "");
    let cut = full.find("[nc_modules.nc_x]").unwrap();
    // The simulated plant stays (it gives the devices' port 0 a free port), without
    // its NC module.
    let sim = full.find("[sim]").unwrap();
    let sim_nc = full.find("[sim.nc_modules.nc_x]").unwrap();
    let toml = format!(
        "{}\n[nc_modules]\n[axes]\n\n{}",
        &full[..cut],
        &full[sim..sim_nc]
    );
    let mut rig = start(&toml).await;
    let s = rig
        .wait_for(10.0, "readings without any axis", |s| {
            s.samples >= 5 && Rig::quality(s, "T_bed") == Quality::Good
        })
        .await;
    assert!(s.axes.is_empty());
    rig.stop().await;
}
