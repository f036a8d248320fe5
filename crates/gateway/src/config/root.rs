//! The top-level [`Config`]: it gathers the sections, each owned by its stage
//! (devices by `source`, channels by `channel`, NC modules by `nc`, axes by `axis`),
//! and its [`validate`] runs the stages' checks plus the references between
//! sections.

use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::keys::{entry, field, secs};
use super::problem::{ConfigProblem, Problems};
use super::service::{validate_service, MetricsConfig, MqttConfig, RecorderConfig};
use super::sim::SimConfig;
use crate::axis::{AxisConfig, ChannelNames};
use crate::channel::ChannelConfig;
use crate::nc::config::NcModuleConfig;
use crate::source::config::{validate_devices, DeviceConfig};

/// Longest name accepted.
const MAX_NAME_LEN: usize = 64;

/// A whole configuration file: `[gateway]`, `[devices.NAME]`, `[channels.NAME]`,
/// `[nc_modules.NAME]`, `[axes.NAME]` and the optional `[sim]`.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Gateway-wide settings. Optional table: every key has a default.
    #[serde(default)]
    pub gateway: GatewayConfig,
    /// Field devices (Modbus TCP servers, Modbus RTU slaves, CANopen nodes), by name. Required
    /// table; a name is 1..=64 characters of `A-Z a-z 0-9 _ -` without `__`, unique
    /// ignoring case (environment overrides address it case-insensitively).
    pub devices: BTreeMap<String, DeviceConfig>,
    /// Measured values, by name (the name axes refer to). Required table; names as
    /// for devices.
    pub channels: BTreeMap<String, ChannelConfig>,
    /// NC axis modules the compensation is written into, by name; names as for
    /// devices. Optional: without NC modules and axes the gateway only monitors (it
    /// polls, filters, records and serves metrics), the first commissioning step.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub nc_modules: BTreeMap<String, NcModuleConfig>,
    /// Compensated axes, by name (e.g. `X`); names as for devices. Optional (see
    /// `nc_modules`); every axis needs an NC module.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub axes: BTreeMap<String, AxisConfig>,
    /// Simulated plant (demo, tests, commissioning dry runs). Absent by default; the
    /// gateway itself ignores it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sim: Option<SimConfig>,
    /// Durable recording of readings and NC jobs into SQLite. Absent: nothing is
    /// recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recorder: Option<RecorderConfig>,
    /// Prometheus metrics endpoint. Absent: no endpoint.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub metrics: Option<MetricsConfig>,
    /// MQTT publishing of readings, writes and health. Absent: nothing is published.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mqtt: Option<MqttConfig>,
}

/// `[gateway]`: settings of the gateway as a whole.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct GatewayConfig {
    /// Seconds between status updates (status line, logs). Default 1.0;
    /// 0.001..=3600.
    #[serde(default = "default_status_interval_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub status_interval_s: f64,
    /// Shadow mode for every axis: compute, record and publish the parameters the
    /// gateway would write, and never write the NC (a first commissioning dry run).
    /// `compgate run --shadow` sets it too. Default false.
    #[serde(default)]
    pub shadow: bool,
}

impl Default for GatewayConfig {
    fn default() -> Self {
        GatewayConfig {
            status_interval_s: default_status_interval_s(),
            shadow: false,
        }
    }
}

impl GatewayConfig {
    /// `status_interval_s` as a [`Duration`].
    pub fn status_interval(&self) -> Duration {
        secs(self.status_interval_s)
    }
}

fn default_status_interval_s() -> f64 {
    1.0
}

/// Checks the meaning of a parsed configuration and returns every problem found
/// (empty = valid). `file` names the origin in the problems.
///
/// What is checked:
///
/// - **Names** of devices, channels, NC modules and axes: 1..=64 characters of
///   `A-Z a-z 0-9 _ -`, no `__` (the environment separator), unique ignoring case
///   (environment overrides match names ignoring case).
/// - **References**: `channels.*.device`, `axes.*.nc_module`, every channel of a
///   `k0`/`tan_beta` term, and the names under `[sim.channels]`/`[sim.nc_modules]`
///   must exist. One axis per NC module; a channel at most once per model.
/// - **Devices** (`source`): `address` is `host:port`; baud 1200..=115200, stop bits
///   1 or 2. Devices sharing a `serial_path` must agree on baud, parity and stop bits
///   (defaults applied) and have distinct unit ids. Which keys a transport takes is
///   the schema's business: a key of another transport is an unknown key.
/// - **CAN**: `interface` a network interface name, `node_id` 1..=127; node ids
///   distinct per interface, and one `poll_interval_s` per interface (its SYNC
///   period).
/// - **Unit ids** 0..=247; on RTU 1..=247 (0 is broadcast).
/// - **Times**: every timeout and interval > 0, `backoff_initial_s <= backoff_max_s`;
///   filter times >= 0 (0 = off).
/// - **Channels** (`channel`): registers on a Modbus device, `can` on a CAN device;
///   the value's last register (2 for 32-bit types) <= 65535 (the same register read
///   by two channels is fine); `adc_full_scale_counts` > 0 and representable in the
///   data type (`f32` counts are allowed, read as fractional counts),
///   `adc_full_scale_ma >= 20`, `range_min_degc < range_max_degc`; direct `gain`
///   finite and not 0; `median_samples` odd 1..=99, `max_rejected_samples >= 1`,
///   `valid_min_degc < valid_max_degc`.
/// - **Axes** (`axis`): `md32750` 0..=7 and its bits enabling every model in use,
///   limits and steps > 0, deadbands >= 0, `max_abs_tan_beta <= 0.1` (MD32760 is 0.01
///   by default; above 0.1 is not a thermal slope), ramp rates > 0 with
///   `ramp_to_zero`.
/// - **Sim**: `period_s > 0`, amplitude and noise >= 0, `md32750` 0..=7,
///   `motion_min_mm <= motion_max_mm`, speed >= 0.
/// - Every number finite (TOML allows `nan` and `inf`).
pub fn validate(cfg: &Config, file: &str) -> Vec<ConfigProblem> {
    validate_assuming(cfg, file, &Assumed::default())
}

