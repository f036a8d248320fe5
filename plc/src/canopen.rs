//! Simulated CANopen transmitter/ADC node on any SocketCAN interface (`vcan0`, `can0`).
//!
//! The node publishes the values of a [`FieldModule`] (the same PT100 transmitters on
//! a 12-bit ADC that the Modbus field module serves), so the gateway scales CAN
//! channels exactly as Modbus ones. It implements the CiA 301 subset a temperature
//! module needs:
//!
//! - NMT slave: boots pre-operational (boot-up message `0x700 + id` with `00`), obeys
//!   start / stop / pre-operational / reset node / reset communication.
//! - Heartbeat producer every `heartbeat_ms` (object 0x1017): `0x700 + id`, the state.
//! - Synchronous TPDOs while operational: on each SYNC (`0x080`) TPDO `p` (1..=4,
//!   COB-ID `0x080 + 0x100 * p + id`) carries the ADC counts of transmitters
//!   `4(p-1) .. 4p-1`, u16 little-endian each, as many PDOs as transmitters need.
//! - SDO server, upload only (`0x600 + id` -> `0x580 + id`), expedited except for
//!   the device name:
//!
//! | index | sub | type | content |
//! |---|---|---|---|
//! | 0x1000 | 0 | u32 | device type 0x00020194 (CiA 404) |
//! | 0x1001 | 0 | u8 | error register |
//! | 0x1008 | 0 | string | device name [`DEVICE_NAME`], segmented upload |
//! | 0x1017 | 0 | u16 | producer heartbeat time, ms |
//! | 0x1018 | 0 / 1 | u8 / u32 | identity: 1 entry / vendor id |
//! | 0x1800..0x1803 | 1 / 2 | u32 / u8 | TPDO 1-4: COB-ID (bit 31 set: no transmitter for it) / transmission type 1 |
//! | 0x1A00..0x1A03 | 0 / k | u8 / u32 | TPDO 1-4 mapping: entries / 6401h sub of its k-th transmitter, 16 bit |
//! | 0x6401 | 0 | u8 | number of analogue inputs |
//! | 0x6401 | i (1..=N) | u16 | ADC counts of transmitter i-1 |
//! | 0x9130 | i (1..=N) | f32 | measured temperature of transmitter i-1, degC |
//!
//!   An unknown object aborts with 0x06020000, an unknown sub-index with 0x06090011,
//!   any other command with 0x05040001. A client's abort is not answered. While a
//!   segmented upload is open, any request but the next segment's aborts it with
//!   0x05040001 (a wrong toggle bit with 0x05030000) under the open object's index,
//!   as common CANopen stacks do.
//! - Fault injection through the cloneable handle: go silent (sends and answers
//!   nothing), send an EMCY (and its error reset), abort the upload of a given object
//!   with a given code.

use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use socketcan::tokio::CanSocket;
use socketcan::{CanFrame, EmbeddedFrame, Id, StandardId};
use tokio::time::MissedTickBehavior;
use tokio_util::sync::CancellationToken;

use crate::field::FieldModule;

/// Most transmitters the TPDOs carry (4 PDOs of 4 u16 values).
pub const MAX_PDO_TRANSMITTERS: usize = 16;

/// Transmitters TPDO `p + 1` carries (0..=4) of a module with `count` transmitters.
fn pdo_transmitters(count: usize, p: u16) -> usize {
    count
        .min(MAX_PDO_TRANSMITTERS)
        .saturating_sub(4 * usize::from(p))
        .min(4)
}

/// Object 0x1008 (manufacturer device name): longer than 4 bytes, so uploaded in
/// segments.
pub const DEVICE_NAME: &str = "compgate simulated CANopen node";

/// Errors of the simulated CANopen node.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CanopenError {
    /// The node id is outside 1..=127.
    #[error("CANopen node id {0} is outside 1..=127")]
    NodeId(u8),
    /// The interface cannot be opened.
    #[error("CAN interface {interface}: {message}")]
    Socket {
        /// Interface name.
        interface: String,
        /// The error.
        message: String,
    },
}

/// NMT state of the node.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NmtState {
    /// Pre-operational: SDO and heartbeat, no PDOs.
    PreOperational,
    /// Operational: PDOs on SYNC.
    Operational,
    /// Stopped: heartbeat and NMT only.
    Stopped,
}

