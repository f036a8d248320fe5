//! The configuration schema: one struct per TOML table.
//!
//! The `///` comment of every field is the operator's manual for that key: meaning,
//! unit, default and allowed range. `config/example.toml` is the annotated example of
//! the same schema; the names here match it exactly. Ranges stated as "allowed" are
//! enforced by [`validate`](super::validate), not by the parser.

use std::collections::BTreeMap;
use std::time::Duration;

use serde::{Deserialize, Serialize};

/// Converts seconds from the configuration into a [`Duration`].
///
/// Saturating: negative or NaN becomes zero, too large becomes [`Duration::MAX`], so a
/// value that [`validate`](super::validate) would reject never panics here.
pub fn secs(s: f64) -> Duration {
    if s.is_nan() || s <= 0.0 {
        Duration::ZERO
    } else {
        Duration::try_from_secs_f64(s).unwrap_or(Duration::MAX)
    }
}

/// A whole configuration file: `[gateway]`, `[devices.NAME]`, `[channels.NAME]`,
/// `[nc_modules.NAME]`, `[axes.NAME]` and the optional `[sim]`.
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Gateway-wide settings. Optional table: every key has a default.
    #[serde(default)]
    pub gateway: GatewayConfig,
    /// Field devices (Modbus TCP servers or Modbus RTU slaves), by name. Required
    /// table; a name is 1..=64 characters of `A-Z a-z 0-9 _ -` without `__`, unique
    /// ignoring case (environment overrides address it case-insensitively).
    pub devices: BTreeMap<String, DeviceConfig>,
    /// Measured values, by name (the name axes refer to). Required table; names as
    /// for devices.
    pub channels: BTreeMap<String, ChannelConfig>,
    /// NC axis modules the compensation is written into, by name. Required table;
    /// names as for devices.
    pub nc_modules: BTreeMap<String, NcModuleConfig>,
    /// Compensated axes, by name (e.g. `X`). Required table; names as for devices.
    pub axes: BTreeMap<String, AxisConfig>,
    /// Simulated plant (demo, tests, commissioning dry runs). Absent by default; the
    /// gateway itself ignores it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sim: Option<SimConfig>,
    /// Durable recording of readings and NC jobs into SQLite. Absent: nothing is
    /// recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recorder: Option<RecorderConfig>,
    /// Prometheus metrics endpoint. Absent: no endpoint.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub metrics: Option<MetricsConfig>,
    /// MQTT publishing of readings, writes and health. Absent: nothing is published.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mqtt: Option<MqttConfig>,
}

// ------------------------------------------------------------------------ gateway --

/// `[gateway]`: settings of the gateway as a whole.
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct GatewayConfig {
    /// Seconds between status updates (status line, logs). Default 1.0; must be > 0.
    #[serde(default = "default_status_interval_s")]
    pub status_interval_s: f64,
}

impl Default for GatewayConfig {
    fn default() -> Self {
        GatewayConfig {
            status_interval_s: default_status_interval_s(),
        }
    }
}

impl GatewayConfig {
    /// `status_interval_s` as a [`Duration`].
    pub fn status_interval(&self) -> Duration {
        secs(self.status_interval_s)
    }
}

// ------------------------------------------------------------------------ devices --

