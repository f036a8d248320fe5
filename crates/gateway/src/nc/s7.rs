//! The S7 data-block target (SINUMERIK route 1): the gateway writes the job into a
//! non-optimized PLC data block over S7comm (ISO-on-TCP); a small PLC program
//! (`deploy/plc/`) hands it to FB3 PUT and answers in the same block with the
//! REQ/DONE/ERROR/STATUS handshake of the NC module (`compgate_ncproto`).
//!
//! # Block layout (one block per axis, big-endian as every S7 datum)
//!
//! `w` is the value size: 4 for REAL, 8 for LREAL. Offsets are bytes from the axis'
//! block start, `start_byte + (axis_number - 1) * block_stride_bytes`.
//!
//! | offset | name | type | written by |
//! |---|---|---|---|
//! | 0 | `REQ` | INT | PC: 1 starts the job, 0 acknowledges DONE/ERROR |
//! | 2 | `JOB_ID` | WORD | PC: echoed in `JOB_ID_DONE` |
//! | 4 | `AXIS` | INT | PC: NC machine axis number |
//! | 6 | `NUM_PAIRS` | INT | PC: 1..=8 |
//! | 8 + 2i | `VAR_ID[i]` | WORD | PC: 43900, 43910, 43920 |
//! | 24 + w i | `VALUE[i]` | REAL / LREAL | PC |
//! | S = 24 + 8w | `STATE` | INT | PLC: 0 idle, 1 busy, 2 done, 3 error |
//! | S + 2 | `STATUS` | INT | PLC: 0 OK, 3, 5, 10, 16 (see `JobStatus`) |
//! | S + 4 | `ERROR_INDEX` | INT | PLC: pair at fault, 1-based, 0 none |
//! | S + 6 | `JOB_ID_DONE` | WORD | PLC |
//! | S + 8 | `FB3_STATE` | WORD | PLC: FB3's `State` output, raw, for diagnosis |
//! | S + 10 | `MD32750` | INT | PLC (FB2 GET) |
//! | S + 12 | `REFERENCED` | INT | PLC: 1 when the axis is referenced |
//! | S + 16 + w k | read-back `k` | REAL / LREAL | PLC (FB2 GET): SD43900, SD43910, SD43920, MD32760, MD32000, MD32450, position, applied and target compensation |
//!
//! The PC writes `JOB_ID` .. `VALUE[8]` in one request and `REQ` in a second, so
//! the PLC never latches half a job; every poll reads `STATE` .. the read-back in
//! one request.
//!
//! # Threads
//!
//! `rust7` is synchronous. Each job or snapshot moves the client onto tokio's
//! blocking pool and back, so no S7 call ever blocks a runtime worker; a job cut off
//! by its timeout leaves the client behind, and the next call connects anew (a late
//! reply in the old stream can never be read as the next answer).

use std::io;
use std::time::Duration;

use compgate_ncproto::{var, JobState, JobStatus, MAX_PAIRS};
use rust7::{S7Client, S7Error};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use tokio::time::Instant;

use super::config::Place;
use super::{Job, JobIds, JobReport, NcError, NcSnapshot, NcWriter, Precision};
use crate::config::keys::secs;
use crate::config::problem::{peer_identity, Problems};
use crate::source::modbus::Backoff;
use crate::source::SourceError;

/// How the block holds the values.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[serde(rename_all = "snake_case")]
pub enum S7ValueType {
    /// 32-bit REAL: every S7 PLC, including the 840D sl's S7-300-class PLC. The NC
    /// receives the value rounded to float32 (about 7 significant digits).
    Real,
    /// 64-bit LREAL: S7-1500-class PLCs (SINUMERIK ONE); bit-exact.
    Lreal,
}

impl S7ValueType {
    /// The read-back tolerance of this type.
    pub fn precision(self) -> Precision {
        match self {
            Self::Real => Precision::F32,
            Self::Lreal => Precision::F64,
        }
    }

    /// The `value_type` key's value: `real` or `lreal`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Real => "real",
            Self::Lreal => "lreal",
        }
    }

    /// Bytes of one value.
    pub fn size(self) -> u16 {
        match self {
            Self::Real => 4,
            Self::Lreal => 8,
        }
    }
}

/// Byte offsets of one axis' block (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct S7Layout {
    /// The value encoding, which sets the offsets past the variable ids.
    pub value_type: S7ValueType,
}

impl S7Layout {
    /// `REQ` (INT).
    pub const REQ: u16 = 0;
    /// `JOB_ID` (WORD).
    pub const JOB_ID: u16 = 2;
    /// `AXIS` (INT).
    pub const AXIS: u16 = 4;
    /// `NUM_PAIRS` (INT).
    pub const NUM_PAIRS: u16 = 6;
    /// `VAR_ID[0]` (WORD); eight of them.
    pub const VAR_IDS: u16 = 8;
    /// `VALUE[0]`; eight of them.
    pub const VALUES: u16 = 24;
    /// Read-back values, in this order from [`Self::readback`].
    pub const READBACK_VARS: [&'static str; 9] = [
        "SD43900",
        "SD43910",
        "SD43920",
        "MD32760",
        "MD32000",
        "MD32450",
        "POSITION",
        "APPLIED_COMP",
        "TARGET_COMP",
    ];

