//! Config -> runtime parts: pollers, links, the pipeline, NC writers.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::Mutex;

use crate::config::{self, Config};
use crate::nc::ModbusNcWriter;
use crate::source::can::sync::{self, SyncDevice, SyncParams};
use crate::source::can::{CanChannelSpec, CanObject, CanParams, CanPoller};
use crate::source::modbus::{Backoff, LinkSpec, ModbusLink};
use crate::source::{ChannelSpec, DevicePoller, DeviceSample, PollParams, SharedLink};
use compgate_core::channel::{ChannelProcessor, CurrentRange, FilterParams, Scaling};
use compgate_core::comp::{Affine, AxisCompensator, BadInputPolicy, Limits, Term, ThermalModel};

use super::{AxisRt, GatewayError, Pipeline};

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

/// Everything [`run`](super::run) needs, built from a config.
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

pub(super) fn scaling_rt(s: &config::Scaling) -> Scaling {
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

pub(super) fn filter_rt(f: &config::FilterConfig) -> FilterParams {
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

pub(super) fn link_spec(dev: &config::DeviceConfig) -> Option<LinkSpec> {
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
pub(super) fn model_rt(ax: &config::AxisConfig) -> (ThermalModel, Vec<String>) {
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

pub(super) fn limits_rt(ax: &config::AxisConfig) -> Limits {
    Limits {
        max_abs_k0_mm: ax.max_abs_k0_mm,
        max_abs_tan_beta: ax.max_abs_tan_beta,
        max_step_k0_mm: ax.max_step_k0_mm,
        max_step_tan_beta: ax.max_step_tan_beta,
        deadband_k0_mm: ax.deadband_k0_mm,
        deadband_tan_beta: ax.deadband_tan_beta,
    }
}

pub(super) fn policy_rt(ax: &config::AxisConfig) -> BadInputPolicy {
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
        pipeline: Pipeline::new(channel_names, processors, axes),
        devices,
        sync_producers,
        nc_modules,
        status_interval: cfg.gateway.status_interval(),
    })
}
