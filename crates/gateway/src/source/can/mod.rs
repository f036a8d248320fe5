//! CAN source: CANopen nodes on a SocketCAN interface (`can0`, `vcan0`, ...).
//!
//! One SYNC producer per interface ([`sync`]) sends SYNC on a fixed-rate timer at the
//! interface's poll interval, on a socket of its own, so no poll cycle can stretch
//! the SYNC period.
//!
//! One [`CanPoller`] per configured node, with its own raw CAN socket filtered to the
//! node's COB-IDs and the SYNC, and a reader task that timestamps every frame as it
//! arrives. The kernel loops the producer's SYNC back to every other socket on the
//! interface, so each poller sees SYNCs and TPDOs in bus order. One poll cycle:
//!
//! 1. takes the frames received since the last cycle (SYNCs, heartbeats, EMCY,
//!    TPDOs);
//! 2. sends NMT start when the node is new, booted or pre-operational;
//! 3. reads the mapped synchronous TPDOs that followed the newest SYNC; those not
//!    there yet (the SYNC has just gone out) are waited for up to the timeout, as is
//!    a SYNC when none has come for two periods (then the PDO channels fail with
//!    [`CanError::NoSync`]); event-driven TPDOs (`tpdo_max_age`) are read as the
//!    newest frame instead, without a wait, and fail when it is too old;
//! 4. uploads every SDO channel's object (expedited, one at a time; a timed-out or
//!    segmented upload is aborted, so the server is free for the next one);
//! 5. checks the heartbeat consumer and the EMCY state: a silent node or an
//!    unreset emergency makes every channel of the node bad.
//!
//! The frame codec ([`codec`]), the bookkeeping ([`node`]) and the SYNC plan
//! ([`sync::plan`]) are pure and tested without a kernel; this file and the producer
//! task hold the socket side.

pub mod codec;
pub mod config;
pub mod node;
pub mod sync;

use std::sync::Arc;
use std::time::Duration;

use socketcan::tokio::CanSocket;
use socketcan::{CanFilter, CanFrame, EmbeddedFrame, Id, SocketOptions, StandardId};
use tokio::sync::mpsc;
use tokio::time::Instant;

use super::{DeviceSample, Fault, SourceError};
use crate::source::plan::DataType;
use codec::{Message, NmtCommand, NmtState, RawFrame};
use compgate_core::channel::Reason;
use node::{NodeEvent, NodeFault, NodeMonitor, PdoStore, SdoClient, SdoFailure};

