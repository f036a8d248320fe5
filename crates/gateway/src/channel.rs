//! `[channels.NAME]`: where a measured value is read, how it is scaled and filtered;
//! the channel's validation and the [`ChannelProcessor`](rt::ChannelProcessor) it builds.

use std::time::Duration;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::config::keys::secs;
use crate::config::problem::Problems;
use crate::source::can::config::CanChannelConfig;
use crate::source::config::{DeviceConfig, Transport};
pub use crate::source::plan::{ByteOrder, DataType, RegisterKind};
use compgate_core::channel as rt;

/// Largest median window accepted.
const MAX_MEDIAN_SAMPLES: u32 = 99;

/// Counts of converter noise the rate check tolerates between two samples (+-1 count).
pub const RATE_NOISE_COUNTS: f64 = 2.0;

/// `[channels.NAME]`: one value read from one device.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ChannelConfig {
    /// Name of the device in `[devices]` the value is read from. Required; at most 64
    /// characters.
    #[schemars(length(max = 64))]
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

    /// Checks the channel; `key` is its path (`channels.NAME`), `device` its device
    /// when that exists (whether the value sits in registers or in a CAN object
    /// depends on it).
    pub fn validate(&self, key: &str, device: Option<&DeviceConfig>, out: &mut Problems<'_>) {
        self.validate_place(key, device.map(DeviceConfig::transport), out);
        let k = |f: &str| format!("{key}.{f}");
        let n = u32::from(self.registers());
        if self.address.is_some_and(|a| u32::from(a) + n > 65_536) {
            out.push(
                k("address"),
                format!(
                    "a {} value takes {n} registers and would run past address 65535; \
                     expected address <= {}",
                    self.data_type.name(),
                    65_536 - n
                ),
            );
        }
        self.scaling.validate(&k("scaling"), self.data_type, out);
        self.filter.validate(&k("filter"), out);
    }

    /// Where a channel is: registers on a Modbus device, `can` on a CAN device.
    fn validate_place(&self, key: &str, transport: Option<Transport>, out: &mut Problems<'_>) {
        let k = |f: &str| format!("{key}.{f}");
        let on_can = match transport {
            Some(t) => t == Transport::Can,
            None => self.can.is_some(),
        };
        if !on_can {
            if self.can.is_some() {
                out.push(
                    k("can"),
                    format!(
                        "only for a channel on a CAN device (transport = \"can\"); `{}` is a Modbus device",
                        self.device
                    ),
                );
            }
            for (f, present) in [
                ("register", self.register.is_some()),
                ("address", self.address.is_some()),
            ] {
                if !present {
                    out.push(k(f), "required for a channel on a Modbus device");
                }
            }
            return;
        }
        for (f, present) in [
            ("register", self.register.is_some()),
            ("address", self.address.is_some()),
        ] {
            if present {
                out.push(
                    k(f),
                    format!(
                        "not used on the CAN device `{}`; give the TPDO or SDO object in `can`",
                        self.device
                    ),
                );
            }
        }
        match &self.can {
            Some(can) => can.validate(&k("can"), self.data_type, out),
            None => out.push(
                k("can"),
                format!(
                    "required for a channel on the CAN device `{}`: {{ pdo = 1, offset_bytes = 0 }} \
                     or {{ sdo_index = 0x6401, sdo_subindex = 1 }}",
                    self.device
                ),
            ),
        }
    }

    /// The channel's processing (scaling and filters).
    pub fn build(&self) -> rt::ChannelProcessor {
        let scaling = self.scaling.build();
        let mut filter = self.filter.build();
        filter.rate_tolerance_degc = self.rate_tolerance_degc(&scaling);
        rt::ChannelProcessor::new(scaling, filter)
    }

    /// What the rate check accepts on top of `max_rate_degc_per_s`: two counts of the
    /// converter in degC. With +-1 count of noise two samples of a steady temperature
    /// differ by up to two counts; on a 12-bit ADC (4095 counts at 24 mA, -50..150 degC)
    /// that is 0.147 degC, more than 0.5 degC/s allows in a 0.2 s poll. A float from a
    /// module that scales it itself has no known count: no tolerance.
    fn rate_tolerance_degc(&self, scaling: &rt::Scaling) -> f64 {
        match (&self.scaling, self.data_type) {
            (Scaling::Direct(_), DataType::F32) => 0.0,
            _ => RATE_NOISE_COUNTS * scaling.degc_per_raw_unit(),
        }
    }
}

