//! Channel processing: pure and synchronous.
//!
//! One [`ChannelProcessor`] per channel turns raw register values into filtered
//! temperatures with a [`Quality`]. Per sample, in this order:
//!
//! 1. scaling (counts -> mA -> degC, or a direct gain/offset), see [`Scaling`];
//! 2. NAMUR NE43 on 4-20 mA loops (< 3.6 mA, > 21 mA: sensor fault);
//! 3. finiteness of raw and result;
//! 4. plausible range (`valid_min_degc..=valid_max_degc`);
//! 5. stale detection on the raw value (bit-identical for `stale_after_s`);
//! 6. rate plausibility against the last accepted value (spike/jump rejection);
//! 7. median window (spike rejection);
//! 8. first-order low pass (exact discretisation for irregular sampling).
//!
//! A sample that fails a check never reaches the filters: the reading keeps the
//! previous filtered value with a `Bad` (or, for a single rate rejection,
//! `Uncertain`) quality. The compensation only uses usable readings.

mod filter;
mod processor;
mod quality;
mod scaling;

pub use filter::{LowPass, LowPassGain, MedianWindow};
pub use processor::ChannelProcessor;
pub use quality::{Quality, Reason};
pub use scaling::{CurrentRange, Scaled, Scaling, MIN_RAW_MAGNITUDE, NE43_HIGH_MA, NE43_LOW_MA};

/// Filter and plausibility settings of one channel. A value of 0 switches a
/// stage off where noted.
#[derive(Debug, Clone, PartialEq)]
pub struct FilterParams {
    /// Spike rejection: median of this many accepted samples (0 or 1 = off).
    pub median_samples: usize,
    /// First-order low-pass time constant, s (0 = off).
    pub lowpass_tau_s: f64,
    /// Fastest plausible change, degC/s (0 = off): a sample with
    /// `|value - last accepted| > rate * dt` is rejected.
    pub max_rate_degc_per_s: f64,
    /// Change always accepted by the rate check on top of `max_rate_degc_per_s * dt`,
    /// degC: the converter's own noise (0 = none).
    pub rate_tolerance_degc: f64,
    /// Consecutive rate rejections after which the channel turns
    /// `Bad(RateRejected)` and the filters re-seed on the new level (0 acts as 1).
    pub max_rejected_samples: u32,
    /// The raw value bit-identical for this long means a frozen transmitter:
    /// `Bad(Stale)`, s (0 = off).
    pub stale_after_s: f64,
    /// Lowest plausible temperature, degC; below it the sample is `Bad(OutOfRange)`.
    pub valid_min_degc: f64,
    /// Highest plausible temperature, degC; above it the sample is `Bad(OutOfRange)`.
    pub valid_max_degc: f64,
}

impl Default for FilterParams {
    /// Every stage off and every finite value plausible.
    fn default() -> Self {
        Self {
            median_samples: 1,
            lowpass_tau_s: 0.0,
            max_rate_degc_per_s: 0.0,
            rate_tolerance_degc: 0.0,
            max_rejected_samples: 1,
            stale_after_s: 0.0,
            valid_min_degc: f64::NEG_INFINITY,
            valid_max_degc: f64::INFINITY,
        }
    }
}

/// What a channel shows after one input (a sample or a missing sample).
#[derive(Debug, Clone, PartialEq)]
pub struct Reading {
    /// Time of the input, s (the processor's time base; 0 before any input).
    pub t_s: f64,
    /// The raw register value of this sample (`None` when the sample was missing).
    pub raw: Option<f64>,
    /// Loop current of this sample, mA (transmitter scaling only).
    pub current_ma: Option<f64>,
    /// This sample's temperature before filtering, degC (`None` when it has none:
    /// missing, NE43 fault, not finite).
    pub unfiltered_degc: Option<f64>,
    /// The filtered temperature, degC: what the compensation uses. Held from the
    /// last accepted sample when this one was not accepted.
    pub value_degc: Option<f64>,
    /// Quality of `value_degc`.
    pub quality: Quality,
}

impl Reading {
    /// The reading before any input: no values, `Bad(NoData)`.
    pub fn no_data() -> Self {
        Self {
            t_s: 0.0,
            raw: None,
            current_ma: None,
            unfiltered_degc: None,
            value_degc: None,
            quality: Quality::Bad(Reason::NoData),
        }
    }

    /// The value if the quality allows using it.
    pub fn usable_degc(&self) -> Option<f64> {
        self.value_degc.filter(|_| self.quality.is_usable())
    }
}
