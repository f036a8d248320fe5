//! Small statistics and a 1-D minimiser shared by the tools.

use std::convert::Infallible;

/// Arithmetic mean; 0 for an empty slice.
pub fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

/// Mean and sample standard deviation (n - 1).
pub fn mean_sd(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
    (mean, var.sqrt())
}

/// The values more than `factor` times their typical size and beyond `min_abs`,
/// farthest first, with that typical size: the median absolute value scaled to a
/// standard deviation (1.4826 for normal noise), which the few values it finds do not
/// move.
pub fn far_off(v: &[f64], factor: f64, min_abs: f64) -> (Vec<usize>, f64) {
    let mut abs: Vec<f64> = v.iter().map(|x| x.abs()).collect();
    abs.sort_by(f64::total_cmp);
    let typical = 1.4826 * abs.get(abs.len() / 2).copied().unwrap_or(0.0);
    let limit = (factor * typical).max(min_abs);
    let mut far: Vec<usize> = (0..v.len()).filter(|&i| v[i].abs() > limit).collect();
    far.sort_by(|&a, &b| v[b].abs().total_cmp(&v[a].abs()));
    (far, typical)
}

/// Golden-section minimisation of a unimodal `f` on `[a, b]`: the better of the two
/// inner points after `iters` steps, with its value.
pub fn golden(a: f64, b: f64, iters: usize, f: &mut dyn FnMut(f64) -> f64) -> (f64, f64) {
    let Ok(best) = try_golden(a, b, iters, &mut |x| Ok::<_, Infallible>(f(x)));
    best
}

/// [`golden`] for an `f` that can fail: stops at the first failure.
pub fn try_golden<E>(
    mut a: f64,
    mut b: f64,
    iters: usize,
    f: &mut dyn FnMut(f64) -> Result<f64, E>,
) -> Result<(f64, f64), E> {
    let r = (5f64.sqrt() - 1.0) / 2.0;
    let mut c = b - r * (b - a);
    let mut e = a + r * (b - a);
    let (mut fc, mut fe) = (f(c)?, f(e)?);
    for _ in 0..iters {
        if fc < fe {
            b = e;
            e = c;
            fe = fc;
            c = b - r * (b - a);
            fc = f(c)?;
        } else {
            a = c;
            c = e;
            fc = fe;
            e = a + r * (b - a);
            fe = f(e)?;
        }
    }
    Ok(if fc < fe { (c, fc) } else { (e, fe) })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mean_and_sd() {
        assert_eq!(mean(&[]), 0.0);
        assert_eq!(mean(&[1.0, 2.0, 6.0]), 3.0);
        assert_eq!(mean_sd(&[1.0, 2.0, 3.0]), (2.0, 1.0));
    }

    #[test]
    fn golden_stops_at_the_first_failure() {
        let (x, _) = golden(0.0, 10.0, 40, &mut |x| (x - 3.3) * (x - 3.3));
        assert!((x - 3.3).abs() < 1e-6);
        let mut calls = 0;
        let r = try_golden(0.0, 1.0, 10, &mut |x| {
            calls += 1;
            if calls > 3 {
                Err("stop")
            } else {
                Ok(x)
            }
        });
        assert_eq!(r, Err("stop"));
        assert_eq!(calls, 4);
    }
}
