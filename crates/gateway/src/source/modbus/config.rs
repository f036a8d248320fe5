//! `[devices.NAME]` with `transport = "tcp"` or `"rtu"`: the Modbus devices' keys,
//! their validation and what they build ([`LinkSpec`], [`PollParams`]).

use std::time::Duration;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::LinkSpec;
use crate::config::keys::secs;
use crate::config::problem::{Problems, MAX_RTU_UNIT_ID};
use crate::source::config::DeviceCommon;
use crate::source::PollParams;

/// `transport = "tcp"`: a Modbus TCP server.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[schemars(deny_unknown_fields)]
pub struct TcpDeviceConfig {
    /// `host:port` of the Modbus TCP server, e.g. `"192.168.0.10:502"`. Required; at most
    /// 300 characters. Devices at one address (units behind a TCP-to-RTU gateway) share
    /// one connection and take turns on it. Port 0 only for `compgate demo` and
    /// `compgate sim` in a file with `[sim]`: the simulated plant binds a free port and
    /// writes it in.
    #[schemars(length(max = 300))]
    pub address: String,
    /// Modbus unit id, 0..=255. Many TCP modules ignore it; some answer only 255 (the
    /// Modbus TCP guide's id for a device addressed by its IP); behind a TCP-to-RTU
    /// gateway it is the serial device's address, 1..=247. Required.
    pub unit_id: u8,
    /// Seconds a TCP connect may take. Default 2.0; 0.001..=3600.
    #[serde(default = "default_connect_timeout_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub connect_timeout_s: f64,
    /// Retries and request merging.
    #[serde(flatten)]
    pub modbus: ModbusCommon,
    /// Timeouts, poll interval, backoff, degradation.
    #[serde(flatten)]
    pub common: DeviceCommon,
}

impl TcpDeviceConfig {
    /// Default of `connect_timeout_s`.
    pub const DEFAULT_CONNECT_TIMEOUT_S: f64 = 2.0;

    /// `connect_timeout_s` as a [`Duration`].
    pub fn connect_timeout(&self) -> Duration {
        secs(self.connect_timeout_s)
    }

    /// `address` is `host:port`, the connect timeout > 0.
    pub fn validate(&self, key: &str, out: &mut Problems<'_>) {
        let k = |f: &str| format!("{key}.{f}");
        out.host_port(&k("address"), &self.address);
        out.positive(&k("connect_timeout_s"), self.connect_timeout_s, "seconds");
    }

    /// The link to the server.
    pub fn link_spec(&self) -> LinkSpec {
        LinkSpec::Tcp {
            address: self.address.clone(),
            connect_timeout: self.connect_timeout(),
        }
    }

    /// The poller's parameters.
    pub fn poll_params(&self) -> PollParams {
        self.modbus.poll_params(self.unit_id, &self.common)
    }
}

/// `transport = "rtu"`: a Modbus RTU slave on an RS-485 line.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[schemars(deny_unknown_fields)]
pub struct RtuDeviceConfig {
    /// Serial device of the RS-485 line, e.g. `"/dev/ttyUSB0"`. Required; at
    /// most 1024 characters. Several
    /// devices on one path share the line: they must agree on baud, parity and stop
    /// bits and have distinct unit ids.
    #[schemars(length(max = 1024))]
    pub serial_path: String,
    /// Modbus unit id (slave address), 1..=247 (0 is the broadcast address, which
    /// never answers). Required.
    #[schemars(range(max = 247))]
    pub unit_id: u8,
    /// Baud rate, 1200..=115200. Default 19200 (the Modbus serial line default).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 1200, max = 115_200))]
    pub baud: Option<u32>,
    /// Parity: `none`, `even` or `odd`. Default `even` (the Modbus serial line
    /// default).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub parity: Option<Parity>,
    /// Stop bits: 1 or 2. Default 1, or 2 when `parity = "none"` (as the Modbus serial
    /// line specification asks).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 1, max = 2))]
    pub stop_bits: Option<u8>,
    /// Retries and request merging.
    #[serde(flatten)]
    pub modbus: ModbusCommon,
    /// Timeouts, poll interval, backoff, degradation.
    #[serde(flatten)]
    pub common: DeviceCommon,
}

impl RtuDeviceConfig {
    /// Default of `baud`.
    pub const DEFAULT_BAUD: u32 = 19200;
    /// Default of `parity`.
    pub const DEFAULT_PARITY: Parity = Parity::Even;

    /// Effective baud rate: `baud` or 19200.
    pub fn baud(&self) -> u32 {
        self.baud.unwrap_or(Self::DEFAULT_BAUD)
    }
    /// Effective parity: `parity` or even.
    pub fn parity(&self) -> Parity {
        self.parity.unwrap_or(Self::DEFAULT_PARITY)
    }
    /// Effective stop bits: `stop_bits`, or 2 without parity and 1 with parity.
    pub fn stop_bits(&self) -> u8 {
        self.stop_bits.unwrap_or(match self.parity() {
            Parity::None => 2,
            Parity::Even | Parity::Odd => 1,
        })
    }

