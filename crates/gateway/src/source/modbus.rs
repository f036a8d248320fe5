//! A Modbus client connection that survives the field.
//!
//! tokio-modbus leaves four gaps this type closes: every request is wrapped in a
//! timeout; connecting has its own timeout; TCP sockets get `TCP_NODELAY`; and after
//! any transport error or timeout the context is dropped and rebuilt, because a late
//! reply left in the old stream would otherwise be read as the answer to the next
//! request (tokio-modbus issue 324). The one exception: at a TCP address several units
//! share (a TCP-to-RTU gateway), a timeout keeps the connection, and a late reply is
//! dropped by its transaction id ([`ModbusLink::shared_address`]). Reconnects back off
//! exponentially up to a cap.
//! While a poll cycle runs, its deadline also bounds every request and connect, so a
//! cycle of many reads to a silent device ends after one deadline.
//!
//! On TCP, a connection that fails other than by a timeout before its first good reply
//! counts as a failed connect for the backoff: a peer that accepts and then closes, or
//! answers something other than Modbus, is retried as slowly as one that refuses. Such
//! faults are named with the peer's address (tokio-modbus reports a closed peer with a
//! stale errno and a peer answering HTTP with "bytes remaining on stream").
//!
//! RTU frames carry no transaction id: a reply that comes after its request's timeout
//! would be taken as the answer to the next request for as many registers. So after
//! the serial port is opened (at start and after every failed exchange) no request
//! goes out before the line has been quiet for [`rtu_guard`]; what arrives until then
//! is dropped. A link whose exchanges succeed keeps its port and never waits.

pub mod config;

use std::borrow::Cow;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::{Arc, Mutex, PoisonError};
use std::task::{Context as TaskContext, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;
use tokio::time::{Instant, Sleep};
use tokio_modbus::client::{rtu, tcp, Client, Context};
use tokio_modbus::prelude::SlaveContext;
use tokio_modbus::prelude::{Request, Response};
use tokio_modbus::{ExceptionCode, Slave};
use tokio_serial::SerialPort;

use super::plan::RegisterKind;
use super::SourceError;

/// Where a Modbus link goes.
#[derive(Debug, Clone, PartialEq)]
pub enum LinkSpec {
    /// Modbus TCP.
    Tcp {
        /// "host:port".
        address: String,
        /// Connect timeout.
        connect_timeout: Duration,
    },
    /// Modbus RTU on a serial line.
    Rtu {
        /// Serial device path.
        path: String,
        /// Baud rate.
        baud: u32,
        /// Parity.
        parity: tokio_serial::Parity,
        /// Stop bits.
        stop_bits: tokio_serial::StopBits,
    },
}

impl std::fmt::Display for LinkSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Tcp { address, .. } => write!(f, "tcp://{address}"),
            Self::Rtu { path, baud, .. } => write!(f, "rtu://{path}@{baud}"),
        }
    }
}

/// Capped exponential backoff between reconnect attempts.
#[derive(Debug, Clone)]
pub struct Backoff {
    initial: Duration,
    max: Duration,
    current: Duration,
    not_before: Option<Instant>,
}

impl Backoff {
    /// A backoff starting at `initial`, doubling up to `max`.
    pub fn new(initial: Duration, max: Duration) -> Self {
        Self {
            initial,
            max,
            current: initial,
            not_before: None,
        }
    }

    /// Time left before the next attempt is allowed.
    pub fn remaining(&self, now: Instant) -> Option<Duration> {
        self.not_before
            .and_then(|t| t.checked_duration_since(now))
            .filter(|d| !d.is_zero())
    }

    /// Records a failed attempt: the next one waits the current delay, which doubles.
    pub fn failed(&mut self, now: Instant) {
        self.not_before = Some(now + self.current);
        self.current = (self.current * 2).min(self.max);
    }

    /// Records a success: the delay starts over.
    pub fn reset(&mut self) {
        self.current = self.initial;
        self.not_before = None;
    }

    /// The delay the next failure will impose.
    pub fn current(&self) -> Duration {
        self.current
    }

    /// Takes `other`'s first and longest delay, keeping where this one stands between
    /// them.
    fn retune(&mut self, other: &Backoff) {
        self.initial = other.initial;
        self.max = other.max;
        self.current = self.current.clamp(self.initial, self.max.max(self.initial));
    }
}

/// One Modbus connection (TCP socket or serial line) with its own recovery.
pub struct ModbusLink {
    spec: LinkSpec,
    timeout: Duration,
    ctx: Option<Context>,
    /// The request deadline, kept for the link's life and pushed forward per request:
    /// tokio extends a registered timer with one atomic step, where a new
    /// `tokio::time::timeout` per request registers and removes a timer-wheel entry
    /// each time (a few tenths of a microsecond on a 9 us loopback read). Made on first
    /// use, inside the runtime.
    deadline: Option<Pin<Box<Sleep>>>,
    /// The end of the poll cycle under way and its length: no request or connect
    /// outlasts it (see [`Self::set_cycle_deadline`]).
    cycle: Option<(Instant, Duration)>,
    /// No request of the cycle under way has gone out yet.
    cycle_fresh: bool,
    backoff: Backoff,
    /// Why the last connect (or connection before its first good reply) failed: what
    /// a request refused by the backoff reports. Boxed: the link sits in every NC
    /// writer, and the error is rare and large.
    connect_error: Option<Box<SourceError>>,
    /// The open connection has given a good reply (see [`Self::fault`]).
    answered: bool,
    /// What the TCP peer of the open connection sent and whether it closed.
    peer: Option<Arc<Mutex<PeerSeen>>>,
    /// Connections made so far, for status and tests.
    connects: u64,
    /// The unit whose request timed out last, until a good reply or the next open of
    /// the serial port: a reply the drain after it finds is most likely its, late.
    /// With the timeout its request waited (on a shared line another device's may be
    /// shorter, and the wait for a quiet line must let this one's late reply pass).
    timed_out: Option<(u8, Duration)>,
    /// When the last late reply was logged at WARN, and how many were not logged
    /// since (one WARN per [`LATE_REPLY_LOG_EVERY`]).
    late_logged: Option<Instant>,
    late_unlogged: u64,
    /// Several units at this TCP address: see [`Self::shared_address`].
    shared_address: bool,
    /// A request timed out on this connection and may still be under way at the peer
    /// for as long as it waited: the next request waits that much longer.
    busy_after_timeout: Option<Duration>,
}

/// A connection at a shared TCP address with a frame from its peer this recently
/// outlives a timeout (see [`ModbusLink::outlives_timeout`]).
const LIFE_WINDOW: Duration = Duration::from_secs(5);

/// At most one WARN per link this often for a late RTU reply: a device answering
/// every request late must not flood the log.
const LATE_REPLY_LOG_EVERY: Duration = Duration::from_secs(60);

impl std::fmt::Debug for ModbusLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ModbusLink")
            .field("spec", &self.spec)
            .field("connected", &self.ctx.is_some())
            .field("connects", &self.connects)
            .finish()
    }
}

impl ModbusLink {
    /// A link that connects on first use.
    pub fn new(spec: LinkSpec, timeout: Duration, backoff: Backoff) -> Self {
        Self {
            spec,
            timeout,
            ctx: None,
            deadline: None,
            cycle: None,
            cycle_fresh: false,
            backoff,
            connect_error: None,
            answered: false,
            peer: None,
            connects: 0,
            timed_out: None,
            late_logged: None,
            late_unlogged: 0,
            shared_address: false,
            busy_after_timeout: None,
        }
    }

    /// Several units are at this TCP address (behind a TCP-to-RTU gateway): a timed-out
    /// request keeps the connection while it was made or the peer sent a frame in the
    /// last 5 s (or three timeouts), is not retried, and the next request waits as much
    /// longer as it waited. The gateway goes on with a request the client gave up,
    /// until its own response timeout, and queues the next one behind it: a new
    /// connection meanwhile was refused by a gateway that takes one, which took every
    /// unit behind it down with the one that timed out. The late reply is dropped by
    /// its transaction id.
    pub fn shared_address(mut self) -> Self {
        self.shared_address = matches!(self.spec, LinkSpec::Tcp { .. });
        self
    }

    /// A link over a context already attached to a transport (an in-memory stream in
    /// the fuzz targets and tests). `spec` is only used to reconnect after a fault.
    #[doc(hidden)]
    pub fn attached(spec: LinkSpec, timeout: Duration, ctx: Context) -> Self {
        let mut link = Self::new(spec, timeout, Backoff::new(timeout, timeout));
        link.ctx = Some(ctx);
        link.connects = 1;
        link
    }

    /// Where the link goes.
    pub fn spec(&self) -> &LinkSpec {
        &self.spec
    }

    /// True while a context is established.
    pub fn is_connected(&self) -> bool {
        self.ctx.is_some()
    }

