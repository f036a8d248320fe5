//! One channel's state: checks, filters and quality, sample by sample.

use super::{FilterParams, LowPass, LowPassGain, MedianWindow, Quality, Reading, Reason, Scaling};

/// Without an accepted sample for this many low-pass time constants the filters
/// re-seed: the old state would weigh less than exp(-5) = 0.7 % anyway.
const GAP_TAUS: f64 = 5.0;

/// Turns one channel's raw values into filtered temperatures with a quality.
///
/// Re-seeding (median window emptied, low pass set to the new sample) happens:
/// - after [`FilterParams::max_rejected_samples`] consecutive rate rejections: the new
///   level is real, the filter follows it instead of staying stuck;
/// - on the first accepted sample after a missing sample ([`Self::on_missing`]:
///   comm outage, device fault): pre-outage samples must not vote in the median or
///   drag the low pass;
/// - when more than 5 low-pass time constants passed since the last accepted sample.
///
/// Short `Bad` stretches (NE43, range, stale) do not re-seed: the filter resumes on
/// its state. The rate check never re-seeds on a gap: its allowance grows with `dt`,
/// so it stays valid across any gap and still catches a spike right after one.
///
/// Holding never upgrades a `Bad` channel: a rejected or missing sample is
/// `Uncertain` only if the reading before it was usable.
#[derive(Debug, Clone)]
pub struct ChannelProcessor {
    scaling: Scaling,
    params: FilterParams,
    median: MedianWindow,
    lowpass: LowPass,
    /// Last sample accepted by the rate check: (t_s, unfiltered degC).
    accepted: Option<(f64, f64)>,
    rejected_in_row: u32,
    /// Bits of the last raw value and the time they were first seen, s.
    raw_since: Option<(u64, f64)>,
    /// A sample went missing since the last accepted one.
    outage: bool,
    last: Reading,
}

impl ChannelProcessor {
    /// A processor with no data yet: [`Self::last`] is `Bad(NoData)`.
    pub fn new(scaling: Scaling, filter: FilterParams) -> Self {
        Self {
            median: MedianWindow::new(filter.median_samples),
            lowpass: LowPass::new(filter.lowpass_tau_s),
            scaling,
            params: filter,
            accepted: None,
            rejected_in_row: 0,
            raw_since: None,
            outage: false,
            last: Reading::no_data(),
        }
    }

    /// Processes a fresh raw register value (ADC counts or an engineering value)
    /// taken at `t_s` and returns the new reading (borrowed: the gateway calls this
    /// for every channel on every poll and mostly does not need a copy).
    pub fn on_sample(&mut self, t_s: f64, raw: f64) -> &Reading {
        self.on_sample_with(t_s, raw, &mut LowPassGain::default())
    }

    /// [`Self::on_sample`] for one of several channels sampled at `t_s`: they share
    /// `gain`, so the low pass's exponential is computed once for all of them.
    pub fn on_sample_with(&mut self, t_s: f64, raw: f64, gain: &mut LowPassGain) -> &Reading {
        // Tracked on every sample, so any change of the raw value restarts the
        // clock even if that sample fails a check.
        let stale = self.track_raw(t_s, raw);
        let scaled = self.scaling.scale(raw);
        let mut value_degc = self.last.value_degc;
        let quality = match scaled.degc {
            Err(reason) => Quality::Bad(reason),
            Ok(degc) => match self.accept(t_s, degc, stale, gain) {
                Ok(filtered_degc) => {
                    value_degc = Some(filtered_degc);
                    Quality::Good
                }
                Err(q) => q,
            },
        };
        self.last = Reading {
            t_s,
            raw: Some(raw),
            current_ma: scaled.current_ma,
            unfiltered_degc: scaled.degc.ok(),
            value_degc,
            quality,
        };
        &self.last
    }

