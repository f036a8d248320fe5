//! The backlash test's pure part: the procedure and its checks, the plateaus of the
//! trace, and the seed's formulas. No I/O, no tokio.

use compgate_ncproto::servo::{MoveStep, TraceConfig, Trigger};

use super::{
    BacklashError, ARRIVAL_WINDOW_MM, MIN_DWELL_S, MIN_PLATEAU_SAMPLES, MIN_STROKE_MM,
    POINT_TOLERANCE_MM, PRE_TRAVEL_MM, TRIGGER_BELOW_A_MM, VELOCITY_SPAN_S,
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
