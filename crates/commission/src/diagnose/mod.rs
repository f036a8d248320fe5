//! `compgate diagnose`: where a thermal model and measurements disagree, which
//! physical effect is missing, the model with that effect added, and how much the gap
//! shrinks.
//!
//! The engine ([`diagnose`]) is pure: measurements in, a [`Diagnosis`] out. It fits
//! the baseline `err = K0(T) + tan(beta)(T) * (pos - P0)` (K0 and tan(beta) affine in
//! the chosen sensors), then grows the model greedily: every candidate effect is fitted
//! jointly with the current model (a time constant or period by a 1-D search with the
//! linear parameters solved exactly at each value) and accepted only when
//!
//! - an information criterion with an effective sample size improves:
//!   `n_eff ln(RSS1/RSS0) + k ln(n_eff) < -ic_margin`, `n_eff = n (1-rho)/(1+rho)` from
//!   the lag-1 autocorrelation `rho` of the candidate model's residuals;
//! - the held-out error of blocked (contiguous) cross-validation drops;
//! - its searched parameter is not at the edge of its range;
//! - it is of a practical size: its RMS is at least `min_size_ratio` of the residual
//!   that remains.
//!
//! The best passing candidate (lowest criterion) is added; a runner-up of another kind
//! within `tie_ic` is reported as ambiguous. Selection repeats until nothing passes.

pub mod command;
pub mod effects;
pub mod engine;
pub mod fit;
pub mod model_file;
pub mod output;
#[cfg(any(test, feature = "synth"))]
pub mod synth;

use std::collections::BTreeMap;

use serde::Serialize;
use thiserror::Error;

pub use effects::EffectKind;
pub use engine::Checks;
use engine::{Current, Data, Evidence};
pub use model_file::ModelFile;

use compgate_core::measure::Measurements;

