//! The filter stages: median window (spike rejection) and first-order low pass.

/// Median of the last up-to-N accepted samples (fewer while the window fills).
///
/// Runs for every channel on every poll. Windows of up to five samples (the usual
/// 3 or 5) live inline in the struct, so a gateway with thousands of channels chases
/// no pointer per sample, and take the median through a fixed network of
/// compare-exchanges: no branch depends on the values, which change order from one
/// noisy sample to the next. Longer windows keep a ring and a sorted copy and move
/// the newest value to its rank in one pass. No allocation after construction.
///
/// The values must be finite (the channel processor checks before it pushes); a NaN
/// gives some member of the window rather than a panic.
#[derive(Debug, Clone, PartialEq)]
pub struct MedianWindow {
    len: usize,
    /// Samples in the window.
    count: usize,
    /// Where the next sample goes in the ring.
    next: usize,
    /// The ring of a short window; `short_degc[..count]` are its samples.
    short_degc: [f64; NETWORK_MAX_LEN],
    /// The ring of a long window (`len` slots; the first `count` hold samples).
    ring_degc: Vec<f64>,
    /// The same values in `f64::total_cmp` order (long windows only).
    sorted_degc: Vec<f64>,
}

/// Longest window whose median comes from a compare network instead of a sorted
/// copy. On 64 channels of noisy 12-bit values with a median of 5, the sorted copy's
/// update cost 5.5 ns a channel more than the network, mostly in mispredicted
/// branches.
const NETWORK_MAX_LEN: usize = 5;

impl MedianWindow {
    /// A window over `len` samples; 0 and 1 both mean "off" (the median of one).
    pub fn new(len: usize) -> Self {
        let len = len.max(1);
        let long = len > NETWORK_MAX_LEN;
        Self {
            len,
            count: 0,
            next: 0,
            short_degc: [0.0; NETWORK_MAX_LEN],
            ring_degc: if long { vec![0.0; len] } else { Vec::new() },
            sorted_degc: if long {
                Vec::with_capacity(len)
            } else {
                Vec::new()
            },
        }
    }

    /// Adds a sample, dropping the oldest when full, and returns the median.
    pub fn push(&mut self, value_degc: f64) -> f64 {
        let dropped = self.put_in_ring(value_degc);
        if self.len <= NETWORK_MAX_LEN {
            return network_median(&self.short_degc[..self.count]).unwrap_or(value_degc);
        }
        let s = &mut self.sorted_degc;
        let mut i = match dropped {
            None => {
                s.push(value_degc);
                s.len() - 1
            }
            Some(old) => {
                // `old` is in `s` bit for bit: overwrite it in place.
                let at = s
                    .iter()
                    .position(|v| v.to_bits() == old.to_bits())
                    .unwrap_or(0);
                s[at] = value_degc;
                at
            }
        };
        // One of the two loops moves the new value to its rank.
        while i > 0 && s[i - 1].total_cmp(&s[i]).is_gt() {
            s.swap(i - 1, i);
            i -= 1;
        }
        while i + 1 < s.len() && s[i].total_cmp(&s[i + 1]).is_gt() {
            s.swap(i, i + 1);
            i += 1;
        }
        self.median().unwrap_or(value_degc)
    }

    /// Puts a sample into the ring; returns the one it replaced once the ring is full.
    /// While the window fills, the samples sit in `ring[..count]`.
    fn put_in_ring(&mut self, value_degc: f64) -> Option<f64> {
        let ring = if self.len <= NETWORK_MAX_LEN {
            &mut self.short_degc[..self.len]
        } else {
            &mut self.ring_degc[..]
        };
        let old = std::mem::replace(&mut ring[self.next], value_degc);
        // A compare instead of `%`, which is an integer division.
        self.next = if self.next + 1 == self.len {
            0
        } else {
            self.next + 1
        };
        if self.count < self.len {
            self.count += 1;
            return None;
        }
        Some(old)
    }

