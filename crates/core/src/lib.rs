//! `compgate-core`: the pure stages of compgate, with no tokio and no network.
//!
//! - [`channel`]: scaling (counts -> mA -> degC), NAMUR NE43, filters (median, low
//!   pass, rate, stale) and quality, one synchronous processor per channel.
//! - [`comp`]: the thermal model `dKx = K0(T) + tan(beta)(T) * (Px - P0)`, limits,
//!   deadband, hold or ramp on bad inputs.
//! - [`measure`]: the measured-error CSV (`t_s,pos_mm,err_um,T_*`) that the
//!   commissioning tools read and the recorder's export writes.
//! - [`outputs`]: the files a command writes, checked against its inputs before
//!   anything is written, and replaced whole.
//!
//! The gateway runs these stages inside its tasks; the simulator and the
//! commissioning tools reuse them without a runtime.

pub mod channel;
pub mod comp;
pub mod measure;
pub mod outputs;
