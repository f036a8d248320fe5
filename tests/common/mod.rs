//! Shared test harness: a simulated plant on loopback port 0 (and ptys), the real
//! gateway against it, and a way to wait for a status condition.
#![allow(dead_code)]

pub mod broker;
pub mod metrics;
pub mod opcua_peer;
pub mod peer;
pub mod process;
pub mod proxy;
pub mod s7_peer;

use std::time::Duration;

use compgate::plant::{Bind, Plant};
use compgate_gateway::config;
use compgate_gateway::runtime::{self, Status};
use tokio::sync::watch;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

/// Waits until `pred` holds for the status published on `status`; panics with the
/// last status and `what` after `secs`.
pub async fn wait_status(
    status: &mut watch::Receiver<Status>,
    secs: f64,
    what: &str,
    pred: impl Fn(&Status) -> bool,
) -> Status {
    let deadline = tokio::time::Instant::now() + Duration::from_secs_f64(secs);
    loop {
        {
            let s = status.borrow_and_update();
            // Status::default() until the gateway publishes its first status.
            if !s.channels.is_empty() && pred(&s) {
                return s.clone();
            }
        }
        if tokio::time::timeout_at(deadline, status.changed())
            .await
            .is_err()
        {
            panic!(
                "timed out after {secs} s waiting for: {what}\nlast status: {}",
                compgate_service::status::render(&status.borrow())
            );
        }
    }
}

/// A running plant and gateway; dropping it stops both.
pub struct Rig {
    pub plant: Plant,
    pub status: watch::Receiver<Status>,
    pub shutdown: CancellationToken,
    pub gateway: Option<JoinHandle<()>>,
}

impl Rig {
    /// Stops the gateway and waits for it to finish.
    pub async fn stop(mut self) -> Status {
        self.shutdown.cancel();
        if let Some(h) = self.gateway.take() {
            tokio::time::timeout(Duration::from_secs(10), h)
                .await
                .expect("gateway stops within 10 s")
                .expect("gateway task did not panic");
        }
        self.status.borrow().clone()
    }

    /// Stops the gateway; asserts that no job of the first axis failed.
    pub async fn stop_without_failed_jobs(self) -> Status {
        let fin = self.stop().await;
        assert_eq!(
            fin.axes[0].jobs_failed, 0,
            "{:?}",
            fin.axes[0].last_job_error
        );
        fin
    }

    /// Waits until `pred` holds for the published status; panics with the last status
    /// and `what` after `secs`.
    pub async fn wait_for(
        &mut self,
        secs: f64,
        what: &str,
        pred: impl Fn(&Status) -> bool,
    ) -> Status {
        wait_status(&mut self.status, secs, what, pred).await
    }

    pub fn channel<'a>(s: &'a Status, name: &str) -> &'a runtime::ChannelStatus {
        s.channels
            .iter()
            .find(|c| &*c.name == name)
            .expect("channel exists")
    }

    /// The quality of channel `name`.
    pub fn quality(s: &Status, name: &str) -> compgate_core::channel::Quality {
        Self::channel(s, name).reading.quality
    }

    /// The value of channel `name`, degC.
    pub fn value(s: &Status, name: &str) -> f64 {
        Self::channel(s, name)
            .reading
            .value_degc
            .expect("channel has a value")
    }
}

impl Drop for Rig {
    fn drop(&mut self) {
        self.shutdown.cancel();
    }
}

/// A free TCP port on loopback (taken from port 0 and released again), for an address
/// that must stay dead or that a restarted process binds again. Anything else binds
/// port 0 itself: another listener can take this one before it is used.
pub fn free_port() -> u16 {
    let l = std::net::TcpListener::bind("127.0.0.1:0").expect("bind port 0");
    l.local_addr().expect("local addr").port()
}

