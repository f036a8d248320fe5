//! Field-device polling.
//!
//! A [`DevicePoller`] reads every channel of one device (one Modbus unit) in as few
//! requests as [`plan::plan`] allows and turns the answer into per-channel results.
//! A device exception ("the device answered no") is kept apart from a transport
//! fault ("no answer"): only the latter rebuilds the connection. Devices sharing an
//! RTU line share one [`modbus::ModbusLink`] behind a mutex, so requests on the line
//! never interleave; a dead unit on that line delays the others by its timeout but
//! never stops them.

pub mod can;
pub mod config;
pub mod modbus;
pub mod plan;

use std::sync::Arc;
use std::time::Duration;

use tokio::sync::Mutex;
use tokio::time::Instant;
use tokio_modbus::ExceptionCode;

use compgate_core::channel::Reason;
use modbus::{exception_name, Backoff, ModbusLink};
use plan::{ByteOrder, DataType, ReadBlock, RegisterKind, Slot};

/// Errors of the source layer.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SourceError {
    /// Connecting took longer than the connect timeout.
    #[error("connect timed out")]
    ConnectTimeout,
    /// Connecting failed.
    #[error("connect failed: {0}")]
    Connect(String),
    /// No reply within the request timeout.
    #[error("no reply within {0:?}")]
    Timeout(Duration),
    /// The poll cycle's deadline passed before this read was answered; the reads left
    /// were given up for this cycle.
    #[error(
        "not answered within the poll cycle's deadline of {} s (the larger of \
         poll_interval_s and timeout_s): the device's reads take longer together; raise \
         poll_interval_s or lower timeout_s",
        .0.as_secs_f64()
    )]
    Deadline(Duration),
    /// The transport failed (reset, EOF, garbled frame).
    #[error("transport fault: {0}")]
    Transport(String),
    /// A reply arrived that is no valid answer to the request: a bad CRC, noise, an
    /// adapter's echo, another unit or function, a wrong register count.
    #[error("bad reply on {link}: {detail}")]
    Frame {
        /// The serial path or "host:port".
        link: String,
        /// What was wrong with it.
        detail: String,
    },
    /// One read of a poll cycle failed with `source`.
    #[error("{read}: {source}{}", hint.as_deref().map(|h| format!(": {h}")).unwrap_or_default())]
    Read {
        /// The read: function, first register, count and the channels in it.
        read: Arc<str>,
        /// Why it failed.
        source: Box<SourceError>,
        /// What to change, where the answer points at the read's shape (see
        /// [`refused_read_hint`]).
        hint: Option<Arc<str>>,
    },
    /// The TCP peer at `address` closed the connection with a request unanswered.
    #[error(
        "connection closed by the peer at {address}{}",
        if *before_reply {
            " before it answered: a module that takes one connection at a time closes \
             the others; is another client connected to it (a second gateway, a SCADA, \
             `compgate probe` while the service runs)?"
        } else {
            ""
        }
    )]
    PeerClosed {
        /// "host:port".
        address: String,
        /// No request on this connection had been answered.
        before_reply: bool,
    },
    /// The TCP peer at `address` answered bytes no Modbus TCP frame begins with.
    #[error("the peer at {address} does not speak Modbus TCP: {detail}")]
    NotModbus {
        /// "host:port".
        address: String,
        /// What it answered.
        detail: String,
    },
    /// The device answered with a Modbus exception.
    #[error("device exception {}", exception_name(*.0))]
    Exception(ExceptionCode),
    /// Reconnect is backing off after failed attempts.
    #[error("reconnect backing off, next attempt in {0:?}")]
    BackingOff(Duration),
    /// Reconnect is backing off after the connect failure `cause`, kept so that the
    /// wait does not hide why the link is down.
    #[error("{cause} (next attempt in {:.1} s)", tenth_s_up(*next_attempt_in))]
    BackingOffAfter {
        /// The last connect attempt's error.
        cause: Box<SourceError>,
        /// Time left before the next attempt.
        next_attempt_in: Duration,
    },
    /// A CANopen node or its bus failed.
    #[error("{0}")]
    Can(can::CanError),
}

impl SourceError {
    /// The channel-quality reason this fault maps to.
    pub fn reason(&self) -> Reason {
        match self {
            // From a TCP-to-RTU gateway: the device behind it did not answer.
            Self::Exception(c) if gateway_exception(*c) => Reason::Comm,
            Self::Exception(_) => Reason::DeviceException,
            Self::Read { source, .. } => source.reason(),
            _ => Reason::Comm,
        }
    }

    /// Short kind name, for counters and status.
    pub fn kind(&self) -> &'static str {
        match self {
            Self::ConnectTimeout | Self::Connect(_) => "connect",
            Self::Timeout(_) => "timeout",
            Self::Deadline(_) => "deadline",
            Self::Frame { .. } => "frame",
            Self::Transport(_) | Self::PeerClosed { .. } | Self::NotModbus { .. } => "transport",
            Self::Exception(_) => "exception",
            // Counted as the cycles the backoff failed (`compgate_device_errors_total`),
            // not as connect attempts.
            Self::BackingOff(_) | Self::BackingOffAfter { .. } => "backoff",
            Self::Can(e) => e.kind(),
            Self::Read { source, .. } => source.kind(),
        }
    }

    /// The refusal of a link still backing off: no request went out.
    fn is_backoff(&self) -> bool {
        matches!(self, Self::BackingOff(_) | Self::BackingOffAfter { .. })
    }
}

