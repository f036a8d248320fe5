//! What `diagnose` shows and writes: the stdout report, SVG plots, `report.html` and
//! the updated model file.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::{DiagnoseError, Diagnosis, ModelFile, Where};
use crate::plot::{self, Color as _};
use crate::table::{plain_line, Column};

fn where_text(out: &mut String, w: &Where) {
    let worst_t = w
        .time_windows
        .iter()
        .copied()
        .fold(None::<(f64, f64, f64)>, |m, x| match m {
            Some(m) if m.2 >= x.2 => Some(m),
            _ => Some(x),
        });
    if w.time_windows.is_empty() {
        let _ = writeln!(out, "  time windows: none (time does not advance)");
    } else {
        let _ = writeln!(out, "  time windows (RMS um):");
    }
    for (a, b, r) in &w.time_windows {
        let mark = if worst_t.is_some_and(|m| m.0 == *a) {
            "  <- largest"
        } else {
            ""
        };
        let _ = writeln!(out, "    {a:>9.0} .. {b:>9.0} s  {r:8.3}{mark}");
    }
    let _ = writeln!(out, "  position ranges (mean / RMS um):");
    for (a, b, m, r) in &w.position_ranges {
        let _ = writeln!(out, "    {a:>9.1} .. {b:>9.1} mm  {m:+8.3} / {r:7.3}");
    }
    let _ = writeln!(
        out,
        "  direction: mean {:+.3} um approaching in + ({} rows), {:+.3} um in - ({} rows), difference {:+.3} um",
        w.dir_plus_mean_um,
        w.dir_rows.0,
        w.dir_minus_mean_um,
        w.dir_rows.1,
        w.dir_plus_mean_um - w.dir_minus_mean_um
    );
    match w.periodic {
        Some((p, a)) => {
            let _ = writeln!(
                out,
                "  periodic in position: strongest period {p:.2} mm, amplitude {a:.3} um"
            );
        }
        None => {
            let _ = writeln!(
                out,
                "  periodic in position: positions too sparse to resolve"
            );
        }
    }
    let _ = writeln!(out, "  lag-1 autocorrelation in time: {:.3}", w.rho);
}

/// The candidates table: the effect, eight right-aligned figures (sensor, param,
/// rms_um, cv_rms, dIC, rho, n_eff, edge), the verdict after two spaces.
fn candidate_columns() -> [Column; 10] {
    const FIGURE_WIDTHS: [usize; 8] = [7, 12, 9, 9, 10, 8, 9, 9];
    std::array::from_fn(|i| match i {
        0 => Column::left(2, 20),
        9 => Column::left(2, 0),
        _ => Column::right(1, FIGURE_WIDTHS[i - 1]),
    })
}