    /// `STATE` (INT): the start of what the PLC writes.
    pub fn state(self) -> u16 {
        Self::VALUES + MAX_PAIRS as u16 * self.value_type.size()
    }
    /// `STATUS` (INT).
    pub fn status(self) -> u16 {
        self.state() + 2
    }
    /// `ERROR_INDEX` (INT).
    pub fn error_index(self) -> u16 {
        self.state() + 4
    }
    /// `JOB_ID_DONE` (WORD).
    pub fn job_id_done(self) -> u16 {
        self.state() + 6
    }
    /// `FB3_STATE` (WORD).
    pub fn fb3_state(self) -> u16 {
        self.state() + 8
    }
    /// `MD32750` (INT).
    pub fn md32750(self) -> u16 {
        self.state() + 10
    }
    /// `REFERENCED` (INT).
    pub fn referenced(self) -> u16 {
        self.state() + 12
    }
    /// Read-back value `k` (see [`Self::READBACK_VARS`]).
    pub fn readback(self, k: u16) -> u16 {
        self.state() + 16 + k * self.value_type.size()
    }
    /// Bytes of the block: 108 for REAL, 176 for LREAL.
    pub fn block_len(self) -> u16 {
        self.readback(Self::READBACK_VARS.len() as u16)
    }
}

/// `kind = "s7"`: a PLC data block reached over S7comm (ISO-on-TCP), one block per
/// axis, handed to FB3 PUT by the PLC program of `deploy/plc/`.
#[derive(Deserialize, Serialize, JsonSchema, Debug, Clone, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct S7TargetConfig {
    /// `host:port` of the PLC's S7 interface; S7comm uses port 102. Required; at
    /// most 300 characters.
    #[schemars(length(max = 300))]
    pub address: String,
    /// Rack of the PLC CPU. Default 0; 0..=7. Not with `remote_tsap`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(max = 7))]
    pub rack: Option<u8>,
    /// Slot of the PLC CPU. Default 2 (the 840D sl's integrated PLC; an S7-1500 /
    /// SINUMERIK ONE PLC is usually slot 1); 0..=31. Not with `remote_tsap`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(max = 31))]
    pub slot: Option<u8>,
    /// Remote TSAP, instead of rack and slot (e.g. 0x0302). Default: derived from
    /// rack and slot as a PG connection (0x0100 + 32 * rack + slot); 1..=65535.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 1))]
    pub remote_tsap: Option<u16>,
    /// Local TSAP. Default 0x0100; 1..=65535.
    #[serde(default = "default_local_tsap")]
    #[schemars(range(min = 1))]
    pub local_tsap: u16,
    /// Number of the data block that holds the axis blocks. Required; 1..=65535.
    /// The block must be non-optimized ("Optimized block access" off).
    #[schemars(range(min = 1))]
    pub db_number: u16,
    /// Byte offset of axis 1's block in the data block. Default 0; 0..=65535, and the
    /// block must end by byte 65535.
    #[serde(default)]
    pub start_byte: u16,
    /// Bytes from one axis' block to the next: axis `n` starts at
    /// `start_byte + (n - 1) * block_stride_bytes`. Default: the block length (108
    /// for REAL, 176 for LREAL: an array of blocks, as `deploy/plc/` declares it); at
    /// least the block length, at most 65535.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub block_stride_bytes: Option<u16>,
    /// How the block holds values: `real` (32 bit, every S7 PLC) or `lreal` (64 bit,
    /// S7-1500 class). Default `real`.
    #[serde(default = "default_value_type")]
    pub value_type: S7ValueType,
    /// Seconds one S7 request may take. Default 1.0; 0.001..=3600.
    #[serde(default = "default_timeout_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub timeout_s: f64,
    /// Seconds a connect (TCP, ISO and PDU negotiation) may take. Default 2.0;
    /// 0.001..=3600.
    #[serde(default = "default_connect_timeout_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub connect_timeout_s: f64,
    /// Seconds the whole job (the running gateway's check of what the NC holds, REQ ..
    /// DONE/ERROR and the read-back) may take; the PLC program needs a few PLC cycles
    /// plus FB3's time. Default 2.0; 0.001..=3600.
    #[serde(default = "default_job_timeout_s")]
    #[schemars(range(min = 0.001, max = 3600.0))]
    pub job_timeout_s: f64,
}

/// Largest byte offset an S7 read or write of `rust7` can address.
const MAX_BYTE: u32 = u16::MAX as u32;

impl S7TargetConfig {
    /// The block layout of this target.
    pub fn layout(&self) -> S7Layout {
        S7Layout {
            value_type: self.value_type,
        }
    }

    /// Bytes from one axis' block to the next.
    pub fn block_stride_bytes(&self) -> u16 {
        self.block_stride_bytes
            .unwrap_or_else(|| self.layout().block_len())
    }

