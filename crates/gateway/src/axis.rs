//! `[axes.NAME]`: a compensated axis' model, limits and bad-input policy; the axis'
//! validation and the runtime parts it builds ([`ThermalModel`], [`Limits`],
//! [`BadInputPolicy`]).

use std::collections::BTreeMap;
use std::time::Duration;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::config::keys::secs;
use crate::config::problem::Problems;
use compgate_core::comp::{
    Affine, BadInputPolicy, Dynamics, InputLag, Limits, MotionHeat, Term, ThermalModel,
};

/// Above this |tan(beta)| limit the value cannot be a thermal slope.
const TAN_BETA_LIMIT_CEILING: f64 = 0.1;

/// `[axes.NAME]`: one compensated axis,
/// `dKx = K0(T) + tan(beta)(T) * (Px - P0)` -> SD43900, SD43910, SD43920.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct AxisConfig {
    /// Name of the target in `[targets]` (or `[nc_modules]`) that carries this axis.
    /// Required; at most 64 characters; one axis per Modbus NC module.
    #[schemars(length(max = 64))]
    pub nc_module: String,
    /// The axis's number on its target's control: the `{axis}` of OPC UA node-id
    /// templates, the axis of an S7 job, the per-axis step of ADS index groups and
    /// offsets. Required on a target of kind `opcua`, `s7` or `ads`; unused on a Modbus
    /// NC module. 1..=255; distinct per target.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 1, max = 255))]
    pub axis_number: Option<u16>,
    /// The allow-list: which setting data may be written to the target, any of
    /// `"sd43900"`, `"sd43910"`, `"sd43920"`. Default all three. A job is built from
    /// these only, and one naming anything else is refused before it is sent.
    #[serde(default = "default_nc_write")]
    pub nc_write: Vec<NcVar>,
    /// MD32750 `$MA_TEMP_COMP_TYPE` the NC must have (bit 0: K0, bit 1: slope).
    /// Checked at every read of the NC: while it differs the axis holds (no job is
    /// sent) and a warning is logged once. Required; 0..=7. A K0 model needs bit 0 and a
    /// tan(beta) model needs bit 1, otherwise the NC would ignore the value written.
    #[schemars(range(max = 7))]
    pub md32750: u16,
    /// SD43920 `$SA_TEMP_COMP_REF_POSITION`: reference position P0 in mm. Default 0.0;
    /// -100000..=100000.
    #[serde(default)]
    #[schemars(range(min = -100_000.0, max = 100_000.0))]
    pub p0_mm: f64,
    /// Seconds between compensation updates. Default 10.0; 0.001..=3600.
    #[serde(default = "default_update_interval_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub update_interval_s: f64,
    /// No write while K0 changed less than this (mm). Default 0.001; 0..=10.
    #[serde(default = "default_deadband_k0_mm")]
    #[schemars(range(min = 0.0, max = 10.0))]
    pub deadband_k0_mm: f64,
    /// No write while tan(beta) changed less than this (dimensionless, mm/mm).
    /// Default 0.000001; 0..=0.1.
    #[serde(default = "default_deadband_tan_beta")]
    #[schemars(range(min = 0.0, max = 0.1))]
    pub deadband_tan_beta: f64,
    /// Hard limit of |K0| in mm; a computed value beyond it is clamped to it, logged
    /// once and exported as `compgate_axis_at_limit`. Default 0.5; > 0 and <= 10 (SD43900 is limited to
    /// 10 mm by the NC).
    #[serde(default = "default_max_abs_k0_mm")]
    #[schemars(range(max = 10.0), extend("exclusiveMinimum" = 0.0))]
    pub max_abs_k0_mm: f64,
    /// Hard limit of |tan(beta)|, kept like `max_abs_k0_mm`; must stay below the
    /// NC's MD32760 `$MA_COMP_ADD_VELO_FACTOR`. Default 0.01 (the MD32760 default); > 0 and
    /// <= 0.1.
    #[serde(default = "default_max_abs_tan_beta")]
    #[schemars(range(max = 0.1), extend("exclusiveMinimum" = 0.0))]
    pub max_abs_tan_beta: f64,
    /// Largest change of K0 in one update (mm). Default 0.02; > 0 and <= 10.
    #[serde(default = "default_max_step_k0_mm")]
    #[schemars(range(max = 10.0), extend("exclusiveMinimum" = 0.0))]
    pub max_step_k0_mm: f64,
    /// Largest change of tan(beta) in one update. Default 0.00002; > 0 and
    /// <= 0.1.
    #[serde(default = "default_max_step_tan_beta")]
    #[schemars(range(max = 0.1), extend("exclusiveMinimum" = 0.0))]
    pub max_step_tan_beta: f64,
    /// What to do while an input channel is bad: `hold` the last value or
    /// `ramp_to_zero`. Default `hold`.
    #[serde(default)]
    pub on_bad_input: OnBadInput,
    /// Ramp rate of K0 towards zero in mm per second (`ramp_to_zero` only).
    /// Default 0.0005; 0..=10, > 0 with `ramp_to_zero`.
    #[serde(default = "default_ramp_k0_mm_per_s")]
    #[schemars(range(min = 0.0, max = 10.0))]
    pub ramp_k0_mm_per_s: f64,
    /// Ramp rate of tan(beta) towards zero per second (`ramp_to_zero` only).
    /// Default 0.0000005; 0..=0.1, > 0 with
    /// `ramp_to_zero`.
    #[serde(default = "default_ramp_tan_beta_per_s")]
    #[schemars(range(min = 0.0, max = 0.1))]
    pub ramp_tan_beta_per_s: f64,
    /// K0(T) model (SD43900). Optional table; default: offset 0, no terms (K0 = 0).
    #[serde(default)]
    pub k0: K0Model,
    /// tan(beta)(T) model (SD43910). Optional table; default: offset 0, no terms.
    #[serde(default)]
    pub tan_beta: TanBetaModel,
    /// Heat of axis motion, from the NC's actual position (diagnose's
    /// `motion_heating`): needs a target that reports it (`kind = "modbus"` or
    /// `"s7"`). Optional table; default: none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub motion_heat: Option<MotionHeatModel>,
    /// The temperatures the model was fitted over, degC, per input channel: `{ T_bed =
    /// [16.9, 27.1] }` (`calibrate` and `diagnose` write them). A usable reading more
    /// than 2 K outside its range is flagged until it is back within 1.5 K: the status,
    /// the metric `compgate_axis_outside_fit` and one WARN say the model extrapolates
    /// there. The axis still compensates. Optional; channels of the model's terms;
    /// min <= max, -100..=500.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub fitted_degc: BTreeMap<String, [f64; 2]>,
    /// The doubts about the model's fit that it was written over (`calibrate
    /// --accept-weak-fit` and `scenario` write them): while any is listed, `validate`
    /// and every start warn, naming them, so a forced model is not forgotten. Remove
    /// the key once the machine is measured again or the doubt is settled. Optional;
    /// default none.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub accepted_doubts: Vec<String>,
    /// Shadow mode: compute, record and publish the parameters this axis would
    /// write, and never write its NC module (jobs are recorded as shadow). The NC
    /// is still read: what it holds is the start of the step limits. Default false.
    #[serde(default)]
    pub shadow: bool,
}