/// Errors of the diagnose workflow.
#[derive(Debug, Error)]
pub enum DiagnoseError {
    #[error("--sensors: no temperature column `T_{sensor}` in the data (columns: {available})")]
    UnknownSensor { sensor: String, available: String },
    #[error("{0}")]
    Arg(#[from] crate::args::ArgError),
    #[error("{rows} data rows are too few for this baseline (at least {min_rows})")]
    TooFewRows { rows: usize, min_rows: usize },
    #[error("--model: channel `{channel}` of {key} is neither a `T_` column of the data nor a lagged channel of the model file")]
    UnknownChannel { channel: String, key: String },
    #[error("{path}: {message}")]
    ModelFile { path: String, message: String },
    #[error("{path}: {source}")]
    Data {
        path: String,
        #[source]
        source: compgate_core::measure::MeasureError,
    },
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("plot {0}")]
    Plot(#[from] crate::plot::PlotError),
    #[error("{0}")]
    Output(#[from] compgate_core::outputs::OutputError),
    /// `--out` holds a model file another command (or a person) wrote: replacing it
    /// would lose it, and a diagnose model in its place would read as that one.
    #[error(
        "--out {dir}: holds {file}, which `compgate diagnose` did not write (it starts \
         {first_line:?}); it is not replaced: use another directory or move it"
    )]
    ForeignModel {
        dir: String,
        file: String,
        first_line: String,
    },
    #[error("fit: {0}")]
    Fit(#[from] crate::lsq::LsqError),
    /// The baseline cannot be fitted to the data (refused as `calibrate` refuses it).
    #[error("fit: {0}")]
    Unfittable(#[from] crate::calibrate::FitError),
}

/// Decision thresholds, calibrated on null data (see the README).
#[derive(Debug, Clone, Copy)]
pub struct Thresholds {
    /// The criterion must drop by more than this.
    pub ic_margin: f64,
    /// Blocked cross-validation MSE must drop by at least this fraction.
    pub cv_min_gain: f64,
    /// A runner-up of another kind within this criterion distance is a near-tie.
    pub tie_ic: f64,
    /// Practical size: the effect's RMS must be at least this fraction of the residual
    /// RMS that remains with it. Smaller effects are of no use to a compensation and
    /// are where artefacts of sensor noise and resolution live (a lag that merely
    /// smooths a quantised sensor).
    pub min_size_ratio: f64,
    /// Contiguous blocks for cross-validation.
    pub cv_blocks: usize,
    /// Most effects added.
    pub max_effects: usize,
}

impl Default for Thresholds {
    fn default() -> Self {
        Thresholds {
            ic_margin: 10.0,
            cv_min_gain: 0.01,
            tie_ic: 6.0,
            min_size_ratio: 0.35,
            cv_blocks: 5,
            max_effects: 4,
        }
    }
}

/// A residual whose lag-1 autocorrelation in time is at least this is systematic,
/// not noise: its RMS is then at least sqrt(5) = 2.2 times the noise level
/// ([`noise_level_um`]). Above what correlated noise (an interferometer in moving
/// air, AR(1) 0.5 in the tests) reaches, and far above what white noise reaches by
/// chance on the rows diagnose needs (standard error about 1/sqrt(n), 0.12 at the
/// fewest rows).
pub const SYSTEMATIC_RHO: f64 = 0.8;

/// The noise level of a residual of RMS `rms_um` and lag-1 autocorrelation `rho`:
/// the RMS of its successive differences over sqrt(2), which is what white noise
/// alone gives, while a slow systematic part cancels in the differences.
pub fn noise_level_um(rms_um: f64, rho: f64) -> f64 {
    rms_um * (1.0 - rho).max(0.0).sqrt()
}

/// The bad readings of the baseline fit, told by time, as calibrate finds them
/// ([`crate::calibrate::bad_readings`]), and whether they move it; `None` where there
/// are none or the baseline cannot be fitted as calibrate fits it.
fn bad_readings(m: &Measurements, sensors: &[String]) -> Option<(String, bool)> {
    let f = crate::calibrate::calibrate(m, sensors, None).ok()?;
    let bad = crate::calibrate::bad_readings(m, sensors, &f);
    let rows = bad.rows();
    let (n, first) = (rows.len(), *rows.first()?);
    let noun = if n == 1 { "row" } else { "rows" };
    Some(if bad.pull() {
        (
            format!(
                "{n} {noun} (a sensor that dropped out or froze, a 0 or a -999 written for a \
                 missing value), the first at t_s {} s; left out, they move the baseline by up \
                 to {:.3} um",
                m.t_s[first], bad.pull_um
            ),
            true,
        )
    } else {
        let (look, moves, them) = if n == 1 {
            ("looks like a bad reading (at", "moves", "it")
        } else {
            ("look like bad readings (the first at", "move", "them")
        };
        (
            format!(
                "{n} {noun} {look} t_s {} s) and, left out, {moves} the baseline by {:.3} um \
                 at most: the verdict stands; the RMS and max figures include {them}",
                m.t_s[first], bad.pull_um
            ),
            false,
        )
    })
}

/// What to do about a candidate whose searched parameter sits at an edge of its
/// range: the data of another run, not finer steps, resolves a time constant as long
/// as the run.
fn edge_advice(c: &CandidateReport) -> &'static str {
    let upper = match (c.param, c.range) {
        (Some(p), Some((lo, hi))) => (p.ln() - lo.ln()).abs() > (hi.ln() - p.ln()).abs(),
        _ => false,
    };
    match (c.param_name, upper) {
        (Some("tau_s"), true) => {
            "a time constant as long as the run is a drift over the run or an effect slower \
             than the run shows; a run several time constants long tells them apart"
        }
        // Rows closer in time made such a lag pass on null data with 0.1 K sensors:
        // it smooths the sensors' steps.
        (Some("tau_s"), false) => {
            "a time constant as short as the rows resolve: more likely the sensors' own lag, \
             filtering or resolution than the machine's, and of no use to a compensation"
        }
        (Some("period_mm"), true) => {
            "a period as long as the travel measured is a curve; a longer travel tells"
        }
        (Some("period_mm"), false) => "target positions closer together tell",
        _ => "measure with finer steps to tell",
    }
}

/// What the user asked for.
#[derive(Debug, Clone, Default)]
pub struct Options {
    /// Baseline sensors (names without `T_`); None: every temperature column.
    pub sensors: Option<Vec<String>>,
    /// The model taken as the simulation (`--model`).
    pub model: Option<ModelFile>,
    pub thresholds: Thresholds,
}

/// A given model whose RMS gap is more than this many times the baseline refit's (and
/// [`STALE_MODEL_MIN_UM`] more) does not describe the data: the verdict says so first.
pub const STALE_MODEL_RATIO: f64 = 2.0;

/// The least RMS excess over the baseline refit, um, that calls a given model stale:
/// below a micrometre the difference is not worth a refit.
pub const STALE_MODEL_MIN_UM: f64 = 1.0;

/// See [`Diagnosis::held_out`].
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct HeldOut {
    /// Contiguous time blocks.
    pub blocks: usize,
    pub baseline_rms_um: f64,
    pub final_rms_um: f64,
}

/// RMS and largest absolute value of a residual, um.
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct Gap {
    pub rms_um: f64,
    pub max_abs_um: f64,
}

impl Gap {
    pub fn of(r: &[f64]) -> Self {
        let n = r.len().max(1) as f64;
        Gap {
            rms_um: (r.iter().map(|v| v * v).sum::<f64>() / n).sqrt(),
            max_abs_um: r.iter().fold(0.0, |m: f64, v| m.max(v.abs())),
        }
    }
}

/// A candidate's evidence as reported.
#[derive(Debug, Clone, Serialize)]
pub struct CandidateReport {
    pub name: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sensor: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub param: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub param_name: Option<&'static str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub range: Option<(f64, f64)>,
    pub k_add: usize,
    pub rms_before_um: f64,
    pub rms_after_um: f64,
    pub rho: f64,
    pub n_eff: f64,
    pub delta_ic: f64,
    pub cv_rms_before_um: f64,
    pub cv_rms_after_um: f64,
    /// Reported inline: `at_edge`, `passes_ic`, ... `passes_size`.
    #[serde(flatten)]
    pub checks: Checks,
    pub accepted: bool,
}

/// One added effect.
#[derive(Debug, Clone, Serialize)]
pub struct EffectReport {
    pub name: &'static str,
    pub params: BTreeMap<String, serde_json::Value>,
    pub rms_before_um: f64,
    pub rms_after_um: f64,
    pub delta_ic: f64,
    /// Other effect names that fit nearly as well (a near-tie).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub ambiguous_with: Vec<&'static str>,
    #[serde(skip)]
    pub kind: EffectKind,
    #[serde(skip)]
    pub sensor: Option<usize>,
    #[serde(skip)]
    pub param: Option<f64>,
    /// Indices of its columns in the final design.
    #[serde(skip)]
    pub cols: (usize, usize),
    /// Mean of each of its signals (lags, heat), the references the model file records.
    #[serde(skip)]
    pub signal_mean: Vec<f64>,
}

/// One round of selection: every candidate's evidence.
#[derive(Debug, Clone, Serialize)]
pub struct Round {
    pub candidates: Vec<CandidateReport>,
}

/// Where the baseline residual lies.
#[derive(Debug, Clone, Serialize)]
pub struct Where {
    /// (t_from_s, t_to_s, rms_um) per time window.
    pub time_windows: Vec<(f64, f64, f64)>,
    /// (pos_from_mm, pos_to_mm, mean_um, rms_um) per position range.
    pub position_ranges: Vec<(f64, f64, f64, f64)>,
    /// Mean residual approaching in + and in - direction, um, and row counts.
    pub dir_plus_mean_um: f64,
    pub dir_minus_mean_um: f64,
    pub dir_rows: (usize, usize),
    /// Strongest periodic component in position: (period_mm, amplitude_um).
    pub periodic: Option<(f64, f64)>,
    /// Lag-1 autocorrelation of the residual in time.
    pub rho: f64,
}

/// The result of the workflow.
#[derive(Debug, Clone, Serialize)]
pub struct Diagnosis {
    /// Gap of the given model (`--model`) before refitting.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model_gap: Option<Gap>,
    pub baseline: Gap,
    pub effects: Vec<EffectReport>,
    #[serde(rename = "final")]
    pub final_gap: Gap,
    pub sensors: Vec<String>,
    pub rows: usize,
    pub ignored_columns: Vec<String>,
    pub where_baseline: Where,
    pub where_final: Where,
    /// Held-out RMS of the baseline and of the final model, um: each of the
    /// `cv_blocks` contiguous time blocks predicted by the fit on the others, so the
    /// gap's shrinking is shown on data each fit did not see.
    pub held_out: HeldOut,
    pub rounds: Vec<Round>,
    /// Candidates the data cannot test, each with the reason (time that does not
    /// advance, positions too sparse for a period).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub untested: Vec<String>,
    /// One-line verdict.
    pub verdict: String,
    #[serde(skip)]
    pub p0_mm: f64,
    #[serde(skip)]
    pub beta: Vec<f64>,
    /// Coefficients of the baseline refit alone.
    #[serde(skip)]
    pub beta_baseline: Vec<f64>,
    #[serde(skip)]
    pub temp_mean_degc: Vec<f64>,
    #[serde(skip)]
    pub temp_range_degc: Vec<[f64; 2]>,
    #[serde(skip)]
    pub temp_names: Vec<String>,
    #[serde(skip)]
    pub sensor_idx: Vec<usize>,
    #[serde(skip)]
    pub pos_range_mm: (f64, f64),
    /// Residual series for the plots.
    #[serde(skip)]
    pub series: Series,
}

/// The series the plots need.
#[derive(Debug, Clone, Default)]
pub struct Series {
    pub t_s: Vec<f64>,
    pub pos_mm: Vec<f64>,
    pub dir: Vec<i8>,
    pub before_um: Vec<f64>,
    pub after_um: Vec<f64>,
}

fn param_name(kind: EffectKind) -> Option<&'static str> {
    match kind {
        EffectKind::ThermalLag | EffectKind::MotionHeating => Some("tau_s"),
        EffectKind::PitchPeriodic => Some("period_mm"),
        _ => None,
    }
}