/// `[devices.NAME]`: one Modbus field device (analog input module, transmitter).
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct DeviceConfig {
    /// `tcp` (Modbus TCP) or `rtu` (Modbus RTU on a serial line). Required.
    pub transport: Transport,
    /// `host:port` of the Modbus TCP server, e.g. `"192.168.0.10:502"`. Required for
    /// `tcp`, not allowed for `rtu`. Port 0 is accepted only because the embedded demo
    /// replaces it with the port its simulator bound.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub address: Option<String>,
    /// Serial device of the RS-485 line, e.g. `"/dev/ttyUSB0"`. Required for `rtu`,
    /// not allowed for `tcp`. Several devices on one path share the line: they must
    /// agree on baud, parity and stop bits and have distinct unit ids.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub serial_path: Option<String>,
    /// Baud rate (`rtu` only), 1200..=115200. Default 19200 (the Modbus serial line
    /// default).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub baud: Option<u32>,
    /// Parity (`rtu` only): `none`, `even` or `odd`. Default `even` (the Modbus serial
    /// line default).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub parity: Option<Parity>,
    /// Stop bits (`rtu` only): 1 or 2. Default 1, or 2 when `parity = "none"` (as the
    /// Modbus serial line specification asks).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stop_bits: Option<u8>,
    /// Modbus unit id (slave address). Required for `tcp` and `rtu`, not allowed for
    /// `can`. 0..=247 for `tcp` (many TCP modules ignore it), 1..=247 for `rtu` (0 is
    /// the broadcast address, which never answers).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unit_id: Option<u8>,
    /// SocketCAN interface of the CAN bus, e.g. `"can0"` or `"vcan0"` (`can` only,
    /// required there). The interface must be up with its bitrate set (see
    /// `deploy/`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub interface: Option<String>,
    /// CANopen node id of the device, 1..=127 (`can` only, required there). The
    /// gateway sends it NMT start and reads its TPDOs (COB-ID 0x180, 0x280, 0x380,
    /// 0x480 plus node id), SDOs (0x600 / 0x580 plus node id), heartbeat (0x700 plus
    /// node id) and EMCY (0x080 plus node id). Node ids on one interface must be distinct.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub node_id: Option<u8>,
    /// Heartbeat consumer timeout in seconds (`can` only): a node whose heartbeat
    /// has been missing for longer has all its channels bad. 0 turns the check off.
    /// Default 1.5 (for the common 1 s or faster producer heartbeat time, object
    /// 0x1017); >= 0. The gateway sends each interface's SYNC from a timer of its
    /// own every `poll_interval_s`; `timeout_s` is the longest wait for the
    /// synchronous TPDOs after it and for each SDO answer.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub heartbeat_timeout_s: Option<f64>,
    /// Seconds one request may take before it counts as failed. Default 1.0; > 0.
    #[serde(default = "default_device_timeout_s")]
    pub timeout_s: f64,
    /// Seconds a TCP connect may take (`tcp` only). Default 2.0; > 0.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub connect_timeout_s: Option<f64>,
    /// Extra attempts of a failed request within one poll cycle. Default 1 (two
    /// attempts in all).
    #[serde(default = "default_retries")]
    pub retries: u32,
    /// Seconds between poll cycles. Default 1.0; > 0. On `can` devices also the
    /// period of the interface's SYNC, so all CAN devices on one interface must use
    /// the same value.
    #[serde(default = "default_poll_interval_s")]
    pub poll_interval_s: f64,
    /// Reconnect backoff after a transport fault: first wait in seconds; it doubles
    /// after every further fault up to `backoff_max_s`. Default 0.5; > 0.
    #[serde(default = "default_backoff_initial_s")]
    pub backoff_initial_s: f64,
    /// Longest reconnect wait in seconds. Default 30.0; >= `backoff_initial_s`.
    #[serde(default = "default_backoff_max_s")]
    pub backoff_max_s: f64,
    /// After this many consecutive failed poll cycles the device's channels turn bad;
    /// before that they hold their last value as uncertain. Default 3; >= 1.
    #[serde(default = "default_degrade_after_cycles")]
    pub degrade_after_cycles: u32,
    /// Registers that may be read and discarded to merge two channels into one
    /// request (0 = merge only adjacent channels). Default 8.
    #[serde(default = "default_max_gap_registers")]
    pub max_gap_registers: u16,
}

impl DeviceConfig {
    /// Default of `heartbeat_timeout_s`.
    pub const DEFAULT_HEARTBEAT_TIMEOUT_S: f64 = 1.5;
    /// `heartbeat_timeout_s` (or its default) as a [`Duration`]; zero = off.
    pub fn heartbeat_timeout(&self) -> Duration {
        secs(
            self.heartbeat_timeout_s
                .unwrap_or(Self::DEFAULT_HEARTBEAT_TIMEOUT_S),
        )
    }
    /// Default of `baud`.
    pub const DEFAULT_BAUD: u32 = 19200;
    /// Default of `parity`.
    pub const DEFAULT_PARITY: Parity = Parity::Even;
    /// Default of `connect_timeout_s`.
    pub const DEFAULT_CONNECT_TIMEOUT_S: f64 = 2.0;