    /// Start of axis `axis_number`'s block, if it fits in the data block.
    fn block_start(&self, axis_number: u16) -> Option<u16> {
        let start = u32::from(self.start_byte)
            + u32::from(axis_number.checked_sub(1)?) * u32::from(self.block_stride_bytes());
        (start + u32::from(self.layout().block_len()) <= MAX_BYTE)
            .then_some(start)
            .and_then(|s| u16::try_from(s).ok())
    }

    /// The block of axis `axis_number`, if it fits (see [`TargetConfig::places`](super::config::TargetConfig::places)).
    pub fn places(&self, axis_number: u16) -> Option<Place> {
        let start = u64::from(self.block_start(axis_number)?);
        Some(Place {
            area: format!(
                "DB{} of the S7 PLC at {} (remote TSAP {:#06x})",
                self.db_number,
                peer_identity(&self.address),
                self.remote_tsap()
            ),
            bytes: start..start + u64::from(self.layout().block_len()),
        })
    }

    /// Whether the block has a place for variable `var_id`: the three thermal setting
    /// data, the only ones the PLC program of `deploy/plc/` passes to FB3.
    pub fn has(&self, var_id: u16) -> bool {
        matches!(var_id, var::SD43900 | var::SD43910 | var::SD43920)
    }

    /// The remote TSAP: `remote_tsap`, or the PG connection to rack/slot.
    pub fn remote_tsap(&self) -> u16 {
        self.remote_tsap.unwrap_or_else(|| {
            0x0100 + 0x20 * u16::from(self.rack.unwrap_or(0)) + u16::from(self.slot.unwrap_or(2))
        })
    }

    /// `address` is `host:port`, rack/slot or a TSAP, the block fits, times > 0.
    pub fn validate(&self, key: &str, out: &mut Problems<'_>) {
        let k = |f: &str| format!("{key}.{f}");
        out.host_port(&k("address"), &self.address);
        if self.address.rsplit_once(':').is_some_and(|(_, p)| p == "0") {
            out.push(k("address"), "port 0: the PLC's S7 port is 102");
        }
        if let Some(rack) = self.rack.filter(|r| *r > 7) {
            out.push(k("rack"), format!("must be 0..=7 (S7 rack), got {rack}"));
        }
        if let Some(slot) = self.slot.filter(|s| *s > 31) {
            out.push(k("slot"), format!("must be 0..=31 (S7 slot), got {slot}"));
        }
        if self.remote_tsap.is_some() && (self.rack.is_some() || self.slot.is_some()) {
            out.push(
                k("remote_tsap"),
                "give either rack/slot or remote_tsap, not both (the TSAP encodes rack and slot)",
            );
        }
        if self.remote_tsap == Some(0) {
            out.push(k("remote_tsap"), "must be 1..=65535");
        }
        if self.local_tsap == 0 {
            out.push(k("local_tsap"), "must be 1..=65535");
        }
        if self.db_number == 0 {
            out.push(k("db_number"), "must be 1..=65535 (there is no DB0)");
        }
        let len = self.layout().block_len();
        if self.block_stride_bytes() < len {
            out.push(
                k("block_stride_bytes"),
                format!(
                    "must be at least the block length, {len} bytes for value_type = \"{}\", got {}; consecutive axes' blocks would overlap",
                    self.value_type.name(),
                    self.block_stride_bytes()
                ),
            );
        }
        if self.block_start(1).is_none() {
            out.push(
                k("start_byte"),
                format!(
                    "the {len}-byte block from byte {} passes byte {MAX_BYTE}, the last an S7 request can address",
                    self.start_byte
                ),
            );
        }
        out.positive(&k("timeout_s"), self.timeout_s, "seconds");
        out.positive(&k("connect_timeout_s"), self.connect_timeout_s, "seconds");
        out.positive(&k("job_timeout_s"), self.job_timeout_s, "seconds");
    }

    /// Why axis `axis_number`'s block does not fit in the data block.
    fn no_room(&self, axis_number: u16) -> String {
        format!(
            "no room for NC axis {axis_number}'s block in DB{}: axis numbers start at 1, and \
             the block (start_byte {} + (axis_number - 1) * block_stride_bytes {} + {} bytes) \
             must end by byte {MAX_BYTE}, the last an S7 request can address",
            self.db_number,
            self.start_byte,
            self.block_stride_bytes(),
            self.layout().block_len()
        )
    }

    /// Every axis' block fits in the data block, as [`Self::build`] places it; `axes`
    /// are the (name, axis number) of the axes on this target. Distinct axis numbers
    /// and a stride of at least the block length (checked elsewhere) keep the blocks
    /// apart.
    pub fn validate_axes(&self, axes: &[(&str, u16)], out: &mut Problems<'_>) {
        for &(name, number) in axes {
            if self.block_start(number).is_none() {
                out.push(
                    crate::config::keys::field("axes", name, "axis_number"),
                    format!(
                        "{}; lower the axis number, or block_stride_bytes / start_byte of its target",
                        self.no_room(number)
                    ),
                );
            }
        }
    }