    /// The median of the window: the middle value, or the mean of the two middle
    /// values for an even count. `None` when empty.
    pub fn median(&self) -> Option<f64> {
        if self.len <= NETWORK_MAX_LEN {
            return network_median(&self.short_degc[..self.count]);
        }
        let s = &self.sorted_degc;
        let n = s.len();
        match n {
            0 => None,
            _ if n % 2 == 1 => Some(s[n / 2]),
            _ => Some((s[n / 2 - 1] + s[n / 2]) / 2.0),
        }
    }

    /// Forgets every sample.
    pub fn clear(&mut self) {
        self.count = 0;
        self.next = 0;
        self.sorted_degc.clear();
    }

    /// Samples in the window.
    pub fn count(&self) -> usize {
        self.count
    }
}

/// The smaller of `a` and `b` as `minsd` computes it (`b` on equality or NaN):
/// `f64::min` adds NaN handling the network does not need. For finite values the
/// order `total_cmp` gives but for the sign of zero.
#[inline(always)]
fn lo(a: f64, b: f64) -> f64 {
    if a < b {
        a
    } else {
        b
    }
}

/// The larger of `a` and `b` as `maxsd` computes it; see [`lo`].
#[inline(always)]
fn hi(a: f64, b: f64) -> f64 {
    if a > b {
        a
    } else {
        b
    }
}

/// `(min, max)`.
#[inline(always)]
fn sort2(a: f64, b: f64) -> (f64, f64) {
    (lo(a, b), hi(a, b))
}

/// The median of up to five values in any order (even counts: the mean of the two
/// middle ones), by fixed compare-exchange networks.
fn network_median(values: &[f64]) -> Option<f64> {
    match *values {
        [] => None,
        [a] => Some(a),
        [a, b] => Some((a + b) / 2.0),
        [a, b, c] => Some(median3(a, b, c)),
        [a, b, c, d] => {
            let (a, b) = sort2(a, b);
            let (c, d) = sort2(c, d);
            let (l, h) = sort2(hi(a, c), lo(b, d));
            Some((l + h) / 2.0)
        }
        [a, b, c, d, e] => Some(median5(a, b, c, d, e)),
        _ => None,
    }
}

/// The median of three values by a compare network.
#[inline(always)]
fn median3(a: f64, b: f64, c: f64) -> f64 {
    let (a, b) = sort2(a, b);
    hi(a, lo(b, c))
}

/// The median of five values by a compare network that selects the middle
/// (N. Devillard, "Fast median search", 1998).
#[inline(always)]
fn median5(a: f64, b: f64, c: f64, d: f64, e: f64) -> f64 {
    let (a, b) = sort2(a, b);
    let (d, e) = sort2(d, e);
    let d = hi(a, d);
    let b = lo(b, e);
    let (b, c) = sort2(b, c);
    hi(b, lo(c, d))
}

/// The low-pass gain `1 - exp(-dt/tau)`, remembered for the last `(dt, tau)` asked.
///
/// The channels of one device sample are updated at the same instant, after the same
/// previous one, mostly with the same time constant: one exponential serves them all
/// instead of one per channel (about 0.2 us of a 64-channel cycle on the bench). The
/// result is bit for bit what each filter would compute alone.
#[derive(Debug, Clone, Copy, Default)]
pub struct LowPassGain {
    /// Bits of `(dt_s, tau_s)` and their gain.
    last: Option<(u64, u64, f64)>,
}

impl LowPassGain {
    /// `1 - exp(-dt_s/tau_s)`.
    pub fn get(&mut self, dt_s: f64, tau_s: f64) -> f64 {
        let key = (dt_s.to_bits(), tau_s.to_bits());
        match self.last {
            Some((dt, tau, gain)) if (dt, tau) == key => gain,
            _ => {
                // exp_m1: no cancellation for dt << tau.
                let gain = -(-dt_s / tau_s).exp_m1();
                self.last = Some((key.0, key.1, gain));
                gain
            }
        }
    }
}

/// First-order low pass with the exact discretisation for irregular sampling:
/// `y += (1 - exp(-dt/tau)) * (x - y)` with the real `dt` since the last update.
#[derive(Debug, Clone, PartialEq)]
pub struct LowPass {
    tau_s: f64,
    /// (time of the last update, output).
    state: Option<(f64, f64)>,
}

