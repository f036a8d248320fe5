//! `compgate diagnose` on the command line: files in, report and files out.

use std::path::PathBuf;

use super::{diagnose, output, DiagnoseError, Diagnosis, ModelFile, Options};
use compgate_core::measure::{MeasureError, Measurements};

/// Arguments of `compgate diagnose`.
#[derive(Debug, Clone, clap::Args)]
pub struct DiagnoseArgs {
    /// Measured error CSV: t_s, pos_mm, err_um, `T_<name>`..., optional dir, travel_mm.
    #[arg(long)]
    pub data: PathBuf,
    /// Baseline sensors, comma separated (names with or without `T_`); default: every
    /// `T_` column.
    #[arg(long, value_delimiter = ',')]
    pub sensors: Option<Vec<String>>,
    /// The model taken as the simulation (model file form; see the README).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Directory for the updated model, the SVG plots and report.html.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Writes the result as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// A diagnosis whose report is still to be shown and whose files are still to be
/// written. The caller prints: the command line's stdout handles a closed pipe and
/// a full disk, which `print!` here would panic on.
#[derive(Debug)]
pub struct Diagnosed<'a> {
    args: &'a DiagnoseArgs,
    diagnosis: Diagnosis,
}

/// Runs the command up to its outputs: reads the data and the model, then creates
/// `--out` and checks every output (none may be an input, a directory or named
/// twice) before diagnosing; writes nothing. A missing or bad input leaves no new
/// directory behind.
pub fn run(args: &DiagnoseArgs) -> Result<Diagnosed<'_>, DiagnoseError> {
    let m = Measurements::read_path(&args.data).map_err(|e| match e {
        // The reader's own error names the file already.
        MeasureError::Io { path, source } => DiagnoseError::Io { path, source },
        source => DiagnoseError::Data {
            path: args.data.display().to_string(),
            source,
        },
    })?;
    let model = args
        .model
        .as_deref()
        .map(ModelFile::read_path)
        .transpose()?;
    let mut outputs: Vec<PathBuf> = args.json.iter().cloned().collect();
    if let Some(dir) = &args.out {
        compgate_core::outputs::make_dir("--out", dir)?;
        outputs.extend(output::OUT_FILES.iter().map(|f| dir.join(f)));
    }
    let mut inputs = vec![args.data.as_path()];
    inputs.extend(args.model.as_deref());
    compgate_core::outputs::check(
        &inputs,
        &outputs.iter().map(PathBuf::as_path).collect::<Vec<_>>(),
    )?;
    if let Some(dir) = &args.out {
        output::check_models_are_ours(dir)?;
    }
    let opts = Options {
        sensors: args.sensors.clone(),
        model,
        ..Default::default()
    };
    Ok(Diagnosed {
        args,
        diagnosis: diagnose(&m, &opts)?,
    })
}

impl Diagnosed<'_> {
    /// The text report, for stdout, shown before the files are written: a file
    /// that cannot be written is told after the report it would have held.
    pub fn report(&self) -> String {
        output::text_report(&self.diagnosis)
    }

    /// Writes `--out`'s files, if asked; returns their paths in the order written.
    /// The directory before `--json`: its model check is the one that can refuse.
    pub fn write_out(&self) -> Result<Vec<PathBuf>, DiagnoseError> {
        match &self.args.out {
            Some(dir) => output::write_out(dir, &self.diagnosis),
            None => Ok(Vec::new()),
        }
    }

    /// Writes `--json`, if asked.
    pub fn write_json(&self) -> Result<(), DiagnoseError> {
        let Some(path) = &self.args.json else {
            return Ok(());
        };
        compgate_core::outputs::write(path, output::json(&self.diagnosis)).map_err(|source| {
            DiagnoseError::Io {
                path: path.display().to_string(),
                source,
            }
        })
    }
}
