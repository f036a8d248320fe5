//! SVG plots of a scenario: error against time and against position, off and on.

use std::ops::Range;

use compgate_commission::plot::{self, Area, Chart, Color as _, DrawError, RGBColor};

use super::{LoopReport, RunData, ScenarioReport};

/// A panel of the scenario's charts: error (um) against `x_desc`.
fn panel<'a, 'p>(
    area: &'a Area<'p>,
    caption: &str,
    x_desc: &str,
    x: Range<f64>,
    y: Range<f64>,
) -> Result<Chart<'a, 'p>, DrawError> {
    plot::Frame::new(x_desc, "error (um)")
        .caption(caption, 17)
        .label_areas(32, 60)
        .draw(area, x, y)
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
) -> Result<(), DrawError> {
    let (near, far) = plot::extent(r.off.series.pos_mm.iter().copied())
        .unwrap_or((f64::INFINITY, f64::NEG_INFINITY));
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
    let y = plot::padded(
        lines.iter().flat_map(|l| l.1.iter().map(|p| p.1)),
        0.08,
        0.5,
        (-0.5, 0.5),
    );
    let mut chart = panel(area, caption, "time (h)", 0.0..r.hours, y)?;
    for (label, pts, color, width) in lines {
        plot::line(&mut chart, pts, color.stroke_width(width), Some(label))?;
    }
    plot::legend(&mut chart, plot::SeriesLabelPosition::UpperLeft)
}

/// Error at both ends of the axis against time; upper panel off and on, lower panel
/// on alone at its own scale.
pub fn error_vs_time(r: &ScenarioReport) -> Result<String, DrawError> {
    plot::render((1000, 760), |root| {
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
            &[("off", &r.off, plot::RED), ("on", &r.on, plot::BLUE)],
        )?;
        time_panel(
            &lower,
            "compensation on (own scale)",
            r,
            &[("on", &r.on, plot::BLUE)],
        )
    })
}

fn position_panel(
    area: &Area<'_>,
    caption: &str,
    run: &RunData,
    hours: f64,
) -> Result<(), DrawError> {
    let m = &run.series;
    let sweeps = compgate_commission::calibrate::sweeps(&m.t_s);
    let step = sweeps.len().div_ceil(10).max(1);
    let (xlo, xhi) =
        plot::extent(m.pos_mm.iter().copied()).unwrap_or((f64::INFINITY, f64::NEG_INFINITY));
    let y = plot::padded(m.err_um.iter().copied(), 0.08, 0.5, (-0.5, 0.5));
    let mut chart = panel(area, caption, "position (mm)", xlo..xhi.max(xlo + 1.0), y)?;
    for r in sweeps.into_iter().step_by(step) {
        let t_h = m.t_s[r.start] / 3600.0;
        // Colour runs from blue (start) to red (end of the run).
        let color = plot::blue_to_red(t_h / hours.max(1e-9), 40);
        for dir in [1i8, -1] {
            let pts: Vec<(f64, f64)> = r
                .clone()
                .filter(|&i| m.dir[i] == dir)
                .map(|i| (m.pos_mm[i], m.err_um[i]))
                .collect();
            // One legend entry per sweep: its + direction.
            let (width, label) = if dir > 0 {
                (2, Some(format!("t = {t_h:.1} h")))
            } else {
                (1, None)
            };
            plot::line(&mut chart, pts, color.stroke_width(width), label)?;
        }
    }
    plot::legend(&mut chart, plot::SeriesLabelPosition::UpperLeft)
}

/// Error curves along the axis (thick: approached +, thin: approached -), off and on.
pub fn error_vs_position(r: &ScenarioReport) -> Result<String, DrawError> {
    plot::render((1200, 560), |root| {
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
        )
    })
}

/// The loop's before and after against time: baseline model (calibrate on the
/// records) and diagnosed model, at both ends of the axis.
pub fn loop_vs_time(r: &ScenarioReport, l: &LoopReport) -> Result<String, DrawError> {
    let green = RGBColor(0, 140, 60);
    plot::render((1000, 420), |root| {
        time_panel(
            root,
            &format!(
                "closed loop, {} h: baseline p-p {:.1} um ({:.1} % less than off), diagnosed p-p {:.1} um ({:.1} % less)",
                r.hours,
                r.on.stats.peak_to_peak_um,
                r.reduction_pp_percent(),
                l.updated.stats.peak_to_peak_um,
                r.reduction_pp_updated_percent().unwrap_or(0.0)
            ),
            r,
            &[
                ("baseline", &r.on, plot::BLUE),
                ("diagnosed", &l.updated, green),
            ],
        )
    })
}

/// The loop's before and after along the axis: baseline and diagnosed model.
pub fn loop_vs_position(r: &ScenarioReport, l: &LoopReport) -> Result<String, DrawError> {
    plot::render((1200, 560), |root| {
        let (left, right) = root.split_horizontally(600);
        position_panel(
            &left,
            &format!("baseline model: p-p {:.1} um", r.on.stats.peak_to_peak_um),
            &r.on,
            r.hours,
        )?;
        position_panel(
            &right,
            &format!(
                "diagnosed model: p-p {:.1} um",
                l.updated.stats.peak_to_peak_um
            ),
            &l.updated,
            r.hours,
        )
    })
}
