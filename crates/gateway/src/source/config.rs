//! `[devices.NAME]`: the field devices, one struct per transport, tagged by the
//! `transport` key (the keys stay flat in the device table). Validation of the device
//! section as a whole: shared serial lines, shared CAN interfaces.

use std::collections::BTreeMap;
use std::time::Duration;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::can::config::CanDeviceConfig;
use super::modbus::config::{RtuDeviceConfig, TcpDeviceConfig};
use crate::config::keys::{field, secs};
use crate::config::problem::Problems;

/// `[devices.NAME]`: one field device (analog input module, transmitter), by
/// `transport`: `tcp` (Modbus TCP), `rtu` (Modbus RTU on a serial line) or `can` (a
/// CANopen node on SocketCAN). A key of another transport is an unknown key.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(tag = "transport", rename_all = "snake_case")]
pub enum DeviceConfig {
    /// `transport = "tcp"`: a Modbus TCP server (`address = "host:port"`).
    Tcp(TcpDeviceConfig),
    /// `transport = "rtu"`: a Modbus RTU slave on a serial line (`serial_path`,
    /// `baud`, `parity`, `stop_bits`).
    Rtu(RtuDeviceConfig),
    /// `transport = "can"`: a CANopen node on a SocketCAN interface (`interface`,
    /// `node_id`, `heartbeat_timeout_s`).
    Can(CanDeviceConfig),
}

/// How a device is reached: the `transport` key.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Transport {
    /// Modbus TCP.
    Tcp,
    /// Modbus RTU on a serial line.
    Rtu,
    /// A CANopen node on a SocketCAN interface.
    Can,
}

impl DeviceConfig {
    /// The transport.
    pub fn transport(&self) -> Transport {
        match self {
            Self::Tcp(_) => Transport::Tcp,
            Self::Rtu(_) => Transport::Rtu,
            Self::Can(_) => Transport::Can,
        }
    }

    /// The keys every transport has.
    pub fn common(&self) -> &DeviceCommon {
        match self {
            Self::Tcp(d) => &d.common,
            Self::Rtu(d) => &d.common,
            Self::Can(d) => &d.common,
        }
    }

    /// The keys every transport has, to change them.
    pub fn common_mut(&mut self) -> &mut DeviceCommon {
        match self {
            Self::Tcp(d) => &mut d.common,
            Self::Rtu(d) => &mut d.common,
            Self::Can(d) => &mut d.common,
        }
    }

    /// The TCP device, if it is one.
    pub fn tcp(&self) -> Option<&TcpDeviceConfig> {
        match self {
            Self::Tcp(d) => Some(d),
            _ => None,
        }
    }

    /// The TCP device, if it is one, to change it.
    pub fn tcp_mut(&mut self) -> Option<&mut TcpDeviceConfig> {
        match self {
            Self::Tcp(d) => Some(d),
            _ => None,
        }
    }

    /// The RTU device, if it is one, to change it.
    pub fn rtu_mut(&mut self) -> Option<&mut RtuDeviceConfig> {
        match self {
            Self::Rtu(d) => Some(d),
            _ => None,
        }
    }

    /// The RTU device, if it is one.
    pub fn rtu(&self) -> Option<&RtuDeviceConfig> {
        match self {
            Self::Rtu(d) => Some(d),
            _ => None,
        }
    }

    /// The CAN node, if it is one.
    pub fn can(&self) -> Option<&CanDeviceConfig> {
        match self {
            Self::Can(d) => Some(d),
            _ => None,
        }
    }

    /// The CAN node, if it is one, to change it.
    pub fn can_mut(&mut self) -> Option<&mut CanDeviceConfig> {
        match self {
            Self::Can(d) => Some(d),
            _ => None,
        }
    }

    /// Checks one device; `key` is its path, e.g. `devices.ain1`.
    pub fn validate(&self, key: &str, out: &mut Problems<'_>) {
        match self {
            Self::Tcp(d) => d.validate(key, out),
            Self::Rtu(d) => d.validate(key, out),
            Self::Can(d) => d.validate(key, out),
        }
        self.common().validate(key, out);
    }
}