fn candidate_report(d: &Data, e: &Evidence, accepted: bool) -> CandidateReport {
    let n = d.n as f64;
    CandidateReport {
        name: e.kind.name(),
        sensor: match (e.sensor, e.kind) {
            (Some(s), _) => Some(d.names[s].clone()),
            (None, EffectKind::ThermalLag) => Some("all".into()),
            _ => None,
        },
        param: e.param,
        param_name: param_name(e.kind),
        range: e.range,
        k_add: e.k_add,
        rms_before_um: (e.rss_before / n).sqrt(),
        rms_after_um: (e.rss_after / n).sqrt(),
        rho: e.rho,
        n_eff: e.n_eff,
        delta_ic: e.delta_ic,
        cv_rms_before_um: e.cv_before.sqrt(),
        cv_rms_after_um: e.cv_after.sqrt(),
        checks: e.checks,
        accepted,
    }
}

/// The candidates the data cannot test, with the reason: they are left out of the
/// rounds, and a verdict that names nothing must not read as if they were tested.
fn untested(d: &Data) -> Vec<String> {
    let mut out = Vec::new();
    if d.tau_range().is_none() {
        let (duration, dt) = d.time_scales();
        let why = if duration <= 0.0 {
            format!("time does not advance: t_s is {} s on every row", d.t_s[0])
        } else {
            format!(
                "the record spans {duration} s, too short to resolve a time constant: it needs \
                 more than 8 sample intervals of {dt} s"
            )
        };
        out.push(format!("thermal_lag, motion_heating ({why})"));
    } else if d.motion_tau_range().is_none() {
        out.push(format!(
            "motion_heating (half of the travel comes in intervals of {} s or longer between \
             rows, and the record spans {} s: how the travel was spread within an interval \
             is not in the data, so a store needs a time constant above the interval and the \
             record 4 times that)",
            d.travel_interval_s(),
            d.time_scales().0
        ));
    }
    if engine::period_range(d).is_none() {
        out.push("pitch_periodic (positions too sparse to resolve a period)".into());
    }
    out
}