/// Errors of the CAN source.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CanError {
    /// The interface cannot be opened, or a frame cannot be sent.
    #[error("CAN interface {interface}: {message}")]
    Socket {
        /// Interface name.
        interface: String,
        /// What failed.
        message: String,
    },
    /// A mapped TPDO did not arrive after the newest SYNC.
    #[error("node {node}: TPDO{pdo} not received within {timeout:?} of the SYNC{}", pdo_hint(*state, *pdo, *last_s_ago))]
    PdoTimeout {
        /// Node id.
        node: u8,
        /// PDO number.
        pdo: u8,
        /// Wait.
        timeout: Duration,
        /// The NMT state of the node's last heartbeat: a node not operational sends
        /// no PDO, which the message must say.
        state: Option<NmtState>,
        /// How long before the wait ended the node's last frame of this TPDO came, if
        /// one came: a node that sends it event-driven shows up so.
        last_s_ago: Option<f64>,
    },
    /// An event-driven TPDO (`tpdo_max_age_s`) is older than its allowed age.
    #[error(
        "node {node}: TPDO{pdo} {} (tpdo_max_age_s = {}){}",
        match age_s { Some(a) => format!("not received for {a:.2}s"), None => "never received".into() },
        max_age.as_secs_f64(),
        not_operational(*state)
    )]
    PdoStale {
        /// Node id.
        node: u8,
        /// PDO number.
        pdo: u8,
        /// Age of its newest frame, s; `None` if none came yet.
        age_s: Option<f64>,
        /// The allowed age.
        max_age: Duration,
        /// The NMT state of the node's last heartbeat.
        state: Option<NmtState>,
    },
    /// No SYNC on the interface for longer than two SYNC periods: the producer
    /// cannot send (interface down, transmit queue full) or has stopped.
    #[error("CAN interface {interface}: no SYNC for more than {max_age:?}")]
    NoSync {
        /// Interface name.
        interface: String,
        /// The age after which the newest SYNC no longer counts.
        max_age: Duration,
    },
    /// A TPDO is shorter than its mapping.
    #[error("node {node}: TPDO{pdo}: {error}")]
    Pdo {
        /// Node id.
        node: u8,
        /// PDO number.
        pdo: u8,
        /// What does not fit.
        error: codec::CodecError,
    },
    /// An SDO upload failed.
    #[error("node {node}: SDO upload {index:04X}h sub {sub}: {what}")]
    Sdo {
        /// Node id.
        node: u8,
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The abort code by name, timeout, ...
        what: String,
        /// The abort code, if the server aborted.
        abort_code: Option<u32>,
    },
    /// No heartbeat for longer than the consumer timeout.
    #[error("node {node}: heartbeat timeout, silent for {silent_s:.2} s (timeout {timeout_s} s){}",
        ignored.as_ref().map(|m| format!("; ignored {m}")).unwrap_or_default())]
    HeartbeatTimeout {
        /// Node id.
        node: u8,
        /// Seconds without heartbeat.
        silent_s: f64,
        /// Configured timeout.
        timeout_s: f64,
        /// A malformed frame on the node's heartbeat COB-ID, with what is wrong: a
        /// node sending those is not silent.
        ignored: Option<String>,
    },
    /// The node sent an EMCY that no error reset has cleared.
    #[error("node {node}: EMCY {code:04X}h ({class}), error register {register:02X}h")]
    Emergency {
        /// Node id.
        node: u8,
        /// EMCY error code.
        code: u16,
        /// Error class in words.
        class: &'static str,
        /// Error register.
        register: u8,
    },
}

/// Whether `interface` is administratively up (IFF_UP in its sysfs flags); `true`
/// where that cannot be read, so an unusual system is not locked out.
fn interface_up(interface: &str) -> bool {
    const IFF_UP: u32 = 0x1;
    std::fs::read_to_string(format!("/sys/class/net/{interface}/flags"))
        .ok()
        .and_then(|f| u32::from_str_radix(f.trim().trim_start_matches("0x"), 16).ok())
        .is_none_or(|flags| flags & IFF_UP != 0)
}

/// Why a node sends no PDO, from its last heartbeat's state; empty when it is
/// operational or unknown.
fn not_operational(state: Option<NmtState>) -> &'static str {
    match state {
        Some(NmtState::Stopped) => {
            "; its heartbeat says stopped (an NMT stop from another master?): \
             it sends PDOs again after an NMT start"
        }
        Some(NmtState::PreOperational | NmtState::BootUp) => {
            "; its heartbeat says pre-operational: the gateway has sent it an NMT start"
        }
        Some(NmtState::Operational) | None => "",
    }
}

/// Why a synchronous TPDO may be missing: the node is not operational, or it sends
/// that TPDO, only not after each SYNC.
fn pdo_hint(state: Option<NmtState>, pdo: u8, last_s_ago: Option<f64>) -> String {
    match (not_operational(state), last_s_ago) {
        ("", Some(ago)) => format!(
            "; the last one came {ago:.2}s before: if the node sends it on its event timer \
             (transmission type 254 or 255 in {:04X}h sub 2), set tpdo_max_age_s",
            0x1800 + u16::from(pdo) - 1
        ),
        (hint, _) => hint.to_string(),
    }
}

impl CanError {
    /// Short kind name, for counters and status.
    pub fn kind(&self) -> &'static str {
        match self {
            Self::Socket { .. } => "can socket",
            Self::PdoTimeout { .. } | Self::PdoStale { .. } | Self::Pdo { .. } => "can pdo",
            Self::NoSync { .. } => "can sync",
            Self::Sdo { .. } => "can sdo",
            Self::HeartbeatTimeout { .. } => "can heartbeat",
            Self::Emergency { .. } => "can emcy",
        }
    }
}