/// The keys of `[devices.NAME]` that every transport has.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
pub struct DeviceCommon {
    /// Seconds one request may take before it counts as failed. Default 1.0;
    /// 0.001..=3600. On Modbus devices a whole poll cycle (every read, retry and
    /// reconnect) ends after the larger of `poll_interval_s` and `timeout_s`. On RTU
    /// the line must also be quiet this long (at most 1 s) after the serial port is
    /// opened, before the first request: a late reply must not answer the next one.
    #[serde(default = "default_device_timeout_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub timeout_s: f64,
    /// Seconds between poll cycles. Default 1.0; 0.001..=3600. On `can` devices also the
    /// period of the interface's SYNC, so all CAN devices on one interface must use
    /// the same value.
    #[serde(default = "default_poll_interval_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub poll_interval_s: f64,
    /// Reconnect backoff after a transport fault: first wait in seconds; it doubles
    /// after every further fault up to `backoff_max_s`. Default 0.5; 0.001..=3600.
    #[serde(default = "default_backoff_initial_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub backoff_initial_s: f64,
    /// Longest reconnect wait in seconds. Default 30.0; 0.001..=3600 and
    /// >= `backoff_initial_s`.
    #[serde(default = "default_backoff_max_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub backoff_max_s: f64,
    /// After this many consecutive failed poll cycles the device's channels turn bad;
    /// before that they hold their last value as uncertain. Default 3; 1..=1000.
    #[serde(default = "default_degrade_after_cycles")]
    #[schemars(range(min = 1, max = 1000))]
    pub degrade_after_cycles: u32,
}

impl Default for DeviceCommon {
    fn default() -> Self {
        DeviceCommon {
            timeout_s: default_device_timeout_s(),
            poll_interval_s: default_poll_interval_s(),
            backoff_initial_s: default_backoff_initial_s(),
            backoff_max_s: default_backoff_max_s(),
            degrade_after_cycles: default_degrade_after_cycles(),
        }
    }
}

impl DeviceCommon {
    /// `timeout_s` as a [`Duration`].
    pub fn timeout(&self) -> Duration {
        secs(self.timeout_s)
    }
    /// `poll_interval_s` as a [`Duration`].
    pub fn poll_interval(&self) -> Duration {
        secs(self.poll_interval_s)
    }
    /// `backoff_initial_s` as a [`Duration`].
    pub fn backoff_initial(&self) -> Duration {
        secs(self.backoff_initial_s)
    }
    /// `backoff_max_s` as a [`Duration`].
    pub fn backoff_max(&self) -> Duration {
        secs(self.backoff_max_s)
    }

    /// The deadline of one Modbus poll cycle: the larger of `poll_interval_s` and
    /// `timeout_s`. Every read, retry and reconnect of the cycle shares it, so a silent
    /// device is noticed after one deadline however many reads a cycle makes; the
    /// cycle's first request still gets its whole timeout, later ones what is left.
    pub fn cycle_deadline(&self) -> Duration {
        secs(self.poll_interval_s.max(self.timeout_s))
    }

    /// Times > 0, `backoff_initial_s <= backoff_max_s`, `degrade_after_cycles >= 1`.
    pub fn validate(&self, key: &str, out: &mut Problems<'_>) {
        let k = |f: &str| format!("{key}.{f}");
        out.positive(&k("timeout_s"), self.timeout_s, "seconds");
        out.positive(&k("poll_interval_s"), self.poll_interval_s, "seconds");
        let init_ok = out.positive(&k("backoff_initial_s"), self.backoff_initial_s, "seconds");
        let max_ok = out.positive(&k("backoff_max_s"), self.backoff_max_s, "seconds");
        if init_ok && max_ok && self.backoff_initial_s > self.backoff_max_s {
            out.push(
                k("backoff_max_s"),
                format!(
                    "must be >= backoff_initial_s ({} s), got {} s",
                    self.backoff_initial_s, self.backoff_max_s
                ),
            );
        }
        if self.degrade_after_cycles == 0 {
            out.push(
                k("degrade_after_cycles"),
                "must be >= 1 (failed poll cycles before the channels turn bad)",
            );
        }
    }
}

