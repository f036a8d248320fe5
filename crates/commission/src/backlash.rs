//! `compgate backlash`: backlash of a full-closed-loop axis from the servo trace of its
//! motor encoder and linear scale (DOMAIN.md section 3).
//!
//! Procedure: the axis moves at feed v positively to A, dwells S s; positively to B,
//! dwells; negatively to C, dwells; positively to D, dwells. The servo trace records
//! the encoder and scale actual positions from the arrival at A. At B, C, D the scale
//! reads L1..L3 and the encoder M1..M3, and
//!
//! ```text
//! H1 = |L1 - L2|   H2 = |L2 - L3|   h1 = |M1 - M2|   h2 = |M2 - M3|
//! F1 = |h1 - H1|   (positive-direction backlash)
//! F2 = |h2 - H2|   (negative-direction backlash)
//! ```
//!
//! The scale is the reference; no external instrument is needed.
//!
//! L and M are not single samples: the drive train is elastic, so while the axis
//! still creeps into position the motor leads the table by more than the gap. Each
//! value is the mean over the settled part (second half) of the standstill plateau at
//! the point, found in the trace from the scale velocity ([`extract`]).
//!
//! The pure part (validation, extraction, the seed's formulas, the report) has no
//! tokio; [`run`] drives an NC axis module over Modbus TCP: it commands the programme,
//! arms and uploads the trace through the servo block of `compgate_ncproto`, and
//! with `--write` writes MD32450 through the FB3 job ([`compgate_gateway::nc::ModbusNcWriter`]).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;

use compgate_ncproto::servo::{MoveStep, TraceConfig, Trigger};
use compgate_ncproto::{self as ncmap, var};

use compgate_gateway::nc::{Job, ModbusNcWriter, NcError, NcWriter};
use compgate_gateway::source::modbus::{Backoff, LinkSpec, ModbusLink};
use compgate_gateway::source::plan::RegisterKind;
use compgate_gateway::source::SourceError;

use crate::plot::{self, Color as _, PlotError};
use crate::stats::mean;

/// Shortest dwell, s: the loop must settle and leave a plateau to average.
pub const MIN_DWELL_S: f64 = 0.5;
/// Fewest samples averaged on one plateau.
pub const MIN_PLATEAU_SAMPLES: usize = 25;
/// Shortest stroke B->C and C->D, mm: longer than the largest MD32450, so each
/// reversal takes the whole gap up.
pub const MIN_STROKE_MM: f64 = 1.0;
/// The axis first goes this far below A, so A is approached positively, mm.
pub const PRE_TRAVEL_MM: f64 = 1.0;
/// Trigger threshold below A: the trace starts as the axis arrives at A, mm.
pub const TRIGGER_BELOW_A_MM: f64 = 0.002;
/// Span of the velocity estimate used to find standstill, s.
pub const VELOCITY_SPAN_S: f64 = 0.05;
/// A plateau's scale value must lie this close to its point, mm.
pub const POINT_TOLERANCE_MM: f64 = 0.1;
/// In-position window of the single-sample extraction, mm.
pub const ARRIVAL_WINDOW_MM: f64 = 0.005;

/// Errors of the backlash test.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BacklashError {
    /// Parameters refused before anything moved; every problem is listed.
    #[error("invalid backlash test parameters: {}", .0.join("; "))]
    Invalid(Vec<String>),
    /// The Modbus link failed.
    #[error("NC link: {0}")]
    Link(#[from] SourceError),
    /// The MD32450 job failed.
    #[error("MD32450 write: {0}")]
    Nc(#[from] NcError),
    /// The NC refused the move programme or the trace configuration.
    #[error("NC refused the {what}: code {code} ({})", refusal_name(*.code))]
    Refused {
        /// "move programme" or "servo trace".
        what: &'static str,
        /// Refusal code (`MV_STATUS` / `TR_STATUS`).
        code: u16,
    },
    /// The programme or the trace did not finish in time.
    #[error("timed out: {0}")]
    Timeout(String),
    /// The trace does not show the plateaus the procedure needs.
    #[error("trace: {0}")]
    Extraction(String),
    /// Writing the report files failed.
    #[error("output: {0}")]
    Io(String),
}

/// Names a refusal code of the servo block.
pub fn refusal_name(code: u16) -> &'static str {
    match code {
        1 => "step count",
        2 => "target outside the software limits",
        3 => "feed out of range",
        4 => "dwell out of range",
        5 => "a programme is running",
        6 => "sample period is not a whole number of servo cycles",
        7 => "record time exceeds the trace buffer",
        8 => "bad post-trigger delay",
        9 => "bad trigger",
        _ => "unknown",
    }
}

