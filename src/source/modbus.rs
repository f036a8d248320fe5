//! A Modbus client connection that survives the field.
//!
//! tokio-modbus leaves four gaps this type closes: every request is wrapped in a
//! timeout; connecting has its own timeout; TCP sockets get `TCP_NODELAY`; and after
//! any transport error or timeout the context is dropped and rebuilt, because a late
//! reply left in the old stream would otherwise be read as the answer to the next
//! request (tokio-modbus issue 324). Reconnects back off exponentially up to a cap.

use std::net::SocketAddr;
use std::time::Duration;

use tokio::net::TcpStream;
use tokio::time::Instant;
use tokio_modbus::client::{rtu, tcp, Client, Context, Writer};
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
    backoff: Backoff,
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
            backoff,
            connects: 0,
        }
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

    async fn connect(&mut self) -> Result<Context, SourceError> {
        match &self.spec {
            LinkSpec::Tcp {
                address,
                connect_timeout,
            } => {
                let stream = tokio::time::timeout(*connect_timeout, TcpStream::connect(address))
                    .await
                    .map_err(|_| SourceError::ConnectTimeout)?
                    .map_err(|e| SourceError::Connect(e.to_string()))?;
                // Small request/response frames: Nagle would add up to 40 ms each.
                stream
                    .set_nodelay(true)
                    .map_err(|e| SourceError::Connect(e.to_string()))?;
                Ok(tcp::attach(stream))
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
                Ok(rtu::attach(port))
            }
        }
    }

    /// Drops the context so the next request starts on a fresh connection.
    pub fn disconnect(&mut self) {
        self.ctx = None;
    }

    /// Returns the live context, connecting first if needed and the backoff allows.
    async fn context(&mut self) -> Result<&mut Context, SourceError> {
        if self.ctx.is_none() {
            if let Some(left) = self.backoff.remaining(Instant::now()) {
                return Err(SourceError::BackingOff(left));
            }
            match self.connect().await {
                Ok(ctx) => {
                    self.connects += 1;
                    tracing::debug!(link = %self.spec, connects = self.connects, "connected");
                    self.ctx = Some(ctx);
                }
                Err(e) => {
                    self.backoff.failed(Instant::now());
                    tracing::debug!(link = %self.spec, error = %e, retry_in_s = self.backoff.current().as_secs_f64(), "connect failed");
                    return Err(e);
                }
            }
        }
        self.ctx
            .as_mut()
            .ok_or_else(|| SourceError::Connect("no context".into()))
    }

    /// Runs one request with the timeout; any transport fault drops the context.
    async fn call<T, F>(&mut self, unit: u8, f: F) -> Result<T, SourceError>
    where
        F: for<'a> FnOnce(
            &'a mut Context,
        ) -> std::pin::Pin<
            Box<dyn std::future::Future<Output = tokio_modbus::Result<T>> + Send + 'a>,
        >,
    {
        let timeout = self.timeout;
        let ctx = self.context().await?;
        ctx.set_slave(Slave(unit));
        let outcome = tokio::time::timeout(timeout, f(ctx)).await;
        match outcome {
            Ok(Ok(Ok(v))) => {
                self.backoff.reset();
                Ok(v)
            }
            // The device answered: the link is fine.
            Ok(Ok(Err(code))) => {
                self.backoff.reset();
                Err(SourceError::Exception(code))
            }
            Ok(Err(e)) => {
                self.disconnect();
                Err(SourceError::Transport(e.to_string()))
            }
            Err(_) => {
                self.disconnect();
                Err(SourceError::Timeout(timeout))
            }
        }
    }

    /// Reads `count` registers at `start` from unit `unit`.
    pub async fn read(
        &mut self,
        unit: u8,
        kind: RegisterKind,
        start: u16,
        count: u16,
    ) -> Result<Vec<u16>, SourceError> {
        let regs = self
            .call(unit, move |ctx| {
                // Not `read_input_registers`/`read_holding_registers`: they
                // debug-assert the register count, which a malformed reply (wrong byte
                // count on RTU) breaks with a panic. The count is checked below.
                let request = match kind {
                    RegisterKind::Input => Request::ReadInputRegisters(start, count),
                    RegisterKind::Holding => Request::ReadHoldingRegisters(start, count),
                };
                Box::pin(async move {
                    ctx.call(request).await.map(|r| {
                        r.map(|response| match response {
                            Response::ReadInputRegisters(w) | Response::ReadHoldingRegisters(w) => {
                                w
                            }
                            // Any other reply is out of step: the count check rejects it.
                            _ => Vec::new(),
                        })
                    })
                })
            })
            .await?;
        if regs.len() != usize::from(count) {
            // A short answer means the stream is out of step: start over.
            self.disconnect();
            return Err(SourceError::Transport(format!(
                "asked for {count} registers at {start}, got {}",
                regs.len()
            )));
        }
        Ok(regs)
    }

    /// Writes holding registers starting at `start`.
    pub async fn write(&mut self, unit: u8, start: u16, words: &[u16]) -> Result<(), SourceError> {
        let words = words.to_vec();
        self.call(unit, move |ctx| {
            Box::pin(async move {
                if let [w] = words[..] {
                    ctx.write_single_register(start, w).await
                } else {
                    ctx.write_multiple_registers(start, &words).await
                }
            })
        })
        .await
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
