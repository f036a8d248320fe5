//! The effect vocabulary: the columns each candidate adds to the design, and the
//! signals they are built from (first-order lags, motion heat, Legendre polynomials,
//! sine pairs).

use std::fmt;

use compgate_core::comp::heat_store_step;

/// A physical effect the baseline `K0(T) + tan(beta)(T) * (pos - P0)` lacks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum EffectKind {
    /// The structure follows a sensor through a first-order lag (`tau_s`).
    ThermalLag,
    /// The error curve along the axis is not straight.
    NonlinearPosition,
    /// The error depends on the direction of approach (`b_um`).
    Reversal,
    /// The error is periodic in position (`period_mm`, `amplitude_um`).
    PitchPeriodic,
    /// Heat from axis motion that no sensor sees (`tau_s`).
    MotionHeating,
    /// A temperature column outside `--sensors` explains the residual.
    ExtraSensor,
}

impl EffectKind {
    /// Every kind, in report order.
    pub const ALL: [EffectKind; 6] = [
        EffectKind::ThermalLag,
        EffectKind::NonlinearPosition,
        EffectKind::Reversal,
        EffectKind::PitchPeriodic,
        EffectKind::MotionHeating,
        EffectKind::ExtraSensor,
    ];

    /// The fixed name of the interface.
    pub fn name(self) -> &'static str {
        match self {
            EffectKind::ThermalLag => "thermal_lag",
            EffectKind::NonlinearPosition => "nonlinear_position",
            EffectKind::Reversal => "reversal",
            EffectKind::PitchPeriodic => "pitch_periodic",
            EffectKind::MotionHeating => "motion_heating",
            EffectKind::ExtraSensor => "extra_sensor",
        }
    }

    /// The kind of a name of the interface.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }
}

impl fmt::Display for EffectKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Response of a first-order lag with time constant `tau_s` to `x`, exact for an input
/// held between samples; starts in equilibrium with the first sample.
pub fn lag(t_s: &[f64], x: &[f64], tau_s: f64) -> Vec<f64> {
    let mut out = Vec::with_capacity(x.len());
    let mut y = x.first().copied().unwrap_or(0.0);
    let mut prev_t = t_s.first().copied().unwrap_or(0.0);
    for (&t, &xi) in t_s.iter().zip(x) {
        let a = (-(t - prev_t).max(0.0) / tau_s).exp();
        y = a * y + (1.0 - a) * xi;
        out.push(y);
        prev_t = t;
    }
    out
}

/// Hidden heat of axis motion: the gateway's store (`heat_store_step`), each row's
/// travel spread evenly over the interval since the row before, so the state is the
/// travel rate (mm/s) seen through the lag however far apart the rows are. It starts
/// cold at the first row, whose travel came over an interval the data does not show
/// (as the gateway's store starts at its first position).
pub fn motion_heat(t_s: &[f64], travel_mm: &[f64], tau_s: f64) -> Vec<f64> {
    let mut out = Vec::with_capacity(t_s.len());
    let mut h = 0.0;
    for (i, (&t, &d)) in t_s.iter().zip(travel_mm).enumerate() {
        if i > 0 {
            h = heat_store_step(h, t - t_s[i - 1], d, tau_s);
        }
        out.push(h);
    }
    out
}

/// Legendre polynomials P2, P3, P4 of `v` in [-1, 1].
pub fn legendre_2_4(v: f64) -> [f64; 3] {
    let v2 = v * v;
    [
        (3.0 * v2 - 1.0) / 2.0,
        (5.0 * v2 * v - 3.0 * v) / 2.0,
        (35.0 * v2 * v2 - 30.0 * v2 + 3.0) / 8.0,
    ]
}

/// Subtracts the mean, returning it.
pub fn center(x: &mut [f64]) -> f64 {
    let mean = x.iter().sum::<f64>() / x.len().max(1) as f64;
    for v in x.iter_mut() {
        *v -= mean;
    }
    mean
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lag_of_a_step_reaches_63_percent_at_tau() {
        let t: Vec<f64> = (0..=200).map(|i| i as f64).collect();
        let x: Vec<f64> = t.iter().map(|&t| if t > 0.0 { 1.0 } else { 0.0 }).collect();
        let y = lag(&t, &x, 100.0);
        assert!(
            (y[100] - (1.0 - (-1.0f64).exp())).abs() < 0.01,
            "{}",
            y[100]
        );
    }

    #[test]
    fn motion_heat_settles_at_the_travel_rate() {
        let t: Vec<f64> = (0..5000).map(|i| i as f64).collect();
        let d = vec![2.0; 5000];
        let h = motion_heat(&t, &d, 100.0);
        assert!((h[4999] - 2.0).abs() < 0.02, "{}", h[4999]);
    }

    /// Rows half an hour apart see the store that rows every 4 s see at the same
    /// times, when the rate between them is steady: an impulse per row gave 1.4
    /// times as much.
    #[test]
    fn motion_heat_of_sparse_rows_is_that_of_dense_rows() {
        let dense_t: Vec<f64> = (0..=900).map(|i| 4.0 * i as f64).collect();
        let dense = motion_heat(&dense_t, &vec![4.0 * 150.0; dense_t.len()], 2400.0);
        let sparse = motion_heat(
            &[0.0, 1800.0, 3600.0],
            &[0.0, 1800.0 * 150.0, 1800.0 * 150.0],
            2400.0,
        );
        for (k, i) in [(1, 450), (2, 900)] {
            assert!(
                (sparse[k] - dense[i]).abs() < 1e-9,
                "{sparse:?} {}",
                dense[i]
            );
        }
    }

    #[test]
    fn names_round_trip() {
        for k in EffectKind::ALL {
            assert_eq!(EffectKind::from_name(k.name()), Some(k));
        }
    }
}
