//! The running gateway: sources -> channels -> compensation -> NC writer.
//!
//! [`build`] turns a validated [`Config`] into runtime parts; [`run`] starts one task
//! per device, one SYNC producer per CAN interface and one task per NC writer around a
//! core loop that owns every channel processor and axis compensator. On shutdown the
//! device tasks end at once and the NC tasks abandon an outstanding snapshot read; a
//! job in flight gets [`NC_JOB_GRACE`] to finish. A reload stops the NC tasks the same
//! way while the devices go on polling, then the devices between two polls.

use std::fmt::Write as _;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::{mpsc, watch};
use tokio::time::{Instant, MissedTickBehavior};
use tokio_util::sync::CancellationToken;

use crate::config::Config;
use crate::nc::{Job, JobReport, NcError, NcSnapshot, NcWriter};
use crate::source::can::sync::{self, SyncParams};
use crate::source::DeviceSample;
use compgate_core::channel::Quality;
use compgate_core::comp::{BeyondLimit, CompParams, Decision, Limits};

mod build;
mod hooks;
mod pipeline;
mod readings;
mod reload;
mod status;
pub use build::*;
pub use hooks::{Hooks, Observer, Observers};
pub use pipeline::*;
pub use readings::{ChannelReading, SampleReadings};
pub use status::*;

/// Errors of the gateway layer.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum GatewayError {
    /// The configuration cannot be turned into a running gateway.
    #[error("config: {0}")]
    Config(String),
}

/// Samples the device tasks may queue ahead of the core loop.
pub const SAMPLE_QUEUE: usize = 64;

/// The NC is read at most this often, whatever `gateway.status_interval_s`: a status
/// interval of 1 ms read it once per millisecond and starved its jobs. Slower status
/// intervals keep reading it once per status interval (what the status shows and the
/// recorder records), so a snapshot is never older than the status showing it.
pub const NC_SNAPSHOT_MIN: Duration = Duration::from_secs(1);

/// How long a job in flight may still take when its NC task is stopped (shutdown,
/// reload): a job usually ends within milliseconds, and a stuck one must not hold up
/// the stop for its whole `job_timeout_s`. Past it the job is abandoned and its
/// outcome is unknown: the NC is read again before the next write.
pub const NC_JOB_GRACE: Duration = Duration::from_secs(2);

/// The period of an NC writer's snapshot reads for `status_interval`.
fn nc_snapshot_interval(status_interval: Duration) -> Duration {
    status_interval.max(NC_SNAPSHOT_MIN)
}

/// What the core loop asks of an NC task.
enum NcCommand {
    Write {
        axis: usize,
        /// For the log: two axes on one target must be told apart.
        axis_name: String,
        job: Job,
        params: CompParams,
        /// What the step was limited from: the job goes out only while the NC holds it.
        from: Option<CompParams>,
    },
}

/// What an NC task reports back to the core loop.
enum NcEvent {
    Snapshot {
        module: usize,
        result: Result<NcSnapshot, NcError>,
    },
    Written {
        axis: usize,
        params: CompParams,
        result: Result<JobReport, NcError>,
    },
    /// The task was stopped with this axis' job in flight and the job did not end
    /// within [`NC_JOB_GRACE`]: whether it landed is unknown.
    Abandoned { axis: usize },
}

/// What a task hands back when it ends, so a reload can keep its state.
enum Returned {
    Device(usize, DeviceRt),
    Nc(usize, NcModuleRt),
    /// A SYNC producer keeps nothing: the next generation opens a fresh socket.
    Sync,
    Aborted,
}

/// Polls until `stop` (between polls: a reload keeps the link clean) or `shutdown`
/// (at once, even mid-request).
async fn device_task(
    index: usize,
    mut dev: DeviceRt,
    tx: mpsc::Sender<DeviceSample>,
    stop: CancellationToken,
    shutdown: CancellationToken,
) -> Returned {
    // Every device ticks from the same start, in phase with the others of its
    // interval: the worker then wakes once for all their requests and once or twice
    // for the replies. Spread over the interval, each device woke it on its own, and
    // at 100k points/s the gateway took half again as much CPU (docs/benchmarks.md).
    let mut tick = tokio::time::interval(dev.poll_interval);
    // A slow device must not burst-poll to catch up.
    tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = stop.cancelled() => break,
            _ = tick.tick() => {}
        }
        let sample = tokio::select! {
            _ = shutdown.cancelled() => return Returned::Aborted,
            s = dev.poller.poll() => s,
        };
        if tx.send(sample).await.is_err() {
            break;
        }
    }
    Returned::Device(index, dev)
}

/// Sends an interface's SYNC until `stop` (a reload or shutdown): at once, since no
/// exchange is in flight and the next generation starts its own producer.
async fn sync_task(params: SyncParams, stop: CancellationToken) -> Returned {
    sync::run(params, stop).await;
    Returned::Sync
}

/// Reads the NC every `snapshot_interval` and runs the jobs the core loop sends, a
/// waiting job before the next read. On `stop` (shutdown or reload) it ends at once:
/// no read starts after it, and an outstanding read is abandoned with the writer (its
/// connection may still get the late reply; the next generation connects afresh). A
/// job in flight gets [`NC_JOB_GRACE`].
async fn nc_task(
    module: usize,
    mut nc: NcModuleRt,
    mut rx: mpsc::Receiver<NcCommand>,
    tx: mpsc::Sender<NcEvent>,
    snapshot_interval: Duration,
    stop: CancellationToken,
) -> Returned {
    let mut tick = tokio::time::interval(snapshot_interval);
    tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            biased;
            () = stop.cancelled() => break,
            cmd = rx.recv() => {
                let Some(NcCommand::Write { axis, axis_name, job, params, from }) = cmd else { break };
                let Some(result) = write_or_abandon(&mut nc, &job, from.as_ref(), &stop).await else {
                    tracing::warn!(axis = %axis_name, target_name = %nc.name, written = written(&job).as_str(), grace_s = NC_JOB_GRACE.as_secs_f64(), "NC job abandoned at stop: whether it landed is unknown; the NC is read again before the next write");
                    let _ = tx.send(NcEvent::Abandoned { axis }).await;
                    return Returned::Aborted;
                };
                match &result {
                    // The job's pairs, not the parameter set: `nc_write` may leave
                    // variables out, and those were not written.
                    Ok(r) => tracing::info!(axis = %axis_name, target_name = %nc.name, job_id = r.job_id, written = written(&job).as_str(), elapsed_ms = r.elapsed.as_secs_f64() * 1e3, "NC job done, read-back verified"),
                    // The core loop logs the change from working to failing once.
                    Err(e) => tracing::debug!(axis = %axis_name, target_name = %nc.name, error = %e, "NC job failed"),
                }
                if tx.send(NcEvent::Written { axis, params, result }).await.is_err() {
                    break;
                }
            }
            _ = tick.tick() => {
                let result = tokio::select! {
                    biased;
                    () = stop.cancelled() => return Returned::Aborted,
                    r = nc.writer.read_snapshot() => r,
                };
                if tx.send(NcEvent::Snapshot { module, result }).await.is_err() {
                    break;
                }
            }
        }
    }
    Returned::Nc(module, nc)
}

/// Runs `job`; once `stop` is cancelled it may take [`NC_JOB_GRACE`] more. `None`:
/// abandoned.
async fn write_or_abandon(
    nc: &mut NcModuleRt,
    job: &Job,
    from: Option<&CompParams>,
    stop: &CancellationToken,
) -> Option<Result<JobReport, NcError>> {
    let write = nc.writer.write_job_from(job, from);
    tokio::pin!(write);
    tokio::select! {
        r = &mut write => return Some(r),
        () = stop.cancelled() => {}
    }
    tokio::time::timeout(NC_JOB_GRACE, write).await.ok()
}

/// The variables `job` writes with their values, e.g. `SD43900=0.04 mm, SD43920=100 mm`.
fn written(job: &Job) -> String {
    let mut out = String::new();
    for (var, value) in &job.pairs {
        let unit = match *var {
            compgate_ncproto::var::SD43900 | compgate_ncproto::var::SD43920 => " mm",
            _ => "",
        };
        let sep = if out.is_empty() { "" } else { ", " };
        let _ = write!(
            out,
            "{sep}{}={}{unit}",
            crate::nc::var_name(*var),
            crate::nc::shown(*var, *value)
        );
    }
    out
}