fn describe(d: &Data, r: &[f64]) -> Where {
    let n = d.n;
    let (t0, t1) = (d.t_s[0], d.t_s[n - 1]);
    // No windows when time does not advance: one "0 .. 0 s" window told nothing.
    let nw = if t1 > t0 { 10.min(n) } else { 0 };
    let mut time_windows = Vec::new();
    for w in 0..nw {
        let a = t0 + (t1 - t0) * w as f64 / nw as f64;
        let b = t0 + (t1 - t0) * (w + 1) as f64 / nw as f64;
        let sel: Vec<f64> = (0..n)
            .filter(|&i| d.t_s[i] >= a && (d.t_s[i] < b || (w + 1 == nw && d.t_s[i] <= b)))
            .map(|i| r[i])
            .collect();
        if !sel.is_empty() {
            time_windows.push((a, b, Gap::of(&sel).rms_um));
        }
    }
    let mut position_ranges = Vec::new();
    let (p0, p1) = (d.pos_min_mm, d.pos_max_mm);
    for w in 0..10 {
        let a = p0 + (p1 - p0) * w as f64 / 10.0;
        let b = p0 + (p1 - p0) * (w + 1) as f64 / 10.0;
        let sel: Vec<f64> = (0..n)
            .filter(|&i| d.pos_mm[i] >= a && (d.pos_mm[i] < b || (w == 9 && d.pos_mm[i] <= b)))
            .map(|i| r[i])
            .collect();
        if !sel.is_empty() {
            let mean = sel.iter().sum::<f64>() / sel.len() as f64;
            position_ranges.push((a, b, mean, Gap::of(&sel).rms_um));
        }
    }
    let mean_of = |want: f64| {
        let sel: Vec<f64> = (0..n).filter(|&i| d.dir[i] == want).map(|i| r[i]).collect();
        let m = if sel.is_empty() {
            0.0
        } else {
            sel.iter().sum::<f64>() / sel.len() as f64
        };
        (m, sel.len())
    };
    let (plus, np) = mean_of(1.0);
    let (minus, nm) = mean_of(-1.0);
    let periodic =
        engine::period_range(d).and_then(|range| engine::periodogram(d, r, range).first().copied());
    Where {
        time_windows,
        position_ranges,
        dir_plus_mean_um: plus,
        dir_minus_mean_um: minus,
        dir_rows: (np, nm),
        periodic,
        rho: fit::ar1(r),
    }
}

