//! The top-level [`Config`]: it gathers the sections, each owned by its stage
//! (devices by `source`, channels by `channel`, NC modules by `nc`, axes by `axis`),
//! and its [`validate`] runs the stages' checks plus the references between
//! sections.

use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::keys::{entry, field, secs};
use super::problem::{ConfigProblem, PortZero, Problems};
use super::service::{validate_service, MetricsConfig, MqttConfig, RecorderConfig};
use super::sim::SimConfig;
use crate::axis::{AxisConfig, ChannelNames, NcVar};
use crate::channel::ChannelConfig;
use crate::nc::config::{NcModuleConfig, Place, TargetConfig};
use crate::nc::var_name;
use crate::source::config::{validate_devices, DeviceConfig};

/// A whole configuration file: `[gateway]`, `[devices.NAME]`, `[channels.NAME]`,
/// `[targets.NAME]` (or the older `[nc_modules.NAME]`), `[axes.NAME]` and the optional
/// `[sim]`.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Gateway-wide settings. Optional table: every key has a default.
    #[serde(default)]
    pub gateway: GatewayConfig,
    /// Field devices (Modbus TCP servers, Modbus RTU slaves, CANopen nodes), by name. Required
    /// table; a name is 1..=64 characters of `A-Z a-z 0-9 _ -` without `__` and not
    /// ending in `_`, unique ignoring case (environment overrides address it
    /// case-insensitively, with `__` between levels).
    pub devices: BTreeMap<String, DeviceConfig>,
    /// Measured values, by name (the name axes refer to). Required table; names as
    /// for devices.
    pub channels: BTreeMap<String, ChannelConfig>,
    /// NC targets the compensation is written into, by name, each with its `kind`
    /// (`modbus`, `opcua`, `s7`, `ads`); names as for devices, distinct from the names
    /// in `[nc_modules]`. Optional: without NC targets and axes the gateway only
    /// monitors (it polls, filters, records and serves metrics), the first
    /// commissioning step.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub targets: BTreeMap<String, TargetConfig>,
    /// NC axis modules over Modbus TCP, by name: the older spelling of a `[targets]`
    /// entry with `kind = "modbus"`. Optional; names as for devices.
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
    /// Seconds between status updates (status line, logs); the NC is read at the
    /// same interval, at most once a second. Default 1.0; 0.001..=3600.
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

impl Config {
    /// The target called `name`, from `[targets]` or `[nc_modules]` (a Modbus one).
    pub fn target(&self, name: &str) -> Option<TargetConfig> {
        self.targets.get(name).cloned().or_else(|| {
            self.nc_modules
                .get(name)
                .map(|m| TargetConfig::Modbus(m.clone()))
        })
    }

    /// Every Modbus NC module, `[nc_modules]` and the `kind = "modbus"` entries of
    /// `[targets]`, by name (what the simulated plant serves).
    pub fn modbus_targets(&self) -> Vec<(String, NcModuleConfig)> {
        let mut v: Vec<(String, NcModuleConfig)> = self
            .nc_modules
            .iter()
            .map(|(n, m)| (n.clone(), m.clone()))
            .collect();
        for (n, t) in &self.targets {
            if let TargetConfig::Modbus(m) = t {
                v.push((n.clone(), m.clone()));
            }
        }
        v
    }

    /// The Modbus NC module called `name` (in either table), to change it.
    pub fn modbus_target_mut(&mut self, name: &str) -> Option<&mut NcModuleConfig> {
        if let Some(m) = self.nc_modules.get_mut(name) {
            return Some(m);
        }
        match self.targets.get_mut(name) {
            Some(TargetConfig::Modbus(m)) => Some(m),
            _ => None,
        }
    }

    /// Every target, `[targets]` then `[nc_modules]`, by name.
    pub fn all_targets(&self) -> Vec<(String, TargetConfig)> {
        let mut v: Vec<(String, TargetConfig)> = self
            .targets
            .iter()
            .map(|(n, t)| (n.clone(), t.clone()))
            .collect();
        v.extend(
            self.nc_modules
                .iter()
                .map(|(n, m)| (n.clone(), TargetConfig::Modbus(m.clone()))),
        );
        v
    }
}

