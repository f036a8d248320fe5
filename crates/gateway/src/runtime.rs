//! The running gateway: sources -> channels -> compensation -> NC writer.
//!
//! [`build`] turns a validated [`Config`] into runtime parts; [`run`] starts one task
//! per device, one SYNC producer per CAN interface and one task per NC module around a
//! core loop that owns every channel processor and axis compensator. Only the device
//! and SYNC tasks watch the shutdown token: when the device tasks end, the core loop
//! sees its input close, finishes, and drops the NC command channels, so an NC job in
//! flight completes before the NC tasks stop.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::{mpsc, watch, Mutex};
use tokio::time::{Instant, MissedTickBehavior};
use tokio_util::sync::CancellationToken;

use crate::config::{self, Config};
use crate::nc::{Job, JobReport, ModbusNcWriter, NcError, NcSnapshot, NcWriter};
use crate::source::can::sync::{self, SyncDevice, SyncParams};
use crate::source::can::{CanChannelSpec, CanObject, CanParams, CanPoller};
use crate::source::modbus::{Backoff, LinkSpec, ModbusLink};
use crate::source::{ChannelSpec, DevicePoller, DeviceSample, PollParams, SharedLink};
use compgate_core::channel::{
    Bank, ChannelProcessor, CurrentRange, FilterParams, LowPassGain, Reading, Scaling,
};
use compgate_core::comp::{
    Affine, AxisCompensator, BadInputPolicy, CompParams, Decision, Limits, Term, ThermalModel,
};

mod hooks;
mod reload;
pub use hooks::{Hooks, Observer, Observers};

/// Errors of the gateway layer.
#[derive(Debug, thiserror::Error)]
pub enum GatewayError {
    /// The configuration cannot be turned into a running gateway.
    #[error("config: {0}")]
    Config(String),
}

/// What the gateway shows of one channel.
#[derive(Debug, Clone, PartialEq)]
pub struct ChannelStatus {
    /// Channel name.
    pub name: String,
    /// The last reading.
    pub reading: Reading,
}

/// What the gateway shows of one device.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct DeviceStatus {
    /// Device name.
    pub name: String,
    /// Link description.
    pub link: String,
    /// Poll cycles run.
    pub cycles: u64,
    /// Cycles with at least one failed read, in a row.
    pub failed_cycles: u32,
    /// Last error, if the last cycle had one.
    pub last_error: Option<String>,
    /// Errors counted by kind (timeout, transport, exception, ...).
    pub errors: BTreeMap<&'static str, u64>,
    /// Duration of the last poll cycle.
    pub last_cycle: Duration,
    /// Connections made to the device so far.
    pub connects: u64,
}

/// What the gateway shows of one axis.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct AxisStatus {
    /// Axis name.
    pub name: String,
    /// Parameters the NC accepted last (read at start, then each verified write).
    pub written: Option<CompParams>,
    /// The last decision, in words.
    pub decision: String,
    /// Jobs that ended verified.
    pub jobs_ok: u64,
    /// Jobs that failed.
    pub jobs_failed: u64,
    /// The last job error.
    pub last_job_error: Option<String>,
    /// The NC's last snapshot.
    pub nc: Option<NcSnapshot>,
    /// A warning a commissioning engineer must see (MD32750 mismatch, NC unreachable).
    pub warning: Option<String>,
}

/// Everything the status line, logs and tests look at.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Status {
    /// Per channel, in config order.
    pub channels: Vec<ChannelStatus>,
    /// Per device.
    pub devices: Vec<DeviceStatus>,
    /// Per axis.
    pub axes: Vec<AxisStatus>,
    /// Device samples processed.
    pub samples: u64,
}

/// One axis at run time.
#[derive(Debug)]
pub struct AxisRt {
    /// Axis name.
    pub name: String,
    /// Index of its NC module.
    pub nc_module: usize,
    /// Channel index of each model input.
    pub inputs: Vec<usize>,
    /// The compensator.
    pub comp: AxisCompensator,
    /// MD32750 the config expects.
    pub md32750: u16,
    /// Time between updates.
    pub update_interval: Duration,
}

