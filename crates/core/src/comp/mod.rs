//! Compensation math: pure, synchronous, no I/O.
//!
//! - [`ThermalModel`]: `K0(T)` and `tan(beta)(T)` as affine functions of the axis'
//!   temperatures, plus the constant `P0`; [`CompParams`] is the resulting
//!   SD43900/SD43910/SD43920 set and [`CompParams::dk_mm`] what the NC makes of it.
//! - [`AxisCompensator`]: from temperatures to a [`Decision`]: absolute and step
//!   limits, deadband, and hold or ramp-to-zero while an input is bad.
//! - [`Dynamics`]: terms with a memory (a lagged input, motion heat from the NC's
//!   actual position) that the compensator adds to the model.

mod compensator;
mod dynamics;
mod model;

pub use compensator::{AxisCompensator, BadInputPolicy, BeyondLimit, Decision, Limits};
pub use dynamics::{heat_store_step, Dynamics, InputLag, MotionHeat};
pub use model::{
    Affine, CompParams, Term, ThermalModel, MAX_TAN_BETA_PER_K, STEEL_EXPANSION_PER_K,
};

/// Errors of the compensation layer: settings that cannot work.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum CompError {
    /// A model term references a temperature the axis does not have.
    #[error("model term references input {input}, but the axis has {n_inputs} inputs")]
    InputOutOfRange {
        /// The referenced input index.
        input: usize,
        /// How many inputs the axis has.
        n_inputs: usize,
    },
    /// A limit is negative, NaN or infinite.
    #[error("limit {field} must be finite and >= 0")]
    InvalidLimit {
        /// Name of the [`Limits`] field.
        field: &'static str,
    },
}