/// `[axes.NAME.motion_heat]`: travel from the NC's actual position (read every
/// `gateway.status_interval_s`, at most once a second) heats a store no sensor sees,
/// `h <- h exp(-dt/tau_s) + |dpos| / tau_s` (h: travel rate through the lag, mm/s);
/// `K0 += k0_mm_per_mm_per_s (h - ref_mm_per_s)` and `tan(beta) +=
/// tan_beta_per_mm_per_s (h - ref_mm_per_s)`.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MotionHeatModel {
    /// Time constant of the store, s. Required; 1..=86400.
    #[schemars(range(min = 1.0, max = 86_400.0))]
    pub tau_s: f64,
    /// Travel rate at which the term is zero, mm/s. Default 0.0; 0..=10000.
    #[serde(default)]
    #[schemars(range(min = 0.0, max = 10_000.0))]
    pub ref_mm_per_s: f64,
    /// K0 change in mm per mm/s of travel rate. Default 0.0; -0.01..=0.01.
    #[serde(default)]
    #[schemars(range(min = -0.01, max = 0.01))]
    pub k0_mm_per_mm_per_s: f64,
    /// tan(beta) change per mm/s of travel rate. Default 0.0; -0.0001..=0.0001.
    #[serde(default)]
    #[schemars(range(min = -0.0001, max = 0.0001))]
    pub tan_beta_per_mm_per_s: f64,
}

