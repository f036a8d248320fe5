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

/// Largest condition number of the column-scaled design a fit accepts: beyond it
/// the sensors' coefficients trade against each other and mean nothing.
pub const MAX_CONDITION: f64 = 1e10;

/// A column counts as constant when its values span less than this (um, mm or K):
/// far below any instrument's resolution.
const CONSTANT_SPAN: f64 = 1e-9;

/// A sensor whose temperatures span less than this over the data, K, is warned
/// about: its coefficients rest on changes of the order of the sensor's noise, and
/// the model extrapolates them to every temperature the machine later reaches.
pub const MIN_SENSOR_SPAN_K: f64 = 0.5;

/// The temperature terms explain the data poorly when they remove less than this
/// share of what the offsets alone leave ([`Fit::temp_r2`]); with every temperature
/// coefficient within [`SIGNIFICANT_SE`] standard errors of 0 as well, the
/// temperatures do not explain the error at all ([`Fit::undetermined`]).
pub const WEAK_R2: f64 = 0.5;

/// A coefficient within this many standard errors of 0 is not told apart from 0.
pub const SIGNIFICANT_SE: f64 = 2.0;

/// A sensor that never reads below this, degC, is in kelvin (room temperature is
/// 293 K): no sensor on a machine structure stays so hot over a run.
pub const KELVIN_LIKE_DEGC: f64 = 200.0;

/// A measured error spanning less than this, um, is below any interferometer's noise:
/// most likely `err_um` in millimetres (a factor 1000 too small).
pub const MIN_ERR_SPAN_UM: f64 = 1.0;

/// A fit with a larger |tan(beta) coefficient| is not written without
/// `--accept-weak-fit`.
pub use compgate_core::comp::{MAX_TAN_BETA_PER_K, STEEL_EXPANSION_PER_K};

/// Why a fit is impossible.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum FitError {
    /// Fewer rows than coefficients.
    #[error("{rows} rows for {coeffs} coefficients: measure more points or use fewer sensors")]
    TooFewRows { rows: usize, coeffs: usize },
    /// Columns of unequal length.
    #[error("column `{0}` has a different number of rows")]
    Length(String),
    /// The error never changes: nothing to fit, and R^2 (1 - RSS/0) is undefined.
    #[error(
        "column `err_um` is constant ({} um on every row): there is no error to fit and R^2 \
         is undefined; was the file exported without --err-channel (err_um is then 0 throughout)?",
        compgate_gateway::nc::number(*value_um)
    )]
    ConstantErr { value_um: f64 },
    /// A sensor's temperature never changes, so its coefficient is undetermined.
    #[error("column `T_{0}` is constant over the data: its coefficient cannot be fitted; drop the sensor with --sensors")]
    ConstantSensor(String),
    /// All measurements at one position.
    #[error("column `pos_mm`: every measurement is at one position: tan(beta) cannot be fitted")]
    OnePosition,
    /// Sensors move together, so their coefficients cannot be told apart.
    #[error(
        "the sensors are linearly dependent (condition number {}){}; use fewer sensors",
        crate::lsq::condition_text(*condition),
        dependent_text(sensor.as_deref())
    )]
    Collinear {
        condition: f64,
        /// The first sensor column (`T_<name>`) that moves with the position and the
        /// sensors before it, when one alone does.
        sensor: Option<String>,
    },
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

fn dependent_text(sensor: Option<&str>) -> String {
    sensor.map_or(String::new(), |s| {
        format!(": column `{s}` moves with the position and the sensors before it")
    })
}

