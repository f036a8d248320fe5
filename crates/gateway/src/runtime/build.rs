//! Config -> runtime parts: pollers, links, the pipeline, NC writers.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::Mutex;

use crate::config::problem::peer_identity;
use crate::config::{Config, DeviceConfig};
use crate::nc::Guarded;
use crate::source::can::sync::{self, SyncDevice, SyncParams};
use crate::source::can::{CanChannelSpec, CanPoller};
use crate::source::modbus::{Backoff, LinkSpec, ModbusLink};
use crate::source::{ChannelSpec, DevicePoller, DeviceSample, SharedLink};
use compgate_core::comp::AxisCompensator;

use super::{AxisRt, FittedRange, GatewayError, Pipeline};

/// The poller of one device, by transport.
// One per device, made once: the Modbus poller stays inline, as the common case on
// the poll path, and the rarer CAN one is boxed.
#[allow(clippy::large_enum_variant)]
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

/// The NC writer of one axis: its target's name and the guarded writer.
#[derive(Debug)]
pub struct NcModuleRt {
    /// Target name (`[targets]` or `[nc_modules]`).
    pub name: String,
    /// Where it is (`host:port`, an endpoint URL), for the log.
    pub address: String,
    /// The writer, behind the guarantees every target shares.
    pub writer: Guarded,
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
    /// One NC writer per axis, in axis order.
    pub nc_modules: Vec<NcModuleRt>,
    /// Time between status updates.
    pub status_interval: Duration,
}

/// The devices on one serial line or at one TCP address, and the connection's settings.
struct Line {
    devices: usize,
    /// TCP only: the shortest `connect_timeout_s` of the devices.
    connect_timeout: Duration,
    backoff_initial: Duration,
    backoff_max: Duration,
    link: Option<SharedLink>,
}