impl NmtState {
    fn code(self) -> u8 {
        match self {
            Self::PreOperational => 0x7F,
            Self::Operational => 0x05,
            Self::Stopped => 0x04,
        }
    }
}

/// What the node has seen and done, for tests.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct NodeCounters {
    /// SYNC frames received.
    pub syncs: u64,
    /// NMT frames addressed to this node (or all nodes).
    pub nmt_commands: u64,
    /// TPDO frames sent.
    pub pdos_sent: u64,
    /// SDO requests answered (with data or an abort).
    pub sdo_answers: u64,
    /// SDO aborts received from the client.
    pub sdo_aborts_received: u64,
    /// Heartbeats sent.
    pub heartbeats: u64,
}

#[derive(Debug)]
struct State {
    nmt: NmtState,
    silent: bool,
    error_register: u8,
    abort: Option<(u16, u8, u32)>,
    /// The open segmented upload: index, sub-index, bytes not yet sent, next toggle.
    segmented: Option<(u16, u8, Vec<u8>, u8)>,
    counters: NodeCounters,
    /// Frames to send from the node's task (EMCY, boot-up after reset).
    outbox: Vec<(u16, Vec<u8>)>,
}

/// Cloneable handle of a running simulated node.
#[derive(Debug, Clone)]
pub struct CanopenNode {
    node_id: u8,
    heartbeat_ms: u16,
    state: Arc<Mutex<State>>,
    wake: Arc<tokio::sync::Notify>,
    stop: CancellationToken,
}

