//! Simulated field I/O module: N PT100 transmitters (4-20 or 0-20 mA) on a 12-bit
//! ADC, served over Modbus TCP or RTU.
//!
//! Each transmitter follows a temperature [`Profile`] plus Gaussian noise, maps it to a
//! loop current (4 mA, or 0 mA for 0-20, at `range_min_degc`, 20 mA at
//! `range_max_degc`, saturating 0.2 mA below its range (3.8 mA like a NAMUR NE43
//! transmitter; 0 mA for 0-20) and at 20.5 mA) and the ADC converts the current to
//! counts, at the module's full scale or the transmitter's own. Sensor faults
//! ([`SensorFault`]) and communication faults ([`CommFault`]) can be injected at run
//! time through the cloneable [`FieldModule`] handle.
//!
//! # Register layout
//!
//! All addresses are 0-based PDU addresses. Input registers (function 0x04) and holding
//! registers (function 0x03) hold the same values. `i` is the transmitter index,
//! `0 <= i < N`, `N <= 500`.
//!
//! | address | content |
//! |---|---|
//! | `i` (0..N) | ADC counts of transmitter `i`, u16, `0..=adc_full_scale_counts` |
//! | `1000 + 2i`, `1001 + 2i` | measured temperature of transmitter `i` (degC), f32, word order CDAB: low word first, big-endian bytes inside each word |
//! | `2000 + 2i`, `2001 + 2i` | the same f32 in word order ABCD: high word first |
//!
//! The measured temperature is what the module's own firmware derives from the counts
//! (counts -> mA -> degC, linear over the range, not clamped), so a sensor fault shows
//! in the float registers too and both views always agree.
//!
//! A read must lie entirely inside one of the three blocks (reading half of a float is
//! allowed); anything else is refused with exception 0x02 `IllegalDataAddress`, a
//! quantity of 0 or more than 125 with 0x03 `IllegalDataValue`. The module is read-only:
//! every write function and every coil/discrete-input read gets 0x01
//! `IllegalFunction`.
//!
//! # Communication faults over TCP
//!
//! [`FieldModule::serve_tcp`] uses tokio-modbus's server with one task per connection.
//! Each connection's socket is wrapped in a transport that watches a cancellation token
//! shared by all connections of the module. Setting [`CommFault::DropConnections`]
//! cancels that token: every open connection reads EOF, its task ends and drops the
//! socket, so the client sees EOF (or a reset if it keeps writing). A reply being
//! delayed is cut short the same way. While the fault is set, new connections are
//! accepted by the kernel and closed at once. Clearing the fault lets new connections
//! work again (with a fresh token).
//!
//! Replies are computed when the request arrives. [`CommFault::Delay`] then holds the
//! reply back and sends it even if the client has timed out meanwhile, so a client
//! that reuses the connection reads the late reply as the answer to its next request.
//!
//! # Sampling
//!
//! The ADC converts every transmitter once per valid read request, drawing one noise
//! sample per transmitter in index order from a [`SimRng`] seeded with
//! [`FieldModuleSpec::seed`], so the same requests at the same (tokio) times give the
//! same values. Profile time `t_s` counts from [`FieldModule::new`] in tokio time, so
//! `tokio::time::pause()` controls it.

use std::future::Future;
use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::task::{Context, Poll};
use std::time::Duration;

use crate::SimRng;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::time::Instant;
use tokio_modbus::server::Service;
use tokio_modbus::{ExceptionCode, Request, Response, SlaveRequest};
use tokio_serial::SerialPort as _;
use tokio_util::sync::{CancellationToken, WaitForCancellationFutureOwned};

/// First register of the counts block.
pub const COUNTS_BASE: u16 = 0;
/// First register of the f32 block in word order CDAB.
pub const FLOAT_CDAB_BASE: u16 = 1000;
/// First register of the f32 block in word order ABCD.
pub const FLOAT_ABCD_BASE: u16 = 2000;
/// Most transmitters one module can hold without its blocks overlapping.
pub const MAX_TRANSMITTERS: usize = 500;
/// Most registers one read may ask for (Modbus limit).
pub const MAX_READ_QUANTITY: u16 = 125;

/// Default ADC full scale, 12 bit.
pub const DEFAULT_ADC_FULL_SCALE_COUNTS: u16 = 4095;
/// Default current at ADC full scale: above 20 mA so over-range and faults stay visible.
pub const DEFAULT_ADC_FULL_SCALE_MA: f64 = 24.0;

/// Loop current at the bottom of the measuring range.
pub const RANGE_LOW_MA: f64 = 4.0;
/// Loop current span of the measuring range (4..20 mA).
pub const RANGE_SPAN_MA: f64 = 16.0;
/// Lowest current of a healthy 4-20 mA transmitter below its range (NE43 saturation).
pub const SATURATION_LOW_MA: f64 = 3.8;
/// Top of every current range, mA.
pub const RANGE_HIGH_MA: f64 = 20.0;
/// Highest current of a healthy transmitter above its range (NE43 saturation).
pub const SATURATION_HIGH_MA: f64 = 20.5;
/// Failure current of an open sensor (NE43 downscale).
pub const OPEN_SENSOR_MA: f64 = 3.5;
/// Failure current of a shorted sensor (NE43 upscale).
pub const SHORT_SENSOR_MA: f64 = 21.5;

/// Errors of the field module layer.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FieldError {
    /// The module description cannot describe a real module.
    #[error("invalid field module spec: {0}")]
    InvalidSpec(String),
    /// A transmitter index beyond the module's transmitters.
    #[error("no transmitter {index}: the module has {count}")]
    NoSuchTransmitter {
        /// Index asked for.
        index: usize,
        /// Transmitters in the module.
        count: usize,
    },
    /// The TCP listener failed.
    #[error("Modbus TCP server failed ({kind:?}): {message}")]
    Tcp {
        /// Kind of the I/O error.
        kind: io::ErrorKind,
        /// Its message.
        message: String,
    },
    /// The serial line failed.
    #[error("Modbus RTU server failed ({kind:?}): {message}")]
    Rtu {
        /// Kind of the I/O error.
        kind: io::ErrorKind,
        /// Its message.
        message: String,
    },
    /// The pseudo terminal pair could not be created.
    #[error("cannot create a pty pair: {0}")]
    Pty(String),
}