/// Arguments of `compgate backlash`.
#[derive(Debug, Clone, clap::Args)]
pub struct BacklashArgs {
    /// Axis name, for the report and file names.
    #[arg(long, default_value = "X1")]
    pub axis: String,
    /// Point A, mm: approached positively; the trace starts here.
    #[arg(long, default_value_t = 10.0)]
    pub a: f64,
    /// Point B, mm: above A.
    #[arg(long, default_value_t = 60.0)]
    pub b: f64,
    /// Point C, mm: below B (negative move).
    #[arg(long, default_value_t = 30.0)]
    pub c: f64,
    /// Point D, mm: above C (positive move).
    #[arg(long, default_value_t = 60.0)]
    pub d: f64,
    /// Feed v of every move, mm/min.
    #[arg(long, default_value_t = 1000.0)]
    pub feed: f64,
    /// Dwell S at every point, s.
    #[arg(long, default_value_t = 2.0)]
    pub dwell: f64,
    /// Servo trace sample period, ms.
    #[arg(long, default_value_t = 2.0)]
    pub period_ms: f64,
    /// Write the result (mean of F1 and F2) to MD32450 through the FB3 job and verify
    /// the read-back.
    #[arg(long)]
    pub write: bool,
    /// NC axis module, host:port (Modbus TCP).
    #[arg(long, value_name = "ADDRESS")]
    pub nc: Option<String>,
    /// Modbus unit id of the NC axis module.
    #[arg(long, default_value_t = 1)]
    pub unit: u8,
    /// Directory for the position-time SVG and the trace CSV.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Run against an in-process simulated axis instead of --nc.
    #[arg(long)]
    pub sim: bool,
    /// Simulated axis: backlash, um.
    #[arg(long, default_value_t = 20.0)]
    pub sim_backlash_um: f64,
    /// Simulated axis: measurement noise (standard deviation) of encoder and scale, um.
    #[arg(long, default_value_t = 0.3)]
    pub sim_noise_um: f64,
    /// Simulated axis: drive-train elasticity time constant, ms (table lag = v * tau).
    #[arg(long, default_value_t = 8.0)]
    pub sim_elastic_ms: f64,
    /// Simulated axis: noise seed.
    #[arg(long, default_value_t = 1)]
    pub sim_seed: u64,
    /// Simulated axis: machine seconds per wall-clock second.
    #[arg(long, default_value_t = 1000.0)]
    pub sim_speed: f64,
}

impl Default for BacklashArgs {
    fn default() -> Self {
        Self {
            axis: "X1".into(),
            a: 10.0,
            b: 60.0,
            c: 30.0,
            d: 60.0,
            feed: 1000.0,
            dwell: 2.0,
            period_ms: 2.0,
            write: false,
            nc: None,
            unit: 1,
            out: None,
            sim: false,
            sim_backlash_um: 20.0,
            sim_noise_um: 0.3,
            sim_elastic_ms: 8.0,
            sim_seed: 1,
            sim_speed: 1000.0,
        }
    }
}

/// The test points, mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Points {
    /// A: start of the trace.
    pub a_mm: f64,
    /// B.
    pub b_mm: f64,
    /// C.
    pub c_mm: f64,
    /// D.
    pub d_mm: f64,
}

/// The procedure's parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Procedure {
    /// Points A..D.
    pub points: Points,
    /// Feed v, mm/min.
    pub feed_mm_per_min: f64,
    /// Dwell S, s.
    pub dwell_s: f64,
    /// Trace sample period, s.
    pub period_s: f64,
}

impl Procedure {
    /// The procedure of `args`.
    pub fn from_args(args: &BacklashArgs) -> Self {
        Self {
            points: Points {
                a_mm: args.a,
                b_mm: args.b,
                c_mm: args.c,
                d_mm: args.d,
            },
            feed_mm_per_min: args.feed,
            dwell_s: args.dwell,
            period_s: args.period_ms / 1000.0,
        }
    }

    /// The move programme: below A, A, B, C, D, each followed by the dwell.
    pub fn program(&self) -> Vec<MoveStep> {
        let p = self.points;
        [p.a_mm - PRE_TRAVEL_MM, p.a_mm, p.b_mm, p.c_mm, p.d_mm]
            .into_iter()
            .map(|target_mm| MoveStep {
                target_mm,
                feed_mm_per_min: self.feed_mm_per_min,
                dwell_s: self.dwell_s,
            })
            .collect()
    }