/// The synchronous part of the gateway: channel processors and axis compensators.
/// The core loop and `compgate bench` drive the same code.
#[derive(Debug)]
pub struct Pipeline {
    /// Channel names, in config order.
    pub channel_names: Vec<String>,
    /// One processor per channel; out of date for a channel its device's bank holds.
    processors: Vec<ChannelProcessor>,
    /// One bank per device, for its steady channels.
    banks: Vec<Bank>,
    /// Each channel's device and its lane in the device's bank.
    homes: Vec<(usize, usize)>,
    /// Axes.
    pub axes: Vec<AxisRt>,
    /// Model inputs of the last decision (kept for its allocation).
    temps_degc: Vec<Option<f64>>,
    epoch: Instant,
}

impl Pipeline {
    /// Seconds since the pipeline started: the time base of channels and axes.
    pub fn now_s(&self, at: Instant) -> f64 {
        at.saturating_duration_since(self.epoch).as_secs_f64()
    }

    /// A pipeline over `processors` (config order), the channels of device `d` being
    /// `device_channels[d]`.
    fn new(
        channel_names: Vec<String>,
        processors: Vec<ChannelProcessor>,
        device_channels: Vec<Vec<usize>>,
        axes: Vec<AxisRt>,
    ) -> Self {
        let mut homes = vec![(usize::MAX, 0); processors.len()];
        for (device, channels) in device_channels.iter().enumerate() {
            for (lane, &ch) in channels.iter().enumerate() {
                homes[ch] = (device, lane);
            }
        }
        let banks = device_channels
            .into_iter()
            .map(|channels| Bank::new(channels, &processors))
            .collect();
        Self {
            channel_names,
            processors,
            banks,
            homes,
            axes,
            temps_degc: Vec::new(),
            epoch: Instant::now(),
        }
    }

    /// The latest reading of channel `ch` (config order); `None` past the last channel.
    pub fn reading(&self, ch: usize) -> Option<Reading> {
        match self.held(ch) {
            Some((bank, lane)) => Some(bank.reading(lane)),
            None => self.processors.get(ch).map(|p| p.last().clone()),
        }
    }

    /// The bank and lane of channel `ch` if its device's bank holds it.
    fn held(&self, ch: usize) -> Option<(&Bank, usize)> {
        let (device, lane) = *self.homes.get(ch)?;
        let bank = self.banks.get(device)?;
        bank.holds(lane).then_some((bank, lane))
    }

    /// Every channel's name and reading, in config order.
    pub fn channel_statuses(&self) -> Vec<ChannelStatus> {
        self.channel_names
            .iter()
            .enumerate()
            .map(|(ch, name)| ChannelStatus {
                name: name.clone(),
                reading: self.reading(ch).unwrap_or_else(Reading::no_data),
            })
            .collect()
    }

    /// The channel processors, brought up to date and taken out (the pipeline is
    /// left without channels): what a reload carries over.
    fn take_processors(&mut self) -> Vec<ChannelProcessor> {
        for bank in &mut self.banks {
            bank.release_all(&mut self.processors);
        }
        self.banks.clear();
        self.homes.clear();
        std::mem::take(&mut self.processors)
    }

    /// Feeds one device sample through the channel processors: the values of steady
    /// channels through the device's bank, the rest one by one.
    pub fn ingest(&mut self, sample: &DeviceSample) {
        let t_s = self.now_s(sample.started);
        let mut gain = LowPassGain::default();
        let mut no_bank = Bank::default();
        let bank = self.banks.get_mut(sample.device).unwrap_or(&mut no_bank);
        for (ch, value) in &sample.values {
            let Some(p) = self.processors.get_mut(*ch) else {
                continue;
            };
            let (device, lane) = self.homes[*ch];
            let in_bank = device == sample.device;
            match value {
                Ok(raw) if in_bank => bank.sample(lane, p, t_s, *raw, &mut gain),
                Ok(raw) => {
                    p.on_sample_with(t_s, *raw, &mut gain);
                }
                Err(fault) if in_bank => {
                    bank.missing(lane, p, t_s, fault.reason, fault.degraded);
                }
                Err(fault) => {
                    p.on_missing(t_s, fault.reason, fault.degraded);
                }
            }
        }
        bank.step(t_s, &mut gain, &mut self.processors);
    }