/// A running simulated plant for `toml` and a config file in `dir` naming its
/// addresses, with `extra` (more sections) appended.
pub async fn plant_and_file(
    dir: &std::path::Path,
    toml: &str,
    extra: &str,
) -> (Plant, std::path::PathBuf) {
    let cfg = config::load_str(toml, "test.toml").expect("test config is valid");
    let plant = Plant::start(&cfg, Bind::Ephemeral)
        .await
        .expect("plant starts");
    let path = dir.join("compgate.toml");
    let text = toml::to_string(&plant.config).expect("config serialises") + extra;
    std::fs::write(&path, text).expect("config file written");
    (plant, path)
}

/// Starts the simulated plant for `toml` and the gateway against it.
pub async fn start(toml: &str) -> Rig {
    start_edited(toml, |_| {}).await
}

/// [`start`], the gateway's config (the plant's addresses in) first passed to `edit`:
/// e.g. to point a target at a server outside the plant.
pub async fn start_edited(toml: &str, edit: impl FnOnce(&mut config::Config)) -> Rig {
    let cfg = config::load_str(toml, "test.toml").expect("test config is valid");
    let plant = Plant::start(&cfg, Bind::Ephemeral)
        .await
        .expect("plant starts");
    let (tx, rx) = watch::channel(Status::default());
    let shutdown = CancellationToken::new();
    let mut cfg = plant.config.clone();
    edit(&mut cfg);
    let sd = shutdown.clone();
    let gateway = tokio::spawn(async move {
        runtime::run(&cfg, sd, tx).await.expect("gateway runs");
    });
    Rig {
        plant,
        status: rx,
        shutdown,
        gateway: Some(gateway),
    }
}

/// The test transmitters' scaling: 4-20 mA over -50..150 degC on a 12-bit ADC at 24 mA.
pub const SCALING: &str = r#"{ kind = "transmitter", adc_full_scale_counts = 4095, adc_full_scale_ma = 24.0, current_range = "4-20", range_min_degc = -50.0, range_max_degc = 150.0 }"#;

/// A filter that passes every sample through, so tests see the raw value at once.
pub const FILTER: &str = "{ median_samples = 1, lowpass_tau_s = 0.0, max_rate_degc_per_s = 0.0, max_rejected_samples = 5, stale_after_s = 0.0, valid_min_degc = -20.0, valid_max_degc = 100.0 }";

/// A fast test config: one TCP field device with three PT100 channels (T_bed at
/// counts address 0, T_screw at 1, T_col at 2), one NC module, axis X.
/// `extra_device` and `axis_extra` are appended to the device and axis tables.
pub fn config(policy: &str, device_extra: &str, filter: &str) -> String {
    let scaling = SCALING;
    let filter = if filter.is_empty() { FILTER } else { filter };
    let channels: String = ["T_bed", "T_screw", "T_col"]
        .iter()
        .enumerate()
        .map(|(address, name)| {
            format!(
                "[channels.{name}]\ndevice = \"ain1\"\nregister = \"input\"\naddress = {address}\n\
                 data_type = \"u16\"\nscaling = {scaling}\nfilter = {filter}\n\n"
            )
        })
        .collect();
    format!(
        r#"
[gateway]
status_interval_s = 0.05

[devices.ain1]
transport = "tcp"
address = "127.0.0.1:0"
unit_id = 1
timeout_s = 0.2
connect_timeout_s = 0.5
retries = 0
poll_interval_s = 0.05
backoff_initial_s = 0.05
backoff_max_s = 0.2
degrade_after_cycles = 3
{device_extra}

{channels}
[nc_modules.nc_x]
address = "127.0.0.1:0"
unit_id = 1
timeout_s = 0.5
job_timeout_s = 0.5

[axes.X]
nc_module = "nc_x"
md32750 = 3
p0_mm = 100.0
update_interval_s = 0.1
deadband_k0_mm = 0.00001
deadband_tan_beta = 0.0000000001
max_abs_k0_mm = 0.5
max_abs_tan_beta = 0.01
max_step_k0_mm = 0.5
max_step_tan_beta = 0.01
on_bad_input = "{policy}"
ramp_k0_mm_per_s = 0.05
ramp_tan_beta_per_s = 0.0001
k0 = {{ offset_mm = 0.0, terms = [{{ channel = "T_bed", ref_degc = 20.0, coeff_mm_per_degc = 0.004 }}] }}
tan_beta = {{ offset = 0.0, terms = [{{ channel = "T_screw", ref_degc = 20.0, coeff_per_degc = 0.0000115 }}] }}

[sim]
seed = 7

[sim.channels.T_bed]
profile = "constant"
mean_degc = 30.0

[sim.channels.T_screw]
profile = "constant"
mean_degc = 25.0

[sim.channels.T_col]
profile = "constant"
mean_degc = 60.0

[sim.nc_modules.nc_x]
referenced = true
md32750 = 3
motion_min_mm = 500.0
motion_max_mm = 500.0
motion_speed_mm_per_s = 0.0
"#
    )
}

