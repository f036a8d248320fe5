//! `compgate iso230`: ISO 230-2 evaluation of bidirectional positioning runs.
//!
//! Input is the measured-error CSV ([`compgate_core::measure`]). How rows map to the
//! standard's terms:
//!
//! - a **target position** P_i is a distinct `pos_mm` value (to 1 um);
//! - the **direction** is the row's `dir` (+1 approached upwards, -1 downwards;
//!   without the column, the direction of the last move);
//! - the **runs** j = 1..n of a target in a direction are its approaches in that
//!   direction in file order; `err_um` is the deviation x_ij = actual - target.
//!
//! The standard asks for 5 runs each way per target; fewer (but at least 2) are
//! evaluated and flagged.
//!
//! Definitions (ISO 230-2:2014, clause 3), with s the sample standard deviation:
//!
//! ```text
//! mean unidirectional deviation   xm_i+ = mean_j x_ij+          (same for -)
//! reversal value at P_i           B_i = xm_i+ - xm_i-;   B = max |B_i|;  mean B = mean B_i
//! mean bidirectional deviation    xm_i = (xm_i+ + xm_i-) / 2
//! unidirectional repeatability    R_i+ = 4 s_i+;  R+ = max R_i+     (same for -)
//! bidirectional repeatability     R_i = max(2 s_i+ + 2 s_i- + |B_i|, R_i+, R_i-);  R = max R_i
//! systematic error                E+ = max xm_i+ - min xm_i+;  E = max(xm+, xm-) - min(xm+, xm-)
//! mean bidirectional error        M = max xm_i - min xm_i
//! accuracy                        A+ = max(xm_i+ + 2 s_i+) - min(xm_i+ - 2 s_i+)
//!                                 A  = max over both directions of (xm + 2s) - min of (xm - 2s)
//! ```

mod command;
mod report;

use thiserror::Error;

use compgate_core::measure::MeasureError;

use crate::stats::mean_sd;
pub use command::{run, Iso230Args};
pub use report::report;

/// Runs the standard asks for, each way per target.
pub const RUNS_REQUIRED: usize = 5;

/// Errors of the evaluation.
#[derive(Debug, Error)]
pub enum Iso230Error {
    #[error("{0}: {1}")]
    Data(String, MeasureError),
    #[error(
        "target {pos_mm} mm has {n} run(s) in the {dir} direction; at least 2 each way are needed"
    )]
    TooFewRuns {
        pos_mm: f64,
        dir: &'static str,
        n: usize,
    },
    #[error("row {row}: direction unknown (no `dir` column and no move before it)")]
    NoDirection { row: usize },
    #[error("fewer than 2 target positions")]
    TooFewTargets,
}

/// One target position's figures, um.
#[derive(Debug, Clone, PartialEq)]
pub struct Target {
    /// Target position, mm.
    pub pos_mm: f64,
    /// Runs upwards and downwards.
    pub runs_up: usize,
    pub runs_down: usize,
    /// Mean unidirectional deviations.
    pub mean_up_um: f64,
    pub mean_down_um: f64,
    /// Standard deviations (n - 1).
    pub s_up_um: f64,
    pub s_down_um: f64,
    /// Reversal value B_i.
    pub b_um: f64,
    /// Mean bidirectional deviation.
    pub mean_um: f64,
    /// Repeatability R_i+, R_i-, R_i.
    pub r_up_um: f64,
    pub r_down_um: f64,
    pub r_um: f64,
}

/// The axis' figures, um.
#[derive(Debug, Clone, PartialEq)]
pub struct Iso230 {
    /// Per target, ascending position.
    pub targets: Vec<Target>,
    /// Accuracy A+, A-, A.
    pub a_up_um: f64,
    pub a_down_um: f64,
    pub a_um: f64,
    /// Reversal value B = max |B_i|, and the mean of B_i.
    pub b_um: f64,
    pub b_mean_um: f64,
    /// Repeatability R+, R-, R.
    pub r_up_um: f64,
    pub r_down_um: f64,
    pub r_um: f64,
    /// Systematic positioning error E+, E-, E.
    pub e_up_um: f64,
    pub e_down_um: f64,
    pub e_um: f64,
    /// Mean bidirectional positioning error M.
    pub m_um: f64,
}