impl LowPass {
    /// A low pass with time constant `tau_s`; 0 (or negative, or NaN) means off:
    /// the output follows the input.
    pub fn new(tau_s: f64) -> Self {
        Self { tau_s, state: None }
    }

    /// Whether the filter does anything.
    pub fn is_on(&self) -> bool {
        self.tau_s > 0.0
    }

    /// Feeds `x_degc` at `t_s` and returns the output. The first sample seeds the
    /// state. A `t_s` before the last update counts as `dt = 0` (no change).
    pub fn update(&mut self, t_s: f64, x_degc: f64) -> f64 {
        self.update_with(t_s, x_degc, &mut LowPassGain::default())
    }

    /// [`Self::update`], taking the gain from `gain`, which filters updated at the
    /// same instants share.
    pub fn update_with(&mut self, t_s: f64, x_degc: f64, gain: &mut LowPassGain) -> f64 {
        let y_degc = match self.state {
            Some((t0_s, y0_degc)) if self.is_on() => {
                let alpha = gain.get((t_s - t0_s).max(0.0), self.tau_s);
                y0_degc + alpha * (x_degc - y0_degc)
            }
            _ => x_degc,
        };
        self.state = Some((t_s, y_degc));
        y_degc
    }

    /// Sets the state to `x_degc` at `t_s`: the next update starts from there.
    pub fn reseed(&mut self, t_s: f64, x_degc: f64) {
        self.state = Some((t_s, x_degc));
    }

    /// Forgets the state: the next update seeds it.
    pub fn clear(&mut self) {
        self.state = None;
    }

