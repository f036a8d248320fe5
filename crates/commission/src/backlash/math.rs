//! The backlash test's pure part: the procedure and its checks, the plateaus of the
//! trace, and the seed's formulas. No I/O, no tokio.

use compgate_ncproto::servo::{MoveStep, TraceConfig, Trigger};

use super::{
    BacklashError, ARRIVAL_WINDOW_MM, BACKOFF_MM, COMMAND_STILL_MM, MIN_DWELL_S,
    MIN_PLATEAU_SAMPLES, MIN_STROKE_MM, POINT_TOLERANCE_MM, PRE_TRAVEL_MM, SETTLED_DRIFT_MM,
    SETTLE_WINDOW_S, SMOOTH_S, TOLERANCE_FRACTION, TOLERANCE_MM, TRIGGER_BELOW_A_MM,
    VELOCITY_SPAN_S,
};
use crate::stats::mean;

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
    /// Position command (interpolator output) per sample, mm; empty when the trace
    /// has no command channel. Where present it marks the dwells.
    pub command_mm: Vec<f64>,
}

/// How L and M are taken from the trace.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Extraction {
    /// Mean over the settled part of the dwell at each point: where encoder and scale
    /// both stand still.
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
    /// Time from the start of the dwell until encoder and scale both stood still, s.
    pub settle_s: f64,
}

/// Standstill runs (first, last inclusive): of the command where the trace has one,
/// else of the scale.
fn standstill_runs(trace: &Trace, feed_mm_per_min: f64) -> Vec<(usize, usize)> {
    let n = trace.scale_mm.len();
    let still: Vec<bool> = if trace.command_mm.len() == n {
        (0..n)
            .map(|i| {
                let lo = i.saturating_sub(1);
                let hi = (i + 1).min(n - 1);
                (trace.command_mm[hi] - trace.command_mm[lo]).abs() < COMMAND_STILL_MM
            })
            .collect()
    } else {
        let w = ((VELOCITY_SPAN_S / trace.period_s / 2.0).round() as usize).max(1);
        let v_limit = (0.01 * feed_mm_per_min / 60.0).max(0.02);
        (0..n)
            .map(|i| {
                let lo = i.saturating_sub(w);
                let hi = (i + w).min(n - 1);
                let span_s = (hi - lo) as f64 * trace.period_s;
                hi == lo || (trace.scale_mm[hi] - trace.scale_mm[lo]).abs() / span_s < v_limit
            })
            .collect()
    };
    let mut runs = Vec::new();
    let mut start = None;
    for (i, s) in still.iter().enumerate() {
        match (*s, start) {
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

/// Least-squares slope (mm per sample) and residual standard deviation (mm) of `v`.
fn slope_sd(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    if v.len() < 3 {
        return (0.0, 0.0);
    }
    let xm = (n - 1.0) / 2.0;
    let ym = mean(v);
    let (mut sxy, mut sxx) = (0.0, 0.0);
    for (i, y) in v.iter().enumerate() {
        let dx = i as f64 - xm;
        sxy += dx * (y - ym);
        sxx += dx * dx;
    }
    let b = sxy / sxx;
    let ss: f64 = v
        .iter()
        .enumerate()
        .map(|(i, y)| (y - ym - b * (i as f64 - xm)).powi(2))
        .sum();
    (b, (ss / (n - 2.0)).sqrt())
}

/// How far a channel drifts over `v`, mm, and the limit its noise allows, mm: the
/// fitted drift must stay under [`SETTLED_DRIFT_MM`] or three standard errors of it.
fn drift(v: &[f64]) -> (f64, f64) {
    let (b, sd) = slope_sd(v);
    let n = v.len() as f64;
    let span = n - 1.0;
    let se = sd * (12.0 / n).sqrt();
    ((b * span).abs(), SETTLED_DRIFT_MM.max(3.0 * se))
}

/// The settled part of the dwell `first..=last` at a point: the earliest start from
/// which both channels stand still to the dwell's end, no later than half the dwell
/// (the settling limit: a slow creep hides in the noise of a short tail, so at least
/// half the dwell must be still). Err names the channel still moving and how fast.
fn settle(trace: &Trace, first: usize, last: usize) -> Result<usize, String> {
    let window = ((SETTLE_WINDOW_S / trace.period_s).round() as usize).max(MIN_PLATEAU_SAMPLES);
    let step = (window / 4).max(1);
    let latest = first + (last + 1 - first) / 2;
    let mut s = first;
    while s <= latest && last + 1 >= s + window {
        let still = |v: &[f64]| {
            let (d, lim) = drift(&v[s..s + window]);
            let (dt, limt) = drift(&v[s..=last]);
            d <= lim && dt <= limt
        };
        if still(&trace.encoder_mm) && still(&trace.scale_mm) {
            return Ok(s);
        }
        s += step;
    }
    // Never settled: name what still moves over the dwell's second half.
    let from = latest.min(last);
    let rate = |v: &[f64]| {
        let (b, _) = slope_sd(&v[from..=last]);
        b / trace.period_s * 1000.0
    };
    let (enc, scale) = (rate(&trace.encoder_mm), rate(&trace.scale_mm));
    Err(format!(
        "encoder and scale never both stood still over the second half of the {:.3} s dwell; there the encoder moves {enc:+.2} um/s and the scale {scale:+.2} um/s{}",
        (last + 1 - first) as f64 * trace.period_s,
        if enc.abs() > 3.0 * scale.abs() {
            " (the motor is still creeping across the gap while the table stands)"
        } else {
            ""
        }
    ))
}

/// Takes L1..L3 and M1..M3 at B, C, D from the trace.
///
/// With [`Extraction::Plateau`] each value is the mean over the dwell's settled part,
/// where encoder and scale both stand still (drift within [`SETTLED_DRIFT_MM`] or the
/// noise). Refused, with the reason, when a point never settles within its dwell, or
/// when the motor backed off against the move during the dwell (an overshooting loop:
/// the motor then sits inside the gap or on its far side, and F is not the backlash).
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
    let targets = [("B", p.b_mm, 1.0), ("C", p.c_mm, -1.0), ("D", p.d_mm, 1.0)];
    let runs = standstill_runs(trace, proc.feed_mm_per_min);
    let min_run = ((0.25 * proc.dwell_s / trace.period_s) as usize).max(2 * MIN_PLATEAU_SAMPLES);
    let mut out = Vec::with_capacity(3);
    let mut after = 0;
    for (name, target_mm, dir) in targets {
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
            Extraction::Plateau => {
                let from = settle(trace, first, last).map_err(|why| {
                    BacklashError::Extraction(format!("{name} = {target_mm} mm: {why}; lengthen --dwell, or lower the feed or the position loop gain"))
                })?;
                backed_off(trace, first, from, last, dir).map_err(|why| {
                    BacklashError::Extraction(format!("{name} = {target_mm} mm: {why}"))
                })?;
                (from, last)
            }
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
            settle_s: (from - first) as f64 * trace.period_s,
        });
        after = last + 1;
    }
    match <[PointValue; 3]>::try_from(out) {
        Ok(values) => Ok(values),
        Err(_) => Err(BacklashError::Extraction("three points expected".into())),
    }
}

