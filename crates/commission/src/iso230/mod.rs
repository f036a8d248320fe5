//! `compgate iso230`: ISO 230-2 evaluation of bidirectional positioning runs.
//!
//! Input is the measured-error CSV ([`compgate_core::measure`]). How rows map to the
//! standard's terms:
//!
//! - a **target position** P_i is a nominal position: either one of a given target
//!   list, each row taken by the nearest listed target within the tolerance, or a
//!   cluster of `pos_mm` values (sorted positions whose neighbours lie within the
//!   tolerance, default [`DEFAULT_TOLERANCE_MM`], form one target; its nominal is
//!   their mean). Recorded positions jitter by a few tenths of a micrometre, so a
//!   target is not an exact value; a cluster wider than the tolerance is refused
//!   rather than guessed at;
//! - the **direction** is the row's `dir` (+1 approached upwards, -1 downwards),
//!   a required column here: the positions alone cannot tell it, because a target at
//!   a reversal is approached from both sides in a row and the overshoot between the
//!   two rows is not recorded (the same position twice, no move in between);
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

use std::path::Path;

use thiserror::Error;

use compgate_core::measure::MeasureError;

use crate::stats::mean_sd;
pub use command::Iso230Args;
pub use report::report;

/// Runs the standard asks for, each way per target.
pub const RUNS_REQUIRED: usize = 5;

/// How far a recorded position may lie from its target by default, mm: well above
/// the jitter of a recorded commanded position (tenths of a micrometre), well below
/// any target spacing ISO 230-2 uses (millimetres and more).
pub const DEFAULT_TOLERANCE_MM: f64 = 0.01;

/// How rows are grouped into target positions.
#[derive(Debug, Clone, PartialEq)]
pub struct Grouping {
    /// The nominal targets, mm; empty: found by clustering.
    pub targets_mm: Vec<f64>,
    /// How far a row's position may lie from its target (or, clustering, from its
    /// neighbour), mm.
    pub tolerance_mm: f64,
}

impl Default for Grouping {
    fn default() -> Self {
        Self {
            targets_mm: Vec::new(),
            tolerance_mm: DEFAULT_TOLERANCE_MM,
        }
    }
}

