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
use modbus::{exception_name, ModbusLink};
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
    /// The poll cycle's deadline passed before every read was answered; the reads
    /// left were given up for this cycle.
    #[error("poll cycle deadline of {0:?} passed before every read was answered")]
    Deadline(Duration),
    /// The transport failed (reset, EOF, garbled frame).
    #[error("transport fault: {0}")]
    Transport(String),
    /// The TCP peer at this address closed the connection with a request unanswered.
    #[error("connection closed by the peer at {0}")]
    PeerClosed(String),
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
            Self::Exception(_) => Reason::DeviceException,
            _ => Reason::Comm,
        }
    }

    /// Short kind name, for counters and status.
    pub fn kind(&self) -> &'static str {
        match self {
            Self::ConnectTimeout | Self::Connect(_) => "connect",
            Self::Timeout(_) | Self::Deadline(_) => "timeout",
            Self::Transport(_) | Self::PeerClosed(_) | Self::NotModbus { .. } => "transport",
            Self::Exception(_) => "exception",
            // Counted as the cycles the backoff failed (`compgate_device_errors_total`),
            // not as connect attempts.
            Self::BackingOff(_) | Self::BackingOffAfter { .. } => "backoff",
            Self::Can(e) => e.kind(),
        }
    }
}

/// `d` in s, rounded up to 0.1 s: an attempt a few ms away does not read "in 0.0 s".
fn tenth_s_up(d: Duration) -> f64 {
    (d.as_secs_f64() * 10.0).ceil() / 10.0
}

/// A link shared by the devices on it.
pub type SharedLink = Arc<Mutex<ModbusLink>>;

/// Where one channel sits on its device and how it is encoded.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChannelSpec {
    /// Index of the channel in the gateway.
    pub channel: usize,
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
    /// Time the cycle took.
    pub elapsed: Duration,
    /// Raw value or fault for every channel of the device.
    pub values: Vec<(usize, Result<f64, Fault>)>,
    /// The first error of the cycle, if any.
    pub error: Option<SourceError>,
    /// Connections the link has made so far (a rise means it reconnected).
    pub connects: u64,
}