    /// Records that no sample arrived at `t_s` (for `reason`). The last filtered
    /// value is held as `Uncertain(reason)`; it is `Bad(DeviceDegraded)` if the
    /// device is `degraded`, `Bad(NoData)` if there never was a value, and
    /// `Bad(reason)` if the reading before was already bad. The next accepted sample
    /// re-seeds the filters. The stale clock keeps running: a raw value identical
    /// before and after an outage counts from when it was first seen.
    pub fn on_missing(&mut self, t_s: f64, reason: Reason, degraded: bool) -> &Reading {
        self.outage = true;
        let value_degc = self.last.value_degc;
        let quality = if degraded {
            Quality::Bad(Reason::DeviceDegraded)
        } else if value_degc.is_none() {
            Quality::Bad(Reason::NoData)
        } else {
            self.hold(reason)
        };
        self.last = Reading {
            t_s,
            raw: None,
            current_ma: None,
            unfiltered_degc: None,
            value_degc,
            quality,
        };
        &self.last
    }

    /// The latest reading (before any input: `Bad(NoData)`, no values).
    pub fn last(&self) -> &Reading {
        &self.last
    }

    /// The scaling this processor applies.
    pub fn scaling(&self) -> &Scaling {
        &self.scaling
    }

    /// The temperature `raw` scales to if it passes the checks that need no history
    /// (NE43, finiteness, a raw value a sensor produces, the plausible range): how a
    /// probe or a word-order hint judges a value without feeding it.
    pub fn plausible_degc(&self, raw: f64) -> Option<f64> {
        let degc = self.scaling.scale(raw).degc.ok()?;
        (self.params.valid_min_degc..=self.params.valid_max_degc)
            .contains(&degc)
            .then_some(degc)
    }

    /// The filter settings this processor applies.
    pub fn filter_params(&self) -> &FilterParams {
        &self.params
    }

    /// Steps 4-8 for a finite scaled value: the filtered value, or the quality of
    /// a sample that did not get through.
    fn accept(
        &mut self,
        t_s: f64,
        degc: f64,
        stale: bool,
        gain: &mut LowPassGain,
    ) -> Result<f64, Quality> {
        // RangeInclusive::contains is false for NaN bounds: a broken range fails safe.
        if !(self.params.valid_min_degc..=self.params.valid_max_degc).contains(&degc) {
            return Err(Quality::Bad(Reason::OutOfRange));
        }
        if stale {
            return Err(Quality::Bad(Reason::Stale));
        }
        if self.rate_rejects(t_s, degc) {
            self.rejected_in_row = self.rejected_in_row.saturating_add(1);
            if self.rejected_in_row >= self.params.max_rejected_samples.max(1) {
                self.reseed(t_s, degc);
                return Err(Quality::Bad(Reason::RateRejected));
            }
            return Err(self.hold(Reason::RateRejected));
        }
        if self.long_gap(t_s) {
            self.median.clear();
            self.lowpass.clear();
        }
        self.outage = false;
        self.rejected_in_row = 0;
        self.accepted = Some((t_s, degc));
        let median_degc = self.median.push(degc);
        Ok(self.lowpass.update_with(t_s, median_degc, gain))
    }

    /// Quality of a held value: uncertain only if the channel was usable.
    fn hold(&self, reason: Reason) -> Quality {
        if self.last.quality.is_usable() {
            Quality::Uncertain(reason)
        } else {
            Quality::Bad(reason)
        }
    }

    /// Updates stale tracking with this raw value; true if it is stale now.
    fn track_raw(&mut self, t_s: f64, raw: f64) -> bool {
        let bits = raw.to_bits();
        let since_s = match self.raw_since {
            Some((b, since_s)) if b == bits => since_s,
            _ => {
                self.raw_since = Some((bits, t_s));
                t_s
            }
        };
        self.params.stale_after_s > 0.0 && t_s - since_s >= self.params.stale_after_s
    }

    fn rate_rejects(&self, t_s: f64, degc: f64) -> bool {
        let rate = self.params.max_rate_degc_per_s;
        match self.accepted {
            Some((t0_s, v0_degc)) if rate > 0.0 => {
                // dt < 0 (time going backwards) allows no change but the noise.
                let allowed = rate * (t_s - t0_s).max(0.0) + self.params.rate_tolerance_degc;
                (degc - v0_degc).abs() > allowed
            }
            _ => false,
        }
    }

