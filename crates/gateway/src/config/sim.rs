//! `[sim]`: the simulated plant (demo, tests, commissioning dry runs) and its
//! validation. The gateway itself ignores it.

use std::collections::BTreeMap;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::problem::Problems;

/// `[sim]`: the simulated plant used by the demo, the tests and commissioning dry
/// runs. The gateway ignores it.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SimConfig {
    /// Seed of the noise generator, so a run can be repeated. Default 1.
    #[serde(default = "default_seed")]
    pub seed: u64,
    /// Temperature profiles by channel name (must exist in `[channels]`). A channel
    /// not listed reads [`SimChannelConfig::default`]: a constant 20 degC.
    #[serde(default)]
    pub channels: BTreeMap<String, SimChannelConfig>,
    /// Simulated NC axis modules by name (must exist in `[nc_modules]`). A module not
    /// listed behaves as [`SimNcModuleConfig::default`].
    #[serde(default)]
    pub nc_modules: BTreeMap<String, SimNcModuleConfig>,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            seed: default_seed(),
            channels: BTreeMap::new(),
            nc_modules: BTreeMap::new(),
        }
    }
}

impl SimConfig {
    /// The profile of channel `name`: its entry or the default.
    pub fn channel(&self, name: &str) -> SimChannelConfig {
        self.channels.get(name).cloned().unwrap_or_default()
    }
    /// The simulated NC module `name`: its entry or the default.
    pub fn nc_module(&self, name: &str) -> SimNcModuleConfig {
        self.nc_modules.get(name).cloned().unwrap_or_default()
    }
}

/// `[sim.channels.NAME]`: the temperature the simulated transmitter reports, with `t`
/// in seconds since the simulator started:
///
/// - `constant`: `mean_degc`
/// - `ramp`: `mean_degc + rate_degc_per_s * t`
/// - `sine`: `mean_degc + amplitude_degc * sin(2 pi t / period_s)`
///
/// plus uniform noise of +-`noise_degc`.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SimChannelConfig {
    /// `constant`, `ramp` or `sine`. Default `constant`.
    #[serde(default)]
    pub profile: SimProfile,
    /// Mean (constant, sine) or start value (ramp) in degC. Default 20.0;
    /// -273.15..=2000.
    #[serde(default = "default_ref_degc")]
    #[schemars(range(min = -273.15, max = 2000.0))]
    pub mean_degc: f64,
    /// Amplitude of the sine in degC (`sine` only). Default 0.0; 0..=1000.
    #[serde(default)]
    #[schemars(range(min = 0.0, max = 1000.0))]
    pub amplitude_degc: f64,
    /// Period of the sine in seconds (`sine` only). Default 600.0;
    /// 0.001..=31536000 (a year).
    #[serde(default = "default_sim_period_s")]
    #[schemars(range(min = 0.001, max = 31_536_000.0))]
    pub period_s: f64,
    /// Slope of the ramp in degC per second (`ramp` only; may be negative).
    /// Default 0.0; -1000..=1000.
    #[serde(default)]
    #[schemars(range(min = -1000.0, max = 1000.0))]
    pub rate_degc_per_s: f64,
    /// Half-width of the uniform noise in degC. Default 0.0; 0..=1000.
    #[serde(default)]
    #[schemars(range(min = 0.0, max = 1000.0))]
    pub noise_degc: f64,
}

impl Default for SimChannelConfig {
    fn default() -> Self {
        SimChannelConfig {
            profile: SimProfile::Constant,
            mean_degc: default_ref_degc(),
            amplitude_degc: 0.0,
            period_s: default_sim_period_s(),
            rate_degc_per_s: 0.0,
            noise_degc: 0.0,
        }
    }
}

/// Shape of a simulated temperature.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
#[serde(rename_all = "snake_case")]
pub enum SimProfile {
    /// `mean_degc`.
    #[default]
    Constant,
    /// `mean_degc + rate_degc_per_s * t`.
    Ramp,
    /// `mean_degc + amplitude_degc * sin(2 pi t / period_s)`.
    Sine,
}