/// Re-searches the time constant or period of every added effect with all the others
/// in the model (one pass, within a factor 2 of the current value), so that a value
/// found while another effect was still missing does not leave a misfit behind.
fn refine(d: &Data, cur: Current, effects: &mut [EffectReport]) -> Current {
    let mut cols = cur.cols;
    for e in effects.iter_mut() {
        let Some(p) = e.param else { continue };
        let (a, b) = e.cols;
        let kind = e.kind;
        let sensor = e.sensor;
        let others: Vec<Vec<f64>> = cols[..a].iter().chain(&cols[b..]).cloned().collect();
        let base = Current::new(d, others);
        let mut f = |lp: f64| base.rss_with(d, &d.effect_columns(kind, sensor, lp.exp()).0);
        // A period has many local minima: stay within 5 % of the one found.
        let factor: f64 = if kind == EffectKind::PitchPeriodic {
            1.05
        } else {
            2.0
        };
        // A time constant stays within the range the data resolves.
        let (lo, hi) = match kind {
            EffectKind::PitchPeriodic => (p / factor, p * factor),
            _ => d.tau_range_of(kind).map_or((p, p), |(lo, hi)| {
                ((p / factor).max(lo), (p * factor).min(hi))
            }),
        };
        let (lp, rss) = crate::stats::golden(lo.ln(), hi.ln(), 16, &mut f);
        if rss < f(p.ln()) {
            let (new_cols, mean) = d.effect_columns(kind, sensor, lp.exp());
            for (k, c) in new_cols.into_iter().enumerate() {
                cols[a + k] = c;
            }
            e.param = Some(lp.exp());
            e.signal_mean = mean;
        }
    }
    Current::new(d, cols)
}