    /// Trace parameters: triggered as the scale rises to A, recording the dwell at A
    /// through the end of the dwell at D, with a margin for acceleration and settling.
    pub fn trace_config(&self) -> TraceConfig {
        let p = self.points;
        let v_mm_per_s = self.feed_mm_per_min / 60.0;
        let travel_mm = (p.b_mm - p.a_mm).abs() + (p.b_mm - p.c_mm).abs() + (p.d_mm - p.c_mm).abs();
        let record_s = 4.0 * self.dwell_s + travel_mm / v_mm_per_s + 3.0 * 0.5 + 0.5;
        TraceConfig {
            period_s: self.period_s,
            record_s,
            trigger: Trigger::ScaleRising,
            threshold_mm: p.a_mm - TRIGGER_BELOW_A_MM,
            delay_s: 0.0,
        }
    }

    /// Checks the procedure; with the NC's limits (software limits, mm, and the
    /// highest feed, mm/min) also the travel and feed. Lists every problem.
    pub fn validate(&self, limits: Option<(f64, f64, f64)>) -> Result<(), BacklashError> {
        let mut problems = Vec::new();
        let p = self.points;
        let all = [
            ("A", p.a_mm),
            ("B", p.b_mm),
            ("C", p.c_mm),
            ("D", p.d_mm),
            ("feed", self.feed_mm_per_min),
            ("dwell", self.dwell_s),
            ("trace period", self.period_s),
        ];
        for (name, v) in all {
            if !v.is_finite() {
                problems.push(format!("{name} is not a finite number"));
            }
        }
        if !problems.is_empty() {
            return Err(BacklashError::Invalid(problems));
        }
        if p.b_mm <= p.a_mm {
            problems.push(format!(
                "B ({} mm) must lie above A ({} mm): A->B is the positive move",
                p.b_mm, p.a_mm
            ));
        }
        if p.b_mm - p.c_mm < MIN_STROKE_MM {
            problems.push(format!(
                "C ({} mm) must lie at least {MIN_STROKE_MM} mm below B ({} mm): B->C is the negative move",
                p.c_mm, p.b_mm
            ));
        }
        if p.d_mm - p.c_mm < MIN_STROKE_MM {
            problems.push(format!(
                "D ({} mm) must lie at least {MIN_STROKE_MM} mm above C ({} mm): C->D is the positive move",
                p.d_mm, p.c_mm
            ));
        }
        if self.feed_mm_per_min <= 0.0 {
            problems.push(format!(
                "feed {} mm/min must be positive",
                self.feed_mm_per_min
            ));
        }
        if self.period_s <= 0.0 {
            problems.push(format!("trace period {} s must be positive", self.period_s));
        }
        let min_dwell_s = MIN_DWELL_S.max(4.0 * MIN_PLATEAU_SAMPLES as f64 * self.period_s);
        if self.dwell_s < min_dwell_s {
            problems.push(format!(
                "dwell {} s is too short: at least {min_dwell_s} s (settling, and {MIN_PLATEAU_SAMPLES} settled samples at a {} ms trace period)",
                self.dwell_s,
                self.period_s * 1000.0
            ));
        }
        if let Some((min_mm, max_mm, max_feed)) = limits {
            let lowest = (p.a_mm - PRE_TRAVEL_MM).min(p.c_mm);
            let highest = p.b_mm.max(p.d_mm);
            if lowest < min_mm || highest > max_mm {
                problems.push(format!(
                    "travel {lowest} .. {highest} mm (A - {PRE_TRAVEL_MM} mm approach included) leaves the axis limits {min_mm} .. {max_mm} mm"
                ));
            }
            if self.feed_mm_per_min > max_feed {
                problems.push(format!(
                    "feed {} mm/min exceeds the axis maximum {max_feed} mm/min",
                    self.feed_mm_per_min
                ));
            }
        }
        if problems.is_empty() {
            Ok(())
        } else {
            Err(BacklashError::Invalid(problems))
        }
    }
}

/// A two-channel servo trace at a fixed sample period.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Trace {
    /// Sample period, s.
    pub period_s: f64,
    /// Motor encoder actual position per sample, mm.
    pub encoder_mm: Vec<f64>,
    /// Linear scale actual position per sample, mm.
    pub scale_mm: Vec<f64>,
}

/// How L and M are taken from the trace.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Extraction {
    /// Mean over the second half of the standstill plateau at each point.
    Plateau,
    /// One sample: the first inside the in-position window of the point. Kept to show
    /// why the plateau is needed.
    ArrivalSample,
}

/// Where a point's value came from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointValue {
    /// The programmed point, mm.
    pub target_mm: f64,
    /// First sample used.
    pub first: usize,
    /// Last sample used (inclusive).
    pub last: usize,
    /// Scale value L, mm.
    pub scale_mm: f64,
    /// Encoder value M, mm.
    pub encoder_mm: f64,
}

