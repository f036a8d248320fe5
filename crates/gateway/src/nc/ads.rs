//! The ADS target (Beckhoff TwinCAT): the three setting data as LREAL or REAL variables
//! at an index group and offset each, from the config, written in one sum-up request
//! and read back one by one (the guard checks the read-back).
//!
//! The `ads` crate is synchronous: every exchange runs on tokio's blocking pool, with
//! the connection moved in and back out, so no runtime worker thread ever waits on a
//! socket. A request cut off by the job timeout leaves its connection with the blocking
//! task; the next exchange connects afresh.

use std::fmt;
use std::sync::Arc;
use std::time::Duration;

use ads::client::WriteRequest;
use ads::{AmsAddr, AmsNetId, Client, Device, Source, Timeouts};
use compgate_ncproto::var;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use tokio::time::Instant;

use super::config::Place;
use super::{number, var_name, Job, JobReport, NcError, NcSnapshot, NcWriter, Precision};
use crate::config::keys::secs;
use crate::config::problem::Problems;
use crate::source::modbus::Backoff;

/// `[targets.NAME]` with `kind = "ads"`: a TwinCAT control reached over ADS (AMS/TCP,
/// port 48898 of its router).
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct AdsTargetConfig {
    /// `host:port` of the control's AMS router, e.g. `"192.168.0.20:48898"`. Required;
    /// at most 300 characters.
    #[schemars(length(max = 300))]
    pub address: String,
    /// AMS Net ID of the control, `a.b.c.d.e.f` (TwinCAT: System > Routes), e.g.
    /// `"192.168.0.20.1.1"`. Required; at most 23 characters.
    #[schemars(length(max = 23))]
    pub ams_net_id: String,
    /// AMS port of the runtime holding the values: 851 the first TwinCAT 3 PLC, 500 or
    /// 501 the NC. Default 851; 1..=65535.
    #[serde(default = "default_ams_port")]
    #[schemars(range(min = 1, max = 65535))]
    pub ams_port: u16,
    /// AMS Net ID compgate presents as its own (the control needs a route to it).
    /// Default: the local IP address followed by `.1.1`; at most 23 characters.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(max = 23))]
    pub source_net_id: Option<String>,
    /// How the control stores the values: `"lreal"` (f64, read back bit for bit) or
    /// `"real"` (f32, read back within one float32 ulp). Default `"lreal"`.
    #[serde(default)]
    pub value_type: AdsValueType,
    /// Where SD43900 (K0, mm) lives. Required.
    pub sd43900: AdsValueAddress,
    /// Where SD43910 (slope, mm/mm) lives. Absent: the control has no slope, and an
    /// axis on it must leave `sd43910` out of `nc_write`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sd43910: Option<AdsValueAddress>,
    /// Where SD43920 (reference position, mm) lives. Absent: as for `sd43910`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sd43920: Option<AdsValueAddress>,
    /// Seconds one ADS request may take. Default 1.0; 0.001..=3600.
    #[serde(default = "default_timeout_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub timeout_s: f64,
    /// Seconds a whole job (the running gateway's check of what the NC holds, the
    /// write and its read-back) may take. Default 2.0; 0.001..=3600.
    #[serde(default = "default_job_timeout_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub job_timeout_s: f64,
}

/// How an ADS variable stores a value.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, Copy, PartialEq, Eq, Default)]
#[serde(rename_all = "lowercase")]
pub enum AdsValueType {
    /// LREAL, 8 bytes.
    #[default]
    Lreal,
    /// REAL, 4 bytes.
    Real,
}

/// Index group and offset of one value; for axis number `n` (`axes.NAME.axis_number`)
/// the value sits at `index_group + n * group_per_axis`, `index_offset + n *
/// offset_per_axis` (TwinCAT NC PTP: index group 0x5000 + axis id, so `index_group =
/// 0x5000, group_per_axis = 1`).
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, Copy, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct AdsValueAddress {
    /// Index group. Required; 0..=4294967295.
    pub index_group: u32,
    /// Index offset. Required; 0..=4294967295.
    pub index_offset: u32,
    /// Added to the index group per axis number. Default 0; 0..=65535.
    #[serde(default)]
    #[schemars(range(max = 65535))]
    pub group_per_axis: u32,
    /// Added to the index offset per axis number. Default 0; 0..=65535.
    #[serde(default)]
    #[schemars(range(max = 65535))]
    pub offset_per_axis: u32,
}

