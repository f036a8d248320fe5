//! What calibrate shows and writes: the fit report and the SVG of the error curves.

use std::fmt::Write as _;
use std::path::Path;

use compgate_core::measure::Measurements;

use super::{sweeps, Fit};
use crate::plot::{self, Color as _, Palette as _, PlotError};
use crate::stats;
use crate::table::Markdown;

/// The fit report, as printed.
pub fn report(f: &Fit) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "fit: {} rows, {} sensors, P0 = {} mm",
        f.rows,
        f.terms.len(),
        f.p0_mm
    );
    let _ = writeln!(
        s,
        "quality: RMS residual {:.3} um, max |residual| {:.3} um, R^2 {:.6}, condition {:.1e}",
        f.rms_um, f.max_abs_um, f.r2, f.condition
    );
    let _ = writeln!(
        s,
        "K0 offset {:+.4} um (+/- {:.4}), tan(beta) offset {:+.4e} (+/- {:.1e})",
        f.k0_offset_um, f.k0_offset_se_um, f.tan_beta_offset, f.tan_beta_offset_se
    );
    let mut table = Markdown::new([
        "sensor",
        "ref degC",
        "K0 um/K",
        "+/-",
        "tan(beta) 1/K",
        "+/-",
    ]);
    for t in &f.terms {
        table.row([
            t.name.clone(),
            format!("{:.2}", t.ref_degc),
            format!("{:+.4}", t.k0_um_per_degc),
            format!("{:.4}", t.k0_se_um_per_degc),
            format!("{:+.4e}", t.tan_beta_per_degc),
            format!("{:.1e}", t.tan_beta_se_per_degc),
        ]);
    }
    s.push_str(&table.render());
    s.push_str(
        "(+/- : standard errors assuming independent residuals; a lower bound on thermal data)\n",
    );
    for w in f.warnings() {
        let _ = writeln!(s, "warning: {w}");
    }
    s
}

/// SVG: measured error against position, one curve per sweep (at most 12, evenly
/// chosen), each with the fitted line at that sweep's mean temperatures.
pub fn plot_curves(path: &Path, m: &Measurements, f: &Fit) -> Result<(), PlotError> {
    let text = render_curves(m, f).map_err(|plot::DrawError(message)| PlotError {
        path: path.display().to_string(),
        message,
    })?;
    compgate_core::outputs::write(path, text).map_err(|e| PlotError {
        path: path.display().to_string(),
        message: e.to_string(),
    })
}

/// The SVG text of [`plot_curves`].
pub fn render_curves(m: &Measurements, f: &Fit) -> Result<String, plot::DrawError> {
    let all = sweeps(&m.t_s);
    let step = all.len().div_ceil(12).max(1);
    let chosen: Vec<_> = all.into_iter().step_by(step).collect();
    let cols: Vec<&[f64]> = f.terms.iter().filter_map(|t| m.temp(&t.name)).collect();
    let (pmin, pmax) = plot::extent(m.pos_mm.iter().copied()).unwrap_or((0.0, 1.0));
    plot::render((1000, 650), |root| {
        let first = f.terms.first().map_or("", |t| t.name.as_str());
        let mut chart = plot::Frame::new("position (mm)", "error, actual - commanded (um)")
            .caption(
                format!(
                    "calibrate: measured error curves (solid) and fitted model (dashed), RMS {:.2} um",
                    f.rms_um
                ),
                18,
            )
            .label_areas(35, 60)
            .draw(
                root,
                pmin..pmax.max(pmin + 1.0),
                plot::padded(m.err_um.iter().copied(), 0.05, 1.0, (-1.0, 1.0)),
            )?;
        for (k, r) in chosen.iter().enumerate() {
            let color = plot::Palette99::pick(k).to_rgba();
            let temps: Vec<f64> = cols.iter().map(|c| stats::mean(&c[r.clone()])).collect();
            // A continuous capture's sweeps hold every row: about 1000 dots in all.
            let mut pts: Vec<(f64, f64)> = plot::thin(r.len(), (1000 / chosen.len()).max(50))
                .into_iter()
                .map(|k| (m.pos_mm[r.start + k], m.err_um[r.start + k]))
                .collect();
            pts.sort_by(|a, b| a.0.total_cmp(&b.0));
            let label = format!(
                "t = {:.1} h, T_{first} = {:.2} degC",
                m.t_s[r.start] / 3600.0,
                temps.first().copied().unwrap_or(f64::NAN)
            );
            plot::line(&mut chart, pts.clone(), color.stroke_width(2), Some(label))?;
            plot::dots(&mut chart, pts, 3, color.filled())?;
            // Dashed fitted line: every other short segment.
            let n = 40;
            let line: Vec<(f64, f64)> = (0..=n)
                .map(|i| {
                    let x = pmin + (pmax - pmin) * i as f64 / n as f64;
                    (x, f.predict_um(x, &temps))
                })
                .collect();
            for w in line.chunks(2) {
                if let [a, b] = w {
                    plot::segment(&mut chart, *a, *b, color)?;
                }
            }
        }
        plot::legend(&mut chart, plot::SeriesLabelPosition::UpperLeft)?;
        Ok(())
    })
}