    /// `timeout_s` as a [`Duration`].
    pub fn timeout(&self) -> Duration {
        secs(self.timeout_s)
    }
    /// `connect_timeout_s` (or its default) as a [`Duration`].
    pub fn connect_timeout(&self) -> Duration {
        secs(
            self.connect_timeout_s
                .unwrap_or(Self::DEFAULT_CONNECT_TIMEOUT_S),
        )
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
}

/// How a device is reached.
#[derive(Deserialize, Serialize, Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[serde(rename_all = "snake_case")]
pub enum Transport {
    /// Modbus TCP (`address = "host:port"`).
    Tcp,
    /// Modbus RTU on a serial line (`serial_path`, `baud`, `parity`, `stop_bits`).
    Rtu,
    /// A CANopen node on a SocketCAN interface (`interface`, `node_id`,
    /// `heartbeat_timeout_s`).
    Can,
}

/// Serial parity.
#[derive(Deserialize, Serialize, Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[serde(rename_all = "snake_case")]
pub enum Parity {
    /// No parity bit.
    None,
    /// Even parity.
    Even,
    /// Odd parity.
    Odd,
}

// ----------------------------------------------------------------------- channels --

/// `[channels.NAME]`: one value read from one device.
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ChannelConfig {
    /// Name of the device in `[devices]` the value is read from. Required.
    pub device: String,
    /// Register table: `input` (function code 0x04) or `holding` (0x03). Required on
    /// a Modbus device, not allowed on a CAN device.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub register: Option<RegisterKind>,
    /// 0-based PDU address of the first register ("30001" in 1-based documentation
    /// is address 0). Required on a Modbus device, not allowed on a CAN device; the
    /// value's last register must be <= 65535.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub address: Option<u16>,
    /// Where the value sits on a CAN device: a TPDO mapping or an SDO object.
    /// Required on a CAN device, not allowed on a Modbus device.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub can: Option<CanChannelConfig>,
    /// Encoding of the raw value: `u16`, `i16` (one register), `u32`, `i32`, `f32`
    /// (two registers); on CAN little-endian, 2 or 4 bytes (`byte_order` unused).
    /// Required.
    pub data_type: DataType,
    /// Byte order of the value, A = most significant byte: `ABCD` (big-endian),
    /// `CDAB` (word swap), `BADC` (byte swap), `DCBA` (little-endian). For 16-bit types
    /// only AB vs BA matters: ABCD/CDAB = AB, BADC/DCBA = BA. Default `ABCD`.
    #[serde(default)]
    pub byte_order: ByteOrder,
    /// How the raw value becomes degrees Celsius. Required table, tagged by `kind`.
    pub scaling: Scaling,
    /// Spike rejection, smoothing and plausibility. Optional table: every key has a
    /// default.
    #[serde(default)]
    pub filter: FilterConfig,
}

impl ChannelConfig {
    /// Number of 16-bit registers the value occupies (1 or 2).
    pub fn registers(&self) -> u16 {
        self.data_type.registers()
    }
}

/// `[channels.NAME.can]`: where a CAN channel's value is on its node. Either a TPDO
/// mapping (`pdo` and `offset_bytes`) or an SDO object (`sdo_index` and
/// `sdo_subindex`), not both.
#[derive(Deserialize, Serialize, Debug, Clone, Copy, PartialEq, Eq)]
#[serde(deny_unknown_fields)]
pub struct CanChannelConfig {
    /// Synchronous TPDO number 1..=4 (COB-ID 0x180 + 0x100 * (pdo - 1) + node id)
    /// carrying the value, sent by the node after each SYNC.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pdo: Option<u8>,
    /// Byte offset of the value in the TPDO, 0..=7; the value must end within the
    /// 8 data bytes (offset + 2 for 16-bit, + 4 for 32-bit types).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub offset_bytes: Option<u8>,
    /// Object dictionary index read by expedited SDO upload each poll cycle, e.g.
    /// `0x6401` (CiA 401 analogue input 16 bit).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sdo_index: Option<u16>,
    /// Sub-index of the SDO object, 0..=255.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sdo_subindex: Option<u8>,
}

// The wire encodings are the source layer's own types; the config names them.
pub use crate::source::plan::{ByteOrder, DataType, RegisterKind};

/// `[channels.NAME.scaling]`: raw value to degrees Celsius, selected by `kind`.
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(tag = "kind", rename_all = "snake_case", try_from = "ScalingRepr")]
pub enum Scaling {
    /// `kind = "transmitter"`: ADC counts -> mA -> degC of a 4-20 mA (or 0-20 mA)
    /// temperature transmitter.
    Transmitter(TransmitterScaling),
    /// `kind = "direct"`: the device reports the value itself; `raw * gain +
    /// offset_degc`.
    Direct(DirectScaling),
}

/// `kind = "transmitter"`: a current-loop transmitter read through an ADC.
///
/// `mA = raw / adc_full_scale_counts * adc_full_scale_ma`, then the current range maps
/// linearly onto `range_min_degc ..= range_max_degc`.
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TransmitterScaling {
    /// ADC counts at the ADC's full scale, e.g. 4095 for 12 bit. Required; > 0 and
    /// representable in the channel's `data_type` (<= 65535 for u16, <= 32767 for i16).
    /// A `f32` channel is allowed: its value is taken as (fractional) counts.
    pub adc_full_scale_counts: u32,
    /// Current in mA at the ADC's full scale, e.g. 24.0. Required; >= 20 so the top of
    /// the range is reachable (above 21 keeps NAMUR NE43 over-range visible).
    pub adc_full_scale_ma: f64,
    /// `"4-20"` or `"0-20"` mA. Default `"4-20"`; NAMUR NE43 fault detection
    /// (< 3.6 mA or > 21 mA) needs 4-20.
    #[serde(default)]
    pub current_range: CurrentRange,
    /// Temperature in degC at the bottom of the current range (4 or 0 mA). Required.
    pub range_min_degc: f64,
    /// Temperature in degC at the top of the current range (20 mA). Required;
    /// > `range_min_degc`.
    pub range_max_degc: f64,
}

/// `kind = "direct"`: `value_degc = raw * gain + offset_degc`.
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct DirectScaling {
    /// Factor from the raw value to degC, e.g. 0.1 for a module reporting tenths of a
    /// degree. Default 1.0; finite and not 0.
    #[serde(default = "one")]
    pub gain: f64,
    /// Offset in degC added after the gain. Default 0.0.
    #[serde(default)]
    pub offset_degc: f64,
}