impl AdsValueAddress {
    /// Group and offset for axis number `axis`, `None` when it overflows.
    pub fn at(&self, axis: u16) -> Option<(u32, u32)> {
        let n = u32::from(axis);
        Some((
            self.index_group
                .checked_add(n.checked_mul(self.group_per_axis)?)?,
            self.index_offset
                .checked_add(n.checked_mul(self.offset_per_axis)?)?,
        ))
    }
}

impl AdsTargetConfig {
    /// `job_timeout_s` as a [`Duration`].
    pub fn job_timeout(&self) -> Duration {
        secs(self.job_timeout_s)
    }

    /// The address of each value, by variable id.
    fn values(&self) -> [(u16, Option<AdsValueAddress>); 3] {
        [
            (var::SD43900, Some(self.sd43900)),
            (var::SD43910, self.sd43910),
            (var::SD43920, self.sd43920),
        ]
    }

    /// Whether the control has a place for `var_id`.
    pub fn has(&self, var_id: u16) -> bool {
        self.values()
            .iter()
            .any(|(v, a)| *v == var_id && a.is_some())
    }

    /// `address` is `host:port`, the Net IDs parse, times > 0.
    pub fn validate(&self, key: &str, out: &mut Problems<'_>) {
        let k = |f: &str| format!("{key}.{f}");
        out.host_port(&k("address"), &self.address);
        if self.ams_net_id.parse::<AmsNetId>().is_err() || self.ams_net_id.split('.').count() != 6 {
            out.push(
                k("ams_net_id"),
                format!(
                    "`{}` is not an AMS Net ID; expected six numbers 0..=255, e.g. \"192.168.0.20.1.1\"",
                    self.ams_net_id
                ),
            );
        }
        if let Some(s) = &self.source_net_id {
            if s.parse::<AmsNetId>().is_err() || s.split('.').count() != 6 {
                out.push(
                    k("source_net_id"),
                    format!("`{s}` is not an AMS Net ID; expected six numbers 0..=255"),
                );
            }
        }
        out.positive(&k("timeout_s"), self.timeout_s, "seconds");
        out.positive(&k("job_timeout_s"), self.job_timeout_s, "seconds");
    }

    /// Where each value of axis `axis_number` lives; `Err` names the variable whose
    /// index group or offset overflows 32 bits.
    fn resolve(&self, axis_number: u16) -> Result<Vec<AdsValue>, String> {
        let mut values = Vec::new();
        for (var_id, a) in self.values() {
            let Some(a) = a else { continue };
            let (g, o) = a.at(axis_number).ok_or_else(|| {
                format!(
                    "the index group or offset of {} overflows 32 bits at axis number \
                     {axis_number} ({:#x} + {axis_number} * {}, {:#x} + {axis_number} * {})",
                    var_name(var_id),
                    a.index_group,
                    a.group_per_axis,
                    a.index_offset,
                    a.offset_per_axis
                )
            })?;
            values.push(AdsValue {
                var: var_id,
                index_group: g,
                index_offset: o,
            });
        }
        Ok(values)
    }

    /// Bytes one value takes in the control.
    fn value_bytes(&self) -> u64 {
        match self.value_type {
            AdsValueType::Lreal => 8,
            AdsValueType::Real => 4,
        }
    }

    /// Each value of axis `axis_number`, if they resolve (see [`TargetConfig::places`](super::config::TargetConfig::places)).
    pub fn places(&self, axis_number: u16) -> Vec<Place> {
        let size = self.value_bytes();
        let values = self.resolve(axis_number).unwrap_or_default();
        values
            .into_iter()
            .map(|v| Place {
                area: format!(
                    "index group {:#x} of ADS device {} port {}",
                    v.index_group, self.ams_net_id, self.ams_port
                ),
                bytes: u64::from(v.index_offset)..u64::from(v.index_offset) + size,
            })
            .collect()
    }

