//! The axis model and its file: the `[axes.NAME]` table calibrate writes, `scenario
//! --model` and diagnose read.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use serde::{Deserialize, Serialize};

use compgate_core::measure::Measurements;
use compgate_gateway::config::{K0Model, K0Term, MotionHeatModel, TanBetaModel, TanBetaTerm};

use super::{CalibrateError, Fit};

/// Why the `[axes.NAME]` of a model file cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    /// The file cannot be read.
    #[error("{0}")]
    Read(#[from] std::io::Error),
    /// The file is not TOML.
    #[error("{0}")]
    Toml(#[from] toml::de::Error),
    /// No `[axes.NAME]` table.
    #[error("no [axes.NAME] table")]
    NoAxes,
    /// `axes.NAME` is a value, not a table.
    #[error("axes.{0} is not a table")]
    NotATable(String),
    /// A model value is NaN, infinite or outside the range the gateway's config
    /// schema accepts for it.
    #[error("{key} = {value:?}: must be a finite number in {min}..={max}")]
    Implausible {
        /// Key path, e.g. `axes.X.k0.terms[0].coeff_mm_per_degc`.
        key: String,
        /// The value found.
        value: f64,
        /// Smallest accepted value.
        min: f64,
        /// Largest accepted value.
        max: f64,
    },
    /// A model key of `axes.NAME` is malformed.
    #[error("axes.{axis}: {}", source.message())]
    Invalid {
        /// The axis name.
        axis: String,
        /// What TOML reported.
        #[source]
        source: toml::de::Error,
    },
}

/// The model part of an `[axes.NAME]` table: what calibrate writes, `scenario
/// --model` reads, and the axis part of diagnose's model file.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct AxisModel {
    /// SD43920, mm.
    #[serde(default)]
    pub p0_mm: f64,
    /// The doubts about the fit that the model was written over (`calibrate
    /// --accept-weak-fit`, or `scenario`, which runs its fit whatever it holds): the
    /// gateway warns of them at every start, and `validate` too.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub accepted_doubts: Vec<String>,
    /// K0(T) -> SD43900.
    #[serde(default)]
    pub k0: K0Model,
    /// tan(beta)(T) -> SD43910.
    #[serde(default)]
    pub tan_beta: TanBetaModel,
    /// Heat of axis motion from the NC's actual position (diagnose adds it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub motion_heat: Option<MotionHeatModel>,
    /// The temperatures the model was fitted over, per channel, degC: the gateway
    /// flags a reading beyond them.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub fitted_degc: BTreeMap<String, [f64; 2]>,
}

/// Plausible ranges of the model's values, the same as the gateway's config schema
/// for `[axes.NAME]` (`p0_mm`, `k0`, `tan_beta` in the gateway's `axis` module): a
/// model outside them would be refused by the gateway, or is a failed fit.
pub mod bounds {
    /// `p0_mm`, mm.
    pub const P0_MM: (f64, f64) = (-100_000.0, 100_000.0);
    /// `k0.offset_mm`, mm (SD43900 is limited to 10 mm by the NC).
    pub const K0_OFFSET_MM: (f64, f64) = (-10.0, 10.0);
    /// `k0.terms[].coeff_mm_per_degc`, mm/K.
    pub const K0_COEFF_MM_PER_DEGC: (f64, f64) = (-1.0, 1.0);
    /// `tan_beta.offset`.
    pub const TAN_BETA_OFFSET: (f64, f64) = (-0.1, 0.1);
    /// `tan_beta.terms[].coeff_per_degc`, 1/K.
    pub const TAN_BETA_COEFF_PER_DEGC: (f64, f64) = (-0.01, 0.01);
    /// `*.terms[].ref_degc`, degC.
    pub const REF_DEGC: (f64, f64) = (-100.0, 500.0);
    /// `*.terms[].lag_tau_s`, s.
    pub const LAG_TAU_S: (f64, f64) = (0.0, 86_400.0);
    /// `motion_heat.tau_s`, s.
    pub const MOTION_TAU_S: (f64, f64) = (1.0, 86_400.0);
    /// `motion_heat.ref_mm_per_s`, mm/s.
    pub const MOTION_REF_MM_PER_S: (f64, f64) = (0.0, 10_000.0);
    /// `motion_heat.k0_mm_per_mm_per_s`.
    pub const MOTION_K0_MM_PER_MM_PER_S: (f64, f64) = (-0.01, 0.01);
    /// `motion_heat.tan_beta_per_mm_per_s`.
    pub const MOTION_TAN_BETA_PER_MM_PER_S: (f64, f64) = (-0.0001, 0.0001);
}

