//! The model file `--model` reads and `--out` writes.
//!
//! The axis part is an `[axes.X]` table in the form `calibrate` writes and
//! `scenario --model` and the gateway config read (`p0_mm`, `[axes.X.k0]`,
//! `[axes.X.tan_beta]`, `[axes.X.motion_heat]`, same structs), with channels named
//! after the data's sensors (`T_<name>` column -> channel `<name>`). A thermal lag
//! is a term with `lag_tau_s`; motion heat is `[axes.X.motion_heat]`. Everything
//! else is written as comments, so that the whole file can be pasted into a gateway
//! config: the lines that start with `#=` hold TOML for `diagnose --model` alone,
//! `applied` (the effects the gateway applies online, one line each) and
//! `[[effects]]` (effects the gateway's K0/tan(beta) form cannot carry, with the NC
//! function that carries them: reversal: backlash MD32450; pitch and nonlinear
//! position: the leadscrew error compensation table). Older files held these as
//! plain top-level keys, and `[[lagged_channels]]` for a lag; both are still read.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::effects::{lag, legendre_2_4, motion_heat, EffectKind};
use super::{DiagnoseError, Diagnosis};
use crate::calibrate::{fitted_range, AxisModel};
use compgate_core::measure::Measurements;
use compgate_gateway::config::schema::{
    K0Model, K0Term, MotionHeatModel, TanBetaModel, TanBetaTerm,
};

/// The first line of every model file diagnose writes (after `# `): how `--out`
/// tells its own files, which it replaces, from anyone else's, which it keeps.
pub const WRITTEN_BY: &str = "Thermal model written by `compgate diagnose`.";

/// A thermal model file: the axis model `calibrate` writes, plus what only diagnose
/// adds (lagged channels, effects outside the K0/tan(beta) form).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ModelFile {
    /// The `[axes.NAME]` part: P0, K0(T) and tan(beta)(T).
    pub axis: AxisModel,
    /// Channels that are a sensor seen through a first-order lag; the gateway realises
    /// one as a channel on the sensor's transmitter with `filter.lowpass_tau_s`.
    pub lagged_channels: Vec<LaggedChannel>,
    /// Effects outside the K0/tan(beta) form, with the NC function that carries them.
    pub effects: Vec<EffectTerm>,
    /// Effects the gateway applies online (in `[axes.X]`), one line each.
    pub applied: Vec<String>,
}

/// A lagged view of a sensor.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LaggedChannel {
    /// Channel name the k0/tan_beta terms use.
    pub channel: String,
    /// Sensor (channel) it is derived from.
    pub sensor: String,
    /// First-order time constant, s (the channel's `filter.lowpass_tau_s`).
    pub lowpass_tau_s: f64,
}

/// An effect term outside the K0/tan(beta) form.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EffectTerm {
    /// Effect name: `reversal`, `pitch_periodic`, `nonlinear_position`,
    /// `motion_heating`.
    pub name: String,
    /// The NC function that carries it, or why the gateway does not apply it.
    pub carried_by: String,
    /// Parameters (units in the names); see the README.
    pub params: BTreeMap<String, f64>,
}

/// The prefix of the comment lines that hold TOML for `diagnose --model` alone.
const NOTE: &str = "#=";

/// `toml` as `#=` comment lines.
fn as_notes(toml: &str) -> String {
    toml.lines()
        .map(|l| {
            if l.is_empty() {
                format!("{NOTE}\n")
            } else {
                format!("{NOTE} {l}\n")
            }
        })
        .collect()
}

/// The TOML of the `#=` lines of `text`.
fn diagnose_lines(text: &str) -> String {
    text.lines()
        .filter_map(|l| l.trim_start().strip_prefix(NOTE))
        .map(|l| format!("{}\n", l.strip_prefix(' ').unwrap_or(l)))
        .collect()
}

fn get(params: &BTreeMap<String, f64>, key: &str) -> f64 {
    params.get(key).copied().unwrap_or(0.0)
}