/// Reaction to a bad input channel.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
#[serde(rename_all = "snake_case")]
pub enum OnBadInput {
    /// Keep the last good parameters.
    #[default]
    Hold,
    /// Ramp the parameters towards zero at `ramp_*_per_s`.
    RampToZero,
}

/// `[axes.NAME.k0]`: `K0(T) = offset_mm + sum(coeff_mm_per_degc * (T[channel] -
/// ref_degc))`, in mm.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct K0Model {
    /// Constant part of K0 in mm. Default 0.0; -10..=10 (SD43900 is limited
    /// to 10 mm by the NC).
    #[serde(default)]
    #[schemars(range(min = -10.0, max = 10.0))]
    pub offset_mm: f64,
    /// Linear temperature terms; each channel at most once per `lag_tau_s`. Default
    /// none.
    #[serde(default)]
    pub terms: Vec<K0Term>,
}

/// One term of the K0 model.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct K0Term {
    /// Name of the channel in `[channels]`. Required; at most 64 characters.
    #[schemars(length(max = 64))]
    pub channel: String,
    /// Temperature in degC at which the term is zero. Default 20.0 (ISO 1 reference
    /// temperature); -100..=500.
    #[serde(default = "default_ref_degc")]
    #[schemars(range(min = -100.0, max = 500.0))]
    pub ref_degc: f64,
    /// K0 change in mm per degC. Required; -1..=1.
    #[schemars(range(min = -1.0, max = 1.0))]
    pub coeff_mm_per_degc: f64,
    /// The term reads the channel through a first-order lag of this time constant,
    /// s (diagnose's `thermal_lag`: the structure follows its sensor late). Default
    /// 0.0 (no lag); 0..=86400.
    #[serde(default, skip_serializing_if = "is_zero")]
    #[schemars(range(min = 0.0, max = 86_400.0))]
    pub lag_tau_s: f64,
}

/// `[axes.NAME.tan_beta]`: `tan(beta)(T) = offset + sum(coeff_per_degc * (T[channel] -
/// ref_degc))`, dimensionless (mm/mm).
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct TanBetaModel {
    /// Constant part of tan(beta). Default 0.0; -0.1..=0.1.
    #[serde(default)]
    #[schemars(range(min = -0.1, max = 0.1))]
    pub offset: f64,
    /// Linear temperature terms; each channel at most once per `lag_tau_s`. Default
    /// none.
    #[serde(default)]
    pub terms: Vec<TanBetaTerm>,
}

/// One term of the tan(beta) model.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TanBetaTerm {
    /// Name of the channel in `[channels]`. Required; at most 64 characters.
    #[schemars(length(max = 64))]
    pub channel: String,
    /// Temperature in degC at which the term is zero. Default 20.0; -100..=500.
    #[serde(default = "default_ref_degc")]
    #[schemars(range(min = -100.0, max = 500.0))]
    pub ref_degc: f64,
    /// tan(beta) change per degC, e.g. 0.0000115 for a steel ball screw
    /// (11.5 um/m/K). Required; -0.01..=0.01.
    #[schemars(range(min = -0.01, max = 0.01))]
    pub coeff_per_degc: f64,
    /// The term reads the channel through a first-order lag of this time constant,
    /// s. Default 0.0 (no lag); 0..=86400.
    #[serde(default, skip_serializing_if = "is_zero")]
    #[schemars(range(min = 0.0, max = 86_400.0))]
    pub lag_tau_s: f64,
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