/// `[channels.NAME.scaling]`: raw value to degrees Celsius, selected by `kind`.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Scaling {
    /// `kind = "transmitter"`: ADC counts -> mA -> degC of a 4-20 mA (or 0-20 mA)
    /// temperature transmitter.
    Transmitter(TransmitterScaling),
    /// `kind = "direct"`: the device reports the value itself; `raw * gain +
    /// offset_degc`.
    Direct(DirectScaling),
}

impl Scaling {
    /// Counts representable in `data_type`, `adc_full_scale_ma >= 20`, a range;
    /// a finite gain other than 0.
    pub fn validate(&self, key: &str, data_type: DataType, out: &mut Problems<'_>) {
        let k = |f: &str| format!("{key}.{f}");
        match self {
            Scaling::Transmitter(t) => {
                let max_counts = match data_type {
                    DataType::U16 => Some(u32::from(u16::MAX)),
                    DataType::I16 => Some(i16::MAX as u32),
                    DataType::U32 | DataType::I32 | DataType::F32 => None,
                };
                let key = k("adc_full_scale_counts");
                if t.adc_full_scale_counts == 0 {
                    out.push(key, "must be > 0, e.g. 4095 for a 12-bit ADC");
                } else if let Some(max) = max_counts.filter(|m| t.adc_full_scale_counts > *m) {
                    out.push(
                        key,
                        format!(
                            "{} counts cannot be read as {}; expected <= {max}",
                            t.adc_full_scale_counts,
                            data_type.name()
                        ),
                    );
                }
                let ma = t.adc_full_scale_ma;
                if !(ma.is_finite() && ma >= 20.0) {
                    out.push(
                        k("adc_full_scale_ma"),
                        format!(
                            "must be >= 20 mA so the top of the {}-20 mA range is reachable \
                             (above 21 keeps NE43 over-range visible), got {ma}",
                            t.current_range.min_ma()
                        ),
                    );
                }
                let lo = out.finite(&k("range_min_degc"), t.range_min_degc);
                let hi = out.finite(&k("range_max_degc"), t.range_max_degc);
                if lo && hi && t.range_min_degc >= t.range_max_degc {
                    out.push(
                        k("range_max_degc"),
                        format!(
                            "must be > range_min_degc ({} degC), got {} degC",
                            t.range_min_degc, t.range_max_degc
                        ),
                    );
                }
            }
            Scaling::Direct(d) => {
                if !(d.gain.is_finite() && d.gain != 0.0) {
                    out.push(
                        k("gain"),
                        format!("must be a finite number other than 0, got {}", d.gain),
                    );
                }
                out.finite(&k("offset_degc"), d.offset_degc);
            }
        }
    }

    /// The runtime scaling.
    pub fn build(&self) -> rt::Scaling {
        match self {
            Scaling::Transmitter(t) => rt::Scaling::Transmitter {
                adc_full_scale_counts: f64::from(t.adc_full_scale_counts),
                adc_full_scale_ma: t.adc_full_scale_ma,
                current_range: match t.current_range {
                    CurrentRange::Ma4To20 => rt::CurrentRange::FourTo20,
                    CurrentRange::Ma0To20 => rt::CurrentRange::ZeroTo20,
                },
                range_min_degc: t.range_min_degc,
                range_max_degc: t.range_max_degc,
            },
            Scaling::Direct(d) => rt::Scaling::Direct {
                gain: d.gain,
                offset_degc: d.offset_degc,
            },
        }
    }
}