/// Checks the meaning of a parsed configuration and returns every problem found
/// (empty = valid). `file` names the origin in the problems.
///
/// What is checked:
///
/// - **Names** of devices, channels, NC modules and axes: 1..=64 characters of
///   `A-Z a-z 0-9 _ -`, no `__` (the environment separator) and no `_` at the end,
///   unique ignoring case (environment overrides match names ignoring case).
/// - **Something to do**: at least one device and one channel (without, `run` would
///   start and stop at once), and every Modbus device read by a channel (its poller
///   would read nothing and never connect; a CAN node alone still gets its NMT start
///   and heartbeat watch).
/// - **References**: `channels.*.device`, `axes.*.nc_module`, every channel of a
///   `k0`/`tan_beta` term, and the names under `[sim.channels]`/`[sim.nc_modules]`
///   must exist. One axis per NC module; a channel at most once per model and
///   `lag_tau_s`.
/// - **Devices** (`source`): `address` is `host:port`; baud 1200..=115200, stop bits
///   1 or 2. Devices sharing a `serial_path` must agree on baud, parity and stop bits
///   (defaults applied) and have distinct unit ids. Which keys a transport takes is
///   the schema's business: a key of another transport is an unknown key.
/// - **CAN**: `interface` a network interface name, `node_id` 1..=127; node ids
///   distinct per interface, and one `poll_interval_s` per interface (its SYNC
///   period).
/// - **Unit ids** on RTU 1..=247 (0 is broadcast); on TCP any byte.
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
///   limits and steps > 0, deadbands >= 0 and reachable (not above the step limit,
///   below twice the limit), `max_abs_tan_beta <= 0.1` (MD32760 is 0.01
///   by default; above 0.1 is not a thermal slope), ramp rates > 0 with
///   `ramp_to_zero`. `nc_write` holds every value the model sets: SD43900 with a K0
///   model, SD43910 and SD43920 with a tan(beta) model, SD43920 with `p0_mm` != 0
///   (motion heat counts towards the model it adds to), each once; its target has a
///   place for each value in `nc_write`, and reports the position for `motion_heat`
///   (a Modbus NC module or an S7 block; OPC UA and ADS do not).
/// - **OPC UA credentials**: `credentials_file` readable with a user name on its
///   first line, or the variables `user_env` and `password_env` set, read as `run`
///   reads them at start.
/// - **Addresses** the gateway connects to: `host:port` (no scheme), port 1..=65535.
///   Port 0 only where the simulated plant binds a free port for it (a file with
///   `[sim]` loaded for `compgate demo` or `compgate sim`), never for `run`.
/// - **Sim**: `period_s > 0`, amplitude and noise >= 0, `md32750` 0..=7,
///   `motion_min_mm <= motion_max_mm`, speed >= 0.
/// - Every number finite (TOML allows `nan` and `inf`).
pub fn validate(cfg: &Config, file: &str) -> Vec<ConfigProblem> {
    validate_assuming(cfg, file, &Assumed::default(), false)
}

