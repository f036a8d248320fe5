//! `[targets.NAME]`: the NC targets, one struct per kind, tagged by the `kind` key (the
//! keys stay flat in the target table; a key of another kind is reported as such by
//! the structural check). `[nc_modules.NAME]` is the older spelling of a
//! `kind = "modbus"` target and stays accepted.

use std::collections::BTreeMap;
use std::time::Duration;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::ads::AdsTargetConfig;
pub use super::modbus::ModbusTargetConfig;
use super::opcua::OpcuaTargetConfig;
use super::s7::S7TargetConfig;
use super::{AnyNcWriter, NcError};
use crate::axis::AxisConfig;
use crate::config::problem::{peer_identity, Problems};

/// The older name of [`ModbusTargetConfig`]: `[nc_modules.NAME]`.
pub type NcModuleConfig = ModbusTargetConfig;

/// `[targets.NAME]`: one NC target, by `kind`: `modbus` (the NC axis module's register
/// map over Modbus TCP), `opcua` (the SINUMERIK OPC UA server), `s7` (a PLC data block
/// passed to FB3, over S7comm) or `ads` (Beckhoff TwinCAT over ADS). A key of another
/// kind is an unknown key.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum TargetConfig {
    /// `kind = "modbus"`: an NC axis module over Modbus TCP (`address`, `unit_id`), one
    /// axis per module.
    Modbus(ModbusTargetConfig),
    /// `kind = "opcua"`: a SINUMERIK OPC UA server (`endpoint_url`, node-id templates,
    /// security, credentials).
    Opcua(OpcuaTargetConfig),
    /// `kind = "s7"`: a PLC data block over S7comm, passed to FB3 by the PLC program of
    /// `deploy/plc/` (`address`, `db_number`, `value_type`).
    S7(S7TargetConfig),
    /// `kind = "ads"`: a TwinCAT control over ADS (`address`, `ams_net_id`,
    /// `ams_port`, index group and offset per value).
    Ads(AdsTargetConfig),
}

/// A stretch of a control's memory that an axis' jobs write. Two axes on targets of
/// different names whose places meet are one control configured twice: each would
/// overwrite the other's values, and every job would find the NC changed behind it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Place {
    /// The control and the area in it, as a user names them ("the Modbus NC module at
    /// 127.0.0.1:502, unit 1"); the address in its [`peer_identity`] form.
    pub area: String,
    /// The bytes taken in the area; `0..1` where the area is one value or module.
    pub bytes: std::ops::Range<u64>,
}

impl Place {
    /// Whether the two share a byte.
    pub fn meets(&self, other: &Place) -> bool {
        self.area == other.area
            && self.bytes.start < other.bytes.end
            && other.bytes.start < self.bytes.end
    }
}

/// The kind of a target: its `kind` key.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TargetKind {
    /// Modbus NC axis module.
    Modbus,
    /// SINUMERIK OPC UA.
    Opcua,
    /// S7 data block + FB3.
    S7,
    /// Beckhoff ADS.
    Ads,
}

impl TargetKind {
    /// The `kind` value.
    pub fn name(self) -> &'static str {
        match self {
            Self::Modbus => "modbus",
            Self::Opcua => "opcua",
            Self::S7 => "s7",
            Self::Ads => "ads",
        }
    }
}

impl TargetConfig {
    /// The kind.
    pub fn kind(&self) -> TargetKind {
        match self {
            Self::Modbus(_) => TargetKind::Modbus,
            Self::Opcua(_) => TargetKind::Opcua,
            Self::S7(_) => TargetKind::S7,
            Self::Ads(_) => TargetKind::Ads,
        }
    }

    /// Whether each axis on this target needs `axes.NAME.axis_number` (a control with
    /// several axes); a Modbus NC module carries one axis.
    pub fn needs_axis_number(&self) -> bool {
        !matches!(self, Self::Modbus(_))
    }

    /// Whether the target carries one axis only.
    pub fn one_axis(&self) -> bool {
        matches!(self, Self::Modbus(_))
    }

    /// Whether the target reports the axis' position, applied compensation, MD32750
    /// and referenced flag (the NC module and the S7 block do; OPC UA and ADS reach
    /// the setting data only).
    pub fn reports_axis_state(&self) -> bool {
        matches!(self, Self::Modbus(_) | Self::S7(_))
    }

