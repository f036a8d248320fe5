//! The steady path of many channels at once, four lanes per SIMD instruction.
//!
//! Most samples of a healthy transmitter take one path through a [`ChannelProcessor`]:
//! scaled, no NE43 fault, finite, in range, not stale, within the rate limit, no long
//! gap, into a full median window and the low pass, `Good`. A [`Bank`] holds the
//! steady channels of one device and runs that path for four channels at a time with
//! SIMD operations and no branch on the values. A sample that leaves the path (any
//! check failing, a long gap, a missing sample, a raw value of exactly zero, whose
//! sign the stale clock would have to tell apart) hands its channel back to its
//! processor, which handles that sample and the ones after it until the channel is
//! steady again; then the bank takes it back.
//!
//! The bank computes with the processor's formulas in the processor's order (lane-wise
//! IEEE operations give the scalar results), and its median is the processor's compare
//! network on the window in the same order (oldest first), so its results are the
//! processor's bit for bit (`tests` below compares the two on noisy and faulty sample
//! streams).

use wide::f64x4;

use super::filter::{median3, median5, Ordered};
use super::processor::{Steady, GAP_TAUS};
use super::{ChannelProcessor, LowPassGain, Reading, Reason};

/// Lanes per block.
const W: usize = 4;

/// Median windows the bank computes; channels with another length stay on their
/// processor.
const BANK_MEDIAN_LENS: [usize; 3] = [1, 3, 5];

/// A true lane of a mask: all bits set.
const TRUE: f64 = f64::from_bits(u64::MAX);

/// The settings of four lanes, as numbers (the scaling as `Scaling::linear` gives it).
#[derive(Debug, Clone, Copy, Default)]
struct Settings {
    mul: f64x4,
    div: f64x4,
    zero: f64x4,
    span_in: f64x4,
    span_out_degc: f64x4,
    base_degc: f64x4,
    /// NE43 limits, mA (infinite for a scaling without them).
    ne43_low_ma: f64x4,
    ne43_high_ma: f64x4,
    /// Mask: the reading has a loop current (transmitter scaling).
    has_current: f64x4,
    valid_min_degc: f64x4,
    valid_max_degc: f64x4,
    stale_after_s: f64x4,
    max_rate_degc_per_s: f64x4,
    tau_s: f64x4,
    /// Median window length; 0: the lane is never held (a length the bank lacks).
    median_len: f64x4,
    // Derived once: masks of the stages that are on, the gap limit.
    stale_on: f64x4,
    rate_on: f64x4,
    lowpass_on: f64x4,
    /// `GAP_TAUS * tau_s`, s.
    gap_s: f64x4,
    // The same for the whole block, so the steady path can skip selects.
    /// The median length of every lane, if they all have the same (else 0).
    same_len: u8,
    /// Every lane has the low pass on.
    lowpass_all: bool,
    /// Every lane's reading has a loop current.
    current_all: bool,
}

/// The state of four lanes (see [`Steady`]) and one sample's work.
#[derive(Debug, Clone, Copy, Default)]
struct State {
    raw: f64x4,
    raw_since_s: f64x4,
    t_s: f64x4,
    unfiltered_degc: f64x4,
    value_degc: f64x4,
    current_ma: f64x4,
    /// Median window, one vector per slot, oldest first: a shift register.
    ring_degc: [f64x4; 5],
    /// This sample's raw values ...
    input: f64x4,
    /// ... where this mask is set (by [`Bank::sample`]); after the steady path, set
    /// only where the sample left it.
    fresh: f64x4,
    /// The low-pass gain of each fresh lane.
    alpha: f64x4,
}

#[derive(Debug, Clone, Copy, Default)]
struct Block {
    set: Settings,
    st: State,
}

/// The steady channels of one device (one lane per channel of the device).
#[derive(Debug, Clone, Default)]
pub struct Bank {
    /// The channel (pipeline index) of each lane.
    channels: Vec<usize>,
    /// Whether the bank holds each lane (its processor's state is then out of date).
    held: Vec<bool>,
    blocks: Vec<Block>,
}