/// Names that count as defined although the parsed configuration lacks them: entries
/// the loader had to leave out for structural problems (already reported), so that
/// references to them do not add a second, misleading problem.
#[derive(Debug, Default)]
pub(crate) struct Assumed {
    pub devices: Names,
    pub channels: Names,
    pub nc_modules: Names,
}

/// A set of names, or every name.
#[derive(Debug, Default)]
pub(crate) struct Names {
    /// Every name counts as defined (the whole section was missing or broken).
    pub any: bool,
    names: BTreeSet<String>,
}

impl Names {
    pub fn insert(&mut self, name: String) {
        self.names.insert(name);
    }
    pub fn contains(&self, name: &str) -> bool {
        self.any || self.names.contains(name)
    }
}

/// `` `a`, `b` `` or "(none defined)".
pub(crate) fn list<'a>(names: impl Iterator<Item = &'a String>) -> String {
    let v: Vec<String> = names.map(|n| format!("`{n}`")).collect();
    if v.is_empty() {
        "(none defined)".to_string()
    } else {
        v.join(", ")
    }
}

pub(crate) fn validate_assuming(cfg: &Config, file: &str, assumed: &Assumed) -> Vec<ConfigProblem> {
    let mut out = Problems::new(file);
    names(&mut out, "devices", cfg.devices.keys());
    names(&mut out, "channels", cfg.channels.keys());
    names(&mut out, "nc_modules", cfg.nc_modules.keys());
    names(&mut out, "axes", cfg.axes.keys());

    out.positive(
        "gateway.status_interval_s",
        cfg.gateway.status_interval_s,
        "seconds",
    );

    validate_devices(&cfg.devices, &mut out);

    for (name, ch) in &cfg.channels {
        let device = cfg.devices.get(&ch.device);
        if device.is_none() && !assumed.devices.contains(&ch.device) {
            out.push(
                field("channels", name, "device"),
                format!(
                    "unknown device `{}`; expected one of the names in [devices]: {}",
                    ch.device,
                    list(cfg.devices.keys())
                ),
            );
        }
        ch.validate(&entry("channels", name), device, &mut out);
    }

    for (name, nc) in &cfg.nc_modules {
        nc.validate(&entry("nc_modules", name), &mut out);
    }

    let channel_list = list(cfg.channels.keys());
    let known = |c: &str| cfg.channels.contains_key(c) || assumed.channels.contains(c);
    let channels = ChannelNames {
        known: &known,
        list: &channel_list,
    };
    let mut carried: BTreeMap<&str, &str> = BTreeMap::new();
    for (name, axis) in &cfg.axes {
        let module = axis.nc_module.as_str();
        if !(cfg.nc_modules.contains_key(module) || assumed.nc_modules.contains(module)) {
            out.push(
                field("axes", name, "nc_module"),
                format!(
                    "unknown NC module `{module}`; expected one of the names in [nc_modules]: {}",
                    list(cfg.nc_modules.keys())
                ),
            );
        } else if let Some(other) = carried.insert(module, name) {
            out.push(
                field("axes", name, "nc_module"),
                format!("NC module `{module}` already carries axis `{other}`; one axis per module"),
            );
        }
        axis.validate(&entry("axes", name), &channels, &mut out);
    }

    if let Some(sim) = &cfg.sim {
        for (name, sc) in &sim.channels {
            let key = entry("sim.channels", name);
            if !known(name) {
                out.push(
                    key.clone(),
                    format!("no channel `{name}` in [channels] to simulate"),
                );
            }
            sc.validate(&key, &mut out);
        }
        for (name, sn) in &sim.nc_modules {
            let key = entry("sim.nc_modules", name);
            if !(cfg.nc_modules.contains_key(name) || assumed.nc_modules.contains(name)) {
                out.push(
                    key.clone(),
                    format!("no NC module `{name}` in [nc_modules] to simulate"),
                );
            }
            sn.validate(&key, &mut out);
        }
    }
    let mut out = out.into_vec();
    out.extend(validate_service(
        cfg.recorder.as_ref(),
        cfg.metrics.as_ref(),
        cfg.mqtt.as_ref(),
        file,
    ));
    out
}

fn names<'n>(out: &mut Problems<'_>, section: &str, names: impl Iterator<Item = &'n String>) {
    let mut folded: BTreeMap<String, &str> = BTreeMap::new();
    for name in names {
        let key = entry(section, name);
        if name.is_empty() {
            out.push(key, "name must not be empty");
            continue;
        }
        if name.chars().count() > MAX_NAME_LEN {
            out.push(
                key.clone(),
                format!("name is longer than {MAX_NAME_LEN} characters"),
            );
        }
        if !name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        {
            out.push(
                key.clone(),
                "name may contain only A-Z, a-z, 0-9, `_` and `-`",
            );
        } else if name.contains("__") {
            out.push(
                key.clone(),
                "name must not contain `__`, the level separator of environment overrides",
            );
        }
        if let Some(other) = folded.insert(name.to_lowercase(), name) {
            out.push(
                key,
                format!(
                    "differs from `{other}` only in case; environment overrides match \
                     names ignoring case and could not tell them apart"
                ),
            );
        }
    }
}

#[cfg(test)]
mod tests;