/// Where one channel's value sits on its node.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CanObject {
    /// In synchronous TPDO `pdo` (1..=4) at byte `offset_bytes`.
    Pdo {
        /// PDO number.
        pdo: u8,
        /// Byte offset in the PDO.
        offset_bytes: u8,
    },
    /// Object `index`/`sub`, read by expedited SDO upload.
    Sdo {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
    },
}

/// One channel of a CAN node.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CanChannelSpec {
    /// Index of the channel in the gateway.
    pub channel: usize,
    /// Where its value is.
    pub object: CanObject,
    /// Encoding (little-endian, as CANopen sends it).
    pub data_type: DataType,
}

/// Parameters of one CAN node's poller.
#[derive(Debug, Clone)]
pub struct CanParams {
    /// SocketCAN interface.
    pub interface: String,
    /// CANopen node id 1..=127.
    pub node_id: u8,
    /// Longest wait for TPDOs after SYNC and for each SDO answer.
    pub timeout: Duration,
    /// Heartbeat consumer timeout (zero = off).
    pub heartbeat_timeout: Duration,
    /// The interface's SYNC period (its producer is [`sync::run`]); a SYNC older than
    /// [`sync::max_age`] of it no longer counts.
    pub sync_period: Duration,
    /// Failed cycles in a row after which the node counts as degraded.
    pub degrade_after_cycles: u32,
    /// `None`: synchronous TPDOs, read after the newest SYNC. `Some(age)`:
    /// event-driven TPDOs (the node's event timer or change of state), read as the
    /// newest frame received within `age`.
    pub tpdo_max_age: Option<Duration>,
}

/// Receive buffer asked for on each node's socket (the kernel doubles it for its
/// bookkeeping); about 1 s of a saturated 1 Mbit/s bus.
pub const RECEIVE_BUFFER_BYTES: std::ffi::c_int = 1 << 20;

/// A frame as the reader task got it.
type Received = (Instant, RawFrame);

struct Link {
    socket: Arc<CanSocket>,
    /// Frames, then the receive error that ended the reader, if one did.
    rx: mpsc::UnboundedReceiver<Result<Received, std::io::Error>>,
    reader: tokio::task::JoinHandle<()>,
}

impl Drop for Link {
    fn drop(&mut self) {
        self.reader.abort();
    }
}

impl std::fmt::Debug for Link {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Link")
    }
}

/// Converts a received socketcan frame: classic data frames with 11-bit ids only.
pub fn from_socketcan(frame: &CanFrame) -> Option<RawFrame> {
    match frame {
        CanFrame::Data(_) => match frame.id() {
            Id::Standard(id) => RawFrame::new(id.as_raw(), frame.data()),
            Id::Extended(_) => None,
        },
        _ => None,
    }
}

/// Converts a frame to send.
pub fn to_socketcan(frame: &RawFrame) -> Option<CanFrame> {
    CanFrame::new(StandardId::new(frame.cob_id)?, frame.data())
}

/// Polls one CANopen node.
#[derive(Debug)]
pub struct CanPoller {
    index: usize,
    name: String,
    params: CanParams,
    specs: Vec<CanChannelSpec>,
    link: Option<Link>,
    epoch: Instant,
    monitor: NodeMonitor,
    sdo: SdoClient,
    pdos: PdoStore,
    needs_start: bool,
    /// A malformed frame on the node's SDO answer COB-ID during the current upload,
    /// with what is wrong: a node answering so must not read as one not answering.
    malformed_sdo: Option<String>,
    /// The last malformed frame on the node's heartbeat COB-ID since its last valid
    /// heartbeat.
    malformed_heartbeat: Option<String>,
    failed_cycles: u32,
    opens: u64,
    frames: u64,
}

impl CanPoller {
    /// A poller for device `index` named `name`.
    pub fn new(index: usize, name: String, params: CanParams, specs: Vec<CanChannelSpec>) -> Self {
        let epoch = Instant::now();
        Self {
            index,
            name,
            monitor: NodeMonitor::new(params.node_id, params.heartbeat_timeout.as_secs_f64(), 0.0),
            sdo: SdoClient::new(params.node_id),
            pdos: PdoStore::default(),
            params,
            specs,
            link: None,
            epoch,
            needs_start: true,
            malformed_sdo: None,
            malformed_heartbeat: None,
            failed_cycles: 0,
            opens: 0,
            frames: 0,
        }
    }

