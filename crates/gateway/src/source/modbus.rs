//! A Modbus client connection that survives the field.
//!
//! tokio-modbus leaves four gaps this type closes: every request is wrapped in a
//! timeout; connecting has its own timeout; TCP sockets get `TCP_NODELAY`; and after
//! any transport error or timeout the context is dropped and rebuilt, because a late
//! reply left in the old stream would otherwise be read as the answer to the next
//! request (tokio-modbus issue 324). Reconnects back off exponentially up to a cap.
//! While a poll cycle runs, its deadline also bounds every request and connect, so a
//! cycle of many reads to a silent device ends after one deadline.
//!
//! On TCP, a connection that fails other than by a timeout before its first good reply
//! counts as a failed connect for the backoff: a peer that accepts and then closes, or
//! answers something other than Modbus, is retried as slowly as one that refuses. Such
//! faults are named with the peer's address (tokio-modbus reports a closed peer with a
//! stale errno and a peer answering HTTP with "bytes remaining on stream").

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
}

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
            backoff,
            connect_error: None,
            answered: false,
            peer: None,
            connects: 0,
        }
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
        match &self.spec {
            LinkSpec::Tcp {
                address,
                connect_timeout,
            } => {
                let at = Instant::now() + *connect_timeout;
                let cut = self.cycle_cut(at);
                let stream = tokio::time::timeout_at(
                    cut.map_or(at, |(end, _)| end),
                    TcpStream::connect(address),
                )
                .await
                .map_err(|_| match cut {
                    Some((_, length)) => SourceError::Deadline(length),
                    None => SourceError::ConnectTimeout,
                })?
                .map_err(|e| SourceError::Connect(format!("{address}: {e}")))?;
                // Small request/response frames: Nagle would add up to 40 ms each.
                stream
                    .set_nodelay(true)
                    .map_err(|e| SourceError::Connect(format!("{address}: {e}")))?;
                let seen = Arc::new(Mutex::new(PeerSeen::default()));
                let stream = WatchedStream {
                    inner: stream,
                    seen: seen.clone(),
                };
                Ok((tcp::attach(stream), Some(seen)))
            }
            LinkSpec::Rtu {
                path,
                baud,
                parity,
                stop_bits,
            } => {
                let builder = tokio_serial::new(path, *baud)
                    .parity(*parity)
                    .stop_bits(*stop_bits)
                    .data_bits(tokio_serial::DataBits::Eight);
                let port = tokio_serial::SerialStream::open(&builder)
                    .map_err(|e| SourceError::Connect(format!("{path}: {e}")))?;
                // A late reply may still sit in the tty buffer: drop it with the old context.
                port.clear(tokio_serial::ClearBuffer::All)
                    .map_err(|e| SourceError::Connect(format!("{path}: {e}")))?;
                Ok((rtu::attach(port), None))
            }
        }
    }

    /// Bounds every request and connect until `None` by `at`, the end of a poll cycle
    /// of length `length`: one deadline for all reads of a cycle, their retries and
    /// reconnects. A request cut by it fails with [`SourceError::Deadline`] and drops
    /// the connection like a timeout.
    pub fn set_cycle_deadline(&mut self, cycle: Option<(Instant, Duration)>) {
        self.cycle = cycle;
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
    }

    /// Records a good reply: the link works, the backoff starts over.
    fn answered(&mut self) {
        self.answered = true;
        self.backoff.reset();
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

    /// What the TCP peer's bytes and EOF say about a request that failed with `io`
    /// (`None`: timed out), where tokio-modbus's error does not: it reports a peer that
    /// closed with a stale `errno` ("Operation now in progress") and one that answered
    /// a few bytes of something else and closed with "bytes remaining on stream".
    fn peer_fault(&self, io: Option<&std::io::Error>) -> Option<SourceError> {
        use std::io::ErrorKind;
        let (LinkSpec::Tcp { address, .. }, Some(seen)) = (&self.spec, &self.peer) else {
            return None;
        };
        let seen = seen.lock().unwrap_or_else(PoisonError::into_inner);
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
            Some(SourceError::PeerClosed(address.clone()))
        } else {
            None
        }
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
        if let Some((_, length)) = self.cycle.filter(|(end, _)| Instant::now() >= *end) {
            return Err(SourceError::Deadline(length));
        }
        self.ensure_connected().await?;
        let timeout = self.timeout;
        let cut = self.cycle_cut(Instant::now() + timeout);
        let at = cut.map_or(Instant::now() + timeout, |(end, _)| end);
        let deadline = self
            .deadline
            .get_or_insert_with(|| Box::pin(tokio::time::sleep_until(at)));
        deadline.as_mut().reset(at);
        let Some(ctx) = self.ctx.as_mut() else {
            return Err(SourceError::Connect("no context".into()));
        };
        ctx.set_slave(Slave(unit));
        let outcome = tokio::select! {
            // The reply wins a tie with the deadline.
            biased;
            r = ctx.call(request) => Some(r),
            () = deadline.as_mut() => None,
        };
        match outcome {
            // Good once the caller has checked its shape.
            Some(Ok(Ok(response))) => Ok(response),
            // The device answered: the link is fine.
            Some(Ok(Err(code))) => {
                self.answered();
                Err(SourceError::Exception(code))
            }
            Some(Err(e)) => {
                // Protocol errors (a reply out of step) come from a Modbus peer and
                // say it well.
                let known = match &e {
                    tokio_modbus::Error::Transport(io) => self.peer_fault(Some(io)),
                    tokio_modbus::Error::Protocol(_) => None,
                };
                let error = known.unwrap_or_else(|| SourceError::Transport(e.to_string()));
                Err(self.fault(error))
            }
            None => {
                // Bytes that are no Modbus frame leave the client waiting for more.
                let error = match (self.peer_fault(None), cut) {
                    (Some(e @ SourceError::NotModbus { .. }), _) => e,
                    (_, Some((_, length))) => SourceError::Deadline(length),
                    (_, None) => SourceError::Timeout(timeout),
                };
                Err(self.fault(error))
            }
        }
    }

    /// A reply out of step with its request: the stream cannot be trusted, start over.
    fn out_of_step(&mut self, what: String) -> SourceError {
        self.fault(SourceError::Transport(what))
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
            other => Err(self.out_of_step(format!(
                "asked for {count} registers at {start}, got {}",
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

/// What a TCP peer sent since the last request went out, and whether it closed.
#[derive(Debug, Default)]
struct PeerSeen {
    /// The first [`REPLY_KEPT_BYTES`] bytes received since the last write.
    reply: Vec<u8>,
    /// The peer closed its side (a read returned end of stream).
    closed: bool,
}

/// A TCP stream that notes in [`PeerSeen`] what the peer does, for the error messages.
#[derive(Debug)]
struct WatchedStream {
    inner: TcpStream,
    seen: Arc<Mutex<PeerSeen>>,
}

impl WatchedStream {
    fn seen(&self) -> std::sync::MutexGuard<'_, PeerSeen> {
        self.seen.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

impl AsyncRead for WatchedStream {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut TaskContext<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
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

impl AsyncWrite for WatchedStream {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut TaskContext<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        // A new request: what came before it is not its reply.
        self.seen().reply.clear();
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut TaskContext<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        self.seen().reply.clear();
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
        Response::ReadInputRegisters(w) | Response::ReadHoldingRegisters(w) => {
            format!("{} registers", w.len())
        }
        Response::WriteSingleRegister(a, v) => format!("write of {v} at {a}"),
        Response::WriteMultipleRegisters(a, n) => format!("write of {n} registers at {a}"),
        other => format!("{other:?}"),
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
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap().to_string();
        let peer = tokio::spawn(async move {
            let mut held = Vec::new();
            while let Ok((s, _)) = listener.accept().await {
                held.push(s);
            }
        });
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
}
