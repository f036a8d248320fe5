//! SVG plots of a scenario: error against time and against position, off and on.

use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;

use super::{RunData, ScenarioReport};

type Area<'a> = DrawingArea<SVGBackend<'a>, Shift>;

fn range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
        (a.min(v), b.max(v))
    });
    if !lo.is_finite() {
        return (-1.0, 1.0);
    }
    let pad = ((hi - lo) * 0.08).max(0.5);
    (lo - pad, hi + pad)
}

/// Rows of `run` at position `pos_mm` approached in `dir`: (t in h, err um).
fn at_position(run: &RunData, pos_mm: f64, dir: i8) -> Vec<(f64, f64)> {
    let m = &run.series;
    (0..m.len())
        .filter(|&i| m.pos_mm[i] == pos_mm && m.dir[i] == dir)
        .map(|i| (m.t_s[i] / 3600.0, m.err_um[i]))
        .collect()
}

fn time_panel(
    area: &Area<'_>,
    caption: &str,
    r: &ScenarioReport,
    runs: &[(&str, &RunData, RGBColor)],
) -> Result<(), String> {
    let e = |x: &dyn std::fmt::Display| x.to_string();
    let far = r
        .off
        .series
        .pos_mm
        .iter()
        .copied()
        .fold(f64::NEG_INFINITY, f64::max);
    let near = r
        .off
        .series
        .pos_mm
        .iter()
        .copied()
        .fold(f64::INFINITY, f64::min);
    let mut lines = Vec::new();
    for (name, run, color) in runs {
        lines.push((
            format!("{name}, at {far:.0} mm"),
            at_position(run, far, 1),
            *color,
            2,
        ));
        lines.push((
            format!("{name}, at {near:.0} mm"),
            at_position(run, near, 1),
            *color,
            1,
        ));
    }
    let (lo, hi) = range(lines.iter().flat_map(|l| l.1.iter().map(|p| p.1)));
    let mut chart = ChartBuilder::on(area)
        .caption(caption, ("sans-serif", 17))
        .margin(10)
        .x_label_area_size(32)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..r.hours, lo..hi)
        .map_err(|x| e(&x))?;
    chart
        .configure_mesh()
        .x_desc("time (h)")
        .y_desc("error (um)")
        .draw()
        .map_err(|x| e(&x))?;
    for (label, pts, color, width) in lines {
        let style = color.stroke_width(width);
        chart
            .draw_series(LineSeries::new(pts, style))
            .map_err(|x| e(&x))?
            .label(label)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], style));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|x| e(&x))?;
    Ok(())
}

/// Error at both ends of the axis against time; upper panel off and on, lower panel
/// on alone at its own scale.
pub fn error_vs_time(path: &Path, r: &ScenarioReport) -> Result<(), String> {
    let root = SVGBackend::new(path, (1000, 760)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| x.to_string())?;
    let (upper, lower) = root.split_vertically(400);
    time_panel(
        &upper,
        &format!(
            "thermal positioning error, {} h: off p-p {:.1} um, on p-p {:.1} um ({:.1} % less)",
            r.hours,
            r.off.stats.peak_to_peak_um,
            r.on.stats.peak_to_peak_um,
            r.reduction_pp_percent()
        ),
        r,
        &[("off", &r.off, RED), ("on", &r.on, BLUE)],
    )?;
    time_panel(
        &lower,
        "compensation on (own scale)",
        r,
        &[("on", &r.on, BLUE)],
    )?;
    root.present().map_err(|x| x.to_string())
}

fn position_panel(area: &Area<'_>, caption: &str, run: &RunData, hours: f64) -> Result<(), String> {
    let e = |x: &dyn std::fmt::Display| x.to_string();
    let m = &run.series;
    let sweeps = compgate_commission::calibrate::sweeps(&m.t_s);
    let step = sweeps.len().div_ceil(10).max(1);
    let (xlo, xhi) = m
        .pos_mm
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(*v), b.max(*v))
        });
    let (lo, hi) = range(m.err_um.iter().copied());
    let mut chart = ChartBuilder::on(area)
        .caption(caption, ("sans-serif", 17))
        .margin(10)
        .x_label_area_size(32)
        .y_label_area_size(60)
        .build_cartesian_2d(xlo..xhi.max(xlo + 1.0), lo..hi)
        .map_err(|x| e(&x))?;
    chart
        .configure_mesh()
        .x_desc("position (mm)")
        .y_desc("error (um)")
        .draw()
        .map_err(|x| e(&x))?;
    for r in sweeps.into_iter().step_by(step) {
        let t_h = m.t_s[r.start] / 3600.0;
        // Colour runs from blue (start) to red (end of the run).
        let f = (t_h / hours.max(1e-9)).clamp(0.0, 1.0);
        let color = RGBColor((255.0 * f) as u8, 40, (255.0 * (1.0 - f)) as u8);
        for dir in [1i8, -1] {
            let pts: Vec<(f64, f64)> = r
                .clone()
                .filter(|&i| m.dir[i] == dir)
                .map(|i| (m.pos_mm[i], m.err_um[i]))
                .collect();
            let series = chart
                .draw_series(LineSeries::new(
                    pts,
                    color.stroke_width(if dir > 0 { 2 } else { 1 }),
                ))
                .map_err(|x| e(&x))?;
            if dir > 0 {
                series
                    .label(format!("t = {t_h:.1} h"))
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color));
            }
        }
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|x| e(&x))?;
    Ok(())
}

/// Error curves along the axis (thick: approached +, thin: approached -), off and on.
pub fn error_vs_position(path: &Path, r: &ScenarioReport) -> Result<(), String> {
    let root = SVGBackend::new(path, (1200, 560)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| x.to_string())?;
    let (left, right) = root.split_horizontally(600);
    position_panel(
        &left,
        &format!(
            "compensation off: p-p {:.1} um",
            r.off.stats.peak_to_peak_um
        ),
        &r.off,
        r.hours,
    )?;
    position_panel(
        &right,
        &format!("compensation on: p-p {:.1} um", r.on.stats.peak_to_peak_um),
        &r.on,
        r.hours,
    )?;
    root.present().map_err(|x| x.to_string())
}