fn describe(
    d: &Decision,
    beyond: Option<&BeyondLimit>,
    limits: &Limits,
    names: &[String],
    inputs: &[usize],
) -> String {
    let bad = |idx: &[usize]| {
        idx.iter()
            .filter_map(|&i| inputs.get(i).and_then(|&c| names.get(c)))
            .cloned()
            .collect::<Vec<_>>()
            .join(",")
    };
    let text: String = match d {
        Decision::Write { clamped: false, .. } => "write".into(),
        Decision::Write { clamped: true, .. } => "write (limited)".into(),
        Decision::WithinDeadband => "within deadband".into(),
        Decision::Hold { bad_inputs } if bad_inputs.is_empty() => {
            "hold: the model value is not finite".into()
        }
        Decision::Hold { bad_inputs } => format!("hold: bad input {}", bad(bad_inputs)),
        Decision::Ramp { bad_inputs, .. } => format!("ramp to zero: bad input {}", bad(bad_inputs)),
    };
    let Some(b) = beyond else {
        return text;
    };
    let mut at = Vec::new();
    if let Some(k0_mm) = b.k0_mm {
        at.push(format!(
            "the model's K0 {} mm is beyond max_abs_k0_mm = {} mm",
            crate::nc::shown_mm(k0_mm),
            crate::nc::number(limits.max_abs_k0_mm)
        ));
    }
    if let Some(tan_beta) = b.tan_beta {
        at.push(format!(
            "the model's tan(beta) {} is beyond max_abs_tan_beta = {}",
            crate::nc::shown(crate::nc::var::SD43910, tan_beta),
            crate::nc::number(limits.max_abs_tan_beta)
        ));
    }
    format!("at the limit ({}): {text}", at.join("; "))
}

/// Runs the gateway until `shutdown` is cancelled, publishing status on `status`.
pub async fn run(
    cfg: &Config,
    shutdown: CancellationToken,
    status: watch::Sender<Status>,
) -> Result<(), GatewayError> {
    run_with(cfg, shutdown, status, Hooks::default()).await
}

/// [`run`] with hooks: an observer (recorder, metrics, MQTT, systemd) and a source of
/// reloaded configs.
pub async fn run_with(
    cfg: &Config,
    shutdown: CancellationToken,
    status: watch::Sender<Status>,
    hooks: Hooks,
) -> Result<(), GatewayError> {
    let built = build(cfg)?;
    run_built_with(built, cfg.clone(), shutdown, status, hooks).await;
    Ok(())
}

/// Runs already-built parts; see [`run`].
pub async fn run_built(
    built: Built,
    shutdown: CancellationToken,
    status_tx: watch::Sender<Status>,
) {
    // Without a reload source the config is never compared: any will do.
    let cfg = Config::default();
    run_built_with(built, cfg, shutdown, status_tx, Hooks::default()).await;
}

/// Runs `built` (made from `cfg`) through generations: a reload stops the NC tasks
/// (see [`nc_task`]) while the devices go on polling, then ends the generation between
/// two polls and starts the next with the state of whatever did not change.
async fn run_built_with(
    built: Built,
    mut cfg: Config,
    shutdown: CancellationToken,
    status_tx: watch::Sender<Status>,
    mut hooks: Hooks,
) {
    let mut state = Running::new(built);
    // What the sections set up once at start run with, whatever was loaded since.
    let started = reload::RestartOnly::of(&cfg);
    loop {
        match generation(&mut state, &shutdown, &status_tx, &mut hooks).await {
            None => break,
            Some((new_cfg, new_built)) => {
                started.warn_changed(&new_cfg);
                state = reload::transplant(&cfg, &new_cfg, state, *new_built);
                cfg = *new_cfg;
                tracing::info!("configuration reloaded");
                hooks.observer.on_reload(&Ok(()));
            }
        }
    }
    state.status_now();
    status_tx.send_replace(state.status);
    tracing::info!("gateway stopped");
}

/// What an axis' NC says against its config (targets that report the axis state).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
struct NcFacts {
    /// The NC's MD32750 when it is not the configured one: the axis holds.
    md32750_wrong: Option<u16>,
    /// The axis is not referenced: the NC applies no compensation (writes still go,
    /// setting data are accepted, and apply once referenced).
    unreferenced: bool,
}

impl NcFacts {
    /// The status warning for these facts, naming every one of them.
    fn warning(&self, md32750_config: u16) -> Option<String> {
        let md = self.md32750_wrong.map(|v| {
            format!(
                "MD32750 is {v} on the NC, the config expects {md32750_config}: nothing is written"
            )
        });
        let unref = self
            .unreferenced
            .then(|| "axis not referenced: the NC applies no temperature compensation".to_string());
        match (md, unref) {
            (Some(a), Some(b)) => Some(format!("{a}; {b}")),
            (a, b) => a.or(b),
        }
    }
}

/// The state that lives across generations.
struct Running {
    pipeline: Pipeline,
    devices: Vec<Option<DeviceRt>>,
    sync_producers: Vec<SyncParams>,
    nc_modules: Vec<Option<NcModuleRt>>,
    status_interval: Duration,
    status: Status,
    /// Per axis: whether its step limits start from what the NC holds: set by a
    /// snapshot, cleared by a failed one, so after an outage nothing is written
    /// before the NC has been read again.
    baselined: Vec<bool>,
    /// Device names by index, for [`SampleReadings::device_name`].
    device_names: Vec<Arc<str>>,
    /// The last sample's outcome (kept for its allocation).
    readings: SampleReadings,
    /// NC module names by index, for the log.
    nc_names: Vec<Arc<str>>,
    /// NC module addresses by index, for the log.
    nc_addresses: Vec<String>,
    /// Per NC module: what the journal was told of it, rate limited like devices: a
    /// target that flaps must not flood.
    nc_logs: Vec<ChangeLog<NcCourse>>,
    /// Per NC module: its last snapshot's error, for a line the rate limit deferred.
    nc_errors: Vec<String>,
    /// Per axis: what its NC's last snapshot said against the config (MD32750,
    /// referenced), as the journal was told: a wrong MD32750 holds the axis.
    nc_facts: Vec<NcFacts>,
    /// Per channel: a byte-order hint was logged and the channel has not been good
    /// since (logged once, not once per poll).
    byte_order_hinted: Vec<bool>,
    /// Per channel: whether it is usable, as the journal was told (carried over a
    /// reload by name).
    channel_logs: Vec<ChangeLog<bool>>,
    /// Per axis: whether it follows its model, as the journal was told (carried over
    /// a reload by name).
    axis_logs: Vec<ChangeLog<AxisCourse>>,
    /// Per device: its link's state, as the journal was told.
    device_logs: Vec<ChangeLog<DeviceCourse>>,
}

impl Running {
    fn new(built: Built) -> Self {
        let Built {
            pipeline,
            devices,
            sync_producers,
            nc_modules,
            status_interval,
        } = built;
        let status = Status {
            channels: pipeline.channel_statuses(),
            devices: devices
                .iter()
                .map(|d| DeviceStatus {
                    name: d.poller.name().to_string(),
                    link: d.poller.describe(),
                    ..DeviceStatus::default()
                })
                .collect(),
            axes: pipeline
                .axes
                .iter()
                .map(|a| AxisStatus {
                    name: a.name.clone(),
                    decision: "waiting for the NC".into(),
                    shadow: a.shadow,
                    ..AxisStatus::default()
                })
                .collect(),
            samples: 0,
            jobs: Default::default(),
        };
        Running {
            baselined: vec![false; pipeline.axes.len()],
            device_names: devices.iter().map(|d| Arc::from(d.poller.name())).collect(),
            readings: SampleReadings::default(),
            nc_names: nc_modules
                .iter()
                .map(|n| Arc::from(n.name.as_str()))
                .collect(),
            nc_addresses: nc_modules.iter().map(|n| n.address.clone()).collect(),
            nc_logs: vec![ChangeLog::new(NcCourse::Up); nc_modules.len()],
            nc_errors: vec![String::new(); nc_modules.len()],
            nc_facts: vec![NcFacts::default(); pipeline.axes.len()],
            byte_order_hinted: vec![false; pipeline.channel_names.len()],
            channel_logs: vec![ChangeLog::new(true); pipeline.channel_names.len()],
            axis_logs: vec![ChangeLog::new(AxisCourse::Model); pipeline.axes.len()],
            device_logs: vec![ChangeLog::new(DeviceCourse::Up); devices.len()],
            pipeline,
            devices: devices.into_iter().map(Some).collect(),
            sync_producers,
            nc_modules: nc_modules.into_iter().map(Some).collect(),
            status_interval,
            status,
        }
    }