    fn long_gap(&self, t_s: f64) -> bool {
        let tau_s = self.params.lowpass_tau_s;
        self.outage
            || (tau_s > 0.0
                && self
                    .accepted
                    .is_some_and(|(t0_s, _)| t_s - t0_s > GAP_TAUS * tau_s))
    }

    /// Restarts the filters on `degc`: the new level is taken as accepted.
    fn reseed(&mut self, t_s: f64, degc: f64) {
        self.median.clear();
        self.median.push(degc);
        self.lowpass.reseed(t_s, degc);
        self.accepted = Some((t_s, degc));
        self.rejected_in_row = 0;
        self.outage = false;
    }
}

#[cfg(test)]
mod tests {
    use super::super::CurrentRange;
    use super::*;

    fn direct() -> Scaling {
        Scaling::Direct {
            gain: 1.0,
            offset_degc: 0.0,
        }
    }

    fn proc_with(f: FilterParams) -> ChannelProcessor {
        ChannelProcessor::new(direct(), f)
    }

    fn close(a: Option<f64>, b: f64) -> bool {
        a.is_some_and(|a| (a - b).abs() < 1e-9)
    }

    #[test]
    fn no_data_before_any_input() {
        let p = proc_with(FilterParams::default());
        let r = p.last();
        assert_eq!(r.quality, Quality::Bad(Reason::NoData));
        assert_eq!(r.value_degc, None);
        assert_eq!(r.raw, None);
        assert_eq!(r.unfiltered_degc, None);
    }

    #[test]
    fn transmitter_sample_is_scaled_and_good() {
        let mut p = ChannelProcessor::new(
            Scaling::Transmitter {
                adc_full_scale_counts: 24000.0,
                adc_full_scale_ma: 24.0,
                current_range: CurrentRange::FourTo20,
                range_min_degc: -50.0,
                range_max_degc: 150.0,
            },
            FilterParams::default(),
        );
        // 8.8 mA -> 10 degC
        let r = p.on_sample(1.0, 8800.0).clone();
        assert_eq!(r.quality, Quality::Good);
        assert!(close(r.current_ma, 8.8));
        assert!(close(r.unfiltered_degc, 10.0));
        assert!(close(r.value_degc, 10.0));
        assert_eq!(r.raw, Some(8800.0));
        assert_eq!(p.last(), &r);
        // 2 mA is an NE43 fault, not an out-of-range temperature; value held.
        let r = p.on_sample(2.0, 2000.0);
        assert_eq!(r.quality, Quality::Bad(Reason::Ne43Low));
        assert_eq!(r.unfiltered_degc, None);
        assert!(close(r.current_ma, 2.0));
        assert!(close(r.value_degc, 10.0));
        let r = p.on_sample(3.0, 22000.0);
        assert_eq!(r.quality, Quality::Bad(Reason::Ne43High));
        // Back to normal: 12 mA -> 50 degC.
        let r = p.on_sample(4.0, 12000.0);
        assert_eq!(r.quality, Quality::Good);
        assert!(close(r.value_degc, 50.0));
    }

    #[test]
    fn bad_samples_do_not_feed_the_median() {
        let mut p = proc_with(FilterParams {
            median_samples: 3,
            valid_min_degc: -20.0,
            valid_max_degc: 80.0,
            ..FilterParams::default()
        });
        assert!(close(p.on_sample(0.0, 20.0).value_degc, 20.0));
        let r = p.on_sample(1.0, 100.0);
        assert_eq!(r.quality, Quality::Bad(Reason::OutOfRange));
        assert!(close(r.unfiltered_degc, 100.0));
        assert!(close(r.value_degc, 20.0));
        let r = p.on_sample(2.0, f64::NAN);
        assert_eq!(r.quality, Quality::Bad(Reason::NotFinite));
        assert!(close(r.value_degc, 20.0));
        // Window holds 20, 21 only: median 20.5 (with 100 it would be 21).
        let r = p.on_sample(3.0, 21.0);
        assert_eq!(r.quality, Quality::Good);
        assert!(close(r.value_degc, 20.5));
    }