/// `d` in s, rounded up to 0.1 s: an attempt a few ms away does not read "in 0.0 s".
fn tenth_s_up(d: Duration) -> f64 {
    (d.as_secs_f64() * 10.0).ceil() / 10.0
}

/// A link shared by the devices on it.
pub type SharedLink = Arc<Mutex<ModbusLink>>;

/// Where one channel sits on its device and how it is encoded.
#[derive(Debug, Clone, PartialEq)]
pub struct ChannelSpec {
    /// Index of the channel in the gateway.
    pub channel: usize,
    /// Channel name, for the errors of the read that holds it.
    pub name: Arc<str>,
    /// Register table.
    pub kind: RegisterKind,
    /// 0-based address.
    pub address: u16,
    /// Encoding.
    pub data_type: DataType,
    /// Byte order.
    pub byte_order: ByteOrder,
}

/// Why a channel got no value this cycle.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Fault {
    /// Reason for the channel's quality.
    pub reason: Reason,
    /// The device has failed for `degrade_after_cycles` cycles in a row.
    pub degraded: bool,
}

/// The outcome of one poll cycle of one device.
#[derive(Debug, Clone)]
pub struct DeviceSample {
    /// Device index.
    pub device: usize,
    /// When the cycle started.
    pub started: Instant,
    /// Time the cycle took on its line: its requests' round trips, not the wait for
    /// other devices on a shared line.
    pub elapsed: Duration,
    /// Raw value or fault for every channel of the device.
    pub values: Vec<(usize, Result<f64, Fault>)>,
    /// The first error of the cycle, if any.
    pub error: Option<SourceError>,
    /// The kind ([`SourceError::kind`]) of every request of the cycle that failed,
    /// retried ones included; a cycle the reconnect backoff refused is one `backoff`.
    pub faults: Vec<&'static str>,
    /// Connections the link has made so far (a rise means it reconnected).
    pub connects: u64,
}

impl DeviceSample {
    /// Whether the device answered at all this cycle: a channel got a value or an
    /// exception of the device's own (a TCP-to-RTU gateway's 0x0A/0x0B for it is no
    /// answer from it). A device one of whose reads fails while the others answer is up;
    /// only its channels in that read go bad.
    pub fn answered(&self) -> bool {
        self.error.is_none()
            || self.values.iter().any(|(_, v)| match v {
                Ok(_) => true,
                Err(f) => f.reason == Reason::DeviceException,
            })
    }
}

/// Polling parameters of one device.
#[derive(Debug, Clone)]
pub struct PollParams {
    /// Modbus unit id.
    pub unit_id: u8,
    /// How long one request waits for its reply. The device's own, also on a line
    /// or at an address it shares with others.
    pub timeout: Duration,
    /// Extra attempts after a transport fault within one cycle.
    pub retries: u32,
    /// Failed cycles in a row after which the device counts as degraded.
    pub degrade_after_cycles: u32,
    /// Largest gap merged into one read.
    pub max_gap_registers: u16,
    /// Most registers one read asks for.
    pub max_read_registers: u16,
    /// Longest time one poll cycle may take, every read, retry and reconnect
    /// included; the reads not done by then fail for this cycle.
    pub cycle_deadline: Duration,
    /// After each connect, how long the device's values are not used: a module that
    /// answers placeholders (0) until its inputs have settled.
    pub settle: Duration,
}

/// One channel's value in a poll cycle's reads.
#[derive(Debug, Clone)]
struct Decode {
    /// Index of the channel in the gateway.
    channel: usize,
    /// The read that holds it.
    block: usize,
    /// Its registers in that read.
    registers: std::ops::Range<usize>,
    data_type: DataType,
    byte_order: ByteOrder,
}

/// Polls one device.
#[derive(Debug)]
pub struct DevicePoller {
    index: usize,
    name: String,
    params: PollParams,
    link: SharedLink,
    blocks: Vec<ReadBlock>,
    /// Per block, what its errors call it: function, first register, count, channels.
    labels: Vec<Arc<str>>,
    /// Per block, what to change when a module refuses its shape.
    hints: Vec<ReadHints>,
    /// Where each channel's value is and how it is encoded, in channel order: see
    /// [`Self::poll`].
    decode: Vec<Decode>,
    failed_cycles: u32,
    /// The link's connects as the last cycle on it saw them: what a skipped cycle
    /// reports while another device holds the line.
    connects: u64,
    /// On a line shared with other devices: how often it is asked while it is
    /// silent (see [`Self::on_shared_line`]).
    silent: Option<Box<Silent>>,
    /// Until when its values are not used, after a connect ([`PollParams::settle`]).
    settling_until: Option<Instant>,
}