    /// Every axis' values resolve, as [`Self::build`] places them, and no two of
    /// them (of one axis or of two) share a byte; `axes` are the (name, axis number)
    /// of the axes on this target, `key` the target's path.
    pub fn validate_axes(&self, key: &str, axes: &[(&str, u16)], out: &mut Problems<'_>) {
        let size = self.value_bytes();
        let mut placed: Vec<(&str, AdsValue)> = Vec::new();
        for &(axis, number) in axes {
            let values = match self.resolve(number) {
                Ok(v) => v,
                Err(why) => {
                    out.push(
                        crate::config::keys::field("axes", axis, "axis_number"),
                        format!("{why}: lower the axis number or the per-axis steps of {key}"),
                    );
                    continue;
                }
            };
            for v in values {
                let overlaps = |(_, p): &&(&str, AdsValue)| {
                    p.index_group == v.index_group
                        && u64::from(p.index_offset).abs_diff(u64::from(v.index_offset)) < size
                };
                if let Some((other, p)) = placed.iter().find(overlaps) {
                    let consequence = if *other == axis {
                        "one variable would take two setting data".to_string()
                    } else {
                        "each axis would overwrite the other's value; set group_per_axis or \
                         offset_per_axis so that each axis number has its own variables"
                            .to_string()
                    };
                    out.push(
                        format!("{key}.{}", var_name(v.var).to_lowercase()),
                        format!(
                            "{} of axis {axis} overlaps {} of axis {other} (a value is {size} \
                             bytes): {consequence}",
                            v.describe(),
                            p.describe()
                        ),
                    );
                } else {
                    placed.push((axis, v));
                }
            }
        }
    }

    /// The writer for axis `axis_number` (not connected yet; connects on first use and
    /// reconnects with a backoff of 0.5 s doubling to 10 s).
    pub fn build(&self, axis_name: &str, axis_number: u16) -> Result<AdsNcWriter, NcError> {
        let bad = |what: String| NcError::Config(format!("axis {axis_name}: {what}"));
        let target_id: AmsNetId = self
            .ams_net_id
            .parse()
            .map_err(|_| bad(format!("AMS Net ID `{}`", self.ams_net_id)))?;
        let source = match &self.source_net_id {
            None => Source::Auto,
            Some(s) => Source::Addr(AmsAddr::new(
                s.parse().map_err(|_| bad(format!("AMS Net ID `{s}`")))?,
                58913,
            )),
        };
        let values = self.resolve(axis_number).map_err(bad)?;
        Ok(AdsNcWriter {
            plan: Arc::new(Plan {
                address: self.address.clone(),
                target: AmsAddr::new(target_id, self.ams_port),
                source,
                timeout: secs(self.timeout_s),
                value_type: self.value_type,
                values,
            }),
            client: None,
            backoff: Backoff::new(Duration::from_millis(500), Duration::from_secs(10)),
            link_error: None,
        })
    }
}

/// One value's place on the control.
#[derive(Debug, Clone, Copy, PartialEq)]
struct AdsValue {
    var: u16,
    index_group: u32,
    index_offset: u32,
}

impl AdsValue {
    fn describe(&self) -> String {
        format!(
            "{} (ADS {:#x}:{:#x})",
            var_name(self.var),
            self.index_group,
            self.index_offset
        )
    }
}

/// What an exchange needs, shared with the blocking pool.
#[derive(Debug)]
struct Plan {
    address: String,
    target: AmsAddr,
    source: Source,
    timeout: Duration,
    value_type: AdsValueType,
    values: Vec<AdsValue>,
}

impl Plan {
    fn connect(&self) -> Result<Client, NcError> {
        Client::new(
            self.address.as_str(),
            Timeouts::new(self.timeout),
            self.source,
        )
        .map_err(|e| NcError::Unreachable(format!("ADS {}: {e}", self.address)))
    }

