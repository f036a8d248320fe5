//! `[nc_modules.NAME]`: an NC axis module's keys, their validation and the writer
//! they build.

use std::time::Duration;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::ModbusNcWriter;
use crate::config::keys::secs;
use crate::config::problem::Problems;
use crate::source::modbus::{Backoff, LinkSpec, ModbusLink};

/// `[nc_modules.NAME]`: an NC axis module reached over Modbus TCP (one axis per
/// module; see `compgate_ncproto`).
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct NcModuleConfig {
    /// `host:port` of the module's Modbus TCP interface. Required; at most
    /// 300 characters. Port 0 is accepted
    /// only because the embedded demo replaces it with the port its simulator bound.
    #[schemars(length(max = 300))]
    pub address: String,
    /// Modbus unit id, 0..=247. Required.
    #[schemars(range(max = 247))]
    pub unit_id: u8,
    /// Seconds one Modbus request may take. Default 1.0; 0.001..=3600.
    #[serde(default = "default_nc_timeout_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub timeout_s: f64,
    /// Seconds a TCP connect may take. Default 2.0; 0.001..=3600.
    #[serde(default = "default_connect_timeout_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub connect_timeout_s: f64,
    /// Seconds the whole FB3 job (REQ .. DONE/ERROR) may take. Default 2.0;
    /// 0.001..=3600.
    #[serde(default = "default_job_timeout_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub job_timeout_s: f64,
}

impl NcModuleConfig {
    /// `timeout_s` as a [`Duration`].
    pub fn timeout(&self) -> Duration {
        secs(self.timeout_s)
    }
    /// `connect_timeout_s` as a [`Duration`].
    pub fn connect_timeout(&self) -> Duration {
        secs(self.connect_timeout_s)
    }
    /// `job_timeout_s` as a [`Duration`].
    pub fn job_timeout(&self) -> Duration {
        secs(self.job_timeout_s)
    }

    /// `address` is `host:port`, unit id 0..=247, every time > 0.
    pub fn validate(&self, key: &str, out: &mut Problems<'_>) {
        let k = |f: &str| format!("{key}.{f}");
        out.host_port(&k("address"), &self.address);
        out.unit_id(&k("unit_id"), self.unit_id);
        out.positive(&k("timeout_s"), self.timeout_s, "seconds");
        out.positive(&k("connect_timeout_s"), self.connect_timeout_s, "seconds");
        out.positive(&k("job_timeout_s"), self.job_timeout_s, "seconds");
    }

    /// The module's job writer (not connected yet).
    pub fn build(&self) -> ModbusNcWriter {
        let link = ModbusLink::new(
            LinkSpec::Tcp {
                address: self.address.clone(),
                connect_timeout: self.connect_timeout(),
            },
            self.timeout(),
            Backoff::new(Duration::from_millis(500), Duration::from_secs(10)),
        );
        ModbusNcWriter::new(link, self.unit_id, self.job_timeout())
    }
}

fn default_nc_timeout_s() -> f64 {
    1.0
}
fn default_connect_timeout_s() -> f64 {
    2.0
}
fn default_job_timeout_s() -> f64 {
    2.0
}