/// Standstill runs (first, last inclusive) of the scale channel.
fn standstill_runs(trace: &Trace, feed_mm_per_min: f64) -> Vec<(usize, usize)> {
    let n = trace.scale_mm.len();
    let w = ((VELOCITY_SPAN_S / trace.period_s / 2.0).round() as usize).max(1);
    let v_limit = (0.01 * feed_mm_per_min / 60.0).max(0.02);
    let mut runs = Vec::new();
    let mut start = None;
    for i in 0..n {
        let lo = i.saturating_sub(w);
        let hi = (i + w).min(n - 1);
        let span_s = (hi - lo) as f64 * trace.period_s;
        let v = if hi > lo {
            (trace.scale_mm[hi] - trace.scale_mm[lo]).abs() / span_s
        } else {
            0.0
        };
        let still = v < v_limit;
        match (still, start) {
            (true, None) => start = Some(i),
            (false, Some(s)) => {
                runs.push((s, i - 1));
                start = None;
            }
            _ => {}
        }
    }
    if let Some(s) = start {
        runs.push((s, n - 1));
    }
    runs
}

/// Takes L1..L3 and M1..M3 at B, C, D from the trace.
pub fn extract(
    trace: &Trace,
    proc: &Procedure,
    how: Extraction,
) -> Result<[PointValue; 3], BacklashError> {
    let n = trace.scale_mm.len();
    if n == 0 || trace.encoder_mm.len() != n || trace.period_s.is_nan() || trace.period_s <= 0.0 {
        return Err(BacklashError::Extraction(format!(
            "{n} scale and {} encoder samples at period {} s",
            trace.encoder_mm.len(),
            trace.period_s
        )));
    }
    let p = proc.points;
    let targets = [("B", p.b_mm), ("C", p.c_mm), ("D", p.d_mm)];
    let runs = standstill_runs(trace, proc.feed_mm_per_min);
    let min_run = ((0.25 * proc.dwell_s / trace.period_s) as usize).max(2 * MIN_PLATEAU_SAMPLES);
    let mut out = Vec::with_capacity(3);
    let mut after = 0;
    for (name, target_mm) in targets {
        let run = runs.iter().find(|&&(first, last)| {
            first >= after
                && last + 1 - first >= min_run
                && (mean(&trace.scale_mm[first..=last]) - target_mm).abs() < POINT_TOLERANCE_MM
        });
        let Some(&(first, last)) = run else {
            return Err(BacklashError::Extraction(format!(
                "no standstill of at least {:.3} s at {name} = {target_mm} mm after sample {after} ({} standstill runs in {n} samples)",
                min_run as f64 * trace.period_s,
                runs.len()
            )));
        };
        let (from, to) = match how {
            Extraction::Plateau => (first + (last + 1 - first) / 2, last),
            Extraction::ArrivalSample => {
                let i = (after..=last)
                    .find(|&i| (trace.scale_mm[i] - target_mm).abs() <= ARRIVAL_WINDOW_MM)
                    .unwrap_or(first);
                (i, i)
            }
        };
        out.push(PointValue {
            target_mm,
            first: from,
            last: to,
            scale_mm: mean(&trace.scale_mm[from..=to]),
            encoder_mm: mean(&trace.encoder_mm[from..=to]),
        });
        after = last + 1;
    }
    match <[PointValue; 3]>::try_from(out) {
        Ok(values) => Ok(values),
        Err(_) => Err(BacklashError::Extraction("three points expected".into())),
    }
}

/// The seed's displacements and backlash values, mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Backlash {
    /// L1..L3: scale at B, C, D.
    pub l_mm: [f64; 3],
    /// M1..M3: encoder at B, C, D.
    pub m_mm: [f64; 3],
    /// H1 = |L1 - L2|.
    pub scale_h1_mm: f64,
    /// H2 = |L2 - L3|.
    pub scale_h2_mm: f64,
    /// h1 = |M1 - M2|.
    pub encoder_h1_mm: f64,
    /// h2 = |M2 - M3|.
    pub encoder_h2_mm: f64,
    /// F1 = |h1 - H1|: positive-direction backlash.
    pub f1_mm: f64,
    /// F2 = |h2 - H2|: negative-direction backlash.
    pub f2_mm: f64,
}