    /// A serial path, baud 1200..=115200, stop bits 1 or 2, unit id 1..=247.
    pub fn validate(&self, key: &str, out: &mut Problems<'_>) {
        let k = |f: &str| format!("{key}.{f}");
        if self.serial_path.trim().is_empty() {
            out.push(
                k("serial_path"),
                "must name the serial device, e.g. \"/dev/ttyUSB0\"",
            );
        }
        if let Some(b) = self.baud {
            if !(1200..=115_200).contains(&b) {
                out.push(k("baud"), format!("must be 1200..=115200, got {b}"));
            }
        }
        if let Some(s) = self.stop_bits {
            if !(1..=2).contains(&s) {
                out.push(k("stop_bits"), format!("must be 1 or 2, got {s}"));
            }
        }
        if self.unit_id == 0 {
            out.push(
                k("unit_id"),
                "must be 1..=247 on RTU: 0 is the broadcast address, which never answers",
            );
        } else if self.unit_id > MAX_RTU_UNIT_ID {
            out.push(
                k("unit_id"),
                format!(
                    "must be 1..=247 on RTU (a serial device's address), got {}",
                    self.unit_id
                ),
            );
        }
    }

    /// The serial line (devices on one path share it).
    pub fn link_spec(&self) -> LinkSpec {
        LinkSpec::Rtu {
            path: self.serial_path.clone(),
            baud: self.baud(),
            parity: match self.parity() {
                Parity::None => tokio_serial::Parity::None,
                Parity::Even => tokio_serial::Parity::Even,
                Parity::Odd => tokio_serial::Parity::Odd,
            },
            stop_bits: if self.stop_bits() == 2 {
                tokio_serial::StopBits::Two
            } else {
                tokio_serial::StopBits::One
            },
        }
    }

    /// The poller's parameters.
    pub fn poll_params(&self) -> PollParams {
        self.modbus.poll_params(self.unit_id, &self.common)
    }
}

/// The keys that TCP and RTU devices share and CAN devices do not have.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
pub struct ModbusCommon {
    /// Extra attempts of a failed request within one poll cycle. Default 1 (two
    /// attempts in all); 0..=100.
    #[serde(default = "default_retries")]
    #[schemars(range(max = 100))]
    pub retries: u32,
    /// Registers that may be read and discarded to merge two channels into one
    /// request (0 = merge only adjacent channels). Default 8; 0..=125.
    #[serde(default = "default_max_gap_registers")]
    #[schemars(range(max = 125))]
    pub max_gap_registers: u16,
    /// Registers one request may ask for at most. Default 125 (the Modbus limit);
    /// 1..=125. Lower it for a module that answers larger reads with exception 0x03
    /// (illegal data value), as some take only 16 or 32 at a time.
    #[serde(default = "default_max_read_registers")]
    #[schemars(range(min = 1, max = 125))]
    pub max_read_registers: u16,
    /// After each connect (the first, and every reconnect), seconds during which the
    /// device's values are not used (its channels read "no data", its link is up): for
    /// a module that answers 0 or another placeholder until its inputs have settled,
    /// which would otherwise be a good reading. Default 0.0 (used at once); 0..=600.
    #[serde(default)]
    #[schemars(range(min = 0.0, max = 600.0))]
    pub settle_s: f64,
}

impl ModbusCommon {
    /// Default of `retries`.
    pub const DEFAULT_RETRIES: u32 = 1;

    /// The poller's parameters for the device at `unit_id`.
    fn poll_params(&self, unit_id: u8, common: &DeviceCommon) -> PollParams {
        PollParams {
            unit_id,
            timeout: common.timeout(),
            retries: self.retries,
            degrade_after_cycles: common.degrade_after_cycles,
            max_gap_registers: self.max_gap_registers,
            max_read_registers: self.max_read_registers,
            cycle_deadline: common.cycle_deadline(),
            settle: crate::config::keys::secs(self.settle_s),
        }
    }
}

/// Serial parity.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[serde(rename_all = "snake_case")]
pub enum Parity {
    /// No parity bit.
    None,
    /// Even parity.
    Even,
    /// Odd parity.
    Odd,
}

fn default_connect_timeout_s() -> f64 {
    TcpDeviceConfig::DEFAULT_CONNECT_TIMEOUT_S
}
fn default_retries() -> u32 {
    ModbusCommon::DEFAULT_RETRIES
}
fn default_max_gap_registers() -> u16 {
    8
}
fn default_max_read_registers() -> u16 {
    crate::source::plan::MAX_READ_REGISTERS
}
