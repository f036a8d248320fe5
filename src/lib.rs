//! compgate: a PLC-style compensation gateway for CNC machine tools.
//!
//! It polls temperature transmitters and ADC modules over Modbus TCP/RTU, filters the
//! readings, computes the thermal compensation parameters SD43900/43910/43920 and
//! writes them into an NC axis module the way a Siemens PLC's FB3 (PUT) job does.
//!
//! # Layout
//!
//! Data flows one way: `source` -> `channel` -> `comp` -> `nc`.
//!
//! - [`config`]: TOML + `COMPGATE__` environment overrides, serde structs with
//!   `deny_unknown_fields`, and `validate`, which reports every problem at once.
//! - [`source`]: field-device polling. Modbus TCP and RTU with request merging,
//!   timeouts, reconnect with capped backoff; CANopen nodes on SocketCAN
//!   ([`source::can`]: NMT, SYNC + TPDOs, SDO upload, heartbeat, EMCY); one task per
//!   device, and one SYNC producer per CAN interface on a fixed-rate timer.
//! - [`channel`]: pure and synchronous: scaling (counts -> mA -> degC), NAMUR NE43,
//!   filters (median, low-pass, rate, stale) and quality.
//! - [`comp`]: pure math: the thermal model `dKx = K0(T) + tan(beta)(T) * (Px - P0)`,
//!   limits, deadband, hold or ramp on bad inputs.
//! - [`nc`]: the `NcWriter` trait and the FB3-style job client over Modbus TCP.
//! - [`backlash`]: `compgate backlash`, backlash of a full-closed-loop axis from the
//!   servo trace of encoder and scale (seed formulas, plateau extraction, MD32450 write).
//! - [`volumetric`]: online volumetric compensation of a 5-axis AC-head machine.
//! - [`calibrate`]: `compgate calibrate`, the patent's step S1: least-squares fit of
//!   K0(T) and tan(beta)(T) (pure part in `calibrate::fit`), model file, plot.
//! - [`iso230`]: `compgate iso230`, ISO 230-2 evaluation (A, B, R, E, M) of
//!   bidirectional runs in the measured-error CSV.
//! - [`diagnose`]: `compgate diagnose`, where model and measurement disagree, which
//!   effect is missing, the model with it added, and how much the gap shrinks.
//! - [`measure`]: the measured-error CSV format (`t_s,pos_mm,err_um,T_*`) that
//!   `calibrate` and `diagnose` read and `export` writes.
//! - [`gateway`]: wires the stages together; `run(config, shutdown)` is the one path
//!   used by the service, the demo and the tests.
//! - [`scenario`]: `compgate scenario`, the simulated machine's thermal test with the
//!   real gateway in the loop over loopback Modbus, compensation off against on.
//! - [`plant`]: the simulated plant for a config (demo, `sim`, tests), from
//!   `compgate-plc`; the service path never uses it.
//! - [`record`]: durable recording into SQLite (WAL) off the control loop, retention,
//!   and `compgate export` to the measurement CSV.
//! - [`service`]: the shop-floor service: systemd notify/watchdog, journald, SIGHUP
//!   reload, and the recorder, metrics and MQTT observers behind the control loop.
//! - [`heap`]: glibc malloc's figures (live heap, free bytes held) and the service's
//!   one-arena setting; the one module with `unsafe` (two libc calls).
//! - [`status`]: the live status line and plain per-update lines.
//! - [`bench`](mod@bench): `compgate bench`, cycle rate against the bare Modbus request rate.
//! - [`cli`]: the command line.
//!
//! The simulated plant lives in the `compgate-plc` crate (`plc/`). The gateway's
//! service code uses only its register map (`compgate_plc::ncmap`), the NC axis
//! module's public interface; the demo, `sim` and the tests start the simulator.

pub mod backlash;
pub mod bench;
pub mod calibrate;
pub mod channel;
pub mod cli;
pub mod comp;
pub mod config;
pub mod diagnose;
pub mod gateway;
pub mod heap;
pub mod iso230;
pub mod measure;
pub mod nc;
pub mod plant;
pub mod record;
pub mod scenario;
pub mod service;
pub mod source;
pub mod status;
pub mod volumetric;
