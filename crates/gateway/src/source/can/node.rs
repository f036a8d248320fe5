//! Per-node bookkeeping with no I/O: heartbeat consumer, EMCY state, the SDO client's
//! one outstanding request, and the latest TPDOs with the SYNC each followed. Time is
//! seconds on the caller's clock, so tests drive it directly.

use super::codec::{self, Message, NmtState, RawFrame, SdoAnswer};

/// Why a node's channels are bad as a whole.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum NodeFault {
    /// No heartbeat for longer than the consumer timeout.
    HeartbeatTimeout {
        /// Seconds since the last heartbeat (or since monitoring started).
        silent_s: f64,
        /// The configured timeout.
        timeout_s: f64,
    },
    /// The node reported an emergency that no error-reset EMCY has cleared.
    Emergency {
        /// EMCY error code.
        code: u16,
        /// Error register (0x1001).
        register: u8,
    },
}

/// What the poller must do after a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NodeEvent {
    /// The node is (again) pre-operational or has just booted: send NMT start.
    NeedsStart,
}

/// How long a node may stay pre-operational after a start was asked for before it is
/// asked again, s: the start may have reached a node still booting, and a master that
/// never repeats it leaves the node without PDOs for good.
pub const START_RETRY_S: f64 = 2.0;

/// Heartbeat consumer and EMCY state of one node.
#[derive(Debug, Clone)]
pub struct NodeMonitor {
    node: u8,
    heartbeat_timeout_s: f64,
    since_s: f64,
    last_heartbeat_s: Option<f64>,
    state: Option<NmtState>,
    /// When a start was last asked for.
    start_asked_s: Option<f64>,
    emergency: Option<(u16, u8)>,
    emergencies: u64,
}

impl NodeMonitor {
    /// Monitors `node` from `now_s`; a timeout of 0 turns the heartbeat check off.
    pub fn new(node: u8, heartbeat_timeout_s: f64, now_s: f64) -> Self {
        Self {
            node,
            heartbeat_timeout_s,
            since_s: now_s,
            last_heartbeat_s: None,
            state: None,
            start_asked_s: None,
            emergency: None,
            emergencies: 0,
        }
    }

    /// The NMT state of the last heartbeat.
    pub fn state(&self) -> Option<NmtState> {
        self.state
    }

    /// Emergencies received so far.
    pub fn emergencies(&self) -> u64 {
        self.emergencies
    }

    /// Takes one decoded frame received at `t_s`; frames of other nodes are ignored.
    pub fn on_message(&mut self, t_s: f64, msg: &Message) -> Option<NodeEvent> {
        match *msg {
            Message::Heartbeat { node, state } if node == self.node => {
                self.last_heartbeat_s = Some(t_s);
                let previous = self.state.replace(state);
                let ask = match state {
                    NmtState::BootUp => {
                        // A restarted node has forgotten its emergency.
                        self.emergency = None;
                        true
                    }
                    NmtState::PreOperational => {
                        previous != Some(NmtState::PreOperational)
                            || self
                                .start_asked_s
                                .is_none_or(|asked_s| t_s - asked_s >= START_RETRY_S)
                    }
                    _ => false,
                };
                ask.then(|| {
                    self.start_asked_s = Some(t_s);
                    NodeEvent::NeedsStart
                })
            }
            Message::Emcy {
                node,
                code,
                register,
                ..
            } if node == self.node => {
                if code == 0 {
                    self.emergency = None;
                } else {
                    self.emergencies += 1;
                    self.emergency = Some((code, register));
                }
                None
            }
            _ => None,
        }
    }

    /// Whether the node's channels can be trusted at `now_s`.
    pub fn health(&self, now_s: f64) -> Result<(), NodeFault> {
        if let Some((code, register)) = self.emergency {
            return Err(NodeFault::Emergency { code, register });
        }
        if self.heartbeat_timeout_s > 0.0 {
            let silent_s = now_s - self.last_heartbeat_s.unwrap_or(self.since_s);
            if silent_s > self.heartbeat_timeout_s {
                return Err(NodeFault::HeartbeatTimeout {
                    silent_s,
                    timeout_s: self.heartbeat_timeout_s,
                });
            }
        }
        Ok(())
    }
}

/// Why an SDO upload failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SdoFailure {
    /// No answer in time.
    Timeout,
    /// The server aborted with this code.
    Abort(u32),
    /// The server started a segmented transfer (not supported).
    Segmented,
    /// The server answered with another command.
    Unexpected(u8),
}

/// SDO client of one node: at most one expedited upload outstanding.
#[derive(Debug, Clone, Default)]
pub struct SdoClient {
    node: u8,
    pending: Option<(u16, u8)>,
}