/// `kind = "transmitter"`: a current-loop transmitter read through an ADC.
///
/// `mA = raw / adc_full_scale_counts * adc_full_scale_ma`, then the current range maps
/// linearly onto `range_min_degc ..= range_max_degc`.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TransmitterScaling {
    /// ADC counts at the ADC's full scale, e.g. 4095 for 12 bit. Required; >= 1 and
    /// representable in the channel's `data_type` (<= 65535 for u16, <= 32767 for i16).
    /// A `f32` channel is allowed: its value is taken as (fractional) counts.
    #[schemars(range(min = 1))]
    pub adc_full_scale_counts: u32,
    /// Current in mA at the ADC's full scale, e.g. 24.0. Required; 20..=50 so the top of
    /// the range is reachable (above 21 keeps NAMUR NE43 over-range visible).
    #[schemars(range(min = 20.0, max = 50.0))]
    pub adc_full_scale_ma: f64,
    /// `"4-20"` or `"0-20"` mA. Default `"4-20"`; NAMUR NE43 fault detection
    /// (< 3.6 mA or > 21 mA) needs 4-20.
    #[serde(default)]
    pub current_range: CurrentRange,
    /// Temperature in degC at the bottom of the current range (4 or 0 mA). Required;
    /// -273.15..=2000.
    #[schemars(range(min = -273.15, max = 2000.0))]
    pub range_min_degc: f64,
    /// Temperature in degC at the top of the current range (20 mA). Required;
    /// -273.15..=2000 and > `range_min_degc`.
    #[schemars(range(min = -273.15, max = 2000.0))]
    pub range_max_degc: f64,
}

/// `kind = "direct"`: `value_degc = raw * gain + offset_degc`.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct DirectScaling {
    /// Factor from the raw value to degC, e.g. 0.1 for a module reporting tenths of a
    /// degree. Default 1.0; -1e6..=1e6 and not 0.
    #[serde(default = "one")]
    #[schemars(range(min = -1e6, max = 1e6))]
    pub gain: f64,
    /// Offset in degC added after the gain. Default 0.0; -2000..=2000.
    #[serde(default)]
    #[schemars(range(min = -2000.0, max = 2000.0))]
    pub offset_degc: f64,
}

/// Current range of a transmitter.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
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

/// `[channels.NAME.filter]`: applied to each scaled sample in this order: plausible
/// range, stale detection (on the raw value), rate plausibility, median, low-pass.
/// A sample failing a check never reaches the median and the low-pass.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct FilterConfig {
    /// Spike rejection: median of this many samples (1 = off). Default 3; odd,
    /// 1..=99 (an even window has no middle sample: a median of 2 is a mean and
    /// rejects no spike, so even numbers are refused).
    #[serde(default = "default_median_samples")]
    #[schemars(range(min = 1, max = 99), extend("not" = {"multipleOf": 2}))]
    pub median_samples: u32,
    /// First-order low-pass time constant in seconds (0 = off). Default 10.0;
    /// 0..=86400.
    #[serde(default = "default_lowpass_tau_s")]
    #[schemars(range(min = 0.0, max = 86400.0))]
    pub lowpass_tau_s: f64,
    /// Plausibility: a change faster than this (degC per second) is rejected as a
    /// spike (0 = off). Default 0.5; 0..=100000. A change within two counts of the
    /// converter (+-1 count of noise; 0.147 degC for 4095 counts at 24 mA over
    /// -50..150 degC) is always accepted on top, except on a `f32` channel with
    /// `direct` scaling, which has no counts.
    #[serde(default = "default_max_rate_degc_per_s")]
    #[schemars(range(min = 0.0, max = 100_000.0))]
    pub max_rate_degc_per_s: f64,
    /// Consecutive rejected samples after which the channel is bad and the filter
    /// re-seeds on the new level. Default 5; 1..=10000.
    #[serde(default = "default_max_rejected_samples")]
    #[schemars(range(min = 1, max = 10_000))]
    pub max_rejected_samples: u32,
    /// Seconds the raw value may stay unchanged before the transmitter counts as
    /// frozen and the channel turns bad (0 = off). Default 0.0 (off); 0..=86400.
    #[serde(default)]
    #[schemars(range(min = 0.0, max = 86400.0))]
    pub stale_after_s: f64,
    /// Lowest plausible value in degC; below it a sample is bad. Default -20.0;
    /// -273.15..=2000.
    #[serde(default = "default_valid_min_degc")]
    #[schemars(range(min = -273.15, max = 2000.0))]
    pub valid_min_degc: f64,
    /// Highest plausible value in degC; above it a sample is bad. Default 80.0;
    /// -273.15..=2000 and > `valid_min_degc`.
    #[serde(default = "default_valid_max_degc")]
    #[schemars(range(min = -273.15, max = 2000.0))]
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

    /// Odd median 1..=99, times and rates >= 0, `max_rejected_samples >= 1`,
    /// `valid_min_degc < valid_max_degc`.
    pub fn validate(&self, key: &str, out: &mut Problems<'_>) {
        let k = |f: &str| format!("{key}.{f}");
        let m = self.median_samples;
        if m == 0 || m > MAX_MEDIAN_SAMPLES || m.is_multiple_of(2) {
            out.push(
                k("median_samples"),
                format!(
                    "must be an odd number 1..={MAX_MEDIAN_SAMPLES} (1 = off; an even \
                     window has no middle sample), got {m}"
                ),
            );
        }
        out.non_negative(&k("lowpass_tau_s"), self.lowpass_tau_s, "seconds, 0 = off");
        out.non_negative(
            &k("max_rate_degc_per_s"),
            self.max_rate_degc_per_s,
            "degC per second, 0 = off",
        );
        if self.max_rejected_samples == 0 {
            out.push(
                k("max_rejected_samples"),
                "must be >= 1 (rejected samples before the channel turns bad)",
            );
        }
        out.non_negative(&k("stale_after_s"), self.stale_after_s, "seconds, 0 = off");
        let lo = out.finite(&k("valid_min_degc"), self.valid_min_degc);
        let hi = out.finite(&k("valid_max_degc"), self.valid_max_degc);
        if lo && hi && self.valid_min_degc >= self.valid_max_degc {
            out.push(
                k("valid_max_degc"),
                format!(
                    "must be > valid_min_degc ({} degC), got {} degC",
                    self.valid_min_degc, self.valid_max_degc
                ),
            );
        }
    }

    /// The runtime filter parameters.
    pub fn build(&self) -> rt::FilterParams {
        rt::FilterParams {
            median_samples: self.median_samples.max(1) as usize,
            lowpass_tau_s: self.lowpass_tau_s,
            max_rate_degc_per_s: self.max_rate_degc_per_s,
            // Depends on the scaling: set by `ChannelConfig::build`.
            rate_tolerance_degc: 0.0,
            max_rejected_samples: self.max_rejected_samples,
            stale_after_s: self.stale_after_s,
            valid_min_degc: self.valid_min_degc,
            valid_max_degc: self.valid_max_degc,
        }
    }
}

