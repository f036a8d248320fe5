//! Linear least squares, solved one way for every tool: scale every column to unit
//! norm, then SVD. Temperatures in K and positions in mm differ by orders of
//! magnitude, and candidate columns can be collinear (a lag near zero, a sensor equal
//! to another); scaling keeps the SVD's tolerance meaningful and gives collinear
//! columns the minimum-norm solution instead of exploding.

use nalgebra::{DMatrix, DVector, SVD};

/// Iteration cap of the SVD. nalgebra's `svd()` iterates until convergence, which a
/// matrix holding NaN or a huge value never reaches: the command hung. A well-posed
/// design of this size converges in a few dozen sweeps; hitting the cap is a failed
/// fit, reported as [`LsqError::NoConvergence`].
pub const SVD_MAX_ITERATIONS: usize = 10_000;

/// A condition number for a message: an exactly singular design has an infinite one,
/// which a report must not print as `inf`.
pub(crate) fn condition_text(condition: f64) -> String {
    if condition.is_finite() {
        format!("{condition:.1e}")
    } else {
        "unbounded: exactly dependent".into()
    }
}

/// Why a least-squares problem has no usable solution.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum LsqError {
    /// The columns are linearly dependent beyond what the caller accepts.
    #[error(
        "the columns are linearly dependent (condition number {})",
        condition_text(*condition)
    )]
    Collinear {
        /// Condition number of the scaled design.
        condition: f64,
    },
    /// A value of the design or the response is NaN or infinite.
    #[error("the design or the response holds a value that is not finite")]
    NotFinite,
    /// The SVD did not converge within [`SVD_MAX_ITERATIONS`].
    #[error("the SVD did not converge within {SVD_MAX_ITERATIONS} iterations")]
    NoConvergence,
    /// The solution holds a value that is not finite (an overflow in the solve).
    #[error("the solution is not finite")]
    NonFiniteSolution,
}

/// The SVD with bounded iterations; `None` (not converged) becomes an error.
fn bounded_svd(m: DMatrix<f64>) -> Result<SVD<f64, nalgebra::Dyn, nalgebra::Dyn>, LsqError> {
    if m.iter().any(|v| !v.is_finite()) {
        return Err(LsqError::NotFinite);
    }
    SVD::try_new(m, true, true, f64::EPSILON, SVD_MAX_ITERATIONS).ok_or(LsqError::NoConvergence)
}

/// A fitted design: coefficients, condition, and what standard errors need.
#[derive(Debug, Clone, PartialEq)]
pub struct DesignFit {
    /// One coefficient per column, in the columns' units.
    pub beta: Vec<f64>,
    /// Condition number of the column-scaled design.
    pub condition: f64,
    /// Diagonal of `(X^T X)^-1`: a coefficient's variance is this times sigma^2.
    pub inv_gram_diag: Vec<f64>,
}

/// `1 / norm` of every column from its squared norm; 0 for a zero column, which then
/// drops out of the solution.
fn inverse_norms(p: usize, norm_sq: impl Fn(usize) -> f64) -> DVector<f64> {
    DVector::from_iterator(
        p,
        (0..p).map(|i| {
            let v = norm_sq(i);
            if v > 1e-300 {
                1.0 / v.sqrt()
            } else {
                0.0
            }
        }),
    )
}

/// Least squares of the design `x` (rows x columns) against `y`; refuses a design
/// whose scaled condition number exceeds `max_condition`.
pub fn solve_design(
    x: &DMatrix<f64>,
    y: &[f64],
    max_condition: f64,
) -> Result<DesignFit, LsqError> {
    if y.iter().any(|v| !v.is_finite()) {
        return Err(LsqError::NotFinite);
    }
    let p = x.ncols();
    let inv = inverse_norms(p, |c| x.column(c).norm_squared());
    let mut xs = x.clone();
    for (c, s) in inv.iter().enumerate() {
        xs.column_mut(c).scale_mut(*s);
    }
    let svd = bounded_svd(xs)?;
    let sv = &svd.singular_values;
    let (s_max, s_min) = (sv.max(), sv.min());
    let condition = if s_min > 0.0 {
        s_max / s_min
    } else {
        f64::INFINITY
    };
    if !condition.is_finite() || condition > max_condition {
        return Err(LsqError::Collinear { condition });
    }
    let beta_s = svd
        .solve(&DVector::from_column_slice(y), 0.0)
        .map_err(|_| LsqError::Collinear { condition })?;
    // (Xs^T Xs)^-1 = V diag(1/s^2) V^T, then unscaled.
    let v_t = svd.v_t.as_ref().ok_or(LsqError::Collinear { condition })?;
    let inv_gram_diag = (0..p)
        .map(|c| {
            let var_s: f64 = (0..sv.len()).map(|k| (v_t[(k, c)] / sv[k]).powi(2)).sum();
            var_s * inv[c] * inv[c]
        })
        .collect();
    let beta: Vec<f64> = (0..p).map(|c| beta_s[c] * inv[c]).collect();
    if beta.iter().any(|b| !b.is_finite()) {
        return Err(LsqError::NonFiniteSolution);
    }
    Ok(DesignFit {
        beta,
        condition,
        inv_gram_diag,
    })
}