impl Backlash {
    /// Formulas 1..6 of the seed.
    pub fn from_values(l_mm: [f64; 3], m_mm: [f64; 3]) -> Self {
        let [l1, l2, l3] = l_mm;
        let [m1, m2, m3] = m_mm;
        let scale_h1_mm = (l1 - l2).abs();
        let scale_h2_mm = (l2 - l3).abs();
        let encoder_h1_mm = (m1 - m2).abs();
        let encoder_h2_mm = (m2 - m3).abs();
        Self {
            l_mm,
            m_mm,
            scale_h1_mm,
            scale_h2_mm,
            encoder_h1_mm,
            encoder_h2_mm,
            f1_mm: (encoder_h1_mm - scale_h1_mm).abs(),
            f2_mm: (encoder_h2_mm - scale_h2_mm).abs(),
        }
    }

    /// From extracted point values.
    pub fn from_points(points: &[PointValue; 3]) -> Self {
        Self::from_values(points.map(|p| p.scale_mm), points.map(|p| p.encoder_mm))
    }

    /// The value for MD32450 (one value per axis): mean of F1 and F2, mm.
    pub fn md32450_mm(&self) -> f64 {
        0.5 * (self.f1_mm + self.f2_mm)
    }
}

/// Everything one test produced.
#[derive(Debug, Clone, PartialEq)]
pub struct Outcome {
    /// The procedure run.
    pub procedure: Procedure,
    /// The trace parameters used.
    pub trace_config: TraceConfig,
    /// The uploaded trace.
    pub trace: Trace,
    /// The plateau values at B, C, D.
    pub points: [PointValue; 3],
    /// The result.
    pub backlash: Backlash,
    /// MD32450 written and read back, mm.
    pub md32450_written_mm: Option<f64>,
    /// Machine time of the move programme (approach to A through the dwell at D), s.
    pub machine_time_s: f64,
    /// Files written.
    pub files: Vec<PathBuf>,
}

/// The report table.
pub fn report(axis: &str, o: &Outcome, sim_note: Option<&str>) -> String {
    let mut s = String::new();
    let p = o.procedure.points;
    let b = &o.backlash;
    let um = |mm: f64| mm * 1000.0;
    let _ = writeln!(
        s,
        "backlash test, axis {axis}{}",
        sim_note.map(|n| format!(" ({n})")).unwrap_or_default()
    );
    let _ = writeln!(
        s,
        "procedure  A {:.3} mm  B {:.3} mm  C {:.3} mm  D {:.3} mm  feed {} mm/min  dwell {} s",
        p.a_mm, p.b_mm, p.c_mm, p.d_mm, o.procedure.feed_mm_per_min, o.procedure.dwell_s
    );
    let t = &o.trace_config;
    let _ = writeln!(
        s,
        "trace      2 channels (encoder, scale), period {} ms, record {:.3} s, trigger scale rising through {:.3} mm, post-trigger delay {} s, {} samples",
        t.period_s * 1000.0,
        t.record_s,
        t.threshold_mm,
        t.delay_s,
        o.trace.scale_mm.len()
    );
    let _ = writeln!(s);
    let _ = writeln!(s, "point  scale L (mm)    encoder M (mm)  plateau (s)");
    for (i, (name, v)) in ["B", "C", "D"].iter().zip(&o.points).enumerate() {
        let _ = writeln!(
            s,
            "{name}  L{n} {:>13.6}  M{n} {:>13.6}  {:.3} .. {:.3}",
            v.scale_mm,
            v.encoder_mm,
            v.first as f64 * o.trace.period_s,
            v.last as f64 * o.trace.period_s,
            n = i + 1
        );
    }
    let _ = writeln!(s);
    let _ = writeln!(
        s,
        "move   scale H (mm)     encoder h (mm)   backlash F (um)"
    );
    let _ = writeln!(
        s,
        "B->C   H1 {:>12.6}  h1 {:>12.6}  F1 {:>9.3}  (positive direction)",
        b.scale_h1_mm,
        b.encoder_h1_mm,
        um(b.f1_mm)
    );
    let _ = writeln!(
        s,
        "C->D   H2 {:>12.6}  h2 {:>12.6}  F2 {:>9.3}  (negative direction)",
        b.scale_h2_mm,
        b.encoder_h2_mm,
        um(b.f2_mm)
    );
    let _ = writeln!(s);
    match o.md32450_written_mm {
        Some(v) => {
            let _ = writeln!(
                s,
                "MD32450 $MA_BACKLASH = {v:.6} mm written (FB3 job) and read back"
            );
        }
        None => {
            let _ = writeln!(
                s,
                "MD32450 $MA_BACKLASH proposal = {:.6} mm (mean of F1, F2; not written: use --write)",
                b.md32450_mm()
            );
        }
    }
    let _ = writeln!(
        s,
        "machine time of the programme (approach to A through the dwell at D): {:.1} s",
        o.machine_time_s
    );
    for f in &o.files {
        let _ = writeln!(s, "wrote {}", f.display());
    }
    s
}