    /// The job writer of NC axis `axis_number` (1-based machine axis; its block is
    /// the `axis_number`-th), not connected yet: it connects on first use and
    /// reconnects with a backoff of 0.5 s doubling to 10 s.
    pub fn build(&self, axis_name: &str, axis_number: u16) -> Result<S7NcWriter, NcError> {
        let block = self.block_start(axis_number).ok_or_else(|| {
            NcError::Config(format!("axis {axis_name}: {}", self.no_room(axis_number)))
        })?;
        let (host, port) = self
            .address
            .rsplit_once(':')
            .and_then(|(h, p)| Some((h.to_string(), p.parse::<u16>().ok()?)))
            .filter(|(_, p)| *p != 0)
            .ok_or_else(|| {
                NcError::Config(format!(
                    "address `{}` is not host:port with a port 1..=65535",
                    self.address
                ))
            })?;
        Ok(S7NcWriter {
            spec: Spec {
                host,
                port,
                local_tsap: self.local_tsap,
                remote_tsap: self.remote_tsap(),
                db: self.db_number,
                block,
                layout: self.layout(),
                axis_number,
                timeout: self.timeout(),
                connect_timeout: self.connect_timeout(),
            },
            job_timeout: self.job_timeout(),
            client: None,
            backoff: Backoff::new(Duration::from_millis(500), Duration::from_secs(10)),
            connect_error: None,
            job_ids: JobIds::default(),
            connects: 0,
        })
    }

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
}

fn default_local_tsap() -> u16 {
    0x0100
}
fn default_value_type() -> S7ValueType {
    S7ValueType::Real
}
fn default_timeout_s() -> f64 {
    1.0
}
fn default_connect_timeout_s() -> f64 {
    2.0
}
fn default_job_timeout_s() -> f64 {
    2.0
}

/// What the blocking side needs to reach one axis' block.
#[derive(Debug, Clone)]
struct Spec {
    host: String,
    port: u16,
    local_tsap: u16,
    remote_tsap: u16,
    db: u16,
    /// Byte offset of the axis' block in the DB.
    block: u16,
    layout: S7Layout,
    axis_number: u16,
    timeout: Duration,
    connect_timeout: Duration,
}

/// FB3-style job client writing one axis' block of a PLC data block over S7comm.
pub struct S7NcWriter {
    spec: Spec,
    job_timeout: Duration,
    /// None while disconnected, and while a blocking call holds it.
    client: Option<S7Client>,
    backoff: Backoff,
    /// Why the last connect failed, named while the backoff waits.
    connect_error: Option<SourceError>,
    job_ids: JobIds,
    connects: u64,
}

impl std::fmt::Debug for S7NcWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("S7NcWriter")
            .field(
                "address",
                &format_args!("{}:{}", self.spec.host, self.spec.port),
            )
            .field("db", &self.spec.db)
            .field("block", &self.spec.block)
            .field("connected", &self.client.is_some())
            .field("connects", &self.connects)
            .finish()
    }
}

/// What one blocking call reports besides its result.
struct Outcome<T> {
    client: Option<S7Client>,
    /// A connect was tried: `Some(true)` it succeeded, `Some(false)` it failed.
    connected: Option<bool>,
    result: Result<T, NcError>,
}

impl S7NcWriter {
    /// Successful connects so far.
    pub fn connects(&self) -> u64 {
        self.connects
    }

    /// True while a connection is held.
    pub fn is_connected(&self) -> bool {
        self.client.is_some()
    }

    /// How the block holds the values (REAL: the read-back is checked to one float32
    /// ulp).
    pub fn value_type(&self) -> S7ValueType {
        self.spec.layout.value_type
    }

    /// Runs `op` on the blocking pool with a connected client, giving up (and the
    /// client with it) at `deadline`.
    async fn blocking<T: Send + 'static>(
        &mut self,
        deadline: Instant,
        op: impl FnOnce(&Spec, &mut S7Client) -> Result<T, NcError> + Send + 'static,
    ) -> Option<Result<T, NcError>> {
        if self.client.is_none() {
            if let Some(wait) = self.backoff.remaining(Instant::now()) {
                let error = match &self.connect_error {
                    Some(cause) => SourceError::BackingOffAfter {
                        cause: Box::new(cause.clone()),
                        next_attempt_in: wait,
                    },
                    None => SourceError::BackingOff(wait),
                };
                return Some(Err(NcError::Link(error)));
            }
        }
        let spec = self.spec.clone();
        let client = self.client.take();
        let task = tokio::task::spawn_blocking(move || run_blocking(&spec, client, op));
        let outcome = match tokio::time::timeout_at(deadline, task).await {
            Ok(Ok(o)) => o,
            Ok(Err(join)) => {
                return Some(Err(NcError::Protocol(format!(
                    "S7 client thread failed: {join}"
                ))))
            }
            // The task keeps the client and drops it when it ends: the next call
            // connects anew.
            Err(_) => return None,
        };
        match outcome.connected {
            Some(true) => {
                self.connects += 1;
                self.backoff.reset();
                self.connect_error = None;
            }
            Some(false) => {
                self.backoff.failed(Instant::now());
                if let Err(NcError::Link(e)) = &outcome.result {
                    self.connect_error = Some(e.clone());
                }
            }
            None => {}
        }
        self.client = outcome.client;
        Some(outcome.result)
    }
}