/// Errors of the evaluation. Rows are reported as the lines of the measurement CSV
/// they come from (the header is line 1, the first row line 2).
#[derive(Debug, Error)]
pub enum Iso230Error {
    #[error("{0}: {1}")]
    Data(String, MeasureError),
    /// The measurement file cannot be opened.
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    /// An error of the evaluation, with the file evaluated.
    #[error("{path}: {source}")]
    InFile {
        path: String,
        source: Box<Iso230Error>,
    },
    #[error(
        "target {pos_mm} mm (line {line} first) has {n} run(s) in the {dir} direction{more}; \
         ISO 230-2 approaches every target from both sides, at least 2 runs each way (an \
         end target too: the test cycle overshoots it){hint}"
    )]
    TooFewRuns {
        pos_mm: f64,
        /// The file line of its first row.
        line: usize,
        dir: &'static str,
        n: usize,
        /// ", as have N other targets", or empty.
        more: String,
        /// What to check when the runs may have been split by a tolerance too tight,
        /// or empty.
        hint: String,
    },
    /// A target of `--targets` no row was taken by.
    #[error(
        "target {target_mm} mm of --targets: no row lies within the tolerance of \
         {tolerance_mm} mm of it (the list's other targets: {others}); leave it out or \
         check the list"
    )]
    NoRows {
        target_mm: f64,
        tolerance_mm: f64,
        others: String,
    },
    /// A row without a direction: the reader gives 0 only when the file has no `dir`
    /// column, and then on its first row at the latest.
    #[error(
        "line {line}, column `dir`: the approach direction is unknown: iso230 requires a \
         `dir` column (+1 approached upwards, -1 downwards); the positions alone cannot \
         tell the two approaches of a target at a reversal apart"
    )]
    NoDirection { line: usize },
    /// Fewer than 2 targets: `found` says where the rows are (or that there are
    /// none); `hint` says what may have merged the targets, or is empty.
    #[error("{found}; ISO 230-2 evaluates an axis at 2 targets or more{hint}")]
    TooFewTargets { found: String, hint: String },
    #[error(
        "line {line}, column `pos_mm`: position {pos_mm} mm is {off_mm:.6} mm from the \
         nearest target {target_mm} mm, beyond the tolerance of {tolerance_mm} mm \
         (--target-tolerance-mm)"
    )]
    OffTarget {
        line: usize,
        pos_mm: f64,
        target_mm: f64,
        off_mm: f64,
        tolerance_mm: f64,
    },
    #[error(
        "positions {from_mm} mm to {to_mm} mm chain together within the tolerance of \
         {tolerance_mm} mm but span more than it: give the targets (--targets), or a \
         --target-tolerance-mm below the targets' spacing, or above this span if these \
         positions are one target (is pos_mm the actual position, not the target?)"
    )]
    AmbiguousTarget {
        from_mm: f64,
        to_mm: f64,
        tolerance_mm: f64,
    },
    #[error("target tolerance {0} mm: give a finite value above 0")]
    BadTolerance(f64),
    #[error(transparent)]
    Arg(#[from] crate::args::ArgError),
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

/// The CSV line of the 0-based data row `row`: its line in `lines` (from the
/// reader, which skips blank lines), else as if rows followed the header line by
/// line.
fn csv_line(lines: &[u64], row: usize) -> usize {
    lines.get(row).map_or(row + 2, |&l| l as usize)
}

/// Runs the command; an error of the evaluation names the file evaluated.
pub fn run(args: &Iso230Args) -> Result<String, Iso230Error> {
    command::run(args).map_err(|e| in_file(e, &args.data))
}

/// Adds the file to an error that does not name it (the reader's errors do; a flag's
/// error is not about the file).
fn in_file(e: Iso230Error, path: &Path) -> Iso230Error {
    match e {
        Iso230Error::Data(..)
        | Iso230Error::Io { .. }
        | Iso230Error::Arg(_)
        | Iso230Error::InFile { .. } => e,
        other => Iso230Error::InFile {
            path: path.display().to_string(),
            source: Box::new(other),
        },
    }
}

fn max(it: impl Iterator<Item = f64>) -> f64 {
    it.fold(f64::NEG_INFINITY, f64::max)
}

fn min(it: impl Iterator<Item = f64>) -> f64 {
    it.fold(f64::INFINITY, f64::min)
}

/// The target index of every row, and the targets' nominal positions (ascending).
fn assign_targets(
    pos_mm: &[f64],
    g: &Grouping,
    lines: &[u64],
) -> Result<(Vec<usize>, Vec<f64>), Iso230Error> {
    let tol = g.tolerance_mm;
    if !(tol.is_finite() && tol > 0.0) {
        return Err(Iso230Error::BadTolerance(tol));
    }
    if !g.targets_mm.is_empty() {
        let mut targets = g.targets_mm.clone();
        targets.sort_by(f64::total_cmp);
        targets.dedup();
        let index = pos_mm
            .iter()
            .enumerate()
            .map(|(row, &p)| {
                let (i, off) = targets
                    .iter()
                    .map(|t| (p - t).abs())
                    .enumerate()
                    .min_by(|a, b| a.1.total_cmp(&b.1))
                    .unwrap_or((0, f64::INFINITY));
                if off <= tol {
                    Ok(i)
                } else {
                    Err(Iso230Error::OffTarget {
                        line: csv_line(lines, row),
                        pos_mm: p,
                        target_mm: targets.get(i).copied().unwrap_or(f64::NAN),
                        off_mm: off,
                        tolerance_mm: tol,
                    })
                }
            })
            .collect::<Result<_, _>>()?;
        return Ok((index, targets));
    }
    let mut order: Vec<usize> = (0..pos_mm.len()).collect();
    order.sort_by(|&a, &b| pos_mm[a].total_cmp(&pos_mm[b]));
    let mut index = vec![0; pos_mm.len()];
    let mut nominal = Vec::new();
    let mut cluster: Vec<usize> = Vec::new();
    let mut close = |cluster: &mut Vec<usize>, nominal: &mut Vec<f64>| {
        let (from, to) = (pos_mm[cluster[0]], pos_mm[cluster[cluster.len() - 1]]);
        if to - from > tol {
            return Err(Iso230Error::AmbiguousTarget {
                from_mm: from,
                to_mm: to,
                tolerance_mm: tol,
            });
        }
        for &r in cluster.iter() {
            index[r] = nominal.len();
        }
        let mean = cluster.iter().map(|&r| pos_mm[r]).sum::<f64>() / cluster.len() as f64;
        // An exact target stays exact (no 1e-13 residue from the mean's rounding); a
        // jittered one is known to a tenth of the tolerance, and the report showed
        // 100.00000000000001 mm for a target recorded within +-0.5 um of 100.
        nominal.push(if from == to {
            from
        } else {
            // Divided by a power of ten, so 493.4 prints as such.
            let per_mm = 10f64.powf(-(tol / 10.0).log10().floor());
            (mean * per_mm).round() / per_mm + 0.0
        });
        cluster.clear();
        Ok(())
    };
    for &r in &order {
        if let Some(&last) = cluster.last() {
            if pos_mm[r] - pos_mm[last] > tol {
                close(&mut cluster, &mut nominal)?;
            }
        }
        cluster.push(r);
    }
    if !cluster.is_empty() {
        close(&mut cluster, &mut nominal)?;
    }
    Ok((index, nominal))
}

/// Per target: its nominal position, its deviations upwards and downwards.
type Groups = [(f64, Vec<f64>, Vec<f64>)];

/// Refuses a listed target no row was taken by, and a file at one target.
fn check_targets(groups: &Groups, pos_mm: &[f64], g: &Grouping) -> Result<(), Iso230Error> {
    let list = |skip: f64| {
        let others: Vec<String> = groups
            .iter()
            .filter(|t| t.0 != skip)
            .map(|t| format!("{} mm", t.0))
            .collect();
        others.join(", ")
    };
    if let Some(empty) = groups.iter().find(|t| t.1.is_empty() && t.2.is_empty()) {
        return Err(Iso230Error::NoRows {
            target_mm: empty.0,
            tolerance_mm: g.tolerance_mm,
            others: list(empty.0),
        });
    }
    if groups.len() >= 2 {
        return Ok(());
    }
    let Some((at_mm, up, down)) = groups.first() else {
        return Err(Iso230Error::TooFewTargets {
            found: "the file has no rows".into(),
            hint: String::new(),
        });
    };
    let span_mm = max(pos_mm.iter().copied()) - min(pos_mm.iter().copied());
    let hint = if !g.targets_mm.is_empty() {
        ": --targets lists one".to_string()
    } else if span_mm > 0.0 {
        format!(
            ": the positions span {span_mm} mm, and clustering within the tolerance of {} mm \
             made them one target; give the targets (--targets) or a smaller \
             --target-tolerance-mm",
            g.tolerance_mm
        )
    } else {
        String::new()
    };
    Err(Iso230Error::TooFewTargets {
        found: format!(
            "every row is at one target position, {at_mm} mm ({} rows)",
            up.len() + down.len()
        ),
        hint,
    })
}

/// Refuses a target with fewer than 2 runs either way: names the first, counts the
/// others, and points at the tolerance when clustering may have split a target.
fn check_runs(
    groups: &Groups,
    index: &[usize],
    nominal: &[f64],
    g: &Grouping,
    lines: &[u64],
) -> Result<(), Iso230Error> {
    let short: Vec<(usize, &'static str, usize)> = groups
        .iter()
        .enumerate()
        .flat_map(|(i, (_, up, down))| [(i, "positive", up.len()), (i, "negative", down.len())])
        .filter(|&(_, _, n)| n < 2)
        .collect();
    let Some(&(i, dir, n)) = short.first() else {
        return Ok(());
    };
    let mut others: Vec<usize> = short.iter().map(|s| s.0).filter(|&j| j != i).collect();
    others.dedup();
    let more = match others.len() {
        0 => String::new(),
        1 => ", as has 1 other target".into(),
        k => format!(", as have {k} other targets"),
    };
    let tol = g.tolerance_mm;
    // Clustered targets lie more than the tolerance apart; barely more, and the
    // positions of one target may jitter more than the tolerance.
    let neighbour = [i.wrapping_sub(1), i + 1]
        .into_iter()
        .filter_map(|j| nominal.get(j))
        .map(|&p| (p, (p - nominal[i]).abs()))
        .min_by(|a, b| a.1.total_cmp(&b.1));
    let hint = match neighbour {
        Some((p, d)) if g.targets_mm.is_empty() && d <= 5.0 * tol => format!(
            "; target {p} mm is only {d:.6} mm away: if the two are one target, its \
             positions jitter more than the tolerance of {tol} mm, and a larger \
             --target-tolerance-mm joins them"
        ),
        _ => String::new(),
    };
    let first = index.iter().position(|&t| t == i).unwrap_or(0);
    Err(Iso230Error::TooFewRuns {
        pos_mm: groups[i].0,
        line: csv_line(lines, first),
        dir,
        n,
        more,
        hint,
    })
}

/// Evaluates rows of position, direction (+1/-1) and deviation (um), targets found by
/// clustering with the default tolerance.
pub fn evaluate(pos_mm: &[f64], dir: &[i8], err_um: &[f64]) -> Result<Iso230, Iso230Error> {
    evaluate_grouped(pos_mm, dir, err_um, &Grouping::default())
}

/// Evaluates rows of position, direction (+1/-1) and deviation (um), grouped into
/// targets as `grouping` says.
pub fn evaluate_grouped(
    pos_mm: &[f64],
    dir: &[i8],
    err_um: &[f64],
    grouping: &Grouping,
) -> Result<Iso230, Iso230Error> {
    evaluate_lines(pos_mm, dir, err_um, grouping, &[])
}

/// [`evaluate_grouped`] on rows read from a file, `lines` their file lines
/// ([`compgate_core::measure::Measurements::read_positions_path`]): an error names
/// the row's own line.
pub fn evaluate_lines(
    pos_mm: &[f64],
    dir: &[i8],
    err_um: &[f64],
    grouping: &Grouping,
    lines: &[u64],
) -> Result<Iso230, Iso230Error> {
    // First: a file without `dir` fails on its first row whatever its positions.
    if let Some(row) = dir.iter().position(|d| !matches!(d, 1 | -1)) {
        return Err(Iso230Error::NoDirection {
            line: csv_line(lines, row),
        });
    }
    let (index, nominal) = assign_targets(pos_mm, grouping, lines)?;
    // Per target and direction, in file order = run order.
    let mut groups: Vec<(f64, Vec<f64>, Vec<f64>)> = nominal
        .iter()
        .map(|&p| (p, Vec::new(), Vec::new()))
        .collect();
    for ((&i, &d), e) in index.iter().zip(dir).zip(err_um) {
        let g = &mut groups[i];
        if d > 0 {
            g.1.push(*e);
        } else {
            g.2.push(*e);
        }
    }
    check_targets(&groups, pos_mm, grouping)?;
    check_runs(&groups, &index, &nominal, grouping, lines)?;
    let mut targets = Vec::with_capacity(groups.len());
    for (pos_mm, up, down) in groups {
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
            e.starts_with("target 1000000000000000000000000000000 mm (line 6 first) has 1 run(s)"),
            "{e}"
        );
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
            text.contains("| A accuracy of positioning | 4.000 | 11.000 | 11.000 |"),
            "{text}"
        );
        assert!(
            text.contains(
                "fewer than the 5 runs each way ISO 230-2 asks for at 0 mm (3/3), 100 mm (3/3)"
            ),
            "{text}"
        );
        assert!(!text.contains("differ in number"), "{text}");
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
        assert!(!report(&r).contains("differ in number"));
        // Two more upward runs at 500 mm: evaluated, and the report asks about them.
        pos.extend([500.0, 500.0]);
        dir.extend([1, 1]);
        err.extend([-2.0, -2.0]);
        let text = report(&evaluate(&pos, &dir, &err).unwrap());
        assert!(
            text.contains("runs upwards and downwards differ in number at 500 mm (7/5)"),
            "{text}"
        );
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
        let text = run(&Iso230Args {
            data: path.clone(),
            targets: Vec::new(),
            target_tolerance_mm: DEFAULT_TOLERANCE_MM,
        })
        .unwrap();
        assert!(
            text.contains("| A accuracy of positioning | 4.000 | 11.000 | 11.000 |"),
            "{text}"
        );
        assert!(
            text.contains("| B reversal value (mean reversal value) | | | 5.000 (1.500) |"),
            "{text}"
        );
        std::fs::write(&path, "t_s,pos_mm,dir,err_um,T_a\n0,0,1,1,20\n1,0,2,1,20\n").unwrap();
        let e = run(&Iso230Args {
            data: path,
            targets: Vec::new(),
            target_tolerance_mm: DEFAULT_TOLERANCE_MM,
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("runs.csv: line 3, column `dir`"), "{e}");
    }

    /// Five bidirectional runs over targets 0, 600.0005 and 1200 mm, every recorded
    /// position off its target by a jitter of up to `jitter_um`.
    fn jittered_runs(jitter_um: f64) -> (Vec<f64>, Vec<i8>, Vec<f64>) {
        let (mut pos, mut dir, mut err) = (Vec::new(), Vec::new(), Vec::new());
        let mut k = 0.0_f64;
        for run in 0..5 {
            for (p, d) in [
                (0.0, 1),
                (600.0005, 1),
                (1200.0, 1),
                (1200.0, -1),
                (600.0005, -1),
                (0.0, -1),
            ] {
                // A deterministic spread over [-jitter, +jitter].
                k += 1.0;
                let j_mm = jitter_um * 1e-3 * (k * 0.7).sin();
                pos.push(p + j_mm);
                dir.push(d);
                err.push(f64::from(d) * 1.5 + f64::from(run));
            }
        }
        (pos, dir, err)
    }

    /// Rounding to 1 um split 600.0005 mm with +-0.1 um jitter into two targets of one
    /// run each, and refused +-2 um jitter.
    #[test]
    fn jittered_positions_group_by_nominal_target() {
        for jitter_um in [0.0, 0.1, 2.0] {
            let (pos, dir, err) = jittered_runs(jitter_um);
            let r = evaluate(&pos, &dir, &err).unwrap_or_else(|e| panic!("{jitter_um} um: {e}"));
            assert_eq!(r.targets.len(), 3, "{jitter_um} um");
            for t in &r.targets {
                assert_eq!((t.runs_up, t.runs_down), (5, 5), "{jitter_um} um");
            }
            assert!(
                (r.targets[1].pos_mm - 600.0005).abs() < 2e-3,
                "{:?}",
                r.targets[1]
            );
            // The runs differ by 1 um each: s = sqrt(2.5), reversal 3 um everywhere.
            assert!(close(r.b_um, 3.0) && close(r.targets[0].s_up_um, 2.5_f64.sqrt()));
            let listed = Grouping {
                targets_mm: vec![1200.0, 0.0, 600.0005],
                tolerance_mm: 0.005,
            };
            assert_eq!(
                evaluate_grouped(&pos, &dir, &err, &listed).unwrap().targets,
                r.targets
                    .iter()
                    .enumerate()
                    .map(|(i, t)| Target {
                        pos_mm: [0.0, 600.0005, 1200.0][i],
                        ..t.clone()
                    })
                    .collect::<Vec<_>>()
            );
        }
    }

    #[test]
    fn refuses_rows_off_every_target_and_chained_clusters() {
        let (pos, dir, err) = jittered_runs(2.0);
        let listed = Grouping {
            targets_mm: vec![0.0, 600.0, 1200.0],
            tolerance_mm: 0.0001,
        };
        let e = evaluate_grouped(&pos, &dir, &err, &listed)
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("line 2, column `pos_mm`: position")
                && e.contains("beyond the tolerance of 0.0001 mm"),
            "{e}"
        );
        // 0, 0.008, 0.016 mm: each within 0.01 mm of the next, 0.016 mm end to end.
        let e = evaluate(&[0.0, 0.008, 0.016, 5.0], &[1, 1, 1, 1], &[0.0; 4])
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("positions 0 mm to 0.016 mm chain together"),
            "{e}"
        );
        let bad = Grouping {
            targets_mm: vec![],
            tolerance_mm: f64::NAN,
        };
        assert!(matches!(
            evaluate_grouped(&pos, &dir, &err, &bad),
            Err(Iso230Error::BadTolerance(_))
        ));
    }

    /// Positions recorded within +-0.5 um of their targets made the report's target
    /// column 100.00000000000001 and -0.00015999999999999999.
    #[test]
    fn a_jittered_target_is_reported_to_a_tenth_of_the_tolerance() {
        let pos = [
            -0.0004, 0.0001, 493.4004, 493.3999, 0.0002, 0.0001, 493.4, 493.3997,
        ];
        let r = evaluate(&pos, &[1, 1, 1, 1, -1, -1, -1, -1], &[0.0; 8]).unwrap();
        let at: Vec<String> = r.targets.iter().map(|t| t.pos_mm.to_string()).collect();
        assert_eq!(at, ["0", "493.4"]);
    }

    /// A laser's deviations in mm in the err_um column gave A = 0.015 um without a word.
    #[test]
    fn deviations_in_millimetres_are_warned_of() {
        let pos = [0.0, 0.0, 0.0, 0.0, 100.0, 100.0, 100.0, 100.0];
        let dir = [1, 1, -1, -1, 1, 1, -1, -1];
        let mm = [
            0.002, 0.0021, -0.002, -0.0019, 0.003, 0.0031, -0.001, -0.0012,
        ];
        let warned =
            |err: &[f64]| report(&evaluate(&pos, &dir, err).unwrap()).contains("is err_um in mm?");
        assert!(warned(&mm));
        let um: Vec<f64> = mm.iter().map(|e| e * 1000.0).collect();
        assert!(!warned(&um));
    }

    #[test]
    fn refuses_too_few_runs_and_unknown_direction() {
        let e = evaluate(&[0.0, 0.0, 1.0, 1.0, 1.0], &[1, -1, 1, -1, -1], &[0.0; 5]).unwrap_err();
        assert!(
            e.to_string().contains(
                "target 0 mm (line 2 first) has 1 run(s) in the positive direction, as has 1 \
                 other target; "
            ),
            "{e}"
        );
        assert!(!e.to_string().contains("jitter"), "{e}");
        let e = evaluate(&[0.0, 1.0, 1.0], &[1, 1, 0], &[0.0; 3]).unwrap_err();
        assert!(e.to_string().starts_with("line 4, column `dir`"), "{e}");
    }

    fn run_file(path: &std::path::Path, targets: Vec<f64>) -> Result<String, Iso230Error> {
        run(&Iso230Args {
            data: path.to_path_buf(),
            targets,
            target_tolerance_mm: DEFAULT_TOLERANCE_MM,
        })
    }

    /// Without `dir` every file failed with "row 1: direction unknown", a data row
    /// and no file, while the help called `dir` "recommended". The direction cannot be
    /// derived at a reversal (the same position twice, in the two directions), so the
    /// column is required, and the refusal says so with file, line and column.
    #[test]
    fn a_file_without_dir_is_refused_saying_the_column_is_required() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("nodir.csv");
        // Two runs of an up-down cycle over 0 and 100 mm: 100 is approached up and
        // then down with no move recorded in between.
        let mut csv = String::from("t_s,pos_mm,err_um,T_a\n");
        for (t, p) in [0.0, 100.0, 100.0, 0.0, 0.0, 100.0, 100.0, 0.0]
            .iter()
            .enumerate()
        {
            csv.push_str(&format!("{t},{p},{},20\n", t % 3));
        }
        std::fs::write(&path, &csv).unwrap();
        let e = run_file(&path, vec![]).unwrap_err().to_string();
        assert!(
            e.contains(
                "nodir.csv: line 2, column `dir`: the approach direction is unknown: \
                 iso230 requires a `dir` column"
            ),
            "{e}"
        );
    }

    /// "row 3: position ... beyond the tolerance" gave a data-row number and no file.
    #[test]
    fn evaluation_errors_name_the_file_and_the_csv_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("off.csv");
        std::fs::write(
            &path,
            "t_s,pos_mm,dir,err_um,T_a\n0,0,1,1,20\n1,100,1,1,20\n2,100.5,-1,1,20\n",
        )
        .unwrap();
        let e = run_file(&path, vec![0.0, 100.0]).unwrap_err().to_string();
        assert!(
            e.contains("off.csv: line 4, column `pos_mm`: position 100.5 mm is 0.500000 mm"),
            "{e}"
        );
        // Errors that are not about one row name the file too.
        let e = run_file(&path, vec![]).unwrap_err().to_string();
        assert!(
            e.contains("off.csv: target 0 mm (line 2 first) has 1 run(s)"),
            "{e}"
        );
    }

    /// With blank lines in the file, the line was counted from the header row by
    /// row: line 19 for a value on line 21.
    #[test]
    fn evaluation_errors_name_the_line_across_blank_lines() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("blank.csv");
        std::fs::write(
            &path,
            "t_s,pos_mm,dir,err_um,T_a\n0,0,1,1,20\n\n\n1,100,1,1,20\n\n2,100.5,-1,1,20\n",
        )
        .unwrap();
        let e = run_file(&path, vec![0.0, 100.0]).unwrap_err().to_string();
        assert!(e.contains("blank.csv: line 7, column `pos_mm`"), "{e}");
        std::fs::write(&path, "t_s,pos_mm,err_um,T_a\n\n\n0,0,1,20\n1,100,1,20\n").unwrap();
        let e = run_file(&path, vec![]).unwrap_err().to_string();
        assert!(e.contains("blank.csv: line 4, column `dir`"), "{e}");
    }

    /// A target whose positions jitter 3 um, clustered with a tolerance of 1 um,
    /// became two targets of one run each way, and the error said nothing of the
    /// tolerance.
    #[test]
    fn a_target_split_by_a_tight_tolerance_points_at_the_tolerance() {
        let pos = [0.0, 0.0, 0.003, 0.003, 100.0, 100.0, 100.0, 100.0];
        let dir = [1, -1, 1, -1, 1, -1, 1, -1];
        let tight = Grouping {
            targets_mm: vec![],
            tolerance_mm: 0.001,
        };
        let e = evaluate_grouped(&pos, &dir, &[0.0; 8], &tight)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("has 1 run(s) in the positive direction, as has 1 other target;")
                && e.ends_with(
                    "target 0.003 mm is only 0.003000 mm away: if the two are one target, its \
                     positions jitter more than the tolerance of 0.001 mm, and a larger \
                     --target-tolerance-mm joins them"
                ),
            "{e}"
        );
        // The default tolerance joins them.
        assert_eq!(evaluate(&pos, &dir, &[0.0; 8]).unwrap().targets.len(), 2);
    }

    /// A --targets entry no row is near said "0 run(s) in the positive direction".
    #[test]
    fn a_listed_target_without_rows_is_named() {
        let (pos, dir, err) = jittered_runs(0.1);
        let listed = Grouping {
            targets_mm: vec![0.0, 600.0005, 1200.0, 1800.0],
            tolerance_mm: DEFAULT_TOLERANCE_MM,
        };
        let e = evaluate_grouped(&pos, &dir, &err, &listed)
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with(
                "target 1800 mm of --targets: no row lies within the tolerance of 0.01 mm of \
                 it (the list's other targets: 0 mm, 600.0005 mm, 1200 mm)"
            ),
            "{e}"
        );
    }

    /// "fewer than 2 target positions" said neither what was found nor why.
    #[test]
    fn a_file_at_one_target_says_where_and_why() {
        let dir = [1, -1, 1, -1];
        let e = evaluate(&[0.0, 0.004, 0.0, 0.004], &dir, &[0.0; 4])
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with(
                "every row is at one target position, 0.002 mm (4 rows); ISO 230-2 evaluates an \
                 axis at 2 targets or more: the positions span 0.004 mm, and clustering"
            ),
            "{e}"
        );
        let one = Grouping {
            targets_mm: vec![0.0],
            tolerance_mm: DEFAULT_TOLERANCE_MM,
        };
        let e = evaluate_grouped(&[0.0, 0.004, 0.0, 0.004], &dir, &[0.0; 4], &one)
            .unwrap_err()
            .to_string();
        assert!(e.ends_with("or more: --targets lists one"), "{e}");
        let e = evaluate(&[5.0; 4], &dir, &[0.0; 4])
            .unwrap_err()
            .to_string();
        assert!(
            e.ends_with("5 mm (4 rows); ISO 230-2 evaluates an axis at 2 targets or more"),
            "{e}"
        );
    }
}