    /// Successful connects so far.
    pub fn connects(&self) -> u64 {
        self.connects
    }

    async fn connect(&mut self) -> Result<(Context, Option<Arc<Mutex<PeerSeen>>>), SourceError> {
        let seen = Arc::new(Mutex::new(PeerSeen::default()));
        match self.spec.clone() {
            LinkSpec::Tcp {
                address,
                connect_timeout,
            } => {
                let at = Instant::now() + connect_timeout;
                let cut = self.cycle_cut(at);
                let stream = tokio::time::timeout_at(
                    cut.map_or(at, |(end, _)| end),
                    TcpStream::connect(&address),
                )
                .await
                // Cut by the cycle's deadline or not, the device did not take the
                // connection: a connect timeout, not reads that take too long.
                .map_err(|_| SourceError::ConnectTimeout)?
                .map_err(|e| SourceError::Connect(format!("{address}: {e}")))?;
                // Small request/response frames: Nagle would add up to 40 ms each.
                stream
                    .set_nodelay(true)
                    .map_err(|e| SourceError::Connect(format!("{address}: {e}")))?;
                seen.lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .last_frame = Some(Instant::now());
                let stream = WatchedStream {
                    inner: stream,
                    seen: seen.clone(),
                    frames: Some(Box::default()),
                };
                Ok((tcp::attach(stream), Some(seen)))
            }
            LinkSpec::Rtu {
                path,
                baud,
                parity,
                stop_bits,
            } => {
                let failed =
                    |e: &dyn std::fmt::Display| SourceError::Connect(format!("{path}: {e}"));
                let builder = tokio_serial::new(&path, baud)
                    .parity(parity)
                    .stop_bits(stop_bits)
                    .data_bits(tokio_serial::DataBits::Eight);
                let mut port = tokio_serial::SerialStream::open(&builder)
                    .map_err(|e| serial_open_failed(&path, &e))?;
                // A late reply to a request given up before (by this link or another
                // process) may still be on its way: let it pass, then start empty.
                let started = Instant::now();
                let late_from = self.timed_out.take();
                let waited = late_from.map_or(self.timeout, |(_, t)| t.max(self.timeout));
                let dropped = drain_until_quiet(&mut port, rtu_guard(waited, baud))
                    .await
                    .map_err(|e| failed(&e))?;
                port.clear(tokio_serial::ClearBuffer::All)
                    .map_err(|e| failed(&e))?;
                if dropped > 0 {
                    match late_from {
                        Some((unit, timeout)) => self.late_reply(unit, timeout, dropped),
                        None => {
                            tracing::debug!(link = %self.spec, bytes = dropped, "dropped what the line brought before the first request");
                        }
                    }
                }
                // The wait is the line's, not the device's: the cycle's reads keep
                // their whole deadline.
                if let Some((end, _)) = &mut self.cycle {
                    *end += started.elapsed();
                }
                let port = WatchedStream {
                    inner: port,
                    seen: seen.clone(),
                    frames: None,
                };
                Ok((rtu::attach(port), Some(seen)))
            }
        }
    }

    /// The request timeout from now on: each device on a shared line sets its own
    /// when its cycle gets the line.
    pub fn set_timeout(&mut self, timeout: Duration) {
        self.timeout = timeout;
    }

    /// Bounds every request and connect until `None` by `at`, the end of a poll cycle
    /// of length `length`: one deadline for all reads of a cycle, their retries and
    /// reconnects. The cycle's first request still gets its whole timeout when the
    /// cycle is no shorter (the end moves out by the time it took to get the line and
    /// connect), so a silent device reports its own timeout; a later
    /// request cut by the deadline fails with [`SourceError::Deadline`] and drops the
    /// connection like a timeout.
    pub fn set_cycle_deadline(&mut self, cycle: Option<(Instant, Duration)>) {
        self.cycle = cycle;
        self.cycle_fresh = cycle.is_some();
    }

    /// The cycle deadline's length, once it has passed: no request goes out any more.
    pub fn cycle_over(&self) -> Option<Duration> {
        self.cycle
            .filter(|(end, _)| Instant::now() >= *end)
            .map(|(_, length)| length)
    }

    /// The cycle deadline if it comes before `at`.
    fn cycle_cut(&self, at: Instant) -> Option<(Instant, Duration)> {
        self.cycle.filter(|(end, _)| *end < at)
    }

    /// Drops the context so the next request starts on a fresh connection.
    pub fn disconnect(&mut self) {
        self.ctx = None;
        self.peer = None;
        self.answered = false;
        self.busy_after_timeout = None;
    }

    /// Takes the settings of `line`, built for the same line by a reload, and keeps the
    /// open connection: the line's shortest connect timeout and backoff, and whether
    /// several units share the address, follow the devices a reload added, changed or
    /// removed beside the unchanged ones that keep this link.
    pub fn adopt_settings(&mut self, line: &ModbusLink) {
        if let (
            LinkSpec::Tcp {
                connect_timeout, ..
            },
            LinkSpec::Tcp {
                connect_timeout: new,
                ..
            },
        ) = (&mut self.spec, &line.spec)
        {
            *connect_timeout = *new;
        }
        self.backoff.retune(&line.backoff);
        self.shared_address = line.shared_address;
    }

    /// Several units are at this TCP address: see [`Self::shared_address`].
    pub fn is_shared_address(&self) -> bool {
        self.shared_address
    }

    /// Whether a request that timed out after `waited` leaves the connection open (see
    /// [`Self::shared_address`]): one made, or with a frame from the peer, in the last
    /// [`LIFE_WINDOW`] (or three timeouts, if longer). A connection silent for longer
    /// is taken for dead and made anew.
    fn outlives_timeout(&mut self, waited: Duration) -> bool {
        if !self.shared_address {
            return false;
        }
        let last = self
            .peer
            .as_ref()
            .and_then(|p| p.lock().unwrap_or_else(PoisonError::into_inner).last_frame);
        let alive = last.is_some_and(|t| t.elapsed() < LIFE_WINDOW.max(waited * 3));
        if alive {
            self.busy_after_timeout = Some(waited);
        }
        alive
    }

    /// The open connection has given a good reply (or an exception).
    pub fn has_answered(&self) -> bool {
        self.ctx.is_some() && self.answered
    }

    /// A reply to a request that timed out came on a TCP connection that outlived the
    /// timeout (the frame filter dropped it): the same WARN as for a late RTU reply.
    fn late_tcp_reply(&mut self) {
        let late = self
            .peer
            .as_ref()
            .and_then(|p| p.lock().unwrap_or_else(PoisonError::into_inner).late.take());
        if let (Some((unit, bytes)), Some((asked, timeout))) = (late, self.timed_out) {
            if unit == asked {
                self.timed_out = None;
                self.late_reply(unit, timeout, bytes);
            }
        }
    }

    /// Records a good reply: the link works, the backoff starts over.
    fn answered(&mut self) {
        self.answered = true;
        self.timed_out = None;
        self.backoff.reset();
    }

    /// `bytes` came on the line after `unit`'s request timed out after
    /// `timeout`: a device slower than its `timeout_s`, whose replies are dropped. One
    /// WARN per [`LATE_REPLY_LOG_EVERY`], with the count of the ones not logged; DEBUG
    /// else.
    fn late_reply(&mut self, unit: u8, timeout: Duration, bytes: usize) {
        let now = Instant::now();
        if self
            .late_logged
            .is_some_and(|t| now.duration_since(t) < LATE_REPLY_LOG_EVERY)
        {
            self.late_unlogged += 1;
            tracing::debug!(link = %self.spec, unit, bytes, "a late reply dropped");
            return;
        }
        let unlogged = std::mem::take(&mut self.late_unlogged);
        let more = if unlogged > 0 {
            format!(
                "; {unlogged} more late replies in the last {} s not logged",
                LATE_REPLY_LOG_EVERY.as_secs()
            )
        } else {
            String::new()
        };
        tracing::warn!(
            link = %self.spec,
            unit,
            "unit {unit} answered after timeout_s = {} s ({bytes} bytes came after its \
             request timed out): a slow device; raise timeout_s for it{more}",
            timeout.as_secs_f64()
        );
        self.late_logged = Some(now);
    }

    /// Drops the connection after `error`, which it returns. A TCP connection that
    /// fails before its first good reply counts as a failed connect, else a peer that
    /// accepts and closes (or answers garbage) is reconnected every request. A link that
    /// has answered reconnects at once: one lost reply must not cost seconds. A timeout
    /// never counts: the request already waited it, so a silent peer is asked at most
    /// once a timeout, and a device gone quiet keeps being reported (and polled) as
    /// timing out every cycle. Not on RTU: reopening a tty costs the field nothing.
    fn fault(&mut self, error: SourceError) -> SourceError {
        let first_reply_missing = !self.answered
            && matches!(self.spec, LinkSpec::Tcp { .. })
            && !matches!(error, SourceError::Timeout(_) | SourceError::Deadline(_));
        self.disconnect();
        if first_reply_missing {
            self.backoff.failed(Instant::now());
            tracing::debug!(link = %self.spec, error = %error, retry_in_s = self.backoff.current().as_secs_f64(), "connection failed before any reply");
            self.connect_error = Some(Box::new(error.clone()));
        }
        error
    }

