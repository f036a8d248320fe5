//! `compgate calibrate`: the patent's step S1. Fits K0(T) and tan(beta)(T) to error
//! curves measured at several temperatures and writes the axis model in the form of
//! the gateway config (`[axes.NAME]` with `p0_mm`, `k0`, `tan_beta`).
//!
//! The model's channels are the CSV's temperature columns without `T_`: name the
//! gateway's channels alike (or rename them in the written file).

pub mod fit;

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use thiserror::Error;

use compgate_core::measure::{MeasureError, Measurements};
use compgate_gateway::config::{K0Model, K0Term, TanBetaModel, TanBetaTerm};

use crate::plot::{self, Color as _, Palette as _, PlotError};
use crate::table::Markdown;
pub use fit::{Fit, FitError};

/// Errors of `calibrate` and of reading a model file.
#[derive(Debug, Error)]
pub enum CalibrateError {
    #[error("{0}: {1}")]
    Data(String, MeasureError),
    #[error("--sensors: no column T_{0} in the data (it has: {1})")]
    NoSensor(String, String),
    #[error("fit: {0}")]
    Fit(#[from] FitError),
    #[error("{path}: {message}")]
    Io { path: String, message: String },
    #[error("{path}: {message}")]
    Model { path: String, message: String },
}

/// `compgate calibrate` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct CalibrateArgs {
    /// Measured-error CSV (`t_s,pos_mm,err_um,T_<sensor>...`).
    #[arg(long)]
    pub data: PathBuf,
    /// Where to write the model (TOML, the gateway's `[axes.NAME]` form).
    #[arg(long)]
    pub out: PathBuf,
    /// Sensors the model uses, comma separated, with or without `T_`; default every
    /// temperature column.
    #[arg(long, value_delimiter = ',')]
    pub sensors: Vec<String>,
    /// Reference position P0, mm; default the measured position nearest 0.
    #[arg(long)]
    pub p0_mm: Option<f64>,
    /// Axis name in the written model.
    #[arg(long, default_value = "X")]
    pub axis: String,
    /// NC module name in the written model.
    #[arg(long, default_value = "nc_x")]
    pub nc_module: String,
    /// SVG plot of the measured error curves with the fitted lines.
    #[arg(long)]
    pub plot: Option<PathBuf>,
}

/// The model part of an `[axes.NAME]` table: what calibrate writes, `scenario
/// --model` reads, and the axis part of diagnose's model file.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct AxisModel {
    /// SD43920, mm.
    #[serde(default)]
    pub p0_mm: f64,
    /// K0(T) -> SD43900.
    #[serde(default)]
    pub k0: K0Model,
    /// tan(beta)(T) -> SD43910.
    #[serde(default)]
    pub tan_beta: TanBetaModel,
}

impl AxisModel {
    /// The fitted model in config units (mm, mm/mm).
    pub fn from_fit(f: &Fit) -> Self {
        Self {
            p0_mm: f.p0_mm,
            k0: K0Model {
                offset_mm: f.k0_offset_um / 1000.0,
                terms: f
                    .terms
                    .iter()
                    .map(|t| K0Term {
                        channel: t.name.clone(),
                        ref_degc: t.ref_degc,
                        coeff_mm_per_degc: t.k0_um_per_degc / 1000.0,
                    })
                    .collect(),
            },
            tan_beta: TanBetaModel {
                offset: f.tan_beta_offset,
                terms: f
                    .terms
                    .iter()
                    .map(|t| TanBetaTerm {
                        channel: t.name.clone(),
                        ref_degc: t.ref_degc,
                        coeff_per_degc: t.tan_beta_per_degc,
                    })
                    .collect(),
            },
        }
    }

    /// Error the model predicts at `pos_mm` with temperatures by channel name, um;
    /// `None` if a channel is missing.
    pub fn predict_um(&self, pos_mm: f64, temp_degc: impl Fn(&str) -> Option<f64>) -> Option<f64> {
        let mut k0_mm = self.k0.offset_mm;
        for t in &self.k0.terms {
            k0_mm += t.coeff_mm_per_degc * (temp_degc(&t.channel)? - t.ref_degc);
        }
        let mut tan = self.tan_beta.offset;
        for t in &self.tan_beta.terms {
            tan += t.coeff_per_degc * (temp_degc(&t.channel)? - t.ref_degc);
        }
        Some(1000.0 * (k0_mm + tan * (pos_mm - self.p0_mm)))
    }