    /// The value of channel `ch` if its quality allows using it.
    pub fn usable_degc(&self, ch: usize) -> Option<f64> {
        match self.held(ch) {
            Some((bank, lane)) => Some(bank.value_degc(lane)),
            None => self.processors.get(ch)?.last().usable_degc(),
        }
    }

    /// Runs one compensation decision for axis `axis`.
    pub fn decide(&mut self, axis: usize, at: Instant) -> Decision {
        let now_s = self.now_s(at);
        // The inputs in a buffer kept between calls: the bench decides on every cycle.
        let mut temps_degc = std::mem::take(&mut self.temps_degc);
        temps_degc.clear();
        temps_degc.extend(
            self.axes[axis]
                .inputs
                .iter()
                .map(|&ch| self.usable_degc(ch)),
        );
        let decision = self.axes[axis].comp.decide(now_s, &temps_degc);
        self.temps_degc = temps_degc;
        decision
    }
}

/// Samples the device tasks may queue ahead of the core loop.
pub const SAMPLE_QUEUE: usize = 64;

/// The poller of one device, by transport.
#[derive(Debug)]
pub enum Poller {
    /// A Modbus TCP or RTU device.
    Modbus(DevicePoller),
    /// A CANopen node.
    Can(Box<CanPoller>),
}

impl Poller {
    /// Device name from the config.
    pub fn name(&self) -> &str {
        match self {
            Self::Modbus(p) => p.name(),
            Self::Can(p) => p.name(),
        }
    }

    /// The link, for the status line.
    pub fn describe(&self) -> String {
        match self {
            Self::Modbus(p) => p
                .link()
                .try_lock()
                .map(|l| l.spec().to_string())
                .unwrap_or_default(),
            Self::Can(p) => p.describe(),
        }
    }

    /// Runs one poll cycle.
    pub async fn poll(&mut self) -> DeviceSample {
        match self {
            Self::Modbus(p) => p.poll().await,
            Self::Can(p) => p.poll().await,
        }
    }
}

/// A device task's parts.
#[derive(Debug)]
pub struct DeviceRt {
    /// The poller.
    pub poller: Poller,
    /// Time between poll cycles.
    pub poll_interval: Duration,
}

/// An NC module's parts.
#[derive(Debug)]
pub struct NcModuleRt {
    /// Module name.
    pub name: String,
    /// The writer.
    pub writer: ModbusNcWriter,
}

/// Everything [`run`] needs, built from a config.
#[derive(Debug)]
pub struct Built {
    /// Synchronous stages.
    pub pipeline: Pipeline,
    /// Device pollers.
    pub devices: Vec<DeviceRt>,
    /// One SYNC producer per CAN interface.
    pub sync_producers: Vec<SyncParams>,
    /// NC modules.
    pub nc_modules: Vec<NcModuleRt>,
    /// Time between status updates.
    pub status_interval: Duration,
}

// Config structs -> runtime parameters (the config layer stays free of runtime types).

fn scaling_rt(s: &config::Scaling) -> Scaling {
    match s {
        config::Scaling::Transmitter(t) => Scaling::Transmitter {
            adc_full_scale_counts: f64::from(t.adc_full_scale_counts),
            adc_full_scale_ma: t.adc_full_scale_ma,
            current_range: match t.current_range {
                config::CurrentRange::Ma4To20 => CurrentRange::FourTo20,
                config::CurrentRange::Ma0To20 => CurrentRange::ZeroTo20,
            },
            range_min_degc: t.range_min_degc,
            range_max_degc: t.range_max_degc,
        },
        config::Scaling::Direct(d) => Scaling::Direct {
            gain: d.gain,
            offset_degc: d.offset_degc,
        },
    }
}

fn filter_rt(f: &config::FilterConfig) -> FilterParams {
    FilterParams {
        median_samples: f.median_samples.max(1) as usize,
        lowpass_tau_s: f.lowpass_tau_s,
        max_rate_degc_per_s: f.max_rate_degc_per_s,
        max_rejected_samples: f.max_rejected_samples,
        stale_after_s: f.stale_after_s,
        valid_min_degc: f.valid_min_degc,
        valid_max_degc: f.valid_max_degc,
    }
}