    /// Runs `sample` through the channel processors and builds, once, what the
    /// status and the observers see of it: [`Self::readings`].
    fn on_sample(&mut self, sample: &DeviceSample) {
        let r = &mut self.readings;
        r.device = sample.device;
        r.device_name = self
            .device_names
            .get(sample.device)
            .cloned()
            .unwrap_or_default();
        r.poll_elapsed = sample.elapsed;
        r.connects = sample.connects;
        r.error.clone_from(&sample.error);
        r.link_up = sample.answered();
        r.faults.clone_from(&sample.faults);
        r.channel_names = self.pipeline.channel_names.clone();
        self.pipeline.ingest(sample, &mut r.channels);

        let status = &mut self.status;
        status.samples += 1;
        if let (Some(d), Some(log)) = (
            status.devices.get_mut(r.device),
            self.device_logs.get_mut(r.device),
        ) {
            // Logged once per change of the link, never once per poll, and rate
            // limited like channels and axes: a flapping device must not flood.
            let course = DeviceCourse::of(r.error.is_some(), r.link_up);
            let t_s = self.pipeline.now_s(sample.started);
            if let Some(more) = log.note(course, t_s) {
                let error = r.error.as_ref().map(|e| (e.kind(), e.to_string()));
                log_device(&d.name, &d.link, course, error, d.failed_cycles, more);
            } else if d.cycles == 0 && course == DeviceCourse::Up {
                tracing::info!(device = %d.name, "device link up");
            }
            d.cycles += 1;
            d.last_cycle = r.poll_elapsed;
            d.connects = r.connects;
            d.link_up = r.link_up;
            for kind in &r.faults {
                *d.errors.entry(kind).or_default() += 1;
            }
            match &r.error {
                Some(e) => {
                    d.failed_cycles += 1;
                    d.last_error = Some(e.to_string());
                }
                None => {
                    d.failed_cycles = 0;
                    d.last_error = None;
                }
            }
        }
        for c in &r.channels {
            // Per sample only the compare inside `note`; a line is built on a change.
            if let (Some(usable), Some(log)) = (
                journal_usable(&c.reading.quality),
                self.channel_logs.get_mut(c.channel),
            ) {
                if let Some(more) = log.note(usable, c.reading.t_s) {
                    let channel = &self.pipeline.channel_names[c.channel];
                    log_channel(channel, Some(&r.device_name), &c.reading.quality, more);
                }
            }
            if let Some(hinted) = self.byte_order_hinted.get_mut(c.channel) {
                if c.reading.quality.is_good() {
                    *hinted = false;
                } else if !*hinted {
                    if let Some(hint) = self.pipeline.byte_order_hint(c.channel, &c.reading) {
                        let channel = &self.pipeline.channel_names[c.channel];
                        tracing::warn!(%channel, device = %r.device_name, "channel {channel} {hint}");
                        *hinted = true;
                    }
                }
            }
        }
    }

    /// NC module `module`'s change of [`NcCourse`], naming the axes on it (two axes on
    /// one target have a writer each).
    fn log_nc(&self, module: usize, course: NcCourse, more: u32) {
        let name = self.nc_names.get(module).map_or("", |n| n);
        let address = self.nc_addresses.get(module).map_or("", |a| a);
        let error = self.nc_errors.get(module).map_or("", |e| e);
        let axis = self
            .pipeline
            .axes
            .iter()
            .filter(|a| a.nc_module == module)
            .map(|a| a.name.as_str())
            .collect::<Vec<_>>()
            .join(",");
        let more = unlogged_suffix(more);
        match course {
            NcCourse::Unreachable => {
                tracing::warn!(%axis, target_name = %name, %address, %error, "NC target unreachable: a job is written only once the read before it gets an answer{more}")
            }
            NcCourse::Refused => {
                tracing::warn!(%axis, target_name = %name, %error, "NC target answered the read with an error: a job is written only once the read before it gets an answer{more}")
            }
            NcCourse::Up => {
                tracing::info!(%axis, target_name = %name, "NC target reachable again{more}")
            }
        }
    }

    /// Logs what the change logs saw but did not log yet (rate limited), at the end of
    /// a generation: the journal's last word must be the state as it is.
    fn flush_change_logs(&mut self) {
        for (ch, log) in self.channel_logs.iter_mut().enumerate() {
            let (Some((_, more)), Some(reading)) = (log.take_unlogged(), self.pipeline.reading(ch))
            else {
                continue;
            };
            // A link failure since is its device's to log.
            if journal_usable(&reading.quality).is_some() {
                let channel = &self.pipeline.channel_names[ch];
                log_channel(channel, None, &reading.quality, more);
            }
        }
        for (i, log) in self.axis_logs.iter_mut().enumerate() {
            if let (Some((course, more)), Some(st)) = (log.take_unlogged(), self.status.axes.get(i))
            {
                log_axis(&st.name, course, &st.decision, false, more);
            }
        }
        for module in 0..self.nc_logs.len() {
            if let Some((course, more)) = self.nc_logs[module].take_unlogged() {
                self.log_nc(module, course, more);
            }
        }
        for (log, d) in self.device_logs.iter_mut().zip(&self.status.devices) {
            if let Some((course, more)) = log.take_unlogged() {
                let error = d.last_error.clone().map(|e| ("", e));
                log_device(&d.name, &d.link, course, error, d.failed_cycles, more);
            }
        }
    }

    /// The status with every channel's latest reading: channels are copied in when
    /// the status is published, not on every sample (at 1M points/s that copy was a
    /// cache miss per point for a status read once a second).
    fn status_now(&mut self) -> &Status {
        self.pipeline.copy_readings_into(&mut self.status.channels);
        &self.status
    }

    /// Shadow mode: `params` are recorded and shown as what would be written, and the
    /// compensator goes on as if the NC had accepted them (so the would-be values
    /// follow the same limits and deadband as real writes); the NC is never written.
    fn on_shadow(&mut self, axis: usize, params: CompParams, observer: &mut dyn Observer) {
        let Some(a) = self.pipeline.axes.get_mut(axis) else {
            return;
        };
        a.comp.confirm(params);
        observer.on_shadow(&a.name, &params);
        tracing::info!(axis = %a.name, sd43900_mm = params.k0_mm, sd43910 = params.tan_beta, sd43920_mm = params.p0_mm, "shadow mode: would write (the NC is not written)");
        let job = JobStatus {
            axis: a.name.clone(),
            at: std::time::SystemTime::now(),
            params,
            shadow: true,
            job_id: None,
            elapsed: None,
            error: None,
        };
        if let Some(st) = self.status.axes.get_mut(axis) {
            st.would_write = Some(params);
            st.jobs_shadow += 1;
        }
        self.status.push_job(job);
    }

