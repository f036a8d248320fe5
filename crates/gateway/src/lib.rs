//! `compgate-gateway`: the running gateway, from field registers to the NC write.
//!
//! Data flows one way: [`source`] -> `compgate_core::channel` -> `compgate_core::comp`
//! -> [`nc`].
//!
//! - [`config`]: TOML + `COMPGATE__` environment overrides checked against the JSON
//!   Schema of the config structs, then the stages' `validate`; every problem at
//!   once. Each stage owns its config struct, `validate` and `build`: [`source`]
//!   (devices), [`channel`], [`nc`] (NC modules), [`axis`].
//! - [`source`]: field-device polling. Modbus TCP and RTU with request merging,
//!   timeouts, reconnect with capped backoff; CANopen nodes on SocketCAN
//!   ([`source::can`]: NMT, SYNC + TPDOs, SDO upload, heartbeat, EMCY); one task per
//!   device, and one SYNC producer per CAN interface on a fixed-rate timer.
//! - [`nc`]: the `NcWriter` trait and the FB3-style job client over Modbus TCP,
//!   speaking the register map of `compgate_ncproto`.
//! - [`runtime`]: wires the stages together; `run(config, shutdown, status)` is the
//!   one path used by the service, the demo and the tests.
//!
//! Nothing here depends on the simulator (`compgate-plc`): tests and the binary's
//! demo wire the two together.

pub mod axis;
pub mod channel;
pub mod config;
pub mod nc;
pub mod runtime;
pub mod source;