/// What an axis' validation needs to know about the channels.
pub struct ChannelNames<'a> {
    /// Whether a channel of this name is defined.
    pub known: &'a dyn Fn(&str) -> bool,
    /// The defined names, for the message (e.g. "`T_bed`, `T_screw`").
    pub list: &'a str,
}

/// A setting datum an axis may write (`axes.NAME.nc_write`).
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, Copy, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum NcVar {
    /// SD43900 `$SA_TEMP_COMP_ABS_VALUE` (K0, mm).
    Sd43900,
    /// SD43910 `$SA_TEMP_COMP_SLOPE` (tan(beta), mm/mm).
    Sd43910,
    /// SD43920 `$SA_TEMP_COMP_REF_POSITION` (P0, mm).
    Sd43920,
}

impl NcVar {
    /// The variable id (`compgate_ncproto::var`).
    pub fn id(self) -> u16 {
        match self {
            Self::Sd43900 => compgate_ncproto::var::SD43900,
            Self::Sd43910 => compgate_ncproto::var::SD43910,
            Self::Sd43920 => compgate_ncproto::var::SD43920,
        }
    }
}

fn default_nc_write() -> Vec<NcVar> {
    vec![NcVar::Sd43900, NcVar::Sd43910, NcVar::Sd43920]
}

impl AxisConfig {
    /// The variable ids of `nc_write`, each once.
    pub fn nc_write_ids(&self) -> Vec<u16> {
        let mut v: Vec<u16> = self.nc_write.iter().map(|n| n.id()).collect();
        v.sort_unstable();
        v.dedup();
        v
    }

    /// `update_interval_s` as a [`Duration`].
    pub fn update_interval(&self) -> Duration {
        secs(self.update_interval_s)
    }