/// A device on a shared line that stopped answering: its timeouts would hold the
/// line's other devices up every cycle, so once degraded it is asked only when this
/// backoff allows (a device demoted, as gateways call it).
#[derive(Debug, Clone)]
struct Silent {
    backoff: Backoff,
    /// The last asked cycle's error while demoted: what each skipped cycle reports.
    cause: Option<SourceError>,
}

impl DevicePoller {
    /// A poller for device `index` named `name` reading `specs` over `link`.
    pub fn new(
        index: usize,
        name: String,
        params: PollParams,
        link: SharedLink,
        specs: Vec<ChannelSpec>,
    ) -> Self {
        let slots: Vec<Slot> = specs
            .iter()
            .enumerate()
            .map(|(i, s)| Slot {
                channel: i,
                kind: s.kind,
                address: s.address,
                len: s.data_type.registers(),
            })
            .collect();
        let blocks = plan::plan(&slots, params.max_gap_registers, params.max_read_registers);
        let labels = blocks.iter().map(|b| read_label(b, &specs)).collect();
        let hints = blocks.iter().map(|b| ReadHints::new(b, &name)).collect();
        let specs = &specs;
        let mut decode: Vec<Decode> = blocks
            .iter()
            .enumerate()
            .flat_map(|(block, b)| {
                b.members.iter().map(move |(slot, offset)| {
                    let spec = &specs[slot.channel];
                    Decode {
                        channel: spec.channel,
                        block,
                        registers: usize::from(*offset)..usize::from(offset + slot.len),
                        data_type: spec.data_type,
                        byte_order: spec.byte_order,
                    }
                })
            })
            .collect();
        decode.sort_by_key(|d| d.channel);
        Self {
            index,
            name,
            params,
            link,
            blocks,
            labels,
            hints,
            decode,
            failed_cycles: 0,
            connects: 0,
            silent: None,
            settling_until: None,
        }
    }

    /// The device shares its line with others: once degraded and silent (every
    /// read timed out), it is asked only when `backoff` allows, doubling from its
    /// first wait to its longest, until it answers again.
    pub fn on_shared_line(mut self, backoff: Backoff) -> Self {
        self.silent = Some(Box::new(Silent {
            backoff,
            cause: None,
        }));
        self
    }

    /// Device name from the config.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The reads one cycle makes.
    pub fn blocks(&self) -> &[ReadBlock] {
        &self.blocks
    }

    /// The shared link.
    pub fn link(&self) -> &SharedLink {
        &self.link
    }

    /// Takes over the link (with its open connection) and the failure count of
    /// `old`: a reload that did not change the device keeps its state.
    pub fn carry_over(&mut self, old: &DevicePoller) {
        self.link = old.link.clone();
        self.failed_cycles = old.failed_cycles;
        // The connection is the old one: no new settling for it.
        self.connects = old.connects;
        self.settling_until = old.settling_until;
        if let (Some(new), Some(old)) = (&mut self.silent, &old.silent) {
            *new = old.clone();
        }
    }

    /// Replaces the link (a reload moving a shared line onto the old link).
    pub fn set_link(&mut self, link: SharedLink) {
        self.link = link;
    }

    /// Failed cycles in a row.
    pub fn failed_cycles(&self) -> u32 {
        self.failed_cycles
    }

    /// Reads one block, retrying transport faults up to `retries` times while the
    /// cycle lasts; `faults` gets the kind of every request that failed. The error is
    /// the first attempt's: a retry refused by the backoff a failed connect started
    /// must not hide the connect's error.
    ///
    /// A connection that had answered and is found closed by the device (modules close
    /// idle connections, some after every reply) is no fault: the request goes out
    /// once more on a new connection, as neither a retry nor an error.
    async fn read_block(
        &self,
        link: &mut ModbusLink,
        block: &ReadBlock,
        faults: &mut Vec<&'static str>,
    ) -> Result<Vec<u16>, SourceError> {
        let mut first: Option<SourceError> = None;
        let mut attempt = 0;
        let mut resent = false;
        loop {
            if let Some(length) = link.cycle_over() {
                return Err(first.unwrap_or(SourceError::Deadline(length)));
            }
            let was_answering = link.has_answered();
            let e = match link
                .read(self.params.unit_id, block.kind, block.start, block.count)
                .await
            {
                Ok(regs) => return Ok(regs),
                Err(e) => e,
            };
            if e.is_backoff() {
                return Err(first.unwrap_or(e));
            }
            if was_answering && !resent && matches!(e, SourceError::PeerClosed { .. }) {
                resent = true;
                tracing::debug!(device = %self.name, error = %e, "the device closed a connection that had answered: the request goes out again on a new one");
                continue;
            }
            faults.push(e.kind());
            // 0x06: the module is busy now, a later request may pass.
            let transient = matches!(
                e,
                SourceError::Exception(ExceptionCode::ServerDeviceBusy)
                    | SourceError::Timeout(_)
                    | SourceError::Transport(_)
                    | SourceError::Frame { .. }
                    | SourceError::PeerClosed { .. }
                    | SourceError::NotModbus { .. }
                    | SourceError::Connect(_)
                    | SourceError::ConnectTimeout
            );
            // Behind a TCP-to-RTU gateway a retry would queue behind the request that
            // timed out, which the gateway still works on, and hold up the other units.
            let queued = link.is_shared_address()
                && matches!(e, SourceError::Timeout(_) | SourceError::Deadline(_));
            if !transient || queued || attempt >= self.params.retries {
                return Err(first.unwrap_or(e));
            }
            attempt += 1;
            tracing::debug!(device = %self.name, attempt, error = %e, "retrying read");
            first.get_or_insert(e);
        }
    }