/// Polling parameters of one device.
#[derive(Debug, Clone)]
pub struct PollParams {
    /// Modbus unit id.
    pub unit_id: u8,
    /// Extra attempts after a transport fault within one cycle.
    pub retries: u32,
    /// Failed cycles in a row after which the device counts as degraded.
    pub degrade_after_cycles: u32,
    /// Largest gap merged into one read.
    pub max_gap_registers: u16,
    /// Longest time one poll cycle may take, every read, retry and reconnect
    /// included; the reads not done by then fail for this cycle.
    pub cycle_deadline: Duration,
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
    /// Where each channel's value is and how it is encoded, in channel order: see
    /// [`Self::poll`].
    decode: Vec<Decode>,
    failed_cycles: u32,
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
        let blocks = plan::plan(&slots, params.max_gap_registers);
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
            decode,
            failed_cycles: 0,
        }
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
    }

    /// Replaces the link (a reload moving a shared serial line onto the old link).
    pub fn set_link(&mut self, link: SharedLink) {
        self.link = link;
    }

    /// Failed cycles in a row.
    pub fn failed_cycles(&self) -> u32 {
        self.failed_cycles
    }

    /// Reads one block, retrying transport faults up to `retries` times.
    async fn read_block(
        &self,
        link: &mut ModbusLink,
        block: &ReadBlock,
    ) -> Result<Vec<u16>, SourceError> {
        let mut attempt = 0;
        loop {
            let result = link
                .read(self.params.unit_id, block.kind, block.start, block.count)
                .await;
            match result {
                Err(
                    e @ (SourceError::Timeout(_)
                    | SourceError::Transport(_)
                    | SourceError::PeerClosed(_)
                    | SourceError::NotModbus { .. }
                    | SourceError::Connect(_)
                    | SourceError::ConnectTimeout),
                ) if attempt < self.params.retries => {
                    attempt += 1;
                    tracing::debug!(device = %self.name, attempt, error = %e, "retrying read");
                }
                other => return other,
            }
        }
    }

    /// Runs one poll cycle.
    pub async fn poll(&mut self) -> DeviceSample {
        let started = Instant::now();
        let mut first_error = None;
        // One lock for the whole cycle: on a shared RTU line the device's reads go
        // out back to back.
        let link = self.link.clone();
        let mut link = link.lock().await;
        // One deadline for all blocks, counted from when the line is ours: a silent
        // device costs one deadline per cycle, not a timeout (and a reconnect) per block.
        let length = self.params.cycle_deadline;
        link.set_cycle_deadline(Some((Instant::now() + length, length)));
        let mut reads = Vec::with_capacity(self.blocks.len());
        for block in &self.blocks {
            match self.read_block(&mut link, block).await {
                Ok(regs) => reads.push(Ok(regs)),
                Err(e) => {
                    tracing::debug!(device = %self.name, start = block.start, count = block.count, error = %e, "read failed");
                    reads.push(Err(e.reason()));
                    first_error.get_or_insert(e);
                }
            }
        }
        link.set_cycle_deadline(None);
        let connects = link.connects();
        drop(link);
        // Values go out in channel order, not register order: the core loop then walks
        // its channel processors front to back, as the CPU's prefetcher expects. In
        // register order, channels whose names do not sort like their addresses are
        // visited at random (about 8 % of the gateway's CPU at 1M points/s).
        let mut values = Vec::with_capacity(self.decode.len());
        let mut failed = false;
        for d in &self.decode {
            let value = match &reads[d.block] {
                Ok(regs) => regs
                    .get(d.registers.clone())
                    .and_then(|r| plan::decode(r, d.data_type, d.byte_order))
                    .ok_or(Reason::Comm),
                Err(reason) => Err(*reason),
            };
            failed |= value.is_err();
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
        DeviceSample {
            connects,
            device: self.index,
            started,
            elapsed: started.elapsed(),
            values,
            error: first_error,
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering};

    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    use super::modbus::{Backoff, LinkSpec};
    use super::*;

    /// A poller of two reads (channels 100 registers apart) over `spec`, retrying once.
    fn poller(spec: LinkSpec) -> DevicePoller {
        let link = ModbusLink::new(
            spec,
            Duration::from_secs(1),
            Backoff::new(Duration::from_millis(500), Duration::from_secs(10)),
        );
        let spec = |channel, address| ChannelSpec {
            channel,
            kind: RegisterKind::Input,
            address,
            data_type: DataType::U16,
            byte_order: ByteOrder::Abcd,
        };
        DevicePoller::new(
            0,
            "ain1".into(),
            PollParams {
                unit_id: 1,
                retries: 1,
                degrade_after_cycles: 3,
                max_gap_registers: 0,
                cycle_deadline: Duration::from_secs(2),
            },
            Arc::new(Mutex::new(link)),
            vec![spec(0, 0), spec(1, 100)],
        )
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
            assert!(error.to_string().starts_with(&closed), "{error}");
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
                error.to_string().starts_with(&expected),
                "cycle {cycle}: {error}"
            );
        }
        assert_eq!(accepts.load(Ordering::SeqCst), 1, "backing off");
        peer.abort();
    }

    // The retry of a failed connect, and every cycle after it, meet the backoff: they
    // must still say why the link is down, not only when it tries again.
    #[tokio::test]
    async fn a_failed_connect_stays_the_reported_error_while_backing_off() {
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
            for cycle in 0..2 {
                let sample = poller.poll().await;
                let error = sample.error.expect("the cycle failed");
                let text = error.to_string();
                assert!(
                    text.starts_with(&cause) && text.ends_with(" s)"),
                    "cycle {cycle}: {text}"
                );
                assert!(
                    text.contains("(next attempt in 0."),
                    "cycle {cycle}: {text}"
                );
                assert_eq!(error.kind(), "backoff");
                assert!(sample.values.iter().all(|(_, v)| v.is_err()));
            }
        }
    }
}