    /// Device name from the config.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// `can:IFACE node N` for the status line.
    pub fn describe(&self) -> String {
        format!("can:{} node {}", self.params.interface, self.params.node_id)
    }

    /// Frames received from the node so far.
    pub fn frames_received(&self) -> u64 {
        self.frames
    }

    /// TPDOs received from the node so far.
    pub fn pdos_received(&self) -> u64 {
        self.pdos.received()
    }

    fn t_s(&self, at: Instant) -> f64 {
        at.saturating_duration_since(self.epoch).as_secs_f64()
    }

    fn socket_error(&self, message: impl std::fmt::Display) -> CanError {
        CanError::Socket {
            interface: self.params.interface.clone(),
            message: message.to_string(),
        }
    }

    fn open(&mut self) -> Result<(), CanError> {
        let socket = CanSocket::open(&self.params.interface).map_err(|e| self.socket_error(e))?;
        let n = u32::from(self.params.node_id);
        // The bus' SYNC, and only this node's EMCY, TPDOs, SDO answers and heartbeats.
        let filters: Vec<CanFilter> = [0x080, 0x180, 0x280, 0x380, 0x480, 0x580, 0x700]
            .iter()
            .map(|base| CanFilter::new(base + n, 0x7FF))
            .chain([CanFilter::new(u32::from(codec::SYNC_COB_ID), 0x7FF)])
            .collect();
        socket
            .set_filters(&filters)
            .map_err(|e| self.socket_error(format!("set filters: {e}")))?;
        // A deep receive queue absorbs bursts (every TPDO of the bus right after a
        // SYNC) while the reader task waits for a CPU. Beyond the kernel's rmem_max
        // this needs CAP_NET_ADMIN (SO_RCVBUFFORCE); otherwise the kernel caps it.
        const SOL_SOCKET: std::ffi::c_int = 1;
        const SO_RCVBUF: std::ffi::c_int = 8;
        const SO_RCVBUFFORCE: std::ffi::c_int = 33;
        let bytes = RECEIVE_BUFFER_BYTES.to_ne_bytes();
        if socket
            .set_socket_option_bytes(SOL_SOCKET, SO_RCVBUFFORCE, &bytes)
            .is_err()
        {
            let _ = socket.set_socket_option_bytes(SOL_SOCKET, SO_RCVBUF, &bytes);
        }
        let socket = Arc::new(socket);
        let (tx, rx) = mpsc::unbounded_channel();
        let reader_socket = socket.clone();
        let reader = tokio::spawn(async move {
            loop {
                let sent = match reader_socket.read_frame().await {
                    Ok(frame) => match from_socketcan(&frame) {
                        Some(raw) => tx.send(Ok((Instant::now(), raw))),
                        None => Ok(()),
                    },
                    // The OS error (e.g. "Network is down") is what the engineer needs.
                    Err(e) => {
                        let _ = tx.send(Err(e));
                        break;
                    }
                };
                if sent.is_err() {
                    break;
                }
            }
        });
        self.opens += 1;
        self.needs_start = true;
        self.link = Some(Link { socket, rx, reader });
        Ok(())
    }

    async fn send(&mut self, frame: RawFrame) -> Result<(), CanError> {
        let Some(link) = &self.link else {
            return Err(self.socket_error("not open"));
        };
        let out = to_socketcan(&frame).ok_or_else(|| self.socket_error("bad frame"))?;
        match link.socket.write_frame(out).await {
            Ok(()) => Ok(()),
            Err(e) => {
                let err = self.socket_error(format!("send {frame}: {e}"));
                self.link = None;
                Err(err)
            }
        }
    }