    #[test]
    fn median_rejects_a_single_spike() {
        let mut p = proc_with(FilterParams {
            median_samples: 3,
            ..FilterParams::default()
        });
        let out: Vec<Option<f64>> = [20.0, 20.0, 80.0, 20.0]
            .iter()
            .enumerate()
            .map(|(i, &v)| p.on_sample(i as f64, v).value_degc)
            .collect();
        assert_eq!(out, vec![Some(20.0), Some(20.0), Some(20.0), Some(20.0)]);
        assert_eq!(p.last().quality, Quality::Good);
    }

    #[test]
    fn stale_after_bit_identical_raw() {
        let mut p = proc_with(FilterParams {
            stale_after_s: 10.0,
            ..FilterParams::default()
        });
        assert_eq!(p.on_sample(0.0, 25.0).quality, Quality::Good);
        assert_eq!(p.on_sample(5.0, 25.0).quality, Quality::Good);
        assert_eq!(p.on_sample(9.9, 25.0).quality, Quality::Good);
        let r = p.on_sample(10.0, 25.0);
        assert_eq!(r.quality, Quality::Bad(Reason::Stale));
        assert!(close(r.value_degc, 25.0));
        assert_eq!(p.on_sample(15.0, 25.0).quality, Quality::Bad(Reason::Stale));
        // A change clears it and restarts the clock.
        assert_eq!(p.on_sample(16.0, 25.5).quality, Quality::Good);
        assert!(close(p.last().value_degc, 25.5));
        assert_eq!(p.on_sample(25.9, 25.5).quality, Quality::Good);
        assert_eq!(p.on_sample(26.0, 25.5).quality, Quality::Bad(Reason::Stale));
    }

    #[test]
    fn any_raw_change_restarts_the_stale_clock() {
        let mut p = proc_with(FilterParams {
            stale_after_s: 10.0,
            valid_max_degc: 50.0,
            ..FilterParams::default()
        });
        p.on_sample(0.0, 25.0);
        // An out-of-range raw value is still a change of the raw value.
        assert_eq!(
            p.on_sample(5.0, 99.0).quality,
            Quality::Bad(Reason::OutOfRange)
        );
        assert_eq!(p.on_sample(10.0, 25.0).quality, Quality::Good);
        assert_eq!(p.on_sample(19.0, 25.0).quality, Quality::Good);
        assert_eq!(p.on_sample(20.0, 25.0).quality, Quality::Bad(Reason::Stale));
    }

    #[test]
    fn stale_off_when_zero() {
        let mut p = proc_with(FilterParams::default());
        for i in 0..100 {
            assert_eq!(
                p.on_sample(f64::from(i) * 100.0, 25.0).quality,
                Quality::Good
            );
        }
    }

    #[test]
    fn out_of_range_wins_over_stale() {
        let mut p = proc_with(FilterParams {
            stale_after_s: 1.0,
            valid_max_degc: 50.0,
            ..FilterParams::default()
        });
        p.on_sample(0.0, 60.0);
        assert_eq!(
            p.on_sample(5.0, 60.0).quality,
            Quality::Bad(Reason::OutOfRange)
        );
    }

    fn rate_params() -> FilterParams {
        FilterParams {
            max_rate_degc_per_s: 1.0,
            max_rejected_samples: 3,
            ..FilterParams::default()
        }
    }

    #[test]
    fn rate_rejects_spike_then_recovers() {
        let mut p = proc_with(rate_params());
        assert_eq!(p.on_sample(0.0, 20.0).quality, Quality::Good);
        // 0.5 in 1 s <= 1 degC/s.
        assert_eq!(p.on_sample(1.0, 20.5).quality, Quality::Good);
        // 9.5 in 1 s: a spike.
        let r = p.on_sample(2.0, 30.0);
        assert_eq!(r.quality, Quality::Uncertain(Reason::RateRejected));
        assert!(close(r.value_degc, 20.5));
        assert!(close(r.unfiltered_degc, 30.0));
        // Compared with the last accepted (20.5 at t=1): 0.4 in 2 s is fine.
        let r = p.on_sample(3.0, 20.9);
        assert_eq!(r.quality, Quality::Good);
        assert!(close(r.value_degc, 20.9));
    }