    /// Runs one poll cycle.
    pub async fn poll(&mut self) -> DeviceSample {
        let started = Instant::now();
        if let Some(sample) = self.skip_while_silent(started) {
            return sample;
        }
        let mut first_error = None;
        let mut faults = Vec::new();
        // One lock for the whole cycle: on a shared RTU line the device's reads go
        // out back to back.
        let link = self.link.clone();
        let mut link = link.lock().await;
        let on_line = Instant::now();
        link.set_timeout(self.params.timeout);
        // One deadline for all blocks, counted from when the line is ours: a silent
        // device costs one deadline per cycle, not a timeout (and a reconnect) per block.
        let length = self.params.cycle_deadline;
        link.set_cycle_deadline(Some((Instant::now() + length, length)));
        let mut reads = Vec::with_capacity(self.blocks.len());
        for ((block, label), hints) in self.blocks.iter().zip(&self.labels).zip(&self.hints) {
            match self.read_block(&mut link, block, &mut faults).await {
                Ok(regs) => reads.push(Ok(regs)),
                Err(e) => {
                    tracing::debug!(device = %self.name, read = %label, error = %e, "read failed");
                    reads.push(Err(e.reason()));
                    first_error.get_or_insert_with(|| SourceError::Read {
                        read: label.clone(),
                        hint: hints.for_error(&e),
                        source: Box::new(e),
                    });
                }
            }
        }
        // No request failed, yet the cycle did: the backoff refused it.
        if let (Some(e), true) = (&first_error, faults.is_empty()) {
            faults.push(e.kind());
        }
        link.set_cycle_deadline(None);
        let connects = link.connects();
        if connects != self.connects && !self.params.settle.is_zero() {
            self.settling_until = Some(Instant::now() + self.params.settle);
            tracing::info!(device = %self.name, settle_s = self.params.settle.as_secs_f64(), "connected: its values are used once settle_s has passed");
        }
        self.connects = connects;
        drop(link);
        let settling = self.settling_until.is_some_and(|t| Instant::now() < t);
        // Values go out in channel order, not register order: the core loop then walks
        // its channel processors front to back, as the CPU's prefetcher expects. In
        // register order, channels whose names do not sort like their addresses are
        // visited at random (about 8 % of the gateway's CPU at 1M points/s).
        let mut values = Vec::with_capacity(self.decode.len());
        let mut failed = false;
        for d in &self.decode {
            let value = match &reads[d.block] {
                // Answered, but not yet to be believed: no value, and no failure.
                Ok(_) if settling => Err(Reason::NoData),
                Ok(regs) => regs
                    .get(d.registers.clone())
                    .and_then(|r| plan::decode(r, d.data_type, d.byte_order))
                    .ok_or(Reason::Comm),
                Err(reason) => Err(*reason),
            };
            failed |= value.as_ref().is_err_and(|r| *r != Reason::NoData);
            values.push((
                d.channel,
                value.map_err(|reason| Fault {
                    reason,
                    degraded: false,
                }),
            ));
        }
        self.failed_cycles = if failed {
            self.failed_cycles.saturating_add(1)
        } else {
            0
        };
        if self.failed_cycles >= self.params.degrade_after_cycles {
            for (_, value) in &mut values {
                if let Err(fault) = value {
                    fault.degraded = true;
                }
            }
        }
        let silent = reads.iter().all(Result::is_err)
            && first_error.as_ref().is_some_and(|e| match e.kind() {
                "timeout" | "deadline" => true,
                // A TCP-to-RTU gateway's 0x0A/0x0B: the unit behind it is silent.
                "exception" => e.reason() == Reason::Comm,
                _ => false,
            });
        self.note_silence(silent, first_error.as_ref());
        DeviceSample {
            connects,
            device: self.index,
            started,
            elapsed: on_line.elapsed(),
            values,
            error: first_error,
            faults,
        }
    }

    /// A cycle that does not go on the line: the device is demoted and its backoff
    /// has not run out. Its channels are bad as in a failed cycle, and the error says
    /// why it was silent and when it is asked next.
    fn skip_while_silent(&mut self, started: Instant) -> Option<DeviceSample> {
        let silent = self.silent.as_ref()?;
        let cause = silent.cause.clone()?;
        let left = silent.backoff.remaining(started)?;
        self.failed_cycles = self.failed_cycles.saturating_add(1);
        let values = self
            .decode
            .iter()
            .map(|d| {
                let fault = Fault {
                    reason: cause.reason(),
                    degraded: true,
                };
                (d.channel, Err(fault))
            })
            .collect();
        let connects = self.link.try_lock().map_or(self.connects, |l| l.connects());
        Some(DeviceSample {
            connects,
            device: self.index,
            started,
            elapsed: started.elapsed(),
            values,
            error: Some(SourceError::BackingOffAfter {
                cause: Box::new(cause),
                next_attempt_in: left,
            }),
            faults: vec!["backoff"],
        })
    }