fn link_spec(dev: &config::DeviceConfig) -> Option<LinkSpec> {
    Some(match dev.transport {
        config::Transport::Can => return None,
        config::Transport::Tcp => LinkSpec::Tcp {
            address: dev.address.clone()?,
            connect_timeout: dev.connect_timeout(),
        },
        config::Transport::Rtu => LinkSpec::Rtu {
            path: dev.serial_path.clone()?,
            baud: dev.baud(),
            parity: match dev.parity() {
                config::Parity::None => tokio_serial::Parity::None,
                config::Parity::Even => tokio_serial::Parity::Even,
                config::Parity::Odd => tokio_serial::Parity::Odd,
            },
            stop_bits: if dev.stop_bits() == 2 {
                tokio_serial::StopBits::Two
            } else {
                tokio_serial::StopBits::One
            },
        },
    })
}

/// The axis' thermal model and the channel name behind each model input.
fn model_rt(ax: &config::AxisConfig) -> (ThermalModel, Vec<String>) {
    let mut names: Vec<String> = Vec::new();
    let mut input = |ch: &str| match names.iter().position(|n| n == ch) {
        Some(i) => i,
        None => {
            names.push(ch.to_string());
            names.len() - 1
        }
    };
    let k0_terms = ax
        .k0
        .terms
        .iter()
        .map(|t| Term {
            input: input(&t.channel),
            ref_degc: t.ref_degc,
            coeff: t.coeff_mm_per_degc,
        })
        .collect();
    let tan_terms = ax
        .tan_beta
        .terms
        .iter()
        .map(|t| Term {
            input: input(&t.channel),
            ref_degc: t.ref_degc,
            coeff: t.coeff_per_degc,
        })
        .collect();
    let model = ThermalModel {
        k0_mm: Affine {
            offset: ax.k0.offset_mm,
            terms: k0_terms,
        },
        tan_beta: Affine {
            offset: ax.tan_beta.offset,
            terms: tan_terms,
        },
        p0_mm: ax.p0_mm,
    };
    (model, names)
}

fn limits_rt(ax: &config::AxisConfig) -> Limits {
    Limits {
        max_abs_k0_mm: ax.max_abs_k0_mm,
        max_abs_tan_beta: ax.max_abs_tan_beta,
        max_step_k0_mm: ax.max_step_k0_mm,
        max_step_tan_beta: ax.max_step_tan_beta,
        deadband_k0_mm: ax.deadband_k0_mm,
        deadband_tan_beta: ax.deadband_tan_beta,
    }
}

fn policy_rt(ax: &config::AxisConfig) -> BadInputPolicy {
    match ax.on_bad_input {
        config::OnBadInput::Hold => BadInputPolicy::Hold,
        config::OnBadInput::RampToZero => BadInputPolicy::RampToZero {
            k0_mm_per_s: ax.ramp_k0_mm_per_s,
            tan_beta_per_s: ax.ramp_tan_beta_per_s,
        },
    }
}