/// Refuses a dwell in which the motor went back against the move (direction `dir`)
/// by more than the noise allows: then it no longer sits at the gap's far side.
/// Smoothed over [`SMOOTH_S`] so that noise alone does not trip it.
fn backed_off(
    trace: &Trace,
    first: usize,
    settled: usize,
    last: usize,
    dir: f64,
) -> Result<(), String> {
    let enc = &trace.encoder_mm;
    let settled_mm = mean(&enc[settled..=last]);
    let k = ((SMOOTH_S / trace.period_s).round() as usize).clamp(1, last + 1 - first);
    let (_, sd) = slope_sd(&enc[settled..=last]);
    let limit_mm = BACKOFF_MM.max(5.0 * sd / (k as f64).sqrt());
    let mut sum: f64 = enc[first..first + k].iter().sum();
    let mut worst = (0.0f64, first);
    for i in first + k..=last + 1 {
        let beyond = dir * (sum / k as f64 - settled_mm);
        if beyond > worst.0 {
            worst = (beyond, i - k);
        }
        if i <= last {
            sum += enc[i] - enc[i - k];
        }
    }
    if worst.0 > limit_mm {
        return Err(format!(
            "the motor went back {:.2} um against the move during the dwell ({:.3} s after it began) while the table stood: the position loop overshoots and the motor no longer rests on the far side of the gap, so F would not be the backlash; lower the position loop gain or damp the axis",
            worst.0 * 1000.0,
            (worst.1 - first) as f64 * trace.period_s
        ));
    }
    Ok(())
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

    /// The acceptance tolerance at this backlash: max([`TOLERANCE_MM`],
    /// [`TOLERANCE_FRACTION`] of the mean of F1 and F2), mm.
    pub fn tolerance_mm(&self) -> f64 {
        TOLERANCE_MM.max(TOLERANCE_FRACTION * self.md32450_mm())
    }

    /// F1 and F2 differ by more than [`Self::tolerance_mm`]: one backlash value for
    /// the axis does not describe it (friction windup, lead error, or an axis that
    /// did not settle). Returns the difference, mm.
    pub fn disagreement_mm(&self) -> Option<f64> {
        let d = (self.f1_mm - self.f2_mm).abs();
        (d > self.tolerance_mm()).then_some(d)
    }

    /// The moves in which the scale (the table) went further than the encoder (the
    /// motor) by more than [`Self::tolerance_mm`]: lost motion only ever makes the
    /// table go less far, so this is a trace whose `encoder_mm` and `scale_mm` are
    /// swapped (F = |h - H| hides the sign). Per move B->C, C->D: H - h, mm.
    pub fn table_ahead_mm(&self) -> Vec<(&'static str, f64)> {
        [
            ("B->C", self.scale_h1_mm - self.encoder_h1_mm),
            ("C->D", self.scale_h2_mm - self.encoder_h2_mm),
        ]
        .into_iter()
        .filter(|&(_, d)| d > self.tolerance_mm())
        .collect()
    }

    /// The value for MD32450 (one value per axis): mean of F1 and F2, mm.
    pub fn md32450_mm(&self) -> f64 {
        0.5 * (self.f1_mm + self.f2_mm)
    }
}