    /// Whether the target has a place for variable `var_id`.
    pub fn has(&self, var_id: u16) -> bool {
        match self {
            // The module's map takes every variable of `compgate_ncproto::var`.
            Self::Modbus(_) => true,
            // The three node-id templates (defaults for each).
            Self::Opcua(_) => matches!(
                var_id,
                super::var::SD43900 | super::var::SD43910 | super::var::SD43920
            ),
            Self::S7(c) => c.has(var_id),
            Self::Ads(c) => c.has(var_id),
        }
    }

    /// Where the target is: `host:port`, or the OPC UA endpoint URL.
    pub fn address(&self) -> &str {
        match self {
            Self::Modbus(c) => &c.address,
            Self::Opcua(c) => &c.endpoint_url,
            Self::S7(c) => &c.address,
            Self::Ads(c) => &c.address,
        }
    }

    /// Where on the control the jobs of axis `axis_name`, number `axis_number`, write
    /// (nothing for a number whose place does not resolve: reported apart).
    pub fn places(&self, axis_name: &str, axis_number: u16) -> Vec<Place> {
        // Port 0: the simulated plant gives each its own port.
        let port = self.address().rsplit(':').next().unwrap_or_default();
        if port.split('/').next() == Some("0") {
            return Vec::new();
        }
        match self {
            Self::Modbus(c) => vec![Place {
                area: format!(
                    "the Modbus NC module at {}, unit {}",
                    peer_identity(&c.address),
                    c.unit_id
                ),
                bytes: 0..1,
            }],
            Self::Opcua(c) => c.places(axis_name, axis_number),
            Self::S7(c) => c.places(axis_number).into_iter().collect(),
            Self::Ads(c) => c.places(axis_number),
        }
    }

    /// Seconds a whole job (write and read-back) may take, as configured.
    pub fn job_timeout(&self) -> Duration {
        match self {
            Self::Modbus(c) => c.job_timeout(),
            Self::Opcua(c) => c.job_timeout(),
            Self::S7(c) => c.job_timeout(),
            Self::Ads(c) => c.job_timeout(),
        }
    }

    /// Checks one target; `key` is its path, e.g. `targets.ctl`.
    pub fn validate(&self, key: &str, out: &mut Problems<'_>) {
        match self {
            Self::Modbus(c) => c.validate(key, out),
            Self::Opcua(c) => c.validate(key, out),
            Self::S7(c) => c.validate(key, out),
            Self::Ads(c) => c.validate(key, out),
        }
    }

    /// Checks the addresses of the axes on target `name` (of all `axes`) as
    /// [`Self::build`] resolves them: each fits (S7 block, ADS index), and no two
    /// setting data share one (ADS variable, OPC UA node). An axis whose number
    /// another axis on the target already has is left out: that is reported apart.
    pub fn validate_axes(
        &self,
        name: &str,
        axes: &BTreeMap<String, AxisConfig>,
        out: &mut Problems<'_>,
    ) {
        let key = crate::config::keys::entry("targets", name);
        let mut on: Vec<(&str, u16)> = Vec::new();
        for (axis, a) in axes {
            if a.nc_module != name {
                continue;
            }
            if let Some(n) = a.axis_number.filter(|n| on.iter().all(|(_, m)| m != n)) {
                on.push((axis.as_str(), n));
            }
        }
        match self {
            Self::Modbus(_) => {}
            Self::Opcua(c) => c.validate_axes(&key, &on, out),
            Self::S7(c) => c.validate_axes(&on, out),
            Self::Ads(c) => c.validate_axes(&key, &on, out),
        }
    }

    /// The writer for one axis of this target (not connected yet).
    pub fn build(&self, axis_name: &str, axis_number: u16) -> Result<AnyNcWriter, NcError> {
        Ok(match self {
            Self::Modbus(c) => AnyNcWriter::Modbus(c.build(axis_name, axis_number)?),
            Self::Opcua(c) => AnyNcWriter::Opcua(Box::new(c.build(axis_name, axis_number)?)),
            Self::S7(c) => AnyNcWriter::S7(c.build(axis_name, axis_number)?),
            Self::Ads(c) => AnyNcWriter::Ads(c.build(axis_name, axis_number)?),
        })
    }
}