/// Current range of a transmitter.
#[derive(Deserialize, Serialize, Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum CurrentRange {
    /// 4-20 mA (live zero, NAMUR NE43 fault detection possible).
    #[default]
    #[serde(rename = "4-20")]
    Ma4To20,
    /// 0-20 mA (no fault detection at the bottom of the range).
    #[serde(rename = "0-20")]
    Ma0To20,
}

impl CurrentRange {
    /// Current in mA at the bottom of the range.
    pub fn min_ma(self) -> f64 {
        match self {
            CurrentRange::Ma4To20 => 4.0,
            CurrentRange::Ma0To20 => 0.0,
        }
    }
    /// Current in mA at the top of the range.
    pub fn max_ma(self) -> f64 {
        20.0
    }
}

/// The parsed form of a `scaling` table before it becomes a [`Scaling`]: one flat
/// table, so that a type error inside it is reported with the key's own path.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ScalingRepr {
    kind: ScalingKind,
    adc_full_scale_counts: Option<u32>,
    adc_full_scale_ma: Option<f64>,
    current_range: Option<CurrentRange>,
    range_min_degc: Option<f64>,
    range_max_degc: Option<f64>,
    gain: Option<f64>,
    offset_degc: Option<f64>,
}

#[derive(Deserialize, Clone, Copy)]
#[serde(rename_all = "snake_case")]
enum ScalingKind {
    Transmitter,
    Direct,
}

impl TryFrom<ScalingRepr> for Scaling {
    type Error = String;

    /// Errors use serde's wording (`unknown field`, `missing field`) so the loader
    /// can attach the key's path to them.
    fn try_from(r: ScalingRepr) -> Result<Self, String> {
        fn required<T>(v: Option<T>, name: &str) -> Result<T, String> {
            v.ok_or_else(|| format!("missing field `{name}`"))
        }
        fn not_for<T>(v: &Option<T>, name: &str, kind: &str) -> Result<(), String> {
            match v {
                Some(_) => Err(format!(
                    "unknown field `{name}` (not used by kind = \"{kind}\")"
                )),
                None => Ok(()),
            }
        }
        match r.kind {
            ScalingKind::Transmitter => {
                not_for(&r.gain, "gain", "transmitter")?;
                not_for(&r.offset_degc, "offset_degc", "transmitter")?;
                Ok(Scaling::Transmitter(TransmitterScaling {
                    adc_full_scale_counts: required(
                        r.adc_full_scale_counts,
                        "adc_full_scale_counts",
                    )?,
                    adc_full_scale_ma: required(r.adc_full_scale_ma, "adc_full_scale_ma")?,
                    current_range: r.current_range.unwrap_or_default(),
                    range_min_degc: required(r.range_min_degc, "range_min_degc")?,
                    range_max_degc: required(r.range_max_degc, "range_max_degc")?,
                }))
            }
            ScalingKind::Direct => {
                not_for(&r.adc_full_scale_counts, "adc_full_scale_counts", "direct")?;
                not_for(&r.adc_full_scale_ma, "adc_full_scale_ma", "direct")?;
                not_for(&r.current_range, "current_range", "direct")?;
                not_for(&r.range_min_degc, "range_min_degc", "direct")?;
                not_for(&r.range_max_degc, "range_max_degc", "direct")?;
                Ok(Scaling::Direct(DirectScaling {
                    gain: r.gain.unwrap_or(1.0),
                    offset_degc: r.offset_degc.unwrap_or(0.0),
                }))
            }
        }
    }
}

/// `[channels.NAME.filter]`: applied to each scaled sample in this order: plausible
/// range, stale detection (on the raw value), rate plausibility, median, low-pass.
/// A sample failing a check never reaches the median and the low-pass.
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct FilterConfig {
    /// Spike rejection: median of this many samples (1 = off). Default 3; odd,
    /// 1..=99 (an even window has no middle sample: a median of 2 is a mean and
    /// rejects no spike, so even numbers are refused).
    #[serde(default = "default_median_samples")]
    pub median_samples: u32,
    /// First-order low-pass time constant in seconds (0 = off). Default 10.0; >= 0.
    #[serde(default = "default_lowpass_tau_s")]
    pub lowpass_tau_s: f64,
    /// Plausibility: a change faster than this (degC per second) is rejected as a
    /// spike (0 = off). Default 0.5; >= 0.
    #[serde(default = "default_max_rate_degc_per_s")]
    pub max_rate_degc_per_s: f64,
    /// Consecutive rejected samples after which the channel is bad and the filter
    /// re-seeds on the new level. Default 5; >= 1.
    #[serde(default = "default_max_rejected_samples")]
    pub max_rejected_samples: u32,
    /// Seconds the raw value may stay unchanged before the transmitter counts as
    /// frozen and the channel turns bad (0 = off). Default 0.0 (off); >= 0.
    #[serde(default)]
    pub stale_after_s: f64,
    /// Lowest plausible value in degC; below it a sample is bad. Default -20.0.
    #[serde(default = "default_valid_min_degc")]
    pub valid_min_degc: f64,
    /// Highest plausible value in degC; above it a sample is bad. Default 80.0;
    /// > `valid_min_degc`.
    #[serde(default = "default_valid_max_degc")]
    pub valid_max_degc: f64,
}