/// Connects if needed, runs `op`, and keeps the client only if the link is sound.
fn run_blocking<T>(
    spec: &Spec,
    client: Option<S7Client>,
    op: impl FnOnce(&Spec, &mut S7Client) -> Result<T, NcError>,
) -> Outcome<T> {
    let (mut client, connected) = match client {
        Some(c) => (c, None),
        None => match connect(spec) {
            Ok(c) => (c, Some(true)),
            Err(e) => {
                return Outcome {
                    client: None,
                    connected: Some(false),
                    result: Err(e),
                }
            }
        },
    };
    let result = op(spec, &mut client);
    // After a transport fault the stream may hold a late or partial reply. A job
    // timeout seen here fell between two requests: the stream is clean.
    let keep = !matches!(result, Err(NcError::Link(_)));
    if !keep {
        client.disconnect();
    }
    Outcome {
        client: keep.then_some(client),
        connected,
        result,
    }
}

fn millis(d: Duration) -> u64 {
    u64::try_from(d.as_millis()).unwrap_or(u64::MAX).max(1)
}

fn connect(spec: &Spec) -> Result<S7Client, NcError> {
    let mut c = S7Client::new();
    let fail = |e: S7Error| {
        NcError::Link(match e {
            S7Error::Io(ref io) if is_timeout(io) => SourceError::ConnectTimeout,
            S7Error::IsoConnectionFailed => SourceError::Connect(format!(
                "{}:{}: the PLC refused the ISO connection (check rack/slot or remote_tsap {:#06x})",
                spec.host, spec.port, spec.remote_tsap
            )),
            e => SourceError::Connect(format!("{}:{}: {e}", spec.host, spec.port)),
        })
    };
    c.set_connection_port(spec.port).map_err(fail)?;
    let t = millis(spec.timeout);
    c.set_timeout(millis(spec.connect_timeout), t, t)
        .map_err(fail)?;
    c.connect_tsap(&spec.host, spec.local_tsap, spec.remote_tsap)
        .map_err(fail)?;
    Ok(c)
}

fn is_timeout(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
    )
}

/// An S7 request's failure: block-level refusals name the block, the rest is the link.
fn s7_error(spec: &Spec, start: u16, len: usize, e: S7Error) -> NcError {
    let end = usize::from(start) + len;
    match e {
        S7Error::S7NotFound => NcError::Protocol(format!(
            "DB{} does not exist in the PLC (db_number)",
            spec.db
        )),
        // A REAL block read with value_type = "lreal", or an axis_number beyond the
        // block's axes, ends here too: name both keys, not only the block.
        S7Error::S7InvalidAddress => NcError::Protocol(format!(
            "DB{} bytes {start}..{end}: invalid address: the block is shorter than axis_number {} of the layout with value_type = \"{}\" (a REAL block read as LREAL? an axis number the block does not have?), or optimized: switch \"Optimized block access\" off",
            spec.db,
            spec.axis_number,
            spec.layout.value_type.name()
        )),
        S7Error::Io(ref io) if is_timeout(io) => NcError::Link(SourceError::Timeout(spec.timeout)),
        e => NcError::Link(SourceError::Transport(e.to_string())),
    }
}

fn write(spec: &Spec, c: &mut S7Client, offset: u16, bytes: &[u8]) -> Result<(), NcError> {
    let start = spec.block + offset;
    c.write_db(spec.db, start, bytes)
        .map_err(|e| s7_error(spec, start, bytes.len(), e))
}

/// What the PLC shows: `STATE` .. the end of the read-back.
struct PlcArea {
    layout: S7Layout,
    db: u16,
    /// Byte offset of the axis' block in the DB.
    block: u16,
    base: u16,
    bytes: Vec<u8>,
}

impl PlcArea {
    fn read(spec: &Spec, c: &mut S7Client) -> Result<Self, NcError> {
        let base = spec.layout.state();
        let mut bytes = vec![0u8; usize::from(spec.layout.block_len() - base)];
        let start = spec.block + base;
        c.read_db(spec.db, start, &mut bytes)
            .map_err(|e| s7_error(spec, start, bytes.len(), e))?;
        Ok(Self {
            layout: spec.layout,
            db: spec.db,
            block: spec.block,
            base,
            bytes,
        })
    }

    fn word(&self, offset: u16) -> u16 {
        let i = usize::from(offset - self.base);
        u16::from_be_bytes([self.bytes[i], self.bytes[i + 1]])
    }

