//! Least squares in Gram form, per contiguous block, so that a candidate column set is
//! fitted on all data and on every blocked cross-validation fold from the same cross
//! products, without touching the rows again.

use nalgebra::{DMatrix, DVector};

pub use crate::lsq::residuals;
use crate::lsq::{solve_normal, LsqError};

/// Cross products of a column set with itself and with the response, per block.
#[derive(Debug, Clone)]
pub struct Gram {
    /// `X_k^T X_k` per block.
    pub xx: Vec<DMatrix<f64>>,
    /// `X_k^T y_k` per block.
    pub xy: Vec<DVector<f64>>,
    /// `y_k^T y_k` per block.
    pub yy: Vec<f64>,
}

/// A least-squares solution with its residual sum of squares.
#[derive(Debug, Clone)]
pub struct Solution {
    pub beta: DVector<f64>,
    pub rss: f64,
}

/// Row ranges of `k` contiguous blocks of `n` rows (fewer when `n < k`).
pub fn blocks(n: usize, k: usize) -> Vec<(usize, usize)> {
    let k = k.clamp(1, n.max(1));
    (0..k).map(|i| (i * n / k, (i + 1) * n / k)).collect()
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

impl Gram {
    /// The Gram of `cols` (each of length n) against `y`.
    pub fn new(cols: &[&[f64]], y: &[f64], blocks: &[(usize, usize)]) -> Self {
        let p = cols.len();
        let mut g = Gram {
            xx: Vec::with_capacity(blocks.len()),
            xy: Vec::with_capacity(blocks.len()),
            yy: Vec::with_capacity(blocks.len()),
        };
        for &(a, b) in blocks {
            let mut xx = DMatrix::zeros(p, p);
            let mut xy = DVector::zeros(p);
            for i in 0..p {
                for j in 0..=i {
                    let v = dot(&cols[i][a..b], &cols[j][a..b]);
                    xx[(i, j)] = v;
                    xx[(j, i)] = v;
                }
                xy[i] = dot(&cols[i][a..b], &y[a..b]);
            }
            g.xx.push(xx);
            g.xy.push(xy);
            g.yy.push(dot(&y[a..b], &y[a..b]));
        }
        g
    }

    /// The Gram of `base ++ extra`, computing only the new cross products.
    pub fn extend(
        &self,
        base: &[&[f64]],
        extra: &[&[f64]],
        y: &[f64],
        blocks: &[(usize, usize)],
    ) -> Self {
        let p = base.len();
        let q = extra.len();
        let mut g = Gram {
            xx: Vec::with_capacity(blocks.len()),
            xy: Vec::with_capacity(blocks.len()),
            yy: self.yy.clone(),
        };
        for (k, &(a, b)) in blocks.iter().enumerate() {
            let mut xx = DMatrix::zeros(p + q, p + q);
            xx.view_mut((0, 0), (p, p)).copy_from(&self.xx[k]);
            let mut xy = DVector::zeros(p + q);
            xy.rows_mut(0, p).copy_from(&self.xy[k]);
            for (j, e) in extra.iter().enumerate() {
                let e = &e[a..b];
                for (i, c) in base.iter().enumerate() {
                    let v = dot(&c[a..b], e);
                    xx[(i, p + j)] = v;
                    xx[(p + j, i)] = v;
                }
                for (i, f) in extra.iter().enumerate().take(j + 1) {
                    let v = dot(&f[a..b], e);
                    xx[(p + i, p + j)] = v;
                    xx[(p + j, p + i)] = v;
                }
                xy[p + j] = dot(e, &y[a..b]);
            }
            g.xx.push(xx);
            g.xy.push(xy);
        }
        g
    }

    fn total(&self, skip: Option<usize>) -> (DMatrix<f64>, DVector<f64>, f64) {
        let p = self.xy[0].len();
        let mut xx = DMatrix::zeros(p, p);
        let mut xy = DVector::zeros(p);
        let mut yy = 0.0;
        for k in 0..self.xx.len() {
            if Some(k) != skip {
                xx += &self.xx[k];
                xy += &self.xy[k];
                yy += self.yy[k];
            }
        }
        (xx, xy, yy)
    }

    /// The fit on all rows; an error if the solver fails (no convergence, values
    /// not finite). What is reported or written comes from here.
    pub fn try_solve(&self) -> Result<Solution, LsqError> {
        let (xx, xy, yy) = self.total(None);
        let beta = solve_normal(&xx, &xy)?;
        let rss = sse(&xx, &xy, yy, &beta);
        if !rss.is_finite() {
            return Err(LsqError::NonFiniteSolution);
        }
        Ok(Solution { beta, rss })
    }

    /// The fit on all rows for a search: a candidate the solver fails on gets an
    /// infinite residual sum of squares, so it is never chosen.
    pub fn solve(&self) -> Solution {
        self.try_solve().unwrap_or_else(|_| Solution {
            beta: DVector::zeros(self.xy[0].len()),
            rss: f64::INFINITY,
        })
    }

    /// Blocked cross-validation: mean squared held-out error, each block predicted by
    /// the fit on all the other blocks.
    pub fn cv_mse(&self, n: usize) -> f64 {
        if self.xx.len() < 2 {
            return f64::NAN;
        }
        let mut total = 0.0;
        for k in 0..self.xx.len() {
            let (xx, xy, _) = self.total(Some(k));
            // A fold the solver fails on makes the candidate unusable (never chosen).
            let Ok(beta) = solve_normal(&xx, &xy) else {
                return f64::INFINITY;
            };
            total += sse(&self.xx[k], &self.xy[k], self.yy[k], &beta);
        }
        total / n as f64
    }
}

/// `y'y - 2 b'X'y + b'X'X b`, never negative.
fn sse(xx: &DMatrix<f64>, xy: &DVector<f64>, yy: f64, beta: &DVector<f64>) -> f64 {
    (yy - 2.0 * beta.dot(xy) + (xx * beta).dot(beta)).max(0.0)
}

/// Lag-1 autocorrelation of a residual series, clamped to [0, 0.99]: negative
/// correlation is not credited as extra information.
pub fn ar1(r: &[f64]) -> f64 {
    let den: f64 = r.iter().map(|x| x * x).sum();
    if den <= 0.0 || r.len() < 3 {
        return 0.0;
    }
    let num: f64 = r.windows(2).map(|w| w[0] * w[1]).sum();
    (num / den).clamp(0.0, 0.99)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exact_fit_and_cv() {
        let n = 100;
        let x: Vec<f64> = (0..n).map(|i| i as f64 / 10.0).collect();
        let one = vec![1.0; n];
        let y: Vec<f64> = x.iter().map(|v| 2.0 + 3.0 * v).collect();
        let b = blocks(n, 5);
        let g = Gram::new(&[&one, &x], &y, &b);
        let s = g.solve();
        assert!((s.beta[0] - 2.0).abs() < 1e-9 && (s.beta[1] - 3.0).abs() < 1e-9);
        assert!(s.rss < 1e-9);
        assert!(g.cv_mse(n) < 1e-9);
        // Extending by a collinear column keeps the fit.
        let x2: Vec<f64> = x.iter().map(|v| 2.0 * v).collect();
        let g2 = g.extend(&[&one, &x], &[&x2], &y, &b);
        assert!(g2.solve().rss < 1e-9);
        let r = residuals(&[&one, &x, &x2], &y, &g2.solve().beta);
        assert!(r.iter().all(|v| v.abs() < 1e-6));
    }

    #[test]
    fn ar1_of_a_smooth_series_is_high() {
        let s: Vec<f64> = (0..200).map(|i| (i as f64 / 20.0).sin()).collect();
        assert!(ar1(&s) > 0.9);
        let alt: Vec<f64> = (0..200)
            .map(|i| if i % 2 == 0 { 1.0 } else { -1.0 })
            .collect();
        assert_eq!(ar1(&alt), 0.0);
    }
}