    /// Checks the axis; `key` is its path (`axes.NAME`).
    pub fn validate(&self, key: &str, channels: &ChannelNames<'_>, out: &mut Problems<'_>) {
        let k = |f: &str| format!("{key}.{f}");
        if self.md32750 > 7 {
            out.push(
                k("md32750"),
                format!(
                    "must be 0..=7 (bit 0: K0, bit 1: slope, bit 2: tool direction), got {}",
                    self.md32750
                ),
            );
        } else {
            let k0_used = self.k0.offset_mm != 0.0 || !self.k0.terms.is_empty();
            let tb_used = self.tan_beta.offset != 0.0 || !self.tan_beta.terms.is_empty();
            if k0_used && self.md32750 & 1 == 0 {
                out.push(
                    k("k0"),
                    format!(
                        "a K0 model is configured but md32750 = {} has bit 0 clear: the NC \
                         would ignore SD43900; set bit 0 or remove the model",
                        self.md32750
                    ),
                );
            }
            if tb_used && self.md32750 & 2 == 0 {
                out.push(
                    k("tan_beta"),
                    format!(
                        "a tan(beta) model is configured but md32750 = {} has bit 1 clear: \
                         the NC would ignore SD43910; set bit 1 or remove the model",
                        self.md32750
                    ),
                );
            }
        }
        out.finite(&k("p0_mm"), self.p0_mm);
        out.positive(&k("update_interval_s"), self.update_interval_s, "seconds");
        out.non_negative(&k("deadband_k0_mm"), self.deadband_k0_mm, "mm");
        out.non_negative(&k("deadband_tan_beta"), self.deadband_tan_beta, "mm/mm");
        out.positive(&k("max_abs_k0_mm"), self.max_abs_k0_mm, "mm");
        if out.positive(&k("max_abs_tan_beta"), self.max_abs_tan_beta, "mm/mm")
            && self.max_abs_tan_beta > TAN_BETA_LIMIT_CEILING
        {
            out.push(
                k("max_abs_tan_beta"),
                format!(
                    "must be <= {TAN_BETA_LIMIT_CEILING} and below the NC's MD32760 \
                     (default 0.01), got {}",
                    self.max_abs_tan_beta
                ),
            );
        }
        out.positive(&k("max_step_k0_mm"), self.max_step_k0_mm, "mm per update");
        out.positive(
            &k("max_step_tan_beta"),
            self.max_step_tan_beta,
            "per update",
        );
        deadband_reachable(
            out,
            key,
            ("deadband_k0_mm", self.deadband_k0_mm),
            ("max_step_k0_mm", self.max_step_k0_mm),
            ("max_abs_k0_mm", self.max_abs_k0_mm),
        );
        deadband_reachable(
            out,
            key,
            ("deadband_tan_beta", self.deadband_tan_beta),
            ("max_step_tan_beta", self.max_step_tan_beta),
            ("max_abs_tan_beta", self.max_abs_tan_beta),
        );
        let mut listed: Vec<NcVar> = Vec::new();
        for v in &self.nc_write {
            if listed.contains(v) {
                let name = crate::nc::var_name(v.id()).to_lowercase();
                out.push(
                    k("nc_write"),
                    format!("\"{name}\" is listed more than once; list each setting datum once"),
                );
            } else {
                listed.push(*v);
            }
        }
        match self.on_bad_input {
            OnBadInput::RampToZero => {
                out.positive(
                    &k("ramp_k0_mm_per_s"),
                    self.ramp_k0_mm_per_s,
                    "mm per second",
                );
                out.positive(
                    &k("ramp_tan_beta_per_s"),
                    self.ramp_tan_beta_per_s,
                    "per second",
                );
            }
            OnBadInput::Hold => {
                out.non_negative(
                    &k("ramp_k0_mm_per_s"),
                    self.ramp_k0_mm_per_s,
                    "mm per second",
                );
                out.non_negative(
                    &k("ramp_tan_beta_per_s"),
                    self.ramp_tan_beta_per_s,
                    "per second",
                );
            }
        }
        out.finite(&k("k0.offset_mm"), self.k0.offset_mm);
        out.finite(&k("tan_beta.offset"), self.tan_beta.offset);
        let k0_terms = self.k0.terms.iter().map(|t| {
            (
                t.channel.as_str(),
                t.ref_degc,
                ("coeff_mm_per_degc", t.coeff_mm_per_degc),
                t.lag_tau_s,
            )
        });
        terms(&k("k0.terms"), k0_terms, channels, out);
        let tb_terms = self.tan_beta.terms.iter().map(|t| {
            (
                t.channel.as_str(),
                t.ref_degc,
                ("coeff_per_degc", t.coeff_per_degc),
                t.lag_tau_s,
            )
        });
        terms(&k("tan_beta.terms"), tb_terms, channels, out);
        for (channel, &[min, max]) in &self.fitted_degc {
            let key = k(&format!("fitted_degc.{channel}"));
            let in_model = self.k0.terms.iter().any(|t| &t.channel == channel)
                || self.tan_beta.terms.iter().any(|t| &t.channel == channel);
            if !in_model {
                out.push(
                    key,
                    format!("`{channel}` is not a channel of the axis' k0 or tan_beta terms"),
                );
            } else if !(min.is_finite() && max.is_finite())
                || min > max
                || min < -100.0
                || max > 500.0
            {
                out.push(
                    key,
                    format!("must be [min, max] with -100 <= min <= max <= 500 degC, got [{min}, {max}]"),
                );
            }
        }
        if let Some(m) = &self.motion_heat {
            if out.positive(&k("motion_heat.tau_s"), m.tau_s, "seconds") && m.tau_s < 1.0 {
                out.push(
                    k("motion_heat.tau_s"),
                    format!("must be 1..=86400 s, got {}", m.tau_s),
                );
            }
            out.non_negative(&k("motion_heat.ref_mm_per_s"), m.ref_mm_per_s, "mm/s");
            out.finite(&k("motion_heat.k0_mm_per_mm_per_s"), m.k0_mm_per_mm_per_s);
            out.finite(
                &k("motion_heat.tan_beta_per_mm_per_s"),
                m.tan_beta_per_mm_per_s,
            );
            if m.k0_mm_per_mm_per_s != 0.0 && self.md32750 & 1 == 0 {
                out.push(
                    k("motion_heat.k0_mm_per_mm_per_s"),
                    "md32750 has bit 0 clear: the NC would ignore SD43900".to_string(),
                );
            }
        }
    }

