//! `[devices.NAME]` with `transport = "can"` and `[channels.NAME.can]`: the CANopen
//! keys, their validation and what they build ([`CanParams`], [`CanObject`]).

use std::time::Duration;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::{CanObject, CanParams};
use crate::config::keys::secs;
use crate::config::problem::Problems;
use crate::source::config::DeviceCommon;
use crate::source::plan::DataType;

/// `transport = "can"`: a CANopen node on a SocketCAN interface.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[schemars(deny_unknown_fields)]
pub struct CanDeviceConfig {
    /// SocketCAN interface of the CAN bus, e.g. `"can0"` or `"vcan0"`. Required; 1..=15
    /// characters, no `/`, `:` or whitespace (as Linux names interfaces). The
    /// interface must be up with its bitrate set (see `deploy/`).
    #[schemars(length(max = 15))]
    pub interface: String,
    /// CANopen node id of the device, 1..=127. Required. The gateway sends it NMT
    /// start and reads its TPDOs (COB-ID 0x180, 0x280, 0x380, 0x480 plus node id),
    /// SDOs (0x600 / 0x580 plus node id), heartbeat (0x700 plus node id) and EMCY
    /// (0x080 plus node id). Node ids on one interface must be distinct.
    #[schemars(range(min = 1, max = 127))]
    pub node_id: u8,
    /// Heartbeat consumer timeout in seconds: a node whose heartbeat has been missing
    /// for longer has all its channels bad. 0 turns the check off. Default 1.5 (for
    /// the common 1 s or faster producer heartbeat time, object 0x1017); 0 or
    /// 0.001..=3600. The
    /// gateway sends each interface's SYNC from a timer of its own every
    /// `poll_interval_s`; `timeout_s` is the longest wait for the synchronous TPDOs
    /// after it and for each SDO answer.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 0.0, max = 3600.0))]
    pub heartbeat_timeout_s: Option<f64>,
    /// For a node that sends its TPDOs event-driven (transmission type 254 or 255 in
    /// 1800h..1803h sub 2: on its event timer, sub 5, or on a change) instead of after
    /// each SYNC: a poll takes each TPDO's newest frame if it came within this many
    /// seconds, else its channels are bad ("not received for ..."). Set it above the
    /// node's event timer, e.g. 3 times it. Unset (default): synchronous TPDOs, read
    /// after the newest SYNC. An interface whose devices all have it gets no SYNC
    /// from the gateway. 0.001..=3600.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub tpdo_max_age_s: Option<f64>,
    /// Timeouts, poll interval (= SYNC period), backoff, degradation.
    #[serde(flatten)]
    pub common: DeviceCommon,
}

impl CanDeviceConfig {
    /// Default of `heartbeat_timeout_s`.
    pub const DEFAULT_HEARTBEAT_TIMEOUT_S: f64 = 1.5;

    /// `heartbeat_timeout_s` (or its default) as a [`Duration`]; zero = off.
    pub fn heartbeat_timeout(&self) -> Duration {
        secs(
            self.heartbeat_timeout_s
                .unwrap_or(Self::DEFAULT_HEARTBEAT_TIMEOUT_S),
        )
    }

    /// An interface name, node id 1..=127, heartbeat timeout 0 or 0.001..=3600 s.
    pub fn validate(&self, key: &str, out: &mut Problems<'_>) {
        let k = |f: &str| format!("{key}.{f}");
        let i = &self.interface;
        // The kernel's rule for interface names (dev_valid_name): such a name would
        // pass here and only fail at run with "No such device".
        let invalid = |c: char| c == '/' || c == ':' || c.is_whitespace();
        if i.is_empty() || i.len() >= 16 || i.chars().any(invalid) || i == "." || i == ".." {
            out.push(
                k("interface"),
                format!("`{i}` is not a network interface name (1..=15 characters, no `/`, `:` or whitespace), e.g. \"can0\""),
            );
        }
        if !(1..=127).contains(&self.node_id) {
            out.push(
                k("node_id"),
                format!("must be 1..=127 (CANopen node id), got {}", self.node_id),
            );
        }
        if let Some(h) = self.heartbeat_timeout_s {
            // The schema holds it within 0..=3600; a tiny non-zero value would be a
            // timeout that always fires.
            if !(h == 0.0 || (0.001..=3600.0).contains(&h)) {
                out.push(
                    k("heartbeat_timeout_s"),
                    format!("must be 0 (no heartbeat check) or 0.001..=3600 seconds, got {h}"),
                );
            }
        }
    }