impl AxisModel {
    /// Checks every value against [`bounds`]; the error names the key under
    /// `axes.<axis>`. Both the writer and the reader call it, so a model file never
    /// holds a value the gateway would refuse or a NaN.
    pub fn check(&self, axis: &str) -> Result<(), ModelError> {
        let one = |key: String, value: f64, (min, max): (f64, f64)| {
            if value.is_finite() && (min..=max).contains(&value) {
                Ok(())
            } else {
                Err(ModelError::Implausible {
                    key: format!("axes.{axis}.{key}"),
                    value,
                    min,
                    max,
                })
            }
        };
        one("p0_mm".into(), self.p0_mm, bounds::P0_MM)?;
        one(
            "k0.offset_mm".into(),
            self.k0.offset_mm,
            bounds::K0_OFFSET_MM,
        )?;
        for (i, t) in self.k0.terms.iter().enumerate() {
            one(
                format!("k0.terms[{i}].ref_degc"),
                t.ref_degc,
                bounds::REF_DEGC,
            )?;
            one(
                format!("k0.terms[{i}].coeff_mm_per_degc"),
                t.coeff_mm_per_degc,
                bounds::K0_COEFF_MM_PER_DEGC,
            )?;
        }
        one(
            "tan_beta.offset".into(),
            self.tan_beta.offset,
            bounds::TAN_BETA_OFFSET,
        )?;
        for (i, t) in self.tan_beta.terms.iter().enumerate() {
            one(
                format!("tan_beta.terms[{i}].ref_degc"),
                t.ref_degc,
                bounds::REF_DEGC,
            )?;
            one(
                format!("tan_beta.terms[{i}].coeff_per_degc"),
                t.coeff_per_degc,
                bounds::TAN_BETA_COEFF_PER_DEGC,
            )?;
        }
        let lags = (self.k0.terms.iter().map(|t| ("k0", t.lag_tau_s))).chain(
            self.tan_beta
                .terms
                .iter()
                .map(|t| ("tan_beta", t.lag_tau_s)),
        );
        for (i, (part, lag)) in lags.enumerate() {
            let i = if part == "k0" {
                i
            } else {
                i - self.k0.terms.len()
            };
            one(
                format!("{part}.terms[{i}].lag_tau_s"),
                lag,
                bounds::LAG_TAU_S,
            )?;
        }
        if let Some(h) = &self.motion_heat {
            one("motion_heat.tau_s".into(), h.tau_s, bounds::MOTION_TAU_S)?;
            one(
                "motion_heat.ref_mm_per_s".into(),
                h.ref_mm_per_s,
                bounds::MOTION_REF_MM_PER_S,
            )?;
            one(
                "motion_heat.k0_mm_per_mm_per_s".into(),
                h.k0_mm_per_mm_per_s,
                bounds::MOTION_K0_MM_PER_MM_PER_S,
            )?;
            one(
                "motion_heat.tan_beta_per_mm_per_s".into(),
                h.tan_beta_per_mm_per_s,
                bounds::MOTION_TAN_BETA_PER_MM_PER_S,
            )?;
        }
        Ok(())
    }