/// The human-readable report.
pub fn text_report(d: &Diagnosis) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "compgate diagnose: {} rows, baseline sensors: {}",
        d.rows,
        d.sensors.join(", ")
    );
    if !d.ignored_columns.is_empty() {
        let _ = writeln!(out, "ignored columns: {}", d.ignored_columns.join(", "));
    }
    if let Some(g) = d.model_gap {
        let _ = writeln!(
            out,
            "given model (simulation) vs measurement: RMS {:.3} um, max |gap| {:.3} um",
            g.rms_um, g.max_abs_um
        );
    }
    let _ = writeln!(
        out,
        "baseline refit K0(T) + tan(beta)(T)*(pos - {:.1}): RMS {:.3} um, max |gap| {:.3} um",
        d.p0_mm, d.baseline.rms_um, d.baseline.max_abs_um
    );
    let _ = writeln!(out, "\nwhere the baseline disagrees:");
    where_text(&mut out, &d.where_baseline);
    if !d.untested.is_empty() {
        let _ = writeln!(out, "\ncandidates not tested:");
        for u in &d.untested {
            let _ = writeln!(out, "  {u}");
        }
    }
    let columns = candidate_columns();
    for (i, round) in d.rounds.iter().enumerate() {
        let _ = writeln!(
            out,
            "\nround {}: candidates (dIC < 0 is better; accepted needs IC, blocked CV, plausible, size)",
            i + 1
        );
        let header = [
            "effect", "sensor", "param", "rms_um", "cv_rms", "dIC", "rho", "n_eff", "edge",
            "verdict",
        ];
        let _ = writeln!(out, "{}", plain_line(&columns, header));
        for c in &round.candidates {
            let param = match (c.param, c.param_name) {
                (Some(v), Some(n)) => format!(
                    "{}={v:.1}",
                    n.trim_end_matches("_mm").trim_end_matches("_s")
                ),
                _ => "-".into(),
            };
            let mut why = Vec::new();
            if !c.checks.passes_ic {
                why.push("IC");
            }
            if !c.checks.passes_cv {
                why.push("CV");
            }
            if !c.checks.plausible {
                why.push("edge of range");
            }
            if !c.checks.passes_size {
                why.push("too small");
            }
            let verdict = if c.accepted {
                "ACCEPTED".to_string()
            } else if why.is_empty() {
                "passes (not best)".into()
            } else {
                format!("fails: {}", why.join(", "))
            };
            let cells = [
                c.name.to_string(),
                c.sensor.as_deref().unwrap_or("-").to_string(),
                param,
                format!("{:.3}", c.rms_after_um),
                format!("{:.3}", c.cv_rms_after_um),
                format!("{:.1}", c.delta_ic),
                format!("{:.3}", c.rho),
                format!("{:.0}", c.n_eff),
                (if c.checks.at_edge { "yes" } else { "no" }).to_string(),
                verdict,
            ];
            let _ = writeln!(out, "{}", plain_line(&columns, cells));
        }
    }
    let _ = writeln!(
        out,
        "\neffects added (each RMS after re-tuning every effect so far):"
    );
    if d.effects.is_empty() {
        let _ = writeln!(out, "  none");
    }
    for e in &d.effects {
        let params: Vec<String> = e
            .params
            .iter()
            .map(|(k, v)| match v.as_f64() {
                Some(x) => format!("{k}={x:.4}"),
                None => format!("{k}={}", v.as_str().unwrap_or("?")),
            })
            .collect();
        let _ = writeln!(
            out,
            "  {}: RMS {:.3} -> {:.3} um; {}{}",
            e.name,
            e.rms_before_um,
            e.rms_after_um,
            params.join(", "),
            if e.ambiguous_with.is_empty() {
                String::new()
            } else {
                format!("; AMBIGUOUS with {}", e.ambiguous_with.join(", "))
            }
        );
    }
    if !d.effects.is_empty() {
        let _ = writeln!(out, "\nwhere the final model still disagrees:");
        where_text(&mut out, &d.where_final);
    }
    let _ = writeln!(
        out,
        "\nfinal: RMS {:.3} um, max |gap| {:.3} um",
        d.final_gap.rms_um, d.final_gap.max_abs_um
    );
    let _ = writeln!(out, "verdict: {}", d.verdict);
    out
}

type Xy = Vec<(f64, f64)>;

/// File, title, x label, x of a row, x range.
type PlotSpec<'a> = (
    &'a str,
    &'a str,
    &'a str,
    Box<dyn Fn(usize) -> f64 + 'a>,
    (f64, f64),
);

fn scatter_svg(
    path: &Path,
    title: &str,
    x_desc: &str,
    before: &Xy,
    after: &Xy,
    x_range: (f64, f64),
) -> Result<(), DiagnoseError> {
    let y_range = plot::padded(
        before.iter().chain(after).map(|&(_, y)| y),
        0.05,
        0.01,
        (-1.0, 1.0),
    );
    plot::svg(path, (900, 620), |root| {
        let (upper, lower) = root.split_vertically(310);
        for (area, series, label, color) in [
            (&upper, before, "before (baseline)", plot::RED),
            (&lower, after, "after (with the added effects)", plot::BLUE),
        ] {
            let mut chart = plot::Frame::new(x_desc, "residual (um)")
                .caption(format!("{title}: {label}"), 16)
                .margin(8)
                .draw(area, x_range.0..x_range.1, y_range.clone())?;
            let style = color.mix(0.5).filled();
            plot::dots(&mut chart, series.iter().copied(), 1, style)?;
        }
        Ok(())
    })?;
    Ok(())
}

/// The files [`write_out`] writes into its directory: the updated model, the
/// baseline model, the three residual plots and the report.
pub const OUT_FILES: [&str; 6] = [
    "model.toml",
    "baseline_model.toml",
    "residual_time.svg",
    "residual_position.svg",
    "residual_direction.svg",
    "report.html",
];

/// Refuses a `dir` whose `model.toml` or `baseline_model.toml` diagnose did not
/// write (a `calibrate` model, say): replacing it would lose it. Its own files of an
/// earlier run are replaced, as a re-run is expected to.
pub fn check_models_are_ours(dir: &Path) -> Result<(), DiagnoseError> {
    for file in &OUT_FILES[..2] {
        let path = dir.join(file);
        let text = match std::fs::read(&path) {
            Ok(bytes) => String::from_utf8_lossy(&bytes).into_owned(),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
            Err(source) => {
                return Err(DiagnoseError::Io {
                    path: path.display().to_string(),
                    source,
                })
            }
        };
        let first_line = text.lines().find(|l| !l.trim().is_empty()).unwrap_or("");
        if first_line.trim_start_matches('#').trim() != super::model_file::WRITTEN_BY {
            return Err(DiagnoseError::ForeignModel {
                dir: dir.display().to_string(),
                file: (*file).to_string(),
                first_line: first_line.chars().take(80).collect(),
            });
        }
    }
    Ok(())
}