impl Default for FilterConfig {
    fn default() -> Self {
        FilterConfig {
            median_samples: default_median_samples(),
            lowpass_tau_s: default_lowpass_tau_s(),
            max_rate_degc_per_s: default_max_rate_degc_per_s(),
            max_rejected_samples: default_max_rejected_samples(),
            stale_after_s: 0.0,
            valid_min_degc: default_valid_min_degc(),
            valid_max_degc: default_valid_max_degc(),
        }
    }
}

impl FilterConfig {
    /// `lowpass_tau_s` as a [`Duration`] (zero = off).
    pub fn lowpass_tau(&self) -> Duration {
        secs(self.lowpass_tau_s)
    }
    /// `stale_after_s` as a [`Duration`] (zero = off).
    pub fn stale_after(&self) -> Duration {
        secs(self.stale_after_s)
    }
}

// --------------------------------------------------------------------- NC modules --

/// `[nc_modules.NAME]`: an NC axis module reached over Modbus TCP (one axis per
/// module; see `compgate_ncproto`).
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct NcModuleConfig {
    /// `host:port` of the module's Modbus TCP interface. Required. Port 0 is accepted
    /// only because the embedded demo replaces it with the port its simulator bound.
    pub address: String,
    /// Modbus unit id, 0..=247. Required.
    pub unit_id: u8,
    /// Seconds one Modbus request may take. Default 1.0; > 0.
    #[serde(default = "default_nc_timeout_s")]
    pub timeout_s: f64,
    /// Seconds a TCP connect may take. Default 2.0; > 0.
    #[serde(default = "default_connect_timeout_s")]
    pub connect_timeout_s: f64,
    /// Seconds the whole FB3 job (REQ .. DONE/ERROR) may take. Default 2.0; > 0.
    #[serde(default = "default_job_timeout_s")]
    pub job_timeout_s: f64,
}

impl NcModuleConfig {
    /// `timeout_s` as a [`Duration`].
    pub fn timeout(&self) -> Duration {
        secs(self.timeout_s)
    }
    /// `connect_timeout_s` as a [`Duration`].
    pub fn connect_timeout(&self) -> Duration {
        secs(self.connect_timeout_s)
    }
    /// `job_timeout_s` as a [`Duration`].
    pub fn job_timeout(&self) -> Duration {
        secs(self.job_timeout_s)
    }
}

// --------------------------------------------------------------------------- axes --

/// `[axes.NAME]`: one compensated axis,
/// `dKx = K0(T) + tan(beta)(T) * (Px - P0)` -> SD43900, SD43910, SD43920.
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct AxisConfig {
    /// Name of the NC module in `[nc_modules]` that carries this axis. Required; one
    /// axis per module.
    pub nc_module: String,
    /// MD32750 `$MA_TEMP_COMP_TYPE` the NC must have (bit 0: K0, bit 1: slope).
    /// Checked against the NC at start. Required; 0..=7. A K0 model needs bit 0 and a
    /// tan(beta) model needs bit 1, otherwise the NC would ignore the value written.
    pub md32750: u16,
    /// SD43920 `$SA_TEMP_COMP_REF_POSITION`: reference position P0 in mm. Default 0.0.
    #[serde(default)]
    pub p0_mm: f64,
    /// Seconds between compensation updates. Default 10.0; > 0.
    #[serde(default = "default_update_interval_s")]
    pub update_interval_s: f64,
    /// No write while K0 changed less than this (mm). Default 0.001; >= 0.
    #[serde(default = "default_deadband_k0_mm")]
    pub deadband_k0_mm: f64,
    /// No write while tan(beta) changed less than this (dimensionless, mm/mm).
    /// Default 0.000001; >= 0.
    #[serde(default = "default_deadband_tan_beta")]
    pub deadband_tan_beta: f64,
    /// Hard limit of |K0| in mm; a computed value beyond it is clamped and logged.
    /// Default 0.5; > 0.
    #[serde(default = "default_max_abs_k0_mm")]
    pub max_abs_k0_mm: f64,
    /// Hard limit of |tan(beta)|; must stay below the NC's MD32760
    /// `$MA_COMP_ADD_VELO_FACTOR`. Default 0.01 (the MD32760 default); > 0 and
    /// <= 0.1.
    #[serde(default = "default_max_abs_tan_beta")]
    pub max_abs_tan_beta: f64,
    /// Largest change of K0 in one update (mm). Default 0.02; > 0.
    #[serde(default = "default_max_step_k0_mm")]
    pub max_step_k0_mm: f64,
    /// Largest change of tan(beta) in one update. Default 0.00002; > 0.
    #[serde(default = "default_max_step_tan_beta")]
    pub max_step_tan_beta: f64,
    /// What to do while an input channel is bad: `hold` the last value or
    /// `ramp_to_zero`. Default `hold`.
    #[serde(default)]
    pub on_bad_input: OnBadInput,
    /// Ramp rate of K0 towards zero in mm per second (`ramp_to_zero` only).
    /// Default 0.0005; > 0 with `ramp_to_zero`.
    #[serde(default = "default_ramp_k0_mm_per_s")]
    pub ramp_k0_mm_per_s: f64,
    /// Ramp rate of tan(beta) towards zero per second (`ramp_to_zero` only).
    /// Default 0.0000005; > 0 with `ramp_to_zero`.
    #[serde(default = "default_ramp_tan_beta_per_s")]
    pub ramp_tan_beta_per_s: f64,
    /// K0(T) model (SD43900). Optional table; default: offset 0, no terms (K0 = 0).
    #[serde(default)]
    pub k0: K0Model,
    /// tan(beta)(T) model (SD43910). Optional table; default: offset 0, no terms.
    #[serde(default)]
    pub tan_beta: TanBetaModel,
}