impl SdoClient {
    /// A client for server `node`.
    pub fn new(node: u8) -> Self {
        Self {
            node,
            pending: None,
        }
    }

    /// The object being uploaded, if any.
    pub fn pending(&self) -> Option<(u16, u8)> {
        self.pending
    }

    /// Starts an upload of `index`/`sub`; the frame to send. A request still
    /// outstanding is dropped.
    pub fn request(&mut self, index: u16, sub: u8) -> RawFrame {
        self.pending = Some((index, sub));
        codec::sdo_upload_request(self.node, index, sub)
    }

    /// Takes an answer from this node's server. `None` while nothing is outstanding
    /// or when the answer is for another object (a late answer to an earlier request);
    /// otherwise the upload's end: the data bytes and their count, or the failure.
    pub fn on_answer(&mut self, answer: &SdoAnswer) -> Option<Result<([u8; 4], u8), SdoFailure>> {
        let (index, sub) = self.pending?;
        let result = match *answer {
            SdoAnswer::Upload {
                index: i,
                sub: s,
                data,
                len,
            } if (i, s) == (index, sub) => Ok((data, len)),
            SdoAnswer::Segmented { index: i, sub: s } if (i, s) == (index, sub) => {
                Err(SdoFailure::Segmented)
            }
            SdoAnswer::Abort {
                index: i,
                sub: s,
                code,
            } if (i, s) == (index, sub) => Err(SdoFailure::Abort(code)),
            SdoAnswer::Other { command } => Err(SdoFailure::Unexpected(command)),
            _ => return None,
        };
        self.pending = None;
        Some(result)
    }

    /// The outstanding upload timed out.
    pub fn on_timeout(&mut self) -> SdoFailure {
        self.pending = None;
        SdoFailure::Timeout
    }
}

/// One SYNC as a node's socket saw it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SyncMark {
    /// Count of SYNCs seen on this socket, 1 for the first.
    pub seq: u64,
    /// Receive time.
    pub t_s: f64,
}

/// A TPDO as stored: its bytes and the SYNC it followed (0 = none yet).
#[derive(Debug, Clone, Copy)]
struct StoredPdo {
    after_sync: u64,
    /// When it was received, s.
    t_s: f64,
    data: [u8; 8],
    len: u8,
}

/// The latest frame of each TPDO 1..=4 of one node, and the SYNC each followed.
///
/// The socket delivers the bus' SYNC (from the interface's SYNC producer, through the
/// kernel's loopback) and the node's TPDOs in bus order, so a TPDO belongs to the last
/// SYNC handled before it. Order decides, not timestamps: a TPDO that answers a SYNC
/// can never be taken for the answer to an earlier one. (A node so slow that its
/// TPDOs of SYNC n come after SYNC n+1 counts as answering n+1; a CANopen master
/// cannot tell either.)
#[derive(Debug, Clone, Default)]
pub struct PdoStore {
    latest: [Option<StoredPdo>; 4],
    sync: Option<SyncMark>,
    received: u64,
}

impl PdoStore {
    /// Takes a decoded frame received at `t_s`: a SYNC, or a TPDO of `node` (other
    /// nodes' PDOs are ignored).
    pub fn on_message(&mut self, node: u8, t_s: f64, msg: &Message) {
        match *msg {
            Message::Sync { .. } => {
                let seq = self.sync.map_or(0, |s| s.seq) + 1;
                self.sync = Some(SyncMark { seq, t_s });
            }
            Message::Tpdo {
                node: n,
                pdo,
                data,
                len,
            } if n == node => {
                if let Some(slot) = self.latest.get_mut(usize::from(pdo.wrapping_sub(1))) {
                    *slot = Some(StoredPdo {
                        after_sync: self.sync.map_or(0, |s| s.seq),
                        t_s,
                        data,
                        len,
                    });
                    self.received += 1;
                }
            }
            _ => {}
        }
    }

    /// The newest SYNC seen, if any.
    pub fn last_sync(&self) -> Option<SyncMark> {
        self.sync
    }

    /// The SYNC a poll at `now_s` reads: the newest one, unless it was received more
    /// than `max_age_s` before `now_s` (the producer has stopped or the bus is down:
    /// its TPDOs are no longer current).
    pub fn current_sync(&self, now_s: f64, max_age_s: f64) -> Option<SyncMark> {
        self.sync.filter(|s| now_s - s.t_s <= max_age_s)
    }