    /// Read-back `k` as the block holds it (f32 widened for REAL).
    fn value(&self, k: u16) -> f64 {
        let i = usize::from(self.layout.readback(k) - self.base);
        let b = &self.bytes[i..];
        match self.layout.value_type {
            S7ValueType::Real => f64::from(f32::from_be_bytes([b[0], b[1], b[2], b[3]])),
            S7ValueType::Lreal => {
                f64::from_be_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]])
            }
        }
    }

    /// The block at `offset` (from the axis' block start) does not hold what the
    /// configured layout puts there.
    fn implausible(&self, offset: u16, what: &str) -> NcError {
        let vt = self.layout.value_type;
        NcError::Implausible(format!(
            "DB{} byte {} ({what}): the block does not look like the layout of value_type = \"{}\" \
             (a {}-byte block per axis, STATE at byte {} of it); the likely cause is value_type \
             (REAL or LREAL in the PLC's block), else start_byte or block_stride_bytes; \
             nothing was written",
            self.db,
            self.block + offset,
            vt.name(),
            self.layout.block_len(),
            self.layout.state()
        ))
    }

    fn state(&self) -> Result<JobState, NcError> {
        let at = self.layout.state();
        let v = self.word(at);
        JobState::from_u16(v)
            .ok_or_else(|| self.implausible(at, &format!("STATE = {v}, not a job state 0..=3")))
    }

    /// Whether the PLC's part of the block looks like the configured layout: STATE a
    /// job state, MD32750 a bit field 0..=7, REFERENCED 0 or 1, every read-back value
    /// finite and not subnormal, the setting data within the NC's limits. A REAL block
    /// read as LREAL (or the other way round) fails this in most states.
    fn check(&self) -> Result<(), NcError> {
        self.state()?;
        let l = self.layout;
        let md32750 = self.word(l.md32750());
        if md32750 > 7 {
            return Err(self.implausible(
                l.md32750(),
                &format!("MD32750 = {md32750}, not a bit field 0..=7"),
            ));
        }
        let referenced = self.word(l.referenced());
        if referenced > 1 {
            return Err(self.implausible(
                l.referenced(),
                &format!("REFERENCED = {referenced}, not 0 or 1"),
            ));
        }
        let ids = [var::SD43900, var::SD43910, var::SD43920];
        for (k, name) in S7Layout::READBACK_VARS.iter().enumerate() {
            let k = k as u16;
            let var_id = ids.get(usize::from(k)).copied().unwrap_or(0);
            let x = self.value(k);
            if let Some(why) = l.value_type.precision().implausible(var_id, x) {
                return Err(self.implausible(
                    l.readback(k),
                    &format!("{name} = {}, {why}", super::number(x)),
                ));
            }
        }
        Ok(())
    }

    fn snapshot(&self) -> NcSnapshot {
        NcSnapshot {
            sd43900_mm: self.value(0),
            sd43910: self.value(1),
            sd43920_mm: self.value(2),
            md32760: self.value(3),
            max_ax_velo_mm_per_min: self.value(4),
            md32450_mm: self.value(5),
            position_mm: Some(self.value(6)),
            // RbApplied and RbTarget: the FB3 program of deploy/plc/ leaves them 0, and
            // a 0 there read as "the NC applies no compensation" (an export of a
            // compensated recording said so).
            applied_comp_mm: None,
            target_comp_mm: None,
            md32750: Some(self.word(self.layout.md32750())),
            referenced: Some(self.word(self.layout.referenced()) != 0),
        }
    }
}

/// The value as the block encodes it; `None` when REAL cannot hold it.
fn encode(value_type: S7ValueType, v: f64) -> Option<Vec<u8>> {
    match value_type {
        S7ValueType::Real => {
            let f = v as f32;
            (f.is_finite() == v.is_finite()).then(|| f.to_be_bytes().to_vec())
        }
        S7ValueType::Lreal => Some(v.to_be_bytes().to_vec()),
    }
}

/// The PC part of the block: `JOB_ID` .. `VALUE[8]`.
fn job_bytes(spec: &Spec, job: &Job, job_id: u16) -> Result<Vec<u8>, NcError> {
    let layout = spec.layout;
    let mut b = vec![0u8; usize::from(layout.state() - S7Layout::JOB_ID)];
    let at = |off: u16| usize::from(off - S7Layout::JOB_ID);
    let put = |b: &mut Vec<u8>, off: u16, bytes: &[u8]| {
        b[at(off)..at(off) + bytes.len()].copy_from_slice(bytes);
    };
    put(&mut b, S7Layout::JOB_ID, &job_id.to_be_bytes());
    put(&mut b, S7Layout::AXIS, &spec.axis_number.to_be_bytes());
    put(
        &mut b,
        S7Layout::NUM_PAIRS,
        &(job.pairs.len() as u16).to_be_bytes(),
    );
    let size = layout.value_type.size();
    for (i, (var_id, value)) in job.pairs.iter().enumerate() {
        let i = i as u16;
        put(&mut b, S7Layout::VAR_IDS + 2 * i, &var_id.to_be_bytes());
        let enc = encode(layout.value_type, *value).ok_or_else(|| {
            NcError::InvalidJob(format!(
                "{} = {} does not fit a REAL",
                super::var_name(*var_id),
                super::number(*value)
            ))
        })?;
        put(&mut b, S7Layout::VALUES + size * i, &enc);
    }
    Ok(b)
}

/// Polls the block until `done(state)` or the deadline; the PLC program answers
/// within a few PLC cycles. `sent`: whether REQ was set (for the timeout's message).
fn wait_state(
    spec: &Spec,
    c: &mut S7Client,
    deadline: std::time::Instant,
    timeout: Duration,
    (job_id, sent): (u16, bool),
    done: impl Fn(JobState) -> bool,
) -> Result<PlcArea, NcError> {
    loop {
        let area = PlcArea::read(spec, c)?;
        let s = area.state()?;
        if done(s) {
            return Ok(area);
        }
        if std::time::Instant::now() >= deadline {
            return Err(NcError::JobTimeout {
                job_id,
                timeout,
                state: Some(s),
                sent,
            });
        }
        std::thread::sleep(Duration::from_millis(1));
    }
}