/// Solves the normal equations `X^T X beta = X^T y` given as `xx` and `xy`; singular
/// values below 1e-12 of the largest are dropped (minimum-norm solution).
pub fn solve_normal(xx: &DMatrix<f64>, xy: &DVector<f64>) -> Result<DVector<f64>, LsqError> {
    if xy.iter().any(|v| !v.is_finite()) {
        return Err(LsqError::NotFinite);
    }
    let p = xy.len();
    let d = inverse_norms(p, |i| xx[(i, i)]);
    let scaled = DMatrix::from_fn(p, p, |i, j| xx[(i, j)] * d[i] * d[j]);
    let rhs = xy.component_mul(&d);
    let svd = bounded_svd(scaled)?;
    let smax = svd.singular_values.max();
    let sol = svd
        .solve(&rhs, smax * 1e-12)
        .unwrap_or_else(|_| DVector::zeros(p))
        .component_mul(&d);
    if sol.iter().any(|v| !v.is_finite()) {
        return Err(LsqError::NonFiniteSolution);
    }
    Ok(sol)
}

/// Residuals `y - X beta` of columns `cols`.
pub fn residuals(cols: &[&[f64]], y: &[f64], beta: &DVector<f64>) -> Vec<f64> {
    let mut r = y.to_vec();
    for (c, b) in cols.iter().zip(beta.iter()) {
        for (ri, ci) in r.iter_mut().zip(c.iter()) {
            *ri -= b * ci;
        }
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn design_and_normal_forms_agree() {
        // y = 2 + 3000 x on columns of very different scale.
        let n = 20;
        let x = DMatrix::from_fn(n, 2, |i, c| if c == 0 { 1.0 } else { i as f64 * 1e-3 });
        let y: Vec<f64> = (0..n).map(|i| 2.0 + 3.0 * i as f64).collect();
        let fit = solve_design(&x, &y, 1e10).expect("well posed");
        assert!((fit.beta[0] - 2.0).abs() < 1e-9 && (fit.beta[1] - 3000.0).abs() < 1e-6);
        let xx = x.transpose() * &x;
        let xy = x.transpose() * DVector::from_column_slice(&y);
        let b = solve_normal(&xx, &xy).expect("finite");
        assert!((b[0] - 2.0).abs() < 1e-6 && (b[1] - 3000.0).abs() < 1e-3);
        let cols: Vec<Vec<f64>> = (0..2)
            .map(|c| x.column(c).iter().copied().collect())
            .collect();
        let refs: Vec<&[f64]> = cols.iter().map(Vec::as_slice).collect();
        assert!(residuals(&refs, &y, &b).iter().all(|r| r.abs() < 1e-6));
    }

    #[test]
    fn collinear_columns() {
        let x = DMatrix::from_fn(5, 2, |i, _| i as f64);
        assert!(solve_design(&x, &[0.0; 5], 1e10).is_err());
        // The normal form gives the minimum-norm solution instead.
        let xx = x.transpose() * &x;
        let xy = x.transpose() * DVector::from_fn(5, |i, _| 2.0 * i as f64);
        let b = solve_normal(&xx, &xy).expect("finite");
        assert!((b[0] - 1.0).abs() < 1e-9 && (b[1] - 1.0).abs() < 1e-9);
    }

    /// Before the iteration cap and the finiteness check, a NaN or a huge value made
    /// nalgebra's SVD loop for ever (calibrate and diagnose never returned).
    #[test]
    fn non_finite_or_huge_input_is_an_error_not_a_hang() {
        let x = DMatrix::from_fn(6, 2, |i, c| if c == 0 { 1.0 } else { i as f64 });
        let mut bad = x.clone();
        bad[(3, 1)] = f64::NAN;
        assert_eq!(
            solve_design(&bad, &[0.0; 6], 1e10),
            Err(LsqError::NotFinite)
        );
        let y = [0.0, 1.0, 2.0, f64::INFINITY, 4.0, 5.0];
        assert_eq!(solve_design(&x, &y, 1e10), Err(LsqError::NotFinite));
        let mut huge = x.clone();
        huge[(3, 1)] = 1e308;
        // Finite but absurd: must return (an error or a finite fit), never hang.
        if let Ok(f) = solve_design(&huge, &[0.0, 1.0, 2.0, 3.0, 4.0, 5.0], 1e10) {
            assert!(f.beta.iter().all(|b| b.is_finite()));
        }
        let xx = DMatrix::from_row_slice(2, 2, &[1.0, f64::NAN, f64::NAN, 1.0]);
        assert_eq!(
            solve_normal(&xx, &DVector::from_element(2, 1.0)),
            Err(LsqError::NotFinite)
        );
    }
}