/// Turns a validated config into runtime parts. Devices on one serial path share a
/// link; every TCP device gets its own connection.
pub fn build(cfg: &Config) -> Result<Built, GatewayError> {
    let device_index: BTreeMap<&str, usize> = cfg
        .devices
        .keys()
        .enumerate()
        .map(|(i, n)| (n.as_str(), i))
        .collect();
    let channel_names: Vec<String> = cfg.channels.keys().cloned().collect();
    let channel_index: BTreeMap<&str, usize> = channel_names
        .iter()
        .enumerate()
        .map(|(i, n)| (n.as_str(), i))
        .collect();

    let mut processors = Vec::with_capacity(cfg.channels.len());
    let mut specs: Vec<Vec<ChannelSpec>> = vec![Vec::new(); cfg.devices.len()];
    let mut can_specs: Vec<Vec<CanChannelSpec>> = vec![Vec::new(); cfg.devices.len()];
    let mut device_channels: Vec<Vec<usize>> = vec![Vec::new(); cfg.devices.len()];
    for (i, (name, ch)) in cfg.channels.iter().enumerate() {
        let dev = *device_index.get(ch.device.as_str()).ok_or_else(|| {
            GatewayError::Config(format!("channels.{name}.device: no device {}", ch.device))
        })?;
        match (ch.can, ch.register, ch.address) {
            (Some(can), _, _) => {
                let object = match (can.pdo, can.offset_bytes, can.sdo_index, can.sdo_subindex) {
                    (Some(pdo), Some(offset_bytes), None, None) => {
                        CanObject::Pdo { pdo, offset_bytes }
                    }
                    (None, None, Some(index), Some(sub)) => CanObject::Sdo { index, sub },
                    _ => {
                        return Err(GatewayError::Config(format!(
                            "channels.{name}.can: a TPDO mapping or an SDO object"
                        )))
                    }
                };
                can_specs[dev].push(CanChannelSpec {
                    channel: i,
                    object,
                    data_type: ch.data_type,
                });
            }
            (None, Some(kind), Some(address)) => specs[dev].push(ChannelSpec {
                channel: i,
                kind,
                address,
                data_type: ch.data_type,
                byte_order: ch.byte_order,
            }),
            _ => {
                return Err(GatewayError::Config(format!(
                    "channels.{name}: register and address, or can, missing"
                )))
            }
        }
        device_channels[dev].push(i);
        processors.push(ChannelProcessor::new(
            scaling_rt(&ch.scaling),
            filter_rt(&ch.filter),
        ));
    }

    // One SYNC per interface at its devices' poll interval (validation makes it one
    // value per interface).
    let sync_producers = sync::plan(
        cfg.devices
            .values()
            .filter(|dev| dev.transport == config::Transport::Can)
            .map(|dev| SyncDevice {
                interface: dev.interface.clone().unwrap_or_default(),
                poll_interval: dev.poll_interval(),
                backoff_initial: dev.backoff_initial(),
                backoff_max: dev.backoff_max(),
            }),
    );
    let mut serial_links: BTreeMap<String, SharedLink> = BTreeMap::new();
    let mut devices = Vec::with_capacity(cfg.devices.len());
    for (((name, dev), specs), can_specs) in cfg.devices.iter().zip(specs).zip(can_specs) {
        if dev.transport == config::Transport::Can {
            let (Some(interface), Some(node_id)) = (dev.interface.clone(), dev.node_id) else {
                return Err(GatewayError::Config(format!(
                    "devices.{name}: interface or node_id missing"
                )));
            };
            let sync_period = sync_producers
                .iter()
                .find(|p| p.interface == interface)
                .map_or(dev.poll_interval(), |p| p.period);
            let params = CanParams {
                sync_period,
                interface,
                node_id,
                timeout: dev.timeout(),
                heartbeat_timeout: dev.heartbeat_timeout(),
                degrade_after_cycles: dev.degrade_after_cycles,
            };
            devices.push(DeviceRt {
                poller: Poller::Can(Box::new(CanPoller::new(
                    devices.len(),
                    name.clone(),
                    params,
                    can_specs,
                ))),
                poll_interval: dev.poll_interval(),
            });
            continue;
        }
        let spec = link_spec(dev).ok_or_else(|| {
            GatewayError::Config(format!("devices.{name}: address or serial_path missing"))
        })?;
        let new_link = || {
            Arc::new(Mutex::new(ModbusLink::new(
                spec.clone(),
                dev.timeout(),
                Backoff::new(dev.backoff_initial(), dev.backoff_max()),
            )))
        };
        let link = match &spec {
            LinkSpec::Rtu { path, .. } => serial_links
                .entry(path.clone())
                .or_insert_with(new_link)
                .clone(),
            LinkSpec::Tcp { .. } => new_link(),
        };
        let params = PollParams {
            unit_id: dev.unit_id.unwrap_or_default(),
            retries: dev.retries,
            degrade_after_cycles: dev.degrade_after_cycles,
            max_gap_registers: dev.max_gap_registers,
        };
        devices.push(DeviceRt {
            poller: Poller::Modbus(DevicePoller::new(
                devices.len(),
                name.clone(),
                params,
                link,
                specs,
            )),
            poll_interval: dev.poll_interval(),
        });
    }

    let nc_index: BTreeMap<&str, usize> = cfg
        .nc_modules
        .keys()
        .enumerate()
        .map(|(i, n)| (n.as_str(), i))
        .collect();
    let nc_modules = cfg
        .nc_modules
        .iter()
        .map(|(name, m)| {
            let link = ModbusLink::new(
                LinkSpec::Tcp {
                    address: m.address.clone(),
                    connect_timeout: m.connect_timeout(),
                },
                m.timeout(),
                Backoff::new(Duration::from_millis(500), Duration::from_secs(10)),
            );
            NcModuleRt {
                name: name.clone(),
                writer: ModbusNcWriter::new(link, m.unit_id, m.job_timeout()),
            }
        })
        .collect();

    let mut axes = Vec::with_capacity(cfg.axes.len());
    for (name, ax) in &cfg.axes {
        let nc_module = *nc_index.get(ax.nc_module.as_str()).ok_or_else(|| {
            GatewayError::Config(format!(
                "axes.{name}.nc_module: no NC module {}",
                ax.nc_module
            ))
        })?;
        let (model, input_names) = model_rt(ax);
        let inputs = input_names
            .iter()
            .map(|n| {
                channel_index
                    .get(n.as_str())
                    .copied()
                    .ok_or_else(|| GatewayError::Config(format!("axes.{name}: no channel {n}")))
            })
            .collect::<Result<Vec<_>, _>>()?;
        axes.push(AxisRt {
            name: name.clone(),
            nc_module,
            inputs,
            comp: AxisCompensator::new(model, limits_rt(ax), policy_rt(ax)),
            md32750: ax.md32750,
            update_interval: ax.update_interval(),
        });
    }

    Ok(Built {
        pipeline: Pipeline::new(channel_names, processors, device_channels, axes),
        devices,
        sync_producers,
        nc_modules,
        status_interval: cfg.gateway.status_interval(),
    })
}

