//! compgate: a PLC-style compensation gateway for CNC machine tools.
//!
//! It polls temperature transmitters and ADC modules over Modbus TCP/RTU or CANopen,
//! filters the readings, computes the thermal compensation parameters
//! SD43900/43910/43920 and writes them into an NC axis module the way a Siemens PLC's
//! FB3 (PUT) job does.
//!
//! # Layout
//!
//! This package is the `compgate` binary: the command line and the wiring. The work
//! is done by the workspace's crates, whose dependencies point one way:
//!
//! - `compgate-core` (`crates/core`): channel processing, compensation math,
//!   measurement types; no tokio, no network.
//! - `compgate-ncproto` (`crates/ncproto`): the NC axis module's register map and job
//!   protocol, shared by the writer and the simulated module.
//! - `compgate-gateway` (`crates/gateway`): config, sources, the NC writer, the running
//!   gateway.
//! - `compgate-service` (`crates/service`): systemd, recording, metrics, MQTT, status.
//! - `compgate-commission` (`crates/commission`): calibrate, iso230, diagnose, backlash,
//!   volumetric.
//! - `compgate-plc` (`plc/`): the simulator; only this package (with the default `sim`
//!   feature), the tests and the benchmarks (`crates/bench`) depend on it.
//!
//! Modules of this package:
//! - [`cli`]: the command line.
//! - [`probe`]: `compgate probe`, one poll of every channel shown in full.
//! - `plant` (feature `sim`): the simulated plant for a config (demo, `sim`, tests) and
//!   the simulated axis of `backlash --sim`.
//! - `scenario` (feature `sim`): `compgate scenario`, the simulated machine's thermal
//!   test with the real gateway in the loop, compensation off against on.

pub mod cli;
#[cfg(feature = "sim")]
pub mod plant;
pub mod probe;
#[cfg(feature = "sim")]
pub mod scenario;