    /// The poller's parameters; `sync_period` is the interface's SYNC period.
    pub fn params(&self, sync_period: Duration) -> CanParams {
        CanParams {
            sync_period,
            interface: self.interface.clone(),
            node_id: self.node_id,
            timeout: self.common.timeout(),
            heartbeat_timeout: self.heartbeat_timeout(),
            degrade_after_cycles: self.common.degrade_after_cycles,
            tpdo_max_age: self.tpdo_max_age_s.map(secs),
        }
    }
}

/// `[channels.NAME.can]`: where a CAN channel's value is on its node. Either a TPDO
/// mapping (`pdo` and `offset_bytes`) or an SDO object (`sdo_index` and
/// `sdo_subindex`), not both.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, Copy, PartialEq, Eq)]
#[serde(deny_unknown_fields)]
pub struct CanChannelConfig {
    /// Synchronous TPDO number 1..=4 (COB-ID 0x180 + 0x100 * (pdo - 1) + node id)
    /// carrying the value, sent by the node after each SYNC.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 1, max = 4))]
    pub pdo: Option<u8>,
    /// Byte offset of the value in the TPDO, 0..=7; the value must end within the
    /// 8 data bytes (offset + 2 for 16-bit, + 4 for 32-bit types).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(max = 7))]
    pub offset_bytes: Option<u8>,
    /// Object dictionary index read by expedited SDO upload each poll cycle, e.g.
    /// `0x6401` (CiA 401 analogue input 16 bit).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sdo_index: Option<u16>,
    /// Sub-index of the SDO object, 0..=255.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sdo_subindex: Option<u8>,
}

impl CanChannelConfig {
    /// A TPDO mapping or an SDO object, complete and within the PDO; `key` is the
    /// table's path (`channels.NAME.can`), `data_type` the value's encoding.
    pub fn validate(&self, key: &str, data_type: DataType, out: &mut Problems<'_>) {
        let k = |f: &str| format!("{key}.{f}");
        let size = u32::from(data_type.registers()) * 2;
        let pdo = self.pdo.is_some() || self.offset_bytes.is_some();
        let sdo = self.sdo_index.is_some() || self.sdo_subindex.is_some();
        match (pdo, sdo) {
            (true, true) => out.push(
                key,
                "either a TPDO mapping (pdo, offset_bytes) or an SDO object (sdo_index, \
                 sdo_subindex), not both",
            ),
            (false, false) => out.push(
                key,
                "empty: give pdo and offset_bytes, or sdo_index and sdo_subindex",
            ),
            (true, false) => {
                match self.pdo {
                    Some(1..=4) => {}
                    Some(p) => out.push(k("pdo"), format!("must be 1..=4 (TPDO1..TPDO4), got {p}")),
                    None => out.push(
                        k("pdo"),
                        "required with offset_bytes: the TPDO number 1..=4",
                    ),
                }
                match self.offset_bytes {
                    Some(o) if u32::from(o) + size <= 8 => {}
                    Some(o) => out.push(
                        k("offset_bytes"),
                        format!(
                            "a {} value at byte {o} takes {size} bytes and would end past the 8 bytes of a PDO; expected offset_bytes <= {}",
                            data_type.name(),
                            8 - size
                        ),
                    ),
                    None => out.push(k("offset_bytes"), "required with pdo: the value's byte offset in the PDO"),
                }
            }
            (false, true) => {
                if self.sdo_index.is_none() {
                    out.push(
                        k("sdo_index"),
                        "required with sdo_subindex: the object index, e.g. 0x6401",
                    );
                }
                if self.sdo_subindex.is_none() {
                    out.push(
                        k("sdo_subindex"),
                        "required with sdo_index: the sub-index, 0..=255",
                    );
                }
            }
        }
    }

    /// The object, when the table is complete (validation makes it so).
    pub fn object(&self) -> Option<CanObject> {
        match (
            self.pdo,
            self.offset_bytes,
            self.sdo_index,
            self.sdo_subindex,
        ) {
            (Some(pdo), Some(offset_bytes), None, None) => {
                Some(CanObject::Pdo { pdo, offset_bytes })
            }
            (None, None, Some(index), Some(sub)) => Some(CanObject::Sdo { index, sub }),
            _ => None,
        }
    }
}