    #[test]
    fn rate_tolerance_accepts_noise_but_not_a_spike() {
        let mut p = proc_with(FilterParams {
            rate_tolerance_degc: 0.15,
            ..rate_params()
        });
        p.on_sample(0.0, 20.0);
        // 0.24 in 0.1 s: 0.1 of change plus 0.14 of noise.
        assert_eq!(p.on_sample(0.1, 20.24).quality, Quality::Good);
        // Backwards in time only the noise is allowed.
        assert_eq!(p.on_sample(0.05, 20.1).quality, Quality::Good);
        assert_eq!(
            p.on_sample(0.2, 20.6).quality,
            Quality::Uncertain(Reason::RateRejected)
        );
    }

    #[test]
    fn rate_limit_scales_with_real_dt() {
        let mut p = proc_with(rate_params());
        p.on_sample(0.0, 20.0);
        // 5 degC after 10 s of silence is plausible at 1 degC/s...
        assert_eq!(p.on_sample(10.0, 25.0).quality, Quality::Good);
        // ...but 5 degC within 0.5 s is not.
        assert_eq!(
            p.on_sample(10.5, 30.0).quality,
            Quality::Uncertain(Reason::RateRejected)
        );
    }

    #[test]
    fn consecutive_rejections_turn_bad_and_reseed() {
        let mut p = proc_with(FilterParams {
            median_samples: 3,
            lowpass_tau_s: 100.0,
            ..rate_params()
        });
        for i in 0..3 {
            assert_eq!(p.on_sample(f64::from(i), 20.0).quality, Quality::Good);
        }
        // A real step to 50: rejected twice (uncertain), the third time bad.
        for t in [3.0, 4.0] {
            let r = p.on_sample(t, 50.0);
            assert_eq!(r.quality, Quality::Uncertain(Reason::RateRejected));
            assert!(close(r.value_degc, 20.0));
        }
        let r = p.on_sample(5.0, 50.0);
        assert_eq!(r.quality, Quality::Bad(Reason::RateRejected));
        assert!(close(r.value_degc, 20.0));
        // Re-seeded on 50 at t=5: 50.2 one second later is consistent. Median of
        // [50, 50.2] = 50.1; low pass from 50: 50 + (1 - e^-0.01) * 0.1
        // = 50.000995016625083.
        let r = p.on_sample(6.0, 50.2);
        assert_eq!(r.quality, Quality::Good);
        assert!(
            close(r.value_degc, 50.000_995_016_625_08),
            "{:?}",
            r.value_degc
        );
    }

    #[test]
    fn rejection_count_resets_on_an_accepted_sample() {
        let mut p = proc_with(rate_params());
        p.on_sample(0.0, 20.0);
        p.on_sample(1.0, 40.0);
        p.on_sample(2.0, 40.0);
        // Accepted: 20.5 vs 20 at t=0.
        assert_eq!(p.on_sample(3.0, 20.5).quality, Quality::Good);
        // Two more rejections are not three in a row.
        p.on_sample(4.0, 40.0);
        assert_eq!(
            p.on_sample(5.0, 40.0).quality,
            Quality::Uncertain(Reason::RateRejected)
        );
    }

    #[test]
    fn max_rejected_zero_acts_as_one() {
        let mut p = proc_with(FilterParams {
            max_rejected_samples: 0,
            ..rate_params()
        });
        p.on_sample(0.0, 20.0);
        assert_eq!(
            p.on_sample(1.0, 50.0).quality,
            Quality::Bad(Reason::RateRejected)
        );
        assert_eq!(p.on_sample(2.0, 50.5).quality, Quality::Good);
        assert!(close(p.last().value_degc, 50.5));
    }