    /// What the peer's bytes and EOF say about a request that failed with `io`
    /// (`None`: timed out), where tokio-modbus's error does not: on TCP it reports a
    /// peer that closed with a stale `errno` ("Operation now in progress") and one that
    /// answered a few bytes of something else and closed with "bytes remaining on
    /// stream"; on RTU a reply with a bad CRC, noise or an adapter's echo of the request
    /// are dropped by its decoder and end in a timeout.
    fn peer_fault(&self, io: Option<&std::io::Error>) -> Option<SourceError> {
        use std::io::ErrorKind;
        let seen = self.peer.as_ref()?;
        let seen = seen.lock().unwrap_or_else(PoisonError::into_inner);
        let address = match &self.spec {
            LinkSpec::Tcp { address, .. } => address,
            LinkSpec::Rtu { path, .. } => {
                let garbled = io.is_none_or(|e| e.kind() == ErrorKind::InvalidData);
                return (garbled && !seen.reply.is_empty()).then(|| SourceError::Frame {
                    link: path.clone(),
                    detail: describe_garbled(&seen),
                });
            }
        };
        if !seen.reply.is_empty() && !mbap_plausible(&seen.reply) {
            Some(SourceError::NotModbus {
                address: address.clone(),
                detail: format!("it answered {}", describe_bytes(&seen.reply)),
            })
        } else if seen.closed
            || io.is_some_and(|e| {
                matches!(
                    e.kind(),
                    ErrorKind::ConnectionReset
                        | ErrorKind::ConnectionAborted
                        | ErrorKind::BrokenPipe
                        | ErrorKind::UnexpectedEof
                )
            })
        {
            Some(SourceError::PeerClosed {
                address: address.clone(),
                before_reply: !self.answered,
            })
        } else {
            None
        }
    }

    /// The serial path or "host:port" the link goes to, for error messages.
    fn place(&self) -> &str {
        match &self.spec {
            LinkSpec::Tcp { address, .. } => address,
            LinkSpec::Rtu { path, .. } => path,
        }
    }

    /// What about a reply tokio-modbus found out of step with the request to `unit`,
    /// in words (its own message is the headers' debug output).
    fn mismatch(&self, unit: u8, error: &tokio_modbus::ProtocolError) -> SourceError {
        use tokio_modbus::ProtocolError as P;
        let function = |r: &Result<Response, tokio_modbus::ExceptionResponse>| match r {
            Ok(r) => r.function_code().value(),
            Err(e) => e.function.value(),
        };
        let detail = match error {
            P::FunctionCodeMismatch { request, result } => format!(
                "the reply is for function 0x{:02X}, the request was function 0x{:02X}",
                function(result),
                request.value()
            ),
            P::HeaderMismatch { .. } => return self.mismatch_seen(unit),
        };
        SourceError::Frame {
            link: self.place().to_string(),
            detail,
        }
    }

    /// A reply whose header does not fit the request to `unit`, from what the peer
    /// sent and was sent.
    fn mismatch_seen(&self, unit: u8) -> SourceError {
        let seen = self
            .peer
            .as_ref()
            .map(|s| s.lock().unwrap_or_else(PoisonError::into_inner));
        let (sent, reply) = seen
            .as_ref()
            .map_or((&[][..], &[][..]), |s| (&s.sent[..], &s.reply[..]));
        SourceError::Frame {
            link: self.place().to_string(),
            detail: header_mismatch(&self.spec, unit, sent, reply),
        }
    }

    /// Connects now, if not connected (a connect the backoff allows).
    pub async fn open(&mut self) -> Result<(), SourceError> {
        self.ensure_connected().await
    }

    /// Connects if needed and the backoff allows.
    async fn ensure_connected(&mut self) -> Result<(), SourceError> {
        if self.ctx.is_some() {
            return Ok(());
        }
        if let Some(left) = self.backoff.remaining(Instant::now()) {
            return Err(match &self.connect_error {
                Some(cause) => SourceError::BackingOffAfter {
                    cause: cause.clone(),
                    next_attempt_in: left,
                },
                None => SourceError::BackingOff(left),
            });
        }
        match self.connect().await {
            Ok((ctx, peer)) => {
                self.connect_error = None;
                self.connects += 1;
                tracing::debug!(link = %self.spec, connects = self.connects, "connected");
                self.ctx = Some(ctx);
                self.peer = peer;
                self.answered = false;
                Ok(())
            }
            Err(e) => {
                self.backoff.failed(Instant::now());
                tracing::debug!(link = %self.spec, error = %e, retry_in_s = self.backoff.current().as_secs_f64(), "connect failed");
                self.connect_error = Some(Box::new(e.clone()));
                Err(e)
            }
        }
    }

    /// Runs one request with the timeout; any transport fault drops the context.
    ///
    /// Goes through `Client::call`, not the typed helpers (`read_input_registers`,
    /// `write_single_register`, ...): those `debug_assert` the reply's shape, which a
    /// malformed reply (a wrong byte count on RTU) breaks with a panic. The callers
    /// check the shape and treat a mismatch as a transport fault.
    async fn call(&mut self, unit: u8, request: Request<'_>) -> Result<Response, SourceError> {
        if let Some(length) = self.cycle_over() {
            return Err(SourceError::Deadline(length));
        }
        self.ensure_connected().await?;
        let timeout = self.timeout;
        let busy = self.busy_after_timeout.take();
        let own = Instant::now() + timeout + busy.unwrap_or_default();
        if std::mem::take(&mut self.cycle_fresh) || busy.is_some() {
            if let Some((end, length)) = &mut self.cycle {
                if *length >= timeout {
                    *end = (*end).max(own);
                }
            }
        }
        let cut = self.cycle_cut(own);
        let at = cut.map_or(own, |(end, _)| end);
        let deadline = self
            .deadline
            .get_or_insert_with(|| Box::pin(tokio::time::sleep_until(at)));
        deadline.as_mut().reset(at);
        let Some(ctx) = self.ctx.as_mut() else {
            return Err(SourceError::Connect("no context".into()));
        };
        let started = Instant::now();
        ctx.set_slave(Slave(unit));
        let outcome = tokio::select! {
            // The reply wins a tie with the deadline.
            biased;
            r = ctx.call(request) => Some(r),
            () = deadline.as_mut() => None,
        };
        self.late_tcp_reply();
        match outcome {
            // Good once the caller has checked its shape.
            Some(Ok(Ok(response))) => Ok(response),
            // The device answered: the link is fine.
            Some(Ok(Err(code))) => {
                self.answered();
                Err(SourceError::Exception(code))
            }
            Some(Err(e)) => {
                let error = match &e {
                    tokio_modbus::Error::Transport(io) => {
                        self.peer_fault(Some(io)).unwrap_or_else(|| {
                            SourceError::Transport(format!("{}: {io}", self.place()))
                        })
                    }
                    tokio_modbus::Error::Protocol(p) => self.mismatch(unit, p),
                };
                Err(self.fault(error))
            }
            None => {
                // Bytes that are no Modbus frame leave the client waiting for more.
                // A reply to another transaction, when no request given up before may
                // still be answered on this connection, is a module that does not echo
                // the id: the frame filter dropped it, say what came.
                let other_transaction = busy.is_none()
                    && matches!(self.spec, LinkSpec::Tcp { .. })
                    && self.peer.as_ref().is_some_and(|p| {
                        let seen = p.lock().unwrap_or_else(PoisonError::into_inner);
                        seen.reply.len() >= 8
                            && mbap_plausible(&seen.reply)
                            && seen.reply.get(..2) != seen.sent.get(..2)
                    });
                let error = match (self.peer_fault(None), cut) {
                    _ if other_transaction => self.mismatch_seen(unit),
                    (Some(e @ (SourceError::NotModbus { .. } | SourceError::Frame { .. })), _) => e,
                    (_, Some((_, length))) => SourceError::Deadline(length),
                    (_, None) => {
                        self.timed_out = Some((unit, timeout));
                        SourceError::Timeout(timeout)
                    }
                };
                if matches!(error, SourceError::Timeout(_) | SourceError::Deadline(_))
                    && self.outlives_timeout(at.duration_since(started))
                {
                    return Err(error);
                }
                Err(self.fault(error))
            }
        }
    }

    /// A reply out of step with its request: the stream cannot be trusted, start over.
    fn out_of_step(&mut self, what: String) -> SourceError {
        self.fault(SourceError::Transport(what))
    }