/// Lane `j` of `v`.
fn lane(v: &mut f64x4, j: usize) -> &mut f64 {
    &mut v.as_mut_array()[j]
}

impl Bank {
    /// A bank for `channels` (pipeline indices into `processors`), none held yet.
    pub fn new(channels: Vec<usize>, processors: &[ChannelProcessor]) -> Self {
        let mut blocks = vec![Block::default(); channels.len().div_ceil(W)];
        for (i, &ch) in channels.iter().enumerate() {
            let p = &processors[ch];
            let l = p.scaling().linear();
            let f = p.filter_params();
            let len = f.median_samples.max(1);
            let (b, j) = (i / W, i % W);
            let set = &mut blocks[b].set;
            for (v, x) in [
                (&mut set.mul, l.mul),
                (&mut set.div, l.div),
                (&mut set.zero, l.zero),
                (&mut set.span_in, l.span_in),
                (&mut set.span_out_degc, l.span_out_degc),
                (&mut set.base_degc, l.base_degc),
                (&mut set.ne43_low_ma, l.ne43_low_ma),
                (&mut set.ne43_high_ma, l.ne43_high_ma),
                (&mut set.has_current, if l.has_current { TRUE } else { 0.0 }),
                (&mut set.valid_min_degc, f.valid_min_degc),
                (&mut set.valid_max_degc, f.valid_max_degc),
                (&mut set.stale_after_s, f.stale_after_s),
                (&mut set.max_rate_degc_per_s, f.max_rate_degc_per_s),
                (&mut set.tau_s, f.lowpass_tau_s),
                (
                    &mut set.median_len,
                    if BANK_MEDIAN_LENS.contains(&len) {
                        len as f64
                    } else {
                        0.0
                    },
                ),
            ] {
                *lane(v, j) = x;
            }
        }
        for Block { set, .. } in &mut blocks {
            let lens = set.median_len.as_array();
            set.same_len = if lens.iter().all(|&l| l == lens[0]) {
                lens[0] as u8
            } else {
                0
            };
            let zero = f64x4::splat(0.0);
            set.stale_on = set.stale_after_s.simd_gt(zero);
            set.rate_on = set.max_rate_degc_per_s.simd_gt(zero);
            set.lowpass_on = set.tau_s.simd_gt(zero);
            set.gap_s = f64x4::splat(GAP_TAUS) * set.tau_s;
            set.lowpass_all = set.lowpass_on.all();
            set.current_all = set.has_current.all();
        }
        Self {
            held: vec![false; channels.len()],
            channels,
            blocks,
        }
    }

    /// Whether the bank holds `lane` (its processor's state is then out of date).
    pub fn holds(&self, lane: usize) -> bool {
        self.held.get(lane).copied().unwrap_or(false)
    }

    /// A fresh raw value of lane `i` (processor `p`) taken at `t_s`: queued for
    /// [`Self::step`] if the bank holds the lane, else processed by `p` at once.
    #[inline]
    pub fn sample(
        &mut self,
        i: usize,
        p: &mut ChannelProcessor,
        t_s: f64,
        raw: f64,
        gain: &mut LowPassGain,
    ) {
        if self.holds(i) {
            let st = &mut self.blocks[i / W].st;
            *lane(&mut st.input, i % W) = raw;
            *lane(&mut st.fresh, i % W) = TRUE;
        } else {
            p.on_sample_with(t_s, raw, gain);
            self.try_hold(i, p);
        }
    }

    /// No sample for lane `i` (processor `p`) at `t_s`: see
    /// [`ChannelProcessor::on_missing`].
    pub fn missing(
        &mut self,
        i: usize,
        p: &mut ChannelProcessor,
        t_s: f64,
        reason: Reason,
        degraded: bool,
    ) {
        self.release(i, p);
        p.on_missing(t_s, reason, degraded);
    }

