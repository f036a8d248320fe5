//! A seeded generator of measured-error data with hidden effects, for the tests, the
//! README figures and the benchmark. Independent of the machine simulation: its own
//! duty cycles, sampling and noise.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use super::effects::{lag, motion_heat, EffectKind};
use super::fit::{residuals, Gram};
use compgate_core::measure::{Measurements, TempColumn};

/// What to generate.
#[derive(Debug, Clone)]
pub struct SynthSpec {
    pub seed: u64,
    /// Rows.
    pub rows: usize,
    /// Hidden effects.
    pub effects: Vec<EffectKind>,
    /// White noise standard deviation, um.
    pub noise_um: f64,
    /// RMS of each effect's part the baseline cannot explain, as a multiple of the noise.
    pub snr: f64,
    /// Laser-style sampling: 21 fixed targets measured in bidirectional cycles at a
    /// regular interval, with machining travel between cycles; else random positions
    /// at irregular times.
    pub laser: bool,
    /// Lag-1 correlation of the noise (0: white); its standard deviation stays
    /// `noise_um`.
    pub noise_ar1: f64,
}

/// The truth behind a generated series.
#[derive(Debug, Clone)]
pub struct Truth {
    /// (effect, tau_s or period_mm or b_um or 0, visible RMS um).
    pub effects: Vec<(EffectKind, f64, f64)>,
    /// Baseline sensors (the extra sensor is `c`, outside them).
    pub sensors: Vec<String>,
    /// The error without noise, um.
    pub clean_um: Vec<f64>,
}

fn first_order(t_s: &[f64], x: &[f64], tau_s: f64) -> Vec<f64> {
    lag(t_s, x, tau_s)
}