    /// Takes one received frame; an SDO answer is returned to the caller.
    fn handle(&mut self, at: Instant, raw: &RawFrame) -> Option<codec::SdoAnswer> {
        if raw.cob_id != codec::SYNC_COB_ID {
            self.frames += 1;
        }
        let t_s = self.t_s(at);
        let msg = match codec::decode(raw) {
            Ok(m) => m,
            Err(e) => {
                tracing::debug!(device = %self.name, frame = %raw, error = %e, "malformed CAN frame ignored");
                let node = u16::from(self.params.node_id);
                if raw.cob_id == codec::SDO_TX_BASE + node {
                    self.malformed_sdo = Some(format!("{raw}: {e}"));
                } else if raw.cob_id == codec::HEARTBEAT_BASE + node {
                    self.malformed_heartbeat = Some(format!("{raw}: {e}"));
                }
                return None;
            }
        };
        if matches!(msg, Message::Heartbeat { node, .. } if node == self.params.node_id) {
            self.malformed_heartbeat = None;
        }
        if self.monitor.on_message(t_s, &msg) == Some(NodeEvent::NeedsStart) {
            self.needs_start = true;
        }
        if let Message::Emcy { code, register, .. } = msg {
            tracing::warn!(device = %self.name, code = format_args!("{code:04X}h"), class = codec::emcy_class(code), register, "EMCY");
        }
        self.pdos.on_message(self.params.node_id, t_s, &msg);
        match msg {
            Message::SdoResponse { node, answer } if node == self.params.node_id => Some(answer),
            _ => None,
        }
    }

    /// Takes every frame already received; the error when the reader has ended.
    fn drain(&mut self) -> Result<(), String> {
        loop {
            let Some(link) = self.link.as_mut() else {
                return Err("receive failed".into());
            };
            match link.rx.try_recv() {
                Ok(Ok((at, raw))) => {
                    self.handle(at, &raw);
                }
                Err(mpsc::error::TryRecvError::Empty) => return Ok(()),
                Ok(Err(e)) => {
                    self.link = None;
                    return Err(format!("receive failed: {e}"));
                }
                Err(mpsc::error::TryRecvError::Disconnected) => {
                    self.link = None;
                    return Err("receive failed".into());
                }
            }
        }
    }

    /// Waits for the next frame until `deadline`; `None` on timeout or a closed link.
    async fn next_frame(&mut self, deadline: Instant) -> Option<Received> {
        let link = self.link.as_mut()?;
        match tokio::time::timeout_at(deadline, link.rx.recv()).await {
            Ok(Some(Ok(r))) => Some(r),
            // The next cycle reopens, and its drain names the error if it persists.
            Ok(Some(Err(_)) | None) => {
                self.link = None;
                None
            }
            Err(_) => None,
        }
    }

    /// Reads the mapped TPDOs that followed the newest SYNC, waiting up to the
    /// timeout for those (or the SYNC) not there yet.
    async fn read_pdos(
        &mut self,
        values: &mut Vec<(usize, Result<f64, Fault>)>,
        errors: &mut Vec<CanError>,
    ) {
        let mut wanted: Vec<u8> = self
            .specs
            .iter()
            .filter_map(|s| match s.object {
                CanObject::Pdo { pdo, .. } => Some(pdo),
                CanObject::Sdo { .. } => None,
            })
            .collect();
        wanted.sort_unstable();
        wanted.dedup();
        if wanted.is_empty() {
            return;
        }
        let node = self.params.node_id;
        let sync_age = sync::max_age(self.params.sync_period);
        // Event-driven TPDOs are read from what the cycle's drain took, without a wait.
        let sync = match self.params.tpdo_max_age {
            Some(_) => None,
            None => self.await_sync_tpdos(&wanted, sync_age).await,
        };
        let now_s = self.t_s(Instant::now());
        for spec in self.specs.clone() {
            let CanObject::Pdo { pdo, offset_bytes } = spec.object else {
                continue;
            };
            let frame = match (self.params.tpdo_max_age, sync) {
                (Some(max_age), _) => match self.pdos.latest(pdo) {
                    Some((t_s, data)) if now_s - t_s <= max_age.as_secs_f64() => Ok(data),
                    newest => Err(CanError::PdoStale {
                        node,
                        pdo,
                        age_s: newest.map(|(t_s, _)| now_s - t_s),
                        max_age,
                        state: self.monitor.state(),
                    }),
                },
                (None, None) => Err(CanError::NoSync {
                    interface: self.params.interface.clone(),
                    max_age: sync_age,
                }),
                (None, Some(sync)) => {
                    self.pdos
                        .after_sync(pdo, sync)
                        .ok_or_else(|| CanError::PdoTimeout {
                            node,
                            pdo,
                            timeout: self.params.timeout,
                            state: self.monitor.state(),
                            last_s_ago: self.pdos.latest(pdo).map(|(t_s, _)| now_s - t_s),
                        })
                }
            };
            let value = frame.and_then(|data| {
                codec::decode_value(data, usize::from(offset_bytes), spec.data_type)
                    .map_err(|error| CanError::Pdo { node, pdo, error })
            });
            match value {
                Ok(v) => values.push((spec.channel, Ok(v))),
                Err(e) => {
                    values.push((spec.channel, Err(self.fault(Reason::Comm))));
                    if !errors.contains(&e) {
                        errors.push(e);
                    }
                }
            }
        }
    }