/// Turns a validated config into runtime parts. Devices on one serial path, or at one
/// TCP address, share a link.
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
    let mut encodings = Vec::with_capacity(cfg.channels.len());
    let mut specs: Vec<Vec<ChannelSpec>> = vec![Vec::new(); cfg.devices.len()];
    let mut can_specs: Vec<Vec<CanChannelSpec>> = vec![Vec::new(); cfg.devices.len()];
    for (i, (name, ch)) in cfg.channels.iter().enumerate() {
        let dev = *device_index.get(ch.device.as_str()).ok_or_else(|| {
            GatewayError::Config(format!("channels.{name}.device: no device {}", ch.device))
        })?;
        match (ch.can, ch.register, ch.address) {
            (Some(can), _, _) => {
                let object = can.object().ok_or_else(|| {
                    GatewayError::Config(format!(
                        "channels.{name}.can: a TPDO mapping or an SDO object"
                    ))
                })?;
                can_specs[dev].push(CanChannelSpec {
                    channel: i,
                    object,
                    data_type: ch.data_type,
                });
            }
            (None, Some(kind), Some(address)) => specs[dev].push(ChannelSpec {
                channel: i,
                name: name.as_str().into(),
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
        processors.push(ch.build());
        encodings.push(ch.can.is_none().then_some((ch.data_type, ch.byte_order)));
    }

    // One SYNC per interface at its devices' poll interval (validation makes it one
    // value per interface). Nodes with event-driven TPDOs need none: an interface of
    // only such nodes gets no producer, so the gateway sends no SYNC on a bus whose
    // SYNC another master may own.
    let sync_producers = sync::plan(
        cfg.devices
            .values()
            .filter_map(DeviceConfig::can)
            .filter(|dev| dev.tpdo_max_age_s.is_none())
            .map(|dev| SyncDevice {
                interface: dev.interface.clone(),
                poll_interval: dev.common.poll_interval(),
                backoff_initial: dev.common.backoff_initial(),
                backoff_max: dev.common.backoff_max(),
            }),
    );
    // Devices on one serial line, or at one TCP address (units behind a TCP-to-RTU
    // gateway, which has one serial line too), share one connection: their requests
    // go out one after the other, as the line takes them, and a module that takes few
    // connections is not asked for one per unit. A silent one is demoted.
    let line_of = |d: &DeviceConfig| match d {
        DeviceConfig::Rtu(rtu) => Some(rtu.serial_path.clone()),
        DeviceConfig::Tcp(tcp) => Some(format!("tcp {}", peer_identity(&tcp.address))),
        DeviceConfig::Can(_) => None,
    };
    // Per line: its devices, and the shortest connect timeout and backoff any of them
    // asks for, which the connection uses (each request waits the device's own
    // `timeout_s`).
    let mut lines: BTreeMap<String, Line> = BTreeMap::new();
    for dev in cfg.devices.values() {
        let Some(key) = line_of(dev) else { continue };
        let common = dev.common();
        let connect_timeout = match dev {
            DeviceConfig::Tcp(tcp) => tcp.connect_timeout(),
            _ => Duration::MAX,
        };
        let line = lines.entry(key).or_insert(Line {
            devices: 0,
            connect_timeout,
            backoff_initial: common.backoff_initial(),
            backoff_max: common.backoff_max(),
            link: None,
        });
        line.devices += 1;
        line.connect_timeout = line.connect_timeout.min(connect_timeout);
        line.backoff_initial = line.backoff_initial.min(common.backoff_initial());
        line.backoff_max = line.backoff_max.min(common.backoff_max());
    }
    let mut devices = Vec::with_capacity(cfg.devices.len());
    for (((name, dev), specs), can_specs) in cfg.devices.iter().zip(specs).zip(can_specs) {
        let common = dev.common();
        let (spec, params) = match dev {
            DeviceConfig::Can(can) => {
                let sync_period = sync_producers
                    .iter()
                    .find(|p| p.interface == can.interface)
                    .map_or(common.poll_interval(), |p| p.period);
                devices.push(DeviceRt {
                    poller: Poller::Can(Box::new(CanPoller::new(
                        devices.len(),
                        name.clone(),
                        can.params(sync_period),
                        can_specs,
                    ))),
                    poll_interval: common.poll_interval(),
                });
                continue;
            }
            DeviceConfig::Tcp(tcp) => (tcp.link_spec(), tcp.poll_params()),
            DeviceConfig::Rtu(rtu) => (rtu.link_spec(), rtu.poll_params()),
        };
        let line = line_of(dev)
            .and_then(|key| lines.get_mut(&key))
            .ok_or_else(|| GatewayError::Config(format!("devices.{name}: no line")))?;
        let link = line
            .link
            .get_or_insert_with(|| {
                let spec = match spec {
                    LinkSpec::Tcp { address, .. } => LinkSpec::Tcp {
                        address,
                        connect_timeout: line.connect_timeout,
                    },
                    rtu => rtu,
                };
                let link = ModbusLink::new(
                    spec,
                    common.timeout(),
                    Backoff::new(line.backoff_initial, line.backoff_max),
                );
                let link = if line.devices > 1 {
                    link.shared_address()
                } else {
                    link
                };
                Arc::new(Mutex::new(link))
            })
            .clone();
        let mut poller = DevicePoller::new(devices.len(), name.clone(), params, link, specs);
        if line.devices > 1 {
            poller =
                poller.on_shared_line(Backoff::new(common.backoff_initial(), common.backoff_max()));
        }
        devices.push(DeviceRt {
            poller: Poller::Modbus(poller),
            poll_interval: common.poll_interval(),
        });
    }

    let mut nc_modules = Vec::with_capacity(cfg.axes.len());
    let mut axes = Vec::with_capacity(cfg.axes.len());
    for (name, ax) in &cfg.axes {
        let target = cfg.target(&ax.nc_module).ok_or_else(|| {
            GatewayError::Config(format!("axes.{name}.nc_module: no target {}", ax.nc_module))
        })?;
        let writer = target
            .build(name, ax.axis_number.unwrap_or(0))
            .map_err(|e| GatewayError::Config(format!("axes.{name}: {e}")))?;
        let nc_module = nc_modules.len();
        nc_modules.push(NcModuleRt {
            name: ax.nc_module.clone(),
            address: target.address().to_string(),
            writer: Guarded::new(writer, ax.nc_write_ids(), target.job_timeout()),
        });
        let (model, input_names, dynamics) = ax.model_parts();
        let inputs = input_names
            .iter()
            .map(|n| {
                channel_index
                    .get(n.as_str())
                    .copied()
                    .ok_or_else(|| GatewayError::Config(format!("axes.{name}: no channel {n}")))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let fitted = ax
            .fitted_degc
            .iter()
            .map(|(n, &[min_degc, max_degc])| {
                let channel = *channel_index.get(n.as_str()).ok_or_else(|| {
                    GatewayError::Config(format!("axes.{name}.fitted_degc: no channel {n}"))
                })?;
                Ok(FittedRange {
                    channel,
                    min_degc,
                    max_degc,
                })
            })
            .collect::<Result<Vec<_>, GatewayError>>()?;
        axes.push(AxisRt {
            name: name.clone(),
            nc_module,
            inputs,
            comp: AxisCompensator::new(model, ax.limits(), ax.policy()).with_dynamics(dynamics),
            md32750: ax.md32750,
            update_interval: ax.update_interval(),
            nc_write: ax.nc_write_ids(),
            shadow: ax.shadow || cfg.gateway.shadow,
            fitted,
        });
    }

    Ok(Built {
        pipeline: Pipeline::new(channel_names, processors, axes, encodings),
        devices,
        sync_producers,
        nc_modules,
        status_interval: cfg.gateway.status_interval(),
    })
}
