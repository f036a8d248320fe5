//! Least-squares fit of the patent's thermal model (step S1), pure math, no I/O.
//!
//! ```text
//! err_um = K0_um(T) + 1000 * tan_beta(T) * (P - P0)
//! K0_um(T)    = k0_offset_um   + sum_j k0_um_per_degc[j]    * (T_j - ref_j)
//! tan_beta(T) = tan_beta_offset + sum_j tan_beta_per_degc[j] * (T_j - ref_j)
//! ```
//!
//! Linear in its 2 + 2m coefficients, so one linear least-squares problem, solved by
//! [`crate::lsq`] on the column-scaled design (temperatures in K and positions in mm
//! differ by three orders of magnitude). Standard errors come from
//! `sigma^2 (X^T X)^-1`, assuming independent residuals; on a slow thermal series
//! they are a lower bound.

use nalgebra::{DMatrix, DVector};
use thiserror::Error;

use crate::lsq;
use crate::stats::mean;

/// Why a fit is impossible.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum FitError {
    /// Fewer rows than coefficients.
    #[error("{rows} rows for {coeffs} coefficients: measure more points or use fewer sensors")]
    TooFewRows { rows: usize, coeffs: usize },
    /// Columns of unequal length.
    #[error("column `{0}` has a different number of rows")]
    Length(String),
    /// A sensor's temperature never changes, so its coefficient is undetermined.
    #[error("sensor `{0}` is constant over the data: its coefficient cannot be fitted; drop it with --sensors")]
    ConstantSensor(String),
    /// All measurements at one position.
    #[error("every measurement is at one position: tan(beta) cannot be fitted")]
    OnePosition,
    /// Sensors move together, so their coefficients cannot be told apart.
    #[error(
        "the sensors are linearly dependent (condition number {}); use fewer sensors",
        crate::lsq::condition_text(*condition)
    )]
    Collinear { condition: f64 },
    /// A value is NaN or infinite.
    #[error("a value of `{0}` is not finite")]
    NotFinite(String),
    /// The solver failed (no convergence, overflow): the data cannot be fitted.
    #[error("least squares failed: {0}")]
    Solver(lsq::LsqError),
    /// A fitted figure came out NaN or infinite (an overflow on extreme data).
    #[error("the fitted {0} is not finite: the data cannot be fitted (check for extreme values)")]
    NonFiniteResult(&'static str),
}

/// One sensor's part of the fitted model.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorTerm {
    /// Sensor (channel) name, without `T_`.
    pub name: String,
    /// Temperature at which the term is zero (the data's mean, to 0.01 K), degC.
    pub ref_degc: f64,
    /// K0 coefficient, um/K, and its standard error.
    pub k0_um_per_degc: f64,
    /// Standard error of `k0_um_per_degc`.
    pub k0_se_um_per_degc: f64,
    /// tan(beta) coefficient, 1/K (mm/mm/K), and its standard error.
    pub tan_beta_per_degc: f64,
    /// Standard error of `tan_beta_per_degc`.
    pub tan_beta_se_per_degc: f64,
}

/// A fitted model and its quality.
#[derive(Debug, Clone, PartialEq)]
pub struct Fit {
    /// Reference position P0, mm.
    pub p0_mm: f64,
    /// K0 at the reference temperatures, um.
    pub k0_offset_um: f64,
    /// Standard error of `k0_offset_um`.
    pub k0_offset_se_um: f64,
    /// tan(beta) at the reference temperatures.
    pub tan_beta_offset: f64,
    /// Standard error of `tan_beta_offset`.
    pub tan_beta_offset_se: f64,
    /// One term per sensor, in input order.
    pub terms: Vec<SensorTerm>,
    /// Rows used.
    pub rows: usize,
    /// RMS of the residuals, um.
    pub rms_um: f64,
    /// Largest absolute residual, um.
    pub max_abs_um: f64,
    /// Coefficient of determination.
    pub r2: f64,
    /// Condition number of the scaled design.
    pub condition: f64,
    /// Measured minus fitted, um, per row.
    pub residuals_um: Vec<f64>,
}

impl Fit {
    /// K0 at temperatures `temps_degc` (one per term), um.
    pub fn k0_um(&self, temps_degc: &[f64]) -> f64 {
        self.k0_offset_um
            + self
                .terms
                .iter()
                .zip(temps_degc)
                .map(|(t, v)| t.k0_um_per_degc * (v - t.ref_degc))
                .sum::<f64>()
    }

