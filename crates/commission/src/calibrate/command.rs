//! `compgate calibrate` on the command line: the measurements in, the model file, the
//! plot and the report out.

use std::fmt::Write as _;
use std::path::PathBuf;

use compgate_core::measure::Measurements;

use super::model::{model_toml, AxisModel};
use super::report::{plot_curves, report};
use super::{calibrate, CalibrateError};

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

/// Runs the command: read, fit, write the model (and plot); returns the report.
pub fn run(args: &CalibrateArgs) -> Result<String, CalibrateError> {
    let mut outputs = vec![args.out.as_path()];
    outputs.extend(args.plot.as_deref());
    compgate_core::outputs::check(&[&args.data], &outputs)?;
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
    // Refused before anything is written: a model the gateway would load must
    // never hold a NaN or an absurd coefficient.
    let text = model_toml(&args.axis, &args.nc_module, &model, &header).map_err(|source| {
        CalibrateError::Model {
            path: args.out.display().to_string(),
            source: Box::new(source),
        }
    })?;
    compgate_core::outputs::write(&args.out, text).map_err(|source| CalibrateError::Io {
        path: args.out.display().to_string(),
        source,
    })?;
    let mut out = report(&f);
    let _ = writeln!(out, "model written to {}", args.out.display());
    if let Some(plot) = &args.plot {
        plot_curves(plot, &m, &f)?;
        let _ = writeln!(out, "plot written to {}", plot.display());
    }
    Ok(out)
}