    /// Channels the model reads, each once.
    pub fn channels(&self) -> Vec<String> {
        let mut c: Vec<String> = Vec::new();
        let names = self.k0.terms.iter().map(|t| &t.channel);
        for n in names.chain(self.tan_beta.terms.iter().map(|t| &t.channel)) {
            if !c.contains(n) {
                c.push(n.clone());
            }
        }
        c
    }
}

#[derive(Serialize)]
struct AxisOut<'a> {
    nc_module: &'a str,
    md32750: u16,
    #[serde(flatten)]
    model: &'a AxisModel,
}

/// The model as a TOML fragment `[axes.<axis>]`, with a comment header.
pub fn model_toml(axis: &str, nc_module: &str, model: &AxisModel, header: &str) -> String {
    let mut axes = BTreeMap::new();
    axes.insert(
        axis,
        AxisOut {
            nc_module,
            // Both parts are fitted: K0 (bit 0) and the slope (bit 1).
            md32750: 3,
            model,
        },
    );
    let mut root = BTreeMap::new();
    root.insert("axes", axes);
    let body = toml::to_string(&root).unwrap_or_default();
    let mut s = String::new();
    for line in header.lines() {
        let _ = writeln!(s, "# {line}");
    }
    s.push_str(&body);
    s
}

/// Reads the first `[axes.NAME]` of a model file (from calibrate or diagnose) or of a
/// whole gateway config; keys other than `p0_mm`, `k0` and `tan_beta` are ignored.
pub fn load_model(path: &Path) -> Result<(String, AxisModel), CalibrateError> {
    let err = |message: String| CalibrateError::Model {
        path: path.display().to_string(),
        message,
    };
    let text = std::fs::read_to_string(path).map_err(|e| err(e.to_string()))?;
    let value: toml::Table = toml::from_str(&text).map_err(|e| err(e.to_string()))?;
    first_axis_model(&value).map_err(err)
}

/// The first `[axes.NAME]` of a parsed model file or gateway config, and its name;
/// keys other than `p0_mm`, `k0` and `tan_beta` are ignored. The error names the key.
pub fn first_axis_model(root: &toml::Table) -> Result<(String, AxisModel), String> {
    let (name, axis) = root
        .get("axes")
        .and_then(|a| a.as_table())
        .and_then(|a| a.iter().next())
        .ok_or("no [axes.NAME] table")?;
    let mut t = axis
        .as_table()
        .cloned()
        .ok_or_else(|| format!("axes.{name} is not a table"))?;
    t.retain(|k, _| matches!(k, "p0_mm" | "k0" | "tan_beta"));
    let model: AxisModel = toml::Value::Table(t)
        .try_into()
        .map_err(|e: toml::de::Error| format!("axes.{name}: {}", e.message()))?;
    Ok((name.clone(), model))
}

/// Picks the sensor columns named in `wanted` (with or without `T_`), or all.
pub fn select_sensors<'a>(
    m: &'a Measurements,
    wanted: &[String],
) -> Result<Vec<(&'a str, &'a [f64])>, CalibrateError> {
    if wanted.is_empty() {
        return Ok(m
            .temps
            .iter()
            .map(|c| (c.name.as_str(), c.degc.as_slice()))
            .collect());
    }
    wanted
        .iter()
        .map(|w| {
            let name = w.trim().strip_prefix("T_").unwrap_or(w.trim());
            m.temps
                .iter()
                .find(|c| c.name == name)
                .map(|c| (c.name.as_str(), c.degc.as_slice()))
                .ok_or_else(|| {
                    let have: Vec<String> =
                        m.temps.iter().map(|c| format!("T_{}", c.name)).collect();
                    CalibrateError::NoSensor(name.to_string(), have.join(", "))
                })
        })
        .collect()
}