fn run_job(
    spec: &Spec,
    c: &mut S7Client,
    job: &Job,
    job_id: u16,
    deadline: std::time::Instant,
    timeout: Duration,
) -> Result<(), NcError> {
    let payload = job_bytes(spec, job, job_id)?;
    // Nothing goes into a block that does not look like the configured layout: with
    // the wrong value_type the PLC would read the job at other offsets.
    let area = PlcArea::read(spec, c)?;
    area.check()?;
    // A job left unacknowledged by an earlier run (crash, timeout) is cleared first;
    // a busy PLC program is waited for, never interrupted.
    if area.state()? != JobState::Idle {
        write(spec, c, S7Layout::REQ, &0u16.to_be_bytes())?;
        wait_state(spec, c, deadline, timeout, (job_id, false), |s| {
            s == JobState::Idle
        })?;
    }
    write(spec, c, S7Layout::JOB_ID, &payload)?;
    write(spec, c, S7Layout::REQ, &1u16.to_be_bytes())?;
    let area = wait_state(spec, c, deadline, timeout, (job_id, true), |s| {
        matches!(s, JobState::Done | JobState::Error)
    })?;
    // Acknowledge before judging, so the PLC program is idle whatever happens next.
    write(spec, c, S7Layout::REQ, &0u16.to_be_bytes())?;
    let l = spec.layout;
    let done_id = area.word(l.job_id_done());
    if done_id != job_id {
        return Err(NcError::Protocol(format!(
            "JOB_ID_DONE = {done_id}, expected {job_id}"
        )));
    }
    let code = area.word(l.status());
    let fb3 = area.word(l.fb3_state());
    let status = JobStatus::from_u16(code)
        .ok_or_else(|| NcError::Protocol(format!("STATUS = {code} (FB3 State W#16#{fb3:04X})")))?;
    let index = area.word(l.error_index());
    match (area.state()?, status) {
        (JobState::Error, JobStatus::Ok) => Err(NcError::Protocol(format!(
            "ERROR with STATUS 0 (FB3 State W#16#{fb3:04X}, pair {index})"
        ))),
        (_, JobStatus::Ok) => Ok(()),
        (_, status) => {
            if fb3 != 0 {
                tracing::warn!(job_id, fb3_state = %format_args!("W#16#{fb3:04X}"), "FB3 PUT refused the job");
            }
            Err(NcError::Refused {
                job_id,
                status,
                index,
                var: job.var_at(index),
            })
        }
    }
}

impl NcWriter for S7NcWriter {
    async fn write_job(&mut self, job: &Job) -> Result<JobReport, NcError> {
        job.check_pair_count()?;
        let job_id = self.job_ids.issue();
        let started = Instant::now();
        let deadline = started + self.job_timeout;
        let timeout = self.job_timeout;
        let std_deadline = std::time::Instant::now() + timeout;
        let job = job.clone();
        // The blocking side stops polling at the deadline itself and reports the last
        // STATE; the grace lets that answer arrive before the outer cut-off.
        let outer = deadline + Duration::from_millis(100).min(self.spec.timeout);
        let r = self
            .blocking(outer, move |spec, c| {
                run_job(spec, c, &job, job_id, std_deadline, timeout)
            })
            .await;
        match r {
            Some(Ok(())) => Ok(JobReport {
                job_id,
                elapsed: started.elapsed(),
            }),
            Some(Err(e)) => Err(e),
            None => Err(NcError::JobTimeout {
                job_id,
                timeout,
                state: None,
                sent: true,
            }),
        }
    }

    async fn read_snapshot(&mut self) -> Result<NcSnapshot, NcError> {
        // Connect (TCP, ISO and PDU negotiation) plus one read, each bounded by the
        // client's own socket timeouts.
        let deadline = Instant::now() + self.spec.connect_timeout + 3 * self.spec.timeout;
        let r = self
            .blocking(deadline, |spec, c| {
                let area = PlcArea::read(spec, c)?;
                area.check()?;
                Ok(area.snapshot())
            })
            .await;
        r.unwrap_or(Err(NcError::Link(SourceError::Timeout(self.spec.timeout))))
    }