fn one() -> f64 {
    1.0
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

#[cfg(test)]
mod tests {
    use super::*;
    use compgate_core::channel::{Quality, Reason};

    /// A 12-bit PT100 channel with the default filter.
    fn pt100_with_defaults() -> ChannelConfig {
        crate::config::load_str(
            r#"
[devices.ain1]
transport = "tcp"
address = "127.0.0.1:502"
unit_id = 1

[channels.T]
device = "ain1"
register = "input"
address = 0
data_type = "u16"
scaling = { kind = "transmitter", adc_full_scale_counts = 4095, adc_full_scale_ma = 24.0, range_min_degc = -50.0, range_max_degc = 150.0 }
"#,
            "t.toml",
        )
        .expect("valid")
        .channels["T"]
            .clone()
    }

    // Issue 23, trap 6: with +-1 count of noise, the default rate limit and a 0.2 s
    // poll, about 10 % of the readings were `uncertain(rate rejected)`. The converter's
    // own quantisation is tolerated; a real spike is still rejected.
    #[test]
    fn the_default_filter_tolerates_one_count_of_noise_at_a_fast_poll() {
        let mut p = pt100_with_defaults().build();
        // 30 degC = 8.8 mA = 1501.5 counts; noise -1, 0, +1 counts from an LCG.
        let mut x: u64 = 42;
        let mut rejected = 0;
        for k in 0..5000 {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let noise = f64::from((x >> 33) as u32 % 3) - 1.0;
            let r = p.on_sample(0.2 * f64::from(k), 1501.0 + noise);
            if r.quality != Quality::Good {
                rejected += 1;
            }
        }
        assert_eq!(rejected, 0, "samples not good out of 5000");
        // 10 counts (0.73 degC) in 0.2 s is a spike.
        let r = p.on_sample(1000.0, 1511.0);
        assert_eq!(r.quality, Quality::Uncertain(Reason::RateRejected));
    }

    #[test]
    fn a_float_in_degc_has_no_count_to_tolerate() {
        let mut ch = pt100_with_defaults();
        ch.data_type = DataType::F32;
        ch.scaling = Scaling::Direct(DirectScaling {
            gain: 1.0,
            offset_degc: 0.0,
        });
        assert_eq!(ch.build().filter_params().rate_tolerance_degc, 0.0);
        ch.data_type = DataType::I16;
        assert_eq!(ch.build().filter_params().rate_tolerance_degc, 2.0);
    }
}