    /// Waits until every TPDO of `wanted` followed the newest SYNC, or the timeout: that
    /// SYNC, if one came within `max_age`. A SYNC arriving during the wait becomes the
    /// one to read: its TPDOs are the freshest, and a silent node still runs into the
    /// deadline.
    async fn await_sync_tpdos(
        &mut self,
        wanted: &[u8],
        max_age: Duration,
    ) -> Option<node::SyncMark> {
        let max_age_s = max_age.as_secs_f64();
        let deadline = Instant::now() + self.params.timeout;
        loop {
            let sync = self.pdos.current_sync(self.t_s(Instant::now()), max_age_s);
            if let Some(sync) = sync {
                if wanted
                    .iter()
                    .all(|&p| self.pdos.after_sync(p, sync).is_some())
                {
                    return Some(sync);
                }
            }
            let Some((at, raw)) = self.next_frame(deadline).await else {
                return self.pdos.current_sync(self.t_s(Instant::now()), max_age_s);
            };
            self.handle(at, &raw);
        }
    }

    async fn upload(&mut self, index: u16, sub: u8, ty: DataType) -> Result<f64, CanError> {
        let (data, len) = self.upload_bytes(index, sub).await?;
        codec::decode_sdo_value(&data, len, ty).map_err(|e| CanError::Sdo {
            node: self.params.node_id,
            index,
            sub,
            what: e.to_string(),
            abort_code: None,
        })
    }

    /// Uploads object `index`/`sub` once, at most 4 bytes, as an unsigned number (the
    /// bytes it has, zero-extended): how `compgate probe` reads a node's PDO settings.
    pub async fn read_object(&mut self, index: u16, sub: u8) -> Result<u32, CanError> {
        if self.link.is_none() {
            self.open()?;
        }
        self.drain().map_err(|e| self.socket_error(e))?;
        let (data, len) = self.upload_bytes(index, sub).await?;
        let mut b = [0u8; 4];
        let n = usize::from(len.min(4));
        b[..n].copy_from_slice(&data[..n]);
        Ok(u32::from_le_bytes(b))
    }

    /// An expedited upload's data bytes and how many of them count.
    async fn upload_bytes(&mut self, index: u16, sub: u8) -> Result<([u8; 4], u8), CanError> {
        let node = self.params.node_id;
        let failed = |what: String, abort_code| CanError::Sdo {
            node,
            index,
            sub,
            what,
            abort_code,
        };
        let request = self.sdo.request(index, sub);
        self.malformed_sdo = None;
        self.send(request).await?;
        let deadline = Instant::now() + self.params.timeout;
        loop {
            let Some((at, raw)) = self.next_frame(deadline).await else {
                self.sdo.on_timeout();
                // CiA 301: the client aborts a transfer it gives up, so a server
                // still busy with it is idle for the next request.
                self.abort_upload(index, sub, codec::ABORT_TIMED_OUT).await;
                let what = match self.malformed_sdo.take() {
                    Some(m) => format!(
                        "no valid answer within {:?}, ignored {m}",
                        self.params.timeout
                    ),
                    None => format!("no answer within {:?}", self.params.timeout),
                };
                return Err(failed(what, None));
            };
            let Some(answer) = self.handle(at, &raw) else {
                continue;
            };
            match self.sdo.on_answer(&answer) {
                None => continue,
                Some(Ok(answer)) => return Ok(answer),
                Some(Err(SdoFailure::Abort(code))) => {
                    return Err(failed(
                        format!("abort {code:08X}h: {}", codec::abort_name(code)),
                        Some(code),
                    ))
                }
                Some(Err(SdoFailure::Segmented)) => {
                    // Left open, the server would wait for segment requests and
                    // answer the next upload (of any object) with an abort of this one.
                    self.abort_upload(index, sub, codec::ABORT_TOO_LONG).await;
                    return Err(failed(
                        format!(
                            "the object is longer than 4 bytes (segmented transfer, not \
                             supported; aborted with {:08X}h)",
                            codec::ABORT_TOO_LONG
                        ),
                        None,
                    ));
                }
                Some(Err(SdoFailure::Unexpected(c))) => {
                    return Err(failed(format!("unexpected server command {c:#04x}"), None))
                }
                Some(Err(SdoFailure::Timeout)) => {
                    return Err(failed("timeout".into(), None));
                }
            }
        }
    }