/// Writes [`OUT_FILES`] into `dir` (which must exist); returns the paths.
pub fn write_out(dir: &Path, d: &Diagnosis) -> Result<Vec<PathBuf>, DiagnoseError> {
    let io = |path: &Path| {
        let path = path.display().to_string();
        move |source| DiagnoseError::Io { path, source }
    };
    let [model_file, base_file, time_svg, position_svg, direction_svg, html_file] = OUT_FILES;
    let mut written = Vec::new();
    let model_path = dir.join(model_file);
    let base_path = dir.join(base_file);
    // Both models are checked before either is written: a refused one leaves the
    // directory as it was.
    let model_text = ModelFile::from_diagnosis(d).to_toml(&model_path.display().to_string())?;
    let base_text =
        ModelFile::baseline_from_diagnosis(d).to_toml(&base_path.display().to_string())?;
    compgate_core::outputs::write(&model_path, &model_text).map_err(io(&model_path))?;
    written.push(model_path);
    compgate_core::outputs::write(&base_path, base_text).map_err(io(&base_path))?;
    written.push(base_path);

    let s = &d.series;
    let idx = plot::thin(s.t_s.len(), 2000);
    let pick =
        |x: &dyn Fn(usize) -> f64, r: &[f64]| -> Xy { idx.iter().map(|&i| (x(i), r[i])).collect() };
    let t_end = s.t_s.last().copied().unwrap_or(1.0).max(s.t_s[0] + 1e-9);
    let (p_lo, p_hi) = d.pos_range_mm;
    let p_pad = ((p_hi - p_lo) * 0.02).max(1e-3);
    // Direction: +1/-1 with a deterministic spread so the points do not pile up.
    let jitter = |i: usize| f64::from(s.dir[i]) + 0.3 * (((i * 7919) % 1000) as f64 / 1000.0 - 0.5);
    let plots: [PlotSpec; 3] = [
        (
            time_svg,
            "residual against time",
            "t (s)",
            Box::new(|i| s.t_s[i]),
            (s.t_s[0], t_end),
        ),
        (
            position_svg,
            "residual against position",
            "position (mm)",
            Box::new(|i| s.pos_mm[i]),
            (p_lo - p_pad, p_hi + p_pad),
        ),
        (
            direction_svg,
            "residual against direction of approach",
            "direction (-1 / +1)",
            Box::new(jitter),
            (-1.6, 1.6),
        ),
    ];
    let mut svgs = Vec::new();
    for (file, title, x_desc, x, range) in plots {
        let path = dir.join(file);
        let before = pick(&*x, &s.before_um);
        let after = pick(&*x, &s.after_um);
        scatter_svg(&path, title, x_desc, &before, &after, range)?;
        let text = std::fs::read_to_string(&path).map_err(io(&path))?;
        svgs.push((title, text));
        written.push(path);
    }
    let html_path = dir.join(html_file);
    let mut html = String::from(
        "<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>compgate diagnose</title>\
         <style>body{font-family:sans-serif;margin:2em;max-width:1000px}pre{background:#f4f4f4;padding:1em;overflow-x:auto}</style>\
         </head><body>\n<h1>compgate diagnose</h1>\n",
    );
    let _ = writeln!(html, "<p><b>Verdict:</b> {}</p>", escape(&d.verdict));
    for (title, svg) in &svgs {
        let svg = svg.trim_start_matches(|c| c != '<');
        let svg = match svg.strip_prefix("<?xml") {
            Some(rest) => rest.split_once("?>").map_or(rest, |(_, r)| r),
            None => svg,
        };
        let _ = writeln!(html, "<h2>{}</h2>\n{}", escape(title), svg);
    }
    let _ = writeln!(
        html,
        "<h2>Report</h2>\n<pre>{}</pre>",
        escape(&text_report(d))
    );
    let _ = writeln!(
        html,
        "<h2>Updated model</h2>\n<pre>{}</pre>\n</body></html>",
        escape(&model_text)
    );
    compgate_core::outputs::write(&html_path, html).map_err(io(&html_path))?;
    written.push(html_path);
    Ok(written)
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// The `--json` document.
pub fn json(d: &Diagnosis) -> String {
    serde_json::to_string_pretty(d).unwrap_or_else(|e| format!("{{\"error\": \"{e}\"}}"))
}