impl AxisConfig {
    /// `update_interval_s` as a [`Duration`].
    pub fn update_interval(&self) -> Duration {
        secs(self.update_interval_s)
    }
}

/// Reaction to a bad input channel.
#[derive(Deserialize, Serialize, Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
#[serde(rename_all = "snake_case")]
pub enum OnBadInput {
    /// Keep the last good parameters.
    #[default]
    Hold,
    /// Ramp the parameters towards zero at `ramp_*_per_s`.
    RampToZero,
}

/// `[axes.NAME.k0]`: `K0(T) = offset_mm + sum(coeff_mm_per_degc * (T[channel] -
/// ref_degc))`, in mm.
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct K0Model {
    /// Constant part of K0 in mm. Default 0.0.
    #[serde(default)]
    pub offset_mm: f64,
    /// Linear temperature terms; each channel at most once. Default none.
    #[serde(default)]
    pub terms: Vec<K0Term>,
}

/// One term of the K0 model.
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct K0Term {
    /// Name of the channel in `[channels]`. Required.
    pub channel: String,
    /// Temperature in degC at which the term is zero. Default 20.0 (ISO 1 reference
    /// temperature).
    #[serde(default = "default_ref_degc")]
    pub ref_degc: f64,
    /// K0 change in mm per degC. Required.
    pub coeff_mm_per_degc: f64,
}

/// `[axes.NAME.tan_beta]`: `tan(beta)(T) = offset + sum(coeff_per_degc * (T[channel] -
/// ref_degc))`, dimensionless (mm/mm).
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct TanBetaModel {
    /// Constant part of tan(beta). Default 0.0.
    #[serde(default)]
    pub offset: f64,
    /// Linear temperature terms; each channel at most once. Default none.
    #[serde(default)]
    pub terms: Vec<TanBetaTerm>,
}

/// One term of the tan(beta) model.
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TanBetaTerm {
    /// Name of the channel in `[channels]`. Required.
    pub channel: String,
    /// Temperature in degC at which the term is zero. Default 20.0.
    #[serde(default = "default_ref_degc")]
    pub ref_degc: f64,
    /// tan(beta) change per degC, e.g. 0.0000115 for a steel ball screw
    /// (11.5 um/m/K). Required.
    pub coeff_per_degc: f64,
}

// ---------------------------------------------------------------------------- sim --

/// `[sim]`: the simulated plant used by the demo, the tests and commissioning dry
/// runs. The gateway ignores it.
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SimConfig {
    /// Seed of the noise generator, so a run can be repeated. Default 1.
    #[serde(default = "default_seed")]
    pub seed: u64,
    /// Temperature profiles by channel name (must exist in `[channels]`). A channel
    /// not listed reads [`SimChannelConfig::default`]: a constant 20 degC.
    #[serde(default)]
    pub channels: BTreeMap<String, SimChannelConfig>,
    /// Simulated NC axis modules by name (must exist in `[nc_modules]`). A module not
    /// listed behaves as [`SimNcModuleConfig::default`].
    #[serde(default)]
    pub nc_modules: BTreeMap<String, SimNcModuleConfig>,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            seed: default_seed(),
            channels: BTreeMap::new(),
            nc_modules: BTreeMap::new(),
        }
    }
}

impl SimConfig {
    /// The profile of channel `name`: its entry or the default.
    pub fn channel(&self, name: &str) -> SimChannelConfig {
        self.channels.get(name).cloned().unwrap_or_default()
    }
    /// The simulated NC module `name`: its entry or the default.
    pub fn nc_module(&self, name: &str) -> SimNcModuleConfig {
        self.nc_modules.get(name).cloned().unwrap_or_default()
    }
}