enum NcCommand {
    Write { axis: usize, params: CompParams },
}

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

async fn nc_task(
    module: usize,
    mut nc: NcModuleRt,
    mut rx: mpsc::Receiver<NcCommand>,
    tx: mpsc::Sender<NcEvent>,
    snapshot_interval: Duration,
) -> Returned {
    let mut tick = tokio::time::interval(snapshot_interval);
    tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            cmd = rx.recv() => {
                let Some(NcCommand::Write { axis, params }) = cmd else { break };
                let result = nc.writer.write_job(&Job::thermal(&params)).await;
                match &result {
                    Ok(r) => tracing::info!(module = %nc.name, job_id = r.job_id, sd43900_mm = params.k0_mm, sd43910 = params.tan_beta, sd43920_mm = params.p0_mm, elapsed_ms = r.elapsed.as_secs_f64() * 1e3, "NC job done, read-back verified"),
                    Err(e) => tracing::warn!(module = %nc.name, error = %e, "NC job failed"),
                }
                if tx.send(NcEvent::Written { axis, params, result }).await.is_err() {
                    break;
                }
            }
            _ = tick.tick() => {
                let result = nc.writer.read_snapshot().await;
                if tx.send(NcEvent::Snapshot { module, result }).await.is_err() {
                    break;
                }
            }
        }
    }
    Returned::Nc(module, nc)
}