/// Temperature over time of one transmitter; `t_s` counts from [`FieldModule::new`].
#[derive(Debug, Clone, PartialEq)]
pub enum Profile {
    /// Fixed temperature.
    Constant {
        /// Temperature, degC.
        degc: f64,
    },
    /// `start_degc + rate_degc_per_s * t_s`.
    Ramp {
        /// Temperature at `t_s = 0`, degC.
        start_degc: f64,
        /// Slope, degC per second.
        rate_degc_per_s: f64,
    },
    /// `mean_degc + amplitude_degc * sin(2 pi t_s / period_s)`.
    Sine {
        /// Mean, degC.
        mean_degc: f64,
        /// Amplitude, degC.
        amplitude_degc: f64,
        /// Period, s (> 0).
        period_s: f64,
    },
    /// Piecewise constant: `(t_s, degc)` pairs sorted by time; the value of the last
    /// step with `t_s <= now` holds, the first value holds before the first step.
    Steps(Vec<(f64, f64)>),
}

impl Profile {
    /// Temperature at `t_s` seconds after the module started.
    pub fn temperature_degc(&self, t_s: f64) -> f64 {
        match self {
            Self::Constant { degc } => *degc,
            Self::Ramp {
                start_degc,
                rate_degc_per_s,
            } => start_degc + rate_degc_per_s * t_s,
            Self::Sine {
                mean_degc,
                amplitude_degc,
                period_s,
            } => mean_degc + amplitude_degc * (std::f64::consts::TAU * t_s / period_s).sin(),
            Self::Steps(steps) => steps
                .iter()
                .take_while(|(step_t_s, _)| *step_t_s <= t_s)
                .last()
                .or(steps.first())
                .map_or(0.0, |(_, degc)| *degc),
        }
    }

    /// Why the profile cannot be run (a value that is not finite, an empty or unsorted
    /// step list).
    fn validate(&self) -> Result<(), FieldError> {
        let finite = |v: f64, what: &str| {
            if v.is_finite() {
                Ok(())
            } else {
                Err(FieldError::InvalidSpec(format!("{what} is not finite")))
            }
        };
        match self {
            Self::Constant { degc } => finite(*degc, "degc"),
            Self::Ramp {
                start_degc,
                rate_degc_per_s,
            } => {
                finite(*start_degc, "start_degc")?;
                finite(*rate_degc_per_s, "rate_degc_per_s")
            }
            Self::Sine {
                mean_degc,
                amplitude_degc,
                period_s,
            } => {
                finite(*mean_degc, "mean_degc")?;
                finite(*amplitude_degc, "amplitude_degc")?;
                if period_s.is_finite() && *period_s > 0.0 {
                    Ok(())
                } else {
                    Err(FieldError::InvalidSpec(format!(
                        "period_s = {period_s} must be > 0"
                    )))
                }
            }
            Self::Steps(steps) => {
                if steps.is_empty() {
                    return Err(FieldError::InvalidSpec(
                        "Steps needs at least one step".into(),
                    ));
                }
                for (t_s, degc) in steps {
                    finite(*t_s, "step t_s")?;
                    finite(*degc, "step degc")?;
                }
                if steps.windows(2).any(|w| w[1].0 < w[0].0) {
                    return Err(FieldError::InvalidSpec(
                        "Steps must be sorted by t_s".into(),
                    ));
                }
                Ok(())
            }
        }
    }
}

/// One PT100 transmitter: profile, noise, its current range and, when it differs from
/// the module's, the ADC full scale it is read with.
#[derive(Debug, Clone, PartialEq)]
pub struct TransmitterSpec {
    /// True temperature over time.
    pub profile: Profile,
    /// Standard deviation of the measurement noise, degC (0 = none).
    pub noise_degc: f64,
    /// Temperature at the bottom of the current range, degC.
    pub range_min_degc: f64,
    /// Temperature at 20 mA, degC.
    pub range_max_degc: f64,
    /// Current at `range_min_degc`, mA: 4 (4-20 mA, live zero) or 0 (0-20 mA).
    pub range_low_ma: f64,
    /// The ADC full scale of this channel; `None`: the module's.
    pub adc_full_scale: Option<AdcFullScale>,
}

/// An ADC's full scale: `counts` at `ma`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdcFullScale {
    /// Counts at full scale.
    pub counts: u16,
    /// Current at full scale, mA.
    pub ma: f64,
}

impl AdcFullScale {
    /// ADC counts for a loop current: rounded and clipped to the ADC's range.
    pub fn ma_to_counts(&self, ma: f64) -> u16 {
        let full_scale = f64::from(self.counts);
        // In 0..=u16::MAX after the clamp, so the cast is exact.
        (ma / self.ma * full_scale).clamp(0.0, full_scale).round() as u16
    }

    /// Loop current for ADC counts.
    pub fn counts_to_ma(&self, counts: u16) -> f64 {
        f64::from(counts) * self.ma / f64::from(self.counts)
    }

    fn validate(&self) -> Result<(), String> {
        if self.counts == 0 {
            return Err("adc_full_scale_counts must be > 0".into());
        }
        if !(self.ma.is_finite() && self.ma > 0.0) {
            return Err(format!("adc_full_scale_ma = {} must be > 0", self.ma));
        }
        Ok(())
    }
}

impl TransmitterSpec {
    /// A noiseless 4-20 mA transmitter over `range_min_degc..range_max_degc`, read at
    /// the module's ADC full scale.
    pub fn new(profile: Profile, range_min_degc: f64, range_max_degc: f64) -> Self {
        Self {
            profile,
            noise_degc: 0.0,
            range_min_degc,
            range_max_degc,
            range_low_ma: RANGE_LOW_MA,
            adc_full_scale: None,
        }
    }