/// `[sim.channels.NAME]`: the temperature the simulated transmitter reports, with `t`
/// in seconds since the simulator started:
///
/// - `constant`: `mean_degc`
/// - `ramp`: `mean_degc + rate_degc_per_s * t`
/// - `sine`: `mean_degc + amplitude_degc * sin(2 pi t / period_s)`
///
/// plus uniform noise of +-`noise_degc`.
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SimChannelConfig {
    /// `constant`, `ramp` or `sine`. Default `constant`.
    #[serde(default)]
    pub profile: SimProfile,
    /// Mean (constant, sine) or start value (ramp) in degC. Default 20.0.
    #[serde(default = "default_ref_degc")]
    pub mean_degc: f64,
    /// Amplitude of the sine in degC (`sine` only). Default 0.0; >= 0.
    #[serde(default)]
    pub amplitude_degc: f64,
    /// Period of the sine in seconds (`sine` only). Default 600.0; > 0.
    #[serde(default = "default_sim_period_s")]
    pub period_s: f64,
    /// Slope of the ramp in degC per second (`ramp` only; may be negative).
    /// Default 0.0.
    #[serde(default)]
    pub rate_degc_per_s: f64,
    /// Half-width of the uniform noise in degC. Default 0.0; >= 0.
    #[serde(default)]
    pub noise_degc: f64,
}

impl Default for SimChannelConfig {
    fn default() -> Self {
        SimChannelConfig {
            profile: SimProfile::Constant,
            mean_degc: default_ref_degc(),
            amplitude_degc: 0.0,
            period_s: default_sim_period_s(),
            rate_degc_per_s: 0.0,
            noise_degc: 0.0,
        }
    }
}

/// Shape of a simulated temperature.
#[derive(Deserialize, Serialize, Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
#[serde(rename_all = "snake_case")]
pub enum SimProfile {
    /// `mean_degc`.
    #[default]
    Constant,
    /// `mean_degc + rate_degc_per_s * t`.
    Ramp,
    /// `mean_degc + amplitude_degc * sin(2 pi t / period_s)`.
    Sine,
}

/// `[sim.nc_modules.NAME]`: state of a simulated NC axis module. MD32750 may differ
/// from the axis' `md32750` on purpose (fault injection: the gateway must refuse).
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SimNcModuleConfig {
    /// Whether the axis is referenced (homed); an unreferenced axis refuses
    /// compensation writes. Default true.
    #[serde(default = "yes")]
    pub referenced: bool,
    /// MD32750 `$MA_TEMP_COMP_TYPE` of the simulated NC. Default 3; 0..=7.
    #[serde(default = "default_sim_md32750")]
    pub md32750: u16,
    /// Lower end of the simulated back-and-forth motion in mm. Default 0.0.
    #[serde(default)]
    pub motion_min_mm: f64,
    /// Upper end of the simulated motion in mm. Default 0.0; >= `motion_min_mm`.
    #[serde(default)]
    pub motion_max_mm: f64,
    /// Speed of the simulated motion in mm per second (0 = the axis stands at
    /// `motion_min_mm`). Default 0.0; >= 0.
    #[serde(default)]
    pub motion_speed_mm_per_s: f64,
}

impl Default for SimNcModuleConfig {
    fn default() -> Self {
        SimNcModuleConfig {
            referenced: true,
            md32750: default_sim_md32750(),
            motion_min_mm: 0.0,
            motion_max_mm: 0.0,
            motion_speed_mm_per_s: 0.0,
        }
    }
}

// ----------------------------------------------------------------------- defaults --

