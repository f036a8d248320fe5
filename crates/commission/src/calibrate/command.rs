//! `compgate calibrate` on the command line: the measurements in, the model file, the
//! plot and the report out.

use std::fmt::Write as _;
use std::path::PathBuf;

use compgate_core::measure::{MeasureError, Measurements};
use compgate_core::outputs::Staged;

use super::model::{model_toml, AxisModel};
use super::report::{render_curves, report};
use super::{bad_readings, calibrate, BadReadings, CalibrateError, Fit};
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
    /// temperature coefficient is within 2 standard errors of 0), a sensor that never
    /// reads below 200 degC (kelvin?), or bad readings that move the fit (a sensor that
    /// dropped out, a -999), each named by its line. The model file's header says why.
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
    /// The data's bad readings ([`BadReadings`]), named with their lines.
    bad_rows: Option<String>,
}

/// Rows named in a warning.
const SHOWN_ROWS: usize = 5;

/// The lines `rows` (0-based, ascending) lie on: "line 7" or "lines 7-9".
fn lines_of(lines: &[u64], rows: &std::ops::Range<usize>) -> String {
    match (lines[rows.start], lines[rows.end - 1]) {
        (a, b) if a == b => format!("line {a}"),
        (a, b) => format!("lines {a}-{b}"),
    }
}

/// The bad readings named by line, what leaving them out does to the fit, and the
/// doubt that keeps the model from being written when they move it.
fn bad_rows_warning(
    m: &Measurements,
    lines: &[u64],
    f: &Fit,
    bad: &BadReadings,
) -> Option<(String, Option<String>)> {
    if bad.is_empty() {
        return None;
    }
    let mut parts: Vec<String> = bad
        .excursions
        .iter()
        .take(SHOWN_ROWS)
        .map(|e| {
            format!(
                "T_{} reads {} on {} ({} degC before)",
                e.sensor,
                e.during_degc,
                lines_of(lines, &e.rows),
                e.before_degc
            )
        })
        .collect();
    if bad.excursions.len() > SHOWN_ROWS {
        parts.push(format!(
            "{} more excursions",
            bad.excursions.len() - SHOWN_ROWS
        ));
    }
    parts.extend(bad.frozen.iter().take(SHOWN_ROWS).map(|z| {
        format!(
            "T_{} holds {} degC exactly on {} ({:.1} h) while T_{} moves {:.1} K",
            z.sensor,
            z.degc,
            lines_of(lines, &z.rows),
            (m.t_s[z.rows.end - 1] - m.t_s[z.rows.start]) / 3600.0,
            z.other,
            z.other_moved_k
        )
    }));
    if bad.frozen.len() > SHOWN_ROWS {
        parts.push(format!(
            "{} more held readings",
            bad.frozen.len() - SHOWN_ROWS
        ));
    }
    parts.extend(bad.far_off.iter().take(SHOWN_ROWS).map(|&i| {
        let temps: String = f
            .terms
            .iter()
            .filter_map(|t| m.temp(&t.name).map(|c| format!(", T_{} {}", t.name, c[i])))
            .collect();
        format!(
            "{} (t_s {}, pos_mm {}, err_um {}{temps}) {:+.3} um off the fit",
            lines_of(lines, &(i..i + 1)),
            m.t_s[i],
            m.pos_mm[i],
            m.err_um[i],
            f.residuals_um[i]
        )
    }));
    if bad.far_off.len() > SHOWN_ROWS {
        parts.push(format!(
            "{} more rows far off",
            bad.far_off.len() - SHOWN_ROWS
        ));
    }
    let n = bad.rows().len();
    let what = format!(
        "{n} {} like bad readings (a temperature that leaves its level by more than {} K \
         and comes back, or holds one value for {} min or more while another moves more than {} K \
         and leaving it out moves the fit, a row more than {} times the typical residual \
         ({:.3} um) off the fit, alone or in a pair): {}",
        if n == 1 { "row looks" } else { "rows look" },
        compgate_core::measure::EXCURSION_K,
        compgate_core::measure::FROZEN_MIN_S / 60.0,
        compgate_core::measure::FROZEN_OTHERS_K,
        super::bad::OUTLIER_FACTOR,
        bad.typical_um,
        parts.join("; ")
    );
    Some(if bad.pull() {
        (
            format!(
                "{what}; left out, they move the fitted error by up to {:.3} um: a sensor \
                 that dropped out or froze, a 0 or a -999 written for a missing value; fix \
                 or remove those rows and fit again",
                bad.pull_um
            ),
            Some(format!(
                "bad readings move the fitted error by up to {:.3} um",
                bad.pull_um
            )),
        )
    } else {
        (
            format!(
                "{what}; left out, they move the fitted error by {:.3} um at most: the model \
                 stands, remove them for a clean record",
                bad.pull_um
            ),
            None,
        )
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
    let bad = bad_readings(&m, &args.sensors, &f);
    let (bad_rows, bad_doubt) = bad_rows_warning(&m, &lines, &f, &bad).unzip();
    let mut model = AxisModel::from_fit(&f);
    // The bad readings too: whoever loads a forced model later is warned of them.
    model.accepted_doubts.extend(bad_doubt.flatten());
    let doubts = model.accepted_doubts.clone();
    let header = format!(
        "compgate calibrate: axis {} from {} rows of {}\nRMS residual {:.3} um, R^2 {:.6}\nchannels are the CSV's T_ columns without T_; name the gateway's channels alike",
        args.axis,
        f.rows,
        args.data.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
        f.rms_um,
        f.r2
    );
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
        if let Some(b) = &self.bad_rows {
            let _ = writeln!(s, "warning: {b}");
        }
        if !self.ignored_columns.is_empty() {
            s = format!("ignored columns: {}\n{s}", self.ignored_columns.join(", "));
        }
        s
    }

    /// The fit's warnings ([`Fit::warnings`]) and the data's bad rows, for stderr.
    pub fn warnings(&self) -> Vec<String> {
        let mut w = self.fit.warnings();
        w.extend(self.bad_rows.clone());
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