    /// Loop current of a healthy transmitter at `degc`, saturated 0.2 mA below its
    /// range (3.8 mA for 4-20, never below 0) and at 20.5 mA.
    pub fn degc_to_ma(&self, degc: f64) -> f64 {
        let span_degc = self.range_max_degc - self.range_min_degc;
        let span_ma = RANGE_HIGH_MA - self.range_low_ma;
        let ma = self.range_low_ma + span_ma * (degc - self.range_min_degc) / span_degc;
        let low_ma = (self.range_low_ma - (RANGE_LOW_MA - SATURATION_LOW_MA)).max(0.0);
        ma.clamp(low_ma, SATURATION_HIGH_MA)
    }

    /// Temperature for a loop current, linear over the range and not clamped.
    pub fn ma_to_degc(&self, ma: f64) -> f64 {
        let span_degc = self.range_max_degc - self.range_min_degc;
        let span_ma = RANGE_HIGH_MA - self.range_low_ma;
        self.range_min_degc + (ma - self.range_low_ma) / span_ma * span_degc
    }
}

/// The whole module: its transmitters, its ADC and the noise seed.
#[derive(Debug, Clone, PartialEq)]
pub struct FieldModuleSpec {
    /// Transmitters, 1..=500; index = channel.
    pub transmitters: Vec<TransmitterSpec>,
    /// ADC counts at `adc_full_scale_ma`.
    pub adc_full_scale_counts: u16,
    /// Current at ADC full scale, mA.
    pub adc_full_scale_ma: f64,
    /// Seed of the noise generator.
    pub seed: u64,
}

impl FieldModuleSpec {
    /// A module with the default 12-bit, 24 mA ADC.
    pub fn new(transmitters: Vec<TransmitterSpec>, seed: u64) -> Self {
        Self {
            transmitters,
            adc_full_scale_counts: DEFAULT_ADC_FULL_SCALE_COUNTS,
            adc_full_scale_ma: DEFAULT_ADC_FULL_SCALE_MA,
            seed,
        }
    }

    /// The module's ADC full scale.
    pub fn adc(&self) -> AdcFullScale {
        AdcFullScale {
            counts: self.adc_full_scale_counts,
            ma: self.adc_full_scale_ma,
        }
    }

    /// The ADC full scale transmitter `i` is read with: its own, else the module's.
    pub fn adc_of(&self, i: usize) -> AdcFullScale {
        self.transmitters
            .get(i)
            .and_then(|t| t.adc_full_scale)
            .unwrap_or_else(|| self.adc())
    }

    /// ADC counts for a loop current at the module's full scale.
    pub fn ma_to_counts(&self, ma: f64) -> u16 {
        self.adc().ma_to_counts(ma)
    }

    /// Loop current for ADC counts at the module's full scale.
    pub fn counts_to_ma(&self, counts: u16) -> f64 {
        self.adc().counts_to_ma(counts)
    }

    /// Checks everything [`FieldModule::new`] relies on.
    pub fn validate(&self) -> Result<(), FieldError> {
        let bad = |msg: String| Err(FieldError::InvalidSpec(msg));
        if self.transmitters.is_empty() || self.transmitters.len() > MAX_TRANSMITTERS {
            return bad(format!(
                "{} transmitters; 1..={MAX_TRANSMITTERS} allowed",
                self.transmitters.len()
            ));
        }
        if let Err(msg) = self.adc().validate() {
            return bad(msg);
        }
        for (i, t) in self.transmitters.iter().enumerate() {
            if let Some(Err(msg)) = t.adc_full_scale.map(|a| a.validate()) {
                return bad(format!("transmitter {i}: {msg}"));
            }
            if !(t.range_low_ma.is_finite() && (0.0..RANGE_HIGH_MA).contains(&t.range_low_ma)) {
                return bad(format!(
                    "transmitter {i}: range_low_ma = {} must be in 0..20 mA",
                    t.range_low_ma
                ));
            }
            if !(t.range_min_degc.is_finite()
                && t.range_max_degc.is_finite()
                && t.range_min_degc < t.range_max_degc)
            {
                return bad(format!(
                    "transmitter {i}: range {}..{} degC is empty or not finite",
                    t.range_min_degc, t.range_max_degc
                ));
            }
            if !(t.noise_degc.is_finite() && t.noise_degc >= 0.0) {
                return bad(format!(
                    "transmitter {i}: noise_degc = {} must be >= 0",
                    t.noise_degc
                ));
            }
            if let Err(FieldError::InvalidSpec(msg)) = t.profile.validate() {
                return bad(format!("transmitter {i}: {msg}"));
            }
        }
        Ok(())
    }
}

/// A sensor-side fault of one transmitter.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SensorFault {
    /// Healthy.
    #[default]
    None,
    /// Broken sensor wire: 3.5 mA (NAMUR NE43 downscale).
    Open,
    /// Shorted sensor: 21.5 mA (NE43 upscale).
    Short,
    /// Stale value: the counts stop changing (frozen at the last conversion).
    Frozen,
}

/// A communication fault of the whole module.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum CommFault {
    /// Answers normally.
    #[default]
    None,
    /// Slow device: each reply is sent after this delay, even if the client has
    /// given up meanwhile (a late reply), and the connection reads nothing meanwhile.
    Delay(Duration),
    /// Answers every request with this exception, e.g. `ServerDeviceBusy`.
    Exception(ExceptionCode),
    /// TCP: closes every open connection now and closes new ones at once while set.
    /// RTU: no answer (there is no connection to drop on a serial line).
    DropConnections,
    /// Reads requests but never answers them.
    Silent,
}

#[derive(Debug, Clone, Default)]
struct ChannelState {
    override_degc: Option<f64>,
    fault: SensorFault,
    /// Counts of the last conversion; `Frozen` keeps serving them.
    last_counts: Option<u16>,
}