/// Writes the trace as CSV: time (s), encoder (mm), scale (mm).
pub fn write_csv(path: &Path, trace: &Trace) -> Result<(), BacklashError> {
    let mut s = String::from("t_s,encoder_mm,scale_mm\n");
    for (i, (e, l)) in trace.encoder_mm.iter().zip(&trace.scale_mm).enumerate() {
        let _ = writeln!(s, "{:.6},{e:.7},{l:.7}", i as f64 * trace.period_s);
    }
    std::fs::write(path, s).map_err(|e| BacklashError::Io(format!("{}: {e}", path.display())))
}

/// Writes the position-time SVG: both channels, the plateaus at B, C, D marked, and
/// the encoder-minus-scale difference below.
pub fn write_svg(
    path: &Path,
    axis: &str,
    trace: &Trace,
    points: &[PointValue; 3],
) -> Result<(), BacklashError> {
    let io = |e: PlotError| BacklashError::Io(format!("{}: {e}", path.display()));
    let n = trace.scale_mm.len();
    if n == 0 {
        return Err(io(PlotError("empty trace".into())));
    }
    let t = |i: usize| i as f64 * trace.period_s;
    let t_end = t(n - 1).max(trace.period_s);
    let (lo, hi) = plot::extent(trace.encoder_mm.iter().chain(&trace.scale_mm).copied())
        .unwrap_or((-1.0, 1.0));
    let pad = ((hi - lo) * 0.05).max(0.01);
    let diff_um: Vec<f64> = trace
        .encoder_mm
        .iter()
        .zip(&trace.scale_mm)
        .map(|(e, l)| (e - l) * 1000.0)
        .collect();
    let root = plot::canvas(path, (1000, 700)).map_err(io)?;
    let (upper, lower) = root.split_vertically(440);
    let mut chart = plot::Frame::new("t (s)", "position (mm)")
        .caption(
            format!("backlash test, axis {axis}: position against time"),
            20,
        )
        .label_areas(30, 70)
        .draw(&upper, 0.0..t_end, (lo - pad)..(hi + pad))
        .map_err(io)?;
    let channels = [
        (&trace.encoder_mm, plot::RED, "encoder (motor)"),
        (&trace.scale_mm, plot::BLUE, "scale (table)"),
    ];
    for (values, color, label) in channels {
        let pts = (0..n).map(|i| (t(i), values[i]));
        plot::line(&mut chart, pts, color, Some(label.into())).map_err(io)?;
    }
    for (name, v) in ["B", "C", "D"].iter().zip(points) {
        let (t0, t1) = (t(v.first), t(v.last));
        let plateau = plot::BLACK.stroke_width(3);
        plot::segment(&mut chart, (t0, v.scale_mm), (t1, v.scale_mm), plateau).map_err(io)?;
        // At the plateau's end, right-aligned: D sits at the right edge.
        let text = format!("{name}: L={:.4} M={:.4}", v.scale_mm, v.encoder_mm);
        plot::note(&mut chart, text, (t1, v.scale_mm + pad * 0.5), 14).map_err(io)?;
    }
    plot::legend(&mut chart, plot::SeriesLabelPosition::MiddleRight).map_err(io)?;
    let y = plot::padded(diff_um.iter().copied(), 0.05, 1.0, (-1.0, 1.0));
    let mut diff = plot::Frame::new("t (s)", "encoder - scale (um)")
        .label_areas(30, 70)
        .draw(&lower, 0.0..t_end, y)
        .map_err(io)?;
    let pts = (0..n).map(|i| (t(i), diff_um[i]));
    plot::line(&mut diff, pts, plot::BLACK, None).map_err(io)?;
    for v in points {
        let d = (v.encoder_mm - v.scale_mm) * 1000.0;
        let plateau = plot::RED.stroke_width(3);
        plot::segment(&mut diff, (t(v.first), d), (t(v.last), d), plateau).map_err(io)?;
    }
    plot::finish(&root).map_err(io)
}

/// Register I/O on the NC axis module's servo block.
struct ServoClient {
    link: ModbusLink,
    unit: u8,
}

impl ServoClient {
    async fn read(&mut self, start: u16, count: u16) -> Result<Vec<u16>, BacklashError> {
        Ok(self
            .link
            .read(self.unit, RegisterKind::Holding, start, count)
            .await?)
    }

    async fn write(&mut self, start: u16, words: &[u16]) -> Result<(), BacklashError> {
        Ok(self.link.write(self.unit, start, words).await?)
    }