    /// tan(beta) at temperatures `temps_degc`.
    pub fn tan_beta(&self, temps_degc: &[f64]) -> f64 {
        self.tan_beta_offset
            + self
                .terms
                .iter()
                .zip(temps_degc)
                .map(|(t, v)| t.tan_beta_per_degc * (v - t.ref_degc))
                .sum::<f64>()
    }

    /// Predicted error at `pos_mm` and `temps_degc`, um.
    pub fn predict_um(&self, pos_mm: f64, temps_degc: &[f64]) -> f64 {
        self.k0_um(temps_degc) + 1000.0 * self.tan_beta(temps_degc) * (pos_mm - self.p0_mm)
    }
}

/// P0 the commissioning way: the measured position nearest the axis zero (where the
/// screw's fixed bearing usually sits and the error is least position dependent).
pub fn choose_p0_mm(pos_mm: &[f64]) -> f64 {
    pos_mm
        .iter()
        .copied()
        .filter(|p| p.is_finite())
        .min_by(|a, b| a.abs().total_cmp(&b.abs()))
        .unwrap_or(0.0)
}

/// Fits the model to rows of `pos_mm`, `err_um` and one temperature column per
/// sensor `(name, degc)`, with reference position `p0_mm`.
pub fn fit(
    pos_mm: &[f64],
    err_um: &[f64],
    sensors: &[(&str, &[f64])],
    p0_mm: f64,
) -> Result<Fit, FitError> {
    let n = pos_mm.len();
    let m = sensors.len();
    let p = 2 + 2 * m;
    if err_um.len() != n {
        return Err(FitError::Length("err_um".into()));
    }
    for (name, col) in sensors {
        if col.len() != n {
            return Err(FitError::Length(format!("T_{name}")));
        }
        if col.iter().any(|v| !v.is_finite()) {
            return Err(FitError::NotFinite(format!("T_{name}")));
        }
    }
    if pos_mm.iter().any(|v| !v.is_finite()) {
        return Err(FitError::NotFinite("pos_mm".into()));
    }
    if err_um.iter().any(|v| !v.is_finite()) {
        return Err(FitError::NotFinite("err_um".into()));
    }
    if n < p + 1 {
        return Err(FitError::TooFewRows { rows: n, coeffs: p });
    }
    let refs: Vec<f64> = sensors
        .iter()
        .map(|(_, col)| (mean(col) * 100.0).round() / 100.0)
        .collect();
    for ((name, col), r) in sensors.iter().zip(&refs) {
        let spread = col.iter().map(|v| (v - r).abs()).fold(0.0, f64::max);
        if spread < 1e-9 {
            return Err(FitError::ConstantSensor((*name).to_string()));
        }
    }
    let dx: Vec<f64> = pos_mm.iter().map(|x| x - p0_mm).collect();
    if dx.iter().all(|d| (d - dx[0]).abs() < 1e-9) {
        return Err(FitError::OnePosition);
    }

    // Columns: 1, dT_j..., dx, dx * dT_j...  (um per unit of each column).
    let mut x = DMatrix::<f64>::zeros(n, p);
    for i in 0..n {
        x[(i, 0)] = 1.0;
        x[(i, 1 + m)] = dx[i];
        for (j, (_, col)) in sensors.iter().enumerate() {
            let dt = col[i] - refs[j];
            x[(i, 1 + j)] = dt;
            x[(i, 2 + m + j)] = dx[i] * dt;
        }
    }
    let design = lsq::solve_design(&x, err_um, 1e10).map_err(|e| match e {
        lsq::LsqError::Collinear { condition } => FitError::Collinear { condition },
        other => FitError::Solver(other),
    })?;
    let beta = &design.beta;
    let condition = design.condition;
    let fitted = &x * DVector::from_column_slice(beta);
    let residuals_um: Vec<f64> = (0..n).map(|i| err_um[i] - fitted[i]).collect();
    let ss_res: f64 = residuals_um.iter().map(|r| r * r).sum();
    let y_mean = mean(err_um);
    let ss_tot: f64 = err_um.iter().map(|v| (v - y_mean).powi(2)).sum();
    let sigma2 = ss_res / (n - p) as f64;
    let se = |c: usize| (sigma2 * design.inv_gram_diag[c]).sqrt();
    // Large-but-finite data can still overflow a sum of squares; a non-finite figure
    // must fail the fit here rather than reach the report or the model file.
    let figures = [
        ("residual sum of squares", ss_res),
        ("total sum of squares", ss_tot),
    ];
    for (what, v) in figures {
        if !v.is_finite() {
            return Err(FitError::NonFiniteResult(what));
        }
    }
    if (0..p).any(|c| !se(c).is_finite()) {
        return Err(FitError::NonFiniteResult("standard error"));
    }
    // tan(beta) = slope_um_per_mm / 1000.
    let terms = sensors
        .iter()
        .enumerate()
        .map(|(j, (name, _))| SensorTerm {
            name: (*name).to_string(),
            ref_degc: refs[j],
            k0_um_per_degc: beta[1 + j],
            k0_se_um_per_degc: se(1 + j),
            tan_beta_per_degc: beta[2 + m + j] / 1000.0,
            tan_beta_se_per_degc: se(2 + m + j) / 1000.0,
        })
        .collect();
    Ok(Fit {
        p0_mm,
        k0_offset_um: beta[0],
        k0_offset_se_um: se(0),
        tan_beta_offset: beta[1 + m] / 1000.0,
        tan_beta_offset_se: se(1 + m) / 1000.0,
        terms,
        rows: n,
        rms_um: (ss_res / n as f64).sqrt(),
        max_abs_um: residuals_um.iter().map(|r| r.abs()).fold(0.0, f64::max),
        r2: if ss_tot > 0.0 {
            1.0 - ss_res / ss_tot
        } else {
            1.0
        },
        condition,
        residuals_um,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_a_hand_made_model_exactly() {
        // err = 5 + 3 (Ta - 20) + 1000 (1e-5 + 2e-6 (Tb - 22)) (P - 100)
        let mut pos = Vec::new();
        let mut ta = Vec::new();
        let mut tb = Vec::new();
        let mut err = Vec::new();
        for k in 0..6 {
            let a = 18.0 + k as f64;
            let b = 22.0 + (k as f64 * 1.7).sin() * 3.0;
            for p in [0.0, 100.0, 500.0, 1000.0] {
                pos.push(p);
                ta.push(a);
                tb.push(b);
                err.push(
                    5.0 + 3.0 * (a - 20.0) + 1000.0 * (1e-5 + 2e-6 * (b - 22.0)) * (p - 100.0),
                );
            }
        }
        let f = fit(&pos, &err, &[("a", &ta), ("b", &tb)], 100.0).unwrap();
        assert!(f.rms_um < 1e-9 && (f.r2 - 1.0).abs() < 1e-12);
        // Prediction at any temperature and position matches the generator.
        let pred = f.predict_um(700.0, &[25.0, 19.0]);
        let truth = 5.0 + 3.0 * 5.0 + 1000.0 * (1e-5 + 2e-6 * (19.0 - 22.0)) * 600.0;
        assert!((pred - truth).abs() < 1e-8, "{pred} {truth}");
        assert!((f.terms[0].k0_um_per_degc - 3.0).abs() < 1e-9);
        assert!(f.terms[1].k0_um_per_degc.abs() < 1e-9);
        assert!((f.terms[1].tan_beta_per_degc - 2e-6).abs() < 1e-15);
        assert!(f.terms[0].tan_beta_per_degc.abs() < 1e-15);
    }

    #[test]
    fn refuses_what_cannot_be_fitted() {
        let pos = [0.0, 1.0, 2.0, 0.0, 1.0, 2.0, 0.0, 1.0];
        let err = [0.0; 8];
        let t = [20.0; 8];
        assert_eq!(
            fit(&pos, &err, &[("bed", &t)], 0.0),
            Err(FitError::ConstantSensor("bed".into()))
        );
        let t2 = [20.0, 21.0, 22.0, 23.0, 24.0, 25.0, 26.0, 27.0];
        assert_eq!(
            fit(&[5.0; 8], &err, &[("bed", &t2)], 0.0),
            Err(FitError::OnePosition)
        );
        assert!(matches!(
            fit(&pos, &err, &[("a", &t2), ("b", &t2)], 0.0),
            Err(FitError::Collinear { .. })
        ));
        assert!(matches!(
            fit(&pos[..4], &err[..4], &[("a", &t2[..4])], 0.0),
            Err(FitError::TooFewRows { .. })
        ));
        assert_eq!(choose_p0_mm(&[300.0, -20.0, 50.0]), -20.0);
    }
}