/// One sensor's part of the fitted model.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorTerm {
    /// Sensor (channel) name, without `T_`.
    pub name: String,
    /// Temperature at which the term is zero (the data's mean, to 0.01 K), degC.
    pub ref_degc: f64,
    /// Largest minus smallest temperature of the sensor in the data, K.
    pub span_degc: f64,
    /// Smallest and largest temperature of the sensor in the data, degC.
    pub range_degc: [f64; 2],
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
    /// What the temperature terms add: the share of the residual sum of squares of
    /// the offsets alone (K0 and tan(beta) constant) that they remove (partial R^2).
    /// The total R^2 counts the geometric slope, which the offsets fit without any
    /// temperature.
    pub temp_r2: f64,
    /// Condition number of the scaled design.
    pub condition: f64,
    /// Measured minus fitted, um, per row.
    pub residuals_um: Vec<f64>,
    /// Largest minus smallest measured error, um.
    pub err_span_um: f64,
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

    /// True when the temperatures do not explain the error: the temperature terms'
    /// partial R^2 ([`Fit::temp_r2`]) below [`WEAK_R2`] and every temperature
    /// coefficient within [`SIGNIFICANT_SE`] standard errors of 0. Such a model
    /// compensates noise, and its large, undetermined coefficients add errors as soon
    /// as the temperatures move.
    pub fn undetermined(&self) -> bool {
        self.temp_r2 < WEAK_R2
            && self.terms.iter().all(|t| {
                t.k0_um_per_degc.abs() <= SIGNIFICANT_SE * t.k0_se_um_per_degc
                    && t.tan_beta_per_degc.abs() <= SIGNIFICANT_SE * t.tan_beta_se_per_degc
            })
    }

    /// Why the model is not written without `--accept-weak-fit`, one short reason
    /// each: a sensor that barely moved ([`MIN_SENSOR_SPAN_K`]), a tan(beta)
    /// coefficient no structure has ([`MAX_TAN_BETA_PER_K`]), an error that barely
    /// moved ([`MIN_ERR_SPAN_UM`]), an undetermined fit ([`Fit::undetermined`]).
    /// [`Fit::warnings`] says each at length.
    pub fn doubts(&self) -> Vec<String> {
        let mut d: Vec<String> = self
            .terms
            .iter()
            .filter(|t| t.span_degc < MIN_SENSOR_SPAN_K)
            .map(|t| format!("T_{} spans only {:.2} K", t.name, t.span_degc))
            .collect();
        d.extend(self.implausible_slopes().map(|t| {
            format!(
                "T_{}'s tan(beta) coefficient is {:.3e} /K",
                t.name, t.tan_beta_per_degc
            )
        }));
        d.extend(
            self.kelvin()
                .map(|t| format!("T_{} never reads below {:.1} degC", t.name, t.range_degc[0])),
        );
        if self.err_span_um < MIN_ERR_SPAN_UM {
            d.push(format!("err_um spans only {:.4} um", self.err_span_um));
        }
        if self.undetermined() {
            d.push(format!(
                "the temperatures do not explain the error (partial R^2 {:.3})",
                self.temp_r2
            ));
        }
        d
    }

    /// Sensors that never read below [`KELVIN_LIKE_DEGC`].
    fn kelvin(&self) -> impl Iterator<Item = &SensorTerm> {
        self.terms
            .iter()
            .filter(|t| t.range_degc[0] > KELVIN_LIKE_DEGC)
    }

    fn implausible_slopes(&self) -> impl Iterator<Item = &SensorTerm> {
        self.terms
            .iter()
            .filter(|t| t.tan_beta_per_degc.abs() > MAX_TAN_BETA_PER_K)
    }

    /// What the engineer must know before applying the model: each of
    /// [`Fit::doubts`], with its cause and remedy.
    pub fn warnings(&self) -> Vec<String> {
        let mut w: Vec<String> = self
            .terms
            .iter()
            .filter(|t| t.span_degc < MIN_SENSOR_SPAN_K)
            .map(|t| {
                format!(
                    "T_{} spans only {:.2} K in the data (less than {MIN_SENSOR_SPAN_K} K): its \
                     coefficients rest on changes near the sensor's noise, and the model \
                     extrapolates them to every temperature the machine reaches; measure over \
                     a run that heats and cools the machine, or leave the sensor out \
                     (--sensors)",
                    t.name, t.span_degc
                )
            })
            .collect();
        if self.err_span_um < MIN_ERR_SPAN_UM {
            w.push(format!(
                "err_um spans only {:.4} um over the data (less than {MIN_ERR_SPAN_UM} um, below \
                 any laser's noise): is it in mm? The column holds micrometres",
                self.err_span_um
            ));
        }
        w.extend(self.implausible_slopes().map(|t| {
            format!(
                "T_{}'s tan(beta) coefficient {:.3e} /K is {:.0} times steel's expansion \
                 ({STEEL_EXPANSION_PER_K:e} /K), beyond {MAX_TAN_BETA_PER_K:e} /K: no machine \
                 structure expands so; check the units of pos_mm (in inches the slope is 25.4 \
                 times too large) and err_um, and whether the sensor warms far less than the \
                 part that grows (a column sensor standing in for the screw: give the screw a \
                 sensor of its own)",
                t.name,
                t.tan_beta_per_degc,
                t.tan_beta_per_degc.abs() / STEEL_EXPANSION_PER_K
            )
        }));
        w.extend(self.kelvin().map(|t| {
            format!(
                "T_{} never reads below {:.1} degC over the data: no sensor on a machine \
                 structure stays so hot; in kelvin? The columns hold degC, and the gateway's \
                 channels read degC, so a model of kelvin never meets its temperatures",
                t.name, t.range_degc[0]
            )
        }));
        if self.undetermined() {
            w.push(format!(
                "the temperatures do not explain the error: beyond constant K0 and tan(beta) \
                 the temperature terms remove only {:.3} of the residual (partial R^2, below \
                 {WEAK_R2}; the total R^2 {:.3} counts the geometric slope, which needs no \
                 temperature) and every temperature coefficient is within {SIGNIFICANT_SE} \
                 standard errors of 0; the model would compensate noise and add error as the \
                 temperatures move (a sensor in the wrong place, or one that drives the error \
                 is missing: see compgate diagnose)",
                self.temp_r2, self.r2
            ));
        }
        w
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

/// Lengths and finiteness of the columns.
fn check_shape(pos_mm: &[f64], err_um: &[f64], sensors: &[(&str, &[f64])]) -> Result<(), FitError> {
    let n = pos_mm.len();
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
    Ok(())
}

fn span(v: &[f64]) -> f64 {
    let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
    hi - lo
}

/// Columns that leave a coefficient undetermined whatever the solver: a constant
/// `err_um` (first: a file without the error is the likeliest mistake), one
/// position, a constant sensor.
fn check_degenerate(
    pos_mm: &[f64],
    err_um: &[f64],
    sensors: &[(&str, &[f64])],
) -> Result<(), FitError> {
    if !err_um.is_empty() && span(err_um) < CONSTANT_SPAN {
        return Err(FitError::ConstantErr {
            value_um: err_um[0],
        });
    }
    if !pos_mm.is_empty() && span(pos_mm) < CONSTANT_SPAN {
        return Err(FitError::OnePosition);
    }
    for (name, col) in sensors {
        // The span, not the distance from the rounded reference: a sensor constant
        // at 20.004 degC once passed and surfaced as "linearly dependent".
        if span(col) < CONSTANT_SPAN {
            return Err(FitError::ConstantSensor((*name).to_string()));
        }
    }
    Ok(())
}

/// Residual sum of squares of the offsets alone, `err = a + b dx` (a straight line
/// in the position; `dx` spans more than a point, see [`check_degenerate`]).
fn offsets_rss(dx: &[f64], err_um: &[f64]) -> f64 {
    let (mx, my) = (mean(dx), mean(err_um));
    let sxx: f64 = dx.iter().map(|x| (x - mx).powi(2)).sum();
    let sxy: f64 = dx
        .iter()
        .zip(err_um)
        .map(|(x, y)| (x - mx) * (y - my))
        .sum();
    let b = sxy / sxx;
    dx.iter()
        .zip(err_um)
        .map(|(x, y)| (y - my - b * (x - mx)).powi(2))
        .sum()
}

/// Reference temperature of every sensor: its mean, to 0.01 K.
fn reference_degc(sensors: &[(&str, &[f64])]) -> Vec<f64> {
    sensors
        .iter()
        .map(|(_, col)| (mean(col) * 100.0).round() / 100.0)
        .collect()
}

/// The design: columns 1, dT_j..., dx, dx * dT_j...  (um per unit of each column).
fn design(dx: &[f64], sensors: &[(&str, &[f64])], refs: &[f64]) -> DMatrix<f64> {
    let n = dx.len();
    let m = sensors.len();
    let mut x = DMatrix::<f64>::zeros(n, 2 + 2 * m);
    for i in 0..n {
        x[(i, 0)] = 1.0;
        x[(i, 1 + m)] = dx[i];
        for (j, (_, col)) in sensors.iter().enumerate() {
            let dt = col[i] - refs[j];
            x[(i, 1 + j)] = dt;
            x[(i, 2 + m + j)] = dx[i] * dt;
        }
    }
    x
}

/// Solves the design, naming the first dependent sensor when it is collinear.
fn solve(
    dx: &[f64],
    err_um: &[f64],
    sensors: &[(&str, &[f64])],
    refs: &[f64],
) -> Result<(DMatrix<f64>, lsq::DesignFit), FitError> {
    let x = design(dx, sensors, refs);
    match lsq::solve_design(&x, err_um, MAX_CONDITION) {
        Ok(fit) => Ok((x, fit)),
        Err(lsq::LsqError::Collinear { condition }) => {
            // Only on failure: grow the sensor set until it turns dependent.
            let sensor = (1..=sensors.len())
                .find(|&k| {
                    let x = design(dx, &sensors[..k], &refs[..k]);
                    matches!(
                        lsq::solve_design(&x, &vec![0.0; dx.len()], MAX_CONDITION),
                        Err(lsq::LsqError::Collinear { .. })
                    )
                })
                .map(|k| format!("T_{}", sensors[k - 1].0));
            Err(FitError::Collinear { condition, sensor })
        }
        Err(other) => Err(FitError::Solver(other)),
    }
}

/// Refuses what [`fit`] refuses for the data itself (constant `err_um`, one position,
/// a constant sensor, sensors that move together), without fitting. `diagnose` fits
/// the same baseline in its own way and uses this so both tools refuse alike.
pub fn check_fittable(
    pos_mm: &[f64],
    err_um: &[f64],
    sensors: &[(&str, &[f64])],
    p0_mm: f64,
) -> Result<(), FitError> {
    check_shape(pos_mm, err_um, sensors)?;
    check_degenerate(pos_mm, err_um, sensors)?;
    let dx: Vec<f64> = pos_mm.iter().map(|x| x - p0_mm).collect();
    solve(&dx, err_um, sensors, &reference_degc(sensors)).map(|_| ())
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
    check_shape(pos_mm, err_um, sensors)?;
    if n < p + 1 {
        return Err(FitError::TooFewRows { rows: n, coeffs: p });
    }
    check_degenerate(pos_mm, err_um, sensors)?;
    let refs = reference_degc(sensors);
    let dx: Vec<f64> = pos_mm.iter().map(|x| x - p0_mm).collect();
    let (x, design) = solve(&dx, err_um, sensors, &refs)?;
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
    let ss_offsets = offsets_rss(&dx, err_um);
    let figures = [
        ("residual sum of squares", ss_res),
        ("total sum of squares", ss_tot),
        ("residual sum of squares of the offsets", ss_offsets),
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
        .map(|(j, (name, col))| SensorTerm {
            name: (*name).to_string(),
            ref_degc: refs[j],
            span_degc: span(col),
            range_degc: [
                col.iter().copied().fold(f64::INFINITY, f64::min),
                col.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            ],
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
        // ss_tot > 0: a constant err_um is refused above.
        r2: 1.0 - ss_res / ss_tot,
        // Offsets that fit to rounding leave the temperatures nothing to explain.
        temp_r2: if ss_offsets > 1e-12 * ss_tot {
            (1.0 - ss_res / ss_offsets).max(0.0)
        } else {
            0.0
        },
        condition,
        residuals_um,
        err_span_um: span(err_um),
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
        let err = [0.5, 1.0, 0.0, 2.0, 1.5, 0.2, 0.3, 0.9];
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
        let e = fit(&pos, &err, &[("a", &t2), ("b", &t2)], 0.0).unwrap_err();
        assert!(
            matches!(&e, FitError::Collinear { sensor: Some(s), .. } if s == "T_b"),
            "{e:?}"
        );
        assert!(e.to_string().contains("column `T_b` moves with"), "{e}");
        assert!(matches!(
            fit(&pos[..4], &err[..4], &[("a", &t2[..4])], 0.0),
            Err(FitError::TooFewRows { .. })
        ));
        assert_eq!(choose_p0_mm(&[300.0, -20.0, 50.0]), -20.0);
    }

    /// err_um 0 on every row (an export without --err-channel) fitted "exactly":
    /// R^2 1, RMS 0, an all-zero model. A constant error is refused, whatever its value.
    #[test]
    fn constant_err_is_refused() {
        let pos = [0.0, 1.0, 2.0, 0.0, 1.0, 2.0, 0.0, 1.0];
        let t = [20.0, 21.0, 22.0, 23.0, 24.0, 25.0, 26.0, 27.0];
        for (v, shown) in [(0.0, "0"), (3.5, "3.5"), (1e-300, "1e-300")] {
            let e = fit(&pos, &[v; 8], &[("a", &t)], 0.0).unwrap_err();
            assert_eq!(e, FitError::ConstantErr { value_um: v });
            let text = e.to_string();
            assert!(
                text.contains(&format!(
                    "column `err_um` is constant ({shown} um on every row)"
                )) && text.contains("--err-channel"),
                "{text}"
            );
        }
    }

    /// A sensor constant at 20.004 degC (mean rounded to 20.00 for its reference) was
    /// reported as "linearly dependent"; it is a constant column.
    #[test]
    fn a_constant_sensor_off_its_rounded_reference_is_named_constant() {
        let pos = [0.0, 1.0, 2.0, 0.0, 1.0, 2.0, 0.0, 1.0];
        let err = [0.5, 1.0, 0.0, 2.0, 1.5, 0.2, 0.3, 0.9];
        let t = [20.004; 8];
        let e = fit(&pos, &err, &[("bed", &t)], 0.0).unwrap_err();
        assert_eq!(e, FitError::ConstantSensor("bed".into()));
        assert!(
            e.to_string().starts_with("column `T_bed` is constant"),
            "{e}"
        );
    }

    /// 48 bidirectional sweeps over 9 targets; temperatures that move 1.2 K and an
    /// error swing of 70 um that has nothing to do with them, plus a geometric slope
    /// of `slope_um_per_m` and noise. Returns (pos, err, column, screw).
    fn unrelated_swing(slope_um_per_m: f64) -> [Vec<f64>; 4] {
        let mut out: [Vec<f64>; 4] = Default::default();
        let mut seed: u64 = 7;
        let mut noise = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        for sweep in 0..48 {
            let s = sweep as f64;
            let targets = (0..9).chain((0..9).rev());
            for (k, i) in targets.enumerate() {
                let pos = 250.0 * i as f64;
                let t = s * 18.0 + k as f64;
                out[0].push(pos);
                out[1].push(
                    slope_um_per_m * pos / 1000.0 + 35.0 * (t * 0.0131).sin() + 2.0 * noise(),
                );
                out[2].push(20.0 + 0.6 * (s * 0.9).sin() + 0.02 * noise());
                out[3].push(22.0 + 0.6 * (s * 2.3 + 1.0).cos() + 0.02 * noise());
            }
        }
        out
    }

    /// A geometric slope of 100 um/m made the total R^2 0.63 while the temperature
    /// coefficients fitted noise (within 0.25 standard errors of 0), and the model
    /// was written; without the slope it was refused. The temperature terms are
    /// judged by what they add over constant K0 and tan(beta), slope or none.
    #[test]
    fn a_geometric_slope_does_not_make_the_temperatures_explain_the_error() {
        for slope in [0.0, 100.0] {
            let [pos, err, col, screw] = unrelated_swing(slope);
            let f = fit(&pos, &err, &[("column", &col), ("screw", &screw)], 0.0).unwrap();
            assert!(f.temp_r2 < 0.1, "slope {slope}: {}", f.temp_r2);
            assert!(f.undetermined(), "slope {slope}: R^2 {}", f.r2);
            let w = f.warnings().join("\n");
            assert!(w.contains("partial R^2"), "{w}");
            if slope > 0.0 {
                // What the old rule looked at.
                assert!(f.r2 > WEAK_R2, "{}", f.r2);
            }
        }
        // The same data with a real column term is determined, slope or none.
        for slope in [0.0, 100.0] {
            let [pos, mut err, col, screw] = unrelated_swing(slope);
            for (e, c) in err.iter_mut().zip(&col) {
                *e += 60.0 * (c - 20.0);
            }
            let f = fit(&pos, &err, &[("column", &col), ("screw", &screw)], 0.0).unwrap();
            assert!(!f.undetermined() && f.temp_r2 > 0.5, "{}", f.temp_r2);
        }
    }

    /// `check_fittable` refuses exactly what `fit` refuses for the data, and passes
    /// what `fit` fits.
    #[test]
    fn check_fittable_agrees_with_fit() {
        let pos = [0.0, 1.0, 2.0, 0.0, 1.0, 2.0, 0.0, 1.0];
        let err = [0.5, 1.0, 0.0, 2.0, 1.5, 0.2, 0.3, 0.9];
        let t = [20.0, 21.0, 22.0, 23.0, 24.0, 25.0, 26.0, 27.0];
        let t_sin: Vec<f64> = (0..8).map(|i| 20.0 + (i as f64 * 1.7).sin()).collect();
        type Case<'a> = (&'a [f64], &'a [f64], Vec<(&'a str, &'a [f64])>);
        let cases: [Case; 5] = [
            (&pos, &err, vec![("a", &t), ("b", &t_sin)]),
            (&pos, &[0.0; 8], vec![("a", &t)]),
            (&[5.0; 8], &err, vec![("a", &t)]),
            (&pos, &err, vec![("a", &[20.0; 8])]),
            (&pos, &err, vec![("a", &t), ("b", &t)]),
        ];
        for (p, e, s) in cases {
            assert_eq!(
                check_fittable(p, e, &s, 0.0).err(),
                fit(p, e, &s, 0.0).err(),
                "{s:?}"
            );
        }
    }
}
