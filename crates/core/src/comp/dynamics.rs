//! Model terms with a memory: a sensor seen through a first-order lag, and the heat of
//! axis motion estimated from the NC's actual position. Both are what `diagnose`
//! names (`thermal_lag`, `motion_heating`) and what the K0/tan(beta) form cannot
//! carry from one temperature reading alone.
//!
//! Pure: the caller hands in time and values; the state is the filters' outputs.

/// A derived model input: input `source` through a first-order lag of `tau_s`,
/// delivered as model input `slot` (after the real inputs).
#[derive(Debug, Clone, PartialEq)]
pub struct InputLag {
    /// Real input it follows.
    pub source: usize,
    /// Model input index it fills.
    pub slot: usize,
    /// Time constant, s (> 0).
    pub tau_s: f64,
}

/// Heat of axis motion: travel (from successive actual positions) feeds a first-order
/// store ([`heat_store_step`]), so `h` is the travel rate (mm/s) seen through the lag;
/// `K0 += k0_mm_per_mm_per_s (h - ref)`, `tan(beta) += tan_beta_per_mm_per_s (h - ref)`.
/// diagnose's `motion_heating` signal is the same store, so its fitted coefficients
/// apply unchanged.
#[derive(Debug, Clone, PartialEq)]
pub struct MotionHeat {
    /// Time constant of the hidden store, s (> 0).
    pub tau_s: f64,
    /// Travel rate at which the term is zero, mm/s.
    pub ref_mm_per_s: f64,
    /// K0 per mm/s of travel rate, mm/(mm/s).
    pub k0_mm_per_mm_per_s: f64,
    /// tan(beta) per mm/s of travel rate, 1/(mm/s).
    pub tan_beta_per_mm_per_s: f64,
}

/// The motion heat store `heat_mm_per_s` after `dt_s` in which the axis travelled
/// `travel_mm`, that travel taken at a constant rate over the interval:
/// `h e^(-dt/tau) + (travel / dt) (1 - e^(-dt/tau))`. Exact for a constant rate however
/// long the interval, so the gateway polling every second and diagnose reading rows
/// half an hour apart compute the same store; with no interval the travel is an
/// impulse `travel / tau`.
pub fn heat_store_step(heat_mm_per_s: f64, dt_s: f64, travel_mm: f64, tau_s: f64) -> f64 {
    let x = dt_s.max(0.0) / tau_s;
    // (1 - e^-x) / x, which tends to 1 as x -> 0.
    let spread = if x > 1e-9 { -(-x).exp_m1() / x } else { 1.0 };
    heat_mm_per_s * (-x).exp() + travel_mm / tau_s * spread
}

/// The state of an axis' lags and motion heat.
#[derive(Debug, Clone, Default)]
pub struct Dynamics {
    lags: Vec<InputLag>,
    lag_state: Vec<Option<(f64, f64)>>,
    motion: Option<MotionHeat>,
    /// (time s, position mm) of the last position, and the store h, mm/s.
    last_pos: Option<(f64, f64)>,
    heat_mm_per_s: f64,
}

impl Dynamics {
    /// Lags and an optional motion heat term; every state starts empty (a lag starts
    /// at its first input, the heat store cold).
    pub fn new(lags: Vec<InputLag>, motion: Option<MotionHeat>) -> Self {
        Self {
            lag_state: vec![None; lags.len()],
            lags,
            motion,
            last_pos: None,
            heat_mm_per_s: 0.0,
        }
    }

    /// No lag and no motion term.
    pub fn is_empty(&self) -> bool {
        self.lags.is_empty() && self.motion.is_none()
    }

    /// The lags.
    pub fn lags(&self) -> &[InputLag] {
        &self.lags
    }

    /// The motion heat term.
    pub fn motion(&self) -> Option<&MotionHeat> {
        self.motion.as_ref()
    }

    /// The model inputs the lags fill, beyond the real ones.
    pub fn slots(&self) -> usize {
        self.lags.iter().map(|l| l.slot + 1).max().unwrap_or(0)
    }

