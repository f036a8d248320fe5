//! The synchronous part of the gateway: channel processors and axis compensators.

use std::sync::Arc;
use std::time::Duration;

use tokio::time::Instant;

use crate::source::plan::{self, ByteOrder, DataType};
use crate::source::DeviceSample;
use compgate_core::channel::{ChannelProcessor, LowPassGain, Quality, Reading, Reason};
use compgate_core::comp::{AxisCompensator, Decision};

use super::{ChannelReading, ChannelStatus};

/// One axis at run time.
#[derive(Debug)]
pub struct AxisRt {
    /// Axis name.
    pub name: String,
    /// Index of its NC writer.
    pub nc_module: usize,
    /// Channel index of each model input.
    pub inputs: Vec<usize>,
    /// The compensator.
    pub comp: AxisCompensator,
    /// MD32750 the config expects.
    pub md32750: u16,
    /// Time between updates.
    pub update_interval: Duration,
    /// The variables it may write (its allow-list), as ids.
    pub nc_write: Vec<u16>,
    /// Shadow mode: compute and record, never write the NC.
    pub shadow: bool,
    /// The temperatures its model was fitted over (`fitted_degc`).
    pub fitted: Vec<FittedRange>,
}

/// How far past its fitted range a reading is flagged, K: the noise and a day's
/// drift of a sensor at the range's edge are no extrapolation worth a warning.
pub const FIT_MARGIN_K: f64 = 2.0;

/// How much closer than [`FIT_MARGIN_K`] a flagged reading must come to clear, K.
pub const FIT_HYSTERESIS_K: f64 = 0.5;

/// One input channel's temperatures the model was fitted over.
#[derive(Debug, Clone, PartialEq)]
pub struct FittedRange {
    /// Channel index.
    pub channel: usize,
    /// Lowest temperature in the fitted data, degC.
    pub min_degc: f64,
    /// Highest, degC.
    pub max_degc: f64,
}

/// The synchronous part of the gateway: channel processors and axis compensators.
/// The core loop and `compgate bench` drive the same code.
#[derive(Debug)]
pub struct Pipeline {
    /// Channel names, in config order (shared with every [`SampleReadings`](super::SampleReadings)).
    pub channel_names: Arc<[String]>,
    /// One processor per channel: the channel's only state.
    pub(super) processors: Vec<ChannelProcessor>,
    /// One per axis.
    pub axes: Vec<AxisRt>,
    /// Model inputs of the last decision (kept for its allocation).
    pub(super) temps_degc: Vec<Option<f64>>,
    pub(super) epoch: Instant,
    /// Per channel, config order: how a Modbus channel's registers encode its value
    /// (`None` on CAN), to name the likely byte order of an implausible value.
    pub(super) encodings: Vec<Option<(DataType, ByteOrder)>>,
}

impl Pipeline {
    /// Seconds since the pipeline started: the time base of channels and axes.
    pub fn now_s(&self, at: Instant) -> f64 {
        at.saturating_duration_since(self.epoch).as_secs_f64()
    }

    /// A pipeline over `processors` (config order).
    pub(super) fn new(
        channel_names: Vec<String>,
        processors: Vec<ChannelProcessor>,
        axes: Vec<AxisRt>,
        encodings: Vec<Option<(DataType, ByteOrder)>>,
    ) -> Self {
        Self {
            channel_names: channel_names.into(),
            processors,
            axes,
            temps_degc: Vec::new(),
            epoch: Instant::now(),
            encodings,
        }
    }

    /// When channel `ch`'s `reading` is bad in a way a wrong byte order produces (an
    /// implausible raw value, out of range, NE43) and another order of its registers
    /// gives a plausible temperature: a sentence naming that order, e.g. "reads raw
    /// -1.595e-23 as ABCD; as CDAB it would read 23.45 degC: check `byte_order`".
    /// Never for a NaN or infinity in the configured order: that is the fault value of
    /// float transmitters, and the NaN's bytes reordered read as a plausible -3.98.
    /// The registers are rebuilt from the finite raw value, which is exact.
    pub fn byte_order_hint(&self, ch: usize, reading: &Reading) -> Option<String> {
        let Quality::Bad(
            Reason::Implausible | Reason::OutOfRange | Reason::Ne43Low | Reason::Ne43High,
        ) = reading.quality
        else {
            return None;
        };
        let (ty, configured) = (*self.encodings.get(ch)?)?;
        let raw = reading.raw.filter(|r| r.is_finite())?;
        let p = self.processors.get(ch)?;
        let regs = plan::encode(raw, ty, configured)?;
        let f = p.filter_params();
        let middle_degc = (f.valid_min_degc + f.valid_max_degc) / 2.0;
        let (order, degc) =
            plan::likely_order(&regs, ty, configured, |r| p.plausible_degc(r), middle_degc)?;
        if order == configured {
            return None;
        }
        let now = match reading.unfiltered_degc {
            Some(d) => format!("{d:.2} degC"),
            None => format!("raw {raw:.4e}"),
        };
        Some(format!(
            "reads {now} as {}; as {} it would read {degc:.2} degC: check `byte_order`",
            configured.name(),
            order.name()
        ))
    }

    /// The latest reading of channel `ch` (config order); `None` past the last channel.
    pub fn reading(&self, ch: usize) -> Option<Reading> {
        self.processors.get(ch).map(|p| p.last().clone())
    }

    /// Every channel's name and reading, in config order.
    pub fn channel_statuses(&self) -> Vec<ChannelStatus> {
        self.channel_names
            .iter()
            .zip(&self.processors)
            .map(|(name, p)| ChannelStatus {
                name: name.as_str().into(),
                reading: p.last().clone(),
            })
            .collect()
    }