/// `[sim.nc_modules.NAME]`: state of a simulated NC axis module. MD32750 may differ
/// from the axis' `md32750` on purpose (fault injection: the axis then holds).
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SimNcModuleConfig {
    /// Whether the axis is referenced (homed); an unreferenced axis takes the setting
    /// data but applies no compensation until it is referenced. Default true.
    #[serde(default = "yes")]
    pub referenced: bool,
    /// MD32750 `$MA_TEMP_COMP_TYPE` of the simulated NC. Default: the `md32750` of
    /// the axis on this module (3 if none); 0..=7.
    #[serde(default)]
    #[schemars(range(max = 7))]
    pub md32750: Option<u16>,
    /// Lower end of the simulated back-and-forth motion in mm. Default 0.0;
    /// -100000..=100000.
    #[serde(default)]
    #[schemars(range(min = -100_000.0, max = 100_000.0))]
    pub motion_min_mm: f64,
    /// Upper end of the simulated motion in mm. Default 0.0; -100000..=100000 and
    /// >= `motion_min_mm`.
    #[serde(default)]
    #[schemars(range(min = -100_000.0, max = 100_000.0))]
    pub motion_max_mm: f64,
    /// Speed of the simulated motion in mm per second (0 = the axis stands at
    /// `motion_min_mm`). Default 0.0; 0..=100000.
    #[serde(default)]
    #[schemars(range(min = 0.0, max = 100_000.0))]
    pub motion_speed_mm_per_s: f64,
}

impl Default for SimNcModuleConfig {
    fn default() -> Self {
        SimNcModuleConfig {
            referenced: true,
            md32750: None,
            motion_min_mm: 0.0,
            motion_max_mm: 0.0,
            motion_speed_mm_per_s: 0.0,
        }
    }
}

impl SimChannelConfig {
    /// Mean finite, amplitude and noise >= 0, period > 0; `key` is the entry's path.
    pub fn validate(&self, key: &str, out: &mut Problems<'_>) {
        let k = |f: &str| format!("{key}.{f}");
        out.finite(&k("mean_degc"), self.mean_degc);
        out.non_negative(&k("amplitude_degc"), self.amplitude_degc, "degC");
        out.positive(&k("period_s"), self.period_s, "seconds");
        out.finite(&k("rate_degc_per_s"), self.rate_degc_per_s);
        out.non_negative(&k("noise_degc"), self.noise_degc, "degC");
    }
}

impl SimNcModuleConfig {
    /// `md32750` 0..=7, `motion_min_mm <= motion_max_mm`, speed >= 0; `key` is the
    /// entry's path.
    pub fn validate(&self, key: &str, out: &mut Problems<'_>) {
        let k = |f: &str| format!("{key}.{f}");
        if let Some(md) = self.md32750.filter(|md| *md > 7) {
            out.push(k("md32750"), format!("must be 0..=7, got {md}"));
        }
        let lo = out.finite(&k("motion_min_mm"), self.motion_min_mm);
        let hi = out.finite(&k("motion_max_mm"), self.motion_max_mm);
        if lo && hi && self.motion_min_mm > self.motion_max_mm {
            out.push(
                k("motion_max_mm"),
                format!(
                    "must be >= motion_min_mm ({} mm), got {} mm",
                    self.motion_min_mm, self.motion_max_mm
                ),
            );
        }
        out.non_negative(
            &k("motion_speed_mm_per_s"),
            self.motion_speed_mm_per_s,
            "mm per second, 0 = standing",
        );
    }
}

fn yes() -> bool {
    true
}
fn default_ref_degc() -> f64 {
    20.0
}
fn default_seed() -> u64 {
    1
}
fn default_sim_period_s() -> f64 {
    600.0
}