    async fn status(&mut self) -> Result<Vec<u16>, BacklashError> {
        self.read(ncmap::SERVO_STATUS, ncmap::SERVO_STATUS_LEN)
            .await
    }
}

fn reg(status: &[u16], address: u16) -> u16 {
    status
        .get(usize::from(address - ncmap::SERVO_STATUS))
        .copied()
        .unwrap_or(0)
}

fn f64_reg(status: &[u16], address: u16) -> f64 {
    let at = usize::from(address - ncmap::SERVO_STATUS);
    status
        .get(at..at + 4)
        .and_then(|r| <[u16; 4]>::try_from(r).ok())
        .map_or(f64::NAN, ncmap::regs_to_f64)
}

fn link_to(address: &str) -> ModbusLink {
    ModbusLink::new(
        LinkSpec::Tcp {
            address: address.to_string(),
            connect_timeout: Duration::from_secs(3),
        },
        Duration::from_secs(2),
        Backoff::new(Duration::from_millis(100), Duration::from_secs(2)),
    )
}

/// Runs the test on the NC axis module at `address` and returns everything measured.
pub async fn run_on(address: &str, args: &BacklashArgs) -> Result<Outcome, BacklashError> {
    let procedure = Procedure::from_args(args);
    procedure.validate(None)?;
    let mut nc = ServoClient {
        link: link_to(address),
        unit: args.unit,
    };
    // The axis limits and the highest feed come from the NC; check them before moving.
    let status = nc.status().await?;
    let rb = nc.read(ncmap::READBACK, ncmap::READBACK_LEN).await?;
    let at = usize::from(ncmap::RB_MAX_AX_VELO - ncmap::READBACK);
    let max_feed = rb
        .get(at..at + 4)
        .and_then(|r| <[u16; 4]>::try_from(r).ok())
        .map_or(f64::NAN, ncmap::regs_to_f64);
    procedure.validate(Some((
        f64_reg(&status, ncmap::AXIS_MIN),
        f64_reg(&status, ncmap::AXIS_MAX),
        max_feed,
    )))?;
    if reg(&status, ncmap::MV_STATE) == 1 {
        return Err(BacklashError::Refused {
            what: "move programme",
            code: 5,
        });
    }

    // Arm the trace first, so it is waiting when the axis arrives at A.
    let cfg = procedure.trace_config();
    let mut words = vec![cfg.trigger as u16, 0];
    for v in [cfg.period_s, cfg.record_s, cfg.threshold_mm, cfg.delay_s] {
        words.extend_from_slice(&ncmap::f64_to_regs(v));
    }
    words.push(1);
    nc.write(ncmap::TR_TRIGGER, &words).await?;
    let status = nc.status().await?;
    if reg(&status, ncmap::TR_STATUS) != 0 {
        return Err(BacklashError::Refused {
            what: "servo trace",
            code: reg(&status, ncmap::TR_STATUS),
        });
    }

    // The programme and its start in one write.
    let steps = procedure.program();
    let mut words = vec![1, steps.len() as u16];
    for s in &steps {
        for v in [s.target_mm, s.feed_mm_per_min, s.dwell_s] {
            words.extend_from_slice(&ncmap::f64_to_regs(v));
        }
    }
    nc.write(ncmap::MV_CMD, &words).await?;
    tracing::info!(axis = %args.axis, nc = address, "backlash test programme started");

    // Wait for the programme and the trace; real time bounds the wait at the
    // programme's own duration plus a margin.
    let move_s: f64 = {
        let mut from = f64_reg(&status, ncmap::SCALE_POS);
        let mut total = 0.0;
        for s in &steps {
            total += (s.target_mm - from).abs() / (s.feed_mm_per_min / 60.0) + 1.0 + s.dwell_s;
            from = s.target_mm;
        }
        total
    };
    let deadline =
        tokio::time::Instant::now() + Duration::from_secs_f64(move_s + cfg.record_s + 30.0);
    let status = loop {
        let status = nc.status().await?;
        match reg(&status, ncmap::MV_STATE) {
            3 => {
                return Err(BacklashError::Refused {
                    what: "move programme",
                    code: reg(&status, ncmap::MV_STATUS),
                })
            }
            2 if reg(&status, ncmap::TR_STATE) == 4 => break status,
            2 if reg(&status, ncmap::TR_STATE) <= 1 => {
                return Err(BacklashError::Timeout(format!(
                    "the programme ended but the trace never triggered (scale rising through {} mm)",
                    cfg.threshold_mm
                )))
            }
            _ => {}
        }
        if tokio::time::Instant::now() >= deadline {
            return Err(BacklashError::Timeout(format!(
                "programme step {}, trace state {} after {:.0} s",
                reg(&status, ncmap::MV_STEP),
                reg(&status, ncmap::TR_STATE),
                move_s + cfg.record_s + 30.0
            )));
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };

    // Upload, page by page.
    let count = ncmap::regs_to_u32([
        reg(&status, ncmap::TR_COUNT),
        reg(&status, ncmap::TR_COUNT + 1),
    ]);
    let per_page = u32::from(ncmap::TR_PAGE_SAMPLES);
    let mut trace = Trace {
        period_s: cfg.period_s,
        ..Trace::default()
    };
    for page in 0..count.div_ceil(per_page) {
        let page_u16 = u16::try_from(page).map_err(|_| {
            BacklashError::Extraction(format!("{count} samples exceed the page index"))
        })?;
        nc.write(ncmap::TR_PAGE, &[page_u16]).await?;
        let w = nc.read(ncmap::TR_WINDOW, ncmap::TR_WINDOW_LEN).await?;
        let in_page = (count - page * per_page).min(per_page) as usize;
        for k in 0..in_page {
            let f = |at: usize| ncmap::regs_to_f64([w[at], w[at + 1], w[at + 2], w[at + 3]]);
            trace.encoder_mm.push(f(8 * k));
            trace.scale_mm.push(f(8 * k + 4));
        }
    }
    let machine_time_s =
        f64_reg(&status, ncmap::MV_END_TIME_S) - f64_reg(&status, ncmap::MV_START_TIME_S);

    let points = extract(&trace, &procedure, Extraction::Plateau)?;
    let backlash = Backlash::from_points(&points);

    let mut files = Vec::new();
    if let Some(dir) = &args.out {
        std::fs::create_dir_all(dir)
            .map_err(|e| BacklashError::Io(format!("{}: {e}", dir.display())))?;
        let stem: String = args
            .axis
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
            .collect();
        let svg = dir.join(format!("backlash_{stem}.svg"));
        write_svg(&svg, &args.axis, &trace, &points)?;
        let csv = dir.join(format!("backlash_{stem}_trace.csv"));
        write_csv(&csv, &trace)?;
        files.push(svg);
        files.push(csv);
    }

    let mut md32450_written_mm = None;
    if args.write {
        let value = backlash.md32450_mm();
        if !(0.0..=compgate_ncproto::MD32450_LIMIT_MM).contains(&value) {
            return Err(BacklashError::Invalid(vec![format!(
                "MD32450 = {value} mm is outside 0 ..= {} mm; not written",
                compgate_ncproto::MD32450_LIMIT_MM
            )]));
        }
        let mut writer = ModbusNcWriter::new(link_to(address), args.unit, Duration::from_secs(5));
        writer
            .write_job(&Job {
                pairs: vec![(var::MD32450, value)],
            })
            .await?;
        let snapshot = writer.read_snapshot().await?;
        if snapshot.md32450_mm.to_bits() != value.to_bits() {
            return Err(NcError::ReadBack {
                var: var::MD32450,
                written: value,
                read: snapshot.md32450_mm,
            }
            .into());
        }
        md32450_written_mm = Some(snapshot.md32450_mm);
    }

    Ok(Outcome {
        procedure,
        trace_config: cfg,
        trace,
        points,
        backlash,
        md32450_written_mm,
        machine_time_s,
        files,
    })
}

/// Checks everything about the arguments that can be checked offline, before any
/// connection is made.
pub fn check_args(args: &BacklashArgs) -> Result<(), BacklashError> {
    let mut problems = match Procedure::from_args(args).validate(None) {
        Err(BacklashError::Invalid(p)) => p,
        _ => Vec::new(),
    };
    match (&args.nc, args.sim) {
        (Some(_), true) => problems.push("--nc and --sim exclude each other".into()),
        (None, false) => problems.push("give --nc ADDRESS or --sim".into()),
        _ => {}
    }
    if problems.is_empty() {
        Ok(())
    } else {
        Err(BacklashError::Invalid(problems))
    }
}

/// `compgate backlash --nc ADDRESS`: runs the test on the NC and returns the report
/// table. (`--sim` is the binary's: it serves the simulated axis, then calls
/// [`run_on`].)
pub async fn run(args: &BacklashArgs) -> Result<String, BacklashError> {
    check_args(args)?;
    let Some(address) = &args.nc else {
        return Err(BacklashError::Invalid(vec!["give --nc ADDRESS".into()]));
    };
    let outcome = run_on(address, args).await?;
    Ok(report(&args.axis, &outcome, None))
}

#[cfg(test)]
mod tests;
