//! `compgate calibrate` on the command line: the measurements in, the model file, the
//! plot and the report out.

use std::fmt::Write as _;
use std::path::PathBuf;

use compgate_core::measure::{MeasureError, Measurements};
use compgate_core::outputs::Staged;

use super::model::{model_toml, AxisModel};
use super::report::{render_curves, report};
use super::{calibrate, CalibrateError, Fit};
use crate::plot::PlotError;

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
    #[arg(long, allow_negative_numbers = true)]
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
    /// Write the model even when the fit is in doubt, which is refused otherwise:
    /// err_um spanning less than 1 um (millimetres?), a sensor that spans less than
    /// 0.5 K in the data, a tan(beta) coefficient beyond 1e-4 /K (no machine structure
    /// expands so), or temperatures that do not explain the error (the temperature
    /// terms remove less than half of what constant K0 and tan(beta) leave, and every
    /// temperature coefficient is within 2 standard errors of 0).
    #[arg(long)]
    pub accept_weak_fit: bool,
}

/// A fit whose report is still to be shown and whose files are still to be written:
/// the report comes first, so that an output that cannot be written is told after
/// the figures it would have held.
#[derive(Debug)]
pub struct Calibrated<'a> {
    args: &'a CalibrateArgs,
    fit: Fit,
    /// The model file's text.
    model: String,
    /// The plot's SVG text, with `--plot`.
    plot: Option<String>,
    /// Columns of the data the fit did not read: not of the format, and `T_`
    /// columns `--sensors` left out.
    ignored_columns: Vec<String>,
    /// Why the model is not written without `--accept-weak-fit`: the fit's
    /// ([`Fit::doubts`]) and the bad rows'.
    doubts: Vec<String>,
    /// Bad rows of the data, named with their lines: temperature jumps and rows far
    /// off the fit.
    bad_rows: Vec<BadRows>,
}

/// Rows of the data that look like bad readings.
#[derive(Debug)]
struct BadRows {
    /// One short reason, for the refusal.
    doubt: String,
    /// The rows named, cause and remedy, for stderr.
    warning: String,
}

/// Rows named in a warning.
const SHOWN_ROWS: usize = 5;

/// "1 row lies", "2 rows lie".
fn count(n: usize, one: &str, many: &str) -> String {
    format!("{n} {}", if n == 1 { one } else { many })
}

/// ", the N first" when more than [`SHOWN_ROWS`] are named.
fn shown(n: usize, which: &str) -> String {
    if n > SHOWN_ROWS {
        format!(", the {SHOWN_ROWS} {which}")
    } else {
        String::new()
    }
}

/// The temperature jumps ([`Measurements::temperature_jumps`]), named by line.
fn jump_warning(m: &Measurements, lines: &[u64]) -> Option<BadRows> {
    let jumps = m.temperature_jumps();
    if jumps.is_empty() {
        return None;
    }
    let named: Vec<String> = jumps
        .iter()
        .take(SHOWN_ROWS)
        .map(|j| {
            format!(
                "T_{} {:+.2} K to {} at line {} ({} s after the row before)",
                j.sensor,
                j.delta_k,
                m.temps
                    .iter()
                    .find(|c| c.name == j.sensor)
                    .map_or(f64::NAN, |c| c.degc[j.row]),
                lines[j.row],
                j.dt_s
            )
        })
        .collect();
    Some(BadRows {
        doubt: count(jumps.len(), "temperature jump", "temperature jumps"),
        warning: format!(
            "{} of more than {} K within {} s{}: {}; no machine structure changes so fast: a \
             sensor that dropped out or a plug swapped, or a 0 or a fault value written for a \
             missing reading; fix or remove those rows and fit again",
            count(jumps.len(), "temperature jump", "temperature jumps"),
            compgate_core::measure::TEMP_JUMP_K,
            compgate_core::measure::TEMP_JUMP_WITHIN_S,
            shown(jumps.len(), "first"),
            named.join("; ")
        ),
    })
}

/// The rows far off the fit ([`Fit::outliers`]), named by line and values.
fn outlier_warning(m: &Measurements, lines: &[u64], f: &Fit) -> Option<BadRows> {
    let (rows, typical_um) = f.outliers();
    if rows.is_empty() {
        return None;
    }
    let named: Vec<String> = rows
        .iter()
        .take(SHOWN_ROWS)
        .map(|&i| {
            let temps: String = m
                .temps
                .iter()
                .filter(|c| f.terms.iter().any(|t| t.name == c.name))
                .map(|c| format!(", T_{} {}", c.name, c.degc[i]))
                .collect();
            format!(
                "line {} (t_s {}, pos_mm {}, err_um {}{temps}) {:+.3} um off",
                lines[i], m.t_s[i], m.pos_mm[i], m.err_um[i], f.residuals_um[i]
            )
        })
        .collect();
    Some(BadRows {
        doubt: format!(
            "{} more than {} times the typical residual off the fit",
            count(rows.len(), "row lies", "rows lie"),
            super::fit::OUTLIER_FACTOR
        ),
        warning: format!(
            "{} more than {} times the typical residual ({:.3} um) off the fit{}: {}; a bad \
             reading (a -999 or a 0 written for a missing value, a sensor that dropped out) \
             pulls every coefficient: fix or remove those rows and fit again",
            count(rows.len(), "row lies", "rows lie"),
            super::fit::OUTLIER_FACTOR,
            typical_um,
            shown(rows.len(), "farthest"),
            named.join("; ")
        ),
    })
}