    /// Copies every channel's latest reading into `statuses` (config order).
    pub(super) fn copy_readings_into(&self, statuses: &mut [ChannelStatus]) {
        for (s, p) in statuses.iter_mut().zip(&self.processors) {
            s.reading.clone_from(p.last());
        }
    }

    /// The channel processors, taken out (the pipeline is left without channels):
    /// what a reload carries over.
    pub(super) fn take_processors(&mut self) -> Vec<ChannelProcessor> {
        std::mem::take(&mut self.processors)
    }

    /// Feeds one device sample through its channels' processors; `readings` gets
    /// their new readings (cleared first, so one buffer serves every sample).
    pub fn ingest(&mut self, sample: &DeviceSample, readings: &mut Vec<ChannelReading>) {
        readings.clear();
        let t_s = self.now_s(sample.started);
        // The sample's channels were read at one instant: one exponential serves them.
        let mut gain = LowPassGain::default();
        for (ch, value) in &sample.values {
            let Some(p) = self.processors.get_mut(*ch) else {
                continue;
            };
            let reading = match value {
                Ok(raw) => p.on_sample_with(t_s, *raw, &mut gain),
                Err(fault) => p.on_missing(t_s, fault.reason, fault.degraded),
            };
            readings.push(ChannelReading {
                channel: *ch,
                reading: reading.clone(),
            });
        }
    }

    /// The quality of channel `ch`'s latest reading; `None` past the last channel.
    pub fn quality(&self, ch: usize) -> Option<Quality> {
        Some(self.processors.get(ch)?.last().quality)
    }

    /// The value of channel `ch` if its quality allows using it.
    pub fn usable_degc(&self, ch: usize) -> Option<f64> {
        self.processors.get(ch)?.last().usable_degc()
    }

    /// Why axis `axis`'s model extrapolates now: each usable input reading more than
    /// [`FIT_MARGIN_K`] outside the range it was fitted over, farthest first, in words.
    /// Once flagged (`previous`), a reading must come [`FIT_HYSTERESIS_K`] closer to
    /// clear it, so that one at the margin does not flag and clear with its noise; and
    /// an input without a usable reading (bad) does not clear it: nothing says it is
    /// back within.
    pub fn outside_fit(&self, axis: usize, previous: Option<&str>) -> Option<String> {
        let flagged = previous.is_some();
        let margin_k = if flagged {
            FIT_MARGIN_K - FIT_HYSTERESIS_K
        } else {
            FIT_MARGIN_K
        };
        let mut outside: Vec<(f64, String)> = self.axes[axis]
            .fitted
            .iter()
            .filter_map(|r| {
                let v = self.usable_degc(r.channel)?;
                let (beyond_k, side) = if v < r.min_degc {
                    (r.min_degc - v, "below")
                } else {
                    (v - r.max_degc, "above")
                };
                (beyond_k > margin_k).then(|| {
                    let text = format!(
                        "{} reads {v:.1} degC, {beyond_k:.1} K {side} the {:.1}..{:.1} degC",
                        self.channel_names[r.channel], r.min_degc, r.max_degc
                    );
                    (beyond_k, text)
                })
            })
            .collect();
        if outside.is_empty() {
            let unknown = self.axes[axis]
                .fitted
                .iter()
                .any(|r| self.usable_degc(r.channel).is_none());
            return previous.filter(|_| unknown).map(str::to_string);
        }
        outside.sort_by(|a, b| b.0.total_cmp(&a.0));
        let each: Vec<String> = outside.into_iter().map(|(_, t)| t).collect();
        Some(format!(
            "{} the model was fitted over: it extrapolates; a sensor replaced or moved reads \
             off (check it), else measure and calibrate over the temperatures the machine now \
             reaches",
            each.join("; ")
        ))
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::{DeviceSample, Fault};

    /// A pipeline of one `f32` channel (holding registers, ABCD, read as degC).
    fn float_channel() -> Pipeline {
        let text = "[devices.d]\ntransport = \"tcp\"\naddress = \"127.0.0.1:502\"\nunit_id = 1\n\n\
                    [channels.t]\ndevice = \"d\"\nregister = \"holding\"\naddress = 0\n\
                    data_type = \"f32\"\nscaling = { kind = \"direct\", gain = 1.0, offset_degc = 0.0 }\n";
        let cfg = crate::config::load_str(text, "f.toml").expect("config");
        super::super::build(&cfg).expect("build").pipeline
    }

    fn hint_for(raw_bits: u32) -> Option<String> {
        let mut p = float_channel();
        let sample = DeviceSample {
            device: 0,
            started: p.epoch,
            elapsed: Duration::ZERO,
            values: vec![(0, Ok::<f64, Fault>(f64::from(f32::from_bits(raw_bits))))],
            error: None,
            faults: Vec::new(),
            connects: 1,
        };
        let mut out = Vec::new();
        p.ingest(&sample, &mut out);
        p.byte_order_hint(0, &out[0].reading)
    }

    // A float transmitter's NaN (0x7FC00000) read BADC is -3.98: it was hinted as a
    // wrong byte order. 23.45 stored CDAB still gets its hint.
    #[test]
    fn nan_and_infinity_get_no_byte_order_hint() {
        for bits in [
            0x7FC0_0000,
            0xFFC0_0000,
            0x7F80_0000,
            0xFF80_0000,
            0xFFFF_FFFF,
        ] {
            assert_eq!(hint_for(bits), None, "{bits:#010X}");
        }
        let cdab = 23.45f32.to_bits().rotate_left(16);
        let hint = hint_for(cdab).expect("a hint");
        assert!(hint.contains("as CDAB it would read 23.45 degC"), "{hint}");
    }
}