    /// A reply whose shape does not fit the request (a wrong register count): the
    /// stream cannot be trusted, start over.
    fn misshapen(&mut self, detail: String) -> SourceError {
        let link = self.place().to_string();
        self.fault(SourceError::Frame { link, detail })
    }

    /// Reads `count` registers at `start` from unit `unit`.
    pub async fn read(
        &mut self,
        unit: u8,
        kind: RegisterKind,
        start: u16,
        count: u16,
    ) -> Result<Vec<u16>, SourceError> {
        let request = match kind {
            RegisterKind::Input => Request::ReadInputRegisters(start, count),
            RegisterKind::Holding => Request::ReadHoldingRegisters(start, count),
        };
        match self.call(unit, request).await? {
            Response::ReadInputRegisters(regs) | Response::ReadHoldingRegisters(regs)
                if regs.len() == usize::from(count) =>
            {
                self.answered();
                Ok(regs)
            }
            other => Err(self.misshapen(format!(
                "the reply holds {}, the request asked for {count} at {start}",
                describe_response(&other)
            ))),
        }
    }

    /// Writes holding registers starting at `start`; the device's echo must match.
    pub async fn write(&mut self, unit: u8, start: u16, words: &[u16]) -> Result<(), SourceError> {
        let request = match words {
            [w] => Request::WriteSingleRegister(start, *w),
            _ => Request::WriteMultipleRegisters(start, Cow::Borrowed(words)),
        };
        let response = self.call(unit, request).await?;
        let echoed = match (&response, words) {
            (Response::WriteSingleRegister(a, v), [w]) => *a == start && v == w,
            (Response::WriteMultipleRegisters(a, n), _) => {
                *a == start && usize::from(*n) == words.len()
            }
            _ => false,
        };
        if echoed {
            self.answered();
            Ok(())
        } else {
            Err(self.out_of_step(format!(
                "wrote {} registers at {start}, the echo was {}",
                words.len(),
                describe_response(&response)
            )))
        }
    }
}

/// Bytes of a reply kept for an error message: enough to recognise a protocol.
const REPLY_KEPT_BYTES: usize = 32;

/// What the peer sent since the last request went out, and whether it closed.
#[derive(Debug, Default)]
struct PeerSeen {
    /// The first [`REPLY_KEPT_BYTES`] bytes of the last request.
    sent: Vec<u8>,
    /// The first [`REPLY_KEPT_BYTES`] bytes received since the last write.
    reply: Vec<u8>,
    /// The peer closed its side (a read returned end of stream).
    closed: bool,
    /// TCP: when the last whole frame came, a late one included, or else when the
    /// connection was made: a sign of life after a timeout.
    last_frame: Option<Instant>,
    /// TCP: the unit and size of the last reply to an earlier request, dropped, until
    /// the link has looked at it.
    late: Option<(u8, usize)>,
}

/// A TCP stream or serial port that notes in [`PeerSeen`] what the peer does, for the
/// error messages. On TCP it also drops whole frames whose transaction id is not the
/// last request's: a reply that comes after its request timed out (tokio-modbus would
/// take it for the next request's and fail that one), so a connection can outlive a
/// timeout.
#[derive(Debug)]
struct WatchedStream<S> {
    inner: S,
    seen: Arc<Mutex<PeerSeen>>,
    /// TCP only.
    frames: Option<Box<Frames>>,
}

/// Bytes read from a TCP peer on their way to tokio-modbus, split into frames.
#[derive(Debug, Default)]
struct Frames {
    /// Read, not yet a whole frame.
    partial: Vec<u8>,
    /// Whole frames of the last request, or bytes that are no plausible frame (passed
    /// on for tokio-modbus to refuse), not yet handed on.
    ready: std::collections::VecDeque<u8>,
}

impl Frames {
    /// Moves the whole frames in `partial` to `ready`, dropping those whose
    /// transaction id is not `tid` (the last one's unit and size go to `late`); returns
    /// how many frames were whole.
    fn split(&mut self, tid: Option<[u8; 2]>, late: &mut Option<(u8, usize)>) -> u64 {
        let mut whole = 0;
        while self.partial.len() >= 6 {
            let len = usize::from(u16::from_be_bytes([self.partial[4], self.partial[5]]));
            if !mbap_plausible(&self.partial[..6]) {
                self.ready.extend(self.partial.drain(..));
                break;
            }
            if self.partial.len() < 6 + len {
                break;
            }
            whole += 1;
            let frame = self.partial.drain(..6 + len);
            if tid.is_none_or(|t| frame.as_slice()[..2] == t) {
                self.ready.extend(frame);
            } else {
                *late = frame.as_slice().get(6).map(|&unit| (unit, 6 + len));
            }
        }
        whole
    }
}

impl<S> WatchedStream<S> {
    fn seen(&self) -> std::sync::MutexGuard<'_, PeerSeen> {
        self.seen.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// A new request (`buf`) went out: what came before it is not its reply.
    fn sent(&self, buf: &[u8]) {
        let mut seen = self.seen();
        seen.reply.clear();
        seen.sent.clear();
        seen.sent
            .extend_from_slice(&buf[..buf.len().min(REPLY_KEPT_BYTES)]);
    }
}

impl<S: AsyncRead + Unpin> WatchedStream<S> {
    /// [`AsyncRead::poll_read`] through [`Frames`].
    fn poll_read_frames(
        &mut self,
        cx: &mut TaskContext<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        let Some(frames) = self.frames.as_mut() else {
            return Poll::Ready(Ok(()));
        };
        loop {
            if !frames.ready.is_empty() {
                let n = buf.remaining().min(frames.ready.len());
                let (a, b) = frames.ready.as_slices();
                let from_a = n.min(a.len());
                buf.put_slice(&a[..from_a]);
                buf.put_slice(&b[..n - from_a]);
                frames.ready.drain(..n);
                return Poll::Ready(Ok(()));
            }
            let mut chunk = [0u8; 512];
            let mut got = ReadBuf::new(&mut chunk);
            std::task::ready!(Pin::new(&mut self.inner).poll_read(cx, &mut got))?;
            let got = got.filled();
            let mut seen = self.seen.lock().unwrap_or_else(PoisonError::into_inner);
            if got.is_empty() {
                seen.closed = true;
                if frames.partial.is_empty() {
                    return Poll::Ready(Ok(()));
                }
                // A frame cut short by the close: tokio-modbus says so.
                frames.ready.extend(frames.partial.drain(..));
                continue;
            }
            let keep = REPLY_KEPT_BYTES
                .saturating_sub(seen.reply.len())
                .min(got.len());
            seen.reply.extend_from_slice(&got[..keep]);
            frames.partial.extend_from_slice(got);
            let tid = seen.sent.get(..2).map(|t| [t[0], t[1]]);
            if frames.split(tid, &mut seen.late) > 0 {
                seen.last_frame = Some(Instant::now());
            }
        }
    }
}

impl<S: AsyncRead + Unpin> AsyncRead for WatchedStream<S> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut TaskContext<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        if self.frames.is_some() {
            return self.poll_read_frames(cx, buf);
        }
        let before = buf.filled().len();
        let room = buf.remaining() > 0;
        let polled = Pin::new(&mut self.inner).poll_read(cx, buf);
        if let Poll::Ready(Ok(())) = polled {
            let got = &buf.filled()[before..];
            let mut seen = self.seen();
            if got.is_empty() {
                seen.closed |= room;
            } else {
                let keep = REPLY_KEPT_BYTES
                    .saturating_sub(seen.reply.len())
                    .min(got.len());
                seen.reply.extend_from_slice(&got[..keep]);
            }
        }
        polled
    }
}

impl<S: AsyncWrite + Unpin> AsyncWrite for WatchedStream<S> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut TaskContext<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        self.sent(buf);
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut TaskContext<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        self.sent(bufs.first().map_or(&[][..], |b| &b[..]));
        Pin::new(&mut self.inner).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut TaskContext<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(
        mut self: Pin<&mut Self>,
        cx: &mut TaskContext<'_>,
    ) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

/// Why the serial port at `path` did not open (`path: ...`, as any other open error),
/// with what to do for the usual causes:
/// a path that does not exist (an adapter unplugged, a typo, a renumbered ttyUSB), one
/// that is no serial device, and a user without the tty's group.
fn serial_open_failed(path: &str, e: &tokio_serial::Error) -> SourceError {
    use std::io::ErrorKind;
    use tokio_serial::ErrorKind as Serial;
    // serialport reports ENOTTY (an ioctl of a regular file or /dev/null) only by its
    // description, which is nix's ("Not a typewriter") or libc's.
    let not_a_tty = matches!(e.kind, Serial::Unknown)
        && (e.description == "Not a typewriter" || e.description.contains("Inappropriate ioctl"));
    SourceError::Connect(match e.kind {
        Serial::Io(ErrorKind::NotFound) => format!(
            "{path}: does not exist: check the adapter is plugged in and the path (ls \
             /dev/serial/by-id gives stable names)"
        ),
        Serial::Io(ErrorKind::PermissionDenied) => format!(
            "{path}: permission denied: the gateway's user needs the tty's group (usually \
             dialout)"
        ),
        _ if not_a_tty => format!("{path}: not a serial device"),
        // EPERM, not EACCES: a device cgroup, e.g. the unit's DevicePolicy=closed.
        _ if e.description == "Operation not permitted" => format!(
            "{path}: operation not permitted: under systemd, the unit's DeviceAllow= may \
             not list its driver (grep tty /proc/devices; docs/deployment.md)"
        ),
        _ => format!("{path}: {e}"),
    })
}