    /// TPDO `pdo` if it followed SYNC `sync` (the newest TPDO of SYNC `sync`): its
    /// data bytes. `None` while the node has not answered that SYNC yet.
    pub fn after_sync(&self, pdo: u8, sync: SyncMark) -> Option<&[u8]> {
        let p = self
            .latest
            .get(usize::from(pdo.wrapping_sub(1)))?
            .as_ref()?;
        (p.after_sync == sync.seq).then(|| &p.data[..usize::from(p.len)])
    }

    /// The newest frame of TPDO `pdo`, whatever SYNC it followed: when it was
    /// received (s) and its data bytes. How an event-driven TPDO is read.
    pub fn latest(&self, pdo: u8) -> Option<(f64, &[u8])> {
        let p = self
            .latest
            .get(usize::from(pdo.wrapping_sub(1)))?
            .as_ref()?;
        Some((p.t_s, &p.data[..usize::from(p.len)]))
    }

    /// TPDOs received so far.
    pub fn received(&self) -> u64 {
        self.received
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use codec::decode;

    fn msg(id: u16, d: &[u8]) -> Message {
        decode(&RawFrame::new(id, d).expect("frame")).expect("decodes")
    }

    #[test]
    fn heartbeat_timeout_and_recovery() {
        let mut m = NodeMonitor::new(5, 1.0, 10.0);
        assert_eq!(m.health(10.9), Ok(()));
        assert!(matches!(
            m.health(11.2),
            Err(NodeFault::HeartbeatTimeout { timeout_s, .. }) if timeout_s == 1.0
        ));
        assert_eq!(m.on_message(11.3, &msg(0x705, &[0x05])), None);
        assert_eq!(m.state(), Some(NmtState::Operational));
        assert_eq!(m.health(12.2), Ok(()));
        // Another node's heartbeat does not count.
        m.on_message(12.5, &msg(0x706, &[0x05]));
        assert!(m.health(12.29).is_ok());
        assert!(m.health(12.31).is_err());
        // Off.
        assert_eq!(NodeMonitor::new(5, 0.0, 0.0).health(1e9), Ok(()));
    }

    #[test]
    fn boot_up_and_pre_operational_ask_for_start() {
        let mut m = NodeMonitor::new(5, 1.0, 0.0);
        assert_eq!(
            m.on_message(0.1, &msg(0x705, &[0x00])),
            Some(NodeEvent::NeedsStart)
        );
        assert_eq!(
            m.on_message(0.2, &msg(0x705, &[0x7F])),
            Some(NodeEvent::NeedsStart)
        );
        // Asked once per change, not on every heartbeat.
        assert_eq!(m.on_message(0.3, &msg(0x705, &[0x7F])), None);
        assert_eq!(m.on_message(0.4, &msg(0x705, &[0x05])), None);
        assert_eq!(
            m.on_message(0.5, &msg(0x705, &[0x7F])),
            Some(NodeEvent::NeedsStart)
        );
        // A node that stays pre-operational (the start reached it while booting) is
        // asked again every START_RETRY_S, not on every heartbeat.
        assert_eq!(m.on_message(2.4, &msg(0x705, &[0x7F])), None);
        assert_eq!(
            m.on_message(2.5, &msg(0x705, &[0x7F])),
            Some(NodeEvent::NeedsStart)
        );
        assert_eq!(m.on_message(2.6, &msg(0x705, &[0x7F])), None);
        assert_eq!(
            m.on_message(4.5, &msg(0x705, &[0x7F])),
            Some(NodeEvent::NeedsStart)
        );
    }

    #[test]
    fn emergency_until_reset() {
        let mut m = NodeMonitor::new(5, 0.0, 0.0);
        m.on_message(1.0, &msg(0x085, &[0x10, 0x42, 0x09, 0, 0, 0, 0, 0]));
        assert_eq!(
            m.health(1.0),
            Err(NodeFault::Emergency {
                code: 0x4210,
                register: 0x09
            })
        );
        assert_eq!(m.emergencies(), 1);
        m.on_message(2.0, &msg(0x086, &[0, 0, 0, 0, 0, 0, 0, 0]));
        assert!(m.health(2.0).is_err(), "another node's reset");
        m.on_message(2.0, &msg(0x085, &[0, 0, 0, 0, 0, 0, 0, 0]));
        assert_eq!(m.health(2.0), Ok(()));
        m.on_message(3.0, &msg(0x085, &[0x00, 0x50, 0x01, 0, 0, 0, 0, 0]));
        assert!(m.health(3.0).is_err());
        m.on_message(4.0, &msg(0x705, &[0x00]));
        assert_eq!(m.health(4.0), Ok(()), "boot-up clears");
    }

    #[test]
    fn sdo_client_matches_answers() {
        let mut c = SdoClient::new(5);
        let upload = SdoAnswer::Upload {
            index: 0x6401,
            sub: 1,
            data: [1, 2, 0, 0],
            len: 2,
        };
        assert_eq!(c.on_answer(&upload), None, "nothing outstanding");
        assert_eq!(c.request(0x6401, 2).cob_id, 0x605);
        assert_eq!(c.on_answer(&upload), None, "late answer to sub 1");
        assert_eq!(c.pending(), Some((0x6401, 2)));
        let upload2 = SdoAnswer::Upload {
            index: 0x6401,
            sub: 2,
            data: [3, 4, 0, 0],
            len: 2,
        };
        assert_eq!(c.on_answer(&upload2), Some(Ok(([3, 4, 0, 0], 2))));
        assert_eq!(c.pending(), None);
        c.request(0x2000, 0);
        assert_eq!(
            c.on_answer(&SdoAnswer::Abort {
                index: 0x2000,
                sub: 0,
                code: 0x0602_0000
            }),
            Some(Err(SdoFailure::Abort(0x0602_0000)))
        );
        c.request(0x1008, 0);
        assert_eq!(
            c.on_answer(&SdoAnswer::Segmented {
                index: 0x1008,
                sub: 0
            }),
            Some(Err(SdoFailure::Segmented))
        );
        c.request(0x1008, 0);
        assert_eq!(
            c.on_answer(&SdoAnswer::Other { command: 0x60 }),
            Some(Err(SdoFailure::Unexpected(0x60)))
        );
        c.request(0x1008, 0);
        assert_eq!(c.on_timeout(), SdoFailure::Timeout);
        assert_eq!(c.pending(), None);
    }

    #[test]
    fn pdo_store_keeps_latest_per_pdo_and_its_sync() {
        let mut s = PdoStore::default();
        // A TPDO before any SYNC belongs to none.
        s.on_message(5, 0.5, &msg(0x185, &[7, 7]));
        assert_eq!(s.last_sync(), None);
        s.on_message(5, 1.0, &msg(0x080, &[]));
        let first = s.last_sync().expect("sync");
        assert_eq!(first.seq, 1);
        assert_eq!(s.after_sync(1, first), None, "older than the SYNC");
        s.on_message(5, 1.001, &msg(0x185, &[1, 2]));
        s.on_message(5, 1.002, &msg(0x285, &[3, 4, 5]));
        s.on_message(5, 1.003, &msg(0x186, &[9, 9]));
        assert_eq!(s.after_sync(1, first), Some(&[1u8, 2][..]));
        assert_eq!(s.after_sync(2, first), Some(&[3u8, 4, 5][..]));
        assert_eq!(s.after_sync(3, first), None);
        assert_eq!(s.after_sync(0, first), None);
        assert_eq!(s.after_sync(9, first), None);
        assert_eq!(s.received(), 3, "node 6's TPDO is not counted");
        // The next SYNC: TPDO2 answers it, TPDO1 not yet.
        s.on_message(5, 1.1, &msg(0x080, &[]));
        let second = s.last_sync().expect("sync");
        assert_eq!(second, SyncMark { seq: 2, t_s: 1.1 });
        s.on_message(5, 1.101, &msg(0x285, &[6]));
        assert_eq!(s.after_sync(1, second), None, "TPDO1 still of SYNC 1");
        assert_eq!(s.after_sync(2, second), Some(&[6u8][..]));
        assert_eq!(s.after_sync(2, first), None, "replaced by SYNC 2's");
        // A SYNC with a counter byte counts the same.
        s.on_message(5, 1.2, &msg(0x080, &[3]));
        assert_eq!(s.last_sync().map(|m| m.seq), Some(3));
        // Read event-driven, the newest frame counts, SYNC or not, with its time.
        assert_eq!(s.latest(1), Some((1.001, &[1u8, 2][..])));
        assert_eq!(s.latest(2), Some((1.101, &[6u8][..])));
        assert_eq!(s.latest(3), None);
        assert_eq!(s.latest(0), None);
    }

    #[test]
    fn a_sync_older_than_max_age_is_not_current() {
        let mut s = PdoStore::default();
        assert_eq!(s.current_sync(0.0, 0.2), None, "none seen");
        s.on_message(5, 10.0, &msg(0x080, &[]));
        assert_eq!(s.current_sync(10.2, 0.2).map(|m| m.seq), Some(1));
        assert_eq!(s.current_sync(10.21, 0.2), None, "producer stopped");
        s.on_message(5, 10.3, &msg(0x080, &[]));
        assert_eq!(s.current_sync(10.4, 0.2).map(|m| m.seq), Some(2));
    }
}
