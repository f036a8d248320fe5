//! `compgate diagnose` on the command line: files in, report and files out.

use std::path::PathBuf;

use super::{diagnose, output, DiagnoseError, ModelFile, Options};
use compgate_core::measure::Measurements;

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

/// Runs the command; the report goes to stdout.
pub fn run(args: &DiagnoseArgs) -> Result<(), DiagnoseError> {
    let mut outputs: Vec<PathBuf> = args.json.iter().cloned().collect();
    if let Some(dir) = &args.out {
        std::fs::create_dir_all(dir).map_err(|source| DiagnoseError::Io {
            path: dir.display().to_string(),
            source,
        })?;
        outputs.extend(output::OUT_FILES.iter().map(|f| dir.join(f)));
    }
    let mut inputs = vec![args.data.as_path()];
    inputs.extend(args.model.as_deref());
    compgate_core::outputs::check(
        &inputs,
        &outputs.iter().map(PathBuf::as_path).collect::<Vec<_>>(),
    )?;
    let m = Measurements::read_path(&args.data).map_err(|source| DiagnoseError::Data {
        path: args.data.display().to_string(),
        source,
    })?;
    let model = args
        .model
        .as_deref()
        .map(ModelFile::read_path)
        .transpose()?;
    let opts = Options {
        sensors: args.sensors.clone(),
        model,
        ..Default::default()
    };
    let d = diagnose(&m, &opts)?;
    print!("{}", output::text_report(&d));
    // The directory first: its model check is the one that can refuse.
    if let Some(dir) = &args.out {
        for p in output::write_out(dir, &d)? {
            println!("wrote {}", p.display());
        }
    }
    if let Some(path) = &args.json {
        compgate_core::outputs::write(path, output::json(&d)).map_err(|source| {
            DiagnoseError::Io {
                path: path.display().to_string(),
                source,
            }
        })?;
    }
    Ok(())
}