    fn precision(&self) -> Precision {
        self.spec.layout.value_type.precision()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg(toml_text: &str) -> S7TargetConfig {
        toml::from_str(toml_text).expect("valid S7 target config")
    }

    fn problems(c: &S7TargetConfig) -> Vec<String> {
        let mut p = Problems::new("t.toml");
        c.validate("targets.plc", &mut p);
        p.into_vec().iter().map(|p| p.to_string()).collect()
    }

    #[test]
    fn layout_offsets_match_the_documented_table() {
        let real = S7Layout {
            value_type: S7ValueType::Real,
        };
        assert_eq!(
            (
                real.state(),
                real.status(),
                real.job_id_done(),
                real.fb3_state()
            ),
            (56, 58, 62, 64)
        );
        assert_eq!((real.readback(0), real.block_len()), (72, 108));
        let lreal = S7Layout {
            value_type: S7ValueType::Lreal,
        };
        assert_eq!(
            (lreal.state(), lreal.readback(0), lreal.block_len()),
            (88, 104, 176)
        );
    }

    #[test]
    fn defaults_and_tsap() {
        let c = cfg("address = \"10.0.0.5:102\"\ndb_number = 120");
        assert!(problems(&c).is_empty(), "{:?}", problems(&c));
        assert_eq!(c.value_type, S7ValueType::Real);
        assert_eq!(c.remote_tsap(), 0x0102);
        let c = cfg("address = \"plc:102\"\ndb_number = 1\nrack = 1\nslot = 3");
        assert_eq!(c.remote_tsap(), 0x0123);
        let c = cfg("address = \"plc:102\"\ndb_number = 1\nremote_tsap = 0x0302");
        assert_eq!(c.remote_tsap(), 0x0302);
    }

    #[test]
    fn validate_names_the_key_at_fault() {
        let c = cfg(
            "address = \"plc:0\"\ndb_number = 0\nrack = 9\nslot = 1\nremote_tsap = 0x0302\nblock_stride_bytes = 100\nstart_byte = 65500\njob_timeout_s = 0.0",
        );
        let p = problems(&c).join("\n");
        for key in [
            "targets.plc.address",
            "targets.plc.rack",
            "targets.plc.remote_tsap",
            "targets.plc.db_number",
            "targets.plc.block_stride_bytes",
            "targets.plc.start_byte",
            "targets.plc.job_timeout_s",
        ] {
            assert!(p.contains(key), "{key} missing from:\n{p}");
        }
        let lreal = cfg("address = \"plc:102\"\ndb_number = 5\nvalue_type = \"lreal\"\nblock_stride_bytes = 150");
        let p = problems(&lreal).join("\n");
        assert!(p.contains("176 bytes"), "{p}");
    }

    #[test]
    fn unknown_keys_and_kind_are_refused() {
        let e =
            toml::from_str::<S7TargetConfig>("address = \"plc:102\"\ndb_number = 5\nkind = \"s7\"")
                .expect_err("kind is the enclosing enum's tag, not a key of this struct");
        assert!(e.to_string().contains("kind"), "{e}");
    }

    #[test]
    fn build_places_each_axis_block_and_refuses_what_does_not_fit() {
        let c = cfg("address = \"127.0.0.1:1102\"\ndb_number = 100\nstart_byte = 16");
        let w = c.build("X1", 3).expect("axis 3 fits");
        assert_eq!(w.spec.block, 16 + 2 * 108);
        assert_eq!((w.spec.host.as_str(), w.spec.port), ("127.0.0.1", 1102));
        let e = c.build("X1", 0).expect_err("axis numbers start at 1");
        assert!(e.to_string().contains("axis X1"), "{e}");
        let e = c.build("Z9", 700).expect_err("past byte 65535");
        assert!(e.to_string().contains("DB100"), "{e}");
    }

    #[test]
    fn real_read_back_allows_one_ulp_and_no_more() {
        let v = 0.012_345_678_9_f64;
        let f = v as f32;
        let next = f32::from_bits(f.to_bits() + 1);
        let two = f32::from_bits(f.to_bits() + 2);
        let read_back_ok =
            |t: S7ValueType, written: f64, read: f64| t.precision().holds(written, read);
        assert!(read_back_ok(S7ValueType::Real, v, f64::from(f)));
        assert!(read_back_ok(S7ValueType::Real, v, f64::from(next)));
        assert!(!read_back_ok(S7ValueType::Real, v, f64::from(two)));
        // Across zero: -0.0 and +0.0 are the same point of the ordered image.
        assert!(read_back_ok(S7ValueType::Real, 0.0, -0.0));
        assert!(!read_back_ok(S7ValueType::Lreal, v, f64::from(f)));
        assert!(read_back_ok(S7ValueType::Lreal, v, v));
    }

    #[test]
    fn job_bytes_are_big_endian_at_the_documented_offsets() {
        let c = cfg("address = \"127.0.0.1:1102\"\ndb_number = 100\nvalue_type = \"lreal\"");
        let w = c.build("X1", 2).expect("fits");
        let job = Job {
            pairs: vec![(var::SD43900, 0.5), (var::SD43920, -12.25)],
        };
        let b = job_bytes(&w.spec, &job, 0x1234).expect("encodes");
        assert_eq!(&b[0..8], &[0x12, 0x34, 0, 2, 0, 2, 0xAB, 0x7C]);
        assert_eq!(&b[8..10], &43920u16.to_be_bytes());
        assert_eq!(&b[22..30], &0.5f64.to_be_bytes());
        assert_eq!(&b[30..38], &(-12.25f64).to_be_bytes());
        let real = cfg("address = \"127.0.0.1:1102\"\ndb_number = 100")
            .build("X1", 1)
            .expect("fits");
        let e = job_bytes(
            &real.spec,
            &Job {
                pairs: vec![(var::SD43900, 1e300)],
            },
            1,
        )
        .expect_err("1e300 is no REAL");
        assert!(e.to_string().contains("REAL"), "{e}");
    }
}