/// The longest [`rtu_guard`].
pub const RTU_GUARD_MAX: Duration = Duration::from_secs(1);

/// How long an RTU line must have been quiet after its port was opened before the
/// first request goes out: `timeout` (a reply that late after its request's timeout
/// still passes), at most [`RTU_GUARD_MAX`], at least the 3.5 characters of 11 bits
/// that end an RTU frame at `baud`.
pub fn rtu_guard(timeout: Duration, baud: u32) -> Duration {
    let frame_gap = Duration::from_secs_f64(3.5 * 11.0 / f64::from(baud.max(1)));
    timeout.min(RTU_GUARD_MAX).max(frame_gap)
}

/// Reads and drops what `port` brings until nothing came for `quiet`; returns the
/// bytes dropped. A line that never falls quiet (a device streaming, another master)
/// is given up on after four times `quiet`: the caller clears the buffer and goes on.
async fn drain_until_quiet<S: AsyncRead + Unpin>(
    port: &mut S,
    quiet: Duration,
) -> std::io::Result<usize> {
    use tokio::io::AsyncReadExt;
    let give_up = Instant::now() + quiet * 4;
    let mut buf = [0u8; 256];
    let mut dropped = 0;
    loop {
        let until = (Instant::now() + quiet).min(give_up);
        match tokio::time::timeout_at(until, port.read(&mut buf)).await {
            Ok(Ok(n)) if n > 0 => dropped += n,
            Ok(Err(e)) => return Err(e),
            Ok(Ok(_)) | Err(_) => return Ok(dropped),
        }
    }
}

/// What an RTU device sent that tokio-modbus's decoder could not take as a reply.
fn describe_garbled(seen: &PeerSeen) -> String {
    if !seen.sent.is_empty() && seen.reply.starts_with(&seen.sent) {
        format!(
            "the request came back as it was sent ({}): the RS-485 adapter echoes what it \
             sends; turn its echo off",
            describe_bytes(&seen.sent)
        )
    } else {
        format!(
            "bytes arrived, but no complete reply with a valid CRC (noise, a wrong baud \
             rate or parity, or two devices answering): {}",
            describe_bytes(&seen.reply)
        )
    }
}

/// Which header field of `reply` differs from that of the request `sent` to `unit`.
fn header_mismatch(spec: &LinkSpec, unit: u8, sent: &[u8], reply: &[u8]) -> String {
    let word = |b: &[u8], at: usize| b.get(at..at + 2).map(|w| u16::from_be_bytes([w[0], w[1]]));
    let (reply_unit, tid) = match spec {
        LinkSpec::Rtu { .. } => (reply.first(), None),
        LinkSpec::Tcp { .. } => (reply.get(6), word(reply, 0).zip(word(sent, 0))),
    };
    match (reply_unit, tid) {
        (_, Some((got, asked))) if got != asked => format!(
            "the reply is to transaction {got}, the request was transaction {asked} (a late \
             or repeated reply)"
        ),
        (Some(&got), _) if got != unit => {
            format!("the reply came from unit {got}, the request went to unit {unit}")
        }
        _ => "the reply's header does not match the request's".into(),
    }
}

/// False when `reply` cannot begin a Modbus TCP frame: the MBAP header's protocol id
/// is 0 and its length (unit id and PDU) 2..=254. Fewer bytes say nothing.
fn mbap_plausible(reply: &[u8]) -> bool {
    let protocol_ok = reply.get(2..4).is_none_or(|p| p == [0, 0]);
    let length_ok = reply
        .get(4..6)
        .is_none_or(|l| (2..=254).contains(&u16::from_be_bytes([l[0], l[1]])));
    protocol_ok && length_ok
}

/// `bytes` as quoted text if they are text, else in hex; "..." if more may follow.
fn describe_bytes(bytes: &[u8]) -> String {
    let more = if bytes.len() >= REPLY_KEPT_BYTES {
        " ..."
    } else {
        ""
    };
    let text = bytes
        .iter()
        .all(|b| b.is_ascii_graphic() || b" \r\n\t".contains(b));
    if text {
        format!("{:?}{more}", String::from_utf8_lossy(bytes))
    } else {
        let hex: Vec<String> = bytes.iter().map(|b| format!("{b:02X}")).collect();
        format!("the bytes {}{more}", hex.join(" "))
    }
}

/// A reply, short enough for an error message.
fn describe_response(r: &Response) -> String {
    match r {
        Response::ReadInputRegisters(w) | Response::ReadHoldingRegisters(w) => match w.len() {
            1 => "1 register".into(),
            n => format!("{n} registers"),
        },
        Response::WriteSingleRegister(a, v) => format!("write of {v} at {a}"),
        Response::WriteMultipleRegisters(a, n) => format!("write of {n} registers at {a}"),
        other => format!(
            "a reply of function 0x{:02X}",
            other.function_code().value()
        ),
    }
}

/// Names a Modbus exception code the way device manuals do.
pub fn exception_name(code: ExceptionCode) -> String {
    match code {
        ExceptionCode::IllegalFunction => "0x01 illegal function".into(),
        ExceptionCode::IllegalDataAddress => "0x02 illegal data address".into(),
        ExceptionCode::IllegalDataValue => "0x03 illegal data value".into(),
        ExceptionCode::ServerDeviceFailure => "0x04 server device failure".into(),
        ExceptionCode::Acknowledge => "0x05 acknowledge".into(),
        ExceptionCode::ServerDeviceBusy => "0x06 server device busy".into(),
        ExceptionCode::MemoryParityError => "0x08 memory parity error".into(),
        ExceptionCode::GatewayPathUnavailable => "0x0A gateway path unavailable".into(),
        ExceptionCode::GatewayTargetDevice => "0x0B gateway target device failed to respond".into(),
        ExceptionCode::Custom(c) => format!("0x{c:02X}"),
    }
}