    /// Sends the SDO abort of `index`/`sub`; a failed send has already closed the
    /// link, which the next cycle reopens.
    async fn abort_upload(&mut self, index: u16, sub: u8, code: u32) {
        let frame = codec::sdo_abort(self.params.node_id, index, sub, code);
        if let Err(e) = self.send(frame).await {
            tracing::debug!(device = %self.name, error = %e, "SDO abort not sent");
        }
    }

    fn fault(&self, reason: Reason) -> Fault {
        Fault {
            reason,
            degraded: self.failed_cycles.saturating_add(1) >= self.params.degrade_after_cycles,
        }
    }

    /// Runs one poll cycle.
    pub async fn poll(&mut self) -> DeviceSample {
        let started = Instant::now();
        let mut values: Vec<(usize, Result<f64, Fault>)> = Vec::with_capacity(self.specs.len());
        let mut errors: Vec<CanError> = Vec::new();
        let mut link_error = None;
        if self.link.is_none() {
            if let Err(e) = self.open() {
                link_error = Some(e);
            }
        }
        if link_error.is_none() {
            if let Err(e) = self.drain() {
                link_error = Some(self.socket_error(e));
            }
        }
        if link_error.is_none() && self.needs_start {
            match self
                .send(codec::nmt(NmtCommand::Start, self.params.node_id))
                .await
            {
                Ok(()) => {
                    tracing::info!(device = %self.name, node = self.params.node_id, "NMT start sent");
                    self.needs_start = false;
                }
                Err(e) => link_error = Some(e),
            }
        }
        // A node whose heartbeat has already timed out is not waited for: the cycle
        // keeps its period, and its next heartbeat is seen at the start of a cycle.
        let node_silent = matches!(
            self.monitor.health(self.t_s(Instant::now())),
            Err(NodeFault::HeartbeatTimeout { .. })
        );
        if link_error.is_none() && !node_silent {
            self.read_pdos(&mut values, &mut errors).await;
            for spec in self.specs.clone() {
                let CanObject::Sdo { index, sub } = spec.object else {
                    continue;
                };
                match self.upload(index, sub, spec.data_type).await {
                    Ok(v) => values.push((spec.channel, Ok(v))),
                    Err(e) => {
                        let reason = match e {
                            CanError::Sdo {
                                abort_code: Some(_),
                                ..
                            } => Reason::DeviceException,
                            _ => Reason::Comm,
                        };
                        values.push((spec.channel, Err(self.fault(reason))));
                        errors.push(e);
                    }
                }
            }
        }
        let node = self.params.node_id;
        let health = self.monitor.health(self.t_s(Instant::now()));
        // A socket binds to a down interface and then just hears nothing, which would
        // read as a silent node or missing PDOs. Looked up for a failed cycle only.
        if (link_error.is_some() || health.is_err() || !errors.is_empty())
            && !interface_up(&self.params.interface)
        {
            link_error = Some(self.socket_error(format!(
                "the interface is down (ip link set {} up)",
                self.params.interface
            )));
        }
        let node_error = match (link_error, health) {
            (Some(e), _) => Some((e, Reason::Comm)),
            (
                None,
                Err(NodeFault::HeartbeatTimeout {
                    silent_s,
                    timeout_s,
                }),
            ) => Some((
                CanError::HeartbeatTimeout {
                    node,
                    silent_s,
                    timeout_s,
                    ignored: self.malformed_heartbeat.clone(),
                },
                Reason::Comm,
            )),
            (None, Err(NodeFault::Emergency { code, register })) => Some((
                CanError::Emergency {
                    node,
                    code,
                    class: codec::emcy_class(code),
                    register,
                },
                Reason::DeviceException,
            )),
            (None, Ok(())) => None,
        };
        let error = match node_error {
            Some((e, reason)) => {
                // The whole node is out: every channel bad at once, not after
                // `degrade_after_cycles`.
                values = self
                    .specs
                    .iter()
                    .map(|s| {
                        (
                            s.channel,
                            Err(Fault {
                                reason,
                                degraded: true,
                            }),
                        )
                    })
                    .collect();
                self.failed_cycles = self.failed_cycles.saturating_add(1);
                Some(e)
            }
            None => {
                if errors.is_empty() {
                    self.failed_cycles = 0;
                } else {
                    self.failed_cycles = self.failed_cycles.saturating_add(1);
                }
                errors.into_iter().next()
            }
        };
        if let Some(e) = &error {
            tracing::debug!(device = %self.name, error = %e, "CAN poll cycle failed");
        }
        let error = error.map(SourceError::Can);
        DeviceSample {
            device: self.index,
            started,
            elapsed: started.elapsed(),
            values,
            faults: error.iter().map(SourceError::kind).collect(),
            error,
            connects: self.opens,
        }
    }