fn max(it: impl Iterator<Item = f64>) -> f64 {
    it.fold(f64::NEG_INFINITY, f64::max)
}

fn min(it: impl Iterator<Item = f64>) -> f64 {
    it.fold(f64::INFINITY, f64::min)
}

/// `pos_mm` rounded to 1 um; beyond 2^52 um an f64 has no fraction left to round.
fn round_to_um(pos_mm: f64) -> f64 {
    let um = pos_mm * 1000.0;
    if um.abs() < 4.5e15 {
        um.round() / 1000.0
    } else {
        pos_mm
    }
}

/// A key ordering f64 values like `f64::total_cmp` (sign-magnitude bits made
/// two's-complement), so that every value keeps its own group.
fn total_order_key(v: f64) -> i64 {
    let bits = v.to_bits() as i64;
    bits ^ ((((bits >> 63) as u64) >> 1) as i64)
}

/// Evaluates rows of position, direction (+1/-1) and deviation (um).
pub fn evaluate(pos_mm: &[f64], dir: &[i8], err_um: &[f64]) -> Result<Iso230, Iso230Error> {
    // Group by target (to 1 um) and direction, keeping file order = run order.
    // Keyed by the target rounded to 1 um, as f64 bits in total order: an `as i64`
    // cast saturated, so a 1e308 target printed as 9223372036854776 mm.
    let mut groups: std::collections::BTreeMap<i64, (f64, Vec<f64>, Vec<f64>)> = Default::default();
    for (row, ((p, d), e)) in pos_mm.iter().zip(dir).zip(err_um).enumerate() {
        let target_mm = round_to_um(*p);
        let g =
            groups
                .entry(total_order_key(target_mm))
                .or_insert((target_mm, Vec::new(), Vec::new()));
        let g = (&mut g.1, &mut g.2);
        match d {
            1 => g.0.push(*e),
            -1 => g.1.push(*e),
            _ => return Err(Iso230Error::NoDirection { row: row + 1 }),
        }
    }
    if groups.len() < 2 {
        return Err(Iso230Error::TooFewTargets);
    }
    let mut targets = Vec::with_capacity(groups.len());
    for (pos_mm, up, down) in groups.into_values() {
        for (v, dir) in [(&up, "positive"), (&down, "negative")] {
            if v.len() < 2 {
                return Err(Iso230Error::TooFewRuns {
                    pos_mm,
                    dir,
                    n: v.len(),
                });
            }
        }
        let (mu, su) = mean_sd(&up);
        let (md, sd) = mean_sd(&down);
        let b = mu - md;
        targets.push(Target {
            pos_mm,
            runs_up: up.len(),
            runs_down: down.len(),
            mean_up_um: mu,
            mean_down_um: md,
            s_up_um: su,
            s_down_um: sd,
            b_um: b,
            mean_um: (mu + md) / 2.0,
            r_up_um: 4.0 * su,
            r_down_um: 4.0 * sd,
            r_um: (2.0 * su + 2.0 * sd + b.abs()).max(4.0 * su).max(4.0 * sd),
        });
    }
    let t = &targets;
    let both = || t.iter().flat_map(|x| [x.mean_up_um, x.mean_down_um]);
    let hi2 = || {
        t.iter().flat_map(|x| {
            [
                x.mean_up_um + 2.0 * x.s_up_um,
                x.mean_down_um + 2.0 * x.s_down_um,
            ]
        })
    };
    let lo2 = || {
        t.iter().flat_map(|x| {
            [
                x.mean_up_um - 2.0 * x.s_up_um,
                x.mean_down_um - 2.0 * x.s_down_um,
            ]
        })
    };
    Ok(Iso230 {
        a_up_um: max(t.iter().map(|x| x.mean_up_um + 2.0 * x.s_up_um))
            - min(t.iter().map(|x| x.mean_up_um - 2.0 * x.s_up_um)),
        a_down_um: max(t.iter().map(|x| x.mean_down_um + 2.0 * x.s_down_um))
            - min(t.iter().map(|x| x.mean_down_um - 2.0 * x.s_down_um)),
        a_um: max(hi2()) - min(lo2()),
        b_um: max(t.iter().map(|x| x.b_um.abs())),
        b_mean_um: t.iter().map(|x| x.b_um).sum::<f64>() / t.len() as f64,
        r_up_um: max(t.iter().map(|x| x.r_up_um)),
        r_down_um: max(t.iter().map(|x| x.r_down_um)),
        r_um: max(t.iter().map(|x| x.r_um)),
        e_up_um: max(t.iter().map(|x| x.mean_up_um)) - min(t.iter().map(|x| x.mean_up_um)),
        e_down_um: max(t.iter().map(|x| x.mean_down_um)) - min(t.iter().map(|x| x.mean_down_um)),
        e_um: max(both()) - min(both()),
        m_um: max(t.iter().map(|x| x.mean_um)) - min(t.iter().map(|x| x.mean_um)),
        targets,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A target beyond i64 um printed as 9223372036854776 mm (a saturating cast).
    #[test]
    fn a_huge_target_prints_as_itself() {
        let e = evaluate(&[1.0, 1.0, 1.0, 1.0, 1e30], &[1, 1, -1, -1, 1], &[0.0; 5])
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("target 1000000000000000000000000000000 mm has 1 run(s)"),
            "{e}"
        );
        assert_eq!(round_to_um(1e308), 1e308);
        assert_eq!(round_to_um(12.3456), 12.346);
        assert!(total_order_key(-1.0) < total_order_key(0.0));
        assert!(total_order_key(1.0) < total_order_key(1e308));
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    /// Worked by hand, 3 runs each way:
    /// P=0:   up 1,2,3 (mean 2, s 1);  down -3,-3,-3 (mean -3, s 0); B = 5, mean -0.5,
    ///        R+ 4, R- 0, R = max(2+0+5, 4, 0) = 7.
    /// P=100: up 4,4,4 (mean 4, s 0);  down 5,6,7 (mean 6, s 1);    B = -2, mean 5,
    ///        R+ 0, R- 4, R = max(0+2+2, 0, 4) = 4.
    /// Axis: B = 5, mean B = 1.5; R+ = 4, R- = 4, R = 7; E+ = 4-2 = 2, E- = 6-(-3) = 9,
    /// E = 6-(-3) = 9; M = 5-(-0.5) = 5.5;
    /// A+ = max(2+2, 4+0) - min(2-2, 4-0) = 4; A- = max(-3, 6+2) - min(-3, 6-2) = 11;
    /// A = max(4, -3, 4, 8) - min(0, -3, 4, 4) = 11.
    #[test]
    fn hand_computed_vector() {
        // Runs interleaved as on a machine: up sweep, down sweep, three times.
        let rows: [(f64, i8, f64); 12] = [
            (0.0, 1, 1.0),
            (100.0, 1, 4.0),
            (100.0, -1, 5.0),
            (0.0, -1, -3.0),
            (0.0, 1, 2.0),
            (100.0, 1, 4.0),
            (100.0, -1, 6.0),
            (0.0, -1, -3.0),
            (0.0, 1, 3.0),
            (100.0, 1, 4.0),
            (100.0, -1, 7.0),
            (0.0, -1, -3.0),
        ];
        let pos: Vec<f64> = rows.iter().map(|r| r.0).collect();
        let dir: Vec<i8> = rows.iter().map(|r| r.1).collect();
        let err: Vec<f64> = rows.iter().map(|r| r.2).collect();
        let r = evaluate(&pos, &dir, &err).unwrap();
        let t0 = &r.targets[0];
        assert!(close(t0.mean_up_um, 2.0) && close(t0.s_up_um, 1.0));
        assert!(close(t0.b_um, 5.0) && close(t0.mean_um, -0.5) && close(t0.r_um, 7.0));
        let t1 = &r.targets[1];
        assert!(close(t1.b_um, -2.0) && close(t1.r_um, 4.0) && close(t1.r_down_um, 4.0));
        assert!(close(r.b_um, 5.0) && close(r.b_mean_um, 1.5));
        assert!(close(r.r_up_um, 4.0) && close(r.r_down_um, 4.0) && close(r.r_um, 7.0));
        assert!(close(r.e_up_um, 2.0) && close(r.e_down_um, 9.0) && close(r.e_um, 9.0));
        assert!(close(r.m_um, 5.5));
        assert!(close(r.a_up_um, 4.0) && close(r.a_down_um, 11.0) && close(r.a_um, 11.0));
        let text = report(&r);
        assert!(
            text.contains("| A accuracy | 4.000 | 11.000 | 11.000 |"),
            "{text}"
        );
        assert!(text.contains("fewer than the 5 runs"), "{text}");
    }

    /// Five runs of a pure reversal error of b: B = b at every target, R = |b|,
    /// E = |b|, M = 0.
    #[test]
    fn pure_reversal() {
        let (mut pos, mut dir, mut err) = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..5 {
            for (p, d) in [
                (0.0, 1),
                (500.0, 1),
                (1000.0, 1),
                (1000.0, -1),
                (500.0, -1),
                (0.0, -1),
            ] {
                pos.push(p);
                dir.push(d);
                err.push(if d > 0 { -2.0 } else { 2.0 });
            }
        }
        let r = evaluate(&pos, &dir, &err).unwrap();
        assert!(close(r.b_um, 4.0) && close(r.b_mean_um, -4.0));
        assert!(close(r.r_um, 4.0) && close(r.r_up_um, 0.0));
        assert!(close(r.e_um, 4.0) && close(r.m_um, 0.0) && close(r.a_um, 4.0));
        assert!(!report(&r).contains("fewer than"));
    }

    #[test]
    fn reads_the_measurement_csv() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("runs.csv");
        let mut csv = String::from("t_s,pos_mm,dir,err_um,T_a\n");
        let rows = [
            (0.0, 1, 1.0),
            (100.0, 1, 4.0),
            (100.0, -1, 5.0),
            (0.0, -1, -3.0),
        ];
        let extra = [(0.0, 2.0, -3.0, 4.0, 6.0), (0.0, 3.0, -3.0, 4.0, 7.0)];
        let mut t = 0;
        for (p, d, e) in rows {
            csv.push_str(&format!("{t},{p},{d},{e},20\n"));
            t += 1;
        }
        for (_, up0, down0, up100, down100) in extra {
            for (p, d, e) in [
                (0.0, 1, up0),
                (100.0, 1, up100),
                (100.0, -1, down100),
                (0.0, -1, down0),
            ] {
                csv.push_str(&format!("{t},{p},{d},{e},20\n"));
                t += 1;
            }
        }
        std::fs::write(&path, csv).unwrap();
        let text = run(&Iso230Args { data: path.clone() }).unwrap();
        assert!(
            text.contains("| A accuracy | 4.000 | 11.000 | 11.000 |"),
            "{text}"
        );
        assert!(
            text.contains("| B reversal value (mean B) | | | 5.000 (1.500) |"),
            "{text}"
        );
        std::fs::write(&path, "t_s,pos_mm,dir,err_um,T_a\n0,0,1,1,20\n1,0,2,1,20\n").unwrap();
        let e = run(&Iso230Args { data: path }).unwrap_err().to_string();
        assert!(e.contains("runs.csv: line 3, column `dir`"), "{e}");
    }

    #[test]
    fn refuses_too_few_runs_and_unknown_direction() {
        let e = evaluate(&[0.0, 0.0, 1.0, 1.0, 1.0], &[1, -1, 1, -1, -1], &[0.0; 5]).unwrap_err();
        assert!(
            e.to_string()
                .contains("target 0 mm has 1 run(s) in the positive"),
            "{e}"
        );
        let e = evaluate(&[0.0, 1.0], &[0, 1], &[0.0; 2]).unwrap_err();
        assert!(e.to_string().contains("row 1"), "{e}");
    }
}