/// Checks every device, then what devices share: serial lines and CAN interfaces.
pub fn validate_devices(devices: &BTreeMap<String, DeviceConfig>, out: &mut Problems<'_>) {
    for (name, dev) in devices {
        dev.validate(&crate::config::keys::entry("devices", name), out);
    }
    serial_lines(devices, out);
    can_buses(devices, out);
}

/// Devices on one serial line share its settings and its address space.
fn serial_lines(devices: &BTreeMap<String, DeviceConfig>, out: &mut Problems<'_>) {
    let mut lines: BTreeMap<&str, Vec<(&String, &RtuDeviceConfig)>> = BTreeMap::new();
    for (name, d) in devices {
        if let DeviceConfig::Rtu(d) = d {
            lines.entry(&d.serial_path).or_default().push((name, d));
        }
    }
    for (path, devs) in lines {
        let Some(&(first_name, first)) = devs.first() else {
            continue;
        };
        let mut ids: BTreeMap<u8, &String> = BTreeMap::new();
        ids.insert(first.unit_id, first_name);
        for &(name, d) in devs.iter().skip(1) {
            let k = |f: &str| field("devices", name, f);
            let shared = |what: &str, theirs: String| {
                format!(
                    "serial line {path} is shared with `{first_name}`, which uses \
                     {what} {theirs}; all devices on one line must use the same {what}"
                )
            };
            if d.baud() != first.baud() {
                out.push(k("baud"), shared("baud", first.baud().to_string()));
            }
            if d.parity() != first.parity() {
                out.push(
                    k("parity"),
                    shared("parity", format!("{:?}", first.parity()).to_lowercase()),
                );
            }
            if d.stop_bits() != first.stop_bits() {
                out.push(
                    k("stop_bits"),
                    shared("stop_bits", first.stop_bits().to_string()),
                );
            }
            if let Some(other) = ids.insert(d.unit_id, name) {
                out.push(
                    k("unit_id"),
                    format!(
                        "unit id {} is already used by `{other}` on serial line {path}; \
                         devices on one line need distinct unit ids",
                        d.unit_id
                    ),
                );
            }
        }
    }
}

/// CAN nodes on one interface need distinct node ids and share its SYNC period.
fn can_buses(devices: &BTreeMap<String, DeviceConfig>, out: &mut Problems<'_>) {
    let mut seen: BTreeMap<(&str, u8), &String> = BTreeMap::new();
    let mut period: BTreeMap<&str, (&String, f64)> = BTreeMap::new();
    for (name, d) in devices {
        let DeviceConfig::Can(d) = d else {
            continue;
        };
        let i = d.interface.as_str();
        let n = d.node_id;
        if let Some(other) = seen.insert((i, n), name) {
            out.push(
                field("devices", name, "node_id"),
                format!("node id {n} is already used by `{other}` on interface {i}"),
            );
        }
        // One SYNC producer per interface sends at the poll interval: two values
        // would leave one device's cycle and the bus' SYNC out of step.
        let p_new = d.common.poll_interval_s;
        match period.get(i) {
            None => {
                period.insert(i, (name, p_new));
            }
            Some(&(first, p)) if p != p_new => out.push(
                field("devices", name, "poll_interval_s"),
                format!(
                    "interface {i} is shared with `{first}`, which uses poll_interval_s = \
                     {p}; the interface has one SYNC, sent every poll_interval_s, so all \
                     CAN devices on one interface must use the same poll_interval_s"
                ),
            ),
            Some(_) => {}
        }
    }
}

fn default_device_timeout_s() -> f64 {
    1.0
}
fn default_poll_interval_s() -> f64 {
    1.0
}
fn default_backoff_initial_s() -> f64 {
    0.5
}
fn default_backoff_max_s() -> f64 {
    30.0
}
fn default_degrade_after_cycles() -> u32 {
    3
}