/// Runs the command up to its outputs: checks them (before the data is read), reads,
/// fits, and renders the model file and the plot; writes nothing.
pub fn run(args: &CalibrateArgs) -> Result<Calibrated<'_>, CalibrateError> {
    let mut outputs = vec![args.out.as_path()];
    outputs.extend(args.plot.as_deref());
    compgate_core::outputs::check(&[&args.data], &outputs)?;
    // A sensor --sensors leaves out is not read: its bad cell cannot stop the fit.
    let read = if args.sensors.is_empty() {
        Measurements::read_path_with_lines(&args.data)
    } else {
        Measurements::read_path_sensors(&args.data, &crate::args::sensor_names(&args.sensors)?)
    };
    let (m, lines) = read.map_err(|e| match e {
        // The reader's own error names the file already.
        MeasureError::Io { path, source } => CalibrateError::Io { path, source },
        e => CalibrateError::Data(args.data.display().to_string(), e),
    })?;
    let f = calibrate(&m, &args.sensors, args.p0_mm)?;
    let bad_rows: Vec<BadRows> = [jump_warning(&m, &lines), outlier_warning(&m, &lines, &f)]
        .into_iter()
        .flatten()
        .collect();
    let mut doubts = f.doubts();
    doubts.extend(bad_rows.iter().map(|b| b.doubt.clone()));
    let model = AxisModel::from_fit(&f);
    let mut header = format!(
        "compgate calibrate: axis {} from {} rows of {}\nRMS residual {:.3} um, R^2 {:.6}\nchannels are the CSV's T_ columns without T_; name the gateway's channels alike",
        args.axis,
        f.rows,
        args.data.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
        f.rms_um,
        f.r2
    );
    // Whoever loads the model later sees that it was forced.
    if args.accept_weak_fit && !doubts.is_empty() {
        let _ = write!(
            header,
            "\nwritten with --accept-weak-fit: {}",
            doubts.join("; ")
        );
    }
    // Refused before anything is written: a model the gateway would load must
    // never hold a NaN or an absurd coefficient.
    let model = model_toml(&args.axis, &args.nc_module, &model, &header).map_err(|source| {
        CalibrateError::Model {
            path: args.out.display().to_string(),
            source: Box::new(source),
        }
    })?;
    let plot = match &args.plot {
        Some(path) => Some(render_curves(&m, &f).map_err(|e| PlotError {
            path: path.display().to_string(),
            message: e.0,
        })?),
        None => None,
    };
    Ok(Calibrated {
        args,
        fit: f,
        model,
        plot,
        doubts,
        bad_rows,
        // The sensors --sensors left out are among them: they were not read.
        ignored_columns: m.ignored_columns,
    })
}

impl Calibrated<'_> {
    /// The fit report (with its warnings), for stdout; it names the columns the fit
    /// did not read, as diagnose does.
    pub fn report(&self) -> String {
        let mut s = report(&self.fit);
        for b in &self.bad_rows {
            let _ = writeln!(s, "warning: {}", b.warning);
        }
        if !self.ignored_columns.is_empty() {
            s = format!("ignored columns: {}\n{s}", self.ignored_columns.join(", "));
        }
        s
    }

    /// The fit's warnings ([`Fit::warnings`]) and the data's bad rows, for stderr.
    pub fn warnings(&self) -> Vec<String> {
        let mut w = self.fit.warnings();
        w.extend(self.bad_rows.iter().map(|b| b.warning.clone()));
        w
    }

    /// Writes the model and the plot, both or neither (an existing model stays as it
    /// was when the plot cannot be written); returns the lines saying so. A fit with
    /// doubts is not written without `--accept-weak-fit`.
    pub fn write(&self) -> Result<String, CalibrateError> {
        if !self.doubts.is_empty() && !self.args.accept_weak_fit {
            return Err(CalibrateError::Doubtful {
                path: self.args.out.display().to_string(),
                doubts: self.doubts.join("; "),
            });
        }
        let io = |(path, source): (PathBuf, std::io::Error)| CalibrateError::Io {
            path: path.display().to_string(),
            source,
        };
        let mut staged = Staged::new();
        let mut files = vec![(&self.args.out, self.model.as_str(), "model")];
        if let (Some(path), Some(svg)) = (&self.args.plot, &self.plot) {
            files.push((path, svg.as_str(), "plot"));
        }
        let mut out = String::new();
        for (path, text, what) in files {
            staged
                .write(path, text)
                .map_err(|e| io((path.clone(), e)))?;
            let _ = writeln!(out, "{what} written to {}", path.display());
        }
        staged.commit().map_err(io)?;
        Ok(out)
    }
}