    fn on_event(&mut self, event: NcEvent, in_flight: &mut [bool], observer: &mut dyn Observer) {
        match event {
            NcEvent::Snapshot { module, result } => {
                let course = match &result {
                    Ok(_) => NcCourse::Up,
                    Err(e) if e.is_unreachable() => NcCourse::Unreachable,
                    Err(_) => NcCourse::Refused,
                };
                if let (Err(e), Some(slot)) = (&result, self.nc_errors.get_mut(module)) {
                    *slot = e.to_string();
                }
                let t_s = self.pipeline.now_s(Instant::now());
                if let Some(more) = self
                    .nc_logs
                    .get_mut(module)
                    .and_then(|l| l.note(course, t_s))
                {
                    self.log_nc(module, course, more);
                }
                let now_s = self.pipeline.now_s(Instant::now());
                for (i, axis) in self.pipeline.axes.iter_mut().enumerate() {
                    if axis.nc_module != module {
                        continue;
                    }
                    let st = &mut self.status.axes[i];
                    match &result {
                        Ok(snap) => {
                            // The motion heat term counts travel between snapshots
                            // (validate refuses the term on a target without a position).
                            if let Some(pos_mm) = snap.position_mm {
                                axis.comp.on_position(now_s, pos_mm);
                            }
                            let held = snap.thermal();
                            // A restarted NC (or a value changed at the HMI) no longer
                            // holds what it confirmed: a baseline it does not hold
                            // would let a step be any size, and its deadband would
                            // leave the NC uncompensated. A job in flight may not have
                            // landed yet, so only compare without one. A shadow axis'
                            // baseline is its would-be values, which the NC never holds.
                            let moved = self.baselined[i]
                                && !in_flight[i]
                                && !axis.shadow
                                && axis
                                    .comp
                                    .baseline()
                                    .is_some_and(|b| !holds(&b, &held, &axis.nc_write));
                            // A shadow axis goes on from its would-be values after an
                            // outage, as a real run goes on from what it wrote.
                            let keep_shadow = axis.shadow && axis.comp.baseline().is_some();
                            if !self.baselined[i] && keep_shadow {
                                self.baselined[i] = true;
                            } else if !self.baselined[i] || moved {
                                // Step limits and the deadband start from what the NC holds.
                                axis.comp.set_baseline(held);
                                self.baselined[i] = true;
                                // Moved under a running axis, or back from an outage
                                // without what it held (a restart): it runs
                                // uncompensated until the steps catch up.
                                let lost = if moved {
                                    Some(st.written.unwrap_or_default())
                                } else {
                                    st.written.filter(|w| !holds(w, &held, &axis.nc_write))
                                };
                                if let Some(was) = lost {
                                    tracing::warn!(axis = %axis.name, sd43900_mm = snap.sd43900_mm, sd43910 = snap.sd43910, sd43920_mm = snap.sd43920_mm, confirmed_sd43900_mm = was.k0_mm, confirmed_sd43910 = was.tan_beta, confirmed_sd43920_mm = was.p0_mm, "the NC holds other values than it confirmed (restarted, changed by hand, or a job that failed took effect): steps start again from what it holds");
                                } else if st.written.is_some() {
                                    tracing::info!(axis = %axis.name, sd43900_mm = snap.sd43900_mm, sd43910 = snap.sd43910, sd43920_mm = snap.sd43920_mm, "NC parameters read again after the outage");
                                } else {
                                    tracing::info!(axis = %axis.name, sd43900_mm = snap.sd43900_mm, sd43910 = snap.sd43910, sd43920_mm = snap.sd43920_mm, "NC parameters read at start");
                                }
                                st.written = Some(held);
                            }
                            let facts = NcFacts {
                                md32750_wrong: snap.md32750.filter(|&m| m != axis.md32750),
                                unreferenced: snap.referenced == Some(false),
                            };
                            log_nc_facts(&axis.name, axis.md32750, self.nc_facts[i], facts);
                            self.nc_facts[i] = facts;
                            st.warning = facts.warning(axis.md32750);
                            st.md32750_wrong = facts.md32750_wrong.is_some();
                            st.unreferenced = facts.unreferenced;
                            st.nc = Some(*snap);
                            st.nc_reads += 1;
                            st.nc_read_at = Some(std::time::Instant::now());
                        }
                        // The last snapshot is no longer what the NC holds: shown or
                        // recorded, it would pass for a live position. Nothing is
                        // decided until it is read again: the decision says why.
                        Err(e) if e.is_unreachable() => {
                            self.baselined[i] = false;
                            st.nc = None;
                            st.warning = Some(format!("NC unreachable: {e}"));
                            st.decision = "hold: NC unreachable".into();
                            st.at_limit = false;
                        }
                        // It answered: say what, not "unreachable".
                        Err(e) => {
                            self.baselined[i] = false;
                            st.nc = None;
                            st.warning = Some(format!("NC answered with an error: {e}"));
                            st.decision = "hold: NC answered the read with an error".into();
                            st.at_limit = false;
                        }
                    }
                }
            }
            NcEvent::Abandoned { axis } => {
                if let Some(f) = in_flight.get_mut(axis) {
                    *f = false;
                }
                // Landed or not: the next write starts from what the NC holds.
                if let Some(b) = self.baselined.get_mut(axis) {
                    *b = false;
                }
                if let Some(st) = self.status.axes.get_mut(axis) {
                    st.decision =
                        "hold: a job was abandoned at a stop; the NC is read again".into();
                }
            }
            NcEvent::Written {
                axis,
                params,
                result,
            } => {
                if let Some(f) = in_flight.get_mut(axis) {
                    *f = false;
                }
                observer.on_job(&self.pipeline.axes[axis].name, &params, &result);
                let st = &mut self.status.axes[axis];
                let name = &self.pipeline.axes[axis].name;
                // Nothing was written: the NC no longer held what the step was limited
                // from. Not a failing NC: steps start again from what it holds.
                if let Err(e @ NcError::NotHeld { snapshot, .. }) = &result {
                    let was = st.written.unwrap_or_default();
                    tracing::warn!(axis = %name, sd43900_mm = snapshot.k0_mm, sd43910 = snapshot.tan_beta, sd43920_mm = snapshot.p0_mm, confirmed_sd43900_mm = was.k0_mm, confirmed_sd43910 = was.tan_beta, confirmed_sd43920_mm = was.p0_mm, "the NC holds other values than it confirmed (restarted, changed by hand, or a job that failed took effect): steps start again from what it holds");
                    st.written = Some(*snapshot);
                    st.decision =
                        "hold: the NC held other values; steps start again from them".into();
                    let name = name.clone();
                    self.pipeline.axes[axis].comp.set_baseline(*snapshot);
                    self.status.push_job(JobStatus {
                        axis: name,
                        at: std::time::SystemTime::now(),
                        params,
                        shadow: false,
                        job_id: None,
                        elapsed: None,
                        error: Some(e.to_string()),
                    });
                    return;
                }
                // Logged once per change from working to failing and back.
                match (&result, st.last_job_error.is_some()) {
                    (Err(e @ NcError::Refused { .. }), false) => {
                        tracing::warn!(axis = %name, error = %e, "NC refusing jobs");
                    }
                    (Err(e), false) => tracing::warn!(axis = %name, error = %e, "NC jobs failing"),
                    (Ok(_), true) => tracing::info!(axis = %name, "NC jobs succeed again"),
                    _ => {}
                }
                let mut job = JobStatus {
                    axis: name.clone(),
                    at: std::time::SystemTime::now(),
                    params,
                    shadow: false,
                    job_id: None,
                    elapsed: None,
                    error: None,
                };
                match result {
                    Ok(report) => {
                        self.pipeline.axes[axis].comp.confirm(params);
                        st.written = Some(params);
                        st.jobs_ok += 1;
                        st.last_job_error = None;
                        job.job_id = Some(report.job_id);
                        job.elapsed = Some(report.elapsed);
                    }
                    Err(e) => {
                        st.jobs_failed += 1;
                        st.last_job_error = Some(e.to_string());
                        st.last_failure = Some((job.at, e.to_string()));
                        job.error = st.last_job_error.clone();
                    }
                }
                self.status.push_job(job);
            }
        }
    }
}

/// Whether the NC holding `held` holds `written` in every variable the axis writes
/// (to one float32 step: the loosest precision of any target).
fn holds(written: &CompParams, held: &CompParams, nc_write: &[u16]) -> bool {
    let w = Job::thermal_allowed(written, nc_write).pairs;
    let h = Job::thermal_allowed(held, nc_write).pairs;
    w.iter()
        .zip(&h)
        .all(|((_, w), (_, h))| crate::nc::Precision::F32.holds(*w, *h))
}

/// How long past its due time an axis waits for a sample of its inputs before the
/// timer decides without one (at least its own update interval).
const DECIDE_FALLBACK: Duration = Duration::from_secs(1);

/// Sets axis `i`'s `outside_fit`, logging when it starts (WARN) and ends (INFO).
fn note_outside_fit(state: &mut Running, i: usize) {
    let st = &mut state.status.axes[i];
    let outside = state.pipeline.outside_fit(i, st.outside_fit.as_deref());
    match (&outside, &st.outside_fit) {
        (Some(why), None) => tracing::warn!(axis = %st.name, "axis {}: {why}", st.name),
        (None, Some(_)) => tracing::info!(
            axis = %st.name,
            "axis {}: its inputs are within the temperatures the model was fitted over again",
            st.name
        ),
        _ => {}
    }
    st.outside_fit = outside;
}