fn describe(d: &Decision, names: &[String], inputs: &[usize]) -> String {
    let bad = |idx: &[usize]| {
        idx.iter()
            .filter_map(|&i| inputs.get(i).and_then(|&c| names.get(c)))
            .cloned()
            .collect::<Vec<_>>()
            .join(",")
    };
    match d {
        Decision::Write { clamped: false, .. } => "write".into(),
        Decision::Write { clamped: true, .. } => "write (limited)".into(),
        Decision::WithinDeadband => "within deadband".into(),
        Decision::Hold { bad_inputs } => format!("hold: bad input {}", bad(bad_inputs)),
        Decision::Ramp { bad_inputs, .. } => format!("ramp to zero: bad input {}", bad(bad_inputs)),
    }
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

/// Runs `built` (made from `cfg`) through generations: a reload ends one generation
/// between polls, after every NC job in flight has finished, and starts the next with
/// the state of whatever did not change.
async fn run_built_with(
    built: Built,
    mut cfg: Config,
    shutdown: CancellationToken,
    status_tx: watch::Sender<Status>,
    mut hooks: Hooks,
) {
    let mut state = Running::new(built);
    loop {
        match generation(&mut state, &shutdown, &status_tx, &mut hooks).await {
            None => break,
            Some((new_cfg, new_built)) => {
                state = reload::transplant(&cfg, &new_cfg, state, *new_built);
                cfg = *new_cfg;
                tracing::info!("configuration reloaded");
                hooks.observer.on_reload(&Ok(()));
            }
        }
    }
    status_tx.send_replace(state.status);
    tracing::info!("gateway stopped");
}

/// The state that lives across generations.
struct Running {
    pipeline: Pipeline,
    devices: Vec<Option<DeviceRt>>,
    sync_producers: Vec<SyncParams>,
    nc_modules: Vec<Option<NcModuleRt>>,
    status_interval: Duration,
    status: Status,
    /// Per axis: whether its step limits start from what the NC holds yet.
    baselined: Vec<bool>,
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
                    ..AxisStatus::default()
                })
                .collect(),
            samples: 0,
        };
        Running {
            baselined: vec![false; pipeline.axes.len()],
            pipeline,
            devices: devices.into_iter().map(Some).collect(),
            sync_producers,
            nc_modules: nc_modules.into_iter().map(Some).collect(),
            status_interval,
            status,
        }
    }

    fn on_sample(&mut self, sample: &DeviceSample) {
        self.pipeline.ingest(sample);
        let status = &mut self.status;
        status.samples += 1;
        let d = &mut status.devices[sample.device];
        d.cycles += 1;
        d.last_cycle = sample.elapsed;
        d.connects = sample.connects;
        match &sample.error {
            Some(e) => {
                d.failed_cycles += 1;
                *d.errors.entry(e.kind()).or_default() += 1;
                d.last_error = Some(e.to_string());
            }
            None => {
                d.failed_cycles = 0;
                d.last_error = None;
            }
        }
        // Only this sample's channels changed (512 channels on 8 devices: 8x less work).
        for (ch, _) in &sample.values {
            if let (Some(cs), Some(r)) = (status.channels.get_mut(*ch), self.pipeline.reading(*ch))
            {
                cs.reading = r;
            }
        }
    }

    fn on_event(&mut self, event: NcEvent, in_flight: &mut [bool], observer: &mut dyn Observer) {
        match event {
            NcEvent::Snapshot { module, result } => {
                for (i, axis) in self.pipeline.axes.iter_mut().enumerate() {
                    if axis.nc_module != module {
                        continue;
                    }
                    let st = &mut self.status.axes[i];
                    match &result {
                        Ok(snap) => {
                            if !self.baselined[i] {
                                // Step limits and the deadband start from what the NC holds.
                                axis.comp.set_baseline(snap.thermal());
                                self.baselined[i] = true;
                                st.written = Some(snap.thermal());
                                tracing::info!(axis = %axis.name, sd43900_mm = snap.sd43900_mm, sd43910 = snap.sd43910, sd43920_mm = snap.sd43920_mm, "NC parameters read at start");
                            }
                            st.warning = (snap.md32750 != axis.md32750).then(|| {
                                format!(
                                    "MD32750 is {} on the NC, the config expects {}",
                                    snap.md32750, axis.md32750
                                )
                            });
                            if !snap.referenced {
                                st.warning.get_or_insert_with(|| "axis not referenced: the NC applies no temperature compensation".into());
                            }
                            st.nc = Some(*snap);
                        }
                        Err(e) => st.warning = Some(format!("NC unreachable: {e}")),
                    }
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
                match result {
                    Ok(_) => {
                        self.pipeline.axes[axis].comp.confirm(params);
                        st.written = Some(params);
                        st.jobs_ok += 1;
                        st.last_job_error = None;
                    }
                    Err(e) => {
                        st.jobs_failed += 1;
                        st.last_job_error = Some(e.to_string());
                    }
                }
            }
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
    status_tx.send_replace(state.status.clone());
    let stop = shutdown.child_token();
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
            tasks.spawn(nc_task(i, nc, rx, event_tx.clone(), state.status_interval));
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
    let mut status_tick = tokio::time::interval(state.status_interval);
    status_tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
    let far = now + Duration::from_secs(86_400 * 365);
    let mut events_open = true;
    let mut reload_to: Option<(Box<Config>, Box<Built>)> = None;
    let observer = &mut *hooks.observer;

    loop {
        let next = next_update.iter().copied().min().unwrap_or(far);
        tokio::select! {
            sample = sample_rx.recv() => {
                let Some(sample) = sample else { break };
                state.on_sample(&sample);
                observer.on_sample(&sample, &state.pipeline);
            }
            event = event_rx.recv(), if events_open => {
                // No NC modules (a monitoring-only config): the channel closes at once.
                let Some(event) = event else {
                    events_open = false;
                    continue;
                };
                state.on_event(event, &mut in_flight, observer);
            }
            _ = tokio::time::sleep_until(next), if next < far => {
                let at = Instant::now();
                let pipeline = &mut state.pipeline;
                for i in 0..pipeline.axes.len() {
                    if next_update[i] > at {
                        continue;
                    }
                    next_update[i] = at + pipeline.axes[i].update_interval;
                    if !state.baselined[i] || in_flight[i] {
                        continue;
                    }
                    let decision = pipeline.decide(i, at);
                    let axis = &pipeline.axes[i];
                    state.status.axes[i].decision = describe(&decision, &pipeline.channel_names, &axis.inputs);
                    let params = match decision {
                        Decision::Write { params, .. } | Decision::Ramp { params, .. } => params,
                        Decision::WithinDeadband | Decision::Hold { .. } => continue,
                    };
                    if nc_tx[axis.nc_module].try_send(NcCommand::Write { axis: i, params }).is_ok() {
                        in_flight[i] = true;
                    }
                }
            }
            _ = status_tick.tick() => {
                // Called from the control loop itself: a stuck loop stops the watchdog.
                observer.on_status(&state.status);
                status_tx.send_replace(state.status.clone());
            }
            new_cfg = next_reload(&mut hooks.reload), if reload_to.is_none() => {
                match build(&new_cfg) {
                    Ok(built) => {
                        tracing::info!("reload: stopping the running generation between polls");
                        reload_to = Some((Box::new(new_cfg), Box::new(built)));
                        stop.cancel();
                    }
                    Err(e) => {
                        tracing::error!(error = %e, "reload refused: the running configuration stays");
                        observer.on_reload(&Err(e.to_string()));
                    }
                }
            }
        }
    }
    drop(nc_tx);
    // Let NC jobs in flight finish and take their results: a reload keeps them.
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
    reload_to
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::Fault;
    use compgate_core::channel::{Quality, Reason};

    fn sample(p: &Pipeline, k: u32, fault_on: Option<usize>) -> DeviceSample {
        let values = (0..p.channel_names.len())
            .filter(|&ch| p.homes[ch].0 == 0)
            .map(|ch| {
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
            connects: 1,
        }
    }

    // The pipeline shows what the bank holds and hands it back whole: after a fault
    // and on a reload the processors carry on from the bank's state.
    #[test]
    fn bank_state_goes_back_to_the_processors() {
        let cfg = config::load_str(include_str!("../../../config/demo.toml"), "demo.toml")
            .expect("demo config");
        let mut p = build(&cfg).expect("build").pipeline;
        for k in 0..30 {
            p.ingest(&sample(&p, k, None));
        }
        let held = (0..p.channel_names.len())
            .filter(|&ch| p.homes[ch].0 == 0 && p.banks[0].holds(p.homes[ch].1))
            .count();
        assert!(held >= 4, "{held} channels held");
        let before: Vec<Reading> = (0..p.channel_names.len())
            .map(|ch| p.reading(ch).expect("reading"))
            .collect();
        assert_eq!(before[0].quality, Quality::Good);
        assert!(before[0].value_degc.is_some_and(|v| (v - 30.0).abs() < 0.1));
        // A missing sample hands the channel back: held value, uncertain.
        p.ingest(&sample(&p, 30, Some(0)));
        let r = p.reading(0).expect("reading");
        assert_eq!(r.quality, Quality::Uncertain(Reason::Comm));
        assert_eq!(r.value_degc, before[0].value_degc);
        assert!(!p.banks[0].holds(p.homes[0].1));
        let now: Vec<Reading> = (0..p.channel_names.len())
            .map(|ch| p.reading(ch).expect("reading"))
            .collect();
        let processors = p.take_processors();
        for (ch, (proc_, r)) in processors.iter().zip(&now).enumerate() {
            assert_eq!(proc_.last(), r, "channel {ch}");
        }
    }
}