impl ModelFile {
    /// Reads and checks a model file; errors name the file and key.
    pub fn read_path(path: &std::path::Path) -> Result<Self, DiagnoseError> {
        let text = std::fs::read_to_string(path).map_err(|source| DiagnoseError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::from_toml(&text, &path.display().to_string())
    }

    /// Parses the text of a model file: the first `[axes.NAME]` (keys other than
    /// `p0_mm`, `k0`, `tan_beta` and `motion_heat` are ignored, so a whole gateway
    /// config or a calibrate model will do) plus the optional `applied`, `effects`
    /// and `lagged_channels`, from the `#=` lines or (older files) the top level.
    /// `origin` names the file in errors.
    pub fn from_toml(text: &str, origin: &str) -> Result<Self, DiagnoseError> {
        let err = |message: String| DiagnoseError::ModelFile {
            path: origin.to_string(),
            message,
        };
        let root: toml::Table = toml::from_str(text).map_err(|e| err(e.to_string()))?;
        let notes: toml::Table = toml::from_str(&diagnose_lines(text))
            .map_err(|e| err(format!("the `{NOTE}` lines: {e}")))?;
        let (_, axis) =
            crate::calibrate::first_axis_model(&root).map_err(|e| err(e.to_string()))?;
        // The same key from both places: the top level (older files) first.
        fn list<T: serde::de::DeserializeOwned>(
            tables: [&toml::Table; 2],
            key: &str,
        ) -> Result<Vec<T>, String> {
            let mut out = Vec::new();
            for t in tables {
                if let Some(v) = t.get(key) {
                    let part: Vec<T> = v
                        .clone()
                        .try_into()
                        .map_err(|e: toml::de::Error| format!("{key}: {}", e.message()))?;
                    out.extend(part);
                }
            }
            Ok(out)
        }
        let tables = [&root, &notes];
        let lagged_channels: Vec<LaggedChannel> = list(tables, "lagged_channels").map_err(err)?;
        let effects: Vec<EffectTerm> = list(tables, "effects").map_err(err)?;
        for e in &effects {
            if EffectKind::from_name(&e.name).is_none() {
                return Err(err(format!("effects: unknown effect name `{}`", e.name)));
            }
        }
        let applied: Vec<String> = list(tables, "applied").map_err(err)?;
        let mf = ModelFile {
            axis,
            lagged_channels,
            effects,
            applied,
        };
        mf.check_extras().map_err(err)?;
        Ok(mf)
    }

    /// The values outside `[axes.X]` (the axis part has [`AxisModel::check`]) must
    /// be finite, and a lag a positive time: they feed the prediction and the fit.
    fn check_extras(&self) -> Result<(), String> {
        for (i, l) in self.lagged_channels.iter().enumerate() {
            let tau = l.lowpass_tau_s;
            if !(tau.is_finite() && tau > 0.0) {
                return Err(format!(
                    "lagged_channels[{i}].lowpass_tau_s = {tau}: must be a finite time > 0 s"
                ));
            }
        }
        for (i, e) in self.effects.iter().enumerate() {
            for (k, v) in &e.params {
                if !v.is_finite() {
                    return Err(format!(
                        "effects[{i}].params.{k} = {v}: must be a finite number"
                    ));
                }
            }
        }
        Ok(())
    }

    /// The TOML text: `[axes.X]` as calibrate writes it, with a header comment, the
    /// `applied` list before it and the effects after it on `#=` lines, so that the
    /// whole file pastes into a gateway config. Refuses a model holding a NaN or a
    /// value outside the gateway's ranges; `origin` names the file in the error.
    pub fn to_toml(&self, origin: &str) -> Result<String, DiagnoseError> {
        let err = |message: String| DiagnoseError::ModelFile {
            path: origin.to_string(),
            message,
        };
        self.check_extras().map_err(err)?;
        let header = format!(
            "{WRITTEN_BY}\n\
             The [axes.X] tables are the gateway's axis form (as calibrate writes it;\n\
             scenario --model reads it): paste the whole file into the gateway config,\n\
             every other line is a comment. Channels are the data's sensors (column\n\
             T_<name> -> channel <name>). lag_tau_s on a term: the gateway reads that\n\
             channel through a first-order lag; [axes.X.motion_heat]: heat of axis motion\n\
             from the NC's actual position.\n\
             The lines that start with `#=` are for `compgate diagnose --model`, not the\n\
             gateway: `applied` names the effects the gateway applies online, [[effects]]\n\
             the others, with the NC function that carries them.\n"
        );
        let mut s = crate::calibrate::model_toml("X", "nc_x", &self.axis, &header)
            .map_err(|e| err(e.to_string()))?;
        #[derive(Serialize)]
        struct Extra<'a> {
            #[serde(skip_serializing_if = "<[_]>::is_empty")]
            lagged_channels: &'a [LaggedChannel],
            #[serde(skip_serializing_if = "<[_]>::is_empty")]
            effects: &'a [EffectTerm],
        }
        if !self.applied.is_empty() {
            #[derive(Serialize)]
            struct Applied<'a> {
                applied: &'a [String],
            }
            let applied = toml::to_string(&Applied {
                applied: &self.applied,
            })
            .unwrap_or_default();
            let at = s.find("\n[axes").map_or(0, |i| i + 1);
            s.insert_str(at, &format!("{}\n", as_notes(&applied)));
        }
        let extra = toml::to_string(&Extra {
            lagged_channels: &self.lagged_channels,
            effects: &self.effects,
        })
        .unwrap_or_default();
        if !extra.is_empty() {
            s.push('\n');
            s.push_str(&as_notes(&extra));
        }
        Ok(s)
    }

    /// The error the model predicts for every row, um.
    // Index loops: several row-aligned series at once.
    #[allow(clippy::needless_range_loop)]
    pub fn predict_um(&self, m: &Measurements) -> Result<Vec<f64>, DiagnoseError> {
        // Lagged channels (older model files) become columns of their own.
        let mut with_lags;
        let mut data = m;
        if !self.lagged_channels.is_empty() {
            with_lags = m.clone();
            for l in &self.lagged_channels {
                let src = m
                    .temp(&l.sensor)
                    .ok_or_else(|| DiagnoseError::UnknownChannel {
                        channel: l.sensor.clone(),
                        key: format!("lagged_channels `{}`", l.channel),
                    })?;
                with_lags.temps.push(compgate_core::measure::TempColumn {
                    name: l.channel.clone(),
                    degc: lag(&m.t_s, src, l.lowpass_tau_s),
                });
            }
            data = &with_lags;
        }
        // Every channel the axis reads must exist, named with its key, before any row.
        let k0 = self.axis.k0.terms.iter().map(|t| (&t.channel, "k0.terms"));
        let tan = self
            .axis
            .tan_beta
            .terms
            .iter()
            .map(|t| (&t.channel, "tan_beta.terms"));
        for (ch, key) in k0.chain(tan) {
            if data.temp(ch).is_none() {
                return Err(DiagnoseError::UnknownChannel {
                    channel: ch.clone(),
                    key: key.to_string(),
                });
            }
        }
        let n = m.len();
        let mut out =
            self.axis
                .predict_series_um(data)
                .map_err(|channel| DiagnoseError::UnknownChannel {
                    channel,
                    key: "k0/tan_beta terms".into(),
                })?;
        for e in &self.effects {
            let p = &e.params;
            match EffectKind::from_name(&e.name) {
                Some(EffectKind::Reversal) => {
                    for i in 0..n {
                        out[i] += 0.5 * get(p, "b_um") * f64::from(m.dir[i]);
                    }
                }
                Some(EffectKind::PitchPeriodic) => {
                    let w = std::f64::consts::TAU / get(p, "period_mm");
                    for i in 0..n {
                        out[i] +=
                            get(p, "amplitude_um") * (w * m.pos_mm[i] + get(p, "phase_rad")).sin();
                    }
                }
                Some(EffectKind::NonlinearPosition) => {
                    let (c, h) = (get(p, "center_mm"), get(p, "half_span_mm").max(1e-9));
                    for i in 0..n {
                        let l = legendre_2_4((m.pos_mm[i] - c) / h);
                        out[i] += get(p, "legendre_p2_um") * l[0]
                            + get(p, "legendre_p3_um") * l[1]
                            + get(p, "legendre_p4_um") * l[2];
                    }
                }
                Some(EffectKind::MotionHeating) => {
                    let h = motion_heat(&m.t_s, &m.travel_mm, get(p, "tau_s").max(1e-9));
                    let r = get(p, "ref_mm_per_s");
                    for i in 0..n {
                        out[i] += (h[i] - r)
                            * (get(p, "k0_um_per_mm_per_s")
                                + get(p, "slope_um_per_mm_per_mm_per_s")
                                    * (m.pos_mm[i] - self.axis.p0_mm));
                    }
                }
                _ => {}
            }
        }
        Ok(out)
    }

    /// The baseline refit alone (K0 and tan(beta) affine in the sensors).
    pub fn baseline_from_diagnosis(d: &Diagnosis) -> Self {
        Self::build(d, &d.beta_baseline, &[])
    }

    /// The updated model of a diagnosis: the refitted baseline plus every added effect.
    pub fn from_diagnosis(d: &Diagnosis) -> Self {
        Self::build(d, &d.beta, &d.effects)
    }

    fn build(d: &Diagnosis, b: &[f64], effects: &[super::EffectReport]) -> Self {
        let mut mf = ModelFile {
            axis: AxisModel {
                p0_mm: d.p0_mm,
                accepted_doubts: Vec::new(),
                k0: K0Model {
                    offset_mm: b[0] / 1000.0,
                    terms: Vec::new(),
                },
                tan_beta: TanBetaModel {
                    offset: b[1] / 1000.0,
                    terms: Vec::new(),
                },
                motion_heat: None,
                fitted_degc: Default::default(),
            },
            ..Default::default()
        };
        let push = |mf: &mut ModelFile,
                    channel: String,
                    ref_degc: f64,
                    k0: f64,
                    slope: f64,
                    lag_tau_s: f64| {
            mf.axis.k0.terms.push(K0Term {
                channel: channel.clone(),
                ref_degc,
                coeff_mm_per_degc: k0 / 1000.0,
                lag_tau_s,
            });
            mf.axis.tan_beta.terms.push(TanBetaTerm {
                channel,
                ref_degc,
                coeff_per_degc: slope / 1000.0,
                lag_tau_s,
            });
        };
        for (j, &s) in d.sensor_idx.iter().enumerate() {
            push(
                &mut mf,
                d.temp_names[s].clone(),
                d.temp_mean_degc[s],
                b[2 + 2 * j],
                b[3 + 2 * j],
                0.0,
            );
        }
        for e in effects {
            let c = &b[e.cols.0..e.cols.1];
            let p = |k: &str| e.params.get(k).and_then(|v| v.as_f64()).unwrap_or(0.0);
            match e.kind {
                EffectKind::ThermalLag => {
                    let which: Vec<usize> = match e.sensor {
                        Some(s) => vec![s],
                        None => d.sensor_idx.clone(),
                    };
                    let tau = e.param.unwrap_or(0.0);
                    let mut names = Vec::new();
                    for (k, s) in which.into_iter().enumerate() {
                        let sensor = d.temp_names[s].clone();
                        names.push(sensor.clone());
                        let mean = e.signal_mean.get(k).copied().unwrap_or(0.0);
                        push(&mut mf, sensor, mean, c[2 * k], c[2 * k + 1], tau);
                    }
                    mf.applied.push(format!(
                        "thermal_lag: {} through a {tau:.0} s lag (terms with lag_tau_s)",
                        names.join(", ")
                    ));
                }
                EffectKind::ExtraSensor => {
                    let s = e.sensor.unwrap_or(0);
                    push(
                        &mut mf,
                        d.temp_names[s].clone(),
                        d.temp_mean_degc[s],
                        c[0],
                        c[1],
                        0.0,
                    );
                    mf.applied.push(format!(
                        "extra_sensor: {} (k0 and tan_beta terms)",
                        d.temp_names[s]
                    ));
                }
                EffectKind::Reversal => mf.effects.push(EffectTerm {
                    name: e.name.into(),
                    carried_by: "NC backlash compensation MD32450 = |b_um| (b_um is the error \
                                 approaching in + minus the error approaching in -); not applied \
                                 by the gateway"
                        .into(),
                    params: BTreeMap::from([("b_um".into(), p("b_um"))]),
                }),
                EffectKind::PitchPeriodic => mf.effects.push(EffectTerm {
                    name: e.name.into(),
                    carried_by: "NC leadscrew error compensation table (LEC); not applied \
                                 by the gateway"
                        .into(),
                    params: BTreeMap::from([
                        ("period_mm".into(), p("period_mm")),
                        ("amplitude_um".into(), p("amplitude_um")),
                        ("phase_rad".into(), p("phase_rad")),
                    ]),
                }),
                EffectKind::NonlinearPosition => mf.effects.push(EffectTerm {
                    name: e.name.into(),
                    carried_by: "NC leadscrew error compensation table (LEC); not applied \
                                 by the gateway"
                        .into(),
                    params: [
                        "legendre_p2_um",
                        "legendre_p3_um",
                        "legendre_p4_um",
                        "center_mm",
                        "half_span_mm",
                    ]
                    .into_iter()
                    .map(|k| (k.to_string(), p(k)))
                    .collect(),
                }),
                EffectKind::MotionHeating => {
                    let tau_s = p("tau_s");
                    mf.axis.motion_heat = Some(MotionHeatModel {
                        tau_s,
                        ref_mm_per_s: e.signal_mean.first().copied().unwrap_or(0.0),
                        k0_mm_per_mm_per_s: c[0] / 1000.0,
                        tan_beta_per_mm_per_s: c[1] / 1000.0,
                    });
                    mf.applied.push(format!(
                        "motion_heating: travel from the NC's actual position through a \
                         {tau_s:.0} s store ([axes.X.motion_heat])"
                    ));
                }
            }
        }
        // Each term's channel, over the temperatures the data held.
        let channels = mf.axis.k0.terms.iter().map(|t| &t.channel);
        let channels = channels.chain(mf.axis.tan_beta.terms.iter().map(|t| &t.channel));
        mf.axis.fitted_degc = channels
            .filter_map(|ch| {
                let s = d.temp_names.iter().position(|n| n == ch)?;
                let [lo, hi] = *d.temp_range_degc.get(s)?;
                Some((ch.clone(), fitted_range(lo, hi)))
            })
            .collect();
        mf
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use compgate_core::measure::TempColumn;
    use compgate_gateway::config::schema::AxisConfig;

    fn model() -> ModelFile {
        ModelFile {
            axis: AxisModel {
                p0_mm: 100.0,
                accepted_doubts: Vec::new(),
                k0: K0Model {
                    offset_mm: 0.001,
                    terms: vec![
                        K0Term {
                            channel: "a".into(),
                            ref_degc: 20.0,
                            coeff_mm_per_degc: 0.002,
                            lag_tau_s: 0.0,
                        },
                        K0Term {
                            channel: "a".into(),
                            ref_degc: 20.0,
                            coeff_mm_per_degc: -0.001,
                            lag_tau_s: 100.0,
                        },
                    ],
                },
                tan_beta: TanBetaModel {
                    offset: 0.0,
                    terms: vec![TanBetaTerm {
                        channel: "a".into(),
                        ref_degc: 20.0,
                        coeff_per_degc: 1e-5,
                        lag_tau_s: 0.0,
                    }],
                },
                motion_heat: None,
                fitted_degc: Default::default(),
            },
            lagged_channels: vec![],
            applied: vec!["thermal_lag: a through a 100 s lag".into()],
            effects: vec![EffectTerm {
                name: "reversal".into(),
                carried_by: "MD32450".into(),
                params: BTreeMap::from([("b_um".into(), 4.0)]),
            }],
        }
    }

    #[test]
    fn round_trips_and_its_axis_keys_load_as_a_gateway_axis() {
        let m = model();
        let text = m.to_toml("m.toml").expect("a valid model");
        let back = ModelFile::from_toml(&text, "m.toml").expect("parse");
        assert_eq!(back, m);
        // calibrate's reader (the one scenario --model uses) takes it too.
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("model.toml");
        std::fs::write(&path, &text).expect("write");
        let (name, axis) = crate::calibrate::load_model(&path).expect("calibrate reads it");
        assert_eq!(name, "X");
        assert_eq!(
            (axis.k0, axis.tan_beta, axis.p0_mm),
            (m.axis.k0.clone(), m.axis.tan_beta.clone(), m.axis.p0_mm)
        );
        // p0_mm, [k0] and [tan_beta] are the keys of [axes.NAME].
        #[derive(Serialize)]
        struct AxisPart<'a> {
            nc_module: &'a str,
            md32750: u16,
            p0_mm: f64,
            k0: &'a K0Model,
            tan_beta: &'a TanBetaModel,
        }
        let axis = toml::to_string(&AxisPart {
            nc_module: "nc1",
            md32750: 3,
            p0_mm: m.axis.p0_mm,
            k0: &m.axis.k0,
            tan_beta: &m.axis.tan_beta,
        })
        .expect("toml");
        let axis: AxisConfig = toml::from_str(&axis).expect("axis config");
        assert_eq!(axis.k0, m.axis.k0);
        assert_eq!(axis.tan_beta, m.axis.tan_beta);
        assert_eq!(axis.p0_mm, 100.0);
    }

    /// The file appended to a gateway config: its top-level `applied = [...]`, after
    /// the tables, attached to the config's last table, and `[[effects]]` was an
    /// unknown key. The whole file now pastes, and `--model` still reads all of it.
    #[test]
    fn the_written_model_pastes_into_a_gateway_config() {
        let config = "[devices.ain1]\ntransport = \"tcp\"\naddress = \"192.168.0.10:502\"\n\
                      unit_id = 1\n\n[channels.a]\ndevice = \"ain1\"\nregister = \"input\"\n\
                      address = 0\ndata_type = \"u16\"\nscaling = { kind = \"transmitter\", \
                      adc_full_scale_counts = 4095, adc_full_scale_ma = 24.0, \
                      range_min_degc = -50.0, range_max_degc = 150.0 }\n\n\
                      [nc_modules.nc_x]\naddress = \"192.168.0.20:502\"\nunit_id = 1\n";
        compgate_gateway::config::load_str(config, "cfg.toml").expect("the config alone");
        let m = model();
        assert!(!m.applied.is_empty() && !m.effects.is_empty());
        let text = m.to_toml("m.toml").expect("a valid model");
        let pasted = format!("{config}\n{text}");
        let cfg = compgate_gateway::config::load_str(&pasted, "cfg.toml")
            .unwrap_or_else(|e| panic!("{e}\n{pasted}"));
        let axis = &cfg.axes["X"];
        assert_eq!(
            (&axis.k0, &axis.tan_beta, axis.p0_mm),
            (&m.axis.k0, &m.axis.tan_beta, m.axis.p0_mm)
        );
        // As --model, the pasted config is the same model, effects and all.
        assert_eq!(ModelFile::from_toml(&pasted, "cfg.toml").expect("parse"), m);
        // Older files: the same keys at the top level are still read.
        let older = "applied = [\"thermal_lag: a\"]\n\
                     [axes.X]\nnc_module = \"nc_x\"\n\
                     [[effects]]\nname = \"reversal\"\ncarried_by = \"MD32450\"\n\
                     params = { b_um = 4.0 }\n";
        let back = ModelFile::from_toml(older, "old.toml").expect("older file");
        assert_eq!((back.applied.len(), back.effects.len()), (1, 1));
        // A broken `#=` line is named as such.
        let e = ModelFile::from_toml(&format!("{text}#= effects = [\n"), "m.toml").unwrap_err();
        assert!(e.to_string().starts_with("m.toml: the `#=` lines: "), "{e}");
    }

    #[test]
    fn predicts_with_lagged_channels_and_effects() {
        let meas = Measurements {
            t_s: vec![0.0, 100.0, 200.0],
            pos_mm: vec![100.0, 200.0, 100.0],
            err_um: vec![0.0; 3],
            dir: vec![0, 1, -1],
            travel_mm: vec![0.0, 100.0, 100.0],
            temps: vec![TempColumn {
                name: "a".into(),
                degc: vec![20.0, 21.0, 21.0],
            }],
            ignored_columns: vec![],
        };
        let p = model().predict_um(&meas).expect("predict");
        // Row 0: K0 offset 1 um, everything at its reference, dir unknown.
        assert!((p[0] - 1.0).abs() < 1e-9, "{}", p[0]);
        // Row 1: lag(a) = 20 + (1 - e^-1) = 20.632; K0 = 1 + 2 - 0.632 um; slope
        // 1e-5 * 1 degC * 100 mm = 1 um; reversal +2 um.
        let lag1 = 20.0 + (1.0 - (-1.0f64).exp());
        let want = 1.0 + 2.0 - (lag1 - 20.0) + 1.0 + 2.0;
        assert!((p[1] - want).abs() < 1e-9, "{} vs {want}", p[1]);
        // A term on a channel the data lacks is an error naming it.
        let mut bad = model();
        bad.axis.k0.terms[0].channel = "z".into();
        let e = bad.predict_um(&meas).expect_err("unknown channel");
        assert!(
            e.to_string().contains("`z`") && e.to_string().contains("k0.terms"),
            "{e}"
        );
    }
}