fn one() -> f64 {
    1.0
}
fn yes() -> bool {
    true
}
fn default_status_interval_s() -> f64 {
    1.0
}
fn default_device_timeout_s() -> f64 {
    1.0
}
fn default_retries() -> u32 {
    1
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
fn default_max_gap_registers() -> u16 {
    8
}
fn default_median_samples() -> u32 {
    3
}
fn default_lowpass_tau_s() -> f64 {
    10.0
}
fn default_max_rate_degc_per_s() -> f64 {
    0.5
}
fn default_max_rejected_samples() -> u32 {
    5
}
fn default_valid_min_degc() -> f64 {
    -20.0
}
fn default_valid_max_degc() -> f64 {
    80.0
}
fn default_nc_timeout_s() -> f64 {
    1.0
}
fn default_connect_timeout_s() -> f64 {
    DeviceConfig::DEFAULT_CONNECT_TIMEOUT_S
}
fn default_job_timeout_s() -> f64 {
    2.0
}
fn default_update_interval_s() -> f64 {
    10.0
}
fn default_deadband_k0_mm() -> f64 {
    0.001
}
fn default_deadband_tan_beta() -> f64 {
    0.000_001
}
fn default_max_abs_k0_mm() -> f64 {
    0.5
}
fn default_max_abs_tan_beta() -> f64 {
    0.01
}
fn default_max_step_k0_mm() -> f64 {
    0.02
}
fn default_max_step_tan_beta() -> f64 {
    0.000_02
}
fn default_ramp_k0_mm_per_s() -> f64 {
    0.0005
}
fn default_ramp_tan_beta_per_s() -> f64 {
    0.000_000_5
}
fn default_ref_degc() -> f64 {
    20.0
}
fn default_seed() -> u64 {
    1
}
fn default_sim_period_s() -> f64 {
    600.0
}
fn default_sim_md32750() -> u16 {
    3
}

// ---------------------------------------------------------------- service sections --

/// `[recorder]`: every poll cycle's raw and filtered readings with their quality, every
/// NC job with its result, and the NC's position, into an SQLite database (WAL mode).
/// Writes are batched on a thread of their own; the control loop never waits for them.
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RecorderConfig {
    /// Database file. A relative path is taken from `$STATE_DIRECTORY` (set by the
    /// unit's `StateDirectory=`, `/var/lib/compgate`), else from the working directory.
    /// Default `compgate.db`.
    #[serde(default = "default_recorder_path")]
    pub path: String,
    /// Seconds between commits of the batched writes: a crash loses at most this much.
    /// Default 0.5; > 0 and <= 1.
    #[serde(default = "default_commit_interval_s")]
    pub commit_interval_s: f64,
    /// Poll cycles the queue between the control loop and the writer holds. When it
    /// is full, cycles are dropped, counted and logged; the loop never waits. Default
    /// 4096; >= 1.
    #[serde(default = "default_queue_cycles")]
    pub queue_cycles: u32,
    /// Days readings, jobs and NC positions are kept. Default 90; > 0.
    #[serde(default = "default_retention_days")]
    pub retention_days: f64,
    /// Largest size of the data in the database, MB; beyond it the oldest records go
    /// first. Default 2048; > 0.
    #[serde(default = "default_max_size_mb")]
    pub max_size_mb: f64,
    /// Seconds between retention passes (age and size). Default 60; > 0.
    #[serde(default = "default_retention_interval_s")]
    pub retention_interval_s: f64,
}

impl Default for RecorderConfig {
    fn default() -> Self {
        RecorderConfig {
            path: default_recorder_path(),
            commit_interval_s: default_commit_interval_s(),
            queue_cycles: default_queue_cycles(),
            retention_days: default_retention_days(),
            max_size_mb: default_max_size_mb(),
            retention_interval_s: default_retention_interval_s(),
        }
    }
}

fn default_recorder_path() -> String {
    "compgate.db".into()
}
fn default_commit_interval_s() -> f64 {
    0.5
}
fn default_queue_cycles() -> u32 {
    4096
}
fn default_retention_days() -> f64 {
    90.0
}
fn default_max_size_mb() -> f64 {
    2048.0
}
fn default_retention_interval_s() -> f64 {
    60.0
}

/// `[metrics]`: a Prometheus text endpoint (`GET /metrics`).
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MetricsConfig {
    /// `host:port` to listen on. Default `127.0.0.1:9464` (localhost only; expose it
    /// further on purpose, e.g. `0.0.0.0:9464` behind the plant firewall).
    #[serde(default = "default_metrics_bind")]
    pub bind: String,
}

impl Default for MetricsConfig {
    fn default() -> Self {
        MetricsConfig {
            bind: default_metrics_bind(),
        }
    }
}

fn default_metrics_bind() -> String {
    "127.0.0.1:9464".into()
}

/// `[mqtt]`: publishing to an MQTT broker with QoS 1. Topics are
/// `<topic_prefix>/<machine>/...` (see the README). Messages wait in the recorder's
/// database until the broker acknowledges them, so `[recorder]` is required.
#[derive(Deserialize, Serialize, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MqttConfig {
    /// Broker `host:port`, e.g. `"broker.plant.local:1883"`. Required.
    pub broker: String,
    /// Machine name in every topic, 1..=64 characters of `A-Z a-z 0-9 _ -`. Required.
    pub machine: String,
    /// First topic level(s). Default `compgate`; no `+`, `#` or leading/trailing `/`.
    #[serde(default = "default_topic_prefix")]
    pub topic_prefix: String,
    /// MQTT client id. Default `compgate-<machine>`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client_id: Option<String>,
    /// Seconds between readings messages per channel (the latest reading is sent).
    /// Default 1.0; > 0.
    #[serde(default = "default_publish_interval_s")]
    pub publish_interval_s: f64,
    /// MQTT keep-alive, seconds. Default 10; >= 1.
    #[serde(default = "default_keep_alive_s")]
    pub keep_alive_s: f64,
    /// Seconds before a message unacknowledged by a connected broker is sent again,
    /// and between reconnect attempts. Default 2; > 0.
    #[serde(default = "default_retry_s")]
    pub retry_s: f64,
    /// Messages kept for the broker at most (oldest dropped, counted and logged beyond).
    /// Default 1000000; >= 1.
    #[serde(default = "default_outbox_max_messages")]
    pub outbox_max_messages: u64,
}

fn default_topic_prefix() -> String {
    "compgate".into()
}
fn default_publish_interval_s() -> f64 {
    1.0
}
fn default_keep_alive_s() -> f64 {
    10.0
}
fn default_retry_s() -> f64 {
    2.0
}
fn default_outbox_max_messages() -> u64 {
    1_000_000
}
