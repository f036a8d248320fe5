//! `compgate calibrate`: the patent's step S1. Fits K0(T) and tan(beta)(T) to error
//! curves measured at several temperatures and writes the axis model in the form of
//! the gateway config (`[axes.NAME]` with `p0_mm`, `k0`, `tan_beta`).
//!
//! The model's channels are the CSV's temperature columns without `T_`: name the
//! gateway's channels alike (or rename them in the written file).

pub mod bad;
mod command;
pub mod fit;
mod model;
mod report;

use compgate_core::measure::{MeasureError, Measurements};
use thiserror::Error;

use crate::plot::PlotError;
pub use bad::{bad_readings, BadReadings};
pub use command::{run, CalibrateArgs, Calibrated};
pub use fit::{Fit, FitError};
pub use model::{
    bounds, first_axis_model, fitted_range, load_model, model_toml, AxisModel, ModelError,
};
pub use report::{plot_curves, render_curves, report};

/// Errors of `calibrate` and of reading a model file.
#[derive(Debug, Error)]
pub enum CalibrateError {
    #[error("{0}: {1}")]
    Data(String, MeasureError),
    #[error("--sensors: no column T_{0} in the data (it has: {1}){2}")]
    NoSensor(String, String, String),
    #[error("fit: {0}")]
    Fit(#[from] FitError),
    #[error("{0}")]
    Arg(#[from] crate::args::ArgError),
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{0}")]
    Plot(#[from] PlotError),
    #[error("{0}")]
    Output(#[from] compgate_core::outputs::OutputError),
    /// The fit is in doubt ([`Fit::doubts`]); nothing written.
    #[error(
        "{path}: not written: {doubts} (see the warnings above); --accept-weak-fit writes \
         it anyway"
    )]
    Doubtful { path: String, doubts: String },
    #[error("{path}: {source}")]
    Model {
        path: String,
        // Boxed: a TOML error is large, and every Result of the module carries this.
        #[source]
        source: Box<ModelError>,
    },
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
    crate::args::sensor_names(wanted)?
        .into_iter()
        .map(|name| {
            m.temps
                .iter()
                .find(|c| c.name == name)
                .map(|c| (c.name.as_str(), c.degc.as_slice()))
                .ok_or_else(|| {
                    // With the columns a selective read left out.
                    let have: Vec<String> = m
                        .temps
                        .iter()
                        .map(|c| format!("T_{}", c.name))
                        .chain(
                            m.ignored_columns
                                .iter()
                                .filter(|c| c.starts_with("T_"))
                                .cloned(),
                        )
                        .collect();
                    // `T_a [degC]` for `a`: units in the header.
                    let prefix = format!("T_{name}");
                    let hint = have
                        .iter()
                        .find(|h| {
                            h.strip_prefix(&prefix).is_some_and(|rest| {
                                rest.starts_with(|c: char| !c.is_ascii_alphanumeric() && c != '_')
                            })
                        })
                        .map_or(String::new(), |h| {
                            format!("; `{h}`: the header holds the name alone, without units")
                        });
                    CalibrateError::NoSensor(name.to_string(), have.join(", "), hint)
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
    if let Some(p) = p0_mm {
        // NaN made the SVD spin for ever; a P0 beyond the gateway's range is a typo.
        crate::args::check_f64("--p0-mm", p, bounds::P0_MM.0, bounds::P0_MM.1, "mm")?;
    }
    let cols = select_sensors(m, sensors)?;
    let p0_mm = p0_mm.unwrap_or_else(|| fit::choose_p0_mm(&m.pos_mm));
    Ok(fit::fit(&m.pos_mm, &m.err_um, &cols, p0_mm)?)
}

/// Longest sweep, s: rows at a regular interval (a recording exported every
/// `--step-s`) have no pauses, and were one "sweep" over the whole run, drawn as one
/// curve at the first row's temperature.
pub const MAX_SWEEP_S: f64 = 3600.0;

/// Splits rows into sweeps: a new sweep starts after a pause longer than 5 times the
/// median time step, or [`MAX_SWEEP_S`] after the sweep's first row.
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
        if t_s[i] - t_s[i - 1] > gap || t_s[i] - t_s[start] >= MAX_SWEEP_S {
            out.push(start..i);
            start = i;
        }
    }
    out.push(start..t_s.len());
    out
}

#[cfg(test)]
mod tests;