    /// Advances every lag to `now_s` with its source's value in `temps_degc` (held
    /// since the last call: exact for a held input) and writes the lagged values into
    /// their slots, growing `temps_degc` as needed. A source that is `None` leaves its
    /// lag where it was and its slot `None`.
    pub fn apply_lags(&mut self, now_s: f64, temps_degc: &mut Vec<Option<f64>>) {
        if temps_degc.len() < self.slots() {
            temps_degc.resize(self.slots(), None);
        }
        for (lag, state) in self.lags.iter().zip(&mut self.lag_state) {
            let x = temps_degc
                .get(lag.source)
                .copied()
                .flatten()
                .filter(|v| v.is_finite());
            let out = match (x, *state) {
                (Some(x), None) => Some((now_s, x)),
                (Some(x), Some((t0, y))) => {
                    let a = (-(now_s - t0).max(0.0) / lag.tau_s).exp();
                    Some((now_s, x + (y - x) * a))
                }
                (None, s) => s,
            };
            *state = out;
            temps_degc[lag.slot] = x.and(out.map(|s| s.1));
        }
    }

    /// The NC's actual position at `now_s`: adds the travel since the last one.
    pub fn on_position(&mut self, now_s: f64, pos_mm: f64) {
        let Some(m) = &self.motion else { return };
        if !(pos_mm.is_finite() && now_s.is_finite()) {
            return;
        }
        if let Some((t0, p0)) = self.last_pos {
            self.heat_mm_per_s =
                heat_store_step(self.heat_mm_per_s, now_s - t0, (pos_mm - p0).abs(), m.tau_s);
        }
        self.last_pos = Some((now_s, pos_mm));
    }

    /// The travel rate through the lag, mm/s.
    pub fn heat_mm_per_s(&self) -> f64 {
        self.heat_mm_per_s
    }

    /// What the motion term adds: (K0 mm, tan(beta)).
    pub fn motion_terms(&self) -> (f64, f64) {
        match &self.motion {
            Some(m) => {
                let x = self.heat_mm_per_s - m.ref_mm_per_s;
                (m.k0_mm_per_mm_per_s * x, m.tan_beta_per_mm_per_s * x)
            }
            None => (0.0, 0.0),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lag_reaches_63_percent_of_a_step_after_tau() {
        let mut d = Dynamics::new(
            vec![InputLag {
                source: 0,
                slot: 1,
                tau_s: 100.0,
            }],
            None,
        );
        let mut t = vec![Some(20.0)];
        d.apply_lags(0.0, &mut t);
        assert_eq!(t, vec![Some(20.0), Some(20.0)]);
        for k in 1..=10 {
            let mut t = vec![Some(21.0)];
            d.apply_lags(10.0 * k as f64, &mut t);
            if k == 10 {
                let want = 20.0 + (1.0 - (-1.0f64).exp());
                assert!((t[1].unwrap_or(0.0) - want).abs() < 1e-12, "{t:?}");
            }
        }
        // A bad source leaves the slot bad and the state as it was.
        let mut t = vec![None];
        d.apply_lags(2000.0, &mut t);
        assert_eq!(t, vec![None, None]);
    }

    /// A steady rate gives the same store over one long step as over many short
    /// ones; with no interval the travel is an impulse.
    #[test]
    fn the_heat_store_does_not_depend_on_the_step() {
        let mut h = 0.0;
        for _ in 0..1000 {
            h = heat_store_step(h, 1.8, 1.8 * 50.0, 600.0);
        }
        let once = heat_store_step(0.0, 1800.0, 1800.0 * 50.0, 600.0);
        assert!((h - once).abs() < 1e-9 && (once - 50.0 * (1.0 - (-3.0f64).exp())).abs() < 1e-9);
        assert_eq!(heat_store_step(1.0, 0.0, 600.0, 600.0), 2.0);
    }

    #[test]
    fn motion_heat_settles_at_the_travel_rate() {
        let m = MotionHeat {
            tau_s: 100.0,
            ref_mm_per_s: 1.0,
            k0_mm_per_mm_per_s: 0.002,
            tan_beta_per_mm_per_s: 1e-6,
        };
        let mut d = Dynamics::new(vec![], Some(m));
        // Oscillating over 0..=100 mm at 10 mm/s, sampled every second.
        for k in 0..5000 {
            let s = 10.0 * k as f64;
            let pos = if (s / 100.0) as i64 % 2 == 0 {
                s % 100.0
            } else {
                100.0 - s % 100.0
            };
            d.on_position(k as f64, pos);
        }
        assert!(
            (d.heat_mm_per_s() - 10.0).abs() < 0.1,
            "{}",
            d.heat_mm_per_s()
        );
        let (k0, tb) = d.motion_terms();
        assert!((k0 - 0.002 * (d.heat_mm_per_s() - 1.0)).abs() < 1e-15);
        assert!((tb - 1e-6 * (d.heat_mm_per_s() - 1.0)).abs() < 1e-18);
    }
}