/// Names that count as defined although the parsed configuration lacks them: entries
/// the loader had to leave out for structural problems (already reported), so that
/// references to them do not add a second, misleading problem.
#[derive(Debug, Default)]
pub(crate) struct Assumed {
    pub devices: Names,
    pub channels: Names,
    pub nc_modules: Names,
    /// The devices the left-out channels read (`any`: the device of one of them is
    /// unknown), so that no device counts as unread because its channel is broken.
    pub devices_read: Names,
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
    /// No name counts as defined.
    pub fn is_empty(&self) -> bool {
        !self.any && self.names.is_empty()
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

/// As [`validate`]; `for_sim`: the simulated plant is to bind the addresses with port
/// 0 of a file with `[sim]` (`compgate demo`, `compgate sim`).
pub(crate) fn validate_assuming(
    cfg: &Config,
    file: &str,
    assumed: &Assumed,
    for_sim: bool,
) -> Vec<ConfigProblem> {
    let port_zero = match (cfg.sim.is_some(), for_sim) {
        (false, _) => PortZero::Refused,
        (true, false) => PortZero::RefusedInSimFile,
        (true, true) => PortZero::ForSim,
    };
    let mut out = Problems::new(file).port_zero(port_zero);
    names(&mut out, "devices", cfg.devices.keys());
    names(&mut out, "channels", cfg.channels.keys());
    names(&mut out, "targets", cfg.targets.keys());
    names(&mut out, "nc_modules", cfg.nc_modules.keys());
    for name in cfg.nc_modules.keys() {
        if cfg.targets.contains_key(name) {
            out.push(
                entry("nc_modules", name),
                format!("`{name}` is also a name in [targets]; a target has one name"),
            );
        }
    }
    names(&mut out, "axes", cfg.axes.keys());

    out.positive(
        "gateway.status_interval_s",
        cfg.gateway.status_interval_s,
        "seconds",
    );

    validate_devices(&cfg.devices, &mut out);
    if cfg.devices.is_empty() && assumed.devices.is_empty() {
        out.push(
            "devices",
            "no device defined; the gateway needs at least one [devices.NAME] to read",
        );
    }

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
    if cfg.channels.is_empty() && assumed.channels.is_empty() {
        out.push(
            "channels",
            "no channel defined; the gateway needs at least one [channels.NAME] to read, \
             otherwise it starts and stops at once with nothing to do",
        );
    } else if !assumed.channels.any && !assumed.devices_read.any {
        unread_devices(cfg, assumed, &mut out);
    }

    for (name, nc) in &cfg.nc_modules {
        nc.validate(&entry("nc_modules", name), &mut out);
    }
    for (name, t) in &cfg.targets {
        t.validate(&entry("targets", name), &mut out);
    }

    let channel_list = list(cfg.channels.keys());
    let known = |c: &str| cfg.channels.contains_key(c) || assumed.channels.contains(c);
    let channels = ChannelNames {
        known: &known,
        list: &channel_list,
    };
    // (target, axis number) -> the axes already on it.
    let mut carried: BTreeMap<(&str, Option<u16>), Vec<&String>> = BTreeMap::new();
    for (name, axis) in &cfg.axes {
        let module = axis.nc_module.as_str();
        let target = cfg.target(module);
        match &target {
            None if !assumed.nc_modules.contains(module) => out.push(
                field("axes", name, "nc_module"),
                format!(
                    "unknown target `{module}`; expected one of the names in [targets] or [nc_modules]: {}",
                    list(cfg.targets.keys().chain(cfg.nc_modules.keys()))
                ),
            ),
            None => {}
            Some(t) => {
                let number = if t.one_axis() { None } else { axis.axis_number };
                if t.needs_axis_number() && axis.axis_number.is_none() {
                    out.push(
                        field("axes", name, "axis_number"),
                        format!(
                            "required: target `{module}` (kind = {}) carries several axes; \
                             give this axis's number on the control",
                            t.kind().name()
                        ),
                    );
                } else {
                    let before = carried.entry((module, number)).or_default();
                    if !before.is_empty() {
                        // Every axis before this one: with three on one module, the
                        // third's message names both others.
                        let others = list(before.iter().copied());
                        let axes = if before.len() == 1 { "axis" } else { "axes" };
                        let message = if t.one_axis() {
                            format!("NC module `{module}` already carries {axes} {others}; one axis per module")
                        } else {
                            format!(
                                "{axes} {others} already {} axis_number {} on target `{module}`",
                                if before.len() == 1 { "has" } else { "have" },
                                number.unwrap_or_default()
                            )
                        };
                        out.push(field("axes", name, "nc_module"), message);
                    }
                    before.push(name);
                }
                if axis.motion_heat.is_some() && !t.reports_axis_state() {
                    out.push(
                        field("axes", name, "motion_heat"),
                        format!(
                            "counts the axis' travel from the NC's position, but target \
                             `{module}` (kind = {}) reports no position: the term would stay \
                             at its value for a standing axis; take motion_heat out, or \
                             reach the axis through a Modbus NC module or an S7 block",
                            t.kind().name()
                        ),
                    );
                }
                for &v in &axis.nc_write_ids() {
                    if !t.has(v) {
                        out.push(
                            field("axes", name, "nc_write"),
                            format!(
                                "{} is to be written, but target `{module}` has no place for it; \
                                 leave it out of nc_write or configure it on the target",
                                var_name(v)
                            ),
                        );
                    }
                }
            }
        }
        axis.validate(&entry("axes", name), &channels, &mut out);
        nc_write_covers_model(name, axis, &mut out);
    }
    for (name, t) in &cfg.targets {
        t.validate_axes(name, &cfg.axes, &mut out);
    }
    one_control_under_two_names(cfg, &mut out);

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
            let modbus = cfg.nc_modules.contains_key(name)
                || matches!(cfg.targets.get(name), Some(TargetConfig::Modbus(_)));
            if !(modbus || assumed.nc_modules.contains(name)) {
                out.push(
                    key.clone(),
                    format!(
                        "no NC module `{name}` in [nc_modules] (or kind = \"modbus\" in [targets]) to simulate"
                    ),
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

/// Every Modbus device is read by a channel: without one its poller reads nothing and
/// never even connects, yet the status shows it polling. A CAN node without channels
/// still does something (NMT start, heartbeat watch), so it may stand alone. Not
/// checked while a channel names an unknown device: that typo most likely meant the
/// device that looks unread.
fn unread_devices(cfg: &Config, assumed: &Assumed, out: &mut Problems<'_>) {
    let defined = |d: &String| cfg.devices.contains_key(d) || assumed.devices.contains(d);
    let named = cfg.channels.values().map(|ch| &ch.device);
    if !named.chain(&assumed.devices_read.names).all(defined) {
        return;
    }
    let modbus = cfg.devices.iter().filter(|(_, d)| d.can().is_none());
    for (name, _) in modbus {
        let read = cfg.channels.values().any(|ch| &ch.device == name)
            || assumed.devices_read.contains(name);
        if !read {
            out.push(
                entry("devices", name),
                format!(
                    "no channel reads device `{name}`; the gateway would never even connect \
                     to it: add a [channels.NAME] with device = \"{name}\" or remove the device"
                ),
            );
        }
    }
}

/// Two targets of different names that are one control (two entries for one NC
/// module, its address spelled two ways, two S7 targets on one data block): the axes
/// on them pass the per-target checks, and at run time each overwrites the other's
/// values every job. Reported at the later axis, naming the place and the other axis.
fn one_control_under_two_names(cfg: &Config, out: &mut Problems<'_>) {
    let mut placed: Vec<(&String, String, Place)> = Vec::new();
    for (name, axis) in &cfg.axes {
        let module = axis.nc_module.as_str();
        let Some(target) = cfg.target(module) else {
            continue;
        };
        let number = if target.one_axis() {
            Some(1)
        } else {
            axis.axis_number
        };
        let Some(number) = number else { continue };
        let mine = target.places(name, number);
        let clash = placed
            .iter()
            .filter(|(_, other_module, _)| other_module != module)
            .find_map(|(other, other_module, p)| {
                mine.iter()
                    .find(|q| q.meets(p))
                    .map(|q| (other, other_module, q))
            });
        if let Some((other, other_module, place)) = clash {
            out.push(
                field("axes", name, "nc_module"),
                format!(
                    "target `{module}` writes {} as target `{other_module}` does for axis \
                     {other}: one control under two names, and each axis would overwrite \
                     the other's values at every job; give each axis its own place on the \
                     control",
                    place.area
                ),
            );
        }
        placed.extend(mine.into_iter().map(|p| (name, module.to_string(), p)));
    }
}

/// `nc_write` leaves out no value the axis' model sets: a job is cut down to
/// `nc_write`, so a value left out never reaches the NC while the job still reads
/// back as verified. Leaving out a value the axis does not model is fine (a K0-only
/// axis on a control without a slope).
fn nc_write_covers_model(name: &str, axis: &AxisConfig, out: &mut Problems<'_>) {
    let heat = axis.motion_heat.as_ref();
    let k0 = axis.k0.offset_mm != 0.0
        || !axis.k0.terms.is_empty()
        || heat.is_some_and(|m| m.k0_mm_per_mm_per_s != 0.0);
    let slope = axis.tan_beta.offset != 0.0
        || !axis.tan_beta.terms.is_empty()
        || heat.is_some_and(|m| m.tan_beta_per_mm_per_s != 0.0);
    // (value, why the NC needs it, the other way out)
    let mut needed: Vec<(NcVar, String, &str)> = Vec::new();
    if k0 {
        needed.push((
            NcVar::Sd43900,
            "the axis models K0: the NC would never receive it".into(),
            "take K0 out of the model",
        ));
    }
    if slope {
        needed.push((
            NcVar::Sd43910,
            "the axis models tan(beta): the NC would never receive it".into(),
            "take tan(beta) out of the model",
        ));
        needed.push((
            NcVar::Sd43920,
            format!(
                "the axis models tan(beta): the NC would apply the slope about the P0 it \
                 holds instead of p0_mm = {}",
                axis.p0_mm
            ),
            "take tan(beta) out of the model",
        ));
    } else if axis.p0_mm != 0.0 {
        needed.push((
            NcVar::Sd43920,
            format!(
                "p0_mm = {} is set: the NC would never receive it",
                axis.p0_mm
            ),
            "remove p0_mm",
        ));
    }
    let written = axis.nc_write_ids();
    for (var, why, or) in needed {
        if !written.contains(&var.id()) {
            let sd = var_name(var.id());
            out.push(
                field("axes", name, "nc_write"),
                format!(
                    "leaves out {sd}, but {why}; add \"{}\" to nc_write or {or}",
                    sd.to_lowercase()
                ),
            );
        }
    }
}

fn names<'n>(out: &mut Problems<'_>, section: &str, names: impl Iterator<Item = &'n String>) {
    let mut folded: BTreeMap<String, &str> = BTreeMap::new();
    for name in names {
        let key = entry(section, name);
        if let Some(problem) = compgate_core::measure::channel_name_problem(name) {
            out.push(key.clone(), problem);
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