    /// After a cycle that went on the line: a degraded device that was `silent`
    /// (every read timed out) is demoted, or stays so with a doubled wait; one that
    /// answered anything is asked every cycle again.
    fn note_silence(&mut self, silent: bool, error: Option<&SourceError>) {
        let degraded = self.failed_cycles >= self.params.degrade_after_cycles;
        let Some(s) = &mut self.silent else {
            return;
        };
        match error.filter(|_| silent && degraded) {
            Some(e) => {
                if s.cause.is_none() {
                    let first_s = s.backoff.current().as_secs_f64();
                    tracing::warn!(device = %self.name, first_s, "device {} is silent on the line it shares (a serial line, or a TCP address other devices use: a TCP-to-RTU gateway): it is asked again after {first_s} s, the wait doubling up to its backoff_max_s, so that its timeouts do not hold up the line's other devices", self.name);
                }
                s.backoff.failed(Instant::now());
                s.cause = Some(e.clone());
            }
            None => {
                if s.cause.take().is_some() {
                    tracing::info!(device = %self.name, "device {} answers again: asked every cycle", self.name);
                }
                s.backoff.reset();
            }
        }
    }
}

/// Exceptions a TCP-to-RTU gateway answers for the serial device behind it: 0x0A (no
/// path to it), 0x0B (it did not answer). The device is silent, not refusing.
fn gateway_exception(code: ExceptionCode) -> bool {
    matches!(
        code,
        ExceptionCode::GatewayPathUnavailable | ExceptionCode::GatewayTargetDevice
    )
}

/// What to change when a module refuses `block` of `device` with `error`, where the
/// read's shape (a merge across a gap, its size) is the likely cause.
pub fn refused_read_hint(block: &ReadBlock, device: &str, error: &SourceError) -> Option<Arc<str>> {
    ReadHints::new(block, device).for_error(error)
}

/// What to change when a module refuses a merged read, which `probe` (one channel at
/// a time) never shows: a read across registers no channel uses (exception 0x02 from
/// a map with holes), or more registers than the module takes at a time (0x03).
#[derive(Debug, Default)]
struct ReadHints {
    gap: Option<Arc<str>>,
    size: Option<Arc<str>>,
}

impl ReadHints {
    fn new(block: &ReadBlock, device: &str) -> Self {
        let mut used = vec![false; usize::from(block.count)];
        for (slot, offset) in &block.members {
            let from = usize::from(*offset);
            for u in used.iter_mut().skip(from).take(usize::from(slot.len)) {
                *u = true;
            }
        }
        let gap = used.iter().position(|u| !u).map(|first| {
            let run = used[first..].iter().take_while(|u| !**u).count();
            let more = if used[first + run..].contains(&false) {
                " (and more)"
            } else {
                ""
            };
            let at = |i: usize| u32::from(block.start) + i as u32;
            format!(
                "the read merges channels across registers {}..={}{more}, which no channel \
                 uses: a module without them refuses it; set \
                 devices.{device}.max_gap_registers = 0",
                at(first),
                at(first + run - 1)
            )
            .into()
        });
        let longest = block.members.iter().map(|(s, _)| s.len).max().unwrap_or(0);
        let size = (block.count > longest).then(|| {
            format!(
                "a module that reads fewer than {} registers at a time refuses it; set \
                 devices.{device}.max_read_registers to what its manual gives (e.g. 16)",
                block.count
            )
            .into()
        });
        Self { gap, size }
    }

    fn for_error(&self, e: &SourceError) -> Option<Arc<str>> {
        match e {
            SourceError::Exception(ExceptionCode::IllegalDataAddress) => {
                self.gap.clone().or_else(|| self.size.clone())
            }
            SourceError::Exception(ExceptionCode::IllegalDataValue) => {
                self.size.clone().or_else(|| self.gap.clone())
            }
            _ => None,
        }
    }
}