    /// Takes lane `i` over from its processor `p` if its channel is steady.
    fn try_hold(&mut self, i: usize, p: &ChannelProcessor) {
        let Block { set, st } = &mut self.blocks[i / W];
        let j = i % W;
        if set.median_len.as_array()[j] == 0.0 {
            return;
        }
        let Some(s) = p.steady() else { return };
        *lane(&mut st.raw, j) = s.raw;
        *lane(&mut st.raw_since_s, j) = s.raw_since_s;
        *lane(&mut st.t_s, j) = s.t_s;
        *lane(&mut st.unfiltered_degc, j) = s.unfiltered_degc;
        *lane(&mut st.value_degc, j) = s.value_degc;
        *lane(&mut st.current_ma, j) = s.current_ma;
        for (slot, v) in st.ring_degc.iter_mut().zip(s.ring_degc) {
            *lane(slot, j) = v;
        }
        self.held[i] = true;
    }

    /// Hands lane `i` back to its processor `p`, if the bank holds it.
    fn release(&mut self, i: usize, p: &mut ChannelProcessor) {
        if self.holds(i) {
            p.resume(&self.steady(i));
            self.held[i] = false;
        }
    }

    /// Hands every held lane back to its processor in `processors`.
    pub fn release_all(&mut self, processors: &mut [ChannelProcessor]) {
        for i in 0..self.channels.len() {
            let ch = self.channels[i];
            self.release(i, &mut processors[ch]);
        }
    }

    /// The filtered value of held lane `i` (a held lane is `Good`).
    pub fn value_degc(&self, i: usize) -> f64 {
        self.blocks[i / W].st.value_degc.as_array()[i % W]
    }

    /// The reading of held lane `i`.
    pub fn reading(&self, i: usize) -> Reading {
        self.steady(i).reading()
    }

    fn steady(&self, i: usize) -> Steady {
        let st = &self.blocks[i / W].st;
        let j = i % W;
        Steady {
            raw: st.raw.as_array()[j],
            raw_since_s: st.raw_since_s.as_array()[j],
            t_s: st.t_s.as_array()[j],
            unfiltered_degc: st.unfiltered_degc.as_array()[j],
            value_degc: st.value_degc.as_array()[j],
            current_ma: st.current_ma.as_array()[j],
            ring_degc: std::array::from_fn(|k| st.ring_degc[k].as_array()[j]),
        }
    }

    /// Processes the values queued by [`Self::sample`], taken at `t_s`: the steady
    /// ones here, each other one by its processor in `processors` (which the bank may
    /// then take back). `gain` is the sample's shared low-pass gain.
    pub fn step(&mut self, t_s: f64, gain: &mut LowPassGain, processors: &mut [ChannelProcessor]) {
        for b in 0..self.blocks.len() {
            let Block { set, st } = &mut self.blocks[b];
            let fresh = st.fresh.to_bitmask();
            if fresh == 0 {
                continue;
            }
            st.alpha = gains(set, st, t_s, fresh, gain);
            steady_path(set, st, t_s);
            // `fresh` is left set where a value left the steady path.
            let left = st.fresh.to_bitmask();
            st.fresh = f64x4::splat(0.0);
            for j in 0..W {
                if left & (1 << j) == 0 {
                    continue;
                }
                let i = b * W + j;
                let raw = self.blocks[b].st.input.as_array()[j];
                let p = &mut processors[self.channels[i]];
                self.release(i, p);
                p.on_sample_with(t_s, raw, gain);
                self.try_hold(i, p);
            }
        }
    }
}