/// [`config`] (policy `hold`) with its NC module replaced by `target` (a
/// `[targets.nc_x]` table) and axis X given axis number `axis`.
pub fn with_target(target: &str, axis: u16) -> String {
    let base = config("hold", "", "");
    let start = base.find("[nc_modules.nc_x]").expect("an NC module");
    let end = start + base[start..].find("\n\n").expect("a blank line after it");
    let sim = base.find("[sim.nc_modules.nc_x]").expect("its simulation");
    format!("{}{target}{}", &base[..start], &base[end..sim]).replace(
        "nc_module = \"nc_x\"\n",
        &format!("nc_module = \"nc_x\"\naxis_number = {axis}\n"),
    )
}

/// What the first axis was written, checked to be the model of [`config`] on the
/// readings (T_bed at 30 degC within one ADC count).
pub fn written_by_model(s: &Status) -> compgate_core::comp::CompParams {
    let w = s.axes[0].written.expect("a written job");
    let t_bed = Rig::value(s, "T_bed");
    let t_screw = Rig::value(s, "T_screw");
    assert!((t_bed - 30.0).abs() <= COUNT_DEGC, "T_bed {t_bed}");
    assert!((w.k0_mm - 0.004 * (t_bed - 20.0)).abs() < 1e-12, "{w:?}");
    assert!(
        (w.tan_beta - 0.0000115 * (t_screw - 20.0)).abs() < 1e-15,
        "{w:?}"
    );
    w
}

/// One ADC count in degC for the test transmitters (24 mA / 4095 counts, 200 degC / 16 mA).
pub const COUNT_DEGC: f64 = 24.0 / 4095.0 * 200.0 / 16.0;

/// Writes a job whose second pair (SD43900 = 25 mm) lies beyond the NC's own limit and
/// asserts that the target refuses it naming that pair, and applies neither pair (all
/// or none). Returns the error for the caller's further checks.
pub async fn refused_all_or_none(
    w: &mut impl compgate_gateway::nc::NcWriter,
) -> compgate_gateway::nc::NcError {
    use compgate_gateway::nc::{Job, NcError};
    use compgate_ncproto::{var, JobStatus};
    let too_big = Job {
        pairs: vec![(var::SD43910, 0.001), (var::SD43900, 25.0)],
    };
    let e = w
        .write_job(&too_big)
        .await
        .expect_err("a job beyond the NC's limit is refused");
    assert!(
        matches!(
            e,
            NcError::Refused {
                status: JobStatus::ValueOutOfRange,
                index: 2,
                var: Some(var::SD43900),
                ..
            }
        ),
        "{e:?}"
    );
    // The valid first pair was not applied either.
    let held = w
        .read_snapshot()
        .await
        .expect("a snapshot after the refusal");
    assert_eq!(held.sd43910, 0.0);
    e
}