/// Fits the data with the chosen sensors and P0 (default [`fit::choose_p0_mm`]).
pub fn calibrate(
    m: &Measurements,
    sensors: &[String],
    p0_mm: Option<f64>,
) -> Result<Fit, CalibrateError> {
    let cols = select_sensors(m, sensors)?;
    let p0_mm = p0_mm.unwrap_or_else(|| fit::choose_p0_mm(&m.pos_mm));
    Ok(fit::fit(&m.pos_mm, &m.err_um, &cols, p0_mm)?)
}

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
    s
}

/// Runs the command: read, fit, write the model (and plot); returns the report.
pub fn run(args: &CalibrateArgs) -> Result<String, CalibrateError> {
    let m = Measurements::read_path(&args.data)
        .map_err(|e| CalibrateError::Data(args.data.display().to_string(), e))?;
    let f = calibrate(&m, &args.sensors, args.p0_mm)?;
    let model = AxisModel::from_fit(&f);
    let header = format!(
        "compgate calibrate: axis {} from {} rows of {}\nRMS residual {:.3} um, R^2 {:.6}\nchannels are the CSV's T_ columns without T_; name the gateway's channels alike",
        args.axis,
        f.rows,
        args.data.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
        f.rms_um,
        f.r2
    );
    let text = model_toml(&args.axis, &args.nc_module, &model, &header);
    std::fs::write(&args.out, text).map_err(|e| CalibrateError::Io {
        path: args.out.display().to_string(),
        message: e.to_string(),
    })?;
    let mut out = report(&f);
    let _ = writeln!(out, "model written to {}", args.out.display());
    if let Some(plot) = &args.plot {
        plot_curves(plot, &m, &f).map_err(|e| CalibrateError::Io {
            path: plot.display().to_string(),
            message: e.to_string(),
        })?;
        let _ = writeln!(out, "plot written to {}", plot.display());
    }
    Ok(out)
}

/// Splits rows into sweeps: a new sweep starts after a pause longer than 5 times the
/// median time step.
pub fn sweeps(t_s: &[f64]) -> Vec<std::ops::Range<usize>> {
    if t_s.is_empty() {
        return Vec::new();
    }
    let mut dts: Vec<f64> = t_s.windows(2).map(|w| w[1] - w[0]).collect();
    dts.sort_by(f64::total_cmp);
    let gap = dts.get(dts.len() / 2).copied().unwrap_or(0.0) * 5.0;
    let mut out = Vec::new();
    let mut start = 0;
    for i in 1..t_s.len() {
        if t_s[i] - t_s[i - 1] > gap {
            out.push(start..i);
            start = i;
        }
    }
    out.push(start..t_s.len());
    out
}

/// SVG: measured error against position, one curve per sweep (at most 12, evenly
/// chosen), each with the fitted line at that sweep's mean temperatures.
pub fn plot_curves(path: &Path, m: &Measurements, f: &Fit) -> Result<(), PlotError> {
    let all = sweeps(&m.t_s);
    let step = all.len().div_ceil(12).max(1);
    let chosen: Vec<_> = all.into_iter().step_by(step).collect();
    let cols: Vec<&[f64]> = f.terms.iter().filter_map(|t| m.temp(&t.name)).collect();
    let (pmin, pmax) = plot::extent(m.pos_mm.iter().copied()).unwrap_or((0.0, 1.0));
    let root = plot::canvas(path, (1000, 650))?;
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
            &root,
            pmin..pmax.max(pmin + 1.0),
            plot::padded(m.err_um.iter().copied(), 0.05, 1.0, (-1.0, 1.0)),
        )?;
    for (k, r) in chosen.iter().enumerate() {
        let color = plot::Palette99::pick(k).to_rgba();
        let temps: Vec<f64> = cols
            .iter()
            .map(|c| c[r.clone()].iter().sum::<f64>() / r.len() as f64)
            .collect();
        let mut pts: Vec<(f64, f64)> = r.clone().map(|i| (m.pos_mm[i], m.err_um[i])).collect();
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
    plot::finish(&root)
}

#[cfg(test)]
mod tests;