/// The low-pass gain of each fresh lane with the low pass on (lanes in `fresh`, a
/// bit mask), through the processors' cache `gain`: one exponential serves all lanes
/// updated together with the same time constant.
#[inline(always)]
fn gains(set: &Settings, st: &State, t_s: f64, fresh: u32, gain: &mut LowPassGain) -> f64x4 {
    let dt_s = (f64x4::splat(t_s) - st.t_s).hi(f64x4::splat(0.0));
    let (dts, taus) = (dt_s.as_array(), set.tau_s.as_array());
    // Usually every lane has the first fresh lane's time step and time constant.
    // Equal values here have equal bits (steps are never -0 or NaN), so the gain is
    // the one `get` would give each lane.
    let j0 = fresh.trailing_zeros() as usize;
    if taus[j0] > 0.0
        && dt_s.simd_eq(f64x4::splat(dts[j0])).all()
        && set.tau_s.simd_eq(f64x4::splat(taus[j0])).all()
    {
        return f64x4::splat(gain.get(dts[j0], taus[j0]));
    }
    let mut alpha = [0.0; W];
    for j in 0..W {
        if fresh & (1 << j) != 0 && taus[j] > 0.0 {
            alpha[j] = gain.get(dts[j], taus[j]);
        }
    }
    f64x4::from(alpha)
}