/// What the errors of `block` call it, e.g. "function 0x04 (input registers), address
/// 5, count 2 (T_a, T_b)": a few of its channels (`specs` by slot), then how many more.
fn read_label(block: &ReadBlock, specs: &[ChannelSpec]) -> Arc<str> {
    const NAMED: usize = 3;
    let (function, table) = match block.kind {
        RegisterKind::Input => (0x04, "input"),
        RegisterKind::Holding => (0x03, "holding"),
    };
    let mut channels: Vec<&str> = block
        .members
        .iter()
        .filter_map(|(slot, _)| specs.get(slot.channel).map(|s| &*s.name))
        .collect();
    channels.dedup();
    let more = channels.len().saturating_sub(NAMED);
    channels.truncate(NAMED);
    let mut named = channels.join(", ");
    if more > 0 {
        named.push_str(&format!(" and {more} more"));
    }
    format!(
        "function 0x{function:02X} ({table} registers), address {}, count {} ({named})",
        block.start, block.count
    )
    .into()
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering};

    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    use super::modbus::{Backoff, LinkSpec};
    use super::*;

    /// A poller of two reads (channels 100 registers apart) over `spec`, retrying once.
    fn poller(spec: LinkSpec) -> DevicePoller {
        poller_with(spec, Duration::from_secs(1), Duration::from_secs(2))
    }

    /// [`poller`] with a request timeout and a cycle deadline.
    fn poller_with(spec: LinkSpec, timeout: Duration, cycle_deadline: Duration) -> DevicePoller {
        let params = PollParams {
            unit_id: 1,
            timeout,
            retries: 1,
            degrade_after_cycles: 3,
            max_gap_registers: 0,
            max_read_registers: plan::MAX_READ_REGISTERS,
            cycle_deadline,
            settle: Duration::ZERO,
        };
        u16_poller(spec, params, &[0, 100])
    }

    /// A poller of device `ain1` over `spec` reading u16 input channels at `registers`.
    fn u16_poller(spec: LinkSpec, params: PollParams, registers: &[u16]) -> DevicePoller {
        let link = ModbusLink::new(
            spec,
            params.timeout,
            Backoff::new(Duration::from_millis(500), Duration::from_secs(10)),
        );
        let specs = registers
            .iter()
            .enumerate()
            .map(|(channel, &address)| ChannelSpec {
                channel,
                name: format!("c{address}").into(),
                kind: RegisterKind::Input,
                address,
                data_type: DataType::U16,
                byte_order: ByteOrder::Abcd,
            })
            .collect();
        DevicePoller::new(0, "ain1".into(), params, Arc::new(Mutex::new(link)), specs)
    }

    /// A Modbus TCP device answering each read-input-registers request by what
    /// `answer` says of its first register and the request's number (from 0): after a
    /// delay, the register value or an exception code.
    async fn device(
        answer: impl Fn(u16, usize) -> (Duration, Result<u16, u8>) + Send + Sync + 'static,
    ) -> (String, tokio::task::JoinHandle<()>) {
        let answer = Arc::new(answer);
        let requests = Arc::new(AtomicUsize::new(0));
        let (address, _, task) = listener(move |mut stream| {
            let (answer, requests) = (answer.clone(), requests.clone());
            async move {
                // MBAP header (7 bytes) + function, address, count.
                let mut req = [0u8; 12];
                while stream.read_exact(&mut req).await.is_ok() {
                    let start = u16::from_be_bytes([req[8], req[9]]);
                    let n = requests.fetch_add(1, Ordering::SeqCst);
                    let (delay, value) = answer(start, n);
                    tokio::time::sleep(delay).await;
                    let pdu = match value {
                        Ok(v) => vec![req[7], 2, (v >> 8) as u8, v as u8],
                        Err(code) => vec![req[7] | 0x80, code],
                    };
                    let mut reply = req[..7].to_vec();
                    reply[4..6].copy_from_slice(&(pdu.len() as u16 + 1).to_be_bytes());
                    reply.extend(pdu);
                    if stream.write_all(&reply).await.is_err() {
                        break;
                    }
                }
            }
        })
        .await;
        (address, task)
    }

    // An exception on one read failed the whole device ("link down") and named no
    // register or channel: the error names the read, the other channel reads good.
    #[tokio::test]
    async fn a_failed_read_is_named_and_the_device_still_answers() {
        let (address, peer) = device(|start, _| match start {
            100 => (Duration::ZERO, Err(0x02)),
            _ => (Duration::ZERO, Ok(1775)),
        })
        .await;
        let mut poller = poller(tcp(&address));
        let sample = poller.poll().await;
        let error = sample.error.clone().expect("a read failed");
        assert_eq!(
            error.to_string(),
            "function 0x04 (input registers), address 100, count 1 (c100): device exception \
             0x02 illegal data address"
        );
        assert!(sample.answered());
        assert_eq!(sample.faults, ["exception"]);
        assert_eq!(sample.values[0].1, Ok(1775.0));
        assert!(sample.values[1].1.is_err());
        peer.abort();
    }

    /// A poller without retries of u16 input channels at `registers` (merged across
    /// gaps of up to 8) from the device at `address`.
    fn poller_of(address: &str, registers: &[u16]) -> DevicePoller {
        let params = PollParams {
            unit_id: 1,
            timeout: Duration::from_secs(1),
            retries: 0,
            degrade_after_cycles: 3,
            max_gap_registers: 8,
            max_read_registers: plan::MAX_READ_REGISTERS,
            cycle_deadline: Duration::from_secs(2),
            settle: Duration::ZERO,
        };
        u16_poller(tcp(address), params, registers)
    }

    // A module that closes the connection after each reply (or an idle one) failed
    // a read every cycle without retries, and cost a counted transport error with
    // them: the request goes out again on a new connection, as no fault.
    #[tokio::test]
    async fn a_connection_the_device_closes_after_answering_is_no_fault() {
        let (address, _, peer) = listener(|mut stream| async move {
            let mut req = [0u8; 12];
            if stream.read_exact(&mut req).await.is_ok() {
                let mut reply = req[..7].to_vec();
                reply[4..6].copy_from_slice(&5u16.to_be_bytes());
                reply.extend([req[7], 2, 0x06, 0xEF]);
                let _ = stream.write_all(&reply).await;
            }
        })
        .await;
        let mut poller = poller_of(&address, &[0, 100]);
        for cycle in 0..4 {
            let sample = poller.poll().await;
            assert_eq!(sample.error, None, "cycle {cycle}");
            assert!(
                sample.faults.is_empty(),
                "cycle {cycle}: {:?}",
                sample.faults
            );
            assert!(
                sample.values.iter().all(|(_, v)| *v == Ok(1775.0)),
                "{sample:?}"
            );
        }
        peer.abort();
    }

    // A module refusing a merged read (a map with holes: 0x02; more registers than it
    // takes: 0x03) left every channel of the read bad with only the exception named,
    // though `probe`, reading one channel at a time, showed them good: the error names
    // the key to change.
    #[tokio::test]
    async fn a_refused_merged_read_names_the_key_to_change() {
        let (address, peer) = device(|_, _| (Duration::ZERO, Err(0x02))).await;
        let (address3, peer3) = device(|_, _| (Duration::ZERO, Err(0x03))).await;
        let holes = poller_of(&address, &[0, 1, 8]).poll().await;
        assert_eq!(
            holes.error.expect("refused").to_string(),
            "function 0x04 (input registers), address 0, count 9 (c0, c1, c8): device \
             exception 0x02 illegal data address: the read merges channels across registers \
             2..=7, which no channel uses: a module without them refuses it; set \
             devices.ain1.max_gap_registers = 0"
        );
        let many: Vec<u16> = (0..20).collect();
        let large = poller_of(&address3, &many).poll().await;
        let text = large.error.expect("refused").to_string();
        assert!(
            text.contains(
                "0x03 illegal data value: a module that reads fewer than 20 \
                 registers at a time refuses it; set devices.ain1.max_read_registers"
            ),
            "{text}"
        );
        // A one-channel read refused: nothing about the read's shape to change.
        let one = poller_of(&address, &[40]).poll().await;
        let text = one.error.expect("refused").to_string();
        assert!(text.ends_with("0x02 illegal data address"), "{text}");
        peer.abort();
        peer3.abort();
    }

    // A device answering each read within its timeout, but both reads not within the
    // poll interval: the second read was cut every cycle, and the log said only "poll
    // cycle deadline of 500ms passed before every read was answered".
    #[tokio::test]
    async fn a_read_the_cycle_deadline_cuts_is_named_with_what_to_change() {
        let (address, peer) = device(|_, _| (Duration::from_millis(600), Ok(1775))).await;
        let mut poller = poller_with(
            tcp(&address),
            Duration::from_secs(1),
            Duration::from_secs(1),
        );
        let sample = poller.poll().await;
        let error = sample.error.clone().expect("the second read was cut");
        let text = error.to_string();
        assert!(
            text.starts_with("function 0x04 (input registers), address 100, count 1 (c100): ")
                && text.contains("raise poll_interval_s"),
            "{text}"
        );
        assert_eq!(error.kind(), "deadline");
        assert_eq!(sample.values[0].1, Ok(1775.0));
        assert!(sample.answered());
        peer.abort();
    }

    // A timeout the retry made good was counted nowhere.
    #[tokio::test]
    async fn a_fault_the_retry_makes_good_is_still_counted() {
        let (address, peer) = device(|_, n| match n {
            0 => (Duration::from_secs(5), Ok(0)),
            _ => (Duration::ZERO, Ok(1775)),
        })
        .await;
        let mut poller = poller_with(
            tcp(&address),
            Duration::from_millis(200),
            Duration::from_secs(2),
        );
        let sample = poller.poll().await;
        assert_eq!(sample.error, None);
        assert_eq!(sample.faults, ["timeout"]);
        peer.abort();
    }

    /// A TCP listener on loopback that runs `serve` on every connection it accepts;
    /// returns its address and the count of accepts.
    async fn listener<F, Fut>(serve: F) -> (String, Arc<AtomicUsize>, tokio::task::JoinHandle<()>)
    where
        F: Fn(tokio::net::TcpStream) -> Fut + Send + 'static,
        Fut: std::future::Future<Output = ()> + Send + 'static,
    {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap().to_string();
        let accepts = Arc::new(AtomicUsize::new(0));
        let counted = accepts.clone();
        let task = tokio::spawn(async move {
            while let Ok((stream, _)) = listener.accept().await {
                counted.fetch_add(1, Ordering::SeqCst);
                tokio::spawn(serve(stream));
            }
        });
        (address, accepts, task)
    }

    fn tcp(address: &str) -> LinkSpec {
        LinkSpec::Tcp {
            address: address.into(),
            connect_timeout: Duration::from_secs(1),
        }
    }

    // A demoted device's skipped cycle, while another device held the shared line,
    // reported 0 connects (review S): it reports the last count its cycles saw.
    #[tokio::test]
    async fn a_skipped_cycle_reports_the_links_connects_while_the_line_is_busy() {
        let (address, _, peer) = listener(|stream| async move {
            tokio::time::sleep(Duration::from_secs(60)).await;
            drop(stream);
        })
        .await;
        let params = PollParams {
            unit_id: 1,
            timeout: Duration::from_millis(50),
            retries: 0,
            degrade_after_cycles: 1,
            max_gap_registers: 0,
            max_read_registers: plan::MAX_READ_REGISTERS,
            cycle_deadline: Duration::from_millis(100),
            settle: Duration::ZERO,
        };
        let mut poller = u16_poller(tcp(&address), params, &[0]).on_shared_line(Backoff::new(
            Duration::from_secs(10),
            Duration::from_secs(10),
        ));
        let asked = poller.poll().await;
        assert!(asked.error.is_some() && asked.connects == 1, "{asked:?}");
        // Another device's cycle holds the line.
        let link = poller.link().clone();
        let _busy = link.lock().await;
        let skipped = poller.poll().await;
        assert!(
            matches!(skipped.error, Some(SourceError::BackingOffAfter { .. })),
            "{skipped:?}"
        );
        assert_eq!(skipped.connects, 1);
        peer.abort();
    }

    // A peer that accepts and closes at once used to be reconnected twice a cycle (the
    // read and its retry) forever, and reported "Operation now in progress (os error
    // 115)": tokio-modbus's stale errno for an end of stream.
    #[tokio::test]
    async fn a_peer_that_accepts_and_closes_is_retried_with_a_growing_backoff() {
        let (address, accepts, peer) = listener(|stream| async move { drop(stream) }).await;
        let mut poller = poller(tcp(&address));
        let closed = format!("connection closed by the peer at {address}");
        let end = Instant::now() + Duration::from_secs(3);
        let mut cycles = 0u32;
        while Instant::now() < end {
            let sample = poller.poll().await;
            let error = sample.error.expect("the cycle failed");
            assert!(error.to_string().contains(&closed), "{error}");
            cycles += 1;
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        // Attempts at 0, 0.5, 1.5 and 3.5 s (0.5 s doubling): 3, give or take one.
        let accepts = accepts.load(Ordering::SeqCst);
        assert!(cycles > 30, "{cycles} cycles");
        assert!((2..10).contains(&accepts), "{accepts} connects in 3 s");
        peer.abort();
    }

    // An HTTP server answers the Modbus request with a 400 and closes: tokio-modbus
    // said "bytes remaining on stream".
    #[tokio::test]
    async fn a_peer_answering_http_does_not_speak_modbus() {
        let (address, accepts, peer) = listener(|mut stream| async move {
            let mut request = [0u8; 64];
            let _ = stream.read(&mut request).await;
            let _ = stream.write_all(b"HTTP/1.1 400 Bad Request\r\n\r\n").await;
        })
        .await;
        let mut poller = poller(tcp(&address));
        let expected = format!(
            "the peer at {address} does not speak Modbus TCP: it answered \"HTTP/1.1 400 Bad Request\\r\\n\\r\\n\""
        );
        for cycle in 0..3 {
            let error = poller.poll().await.error.expect("the cycle failed");
            assert!(
                error.to_string().contains(&expected),
                "cycle {cycle}: {error}"
            );
        }
        assert_eq!(accepts.load(Ordering::SeqCst), 1, "backing off");
        peer.abort();
    }

    // The retry of a failed connect, and every cycle after it, meet the backoff: they
    // must still say why the link is down. The cycle that tried to connect is counted
    // and reported as a failed connect: with `retries = 1` the retry met the backoff,
    // and the first line said "backoff" for a refused connection.
    #[tokio::test]
    async fn a_failed_connect_is_reported_as_such_and_stays_the_cause_while_backing_off() {
        let closed = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let address = closed.local_addr().unwrap().to_string();
        drop(closed);
        let cases = [
            (
                LinkSpec::Tcp {
                    address: address.clone(),
                    connect_timeout: Duration::from_secs(1),
                },
                format!("connect failed: {address}: Connection refused"),
            ),
            (
                LinkSpec::Rtu {
                    path: "/dev/ttyNOPE0".into(),
                    baud: 9600,
                    parity: tokio_serial::Parity::None,
                    stop_bits: tokio_serial::StopBits::One,
                },
                "connect failed: /dev/ttyNOPE0: ".to_string(),
            ),
        ];
        for (spec, cause) in cases {
            let mut poller = poller(spec);
            // The first cycle connects and fails; the second falls in the backoff.
            for (cycle, kind) in [(0, "connect"), (1, "backoff")] {
                let sample = poller.poll().await;
                let error = sample.error.clone().expect("the cycle failed");
                let text = error.to_string();
                let read = "function 0x04 (input registers), address 0, count 1 (c0): ";
                assert!(
                    text.starts_with(&format!("{read}{cause}")),
                    "cycle {cycle}: {text}"
                );
                assert_eq!(
                    text.contains("(next attempt in 0."),
                    cycle == 1,
                    "cycle {cycle}: {text}"
                );
                assert_eq!(error.kind(), kind);
                assert_eq!(sample.faults, [kind], "cycle {cycle}");
                assert!(!sample.answered());
                assert!(sample.values.iter().all(|(_, v)| v.is_err()));
            }
        }
    }
}