    #[test]
    fn rejection_after_bad_stays_bad() {
        let mut p = proc_with(FilterParams {
            valid_max_degc: 80.0,
            ..rate_params()
        });
        p.on_sample(0.0, 20.0);
        p.on_sample(1.0, 99.0);
        // The channel was bad: a rejected sample cannot make the held value usable.
        assert_eq!(
            p.on_sample(2.0, 60.0).quality,
            Quality::Bad(Reason::RateRejected)
        );
    }

    #[test]
    fn lowpass_irregular_dt_and_gap_reseed() {
        let mut p = proc_with(FilterParams {
            lowpass_tau_s: 10.0,
            ..FilterParams::default()
        });
        assert!(close(p.on_sample(0.0, 20.0).value_degc, 20.0));
        // dt = tau: 20 + (1 - e^-1) * 10
        assert!(close(
            p.on_sample(10.0, 30.0).value_degc,
            26.321_205_588_285_58
        ));
        // dt = 2 s: 26.3212 + (1 - e^-0.2) * (30 - 26.3212) = 26.988057880877978
        assert!(close(
            p.on_sample(12.0, 30.0).value_degc,
            26.988_057_880_877_98
        ));
        // dt = 60 s > 5 tau: re-seed on 40 exactly (averaging would give
        // 40 - 13.01 * e^-6 = 39.9678).
        let r = p.on_sample(72.0, 40.0);
        assert_eq!(r.value_degc, Some(40.0));
    }

    #[test]
    fn missing_sample_holds_value_as_uncertain() {
        let mut p = proc_with(FilterParams::default());
        let r = p.on_missing(0.0, Reason::Comm, false);
        assert_eq!(r.quality, Quality::Bad(Reason::NoData));
        assert_eq!(r.value_degc, None);
        p.on_sample(1.0, 21.0);
        let r = p.on_missing(2.0, Reason::Comm, false);
        assert_eq!(r.quality, Quality::Uncertain(Reason::Comm));
        assert!(close(r.value_degc, 21.0));
        assert_eq!(r.raw, None);
        assert_eq!(r.unfiltered_degc, None);
        assert_eq!(r.t_s, 2.0);
        let r = p.on_missing(3.0, Reason::DeviceException, false);
        assert_eq!(r.quality, Quality::Uncertain(Reason::DeviceException));
        let r = p.on_missing(4.0, Reason::Comm, true);
        assert_eq!(r.quality, Quality::Bad(Reason::DeviceDegraded));
        assert!(close(r.value_degc, 21.0));
        // Once bad, a missing sample does not make it usable again.
        let r = p.on_missing(5.0, Reason::Comm, false);
        assert_eq!(r.quality, Quality::Bad(Reason::Comm));
        assert_eq!(p.on_sample(6.0, 22.0).quality, Quality::Good);
    }

    #[test]
    fn degraded_without_data() {
        let mut p = proc_with(FilterParams::default());
        let r = p.on_missing(0.0, Reason::Comm, true);
        assert_eq!(r.quality, Quality::Bad(Reason::DeviceDegraded));
    }

    #[test]
    fn outage_reseeds_the_filters() {
        let mut p = proc_with(FilterParams {
            median_samples: 3,
            lowpass_tau_s: 100.0,
            ..FilterParams::default()
        });
        for i in 0..3 {
            p.on_sample(f64::from(i), 20.0);
        }
        p.on_missing(3.0, Reason::Comm, false);
        // Without re-seeding: median(20, 20, 30) = 20 and the low pass near 20.
        let r = p.on_sample(4.0, 30.0);
        assert_eq!(r.quality, Quality::Good);
        assert_eq!(r.value_degc, Some(30.0));
    }

    #[test]
    fn short_bad_stretch_resumes_without_reseed() {
        let mut p = proc_with(FilterParams {
            lowpass_tau_s: 10.0,
            valid_max_degc: 80.0,
            ..FilterParams::default()
        });
        p.on_sample(0.0, 20.0);
        p.on_sample(5.0, 99.0);
        // Resumes from 20 at t=0: 20 + (1 - e^-1) * 10.
        assert!(close(
            p.on_sample(10.0, 30.0).value_degc,
            26.321_205_588_285_58
        ));
    }
}