/// `ChannelProcessor::on_sample_with` for the fresh lanes of a block whose values
/// stay on the steady path; computed for all four lanes and kept by mask.
fn steady_path(set: &Settings, st: &mut State, t_s: f64) {
    let zero = f64x4::splat(0.0);
    let inf = f64x4::splat(f64::INFINITY);
    let t = f64x4::splat(t_s);
    let raw = st.input;
    // Stale clock (`track_raw`): the same bits are the same value, but for the sign
    // of zero; so a raw zero leaves the steady path (below), as a NaN does anyway.
    let since_s = raw.simd_eq(st.raw).select(st.raw_since_s, t);
    let stale = set.stale_on & (t - since_s).simd_ge(set.stale_after_s);
    // Scaling (`Scaling::scale`): NE43, finiteness (a raw value that is not finite
    // gives a temperature that is not finite).
    let ma = raw * set.mul / set.div;
    let degc = set.base_degc + (ma - set.zero) / set.span_in * set.span_out_degc;
    let mut fail = raw.simd_eq(zero)
        | ma.simd_lt(set.ne43_low_ma)
        | ma.simd_gt(set.ne43_high_ma)
        | !degc.abs().simd_lt(inf);
    // Range, stale, rate and gap (`accept`).
    fail = fail | !(set.valid_min_degc.simd_le(degc) & degc.simd_le(set.valid_max_degc)) | stale;
    let dt_s = t - st.t_s;
    let rate = set.max_rate_degc_per_s;
    fail = fail
        | (set.rate_on
            & (degc - st.unfiltered_degc)
                .abs()
                .simd_gt(rate * dt_s.hi(zero)))
        | (set.lowpass_on & dt_s.simd_gt(set.gap_s));
    let plain = st.fresh & !fail;
    // Usually every lane stays on the path and the block's lanes have the same
    // settings: then no selects (three instructions each on SSE2) are needed.
    let all_plain = plain.all();
    // Median (`MedianWindow::push` on a full window): shift in the new value.
    let r = st.ring_degc;
    let len = set.median_len;
    let (median_degc, ring) = match (set.same_len, all_plain) {
        (5, true) => (
            median5(r[1], r[2], r[3], r[4], degc),
            [r[1], r[2], r[3], r[4], degc],
        ),
        (3, true) => (median3(r[1], r[2], degc), [r[1], r[2], degc, r[3], r[4]]),
        (1, true) => (degc, [degc, r[1], r[2], r[3], r[4]]),
        _ => {
            let last = |slot: f64| plain & len.simd_eq(f64x4::splat(slot));
            let moves = |slot: f64| plain & len.simd_gt(f64x4::splat(slot));
            let s: [f64x4; 5] = std::array::from_fn(|j| {
                let shifted = if j < 4 { r[j + 1] } else { r[4] };
                last(j as f64 + 1.0).select(degc, moves(j as f64 + 1.0).select(shifted, r[j]))
            });
            let m = len.simd_eq(f64x4::splat(5.0)).select(
                median5(s[0], s[1], s[2], s[3], s[4]),
                len.simd_eq(f64x4::splat(3.0))
                    .select(median3(s[0], s[1], s[2]), s[0]),
            );
            (m, s)
        }
    };
    st.ring_degc = ring;
    // Low pass (`LowPass::update_with`).
    let y0 = st.value_degc;
    let smoothed = y0 + st.alpha * (median_degc - y0);
    let y = if set.lowpass_all {
        smoothed
    } else {
        set.lowpass_on.select(smoothed, median_degc)
    };
    let ma_shown = if set.current_all {
        ma
    } else {
        set.has_current.select(ma, f64x4::splat(f64::NAN))
    };
    if all_plain {
        st.raw = raw;
        st.raw_since_s = since_s;
        st.t_s = t;
        st.unfiltered_degc = degc;
        st.value_degc = y;
        st.current_ma = ma_shown;
        st.fresh = zero;
        return;
    }
    st.raw = plain.select(raw, st.raw);
    st.raw_since_s = plain.select(since_s, st.raw_since_s);
    st.t_s = plain.select(t, st.t_s);
    st.unfiltered_degc = plain.select(degc, st.unfiltered_degc);
    st.value_degc = plain.select(y, y0);
    st.current_ma = plain.select(ma_shown, st.current_ma);
    st.fresh &= fail;
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::super::{CurrentRange, FilterParams, Scaling};
    use super::*;

    /// A mix of the settings a device's channels have: every scaling, median lengths
    /// the bank computes and one it does not (7), the low pass on and off, rate and
    /// stale checks on and off.
    fn processors() -> Vec<ChannelProcessor> {
        let mut out = Vec::new();
        for i in 0..24_usize {
            let scaling = match i % 3 {
                0 => Scaling::Transmitter {
                    adc_full_scale_counts: 4095.0,
                    adc_full_scale_ma: 24.0,
                    current_range: CurrentRange::FourTo20,
                    range_min_degc: -50.0,
                    range_max_degc: 150.0,
                },
                1 => Scaling::Transmitter {
                    adc_full_scale_counts: 4095.0,
                    adc_full_scale_ma: 24.0,
                    current_range: CurrentRange::ZeroTo20,
                    range_min_degc: -20.0,
                    range_max_degc: 80.0,
                },
                _ => Scaling::Direct {
                    gain: 0.0625,
                    offset_degc: 20.0,
                },
            };
            let filter = FilterParams {
                median_samples: [5, 3, 1, 7, 5, 0][i % 6],
                lowpass_tau_s: [2.0, 0.0, 5.0, 2.0][i % 4],
                max_rate_degc_per_s: [40.0, 0.0][i % 2],
                max_rejected_samples: 3,
                stale_after_s: [0.0, 0.0, 1.5][i % 3],
                valid_min_degc: -20.0,
                valid_max_degc: 60.0,
            };
            out.push(ChannelProcessor::new(scaling, filter));
        }
        // Blocks of four alike, as most devices have: transmitters, then direct values
        // of +-0 in the median window, where only the order the network reads them
        // decides the sign of the median.
        for i in 24..40 {
            let median_samples = [5, 3][(i / 4) % 2];
            let (scaling, filter) = if i < 32 {
                let scaling = Scaling::Transmitter {
                    adc_full_scale_counts: 4095.0,
                    adc_full_scale_ma: 24.0,
                    current_range: CurrentRange::FourTo20,
                    range_min_degc: -50.0,
                    range_max_degc: 150.0,
                };
                let filter = FilterParams {
                    median_samples,
                    lowpass_tau_s: 2.0,
                    max_rate_degc_per_s: 40.0,
                    max_rejected_samples: 3,
                    stale_after_s: 1.5,
                    valid_min_degc: -20.0,
                    valid_max_degc: 60.0,
                };
                (scaling, filter)
            } else {
                let scaling = Scaling::Direct {
                    gain: 1.0,
                    offset_degc: -0.0,
                };
                let filter = FilterParams {
                    median_samples,
                    ..FilterParams::default()
                };
                (scaling, filter)
            };
            out.push(ChannelProcessor::new(scaling, filter));
        }
        out
    }

    /// The raw value of channel `i` at step `k`: noisy counts around a level that
    /// drifts, with spikes, NE43 faults, NaN, out-of-range values, frozen stretches.
    fn raw_value(rng: &mut ChaCha8Rng, i: usize, k: usize) -> f64 {
        if i >= 32 {
            return [-1.0, -0.0, 0.0, 1.0][rng.random_range(0..4)];
        }
        if i % 3 == 2 && i < 24 {
            // Direct: 1/16 degC per count, counts around 0 (rounding gives -0.0 too).
            let counts = (k as f64 / 7.0).sin() * 30.0 + f64::from(rng.random_range(-2..=2));
            return match rng.random_range(0..100) {
                0 => f64::NAN,
                1 => counts + 800.0,
                // Frozen at zero, the sign flipping each second: a change of the raw
                // bits, so never stale.
                _ if (k / 50) % 4 == 3 => [0.0, -0.0][(k / 10) % 2],
                _ => counts.round(),
            };
        }
        let base = 1300.0 + 200.0 * ((k + 13 * i) as f64 / 40.0).sin();
        match rng.random_range(0..200) {
            0 => 200.0,                       // 1.2 mA: NE43 low
            1 => 4000.0,                      // 23.4 mA: NE43 high
            2 => f64::INFINITY,               // not finite
            3..=5 => base + 300.0,            // a spike
            6 => 3000.0,                      // out of range
            _ if (k / 50) % 4 == 3 => 1234.0, // frozen transmitter
            _ => (base + rng.random_range(-3..=3) as f64).round(),
        }
    }

    /// The reading with its floats as bits, so NaN and -0.0 compare exactly.
    fn bits(r: &Reading) -> String {
        let b = |v: Option<f64>| v.map(f64::to_bits);
        format!(
            "{:?} {:?} {:?} {:?} {:?} {:?}",
            r.t_s.to_bits(),
            b(r.raw),
            b(r.current_ma),
            b(r.unfiltered_degc),
            b(r.value_degc),
            r.quality
        )
    }

    #[test]
    fn bank_matches_the_processors_bit_for_bit() {
        let mut reference = processors();
        let mut own = processors();
        let n = own.len();
        let mut bank = Bank::new((0..n).collect(), &own);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut t_s = 0.0;
        let mut held_samples = 0;
        for k in 0..4000 {
            // Mostly regular steps, some jitter, now and then a gap of seconds.
            t_s += match rng.random_range(0..100) {
                0 => 12.0,
                1..=9 => rng.random_range(0.05..0.2),
                _ => 0.1,
            };
            let mut gain_ref = LowPassGain::default();
            let mut gain = LowPassGain::default();
            let outage = rng.random_range(0..150) == 0;
            for (i, p) in own.iter_mut().enumerate() {
                if outage || rng.random_range(0..400) == 0 {
                    reference[i].on_missing(t_s, Reason::Comm, outage);
                    bank.missing(i, p, t_s, Reason::Comm, outage);
                    continue;
                }
                let raw = raw_value(&mut rng, i, k);
                reference[i].on_sample_with(t_s, raw, &mut gain_ref);
                held_samples += usize::from(bank.holds(i));
                bank.sample(i, p, t_s, raw, &mut gain);
            }
            bank.step(t_s, &mut gain, &mut own);
            for (i, r) in reference.iter().enumerate() {
                let ours = if bank.holds(i) {
                    bank.reading(i)
                } else {
                    own[i].last().clone()
                };
                assert_eq!(bits(&ours), bits(r.last()), "channel {i} at step {k}");
            }
        }
        // The comparison covered the bank's path, not just the processors'.
        assert!(held_samples > n * 4000 / 3, "{held_samples} held samples");
        bank.release_all(&mut own);
        for (a, b) in own.iter().zip(&reference) {
            assert_eq!(format!("{a:?}"), format!("{b:?}"));
        }
    }
}