    /// The axis' thermal model and the channel name behind each model input.
    pub fn model(&self) -> (ThermalModel, Vec<String>) {
        let (model, names, _) = self.model_parts();
        (model, names)
    }

    /// The thermal model, the channel behind each real model input, and the lags
    /// (model inputs after the real ones) and motion heat term.
    pub fn model_parts(&self) -> (ThermalModel, Vec<String>, Dynamics) {
        let mut names: Vec<String> = Vec::new();
        let all = (self.k0.terms.iter().map(|t| (&t.channel, t.lag_tau_s))).chain(
            self.tan_beta
                .terms
                .iter()
                .map(|t| (&t.channel, t.lag_tau_s)),
        );
        for (ch, _) in all.clone() {
            if !names.contains(ch) {
                names.push(ch.clone());
            }
        }
        // One slot per (channel, lag), after the real inputs.
        let mut lags: Vec<InputLag> = Vec::new();
        for (ch, tau_s) in all.filter(|(_, tau)| *tau > 0.0) {
            let source = names.iter().position(|n| n == ch).unwrap_or(0);
            if !lags.iter().any(|l| l.source == source && l.tau_s == tau_s) {
                let slot = names.len() + lags.len();
                lags.push(InputLag {
                    source,
                    slot,
                    tau_s,
                });
            }
        }
        let input = |ch: &str, tau_s: f64| {
            let source = names.iter().position(|n| n == ch).unwrap_or(0);
            match lags
                .iter()
                .find(|l| tau_s > 0.0 && l.source == source && l.tau_s == tau_s)
            {
                Some(l) => l.slot,
                None => source,
            }
        };
        let term = |channel: &str, ref_degc: f64, coeff: f64, tau_s: f64| Term {
            input: input(channel, tau_s),
            ref_degc,
            coeff,
        };
        let k0_terms = (self.k0.terms.iter())
            .map(|t| term(&t.channel, t.ref_degc, t.coeff_mm_per_degc, t.lag_tau_s))
            .collect();
        let tan_terms = (self.tan_beta.terms.iter())
            .map(|t| term(&t.channel, t.ref_degc, t.coeff_per_degc, t.lag_tau_s))
            .collect();
        let model = ThermalModel {
            k0_mm: Affine {
                offset: self.k0.offset_mm,
                terms: k0_terms,
            },
            tan_beta: Affine {
                offset: self.tan_beta.offset,
                terms: tan_terms,
            },
            p0_mm: self.p0_mm,
        };
        let motion = self.motion_heat.as_ref().map(|m| MotionHeat {
            tau_s: m.tau_s,
            ref_mm_per_s: m.ref_mm_per_s,
            k0_mm_per_mm_per_s: m.k0_mm_per_mm_per_s,
            tan_beta_per_mm_per_s: m.tan_beta_per_mm_per_s,
        });
        (model, names, Dynamics::new(lags, motion))
    }

    /// The axis' limits and deadbands.
    pub fn limits(&self) -> Limits {
        Limits {
            max_abs_k0_mm: self.max_abs_k0_mm,
            max_abs_tan_beta: self.max_abs_tan_beta,
            max_step_k0_mm: self.max_step_k0_mm,
            max_step_tan_beta: self.max_step_tan_beta,
            deadband_k0_mm: self.deadband_k0_mm,
            deadband_tan_beta: self.deadband_tan_beta,
        }
    }