    /// The fitted model in config units (mm, mm/mm).
    pub fn from_fit(f: &Fit) -> Self {
        Self {
            p0_mm: f.p0_mm,
            accepted_doubts: f.doubts(),
            k0: K0Model {
                offset_mm: f.k0_offset_um / 1000.0,
                terms: f
                    .terms
                    .iter()
                    .map(|t| K0Term {
                        channel: t.name.clone(),
                        ref_degc: t.ref_degc,
                        coeff_mm_per_degc: t.k0_um_per_degc / 1000.0,
                        lag_tau_s: 0.0,
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
                        lag_tau_s: 0.0,
                    })
                    .collect(),
            },
            motion_heat: None,
            fitted_degc: f
                .terms
                .iter()
                .map(|t| {
                    (
                        t.name.clone(),
                        fitted_range(t.range_degc[0], t.range_degc[1]),
                    )
                })
                .collect(),
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

    /// Error the model predicts for every row of `m`, um, as the gateway computes it
    /// online: lagged terms read their channel through the lag, the motion heat term
    /// the travel column. `Err(channel)` names a channel the data lacks.
    pub fn predict_series_um(&self, m: &Measurements) -> Result<Vec<f64>, String> {
        let n = m.len();
        let signal = |ch: &str, tau_s: f64| -> Result<Vec<f64>, String> {
            let x = m.temp(ch).ok_or_else(|| ch.to_string())?;
            Ok(if tau_s > 0.0 {
                crate::diagnose::effects::lag(&m.t_s, x, tau_s)
            } else {
                x.to_vec()
            })
        };
        let mut k0_mm = vec![self.k0.offset_mm; n];
        for t in &self.k0.terms {
            for (k, x) in k0_mm.iter_mut().zip(signal(&t.channel, t.lag_tau_s)?) {
                *k += t.coeff_mm_per_degc * (x - t.ref_degc);
            }
        }
        let mut tan = vec![self.tan_beta.offset; n];
        for t in &self.tan_beta.terms {
            for (k, x) in tan.iter_mut().zip(signal(&t.channel, t.lag_tau_s)?) {
                *k += t.coeff_per_degc * (x - t.ref_degc);
            }
        }
        if let Some(h) = &self.motion_heat {
            let heat = crate::diagnose::effects::motion_heat(&m.t_s, &m.travel_mm, h.tau_s);
            for i in 0..n {
                k0_mm[i] += h.k0_mm_per_mm_per_s * (heat[i] - h.ref_mm_per_s);
                tan[i] += h.tan_beta_per_mm_per_s * (heat[i] - h.ref_mm_per_s);
            }
        }
        Ok((0..n)
            .map(|i| 1000.0 * (k0_mm[i] + tan[i] * (m.pos_mm[i] - self.p0_mm)))
            .collect())
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

/// The model as a TOML fragment `[axes.<axis>]`, with a comment header; refuses a
/// model with a non-finite or implausible value ([`AxisModel::check`]).
pub fn model_toml(
    axis: &str,
    nc_module: &str,
    model: &AxisModel,
    header: &str,
) -> Result<String, ModelError> {
    model.check(axis)?;
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
    Ok(s)
}

/// A `fitted_degc` entry for temperatures from `lo` to `hi`: to 0.01 K, outwards, so
/// that it holds every temperature fitted.
pub fn fitted_range(lo: f64, hi: f64) -> [f64; 2] {
    [(lo * 100.0).floor() / 100.0, (hi * 100.0).ceil() / 100.0]
}

/// Reads the first `[axes.NAME]` of a model file (from calibrate or diagnose) or of a
/// whole gateway config; keys other than `p0_mm`, `k0`, `tan_beta` and `motion_heat`
/// are ignored.
pub fn load_model(path: &Path) -> Result<(String, AxisModel), CalibrateError> {
    let read = || -> Result<_, ModelError> {
        let text = std::fs::read_to_string(path)?;
        first_axis_model(&toml::from_str(&text)?)
    };
    read().map_err(|source| CalibrateError::Model {
        path: path.display().to_string(),
        source: Box::new(source),
    })
}

/// The first `[axes.NAME]` of a parsed model file or gateway config, and its name;
/// keys other than `p0_mm`, `k0` and `tan_beta` are ignored. The error names the key.
pub fn first_axis_model(root: &toml::Table) -> Result<(String, AxisModel), ModelError> {
    let (name, axis) = root
        .get("axes")
        .and_then(|a| a.as_table())
        .and_then(|a| a.iter().next())
        .ok_or(ModelError::NoAxes)?;
    let mut t = axis
        .as_table()
        .cloned()
        .ok_or_else(|| ModelError::NotATable(name.clone()))?;
    t.retain(|k, _| {
        matches!(
            k,
            "p0_mm" | "k0" | "tan_beta" | "motion_heat" | "fitted_degc"
        )
    });
    let model: AxisModel =
        toml::Value::Table(t)
            .try_into()
            .map_err(|source| ModelError::Invalid {
                axis: name.clone(),
                source,
            })?;
    model.check(name)?;
    Ok((name.clone(), model))
}