impl CanopenNode {
    /// Starts node `node_id` on `interface`, publishing `module`'s transmitters, with
    /// a heartbeat every `heartbeat_ms` (0 = no heartbeat). It sends its boot-up
    /// message and waits, pre-operational, for NMT start.
    pub fn spawn(
        interface: &str,
        node_id: u8,
        heartbeat_ms: u16,
        module: FieldModule,
    ) -> Result<Self, CanopenError> {
        if !(1..=127).contains(&node_id) {
            return Err(CanopenError::NodeId(node_id));
        }
        let socket = CanSocket::open(interface).map_err(|e| CanopenError::Socket {
            interface: interface.to_string(),
            message: e.to_string(),
        })?;
        let node = Self {
            node_id,
            heartbeat_ms,
            state: Arc::new(Mutex::new(State {
                nmt: NmtState::PreOperational,
                silent: false,
                error_register: 0,
                abort: None,
                segmented: None,
                counters: NodeCounters::default(),
                outbox: vec![(0x700 + u16::from(node_id), vec![0x00])],
            })),
            wake: Arc::new(tokio::sync::Notify::new()),
            stop: CancellationToken::new(),
        };
        let task = node.clone();
        tokio::spawn(async move { task.serve(socket, heartbeat_ms, module).await });
        node.wake.notify_one();
        Ok(node)
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Node id.
    pub fn node_id(&self) -> u8 {
        self.node_id
    }

    /// NMT state now.
    pub fn nmt_state(&self) -> NmtState {
        self.lock().nmt
    }

    /// Counters so far.
    pub fn counters(&self) -> NodeCounters {
        self.lock().counters
    }

    /// Goes silent (`true`: sends and answers nothing, as a node whose bus line was
    /// cut) or speaks again in the state it had.
    pub fn set_silent(&self, silent: bool) {
        self.lock().silent = silent;
    }

    /// Sends an EMCY with `code` and sets the error register to `register`; code 0
    /// is the error reset.
    pub fn send_emcy(&self, code: u16, register: u8) {
        let mut s = self.lock();
        s.error_register = register;
        let [lo, hi] = code.to_le_bytes();
        s.outbox.push((
            0x080 + u16::from(self.node_id),
            vec![lo, hi, register, 0, 0, 0, 0, 0],
        ));
        drop(s);
        self.wake.notify_one();
    }

    /// Answers uploads of `index`/`sub` with abort `code` (`None`: answer normally).
    pub fn set_sdo_abort(&self, abort: Option<(u16, u8, u32)>) {
        self.lock().abort = abort;
    }

    /// Stops the node's task.
    pub fn stop(&self) {
        self.stop.cancel();
    }

    async fn serve(self, socket: CanSocket, heartbeat_ms: u16, module: FieldModule) {
        let mut heartbeat =
            tokio::time::interval(Duration::from_millis(u64::from(heartbeat_ms.max(1))));
        heartbeat.set_missed_tick_behavior(MissedTickBehavior::Delay);
        loop {
            let outgoing: Vec<(u16, Vec<u8>)> = tokio::select! {
                _ = self.stop.cancelled() => break,
                _ = self.wake.notified() => std::mem::take(&mut self.lock().outbox),
                _ = heartbeat.tick(), if heartbeat_ms > 0 => {
                    let mut s = self.lock();
                    if s.silent {
                        continue;
                    }
                    s.counters.heartbeats += 1;
                    vec![(0x700 + u16::from(self.node_id), vec![s.nmt.code()])]
                }
                frame = socket.read_frame() => match frame {
                    Ok(frame) => self.on_frame(&frame, &module),
                    Err(e) => {
                        // As a real node, it outlives a bus outage (ENETDOWN while the
                        // interface is down) in the state it had.
                        tracing::debug!(node = self.node_id, error = %e, "CANopen node: receive failed");
                        tokio::select! {
                            _ = self.stop.cancelled() => break,
                            _ = tokio::time::sleep(Duration::from_millis(100)) => {}
                        }
                        continue;
                    }
                },
            };
            if self.lock().silent {
                continue;
            }
            for (id, data) in outgoing {
                let Some(frame) = StandardId::new(id).and_then(|id| CanFrame::new(id, &data))
                else {
                    continue;
                };
                if let Err(e) = socket.write_frame(frame).await {
                    tracing::warn!(node = self.node_id, error = %e, "CANopen node: send failed");
                }
            }
        }
    }

    /// Reacts to one received frame; the frames to send.
    fn on_frame(&self, frame: &CanFrame, module: &FieldModule) -> Vec<(u16, Vec<u8>)> {
        let Id::Standard(id) = frame.id() else {
            return Vec::new();
        };
        if !matches!(frame, CanFrame::Data(_)) {
            return Vec::new();
        }
        let id = id.as_raw();
        let d = frame.data();
        let me = u16::from(self.node_id);
        let mut s = self.lock();
        if s.silent {
            return Vec::new();
        }
        match id {
            0x000 if d.len() == 2 && (d[1] == 0 || d[1] == self.node_id) => {
                s.counters.nmt_commands += 1;
                match d[0] {
                    0x01 => s.nmt = NmtState::Operational,
                    0x02 => s.nmt = NmtState::Stopped,
                    0x80 => s.nmt = NmtState::PreOperational,
                    0x81 | 0x82 => {
                        s.nmt = NmtState::PreOperational;
                        s.error_register = 0;
                        s.segmented = None;
                        return vec![(0x700 + me, vec![0x00])];
                    }
                    _ => {}
                }
                Vec::new()
            }
            0x080 if d.len() <= 1 => {
                s.counters.syncs += 1;
                if s.nmt != NmtState::Operational {
                    return Vec::new();
                }
                drop(s);
                let values = module.scan();
                let n = values.len().min(MAX_PDO_TRANSMITTERS);
                let pdos: Vec<(u16, Vec<u8>)> = values[..n]
                    .chunks(4)
                    .enumerate()
                    .map(|(p, chunk)| {
                        let data = chunk
                            .iter()
                            .flat_map(|(counts, _)| counts.to_le_bytes())
                            .collect();
                        (0x180 + 0x100 * p as u16 + me, data)
                    })
                    .collect();
                self.lock().counters.pdos_sent += pdos.len() as u64;
                pdos
            }
            _ if id == 0x600 + me && d.len() == 8 && s.nmt != NmtState::Stopped => {
                let index = u16::from_le_bytes([d[1], d[2]]);
                let sub = d[3];
                let abort_of = |index: u16, sub: u8, code: u32| {
                    let [lo, hi] = index.to_le_bytes();
                    let mut a = vec![0x80, lo, hi, sub];
                    a.extend_from_slice(&code.to_le_bytes());
                    vec![(0x580 + me, a)]
                };
                let abort = |code: u32| abort_of(index, sub, code);
                if d[0] == 0x80 {
                    s.counters.sdo_aborts_received += 1;
                    s.segmented = None;
                    return Vec::new();
                }
                s.counters.sdo_answers += 1;
                if let Some((i, su, rest, toggle)) = s.segmented.take() {
                    if d[0] & 0xEF != 0x60 {
                        return abort_of(i, su, 0x0504_0001);
                    }
                    if d[0] & 0x10 != toggle {
                        return abort_of(i, su, 0x0503_0000);
                    }
                    // Upload segment response: toggle, unused bytes, last segment.
                    let n = rest.len().min(7);
                    let last = n == rest.len();
                    let mut a = vec![toggle | (((7 - n) as u8) << 1) | u8::from(last)];
                    a.extend_from_slice(&rest[..n]);
                    a.resize(8, 0);
                    if !last {
                        s.segmented = Some((i, su, rest[n..].to_vec(), toggle ^ 0x10));
                    }
                    return vec![(0x580 + me, a)];
                }
                if d[0] != 0x40 {
                    return abort(0x0504_0001);
                }
                if let Some((i, su, code)) = s.abort {
                    if (i, su) == (index, sub) {
                        return abort(code);
                    }
                }
                if (index, sub) == (0x1008, 0) {
                    // Initiate upload response, segmented, size indicated.
                    let name = DEVICE_NAME.as_bytes();
                    s.segmented = Some((index, sub, name.to_vec(), 0));
                    let mut a = vec![0x41, d[1], d[2], sub];
                    a.extend_from_slice(&(name.len() as u32).to_le_bytes());
                    return vec![(0x580 + me, a)];
                }
                let error_register = s.error_register;
                drop(s);
                let value: Result<Vec<u8>, u32> = match (index, sub) {
                    (0x1000, 0) => Ok(0x0002_0194u32.to_le_bytes().to_vec()),
                    (0x1001, 0) => Ok(vec![error_register]),
                    (0x1017, 0) => Ok(self.heartbeat_ms.to_le_bytes().to_vec()),
                    (0x1018, 0) => Ok(vec![1]),
                    (0x1018, 1) => Ok(0x0000_0CA7u32.to_le_bytes().to_vec()),
                    (0x6401, 0) => Ok(vec![module.transmitter_count().min(254) as u8]),
                    (0x6401 | 0x9130, i) if i >= 1 => {
                        let values = module.scan();
                        match values.get(usize::from(i) - 1) {
                            Some((counts, _)) if index == 0x6401 => {
                                Ok(counts.to_le_bytes().to_vec())
                            }
                            Some((_, degc)) => Ok(degc.to_le_bytes().to_vec()),
                            None => Err(0x0609_0011),
                        }
                    }
                    // TPDO p's parameters, as it sends it: synchronous, its transmitters'
                    // counts in order; one with no transmitter is off (COB-ID bit 31).
                    (0x1800..=0x1803, 1) => {
                        let p = index - 0x1800;
                        let off = if pdo_transmitters(module.transmitter_count(), p) == 0 {
                            0x8000_0000
                        } else {
                            0
                        };
                        Ok((off | u32::from(0x180 + 0x100 * p + me))
                            .to_le_bytes()
                            .to_vec())
                    }
                    (0x1800..=0x1803, 2) => Ok(vec![1]),
                    (0x1A00..=0x1A03, k) => {
                        let p = index - 0x1A00;
                        let n = pdo_transmitters(module.transmitter_count(), p);
                        match k {
                            0 => Ok(vec![n as u8]),
                            k if usize::from(k) <= n => {
                                let sub = u32::from(4 * p) + u32::from(k);
                                Ok((0x6401_0010 | sub << 8).to_le_bytes().to_vec())
                            }
                            _ => Err(0x0609_0011),
                        }
                    }
                    (0x1000 | 0x1001 | 0x1008 | 0x1017 | 0x1018 | 0x1800..=0x1803 | 0x9130, _) => {
                        Err(0x0609_0011)
                    }
                    _ => Err(0x0602_0000),
                };
                match value {
                    Ok(bytes) => {
                        // Expedited, size indicated: 0x43 | (4 - n) << 2.
                        let n = bytes.len().min(4);
                        let mut a =
                            vec![0x43 | (((4 - n) as u8) << 2), d[1], d[2], sub, 0, 0, 0, 0];
                        a[4..4 + n].copy_from_slice(&bytes[..n]);
                        vec![(0x580 + me, a)]
                    }
                    Err(code) => abort(code),
                }
            }
            _ => Vec::new(),
        }
    }
}