/// Runs axis `i`'s decision at `at` and hands a write to its NC task (one job in
/// flight per axis), or, in shadow mode, only reports it.
fn decide_axis(
    state: &mut Running,
    i: usize,
    at: Instant,
    next_update: &mut [Instant],
    in_flight: &mut [bool],
    nc_tx: &[mpsc::Sender<NcCommand>],
    observer: &mut dyn Observer,
) {
    next_update[i] = at + state.pipeline.axes[i].update_interval;
    // Whatever the NC does: a model that extrapolates is worth knowing in a dry run
    // against an NC that does not answer, too.
    note_outside_fit(state, i);
    let pipeline = &mut state.pipeline;
    if !state.baselined[i] || in_flight[i] {
        return;
    }
    // The NC runs another compensation type than the model is for: a written value
    // would compensate wrongly. A shadow axis holds too, as the real run would.
    if let Some(nc) = state.nc_facts[i].md32750_wrong {
        let expected = pipeline.axes[i].md32750;
        state.status.axes[i].decision =
            format!("hold: MD32750 is {nc} on the NC, the config expects {expected}");
        state.status.axes[i].at_limit = false;
        return;
    }
    let decision = pipeline.decide(i, at);
    let axis = &pipeline.axes[i];
    let (shadow, module) = (axis.shadow, axis.nc_module);
    let beyond = axis.comp.beyond_limit();
    let text = describe(
        &decision,
        beyond.as_ref(),
        axis.comp.limits(),
        &pipeline.channel_names,
        &axis.inputs,
    );
    let course = AxisCourse::of(&decision, beyond.is_some());
    if let Some(more) = state.axis_logs[i].note(course, pipeline.now_s(at)) {
        // Inputs bad only because their device's link is down: the device's line
        // warned already, this one says what the axis does about it.
        let link_only = match &decision {
            Decision::Hold { bad_inputs } | Decision::Ramp { bad_inputs, .. } => {
                !bad_inputs.is_empty()
                    && bad_inputs.iter().all(|&k| {
                        let quality = axis.inputs.get(k).and_then(|&ch| pipeline.quality(ch));
                        quality.is_some_and(|q| journal_usable(&q).is_none())
                    })
            }
            _ => false,
        };
        log_axis(&axis.name, course, &text, link_only, more);
    }
    state.status.axes[i].decision = text;
    state.status.axes[i].at_limit = course == AxisCourse::AtLimit;
    let params = match decision {
        Decision::Write { params, .. } | Decision::Ramp { params, .. } => params,
        Decision::WithinDeadband | Decision::Hold { .. } => return,
    };
    if shadow {
        state.on_shadow(i, params, observer);
        return;
    }
    let axis = &state.pipeline.axes[i];
    let job = Job::thermal_allowed(&params, &axis.nc_write);
    if nc_tx[module]
        .try_send(NcCommand::Write {
            axis: i,
            axis_name: axis.name.clone(),
            job,
            params,
            from: axis.comp.baseline(),
        })
        .is_ok()
    {
        in_flight[i] = true;
    }
}

/// An axis' NC facts going from `was` to `now`: a wrong MD32750 and an axis not
/// referenced are each logged once per change (WARN), and their end (INFO).
fn log_nc_facts(axis: &str, md32750_config: u16, was: NcFacts, now: NcFacts) {
    match (was.md32750_wrong, now.md32750_wrong) {
        (w, Some(nc)) if w != Some(nc) => {
            tracing::warn!(%axis, md32750_nc = nc, md32750_config, "axis {axis}: MD32750 is {nc} on the NC, the config expects {md32750_config}: the axis holds, nothing is written to it")
        }
        (Some(_), None) => {
            tracing::info!(%axis, md32750 = md32750_config, "axis {axis}: MD32750 on the NC matches the config again: writes resume")
        }
        _ => {}
    }
    match (was.unreferenced, now.unreferenced) {
        (false, true) => {
            tracing::warn!(%axis, "axis {axis} is not referenced on the NC: it applies no temperature compensation until referenced; setting data written meanwhile take effect then")
        }
        (true, false) => {
            tracing::info!(%axis, "axis {axis} is referenced again: the NC applies the compensation")
        }
        _ => {}
    }
}

/// A channel's change to bad (WARN) or back to usable (INFO); `device` when known.
fn log_channel(channel: &str, device: Option<&str>, quality: &Quality, more: u32) {
    let more = unlogged_suffix(more);
    match quality {
        Quality::Bad(reason) => {
            tracing::warn!(%channel, device, reason = reason.as_str(), "channel {channel} bad: {reason}{more}")
        }
        q => {
            tracing::info!(%channel, device, quality = %q, "channel {channel} usable again ({q}){more}")
        }
    }
}

/// What the journal says of an NC target, from its snapshots.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum NcCourse {
    /// Its last read answered.
    Up,
    /// Its last read did not reach it.
    Unreachable,
    /// It answered its last read with an error.
    Refused,
}

/// What the journal says of a device's link.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum DeviceCourse {
    /// Every read answered.
    Up,
    /// The device answers, but a read failed: only its channels go bad.
    ReadFailed,
    /// The device did not answer at all.
    Down,
}

impl DeviceCourse {
    fn of(failed: bool, answered: bool) -> Self {
        match (failed, answered) {
            (false, _) => Self::Up,
            (true, true) => Self::ReadFailed,
            (true, false) => Self::Down,
        }
    }
}

/// A device's change of [`DeviceCourse`]: `error` is the cycle's first, with its kind
/// ("" when not known), and `failed_cycles` the failed cycles before an `Up`.
fn log_device(
    device: &str,
    link: &str,
    course: DeviceCourse,
    error: Option<(&str, String)>,
    failed_cycles: u32,
    more: u32,
) {
    let more = unlogged_suffix(more);
    let (kind, error) = error.unwrap_or_default();
    match course {
        DeviceCourse::Down => {
            tracing::warn!(%device, %link, kind, %error, "device link down: its channels hold their last values, then go bad{more}")
        }
        DeviceCourse::ReadFailed => {
            tracing::warn!(%device, %link, kind, %error, "device {device} answers, but a read failed: its channels hold their last values, then go bad{more}")
        }
        DeviceCourse::Up => {
            tracing::info!(%device, failed_cycles, "device link up again: every read answered{more}")
        }
    }
}

/// An axis' change from following its model to hold or ramp to zero (WARN; INFO when
/// `link_only`: its inputs are bad only because their device's link is down) or back
/// (INFO); `decision` is its [`describe`] text, naming the bad inputs.
fn log_axis(axis: &str, course: AxisCourse, decision: &str, link_only: bool, more: u32) {
    let more = unlogged_suffix(more);
    match course {
        AxisCourse::Fallback if link_only => {
            tracing::info!(%axis, decision, "axis {axis} no longer follows its model: {decision} (inputs lost with their device){more}")
        }
        AxisCourse::Fallback => {
            tracing::warn!(%axis, decision, "axis {axis} no longer follows its model: {decision}{more}")
        }
        AxisCourse::AtLimit => {
            tracing::warn!(%axis, decision, "axis {axis} is held at its limit: {decision}; check the model and the limit{more}")
        }
        AxisCourse::Model => {
            tracing::info!(%axis, decision, "axis {axis} follows its model again: {decision}{more}")
        }
    }
}

async fn next_reload(reload: &mut Option<mpsc::Receiver<Config>>) -> Config {
    if let Some(rx) = reload {
        if let Some(cfg) = rx.recv().await {
            return cfg;
        }
    }
    *reload = None;
    std::future::pending().await
}