/// Generates a series; the effect signals are scaled so that the part of each one the
/// baseline cannot explain has RMS `snr * noise_um`.
pub fn generate(spec: &SynthSpec) -> (Measurements, Truth) {
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed);
    let n = spec.rows;
    let span_mm: f64 = rng.random_range(300.0..1500.0);
    let mut t_s = Vec::with_capacity(n);
    let mut pos_mm = Vec::with_capacity(n);
    let mut travel_mm = Vec::with_capacity(n);
    if spec.laser {
        // Bidirectional cycles over 21 targets, one row per target, then a machining
        // spell whose travel shows in the next row.
        let dt = rng.random_range(5.0..15.0);
        let gap_s = rng.random_range(300.0..1200.0);
        let targets: Vec<f64> = (0..21).map(|k| span_mm * k as f64 / 20.0).collect();
        let mut t = 0.0;
        let mut pos = 0.0;
        let mut k = 0usize;
        while t_s.len() < n {
            let fwd = k.is_multiple_of(2);
            let mut extra = if k > 0 {
                rng.random_range(0.0..2000.0) * gap_s / 600.0
            } else {
                0.0
            };
            if k > 0 {
                t += gap_s * rng.random_range(0.5..1.5);
            }
            for j in 0..21 {
                if t_s.len() == n {
                    break;
                }
                let target = if fwd { targets[j] } else { targets[20 - j] };
                t_s.push(t);
                travel_mm.push((target - pos).abs() + extra);
                extra = 0.0;
                pos_mm.push(target);
                pos = target;
                t += dt;
            }
            k += 1;
        }
    } else {
        // Irregular sampling: mean interval 4..20 s with jitter; runs of moves to
        // random targets with idle spells.
        let dt_mean = rng.random_range(4.0..20.0);
        let mut t = 0.0;
        for _ in 0..n {
            t_s.push(t);
            t += dt_mean * rng.random_range(0.5..1.5);
        }
        let mut pos: f64 = span_mm * rng.random_range(0.0..1.0);
        let mut busy = true;
        let mut speed_scale = 1.0;
        for _ in 0..n {
            if rng.random_bool(0.01) {
                busy = !busy;
                speed_scale = rng.random_range(0.3..1.0);
            }
            let prev = pos;
            if busy || rng.random_bool(0.1) {
                pos = if rng.random_bool(speed_scale) {
                    span_mm * rng.random_range(0.0..1.0)
                } else {
                    (pos + rng.random_range(-0.1..0.1) * span_mm).clamp(0.0, span_mm)
                };
            }
            travel_mm.push((pos - prev).abs());
            pos_mm.push(pos);
        }
    }
    let duration = t_s[n - 1] - t_s[0];
    // Temperatures: a spindle-like source with an on/off schedule, ambient drift, and
    // an independent coolant sensor.
    let mut heat = Vec::with_capacity(n);
    let mut on = false;
    for _ in 0..n {
        if rng.random_bool(0.004) {
            on = !on;
        }
        heat.push(if on { rng.random_range(8.0..12.0) } else { 0.0 });
    }
    let tau_a = duration * rng.random_range(0.05..0.15);
    let amb_period = duration * rng.random_range(0.8..2.0);
    let amb_phase = rng.random_range(0.0..std::f64::consts::TAU);
    let amb: Vec<f64> = t_s
        .iter()
        .map(|&t| 20.0 + 1.5 * (std::f64::consts::TAU * t / amb_period + amb_phase).sin())
        .collect();
    let a_lag = first_order(&t_s, &heat, tau_a);
    let temp_noise = Normal::new(0.0, 0.02).unwrap_or_else(|_| unreachable!());
    let t_a: Vec<f64> = (0..n)
        .map(|i| amb[i] + a_lag[i] + temp_noise.sample(&mut rng))
        .collect();
    let b_src: Vec<f64> = (0..n).map(|i| amb[i] + 0.3 * a_lag[i]).collect();
    let t_b0 = first_order(&t_s, &b_src, duration * rng.random_range(0.02..0.06));
    let t_b: Vec<f64> = t_b0
        .iter()
        .map(|v| v + temp_noise.sample(&mut rng))
        .collect();
    let mut cool = Vec::with_capacity(n);
    let mut cool_on = rng.random_bool(0.5);
    for _ in 0..n {
        if rng.random_bool(0.006) {
            cool_on = !cool_on;
        }
        cool.push(if cool_on { 24.0 } else { 19.0 });
    }
    let t_c0 = first_order(&t_s, &cool, duration * rng.random_range(0.02..0.08));
    let t_c: Vec<f64> = t_c0
        .iter()
        .map(|v| v + temp_noise.sample(&mut rng))
        .collect();

    // Baseline truth: K0 and tan(beta) affine in T_a and T_b.
    let p0 = span_mm / 2.0;
    let k0_a = rng.random_range(2.0..8.0); // um/degC
    let k0_b = rng.random_range(-3.0..3.0);
    let sl_a = rng.random_range(5.0..15.0) * 1e-3; // um/mm/degC
    let sl_b = rng.random_range(-5.0..5.0) * 1e-3;
    let mut err: Vec<f64> = (0..n)
        .map(|i| {
            let x = pos_mm[i] - p0;
            k0_a * (t_a[i] - 20.0)
                + k0_b * (t_b[i] - 20.0)
                + x * (sl_a * (t_a[i] - 20.0) + sl_b * (t_b[i] - 20.0))
        })
        .collect();

    // Baseline design to measure each effect's visible part.
    let one = vec![1.0; n];
    let x: Vec<f64> = pos_mm.iter().map(|p| p - p0).collect();
    let ax: Vec<f64> = (0..n).map(|i| t_a[i] * x[i]).collect();
    let bx: Vec<f64> = (0..n).map(|i| t_b[i] * x[i]).collect();
    let base: Vec<&[f64]> = vec![&one, &x, &t_a, &ax, &t_b, &bx];

    let mut dir = Vec::with_capacity(n);
    let mut last = 1i8;
    for i in 0..n {
        let d = if i == 0 {
            0.0
        } else {
            pos_mm[i] - pos_mm[i - 1]
        };
        if d > 0.0 {
            last = 1;
        } else if d < 0.0 {
            last = -1;
        }
        dir.push(last);
    }

    let mut truth = Truth {
        effects: Vec::new(),
        sensors: vec!["a".into(), "b".into()],
        clean_um: Vec::new(),
    };
    for &kind in &spec.effects {
        let sign = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
        let mix = rng.random_range(0.0..1.0);
        let (signal, param): (Vec<f64>, f64) = match kind {
            EffectKind::ThermalLag => {
                let tau = duration * rng.random_range(0.03..0.15);
                let l = lag(&t_s, &t_a, tau);
                (
                    (0..n)
                        .map(|i| sign * (l[i] - 20.0) * (1.0 + mix * x[i] / span_mm))
                        .collect(),
                    tau,
                )
            }
            EffectKind::MotionHeating => {
                let tau = duration * rng.random_range(0.03..0.15);
                let h = motion_heat(&t_s, &travel_mm, tau);
                (
                    (0..n)
                        .map(|i| sign * h[i] * (1.0 + mix * x[i] / span_mm))
                        .collect(),
                    tau,
                )
            }
            EffectKind::ExtraSensor => (
                (0..n)
                    .map(|i| sign * (t_c[i] - 20.0) * (1.0 + mix * x[i] / span_mm))
                    .collect(),
                0.0,
            ),
            EffectKind::NonlinearPosition => {
                let c3 = rng.random_range(-1.0..1.0);
                (
                    (0..n)
                        .map(|i| {
                            let v = 2.0 * pos_mm[i] / span_mm - 1.0;
                            sign * v * v + c3 * v * v * v
                        })
                        .collect(),
                    0.0,
                )
            }
            EffectKind::Reversal => ((0..n).map(|i| f64::from(dir[i])).collect(), 0.0),
            EffectKind::PitchPeriodic => {
                let period = if spec.laser {
                    span_mm / 20.0 * rng.random_range(4.0..8.0)
                } else {
                    span_mm * rng.random_range(0.02..0.2)
                };
                let ph = rng.random_range(0.0..std::f64::consts::TAU);
                (
                    pos_mm
                        .iter()
                        .map(|p| (std::f64::consts::TAU * p / period + ph).sin())
                        .collect(),
                    period,
                )
            }
        };
        let b = super::fit::blocks(n, 1);
        let g = Gram::new(&base, &signal, &b);
        let vis = residuals(&base, &signal, &g.solve().beta);
        let vis_rms = (vis.iter().map(|v| v * v).sum::<f64>() / n as f64).sqrt();
        let scale = spec.snr * spec.noise_um / vis_rms.max(1e-12);
        for i in 0..n {
            err[i] += scale * signal[i];
        }
        let param = match kind {
            EffectKind::Reversal => 2.0 * scale,
            EffectKind::PitchPeriodic => param,
            _ => param,
        };
        truth.effects.push((kind, param, spec.snr * spec.noise_um));
    }
    truth.clean_um = err.clone();
    let noise = Normal::new(0.0, spec.noise_um.max(1e-12)).unwrap_or_else(|_| unreachable!());
    let rho = spec.noise_ar1.clamp(0.0, 0.999);
    let mut z: f64 = noise.sample(&mut rng);
    for e in err.iter_mut() {
        *e += z;
        z = rho * z + (1.0 - rho * rho).sqrt() * noise.sample(&mut rng);
    }
    let m = Measurements {
        t_s,
        pos_mm,
        err_um: err,
        dir,
        travel_mm,
        temps: vec![
            TempColumn {
                name: "a".into(),
                degc: t_a,
            },
            TempColumn {
                name: "b".into(),
                degc: t_b,
            },
            TempColumn {
                name: "c".into(),
                degc: t_c,
            },
        ],
        ignored_columns: Vec::new(),
    };
    (m, truth)
}