    /// The axis' reaction to a bad input.
    pub fn policy(&self) -> BadInputPolicy {
        match self.on_bad_input {
            OnBadInput::Hold => BadInputPolicy::Hold,
            OnBadInput::RampToZero => BadInputPolicy::RampToZero {
                k0_mm_per_s: self.ramp_k0_mm_per_s,
                tan_beta_per_s: self.ramp_tan_beta_per_s,
            },
        }
    }
}

/// A change can pass the deadband: after the first write the change of one update is
/// at most the step limit, and between two values within the limit at most twice it.
/// A deadband beyond either holds the value for ever, each update "within the
/// deadband".
fn deadband_reachable(
    out: &mut Problems<'_>,
    key: &str,
    (deadband_key, deadband): (&str, f64),
    (step_key, step): (&str, f64),
    (abs_key, abs): (&str, f64),
) {
    if ![deadband, step, abs]
        .iter()
        .all(|v| v.is_finite() && *v > 0.0)
    {
        return;
    }
    let bound = if deadband > step {
        format!("above {step_key} = {step}, the largest change of one update")
    } else if deadband >= 2.0 * abs {
        format!(
            "not below 2 x {abs_key} = {}, the largest change within the limit",
            2.0 * abs
        )
    } else {
        return;
    };
    out.push(
        format!("{key}.{deadband_key}"),
        format!(
            "{deadband} is {bound}: no change of this value could pass the deadband, so \
             it would never be written on its own; make {deadband_key} smaller"
        ),
    );
}

/// Every term's channel exists and appears once per lag; numbers finite.
fn terms<'t>(
    key: &str,
    terms: impl Iterator<Item = (&'t str, f64, (&'static str, f64), f64)>,
    channels: &ChannelNames<'_>,
    out: &mut Problems<'_>,
) {
    let mut seen: BTreeMap<(&str, u64), usize> = BTreeMap::new();
    for (i, (channel, ref_degc, (coeff_name, coeff), lag_tau_s)) in terms.enumerate() {
        let tk = |f: &str| format!("{key}[{i}].{f}");
        if !(channels.known)(channel) {
            out.push(
                tk("channel"),
                format!(
                    "unknown channel `{channel}`; expected one of the names in \
                     [channels]: {}",
                    channels.list
                ),
            );
        } else if let Some(first) = seen.insert((channel, lag_tau_s.to_bits()), i) {
            out.push(
                tk("channel"),
                format!(
                    "channel `{channel}` already has term [{first}] with the same \
                     lag_tau_s; combine the coefficients into one term"
                ),
            );
        }
        if !(lag_tau_s.is_finite() && (0.0..=86_400.0).contains(&lag_tau_s)) {
            out.push(
                tk("lag_tau_s"),
                format!("must be 0..=86400 s (0: no lag), got {lag_tau_s}"),
            );
        }
        out.finite(&tk("ref_degc"), ref_degc);
        out.finite(&tk(coeff_name), coeff);
    }
}

fn default_update_interval_s() -> f64 {
    10.0
}
fn default_deadband_k0_mm() -> f64 {
    0.001
}
fn default_deadband_tan_beta() -> f64 {
    0.000_001
}
fn default_max_abs_k0_mm() -> f64 {
    0.5
}
fn default_max_abs_tan_beta() -> f64 {
    0.01
}
fn default_max_step_k0_mm() -> f64 {
    0.02
}
fn default_max_step_tan_beta() -> f64 {
    0.000_02
}
fn default_ramp_k0_mm_per_s() -> f64 {
    0.0005
}
fn default_ramp_tan_beta_per_s() -> f64 {
    0.000_000_5
}
fn default_ref_degc() -> f64 {
    20.0
}

#[cfg(test)]
mod tests {
    use super::*;

    fn axis(text: &str) -> AxisConfig {
        let base = "nc_module = \"nc\"\nmd32750 = 3\n";
        toml::from_str(&format!("{base}{text}")).expect("axis toml")
    }