    fn encode(&self, value: f64) -> Vec<u8> {
        match self.value_type {
            AdsValueType::Lreal => value.to_le_bytes().to_vec(),
            AdsValueType::Real => (value as f32).to_le_bytes().to_vec(),
        }
    }

    fn precision(&self) -> Precision {
        match self.value_type {
            AdsValueType::Lreal => Precision::F64,
            AdsValueType::Real => Precision::F32,
        }
    }

    /// The `value_type` value and the size it reads.
    fn type_name(&self) -> (&'static str, usize) {
        match self.value_type {
            AdsValueType::Lreal => ("lreal", 8),
            AdsValueType::Real => ("real", 4),
        }
    }

    /// Reads one value and refuses one the NC cannot hold: the size of an ADS variable
    /// is not told by the read (TwinCAT answers 4 bytes of an LREAL), so a wrong
    /// `value_type` shows as a subnormal, huge or non-finite value.
    fn read(&self, dev: &Device<'_>, v: &AdsValue) -> Result<f64, NcError> {
        let what = || format!("read of {}", v.describe());
        let (type_name, size) = self.type_name();
        let mut b = [0; 8];
        dev.read_exact(v.index_group, v.index_offset, &mut b[..size])
            .map_err(|e| match e {
                // A whole answer, shorter than asked: the variable is smaller.
                ads::Error::Reply(_, "got less data than expected", got) => NcError::Answered {
                    what: what(),
                    answer: format!(
                        "the control answered {got} bytes where value_type = \"{type_name}\" \
                         reads {size}: check value_type (REAL is 4 bytes, LREAL 8)"
                    ),
                },
                e => ads_error(what(), e),
            })?;
        let x = if size == 8 {
            f64::from_le_bytes(b)
        } else {
            f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        };
        match self.precision().implausible(v.var, x) {
            None => Ok(x),
            Some(why) => Err(NcError::Implausible(format!(
                "{} reads {}, {why}: not a value the NC holds; the likely cause is value_type \
                 = \"{type_name}\" while the control's variable is {} (REAL is 4 bytes, LREAL \
                 8); nothing is written while it reads so",
                v.describe(),
                number(x),
                if size == 8 { "a REAL" } else { "an LREAL" }
            ))),
        }
    }
}

/// An ADS error: an answer with an error code names it, anything else is a link
/// failure.
fn ads_error(what: String, e: ads::Error) -> NcError {
    match e {
        // The codes a wrong key gives name the key to check.
        ads::Error::Ads(_, name, code) => NcError::Answered {
            what,
            answer: format!(
                "ADS error {code:#x} ({name}){}",
                match code {
                    0x702 | 0x703 => ": check the value's index_group and index_offset",
                    0x705 => ": check value_type (REAL is 4 bytes, LREAL 8)",
                    _ => "",
                }
            ),
        },
        other => NcError::Unreachable(format!("{what}: {other}")),
    }
}

/// Job writer for one axis of an ADS target.
pub struct AdsNcWriter {
    plan: Arc<Plan>,
    client: Option<Client>,
    backoff: Backoff,
    /// Why the connection was lost or not made, named while the backoff waits.
    link_error: Option<String>,
}

impl fmt::Debug for AdsNcWriter {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("AdsNcWriter")
            .field("plan", &self.plan)
            .field("connected", &self.client.is_some())
            .finish()
    }
}