#[derive(Debug)]
struct Inner {
    spec: FieldModuleSpec,
    start: Instant,
    rng: SimRng,
    noise: Vec<Normal<f64>>,
    channels: Vec<ChannelState>,
    comm_fault: CommFault,
    /// Cancelled to close every open TCP connection; replaced afterwards.
    kill_connections: CancellationToken,
    requests_received: u64,
    requests_served: u64,
    /// Arrival of every read request while logging is on (benchmarks).
    request_log: Option<Vec<RequestArrival>>,
}

/// One read request as it arrived at the module: when, and which registers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RequestArrival {
    /// Arrival time (tokio clock).
    pub at: Instant,
    /// First register asked for.
    pub address: u16,
    /// Registers asked for.
    pub quantity: u16,
}

/// Cloneable handle of a simulated field I/O module; clones share one module.
#[derive(Debug, Clone)]
pub struct FieldModule {
    inner: Arc<Mutex<Inner>>,
}

impl FieldModule {
    /// Builds a module after [`FieldModuleSpec::validate`]; its profile clock starts now.
    pub fn new(spec: FieldModuleSpec) -> Result<Self, FieldError> {
        spec.validate()?;
        let noise = spec
            .transmitters
            .iter()
            .map(|t| {
                Normal::new(0.0, t.noise_degc)
                    .map_err(|e| FieldError::InvalidSpec(format!("noise_degc: {e}")))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let inner = Inner {
            rng: SimRng::seed_from_u64(spec.seed),
            channels: vec![ChannelState::default(); spec.transmitters.len()],
            noise,
            spec,
            start: Instant::now(),
            comm_fault: CommFault::None,
            kill_connections: CancellationToken::new(),
            requests_received: 0,
            requests_served: 0,
            request_log: None,
        };
        Ok(Self {
            inner: Arc::new(Mutex::new(inner)),
        })
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        // The state stays consistent even if a holder panicked: every update is a
        // plain field assignment.
        self.inner.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The module's description.
    pub fn spec(&self) -> FieldModuleSpec {
        self.lock().spec.clone()
    }

    /// Number of transmitters.
    pub fn transmitter_count(&self) -> usize {
        self.lock().channels.len()
    }

    /// True (noiseless) temperature of transmitter `i` now: the override if set, else
    /// the profile. `None` if there is no transmitter `i`.
    pub fn true_temperature_degc(&self, i: usize) -> Option<f64> {
        let inner = self.lock();
        let t_s = inner.start.elapsed().as_secs_f64();
        inner.true_temperature_degc(i, t_s)
    }

    /// Pins transmitter `i` to a temperature (`Some`) or returns it to its profile.
    pub fn set_temperature_override(&self, i: usize, degc: Option<f64>) -> Result<(), FieldError> {
        let mut inner = self.lock();
        inner.channel_mut(i)?.override_degc = degc;
        Ok(())
    }

    /// Sets the sensor fault of transmitter `i`.
    pub fn set_sensor_fault(&self, i: usize, fault: SensorFault) -> Result<(), FieldError> {
        let mut inner = self.lock();
        inner.channel_mut(i)?.fault = fault;
        Ok(())
    }

    /// Sets the communication fault. Setting [`CommFault::DropConnections`] closes
    /// every open TCP connection at once.
    pub fn set_comm_fault(&self, fault: CommFault) {
        let mut inner = self.lock();
        inner.comm_fault = fault;
        if fault == CommFault::DropConnections {
            inner.kill_connections.cancel();
            // Connections accepted after the fault is cleared get a live token.
            inner.kill_connections = CancellationToken::new();
        }
    }

    /// The communication fault in force.
    pub fn comm_fault(&self) -> CommFault {
        self.lock().comm_fault
    }

    /// One ADC scan of every transmitter now, as a request would trigger it: counts
    /// and measured temperature (degC) per transmitter. Other buses (the CANopen node
    /// of [`crate::canopen`]) publish the module's values through this.
    pub fn scan(&self) -> Vec<(u16, f32)> {
        let mut inner = self.lock();
        let t_s = inner.start.elapsed().as_secs_f64();
        inner.convert(t_s);
        (0..inner.channels.len())
            .map(|i| inner.measured(i))
            .collect()
    }

    /// Requests answered, with data or with an exception.
    pub fn requests_served(&self) -> u64 {
        self.lock().requests_served
    }

    /// Requests received, answered or not.
    pub fn requests_received(&self) -> u64 {
        self.lock().requests_received
    }

    /// Starts logging the arrival of every read request (`true`, an empty log) or
    /// stops it. The scale benchmark measures poll periods from the device's side
    /// with it, so the clients under test need no instrumentation.
    pub fn log_requests(&self, on: bool) {
        self.lock().request_log = on.then(Vec::new);
    }

    /// The arrivals logged since the last call (or since logging started).
    pub fn take_request_log(&self) -> Vec<RequestArrival> {
        self.lock()
            .request_log
            .as_mut()
            .map(std::mem::take)
            .unwrap_or_default()
    }

    /// Handles one request, with the communication fault applied. `Ok(None)`: no
    /// answer. `kill` ends a delayed reply early when the connection is dropped.
    async fn answer(
        &self,
        request: &Request<'_>,
        kill: Option<CancellationToken>,
    ) -> Result<Option<Response>, ExceptionCode> {
        let (fault, reply) = {
            let mut inner = self.lock();
            inner.requests_received += 1;
            if let (
                Some(log),
                Request::ReadInputRegisters(a, q) | Request::ReadHoldingRegisters(a, q),
            ) = (&mut inner.request_log, request)
            {
                log.push(RequestArrival {
                    at: Instant::now(),
                    address: *a,
                    quantity: *q,
                });
            }
            let fault = inner.comm_fault;
            let reply = match fault {
                CommFault::Exception(code) => Err(code),
                CommFault::DropConnections | CommFault::Silent => return Ok(None),
                CommFault::None | CommFault::Delay(_) => {
                    let t_s = inner.start.elapsed().as_secs_f64();
                    inner.reply(request, t_s)
                }
            };
            (fault, reply)
        };
        if let CommFault::Delay(delay) = fault {
            let sleep = hold_reply(delay);
            match kill {
                Some(kill) => {
                    tokio::select! {
                        () = sleep => {}
                        () = kill.cancelled() => return Ok(None),
                    }
                }
                None => sleep.await,
            }
        }
        self.lock().requests_served += 1;
        reply.map(Some)
    }

    /// Serves the module over Modbus TCP on `listener`, for any unit id, until
    /// `shutdown` is cancelled; cancelling also closes every open connection.
    pub async fn serve_tcp(
        self,
        listener: TcpListener,
        shutdown: CancellationToken,
    ) -> Result<(), FieldError> {
        let local = listener.local_addr().ok();
        tracing::debug!(addr = ?local, "field module serving Modbus TCP");
        let server = tokio_modbus::server::tcp::Server::new(listener);
        let on_connected = |stream: TcpStream, peer: SocketAddr| {
            let module = self.clone();
            async move { Ok(module.accept(stream, peer)) }
        };
        let on_process_error = |err: io::Error| {
            tracing::debug!(%err, "field module connection ended with an error");
        };
        // Dropping the `serve` future cancels every connection task it spawned.
        tokio::select! {
            res = server.serve(&on_connected, on_process_error) => res.map_err(|e| FieldError::Tcp {
                kind: e.kind(),
                message: e.to_string(),
            }),
            () = shutdown.cancelled() => Ok(()),
        }
    }

    /// Builds the service and the killable transport of a new TCP connection, or
    /// refuses it (`None` closes the socket) while connections are being dropped.
    fn accept(
        &self,
        stream: TcpStream,
        peer: SocketAddr,
    ) -> Option<(TcpFieldService, KillableStream)> {
        let (fault, kill) = {
            let inner = self.lock();
            (inner.comm_fault, inner.kill_connections.clone())
        };
        if fault == CommFault::DropConnections {
            tracing::debug!(%peer, "field module refuses connection (DropConnections)");
            return None;
        }
        // Replies are small and latency matters more than throughput.
        let _ = stream.set_nodelay(true);
        let transport = KillableStream {
            killed: Box::pin(kill.clone().cancelled_owned()),
            inner: stream,
        };
        let service = TcpFieldService {
            module: self.clone(),
            kill,
        };
        Some((service, transport))
    }
}

impl Inner {
    fn channel_mut(&mut self, i: usize) -> Result<&mut ChannelState, FieldError> {
        let count = self.channels.len();
        self.channels
            .get_mut(i)
            .ok_or(FieldError::NoSuchTransmitter { index: i, count })
    }

    fn true_temperature_degc(&self, i: usize, t_s: f64) -> Option<f64> {
        let channel = self.channels.get(i)?;
        let spec = self.spec.transmitters.get(i)?;
        Some(
            channel
                .override_degc
                .unwrap_or_else(|| spec.profile.temperature_degc(t_s)),
        )
    }

    /// One ADC scan at `t_s`: updates `last_counts` of every transmitter.
    fn convert(&mut self, t_s: f64) {
        for i in 0..self.channels.len() {
            // Draw noise for every channel, faulty or not, so a fault on one channel
            // does not shift the noise sequence of the others.
            let noise_degc = self.noise[i].sample(&mut self.rng);
            let true_degc = self.true_temperature_degc(i, t_s).unwrap_or(0.0);
            let spec = &self.spec.transmitters[i];
            let channel = &self.channels[i];
            let ma = match channel.fault {
                SensorFault::None => spec.degc_to_ma(true_degc + noise_degc),
                SensorFault::Open => OPEN_SENSOR_MA,
                SensorFault::Short => SHORT_SENSOR_MA,
                SensorFault::Frozen => match channel.last_counts {
                    Some(_) => continue,
                    // Never converted yet: take one value, then hold it.
                    None => spec.degc_to_ma(true_degc + noise_degc),
                },
            };
            self.channels[i].last_counts = Some(self.spec.adc_of(i).ma_to_counts(ma));
        }
    }

    /// Counts and measured temperature of transmitter `i` from the last scan.
    fn measured(&self, i: usize) -> (u16, f32) {
        let counts = self.channels[i].last_counts.unwrap_or(0);
        let ma = self.spec.adc_of(i).counts_to_ma(counts);
        let degc = self.spec.transmitters[i].ma_to_degc(ma);
        // The module publishes single precision, as such modules do.
        (counts, degc as f32)
    }

    fn reply(&mut self, request: &Request<'_>, t_s: f64) -> Result<Response, ExceptionCode> {
        let (address, quantity, holding) = match *request {
            Request::ReadInputRegisters(a, q) => (a, q, false),
            Request::ReadHoldingRegisters(a, q) => (a, q, true),
            _ => return Err(ExceptionCode::IllegalFunction),
        };
        if quantity == 0 || quantity > MAX_READ_QUANTITY {
            return Err(ExceptionCode::IllegalDataValue);
        }
        let n = self.channels.len();
        let end = u32::from(address) + u32::from(quantity);
        let inside = |base: u16, len: usize| {
            // len <= 2 * MAX_TRANSMITTERS, so these sums cannot overflow u32.
            address >= base && end <= u32::from(base) + len as u32
        };
        let block = if inside(COUNTS_BASE, n) {
            Block::Counts
        } else if inside(FLOAT_CDAB_BASE, 2 * n) {
            Block::Cdab
        } else if inside(FLOAT_ABCD_BASE, 2 * n) {
            Block::Abcd
        } else {
            return Err(ExceptionCode::IllegalDataAddress);
        };
        self.convert(t_s);
        let words = (address..address.saturating_add(quantity))
            .map(|reg| match block {
                Block::Counts => self.measured(usize::from(reg - COUNTS_BASE)).0,
                Block::Cdab | Block::Abcd => {
                    let base = if block == Block::Cdab {
                        FLOAT_CDAB_BASE
                    } else {
                        FLOAT_ABCD_BASE
                    };
                    let offset = usize::from(reg - base);
                    let words = match block {
                        Block::Cdab => f32_to_regs_cdab(self.measured(offset / 2).1),
                        _ => f32_to_regs_abcd(self.measured(offset / 2).1),
                    };
                    words[offset % 2]
                }
            })
            .collect();
        Ok(if holding {
            Response::ReadHoldingRegisters(words)
        } else {
            Response::ReadInputRegisters(words)
        })
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Block {
    Counts,
    Cdab,
    Abcd,
}

/// Encodes an f32 as two registers in word order CDAB (low word first).
pub fn f32_to_regs_cdab(v: f32) -> [u16; 2] {
    let [high, low] = f32_to_regs_abcd(v);
    [low, high]
}

/// Encodes an f32 as two registers in word order ABCD (high word first).
pub fn f32_to_regs_abcd(v: f32) -> [u16; 2] {
    let bits = v.to_bits();
    [(bits >> 16) as u16, bits as u16]
}

/// Decodes two registers in word order CDAB (low word first).
pub fn regs_cdab_to_f32(r: [u16; 2]) -> f32 {
    regs_abcd_to_f32([r[1], r[0]])
}

/// Waits `delay` on a timerfd of its own: tokio's timer wheel ticks once a
/// millisecond and rounds a 1 ms sleep up to 1-2 ms, which would make a device's
/// reply time twice what was set and its spread that of the timer, not the device.
async fn hold_reply(delay: Duration) {
    let deadline = std::time::Instant::now() + delay;
    let precise: std::io::Result<()> = async { tokio_timerfd::Delay::new(deadline)?.await }.await;
    if let Err(e) = precise {
        tracing::debug!(%e, "timerfd failed; the delayed reply waits on tokio's timer");
        tokio::time::sleep_until(deadline.into()).await;
    }
}

/// Decodes two registers in word order ABCD (high word first).
pub fn regs_abcd_to_f32(r: [u16; 2]) -> f32 {
    f32::from_bits((u32::from(r[0]) << 16) | u32::from(r[1]))
}

/// Per-connection Modbus TCP service of a field module.
#[derive(Debug)]
struct TcpFieldService {
    module: FieldModule,
    kill: CancellationToken,
}

type ReplyFuture =
    Pin<Box<dyn Future<Output = Result<Option<Response>, ExceptionCode>> + Send + 'static>>;

impl Service for TcpFieldService {
    type Request = Request<'static>;
    // `None` sends nothing: Silent, or a delayed reply cut short by DropConnections,
    // after which the transport reads EOF and the connection closes.
    type Response = Option<Response>;
    type Exception = ExceptionCode;
    type Future = ReplyFuture;

    fn call(&self, request: Self::Request) -> Self::Future {
        let module = self.module.clone();
        let kill = self.kill.clone();
        Box::pin(async move { module.answer(&request, Some(kill)).await })
    }
}

/// A TCP stream that reports EOF as soon as its kill token is cancelled, so the
/// tokio-modbus connection task ends and drops (closes) the socket.
struct KillableStream {
    inner: TcpStream,
    killed: Pin<Box<WaitForCancellationFutureOwned>>,
}

impl std::fmt::Debug for KillableStream {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("KillableStream")
            .field("inner", &self.inner)
            .finish_non_exhaustive()
    }
}

impl AsyncRead for KillableStream {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        // Polling the token registers the waker, so a cancel wakes a pending read.
        if self.killed.as_mut().poll(cx).is_ready() {
            return Poll::Ready(Ok(()));
        }
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl AsyncWrite for KillableStream {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        if self.killed.as_mut().poll(cx).is_ready() {
            return Poll::Ready(Err(io::ErrorKind::ConnectionAborted.into()));
        }
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

/// Modbus RTU service of several modules on one line.
#[derive(Debug)]
struct RtuFieldService {
    units: Arc<Vec<(u8, FieldModule)>>,
}

impl Service for RtuFieldService {
    type Request = SlaveRequest<'static>;
    type Response = Option<Response>;
    type Exception = ExceptionCode;
    type Future = ReplyFuture;

    fn call(&self, request: Self::Request) -> Self::Future {
        // Requests for other unit ids, and broadcasts (0), get no answer, as on a
        // real RS-485 line.
        let module = self
            .units
            .iter()
            .find(|(unit, _)| *unit == request.slave && request.slave != 0)
            .map(|(_, module)| module.clone());
        Box::pin(async move {
            match module {
                Some(module) => module.answer(&request.request, None).await,
                None => Ok(None),
            }
        })
    }
}

/// Serves several modules, each under its unit id, on one Modbus RTU line until
/// `shutdown` is cancelled. Requests for unknown unit ids get no answer.
pub async fn serve_rtu(
    units: Vec<(u8, FieldModule)>,
    serial: tokio_serial::SerialStream,
    shutdown: CancellationToken,
) -> Result<(), FieldError> {
    tracing::debug!(
        units = ?units.iter().map(|(u, _)| *u).collect::<Vec<_>>(),
        "field modules serving Modbus RTU"
    );
    let server = tokio_modbus::server::rtu::Server::new(serial);
    let service = RtuFieldService {
        units: Arc::new(units),
    };
    tokio::select! {
        res = server.serve_forever(service) => res.map_err(|e| FieldError::Rtu {
            kind: e.kind(),
            message: e.to_string(),
        }),
        () = shutdown.cancelled() => Ok(()),
    }
}

/// A connected pseudo-terminal pair for RTU tests: `(master, slave, slave_path)`.
///
/// Serve on `master` with [`serve_rtu`] and let the client open `slave_path` by name
/// (as it would open `/dev/ttyUSB0`). The caller must keep the returned `slave` stream
/// alive for as long as the line is in use: once every file descriptor of the slave
/// side is closed, reads on the master fail with EIO, which ends the server. Holding
/// it also lets the client close and reopen the path (reconnect) without killing the
/// line. Unix only.
pub fn pty_pair() -> Result<
    (
        tokio_serial::SerialStream,
        tokio_serial::SerialStream,
        String,
    ),
    FieldError,
> {
    let (master, slave) =
        tokio_serial::SerialStream::pair().map_err(|e| FieldError::Pty(e.to_string()))?;
    let path = slave
        .name()
        .ok_or_else(|| FieldError::Pty("the slave pty has no name".into()))?;
    Ok((master, slave, path))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec_one(profile: Profile, noise_degc: f64) -> FieldModuleSpec {
        FieldModuleSpec::new(
            vec![TransmitterSpec {
                noise_degc,
                ..TransmitterSpec::new(profile, 0.0, 100.0)
            }],
            7,
        )
    }

    #[test]
    fn profiles_give_documented_values() {
        let ramp = Profile::Ramp {
            start_degc: 20.0,
            rate_degc_per_s: 0.5,
        };
        assert_eq!(ramp.temperature_degc(10.0), 25.0);
        let sine = Profile::Sine {
            mean_degc: 20.0,
            amplitude_degc: 2.0,
            period_s: 100.0,
        };
        assert!((sine.temperature_degc(25.0) - 22.0).abs() < 1e-12);
        assert!((sine.temperature_degc(75.0) - 18.0).abs() < 1e-12);
        let steps = Profile::Steps(vec![(0.0, 20.0), (10.0, 25.0), (20.0, 22.0)]);
        assert_eq!(steps.temperature_degc(-1.0), 20.0);
        assert_eq!(steps.temperature_degc(9.999), 20.0);
        assert_eq!(steps.temperature_degc(10.0), 25.0);
        assert_eq!(steps.temperature_degc(1e6), 22.0);
    }

    #[test]
    fn current_and_counts_follow_the_formulas() {
        let spec = spec_one(Profile::Constant { degc: 25.0 }, 0.0);
        let t = &spec.transmitters[0];
        assert_eq!(t.degc_to_ma(0.0), 4.0);
        assert_eq!(t.degc_to_ma(100.0), 20.0);
        assert_eq!(t.degc_to_ma(25.0), 8.0);
        assert_eq!(t.degc_to_ma(-30.0), SATURATION_LOW_MA);
        assert_eq!(t.degc_to_ma(130.0), SATURATION_HIGH_MA);
        // 8 mA of 24 mA full scale on 4095 counts.
        assert_eq!(spec.ma_to_counts(8.0), 1365);
        assert_eq!(spec.ma_to_counts(3.5), 597); // 597.1875
        assert_eq!(spec.ma_to_counts(21.5), 3668); // 3668.4375
        assert_eq!(spec.ma_to_counts(30.0), 4095);
        assert_eq!(spec.ma_to_counts(-1.0), 0);
        // 0-20 mA: 0 mA at the bottom, 5 mA at a quarter, never below 0 mA.
        let t = TransmitterSpec {
            range_low_ma: 0.0,
            ..t.clone()
        };
        assert_eq!(t.degc_to_ma(0.0), 0.0);
        assert_eq!(t.degc_to_ma(25.0), 5.0);
        assert_eq!(t.degc_to_ma(-30.0), 0.0);
        assert_eq!(t.ma_to_degc(5.0), 25.0);
    }

    /// Each transmitter is read at its own full scale when it has one; both register
    /// views decode it back to the temperature.
    #[test]
    fn a_transmitter_with_its_own_full_scale_and_range_reads_back() {
        let own = TransmitterSpec {
            range_low_ma: 0.0,
            adc_full_scale: Some(AdcFullScale {
                counts: 4095,
                ma: 20.0,
            }),
            ..TransmitterSpec::new(Profile::Constant { degc: 25.0 }, 0.0, 100.0)
        };
        let spec = FieldModuleSpec::new(
            vec![
                own,
                TransmitterSpec::new(Profile::Constant { degc: 25.0 }, 0.0, 100.0),
            ],
            1,
        );
        let module = FieldModule::new(spec).expect("module");
        let mut inner = module.lock();
        inner.convert(0.0);
        // 5 mA of 20 mA on 4095 counts; 8 mA of the module's 24 mA.
        for (i, counts) in [(0, 1024), (1, 1365)] {
            let (got, degc) = inner.measured(i);
            assert!(
                got == counts && (degc - 25.0).abs() < 0.01,
                "{i}: {got} {degc}"
            );
        }
    }

    #[test]
    fn invalid_specs_are_refused() {
        let mut spec = spec_one(Profile::Constant { degc: 25.0 }, 0.0);
        spec.transmitters[0].range_max_degc = 0.0;
        assert!(matches!(
            FieldModule::new(spec),
            Err(FieldError::InvalidSpec(_))
        ));
        let spec = spec_one(Profile::Steps(vec![(5.0, 1.0), (1.0, 2.0)]), 0.0);
        assert!(FieldModule::new(spec).is_err());
        let spec = spec_one(Profile::Constant { degc: 25.0 }, -1.0);
        assert!(FieldModule::new(spec).is_err());
        assert!(FieldModule::new(FieldModuleSpec::new(vec![], 1)).is_err());
    }

    fn read(module: &FieldModule, req: Request<'_>, t_s: f64) -> Result<Response, ExceptionCode> {
        module.lock().reply(&req, t_s)
    }

    #[test]
    fn register_blocks_agree_and_decode() {
        let module = FieldModule::new(spec_one(Profile::Constant { degc: 25.0 }, 0.0)).unwrap();
        let Ok(Response::ReadInputRegisters(counts)) =
            read(&module, Request::ReadInputRegisters(0, 1), 0.0)
        else {
            panic!("counts read failed");
        };
        assert_eq!(counts, vec![1365]);
        let Ok(Response::ReadHoldingRegisters(cdab)) =
            read(&module, Request::ReadHoldingRegisters(1000, 2), 0.0)
        else {
            panic!("cdab read failed");
        };
        let Ok(Response::ReadInputRegisters(abcd)) =
            read(&module, Request::ReadInputRegisters(2000, 2), 0.0)
        else {
            panic!("abcd read failed");
        };
        assert_eq!(cdab, vec![abcd[1], abcd[0]]);
        let degc = regs_abcd_to_f32([abcd[0], abcd[1]]);
        // 1365 counts = 8.0 mA exactly = 25 degC.
        assert!((f64::from(degc) - 25.0).abs() < 1e-4, "{degc}");
        assert_eq!(regs_cdab_to_f32([cdab[0], cdab[1]]), degc);
    }

    #[test]
    fn bad_addresses_and_functions_are_refused() {
        let module = FieldModule::new(spec_one(Profile::Constant { degc: 25.0 }, 0.0)).unwrap();
        for req in [
            Request::ReadInputRegisters(1, 1),
            Request::ReadInputRegisters(0, 2),
            Request::ReadHoldingRegisters(999, 2),
            Request::ReadHoldingRegisters(1001, 2),
            Request::ReadHoldingRegisters(2002, 1),
            Request::ReadHoldingRegisters(500, 1),
        ] {
            assert_eq!(
                read(&module, req.clone(), 0.0),
                Err(ExceptionCode::IllegalDataAddress),
                "{req:?}"
            );
        }
        assert_eq!(
            read(&module, Request::ReadInputRegisters(0, 0), 0.0),
            Err(ExceptionCode::IllegalDataValue)
        );
        // Reading half a float is allowed.
        assert!(read(&module, Request::ReadHoldingRegisters(1001, 1), 0.0).is_ok());
        for req in [
            Request::WriteSingleRegister(0, 1),
            Request::WriteMultipleRegisters(0, vec![1].into()),
            Request::ReadCoils(0, 1),
        ] {
            assert_eq!(read(&module, req, 0.0), Err(ExceptionCode::IllegalFunction));
        }
    }

    fn counts_at(module: &FieldModule, t_s: f64) -> u16 {
        match read(module, Request::ReadInputRegisters(0, 1), t_s) {
            Ok(Response::ReadInputRegisters(w)) => w[0],
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn ramp_is_tracked_within_quantisation() {
        let module = FieldModule::new(spec_one(
            Profile::Ramp {
                start_degc: 10.0,
                rate_degc_per_s: 0.1,
            },
            0.0,
        ))
        .unwrap();
        let spec = module.spec();
        // One count = 24/4095 mA = 0.0366 degC on a 100 degC span.
        let half_count_degc = 0.5 * 24.0 / 4095.0 / 16.0 * 100.0;
        for t_s in [0.0, 10.0, 100.0, 500.0] {
            let degc = spec.transmitters[0].ma_to_degc(spec.counts_to_ma(counts_at(&module, t_s)));
            assert!(
                (degc - (10.0 + 0.1 * t_s)).abs() <= half_count_degc + 1e-9,
                "t = {t_s}: {degc}"
            );
        }
    }

    #[test]
    fn noise_is_deterministic_for_a_seed_and_has_the_right_spread() {
        let make = || FieldModule::new(spec_one(Profile::Constant { degc: 50.0 }, 0.5)).unwrap();
        let (a, b) = (make(), make());
        let series_a: Vec<u16> = (0..2000).map(|_| counts_at(&a, 0.0)).collect();
        let series_b: Vec<u16> = (0..2000).map(|_| counts_at(&b, 0.0)).collect();
        assert_eq!(series_a, series_b);
        let spec = a.spec();
        let degc: Vec<f64> = series_a
            .iter()
            .map(|c| spec.transmitters[0].ma_to_degc(spec.counts_to_ma(*c)))
            .collect();
        let mean = degc.iter().sum::<f64>() / degc.len() as f64;
        let var = degc.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / degc.len() as f64;
        assert!((mean - 50.0).abs() < 0.05, "mean {mean}");
        assert!((var.sqrt() - 0.5).abs() < 0.05, "std {}", var.sqrt());
    }

    #[test]
    fn sensor_faults_and_overrides() {
        let module = FieldModule::new(spec_one(Profile::Constant { degc: 25.0 }, 0.0)).unwrap();
        module.set_sensor_fault(0, SensorFault::Open).unwrap();
        assert_eq!(counts_at(&module, 0.0), 597);
        module.set_sensor_fault(0, SensorFault::Short).unwrap();
        assert_eq!(counts_at(&module, 0.0), 3668);
        module.set_sensor_fault(0, SensorFault::None).unwrap();
        assert_eq!(counts_at(&module, 0.0), 1365);
        module.set_sensor_fault(0, SensorFault::Frozen).unwrap();
        module.set_temperature_override(0, Some(50.0)).unwrap();
        assert_eq!(module.true_temperature_degc(0), Some(50.0));
        assert_eq!(counts_at(&module, 0.0), 1365, "frozen counts must not move");
        module.set_sensor_fault(0, SensorFault::None).unwrap();
        assert_eq!(counts_at(&module, 0.0), 2048); // 12 mA = 2047.5 -> 2048
        assert_eq!(
            module.set_sensor_fault(3, SensorFault::Open),
            Err(FieldError::NoSuchTransmitter { index: 3, count: 1 })
        );
        assert_eq!(module.true_temperature_degc(1), None);
    }

    #[test]
    fn cdab_and_abcd_encodings() {
        let v = 25.5_f32; // 0x41CC0000
        assert_eq!(f32_to_regs_abcd(v), [0x41CC, 0x0000]);
        assert_eq!(f32_to_regs_cdab(v), [0x0000, 0x41CC]);
        assert_eq!(regs_cdab_to_f32(f32_to_regs_cdab(-3.25)), -3.25);
    }
}
