//! What the backlash test shows and writes: the report table, the trace CSV and the
//! position-time SVG.

use std::fmt::Write as _;
use std::path::Path;

use super::math::{PointValue, Trace};
use super::{BacklashError, Outcome};
use crate::plot::{self, Color as _, PlotError};

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
    if let Some(file) = &o.trace_file {
        let _ = writeln!(
            s,
            "trace      file {}, {} samples at {:.4} ms{}",
            file.display(),
            o.trace.scale_mm.len(),
            t.period_s * 1000.0,
            if o.trace.command_mm.is_empty() {
                " (encoder, scale; dwells found from the scale)"
            } else {
                " (encoder, scale, command; dwells from the command)"
            }
        );
    } else {
        let _ = writeln!(
        s,
        "trace      2 channels (encoder, scale), period {} ms, record {:.3} s, trigger scale rising through {:.3} mm, post-trigger delay {} s, {} samples",
        t.period_s * 1000.0,
        t.record_s,
        t.threshold_mm,
        t.delay_s,
        o.trace.scale_mm.len()
    );
    }
    let _ = writeln!(s);
    let _ = writeln!(
        s,
        "point  scale L (mm)    encoder M (mm)  plateau (s)      settled after (s)"
    );
    for (i, (name, v)) in ["B", "C", "D"].iter().zip(&o.points).enumerate() {
        let _ = writeln!(
            s,
            "{name}  L{n} {:>13.6}  M{n} {:>13.6}  {:.3} .. {:.3}  {:.3}",
            v.scale_mm,
            v.encoder_mm,
            v.first as f64 * o.trace.period_s,
            v.last as f64 * o.trace.period_s,
            v.settle_s,
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
    if let Some(d) = b.disagreement_mm() {
        let _ = writeln!(
            s,
            "WARNING: F1 and F2 differ by {:.3} um, more than the tolerance {:.3} um (max 0.5 um, 2 %): one MD32450 value does not describe this axis. Friction windup adds to both, a lead error over B..C or C..D to one; check the dwells in the plot. MD32450 is not written.",
            d * 1000.0,
            b.tolerance_mm() * 1000.0
        );
    }
    for (mv, d) in b.table_ahead_mm() {
        let _ = writeln!(
            s,
            "WARNING: in {mv} the scale moved {:.3} um further than the encoder: the table cannot move further than the motor through lost motion. Are the encoder and the scale swapped (the trace's encoder_mm and scale_mm columns, or the NC's channels)? F is then not this axis's backlash.",
            d * 1000.0
        );
    }
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
    if o.trace_file.is_none() {
        let _ = writeln!(
            s,
            "machine time of the programme (approach to A through the dwell at D): {:.1} s",
            o.machine_time_s
        );
    }
    for f in &o.files {
        let _ = writeln!(s, "wrote {}", f.display());
    }
    s
}

/// Writes the trace as CSV: time (s), encoder (mm), scale (mm), and the command (mm)
/// where the trace has one; `--trace` reads it back.
pub fn write_csv(path: &Path, trace: &Trace) -> Result<(), BacklashError> {
    let with_command = trace.command_mm.len() == trace.scale_mm.len();
    let mut s = String::from(if with_command {
        "t_s,encoder_mm,scale_mm,command_mm\n"
    } else {
        "t_s,encoder_mm,scale_mm\n"
    });
    for (i, (e, l)) in trace.encoder_mm.iter().zip(&trace.scale_mm).enumerate() {
        let _ = write!(s, "{:.6},{e:.7},{l:.7}", i as f64 * trace.period_s);
        if with_command {
            let _ = write!(s, ",{:.7}", trace.command_mm[i]);
        }
        s.push('\n');
    }
    compgate_core::outputs::write(path, s)
        .map_err(|e| BacklashError::Io(format!("{}: {e}", path.display())))
}

/// Writes the position-time SVG: both channels, the plateaus at B, C, D marked, and
/// the encoder-minus-scale difference below.
pub fn write_svg(
    path: &Path,
    axis: &str,
    trace: &Trace,
    points: &[PointValue; 3],
) -> Result<(), BacklashError> {
    let n = trace.scale_mm.len();
    if n == 0 {
        return Err(BacklashError::Plot(PlotError {
            path: path.display().to_string(),
            message: "empty trace".into(),
        }));
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
    plot::svg(path, (1000, 700), |root| {
        let (upper, lower) = root.split_vertically(440);
        let mut chart = plot::Frame::new("t (s)", "position (mm)")
            .caption(
                format!("backlash test, axis {axis}: position against time"),
                20,
            )
            .label_areas(30, 70)
            .draw(&upper, 0.0..t_end, (lo - pad)..(hi + pad))?;
        let channels = [
            (&trace.encoder_mm, plot::RED, "encoder (motor)"),
            (&trace.scale_mm, plot::BLUE, "scale (table)"),
        ];
        for (values, color, label) in channels {
            let pts = (0..n).map(|i| (t(i), values[i]));
            plot::line(&mut chart, pts, color, Some(label.into()))?;
        }
        for (name, v) in ["B", "C", "D"].iter().zip(points) {
            let (t0, t1) = (t(v.first), t(v.last));
            let plateau = plot::BLACK.stroke_width(3);
            plot::segment(&mut chart, (t0, v.scale_mm), (t1, v.scale_mm), plateau)?;
            // At the plateau's end, right-aligned: D sits at the right edge.
            let text = format!("{name}: L={:.4} M={:.4}", v.scale_mm, v.encoder_mm);
            plot::note(&mut chart, text, (t1, v.scale_mm + pad * 0.5), 14)?;
        }
        plot::legend(&mut chart, plot::SeriesLabelPosition::MiddleRight)?;
        let y = plot::padded(diff_um.iter().copied(), 0.05, 1.0, (-1.0, 1.0));
        let mut diff = plot::Frame::new("t (s)", "encoder - scale (um)")
            .label_areas(30, 70)
            .draw(&lower, 0.0..t_end, y)?;
        let pts = (0..n).map(|i| (t(i), diff_um[i]));
        plot::line(&mut diff, pts, plot::BLACK, None)?;
        for v in points {
            let d = (v.encoder_mm - v.scale_mm) * 1000.0;
            let plateau = plot::RED.stroke_width(3);
            plot::segment(&mut diff, (t(v.first), d), (t(v.last), d), plateau)?;
        }
        Ok(())
    })?;
    Ok(())
}