impl AdsNcWriter {
    /// Runs `op` on the blocking pool with the connection (made first if there is
    /// none, unless the backoff forbids it yet).
    async fn exchange<T: Send + 'static>(
        &mut self,
        op: impl FnOnce(&Plan, &Device<'_>) -> Result<T, NcError> + Send + 'static,
    ) -> Result<T, NcError> {
        if self.client.is_none() {
            if let Some(left) = self.backoff.remaining(Instant::now()) {
                let why = self
                    .link_error
                    .as_deref()
                    .unwrap_or("reconnect backing off");
                return Err(NcError::Unreachable(format!(
                    "{why} (next attempt in {:.1} s)",
                    left.as_secs_f64()
                )));
            }
        }
        let client = self.client.take();
        let plan = Arc::clone(&self.plan);
        let (client, result) = tokio::task::spawn_blocking(move || {
            let client = match client {
                Some(c) => c,
                None => match plan.connect() {
                    Ok(c) => c,
                    Err(e) => return (None, Err(e)),
                },
            };
            let result = op(&plan, &client.device(plan.target));
            // An answer, even a refusal, leaves the connection good; a link failure
            // does not.
            let keep = !matches!(&result, Err(NcError::Unreachable(_)));
            (keep.then_some(client), result)
        })
        .await
        .map_err(|e| NcError::Unreachable(format!("ADS exchange: {e}")))?;
        match (&client, &result) {
            (Some(_), _) => {
                self.backoff.reset();
                self.link_error = None;
            }
            (None, Err(e)) => {
                self.backoff.failed(Instant::now());
                self.link_error = Some(match e {
                    NcError::Unreachable(why) => why.clone(),
                    e => e.to_string(),
                });
            }
            (None, Ok(_)) => {}
        }
        self.client = client;
        result
    }
}

impl NcWriter for AdsNcWriter {
    async fn write_job(&mut self, job: &Job) -> Result<JobReport, NcError> {
        let started = Instant::now();
        let mut items = Vec::with_capacity(job.pairs.len());
        for &(var_id, value) in &job.pairs {
            let v = self
                .plan
                .values
                .iter()
                .find(|v| v.var == var_id)
                .copied()
                .ok_or(NcError::NotAllowed { var: var_id })?;
            items.push((v, self.plan.encode(value)));
        }
        self.exchange(move |_plan, dev| {
            let what = || {
                let names: Vec<String> = items.iter().map(|(v, _)| v.describe()).collect();
                format!("write of {}", names.join(", "))
            };
            let mut reqs: Vec<WriteRequest<'_>> = items
                .iter()
                .map(|(v, b)| WriteRequest::new(v.index_group, v.index_offset, b))
                .collect();
            // One sum-up request: the values arrive together.
            dev.write_multi(&mut reqs)
                .map_err(|e| ads_error(what(), e))?;
            for (r, (v, _)) in reqs.iter().zip(&items) {
                r.ensure()
                    .map_err(|e| ads_error(format!("write of {}", v.describe()), e))?;
            }
            Ok(())
        })
        .await?;
        Ok(JobReport {
            job_id: 0,
            elapsed: started.elapsed(),
        })
    }

    async fn read_snapshot(&mut self) -> Result<NcSnapshot, NcError> {
        self.exchange(|plan, dev| {
            let mut snap = NcSnapshot::default();
            for v in &plan.values {
                let x = plan.read(dev, v)?;
                match v.var {
                    var::SD43900 => snap.sd43900_mm = x,
                    var::SD43910 => snap.sd43910 = x,
                    var::SD43920 => snap.sd43920_mm = x,
                    _ => {}
                }
            }
            Ok(snap)
        })
        .await
    }

    fn precision(&self) -> Precision {
        self.plan.precision()
    }
}

fn default_ams_port() -> u16 {
    851
}
fn default_timeout_s() -> f64 {
    1.0
}
fn default_job_timeout_s() -> f64 {
    2.0
}

#[cfg(test)]
mod tests {
    use super::*;

    // While the reconnect waited, the status said only "reconnect backing off": why
    // the control was unreachable was gone.
    #[tokio::test]
    async fn the_wait_before_a_reconnect_names_why_the_last_connect_failed() {
        let at = crate::nc::refused_address();
        let cfg: AdsTargetConfig = toml::from_str(&format!(
            "address = \"{at}\"\nams_net_id = \"10.1.2.3.1.1\"\n\
             sd43900 = {{ index_group = 0x4020, index_offset = 0 }}"
        ))
        .expect("valid ADS target config");
        let mut w = cfg.build("X", 1).expect("writer");
        let (first, waiting) = crate::nc::refused_then_waiting(&mut w).await;
        assert!(first.contains("refused"), "{first}");
        assert!(
            waiting.contains(&at)
                && waiting.contains("refused")
                && waiting.contains("(next attempt in"),
            "{waiting}"
        );
    }
}