    fn problems(a: &AxisConfig) -> Vec<String> {
        let known = |c: &str| ["column", "screw", "spindle"].contains(&c);
        let names = ChannelNames {
            known: &known,
            list: "`column`, `screw`, `spindle`",
        };
        let mut out = Problems::new("t.toml");
        a.validate("axes.X", &names, &mut out);
        out.into_vec().into_iter().map(|p| p.key).collect()
    }

    const LAGGED: &str = "[k0]\nterms = [\
        { channel = \"column\", coeff_mm_per_degc = 0.009 },\
        { channel = \"column\", lag_tau_s = 1200.0, coeff_mm_per_degc = -0.004 },\
        { channel = \"spindle\", coeff_mm_per_degc = 0.0015 }]\n\
        [tan_beta]\nterms = [{ channel = \"screw\", lag_tau_s = 1200.0, coeff_per_degc = 0.0000115 }]\n\
        [motion_heat]\ntau_s = 2400.0\nref_mm_per_s = 30.0\nk0_mm_per_mm_per_s = 0.00006\n";

    #[test]
    fn fitted_ranges_name_channels_of_the_model_in_order() {
        let ok = axis(&format!(
            "fitted_degc = {{ column = [16.9, 23.5], screw = [17.0, 27.1] }}\n{LAGGED}"
        ));
        assert!(problems(&ok).is_empty(), "{:?}", problems(&ok));
        let bad = axis(
            "fitted_degc = { column = [23.5, 16.9], spindle = [20.0, 30.0], T_x = [0.0, 1.0] }\n\
             [tan_beta]\nterms = [{ channel = \"screw\", coeff_per_degc = 0.0000115 }]\n\
             [k0]\nterms = [{ channel = \"column\", coeff_mm_per_degc = 0.009 }]\n",
        );
        assert_eq!(
            problems(&bad),
            [
                "axes.X.fitted_degc.T_x",
                "axes.X.fitted_degc.column",
                "axes.X.fitted_degc.spindle"
            ]
        );
    }

    #[test]
    fn lagged_terms_get_slots_after_the_channels() {
        let a = axis(LAGGED);
        assert!(problems(&a).is_empty(), "{:?}", problems(&a));
        let (model, names, dynamics) = a.model_parts();
        assert_eq!(names, ["column", "spindle", "screw"]);
        // column lagged 1200 s and screw lagged 1200 s: two slots after the 3 inputs.
        let lags: Vec<(usize, usize)> =
            dynamics.lags().iter().map(|l| (l.source, l.slot)).collect();
        assert_eq!(lags, [(0, 3), (2, 4)]);
        let k0_inputs: Vec<usize> = model.k0_mm.terms.iter().map(|t| t.input).collect();
        assert_eq!(k0_inputs, [0, 3, 1]);
        assert_eq!(model.tan_beta.terms[0].input, 4);
        let m = dynamics.motion().expect("motion heat");
        assert_eq!((m.tau_s, m.ref_mm_per_s), (2400.0, 30.0));
        // Round trip: lag_tau_s = 0 is left out, motion_heat kept.
        let text = toml::to_string(&a).expect("serialize");
        assert_eq!(text.matches("lag_tau_s").count(), 2, "{text}");
        assert_eq!(toml::from_str::<AxisConfig>(&text).expect("parse"), a);
    }

    #[test]
    fn bad_lags_and_motion_heat_name_their_key() {
        let a = axis(
            "[k0]\nterms = [\
             { channel = \"column\", lag_tau_s = 600.0, coeff_mm_per_degc = 0.009 },\
             { channel = \"column\", lag_tau_s = 600.0, coeff_mm_per_degc = 0.001 },\
             { channel = \"screw\", lag_tau_s = -1.0, coeff_mm_per_degc = 0.001 }]\n\
             [motion_heat]\ntau_s = 0.5\nref_mm_per_s = -1.0\n",
        );
        assert_eq!(
            problems(&a),
            [
                "axes.X.k0.terms[1].channel",
                "axes.X.k0.terms[2].lag_tau_s",
                "axes.X.motion_heat.tau_s",
                "axes.X.motion_heat.ref_mm_per_s",
            ]
        );
    }
}