    /// The NMT state of the node's last heartbeat.
    pub fn nmt_state(&self) -> Option<NmtState> {
        self.monitor.state()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A stopped node sends no PDO: "not received" alone sent people looking at the
    /// wiring.
    #[test]
    fn a_pdo_timeout_names_a_node_that_is_not_operational() {
        let timeout = |state| {
            CanError::PdoTimeout {
                node: 5,
                pdo: 1,
                timeout: Duration::from_millis(50),
                state,
                last_s_ago: None,
            }
            .to_string()
        };
        let plain = "node 5: TPDO1 not received within 50ms of the SYNC";
        assert_eq!(timeout(None), plain);
        assert_eq!(timeout(Some(NmtState::Operational)), plain);
        let stopped = timeout(Some(NmtState::Stopped));
        assert!(
            stopped.starts_with(plain) && stopped.contains("its heartbeat says stopped"),
            "{stopped}"
        );
        assert!(timeout(Some(NmtState::PreOperational)).contains("pre-operational"));
    }

    /// A node that sends the TPDO, only not after each SYNC: the message says when it
    /// came and which key reads it (the state's hint wins: a stopped node sends none).
    #[test]
    fn a_pdo_timeout_points_an_event_driven_node_to_tpdo_max_age() {
        let timeout = |state, pdo| {
            CanError::PdoTimeout {
                node: 5,
                pdo,
                timeout: Duration::from_millis(50),
                state,
                last_s_ago: Some(0.337),
            }
            .to_string()
        };
        assert_eq!(
            timeout(None, 2),
            "node 5: TPDO2 not received within 50ms of the SYNC; the last one came 0.34s \
             before: if the node sends it on its event timer (transmission type 254 or 255 \
             in 1801h sub 2), set tpdo_max_age_s"
        );
        assert!(timeout(Some(NmtState::Stopped), 1).contains("its heartbeat says stopped"));
        let stale = |age_s| {
            CanError::PdoStale {
                node: 5,
                pdo: 4,
                age_s,
                max_age: Duration::from_millis(300),
                state: Some(NmtState::PreOperational),
            }
            .to_string()
        };
        assert!(
            stale(Some(0.6181)).starts_with(
                "node 5: TPDO4 not received for 0.62s (tpdo_max_age_s = 0.3); its heartbeat \
                 says pre-operational"
            ),
            "{}",
            stale(Some(0.6181))
        );
        assert!(stale(None).starts_with("node 5: TPDO4 never received (tpdo_max_age_s = 0.3)"));
    }
}