/// Resolves "host:port" now, for validation messages; connecting resolves again.
pub fn parse_socket_addr(s: &str) -> Option<SocketAddr> {
    use std::net::ToSocketAddrs;
    s.to_socket_addrs().ok()?.next()
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    /// A Modbus TCP peer that answers every write-single-register request with the
    /// register and `value + 1`: a reply out of step with its request.
    async fn wrong_echo_peer() -> (String, tokio::task::JoinHandle<()>) {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap().to_string();
        let task = tokio::spawn(async move {
            while let Ok((mut s, _)) = listener.accept().await {
                // MBAP header (7 bytes) + function 0x06, address, value.
                let mut req = [0u8; 12];
                while s.read_exact(&mut req).await.is_ok() {
                    let mut reply = req;
                    let value = u16::from_be_bytes([req[10], req[11]]).wrapping_add(1);
                    reply[10..12].copy_from_slice(&value.to_be_bytes());
                    if s.write_all(&reply).await.is_err() {
                        break;
                    }
                }
            }
        });
        (addr, task)
    }

    // A module that answers every request with transaction id 0 (some do not echo
    // it): its replies never reach tokio-modbus (the frame filter drops a reply to
    // another request), and the request timed out as if nothing came. The error says
    // what came, as it did before the filter.
    #[tokio::test]
    async fn a_reply_with_another_transaction_id_is_named() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap().to_string();
        let peer = tokio::spawn(async move {
            while let Ok((mut s, _)) = listener.accept().await {
                let mut req = [0u8; 12];
                while s.read_exact(&mut req).await.is_ok() {
                    let reply = [0, 0, 0, 0, 0, 5, req[6], 4, 2, 0, 7];
                    if s.write_all(&reply).await.is_err() {
                        break;
                    }
                }
            }
        });
        let mut link = tcp_link(
            address,
            Duration::from_millis(300),
            Duration::from_millis(10),
        );
        assert!(link.read(1, RegisterKind::Input, 0, 1).await.is_ok());
        let err = link.read(1, RegisterKind::Input, 0, 1).await.unwrap_err();
        assert!(
            err.to_string()
                .contains("the reply is to transaction 0, the request was transaction 1"),
            "{err}"
        );
        peer.abort();
    }

    #[tokio::test]
    async fn a_write_whose_echo_differs_is_a_transport_fault_and_reconnects() {
        let (address, peer) = wrong_echo_peer().await;
        let mut link = ModbusLink::new(
            LinkSpec::Tcp {
                address,
                connect_timeout: Duration::from_secs(1),
            },
            Duration::from_secs(1),
            Backoff::new(Duration::from_millis(10), Duration::from_millis(10)),
        );
        let err = link.write(1, 7, &[41]).await.unwrap_err();
        match &err {
            SourceError::Transport(m) => {
                assert!(m.contains("at 7") && m.contains("write of 42 at 7"), "{m}")
            }
            other => panic!("expected a transport fault, got {other:?}"),
        }
        // The stream is not trusted after a mismatch: the next request reconnects, once
        // the backoff allows (the connection never answered well).
        assert!(!link.is_connected());
        let err = link.write(1, 7, &[1]).await.unwrap_err();
        assert!(
            matches!(&err, SourceError::BackingOffAfter { cause, .. } if matches!(**cause, SourceError::Transport(_))),
            "{err:?}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert!(link.write(1, 7, &[1]).await.is_err());
        assert_eq!(link.connects(), 2);
        peer.abort();
    }

    // A silent server: the cycle's end cuts the request short of its own timeout, drops
    // the connection, and a later request of the same cycle fails at once.
    #[tokio::test]
    async fn the_cycle_deadline_cuts_a_request_and_the_rest_of_the_cycle() {
        let (address, peer) = silent_peer().await;
        let mut link = ModbusLink::new(
            LinkSpec::Tcp {
                address,
                connect_timeout: Duration::from_secs(5),
            },
            Duration::from_secs(5),
            Backoff::new(Duration::from_millis(10), Duration::from_millis(10)),
        );
        let length = Duration::from_millis(50);
        link.set_cycle_deadline(Some((Instant::now() + length, length)));
        let err = link.read(1, RegisterKind::Input, 0, 1).await.unwrap_err();
        assert_eq!(err, SourceError::Deadline(length));
        assert!(
            !link.is_connected(),
            "the stream is dropped with the request"
        );
        let err = link.read(1, RegisterKind::Input, 1, 1).await.unwrap_err();
        assert_eq!(err, SourceError::Deadline(length));
        assert_eq!(link.connects(), 1, "no reconnect after the cycle's end");
        // The next cycle connects again and gets its own deadline.
        link.set_cycle_deadline(Some((Instant::now() + length, length)));
        assert!(link.read(1, RegisterKind::Input, 0, 1).await.is_err());
        assert_eq!(link.connects(), 2);
        peer.abort();
    }

    // The cycle's first request gets its whole timeout even when the line took a
    // while to get (D = max(poll_interval_s, timeout_s) = timeout_s here): a silent
    // device reported "poll cycle deadline ... passed", not its timeout.
    #[tokio::test]
    async fn the_first_request_of_a_cycle_gets_its_whole_timeout() {
        let (address, peer) = silent_peer().await;
        let timeout = Duration::from_millis(100);
        let mut link = tcp_link(address, timeout, Duration::from_millis(10));
        link.set_cycle_deadline(Some((Instant::now() + timeout, timeout)));
        tokio::time::sleep(Duration::from_millis(30)).await;
        let err = link.read(1, RegisterKind::Input, 0, 1).await.unwrap_err();
        assert_eq!(err, SourceError::Timeout(timeout));
        // The next request of the cycle gets only what is left: nothing.
        let err = link.read(1, RegisterKind::Input, 0, 1).await.unwrap_err();
        assert_eq!(err, SourceError::Deadline(timeout));
        peer.abort();
    }

    // A device whose TCP stack takes no more connections (its accept queue full, as
    // a stopped process' fills up): a connect cut by the cycle's deadline is a connect
    // timeout. It was reported as reads that take too long together ("raise
    // poll_interval_s or lower timeout_s"), and sent the operator tuning timeouts.
    #[tokio::test]
    async fn a_connect_cut_by_the_cycle_deadline_is_a_connect_timeout() {
        let socket = tokio::net::TcpSocket::new_v4().unwrap();
        socket.bind("127.0.0.1:0".parse().unwrap()).unwrap();
        let listener = socket.listen(0).unwrap();
        let address = listener.local_addr().unwrap();
        let mut held = Vec::new();
        while let Ok(Ok(s)) =
            tokio::time::timeout(Duration::from_millis(200), TcpStream::connect(address)).await
        {
            held.push(s);
            assert!(held.len() < 64, "the accept queue never filled");
        }
        let timeout = Duration::from_millis(100);
        let mut link = tcp_link(address.to_string(), timeout, Duration::from_millis(10));
        link.set_cycle_deadline(Some((Instant::now() + timeout, timeout)));
        let err = link.read(1, RegisterKind::Input, 0, 1).await.unwrap_err();
        assert_eq!(err, SourceError::ConnectTimeout);
    }

    /// A Modbus TCP peer answering read-input-registers requests with zeros, except
    /// that on its first connection it leaves request `skip` (0-based) unanswered.
    async fn modbus_peer(skip: usize) -> (String, tokio::task::JoinHandle<()>) {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap().to_string();
        let task = tokio::spawn(async move {
            let mut first = true;
            while let Ok((mut s, _)) = listener.accept().await {
                let skip = if std::mem::take(&mut first) {
                    skip
                } else {
                    usize::MAX
                };
                tokio::spawn(async move {
                    // MBAP header (7 bytes) + function 0x04, address, count.
                    let mut req = [0u8; 12];
                    let mut n = 0;
                    while s.read_exact(&mut req).await.is_ok() {
                        n += 1;
                        if n - 1 == skip {
                            continue;
                        }
                        let count = u16::from_be_bytes([req[10], req[11]]);
                        let bytes = 2 * count;
                        let mut reply = req[..7].to_vec();
                        reply[4..6].copy_from_slice(&(3 + bytes).to_be_bytes());
                        reply.extend([0x04, bytes as u8]);
                        reply.resize(reply.len() + usize::from(bytes), 0);
                        if s.write_all(&reply).await.is_err() {
                            break;
                        }
                    }
                });
            }
        });
        (addr, task)
    }

    /// A peer that accepts connections, holds them and never answers: its address.
    async fn silent_peer() -> (String, tokio::task::JoinHandle<()>) {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap().to_string();
        let peer = tokio::spawn(async move {
            let mut held = Vec::new();
            while let Ok((s, _)) = listener.accept().await {
                held.push(s);
            }
        });
        (address, peer)
    }

    fn tcp_link(address: String, timeout: Duration, backoff: Duration) -> ModbusLink {
        ModbusLink::new(
            LinkSpec::Tcp {
                address,
                connect_timeout: Duration::from_secs(1),
            },
            timeout,
            Backoff::new(backoff, backoff),
        )
    }

    // A timeout reconnects at once, with or without a good reply before it: a backoff
    // would push the next poll of a device that lost one reply out by seconds, and a
    // silent device must keep being reported as timing out.
    #[tokio::test]
    async fn a_timeout_never_starts_the_backoff() {
        let timeout = Duration::from_millis(100);
        let (address, peer) = modbus_peer(1).await;
        let mut link = tcp_link(address, timeout, Duration::from_secs(5));
        assert_eq!(
            link.read(1, RegisterKind::Input, 0, 2).await,
            Ok(vec![0, 0])
        );
        let err = link.read(1, RegisterKind::Input, 0, 2).await.unwrap_err();
        assert_eq!(err, SourceError::Timeout(timeout));
        assert_eq!(
            link.read(1, RegisterKind::Input, 0, 2).await,
            Ok(vec![0, 0])
        );
        assert_eq!(link.connects(), 2);
        peer.abort();

        let (address, peer) = modbus_peer(0).await;
        let mut link = tcp_link(address, timeout, Duration::from_secs(5));
        let err = link.read(1, RegisterKind::Input, 0, 2).await.unwrap_err();
        assert_eq!(err, SourceError::Timeout(timeout));
        assert_eq!(
            link.read(1, RegisterKind::Input, 0, 2).await,
            Ok(vec![0, 0])
        );
        assert_eq!(link.connects(), 2);
        peer.abort();
    }

    // A peer that greets with something else and waits (an HTTP server keeping the
    // connection open): the request times out, the bytes say why.
    #[tokio::test]
    async fn a_peer_sending_no_modbus_frame_is_named_on_timeout() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap().to_string();
        let peer = tokio::spawn(async move {
            let mut held = Vec::new();
            while let Ok((mut s, _)) = listener.accept().await {
                let _ = s.write_all(b"HTTP/1.1 400 Bad Request\r\n").await;
                held.push(s);
            }
        });
        let mut link = tcp_link(
            address.clone(),
            Duration::from_millis(100),
            Duration::from_secs(5),
        );
        let err = link.read(1, RegisterKind::Input, 0, 2).await.unwrap_err();
        assert_eq!(
            err.to_string(),
            format!("the peer at {address} does not speak Modbus TCP: it answered \"HTTP/1.1 400 Bad Request\\r\\n\"")
        );
        // Unlike a plain timeout, an answer in another protocol starts the backoff.
        match link.read(1, RegisterKind::Input, 0, 2).await.unwrap_err() {
            SourceError::BackingOffAfter { cause, .. } => assert_eq!(*cause, err),
            other => panic!("expected the backoff, got {other:?}"),
        }
        peer.abort();
    }

    /// CRC-16/MODBUS, low byte first as it goes on the wire.
    fn crc16(bytes: &[u8]) -> [u8; 2] {
        let mut crc = 0xFFFFu16;
        for &b in bytes {
            crc ^= u16::from(b);
            for _ in 0..8 {
                crc = if crc & 1 == 1 {
                    (crc >> 1) ^ 0xA001
                } else {
                    crc >> 1
                };
            }
        }
        crc.to_le_bytes()
    }

    /// An RTU read reply of `unit` holding `regs`, with its CRC.
    fn rtu_reply(unit: u8, function: u8, regs: &[u16]) -> Vec<u8> {
        let mut f = vec![unit, function, (regs.len() * 2) as u8];
        for r in regs {
            f.extend_from_slice(&r.to_be_bytes());
        }
        let crc = crc16(&f);
        f.extend_from_slice(&crc);
        f
    }

    /// An RTU slave on the far end of a pty pair, one request at a time like a real
    /// one: `answer` gives each (8-byte) request's delay and reply. Returns the path
    /// the link opens and the near end, which must stay open while it is used.
    fn rtu_device(
        answer: impl Fn(&[u8; 8]) -> (Duration, Vec<u8>) + Send + 'static,
    ) -> (
        String,
        tokio_serial::SerialStream,
        tokio::task::JoinHandle<()>,
    ) {
        let (mut far, near) = tokio_serial::SerialStream::pair().expect("pty pair");
        let path = near.name().expect("pty name");
        let task = tokio::spawn(async move {
            let mut req = [0u8; 8];
            while far.read_exact(&mut req).await.is_ok() {
                let (delay, reply) = answer(&req);
                tokio::time::sleep(delay).await;
                if far.write_all(&reply).await.is_err() {
                    break;
                }
            }
        });
        (path, near, task)
    }

    fn rtu_link(path: &str, timeout: Duration) -> ModbusLink {
        ModbusLink::new(
            LinkSpec::Rtu {
                path: path.into(),
                baud: 19200,
                parity: tokio_serial::Parity::None,
                stop_bits: tokio_serial::StopBits::One,
            },
            timeout,
            Backoff::new(Duration::from_millis(10), Duration::from_millis(10)),
        )
    }

    // RTU replies carry no transaction id: register 0's reply, 100 ms after its
    // request timed out, was read as the answer to the next request (register 5, the
    // same count) and its value taken as good; register 5's own reply then answered
    // the next request for register 0, and so on.
    #[tokio::test]
    async fn a_late_rtu_reply_never_answers_the_next_request() {
        let timeout = Duration::from_millis(400);
        let (path, _near, device) = rtu_device(move |req| {
            let start = u16::from_be_bytes([req[2], req[3]]);
            let (delay, value) = if start == 0 {
                (timeout + Duration::from_millis(100), 1000)
            } else {
                (Duration::ZERO, 2000)
            };
            (delay, rtu_reply(req[0], req[1], &[value]))
        });
        let mut link = rtu_link(&path, timeout);
        for round in 0..2 {
            let late = link.read(1, RegisterKind::Input, 0, 1).await;
            assert_eq!(late, Err(SourceError::Timeout(timeout)), "round {round}");
            let next = link.read(1, RegisterKind::Input, 5, 1).await;
            assert_eq!(next, Ok(vec![2000]), "round {round}");
        }
        device.abort();
    }

    /// Every event at WARN or above logged while it is the default subscriber: its
    /// message and fields.
    #[derive(Clone, Default)]
    struct Warnings(Arc<Mutex<Vec<String>>>);

    impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for Warnings {
        fn on_event(
            &self,
            event: &tracing::Event<'_>,
            _: tracing_subscriber::layer::Context<'_, S>,
        ) {
            struct Text(String);
            impl tracing::field::Visit for Text {
                fn record_debug(&mut self, f: &tracing::field::Field, v: &dyn std::fmt::Debug) {
                    use std::fmt::Write as _;
                    let _ = write!(self.0, " {}={v:?}", f.name());
                }
            }
            if *event.metadata().level() <= tracing::Level::WARN {
                let mut text = Text(String::new());
                event.record(&mut text);
                self.0.lock().unwrap().push(text.0);
            }
        }
    }

    /// The WARN for `bytes` from `unit` on `link` after a 0.2 s timeout, as [`Warnings`]
    /// records it.
    fn late_warning(unit: u8, bytes: usize, link: &str) -> String {
        format!(
            " message=unit {unit} answered after timeout_s = 0.2 s ({bytes} bytes came after \
             its request timed out): a slow device; raise timeout_s for it link={link} \
             unit={unit}"
        )
    }

    // Field review: a slow module's reply, after its request timed out, was dropped by
    // the drain of the reopened port with a DEBUG line naming neither the device nor
    // the fix. One WARN names the unit (and the link); the next ones within the minute
    // are only counted.
    #[tokio::test]
    async fn a_late_rtu_reply_is_one_warn_naming_the_unit() {
        use tracing_subscriber::layer::SubscriberExt;
        let warnings = Warnings::default();
        let _log =
            tracing::subscriber::set_default(tracing_subscriber::registry().with(warnings.clone()));
        let timeout = Duration::from_millis(200);
        let (path, _near, device) = rtu_device(move |req| {
            let start = u16::from_be_bytes([req[2], req[3]]);
            let delay = if start == 0 {
                timeout + Duration::from_millis(50)
            } else {
                Duration::ZERO
            };
            (delay, rtu_reply(req[0], req[1], &[7]))
        });
        let mut link = rtu_link(&path, timeout);
        for round in 0..3 {
            let late = link.read(3, RegisterKind::Input, 0, 1).await;
            assert_eq!(late, Err(SourceError::Timeout(timeout)), "round {round}");
            let next = link.read(3, RegisterKind::Input, 5, 1).await;
            assert_eq!(next, Ok(vec![7]), "round {round}");
        }
        device.abort();
        let seen = warnings.0.lock().unwrap().clone();
        assert_eq!(seen, [late_warning(3, 7, &format!("rtu://{path}@19200"))]);
    }

    // Behind a TCP-to-RTU gateway (a shared address), a unit slower than its timeout_s:
    // the connection outlives the timeout, the next unit's request waits behind it and
    // is answered, and the late reply, dropped, is the same WARN as on RTU (it was a
    // DEBUG line, and only the timeouts showed).
    #[tokio::test]
    async fn a_late_reply_at_a_shared_address_is_one_warn_naming_the_unit() {
        use tracing_subscriber::layer::SubscriberExt;
        let warnings = Warnings::default();
        let _log =
            tracing::subscriber::set_default(tracing_subscriber::registry().with(warnings.clone()));
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap().to_string();
        let peer = tokio::spawn(async move {
            let (mut s, _) = listener.accept().await.unwrap();
            let mut req = [0u8; 12];
            while s.read_exact(&mut req).await.is_ok() {
                if req[6] == 4 {
                    tokio::time::sleep(Duration::from_millis(300)).await;
                }
                let reply = [req[0], req[1], 0, 0, 0, 5, req[6], 4, 2, 0, 7];
                if s.write_all(&reply).await.is_err() {
                    break;
                }
            }
        });
        let timeout = Duration::from_millis(200);
        let mut link = tcp_link(address.clone(), timeout, timeout).shared_address();
        assert_eq!(link.read(1, RegisterKind::Input, 0, 1).await, Ok(vec![7]));
        assert_eq!(
            link.read(4, RegisterKind::Input, 0, 1).await,
            Err(SourceError::Timeout(timeout))
        );
        assert_eq!(link.read(1, RegisterKind::Input, 0, 1).await, Ok(vec![7]));
        assert_eq!(link.connects(), 1);
        peer.abort();
        let seen = warnings.0.lock().unwrap().clone();
        assert_eq!(seen, [late_warning(4, 11, &format!("tcp://{address}"))]);
    }

    // A device answering every request late logs one WARN a minute, the next one
    // with the count of those not logged.
    #[tokio::test(start_paused = true)]
    async fn late_rtu_replies_are_logged_once_a_minute_with_a_count() {
        use tracing_subscriber::layer::SubscriberExt;
        let warnings = Warnings::default();
        let _log =
            tracing::subscriber::set_default(tracing_subscriber::registry().with(warnings.clone()));
        let mut link = rtu_link("/dev/ttyX", Duration::from_millis(200));
        for _ in 0..3 {
            link.late_reply(4, Duration::from_millis(200), 7);
            tokio::time::advance(Duration::from_secs(20)).await;
        }
        assert_eq!(warnings.0.lock().unwrap().len(), 1);
        link.late_reply(4, Duration::from_millis(200), 7);
        let seen = warnings.0.lock().unwrap().clone();
        assert_eq!(seen.len(), 2, "{seen:#?}");
        assert!(
            seen[1].contains(
                "raise timeout_s for it; 2 more late replies in the last 60 s not logged"
            ),
            "{}",
            seen[1]
        );
    }

    // A reply with a bad CRC, an adapter echoing the request, another unit answering:
    // tokio-modbus drops the first two and waits (reported as "no reply within"), and
    // said the third in debug output. Each is a bad frame naming the serial path.
    #[tokio::test]
    async fn garbled_rtu_replies_are_bad_frames_naming_the_line() {
        let timeout = Duration::from_millis(200);
        type Reply = fn(&[u8; 8]) -> Vec<u8>;
        let cases: [(Reply, &str); 3] = [
            (
                |req| {
                    let mut f = rtu_reply(req[0], req[1], &[1775]);
                    let last = f.len() - 1;
                    f[last] ^= 0xFF;
                    f
                },
                "no complete reply with a valid CRC",
            ),
            (
                |req| [&req[..], &rtu_reply(req[0], req[1], &[1775])].concat(),
                "the request came back as it was sent (the bytes 01 04 00 00 00 01",
            ),
            (
                |req| rtu_reply(req[0] + 1, req[1], &[1775]),
                "the reply came from unit 2, the request went to unit 1",
            ),
        ];
        for (reply, says) in cases {
            let (path, _near, device) = rtu_device(move |req| (Duration::ZERO, reply(req)));
            let mut link = rtu_link(&path, timeout);
            let err = link.read(1, RegisterKind::Input, 0, 1).await.unwrap_err();
            assert_eq!(err.kind(), "frame", "{err}");
            let text = err.to_string();
            assert!(
                text.starts_with(&format!("bad reply on {path}: ")) && text.contains(says),
                "{text}"
            );
            device.abort();
        }
    }

    // An RTU adapter unplugged mid-use said "Input/output error (os error 5)", not
    // which line.
    #[tokio::test]
    async fn a_failing_serial_line_is_named() {
        let (path, near, device) =
            rtu_device(|req| (Duration::ZERO, rtu_reply(req[0], req[1], &[7])));
        let mut link = rtu_link(&path, Duration::from_millis(500));
        assert_eq!(link.read(1, RegisterKind::Input, 0, 1).await, Ok(vec![7]));
        device.abort();
        let _ = device.await;
        drop(near);
        let err = link.read(1, RegisterKind::Input, 0, 1).await.unwrap_err();
        assert!(err.to_string().contains(&path), "{err}");
    }

    /// The error opening an RTU link at `path` reports.
    async fn open_error(path: &str) -> String {
        let mut link = rtu_link(path, Duration::from_millis(100));
        let err = link.open().await.expect_err("no serial device");
        assert_eq!(err.kind(), "connect", "{err}");
        err.to_string()
    }

    // Field review: "connect failed: /dev/ttyUSB1: No such file or directory" and
    // "Not a typewriter" said nothing of what to do.
    #[tokio::test]
    async fn a_serial_path_that_is_missing_or_no_tty_says_what_to_check() {
        let dir = std::env::temp_dir().join(format!("compgate-serial-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let missing = dir.join("ttyUSB9").display().to_string();
        assert_eq!(
            open_error(&missing).await,
            format!(
                "connect failed: {missing}: does not exist: check the adapter is plugged in \
                 and the path (ls /dev/serial/by-id gives stable names)"
            )
        );
        let file = dir.join("a-regular-file");
        std::fs::write(&file, b"").unwrap();
        let file = file.display().to_string();
        for path in [file.as_str(), "/dev/null"] {
            let text = open_error(path).await;
            assert!(
                text == format!("connect failed: {path}: not a serial device"),
                "{text}"
            );
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    // As root every path opens, so the kinds serialport gives are mapped here; the
    // binary's test as another user (tests/cli.rs) opens a file it may not read.
    #[test]
    fn serial_open_errors_are_mapped_to_what_to_do() {
        use tokio_serial::{Error, ErrorKind as K};
        let mapped = |kind, description: &str| {
            serial_open_failed("/dev/ttyX", &Error::new(kind, description)).to_string()
        };
        assert_eq!(
            mapped(
                K::Io(std::io::ErrorKind::PermissionDenied),
                "Permission denied"
            ),
            "connect failed: /dev/ttyX: permission denied: the gateway's user needs the \
             tty's group (usually dialout)"
        );
        assert!(mapped(
            K::Io(std::io::ErrorKind::NotFound),
            "No such file or directory"
        )
        .starts_with("connect failed: /dev/ttyX: does not exist: "));
        assert_eq!(
            mapped(K::Unknown, "Not a typewriter"),
            "connect failed: /dev/ttyX: not a serial device"
        );
        assert!(mapped(K::Unknown, "Operation not permitted")
            .contains("operation not permitted: under systemd, the unit's DeviceAllow="));
        assert_eq!(
            mapped(K::NoDevice, "Device or resource busy"),
            "connect failed: /dev/ttyX: Device or resource busy"
        );
    }

    // Frames reach tokio-modbus whole and only for the last request: a late reply
    // (another transaction id) is dropped, a frame split across reads waits for its
    // end, and bytes that are no MBAP frame are passed on for tokio-modbus to refuse.
    #[test]
    fn only_whole_frames_of_the_last_request_are_passed_on() {
        let frame = |tid: u8, unit: u8| vec![0, tid, 0, 0, 0, 5, unit, 4, 2, 0, 7];
        let mut frames = Frames::default();
        let mut late = None;
        frames.partial.extend(frame(1, 4));
        frames.partial.extend(&frame(2, 1)[..8]);
        assert_eq!(frames.split(Some([0, 2]), &mut late), 1);
        assert!(
            frames.ready.is_empty(),
            "the late reply of request 1 passed"
        );
        frames.partial.extend(&frame(2, 1)[8..]);
        assert_eq!(frames.split(Some([0, 2]), &mut late), 1);
        assert_eq!(frames.ready.drain(..).collect::<Vec<_>>(), frame(2, 1));
        frames.partial.extend(b"HTTP/1.1 400 Bad Request");
        assert_eq!(frames.split(Some([0, 3]), &mut late), 0);
        assert_eq!(frames.ready.len(), 24);
    }

    #[test]
    fn bytes_are_shown_as_text_or_hex() {
        assert_eq!(describe_bytes(b"SSH-2.0\r\n"), "\"SSH-2.0\\r\\n\"");
        assert_eq!(describe_bytes(&[0x16, 0x03, 0x01]), "the bytes 16 03 01");
        assert!(describe_bytes(&[b'x'; REPLY_KEPT_BYTES]).ends_with("\" ..."));
        assert!(mbap_plausible(&[0, 1, 0, 0, 0, 5, 1, 4]));
        assert!(!mbap_plausible(b"HTTP/1.1"));
        assert!(!mbap_plausible(&[0, 1, 0, 0, 0x2F, 0x31]));
    }

    #[test]
    fn backoff_doubles_and_caps_and_resets() {
        let t0 = Instant::now();
        let mut b = Backoff::new(Duration::from_millis(100), Duration::from_millis(350));
        assert_eq!(b.remaining(t0), None);
        b.failed(t0);
        assert_eq!(b.remaining(t0), Some(Duration::from_millis(100)));
        b.failed(t0);
        assert_eq!(b.remaining(t0), Some(Duration::from_millis(200)));
        b.failed(t0);
        assert_eq!(b.remaining(t0), Some(Duration::from_millis(350)));
        b.failed(t0);
        assert_eq!(b.remaining(t0), Some(Duration::from_millis(350)));
        assert_eq!(b.remaining(t0 + Duration::from_secs(1)), None);
        b.reset();
        assert_eq!(b.current(), Duration::from_millis(100));
        assert_eq!(b.remaining(t0), None);
    }

    // A reload that gives a kept link a shorter backoff (a device added beside it):
    // the delay reached so far is cut to the new longest, and a reset starts at the
    // new first delay.
    #[test]
    fn a_retuned_backoff_keeps_within_its_new_bounds() {
        let t0 = Instant::now();
        let mut b = Backoff::new(Duration::from_secs(1), Duration::from_secs(30));
        for _ in 0..4 {
            b.failed(t0);
        }
        assert_eq!(b.current(), Duration::from_secs(16));
        b.retune(&Backoff::new(
            Duration::from_millis(200),
            Duration::from_secs(2),
        ));
        assert_eq!(b.current(), Duration::from_secs(2));
        b.reset();
        assert_eq!(b.current(), Duration::from_millis(200));
    }
}