/// Runs the workflow on measurements.
pub fn diagnose(m: &Measurements, opts: &Options) -> Result<Diagnosis, DiagnoseError> {
    let th = opts.thresholds;
    let d = Data::new(
        m,
        opts.sensors.as_deref(),
        opts.model.as_ref().map(|mf| mf.axis.p0_mm),
        th.cv_blocks,
    )?;
    let model_gap = match &opts.model {
        Some(mf) => {
            let pred = mf.predict_um(m)?;
            let gap: Vec<f64> = m.err_um.iter().zip(&pred).map(|(e, p)| e - p).collect();
            Some(Gap::of(&gap))
        }
        None => None,
    };

    let mut cur = Current::new(&d, d.baseline_columns());
    let r0 = cur.residuals(&d)?;
    let beta_baseline: Vec<f64> = cur.gram.try_solve()?.beta.iter().copied().collect();
    let baseline = Gap::of(&r0);
    let where_baseline = describe(&d, &r0);
    let held_out_baseline_mse = cur.cv;

    let mut effects: Vec<EffectReport> = Vec::new();
    let mut rounds = Vec::new();
    let mut used: Vec<(EffectKind, Option<usize>)> = Vec::new();
    let mut r_cur = r0.clone();
    while effects.len() < th.max_effects {
        let mut evs: Vec<(Evidence, Vec<Vec<f64>>, Vec<f64>)> = Vec::new();
        let mut cands: Vec<(EffectKind, Option<usize>)> = Vec::new();
        for kind in EffectKind::ALL {
            match kind {
                EffectKind::ThermalLag => {
                    cands.extend(d.sensors.iter().map(|&s| (kind, Some(s))));
                    if d.sensors.len() > 1 {
                        // Every baseline sensor through one lag.
                        cands.push((kind, None));
                    }
                }
                EffectKind::ExtraSensor => cands.extend(
                    (0..d.names.len())
                        .filter(|s| !d.sensors.contains(s))
                        .map(|s| (kind, Some(s))),
                ),
                _ => cands.push((kind, None)),
            }
        }
        cands.retain(|&(kind, sensor)| {
            !used
                .iter()
                .any(|&(k, s)| k == kind && (s == sensor || sensor.is_none()))
        });
        // Candidates are independent: spread them over the available cores.
        let workers = std::thread::available_parallelism()
            .map_or(1, |n| n.get())
            .min(cands.len().max(1));
        let (dr, cr, rr) = (&d, &cur, &r_cur);
        let results: Vec<Vec<_>> = std::thread::scope(|scope| {
            let handles: Vec<_> = (0..workers)
                .map(|w| {
                    let mine: Vec<_> = cands.iter().copied().skip(w).step_by(workers).collect();
                    scope.spawn(move || {
                        mine.into_iter()
                            .filter_map(|(kind, sensor)| {
                                engine::evaluate(dr, cr, kind, sensor, &th, rr).map(|(ev, cols)| {
                                    let mean =
                                        dr.effect_columns(kind, sensor, ev.param.unwrap_or(0.0)).1;
                                    (ev, cols, mean)
                                })
                            })
                            .collect()
                    })
                })
                .collect();
            handles
                .into_iter()
                .map(|h| h.join().unwrap_or_default())
                .collect()
        });
        evs.extend(results.into_iter().flatten());
        evs.sort_by(|a, b| a.0.delta_ic.total_cmp(&b.0.delta_ic));
        let mut best = evs.iter().position(|e| e.0.passes());
        // Near-tie within one kind (one sensor's lag against every sensor's): the
        // simpler candidate wins.
        if let Some(b) = best {
            let (kind, ic, k) = (evs[b].0.kind, evs[b].0.delta_ic, evs[b].0.k_add);
            if let Some(simpler) = evs.iter().position(|e| {
                e.0.passes() && e.0.kind == kind && e.0.k_add < k && e.0.delta_ic - ic < th.tie_ic
            }) {
                best = Some(simpler);
            }
        }
        rounds.push(Round {
            candidates: evs
                .iter()
                .enumerate()
                .map(|(i, e)| candidate_report(&d, &e.0, Some(i) == best))
                .collect(),
        });
        let Some(best) = best else { break };
        let (ev, cols, mean) = evs[best].clone();
        let mut ambiguous_with: Vec<&'static str> = Vec::new();
        for (other, _, _) in evs.iter() {
            // A candidate that passes every test but the edge of its search range, and
            // fits better than the one named, is as much a rival as a near tie.
            let edge_rival = other.checks.at_edge
                && other.checks.passes_ic
                && other.checks.passes_cv
                && other.checks.passes_size
                && other.delta_ic < ev.delta_ic;
            if other.kind != ev.kind
                && (edge_rival || (other.passes() && other.delta_ic - ev.delta_ic < th.tie_ic))
                && !ambiguous_with.contains(&other.kind.name())
            {
                ambiguous_with.push(other.kind.name());
            }
        }
        let start = cur.cols.len();
        let rms_before = Gap::of(&r_cur).rms_um;
        cur.push(&d, cols);
        used.push((ev.kind, ev.sensor));
        effects.push(EffectReport {
            name: ev.kind.name(),
            params: BTreeMap::new(),
            rms_before_um: rms_before,
            // Set after the refinement below.
            rms_after_um: f64::NAN,
            delta_ic: ev.delta_ic,
            ambiguous_with,
            kind: ev.kind,
            sensor: ev.sensor,
            param: ev.param,
            cols: (start, cur.cols.len()),
            signal_mean: mean,
        });
        cur = refine(&d, cur, &mut effects);
        r_cur = cur.residuals(&d)?;
        // After the refinement, which re-tunes every effect so far: the next step
        // starts where this one ends, and the last one ends at the final gap.
        if let Some(e) = effects.last_mut() {
            e.rms_after_um = Gap::of(&r_cur).rms_um;
        }
    }

    let beta: Vec<f64> = cur.gram.try_solve()?.beta.iter().copied().collect();
    let r_final = cur.residuals(&d)?;
    let half = 0.5 * (d.pos_max_mm - d.pos_min_mm);
    for e in &mut effects {
        let b = &beta[e.cols.0..e.cols.1];
        let p = &mut e.params;
        let num = |v: f64| serde_json::json!(v);
        if let Some(s) = e.sensor {
            p.insert("sensor".into(), serde_json::json!(d.names[s]));
        }
        match e.kind {
            EffectKind::ThermalLag if e.sensor.is_none() => {
                p.insert("tau_s".into(), num(e.param.unwrap_or(0.0)));
                let names: Vec<&str> = d.sensors.iter().map(|&s| d.names[s].as_str()).collect();
                p.insert("sensor".into(), serde_json::json!(names.join(",")));
                for (k, name) in names.iter().enumerate() {
                    p.insert(format!("k0_um_per_degc_{name}"), num(b[2 * k]));
                    p.insert(
                        format!("slope_um_per_mm_per_degc_{name}"),
                        num(b[2 * k + 1]),
                    );
                }
            }
            EffectKind::ThermalLag | EffectKind::MotionHeating => {
                p.insert("tau_s".into(), num(e.param.unwrap_or(0.0)));
                let unit = if e.kind == EffectKind::ThermalLag {
                    "degc"
                } else {
                    "mm_per_s"
                };
                p.insert(format!("k0_um_per_{unit}"), num(b[0]));
                p.insert(format!("slope_um_per_mm_per_{unit}"), num(b[1]));
            }
            EffectKind::ExtraSensor => {
                p.insert("k0_um_per_degc".into(), num(b[0]));
                p.insert("slope_um_per_mm_per_degc".into(), num(b[1]));
            }
            EffectKind::Reversal => {
                p.insert("b_um".into(), num(2.0 * b[0]));
            }
            EffectKind::PitchPeriodic => {
                p.insert("period_mm".into(), num(e.param.unwrap_or(0.0)));
                p.insert("amplitude_um".into(), num(b[0].hypot(b[1])));
                p.insert("phase_rad".into(), num(b[1].atan2(b[0])));
            }
            EffectKind::NonlinearPosition => {
                let mut lo = f64::INFINITY;
                let mut hi = f64::NEG_INFINITY;
                for i in 0..=100 {
                    let v = -1.0 + i as f64 / 50.0;
                    let l = effects::legendre_2_4(v);
                    let y = b[0] * l[0] + b[1] * l[1] + b[2] * l[2];
                    lo = lo.min(y);
                    hi = hi.max(y);
                }
                p.insert("peak_to_peak_um".into(), num(hi - lo));
                p.insert("legendre_p2_um".into(), num(b[0]));
                p.insert("legendre_p3_um".into(), num(b[1]));
                p.insert("legendre_p4_um".into(), num(b[2]));
                p.insert("center_mm".into(), num(0.5 * (d.pos_min_mm + d.pos_max_mm)));
                p.insert("half_span_mm".into(), num(half));
            }
        }
    }

    let final_gap = Gap::of(&r_final);
    let where_final = describe(&d, &r_final);
    let held_out = HeldOut {
        blocks: th.cv_blocks,
        baseline_rms_um: held_out_baseline_mse.sqrt(),
        final_rms_um: cur.cv.sqrt(),
    };
    // The last round's candidates that pass every test but the edge of their search
    // range: the data cannot tell such an effect apart, but it must not read as noise.
    let edge_rivals: Vec<&CandidateReport> = rounds
        .last()
        .map(|r| {
            r.candidates
                .iter()
                .filter(|c| {
                    let k = &c.checks;
                    k.at_edge && k.passes_ic && k.passes_cv && k.passes_size
                })
                .collect()
        })
        .unwrap_or_default();
    let untested = untested(&d);
    let not_tested = if untested.is_empty() {
        String::new()
    } else {
        format!("; not tested: {}", untested.join("; "))
    };
    // What a residual that is still systematic says, after the candidates.
    let systematic = |rho: f64, rms_um: f64| {
        format!(
            "systematic, not noise: RMS {rms_um:.3} um, lag-1 autocorrelation {rho:.3} in \
             time (noise level about {:.3} um from successive rows)",
            noise_level_um(rms_um, rho)
        )
    };
    let verdict = if let (true, Some(c)) = (effects.is_empty(), edge_rivals.first()) {
        let baseline_systematic = if where_baseline.rho >= SYSTEMATIC_RHO {
            format!(
                "; the residual is {}",
                systematic(where_baseline.rho, baseline.rms_um)
            )
        } else {
            String::new()
        };
        format!(
            "no effect named, but {} fits better (residual RMS {:.3} -> {:.3} um) with its {} \
             at the edge of the range the data resolves ({:.4}): {}{baseline_systematic}{not_tested}",
            c.name,
            c.rms_before_um,
            c.rms_after_um,
            c.param_name.unwrap_or("parameter"),
            c.param.unwrap_or(f64::NAN),
            edge_advice(c),
        )
    } else if effects.is_empty() && where_baseline.rho >= SYSTEMATIC_RHO {
        format!(
            "no candidate explains the residual, but it is systematic, not noise: RMS {:.3} um, \
             lag-1 autocorrelation {:.3} in time (noise level about {:.3} um from successive \
             rows); a sensor that drives the error is missing or misplaced, or the error has a \
             form none of the candidates has{not_tested}",
            baseline.rms_um,
            where_baseline.rho,
            noise_level_um(baseline.rms_um, where_baseline.rho)
        )
    } else if effects.is_empty() && untested.is_empty() {
        format!(
            "no missing effect: the baseline explains the data to within its noise (residual RMS {:.3} um)",
            baseline.rms_um
        )
    } else if effects.is_empty() {
        format!(
            "none of the candidates tested is missing: the baseline explains the data to \
             within its noise (residual RMS {:.3} um){not_tested}",
            baseline.rms_um
        )
    } else {
        let names: Vec<String> = effects
            .iter()
            .map(|e| {
                if e.ambiguous_with.is_empty() {
                    e.name.to_string()
                } else {
                    format!(
                        "{} (ambiguous with {})",
                        e.name,
                        e.ambiguous_with.join(", ")
                    )
                }
            })
            .collect();
        // A named effect can take up part of what none of the candidates has (a step
        // at a tool change fitted as a lag as long as the run): the rest then stays
        // systematic, and the model is no better on the next run.
        let rest = if where_final.rho >= SYSTEMATIC_RHO {
            format!(
                "; but what remains is {}: something none of the candidates has (a step such \
                 as a tool change or a re-zeroed probe, a drift over the run) or a missing \
                 sensor, which the effects named may have partly taken up; look at the \
                 residual over time before using the model",
                systematic(where_final.rho, final_gap.rms_um)
            )
        } else {
            String::new()
        };
        format!(
            "missing: {}; residual RMS {:.3} -> {:.3} um ({:.0} % smaller; held out, each of \
             {} time blocks predicted from the others: {:.3} -> {:.3} um){rest}",
            names.join(", then "),
            baseline.rms_um,
            final_gap.rms_um,
            100.0 * (1.0 - final_gap.rms_um / baseline.rms_um.max(1e-300)),
            held_out.blocks,
            held_out.baseline_rms_um,
            held_out.final_rms_um,
        )
    };
    // A bad reading pulls the baseline and every candidate: a single err_um of -999
    // made a lag that was there read as noise. Named first, by time.
    let sensors: Vec<String> = d.sensors.iter().map(|&s| d.names[s].clone()).collect();
    let verdict = match bad_readings(m, &sensors) {
        Some((bad, true)) => format!(
            "the data hold bad readings: {bad}; fix or remove them and diagnose again; what \
             follows is on them: {verdict}"
        ),
        // A single -999 that moves nothing still made the RMS 2.6 um for 0.5.
        Some((bad, false)) => format!("{verdict}; {bad}"),
        None => verdict,
    };
    // A given model far off the refit of its own form is stale: the refit absorbed an
    // offset or a swap, and the verdict on the rest read as if the model were fine.
    let verdict = match model_gap {
        Some(g)
            if g.rms_um > STALE_MODEL_RATIO * baseline.rms_um
                && g.rms_um - baseline.rms_um > STALE_MODEL_MIN_UM =>
        {
            format!(
                "the given model does not fit this data: RMS {:.3} um against {:.3} um for the \
             refit of K0(T) + tan(beta)(T) on it; a sensor replaced, moved, swapped or \
             drifting, or a changed machine; refit (calibrate) before anything else; the \
             rest, on the refit: {verdict}",
                g.rms_um, baseline.rms_um
            )
        }
        _ => verdict,
    };
    Ok(Diagnosis {
        model_gap,
        baseline,
        effects,
        final_gap,
        sensors: d.sensors.iter().map(|&s| d.names[s].clone()).collect(),
        rows: d.n,
        ignored_columns: m.ignored_columns.clone(),
        where_baseline,
        where_final,
        held_out,
        rounds,
        untested,
        verdict,
        p0_mm: d.p0_mm,
        beta,
        beta_baseline,
        temp_mean_degc: d.temp_mean_degc.clone(),
        temp_range_degc: d.temp_range_degc.clone(),
        temp_names: d.names.clone(),
        sensor_idx: d.sensors.clone(),
        pos_range_mm: (d.pos_min_mm, d.pos_max_mm),
        series: Series {
            t_s: d.t_s.clone(),
            pos_mm: d.pos_mm.clone(),
            dir: m.dir.clone(),
            before_um: r0,
            after_um: r_final,
        },
    })
}