/// Runs one generation. Returns the next config and its parts when a reload ended it,
/// `None` on shutdown.
async fn generation(
    state: &mut Running,
    shutdown: &CancellationToken,
    status_tx: &watch::Sender<Status>,
    hooks: &mut Hooks,
) -> Option<(Box<Config>, Box<Built>)> {
    status_tx.send_replace(state.status_now().clone());
    // Devices and SYNC producers: between two polls, after the NC tasks.
    let stop = shutdown.child_token();
    // NC tasks: at once (a job in flight gets its grace), on shutdown or a reload.
    let nc_stop = shutdown.child_token();
    let (sample_tx, mut sample_rx) = mpsc::channel::<DeviceSample>(SAMPLE_QUEUE);
    let mut tasks = tokio::task::JoinSet::new();
    for (i, dev) in state.devices.iter_mut().enumerate() {
        if let Some(dev) = dev.take() {
            tasks.spawn(device_task(
                i,
                dev,
                sample_tx.clone(),
                stop.clone(),
                shutdown.clone(),
            ));
        }
    }
    drop(sample_tx);
    // Each generation starts the producers of its own config; they stop with `stop`
    // like the device tasks, so a reload that changes an interface or its period
    // takes effect and a shutdown leaves no SYNC on the bus.
    for p in &state.sync_producers {
        tasks.spawn(sync_task(p.clone(), stop.clone()));
    }

    let (event_tx, mut event_rx) = mpsc::channel::<NcEvent>(16);
    let mut nc_tx = Vec::new();
    for (i, nc) in state.nc_modules.iter_mut().enumerate() {
        let (tx, rx) = mpsc::channel(4);
        nc_tx.push(tx);
        if let Some(nc) = nc.take() {
            tasks.spawn(nc_task(
                i,
                nc,
                rx,
                event_tx.clone(),
                nc_snapshot_interval(state.status_interval),
                nc_stop.clone(),
            ));
        }
    }
    drop(event_tx);

    // Per axis: next decision time, and whether a job is in flight (one at a time).
    let now = Instant::now();
    let mut next_update: Vec<Instant> = state
        .pipeline
        .axes
        .iter()
        .map(|a| now + a.update_interval)
        .collect();
    let mut in_flight = vec![false; state.pipeline.axes.len()];
    // Per device: the axes its channels feed, learnt from its first sample.
    let mut feeds: Vec<Option<Vec<usize>>> = Vec::new();
    let mut status_tick = tokio::time::interval(state.status_interval);
    status_tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
    // Its own period, whatever the status interval: systemd's watchdog needs pings
    // more often than a slow status tick would send them.
    let watchdog_on = hooks.watchdog_interval.is_some();
    let mut watchdog_tick =
        tokio::time::interval(hooks.watchdog_interval.unwrap_or(Duration::from_secs(3600)));
    watchdog_tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
    let far = now + Duration::from_secs(86_400 * 365);
    let mut events_open = true;
    let mut reload_to: Option<(Box<Config>, Box<Built>)> = None;
    let observer = &mut *hooks.observer;

    loop {
        // A reload waits for the NC tasks to end (at most a job's grace) with the
        // devices still polling, the status and the watchdog going.
        if reload_to.is_some() && !events_open {
            break;
        }
        let deciding = reload_to.is_none();
        // An axis decides when a sample of its inputs arrives and its interval is up,
        // so a change reaches the NC one poll after it happens. The timer only stands
        // in when no input sample came for a while past the due time (an input device
        // that stopped sending), so hold and ramp still go on.
        let fallback = state
            .pipeline
            .axes
            .iter()
            .zip(&next_update)
            .map(|(a, &due)| due + a.update_interval.max(DECIDE_FALLBACK))
            .min()
            .unwrap_or(far);
        tokio::select! {
            sample = sample_rx.recv() => {
                let Some(sample) = sample else { break };
                state.on_sample(&sample);
                observer.on_sample(&state.readings);
                if feeds.len() <= sample.device {
                    feeds.resize(sample.device + 1, None);
                }
                let axes = feeds[sample.device].get_or_insert_with(|| {
                    state
                        .pipeline
                        .axes
                        .iter()
                        .enumerate()
                        .filter(|(_, a)| sample.values.iter().any(|(ch, _)| a.inputs.contains(ch)))
                        .map(|(i, _)| i)
                        .collect()
                });
                let at = Instant::now();
                for &i in axes.iter() {
                    if deciding && next_update[i] <= at {
                        decide_axis(state, i, at, &mut next_update, &mut in_flight, &nc_tx, observer);
                    }
                }
            }
            event = event_rx.recv(), if events_open => {
                // No NC modules (a monitoring-only config): the channel closes at once.
                let Some(event) = event else {
                    events_open = false;
                    continue;
                };
                state.on_event(event, &mut in_flight, observer);
            }
            _ = tokio::time::sleep_until(fallback), if fallback < far && deciding => {
                let at = Instant::now();
                for i in 0..state.pipeline.axes.len() {
                    let a = &state.pipeline.axes[i];
                    if next_update[i] + a.update_interval.max(DECIDE_FALLBACK) <= at {
                        decide_axis(state, i, at, &mut next_update, &mut in_flight, &nc_tx, observer);
                    }
                }
            }
            _ = watchdog_tick.tick(), if watchdog_on => {
                // Called from the control loop itself: a stuck loop stops the pings.
                observer.on_watchdog();
            }
            _ = status_tick.tick() => {
                // Called from the control loop itself: a stuck loop stops the watchdog.
                let status = state.status_now();
                observer.on_status(status);
                status_tx.send_replace(status.clone());
            }
            new_cfg = next_reload(&mut hooks.reload), if reload_to.is_none() => {
                match build(&new_cfg) {
                    Ok(built) => {
                        tracing::info!("reload: stopping the running generation between polls");
                        reload_to = Some((Box::new(new_cfg), Box::new(built)));
                        nc_stop.cancel();
                    }
                    Err(e) => {
                        tracing::error!(error = %e, "reload refused: the running configuration stays");
                        observer.on_reload(&Err(e));
                    }
                }
            }
        }
    }
    stop.cancel();
    // A device task ending its last poll must not wait on a full queue.
    drop(sample_rx);
    drop(nc_tx);
    // On shutdown: take the results of jobs in flight (they end within their grace).
    while let Some(event) = event_rx.recv().await {
        state.on_event(event, &mut in_flight, observer);
    }
    while let Some(done) = tasks.join_next().await {
        match done {
            Ok(Returned::Device(i, dev)) => state.devices[i] = Some(dev),
            Ok(Returned::Nc(i, nc)) => state.nc_modules[i] = Some(nc),
            Ok(Returned::Sync | Returned::Aborted) => {}
            Err(e) => tracing::error!(error = %e, "gateway task failed"),
        }
    }
    if shutdown.is_cancelled() {
        return None;
    }
    state.flush_change_logs();
    reload_to
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::Fault;
    use compgate_core::channel::Reading;
    use compgate_core::channel::{Quality, Reason};

    fn demo() -> Config {
        crate::config::load_str(include_str!("../../../../config/demo.toml"), "demo.toml")
            .expect("demo config")
    }

    /// The channels of the first device (index 0), in config order.
    fn first_device_channels(cfg: &Config) -> Vec<usize> {
        let device = cfg.devices.keys().next().expect("a device");
        cfg.channels
            .values()
            .enumerate()
            .filter(|(_, c)| &c.device == device)
            .map(|(ch, _)| ch)
            .collect()
    }

    fn sample(p: &Pipeline, channels: &[usize], k: u32, fault_on: Option<usize>) -> DeviceSample {
        let values = channels
            .iter()
            .map(|&ch| {
                let value = if Some(ch) == fault_on {
                    Err(Fault {
                        reason: Reason::Comm,
                        degraded: false,
                    })
                } else {
                    // About 30 degC, one count of noise.
                    Ok(1774.0 + f64::from((k + ch as u32) % 2))
                };
                (ch, value)
            })
            .collect();
        DeviceSample {
            device: 0,
            started: p.epoch + Duration::from_millis(100 * u64::from(k)),
            elapsed: Duration::ZERO,
            values,
            error: None,
            faults: Vec::new(),
            connects: 1,
        }
    }

    fn readings(p: &Pipeline) -> Vec<Reading> {
        (0..p.channel_names.len())
            .map(|ch| p.reading(ch).expect("reading"))
            .collect()
    }

    // A fault shows in the channel's quality with its value held, and a reload of an
    // unchanged config carries every channel's state over whole.
    #[test]
    fn a_fault_holds_the_value_and_a_reload_keeps_the_channels() {
        let cfg = demo();
        let channels = first_device_channels(&cfg);
        assert!(channels.len() >= 4, "{} channels", channels.len());
        let mut p = build(&cfg).expect("build").pipeline;
        let mut out = Vec::new();
        for k in 0..30 {
            p.ingest(&sample(&p, &channels, k, None), &mut out);
        }
        let before = readings(&p);
        let ch = channels[0];
        assert_eq!(before[ch].quality, Quality::Good);
        assert!(before[ch]
            .value_degc
            .is_some_and(|v| (v - 30.0).abs() < 0.1));
        // A missing sample: held value, uncertain.
        p.ingest(&sample(&p, &channels, 30, Some(ch)), &mut out);
        let r = p.reading(ch).expect("reading");
        assert_eq!(r.quality, Quality::Uncertain(Reason::Comm));
        assert_eq!(r.value_degc, before[ch].value_degc);
        let now = readings(&p);

        let old = Running::new(Built {
            pipeline: p,
            ..build(&cfg).expect("build")
        });
        let next = reload::transplant(&cfg, &cfg, old, build(&cfg).expect("build"));
        assert_eq!(readings(&next.pipeline), now);
        let shown: Vec<Reading> = next
            .status
            .channels
            .iter()
            .map(|c| c.reading.clone())
            .collect();
        assert_eq!(shown, now);
        // The carried processors go on from their state: the next good sample of the
        // faulted channel is good again.
        let mut p = next.pipeline;
        p.ingest(&sample(&p, &channels, 31, None), &mut out);
        assert_eq!(p.reading(ch).expect("reading").quality, Quality::Good);
    }

    // Shadow mode on or off by reload: the axis starts again from what the NC holds
    // (its would-be values are no baseline for real writes); an unchanged reload
    // keeps the axis and the job history.
    #[test]
    fn a_reload_into_shadow_mode_starts_the_axis_from_the_nc_again() {
        let cfg = demo();
        let running = |cfg: &Config| {
            let mut r = Running::new(build(cfg).expect("build"));
            r.baselined[0] = true;
            r.status.axes[0].jobs_ok = 3;
            r.status.push_job(JobStatus {
                axis: "X".into(),
                at: std::time::SystemTime::UNIX_EPOCH,
                params: CompParams::default(),
                shadow: false,
                job_id: Some(1),
                elapsed: None,
                error: None,
            });
            r
        };
        let same = reload::transplant(&cfg, &cfg, running(&cfg), build(&cfg).expect("build"));
        assert!(same.baselined[0]);
        assert_eq!(same.status.axes[0].jobs_ok, 3);
        assert!(!same.pipeline.axes[0].shadow);

        let mut shadow = cfg.clone();
        shadow.gateway.shadow = true;
        let next = reload::transplant(&cfg, &shadow, running(&cfg), build(&shadow).expect("build"));
        assert!(next.pipeline.axes[0].shadow);
        assert!(next.status.axes[0].shadow);
        assert!(!next.baselined[0], "carried a baseline into shadow mode");
        assert_eq!(next.status.axes[0].jobs_ok, 3, "job counts kept");
        assert_eq!(next.status.jobs.len(), 1, "job history kept");
    }

    // Every reload logged "NC target unreachable" again for a target still down, and
    // an axis whose model changed showed its job counts from zero while
    // `compgate_nc_jobs_total` went on.
    #[test]
    fn a_reload_keeps_what_the_journal_was_told_of_a_target_and_the_job_counts() {
        let cfg = demo();
        let running = |cfg: &Config| {
            let mut r = Running::new(build(cfg).expect("build"));
            r.nc_logs[0] = ChangeLog::new(NcCourse::Unreachable);
            r.status.axes[0].jobs_ok = 7;
            r.status.axes[0].jobs_failed = 2;
            r
        };
        let mut model = cfg.clone();
        let x = model.axes.values_mut().next().expect("an axis");
        x.max_abs_k0_mm *= 0.5;
        let mut next =
            reload::transplant(&cfg, &model, running(&cfg), build(&model).expect("build"));
        assert!(
            next.nc_logs[0].take_unlogged().is_none()
                && next.nc_logs[0].note(NcCourse::Unreachable, 0.0).is_none(),
            "the target is still down: nothing new to log"
        );
        assert_eq!(
            (next.status.axes[0].jobs_ok, next.status.axes[0].jobs_failed),
            (7, 2)
        );

        let mut moved = cfg.clone();
        for m in moved.nc_modules.values_mut() {
            m.unit_id += 1;
        }
        let mut next =
            reload::transplant(&cfg, &moved, running(&cfg), build(&moved).expect("build"));
        assert!(
            next.nc_logs[0].note(NcCourse::Unreachable, 0.0).is_some(),
            "another target: its state is logged afresh"
        );
    }

    // The core loop builds one value per sample: the link outcome and the new reading
    // of exactly the sample's channels; the status shows the same.
    #[test]
    fn one_sample_builds_its_readings_once_for_status_and_observers() {
        let cfg = demo();
        let channels = first_device_channels(&cfg);
        let mut state = Running::new(build(&cfg).expect("build"));
        let mut s = sample(&state.pipeline, &channels, 1, Some(channels[1]));
        s.error = Some(crate::source::SourceError::Timeout(Duration::from_millis(
            200,
        )));
        s.elapsed = Duration::from_millis(3);
        s.connects = 2;
        state.on_sample(&s);
        let shown = state.status_now().channels.clone();

        let r = &state.readings;
        assert_eq!(r.device, 0);
        assert_eq!(
            &*r.device_name,
            cfg.devices.keys().next().expect("device").as_str()
        );
        assert_eq!(r.error, s.error);
        assert_eq!((r.poll_elapsed, r.connects), (s.elapsed, 2));
        let got: Vec<usize> = r.channels.iter().map(|c| c.channel).collect();
        assert_eq!(got, channels);
        for (name, c) in r.named() {
            assert_eq!(name, state.pipeline.channel_names[c.channel]);
            assert_eq!(Some(&c.reading), state.pipeline.reading(c.channel).as_ref());
            assert_eq!(shown[c.channel].reading, c.reading);
        }
        assert_eq!(r.channels[0].reading.quality, Quality::Good);
        assert_eq!(r.channels[1].reading.quality, Quality::Bad(Reason::NoData));
        let d = &state.status.devices[0];
        assert_eq!((d.cycles, d.failed_cycles, d.connects), (1, 1, 2));
        assert_eq!(d.last_error, s.error.as_ref().map(ToString::to_string));
        assert_eq!(state.status.samples, 1);
    }

    // A device's values come in channel (config) order, whatever the register order:
    // the core loop walks its processors front to back. Each channel still gets the
    // value of its own register.
    #[tokio::test]
    async fn a_sample_lists_channels_in_config_order_each_with_its_own_register() {
        use compgate_plc::field::{FieldModule, FieldModuleSpec, Profile, TransmitterSpec};
        let n = 12;
        let degc = |address: usize| 10.0 + 5.0 * address as f64;
        let module = FieldModule::new(FieldModuleSpec::new(
            (0..n)
                .map(|a| TransmitterSpec::new(Profile::Constant { degc: degc(a) }, -50.0, 150.0))
                .collect(),
            1,
        ))
        .expect("field module");
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .expect("bind");
        let port = listener.local_addr().expect("address").port();
        let stop = CancellationToken::new();
        tokio::spawn(module.serve_tcp(listener, stop.clone()));

        // Names sort against the addresses: "c11" holds register 0, "c00" register 11,
        // and "c05" sits between "c04" and "c06" only by name.
        let mut text = format!(
            "[devices.d]\ntransport = \"tcp\"\naddress = \"127.0.0.1:{port}\"\nunit_id = 1\n\n"
        );
        for a in 0..n {
            text.push_str(&format!(
                "[channels.c{:02}]\ndevice = \"d\"\nregister = \"input\"\naddress = {a}\ndata_type = \"u16\"\nscaling = {{ kind = \"transmitter\", adc_full_scale_counts = 4095, adc_full_scale_ma = 24.0, current_range = \"4-20\", range_min_degc = -50.0, range_max_degc = 150.0 }}\n\n",
                n - 1 - a
            ));
        }
        let cfg = crate::config::load_str(&text, "order.toml").expect("config");
        let mut built = build(&cfg).expect("build");
        let sample = built.devices[0].poller.poll().await;
        stop.cancel();
        assert_eq!(sample.error, None);
        let order: Vec<usize> = sample.values.iter().map(|(ch, _)| *ch).collect();
        assert_eq!(order, (0..n).collect::<Vec<_>>());
        let mut out = Vec::new();
        built.pipeline.ingest(&sample, &mut out);
        for (name, c) in built.pipeline.channel_names.iter().zip(&out) {
            let address = n - 1 - name[1..].parse::<usize>().expect("number");
            let got = c.reading.unfiltered_degc.expect("a value");
            // One ADC count is about 0.06 degC on this range.
            assert!((got - degc(address)).abs() < 0.1, "{name}: {got} degC");
        }
    }

    /// The messages of the events logged while `f` runs (this thread only).
    fn logged(f: impl FnOnce()) -> Vec<String> {
        use std::sync::Mutex;
        use tracing::field::{Field, Visit};
        #[derive(Default)]
        struct Lines(Mutex<Vec<String>>);
        struct Message(String);
        impl Visit for Message {
            fn record_debug(&mut self, field: &Field, value: &dyn std::fmt::Debug) {
                if field.name() == "message" {
                    self.0 = format!("{value:?}");
                }
            }
        }
        impl tracing::Subscriber for Lines {
            fn enabled(&self, _: &tracing::Metadata<'_>) -> bool {
                true
            }
            fn new_span(&self, _: &tracing::span::Attributes<'_>) -> tracing::span::Id {
                tracing::span::Id::from_u64(1)
            }
            fn record(&self, _: &tracing::span::Id, _: &tracing::span::Record<'_>) {}
            fn record_follows_from(&self, _: &tracing::span::Id, _: &tracing::span::Id) {}
            fn event(&self, event: &tracing::Event<'_>) {
                let mut m = Message(String::new());
                event.record(&mut m);
                self.0.lock().unwrap().push(m.0);
            }
            fn enter(&self, _: &tracing::span::Id) {}
            fn exit(&self, _: &tracing::span::Id) {}
        }
        let lines = Arc::new(Lines::default());
        tracing::subscriber::with_default(lines.clone(), f);
        let out = lines.0.lock().unwrap().clone();
        out
    }

    /// A sample of `channels` at `t_s` in which channel `failed` (if any) failed with
    /// `reason`, its read's error `error`.
    fn failed_sample(
        p: &Pipeline,
        channels: &[usize],
        t_s: f64,
        failed: Option<(usize, Reason)>,
    ) -> DeviceSample {
        let mut s = sample(p, channels, 0, None);
        s.started = p.epoch + Duration::from_secs_f64(t_s);
        if let Some((ch, reason)) = failed {
            for (c, v) in &mut s.values {
                if *c == ch || reason == Reason::Comm {
                    *v = Err(Fault {
                        reason,
                        degraded: false,
                    });
                }
            }
            s.error = Some(crate::source::SourceError::Read {
                read: "function 0x04 (input registers), address 5, count 1 (T)".into(),
                hint: None,
                source: Box::new(if reason == Reason::Comm {
                    crate::source::SourceError::Timeout(Duration::from_millis(300))
                } else {
                    crate::source::SourceError::Exception(
                        tokio_modbus::ExceptionCode::IllegalDataAddress,
                    )
                }),
            });
            s.faults = vec![s.error.as_ref().expect("error").kind()];
        }
        s
    }

    // One register answering exception 0x02 took the whole device "link down"
    // (`compgate_device_link_up 0`) though its other channels read good: the device
    // is up, the log names the read, and only that read's channel goes bad.
    #[test]
    fn a_failed_read_of_a_device_that_answers_is_no_link_down() {
        let cfg = demo();
        let channels = first_device_channels(&cfg);
        let mut state = Running::new(build(&cfg).expect("build"));
        let bad = channels[1];
        let lines = logged(|| {
            let s = failed_sample(
                &state.pipeline,
                &channels,
                0.1,
                Some((bad, Reason::DeviceException)),
            );
            state.on_sample(&s);
        });
        assert!(state.readings.link_up);
        let d = &state.status.devices[0];
        assert!(d.link_up);
        assert_eq!(d.errors.get("exception"), Some(&1));
        let line = lines
            .iter()
            .find(|l| l.contains("read failed"))
            .expect("a line");
        assert!(!lines.iter().any(|l| l.contains("link down")), "{lines:?}");
        assert!(line.contains("answers, but a read failed"), "{line}");
        let error = d.last_error.as_deref().expect("an error");
        assert!(
            error.contains("address 5, count 1 (T): device exception 0x02"),
            "{error}"
        );
        let quality = |ch: usize| state.pipeline.quality(ch).expect("quality");
        assert_eq!(quality(bad), Quality::Bad(Reason::NoData));
        assert_eq!(quality(channels[0]), Quality::Good);

        // A device that answers nothing is down.
        let s = failed_sample(&state.pipeline, &channels, 0.2, Some((bad, Reason::Comm)));
        let lines = logged(|| state.on_sample(&s));
        assert!(!state.status.devices[0].link_up);
        assert!(
            lines.iter().any(|l| l.contains("device link down")),
            "{lines:?}"
        );
    }

    // A device failing every other poll for 20 s logged 40 lines of down and up: now
    // at most two lines per 10 s window, and the last word is the state as it is.
    #[test]
    fn a_flapping_device_link_is_logged_at_most_twice_per_window() {
        let cfg = demo();
        let channels = first_device_channels(&cfg);
        let mut state = Running::new(build(&cfg).expect("build"));
        let lines = logged(|| {
            for k in 0..40 {
                let fault = (k % 2 == 1).then_some((channels[0], Reason::Comm));
                let s = failed_sample(&state.pipeline, &channels, 0.5 * f64::from(k), fault);
                state.on_sample(&s);
            }
            state.flush_change_logs();
        });
        let device: Vec<&String> = lines.iter().filter(|l| l.contains("device")).collect();
        // The first "link up", two per window in 20 s, the flushed last state.
        assert!(device.len() <= 1 + 2 * 2 + 1, "{device:#?}");
        assert!(
            device
                .iter()
                .any(|l| l.contains("more changes since the last line")),
            "{device:#?}"
        );
        let last = device.last().expect("a line");
        assert!(
            last.contains("device link down"),
            "the last sample failed: {last}"
        );
    }

    // Each NC snapshot's actual position feeds the axis' motion heat term.
    #[test]
    fn nc_snapshots_feed_the_motion_heat_term() {
        let mut cfg = demo();
        let axis = cfg.axes.values_mut().next().expect("an axis");
        axis.motion_heat = Some(crate::axis::MotionHeatModel {
            tau_s: 100.0,
            ref_mm_per_s: 0.0,
            k0_mm_per_mm_per_s: 0.001,
            tan_beta_per_mm_per_s: 0.0,
        });
        let mut state = Running::new(build(&cfg).expect("build"));
        let module = state.pipeline.axes[0].nc_module;
        let mut in_flight = vec![false];
        for pos_mm in [0.0, 500.0, 200.0] {
            let snap = NcSnapshot {
                position_mm: Some(pos_mm),
                ..NcSnapshot::default()
            };
            state.on_event(
                NcEvent::Snapshot {
                    module,
                    result: Ok(snap),
                },
                &mut in_flight,
                &mut (),
            );
        }
        // 800 mm of travel into a 100 s store, well within one time constant.
        let heat = state.pipeline.axes[0].comp.dynamics().heat_mm_per_s();
        assert!(heat > 7.0 && heat <= 8.0, "{heat}");
    }

    // An NC whose replies took as long as its timeout logged an "unreachable" and a
    // "reachable again" every few seconds, 30 lines a minute; devices, channels and
    // axes were rate limited already.
    #[test]
    fn a_flapping_nc_target_is_logged_at_most_twice_per_window() {
        let cfg = demo();
        let mut state = Running::new(build(&cfg).expect("build"));
        let module = state.pipeline.axes[0].nc_module;
        let mut in_flight = vec![false];
        let lines = logged(|| {
            for k in 0..10 {
                let result = if k % 2 == 0 {
                    Err(NcError::Unreachable("connect timed out".into()))
                } else {
                    Ok(NcSnapshot::default())
                };
                state.on_event(
                    NcEvent::Snapshot { module, result },
                    &mut in_flight,
                    &mut (),
                );
            }
            state.flush_change_logs();
        });
        let nc: Vec<&String> = lines.iter().filter(|l| l.contains("NC target")).collect();
        assert_eq!(nc.len(), 3, "{nc:#?}");
        assert!(
            nc[0].contains("unreachable") && nc[1].contains("reachable again"),
            "{nc:#?}"
        );
        // The last word is the state as it is, with what was not logged.
        assert!(
            nc[2].contains("reachable again") && nc[2].contains("7 more changes"),
            "{nc:#?}"
        );
    }
}