    /// The current output, if seeded.
    pub fn output_degc(&self) -> Option<f64> {
        self.state.map(|(_, y)| y)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    /// The median by sorting: the reference the windows are checked against.
    fn sorted_median(values: &[f64]) -> f64 {
        let mut sorted = values.to_vec();
        sorted.sort_by(f64::total_cmp);
        let n = sorted.len();
        if n % 2 == 1 {
            sorted[n / 2]
        } else {
            (sorted[n / 2 - 1] + sorted[n / 2]) / 2.0
        }
    }

    #[test]
    fn median_while_filling_and_full() {
        let mut m = MedianWindow::new(3);
        assert_eq!(m.median(), None);
        assert_eq!(m.push(10.0), 10.0);
        // Two samples: mean of the middle pair.
        assert_eq!(m.push(20.0), 15.0);
        // 10, 20, 90: a spike does not pass.
        assert_eq!(m.push(90.0), 20.0);
        // 20, 90, 21: the oldest (10) dropped.
        assert_eq!(m.push(21.0), 21.0);
        assert_eq!(m.count(), 3);
        m.clear();
        assert_eq!(m.count(), 0);
        assert_eq!(m.push(5.0), 5.0);
    }

    #[test]
    fn incremental_median_matches_sorting_the_window() {
        // Deterministic LCG; coarse values so duplicates occur.
        let mut x: u64 = 12345;
        for len in [1, 2, 3, 4, 5, 6, 8] {
            let mut w = MedianWindow::new(len);
            let mut window: Vec<f64> = Vec::new();
            for _ in 0..500 {
                x = x
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let v = ((x >> 33) % 17) as f64 * 0.5 - 4.0;
                window.push(v);
                if window.len() > len {
                    window.remove(0);
                }
                assert_eq!(
                    w.push(v),
                    sorted_median(&window),
                    "len {len} window {window:?}"
                );
            }
        }
    }

    #[test]
    fn network_median_of_every_order() {
        // Every order of five distinct values, and of values with ties: the median
        // networks are right for any input order, not just the ones a ring produces.
        fn orders(v: &[f64]) -> Vec<Vec<f64>> {
            if v.len() <= 1 {
                return vec![v.to_vec()];
            }
            let mut out = Vec::new();
            for i in 0..v.len() {
                let mut rest = v.to_vec();
                let x = rest.remove(i);
                for mut o in orders(&rest) {
                    o.insert(0, x);
                    out.push(o);
                }
            }
            out
        }
        for values in [
            &[3.0, -1.0, 4.0, 1.5, 9.0][..],
            &[2.0, 2.0, 7.0, 7.0, 1.0],
            &[5.0, 5.0, 5.0, -5.0, 6.0],
            &[0.5, 0.25, 0.125, 8.0],
            &[1.0, 3.0, 2.0],
            &[4.0, -4.0],
        ] {
            let expect = sorted_median(values);
            for o in orders(values) {
                assert_eq!(network_median(&o), Some(expect), "{o:?}");
            }
        }
    }

    #[test]
    fn median_of_one_is_off() {
        for len in [0, 1] {
            let mut m = MedianWindow::new(len);
            assert_eq!(m.push(1.0), 1.0);
            assert_eq!(m.push(100.0), 100.0);
            assert_eq!(m.count(), 1);
        }
    }

    #[test]
    fn lowpass_exact_discretisation() {
        let mut lp = LowPass::new(10.0);
        assert_eq!(lp.update(0.0, 20.0), 20.0);
        // dt = tau: y = 20 + (1 - e^-1) * 10 = 26.3212055882856
        let y = lp.update(10.0, 30.0);
        assert!(close(y, 26.321_205_588_285_577), "{y}");
        // Irregular: dt = 2*tau after that, input 30:
        // y = 26.3212 + (1 - e^-2) * (30 - 26.3212) = 30 - 3.6788 * e^-2 = 29.502129316321360
        let y = lp.update(30.0, 30.0);
        assert!(close(y, 29.502_129_316_321_36), "{y}");
    }

    #[test]
    fn shared_gain_is_bit_identical_to_each_filter_alone() {
        // Filters with two time constants and different histories (the third one
        // skips every other instant, so its dt differs), updated at common instants
        // through one shared gain, as `Pipeline::ingest` does for a device sample.
        let taus_s = [10.0, 10.0, 10.0, 3.0];
        let mut shared: Vec<LowPass> = taus_s.iter().map(|&t| LowPass::new(t)).collect();
        let mut alone = shared.clone();
        let mut x: u64 = 7;
        for step in 0..200 {
            let t_s = f64::from(step) * 0.013 + if step % 7 == 0 { 0.4 } else { 0.0 };
            let mut gain = LowPassGain::default();
            for (i, (a, b)) in shared.iter_mut().zip(&mut alone).enumerate() {
                if i == 2 && step % 2 == 0 {
                    continue;
                }
                x = x
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let v = 20.0 + ((x >> 40) % 1000) as f64 * 1e-3;
                let y_shared = a.update_with(t_s, v, &mut gain);
                let y_alone = b.update(t_s, v);
                assert_eq!(
                    y_shared.to_bits(),
                    y_alone.to_bits(),
                    "step {step} filter {i}"
                );
            }
        }
    }

    #[test]
    fn lowpass_same_time_or_backwards_changes_nothing() {
        let mut lp = LowPass::new(5.0);
        lp.update(10.0, 20.0);
        assert_eq!(lp.update(10.0, 99.0), 20.0);
        assert_eq!(lp.update(9.0, 99.0), 20.0);
    }

    #[test]
    fn lowpass_off_follows_input() {
        for tau in [0.0, -1.0, f64::NAN] {
            let mut lp = LowPass::new(tau);
            assert!(!lp.is_on());
            lp.update(0.0, 20.0);
            assert_eq!(lp.update(1.0, 30.0), 30.0);
        }
    }

    #[test]
    fn lowpass_reseed_and_clear() {
        let mut lp = LowPass::new(10.0);
        lp.update(0.0, 20.0);
        lp.reseed(5.0, 40.0);
        assert_eq!(lp.output_degc(), Some(40.0));
        // From 40 at t=5: dt = 0 -> no change.
        assert_eq!(lp.update(5.0, 0.0), 40.0);
        lp.clear();
        assert_eq!(lp.output_degc(), None);
        assert_eq!(lp.update(6.0, 7.0), 7.0);
    }
}
