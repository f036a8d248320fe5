//! The configuration schema: the section types, each defined by the stage that owns
//! it and re-exported here, and the JSON Schema derived from them.
//!
//! The `///` comment of every field is the operator's manual for that key: meaning,
//! unit, default and allowed range; [`json_schema`] carries them as descriptions.
//! `config/example.toml` is the annotated example of the same schema; the names here
//! match it exactly. Every numeric key's range and every text key's longest length
//! is declared on its field (`#[schemars(range(..))]`, `#[schemars(length(..))]`),
//! so the JSON Schema carries it and the loader's structural check enforces it;
//! what the schema cannot say (a median window is odd, `backoff_initial_s <=
//! backoff_max_s`, references between sections) is checked by the stages'
//! `validate`.

pub use super::keys::secs;
pub use super::root::{Config, GatewayConfig};
pub use super::service::{MetricsConfig, MqttConfig, RecorderConfig};
pub use super::sim::{SimChannelConfig, SimConfig, SimNcModuleConfig, SimProfile};
pub use crate::axis::{
    AxisConfig, K0Model, K0Term, MotionHeatModel, OnBadInput, TanBetaModel, TanBetaTerm,
};
pub use crate::channel::{
    ByteOrder, ChannelConfig, CurrentRange, DataType, DirectScaling, FilterConfig, RegisterKind,
    Scaling, TransmitterScaling,
};
pub use crate::nc::config::NcModuleConfig;
pub use crate::source::can::config::{CanChannelConfig, CanDeviceConfig};
pub use crate::source::config::{DeviceCommon, DeviceConfig, Transport};
pub use crate::source::modbus::config::{Parity, RtuDeviceConfig, TcpDeviceConfig};

/// The JSON Schema (draft 2020-12) of a configuration file, derived from the config
/// structs; every key's `///` documentation is its `description`. The loader checks
/// every file against it before the stages' semantic validation.
pub fn json_schema() -> serde_json::Value {
    schemars::schema_for!(Config).to_value()
}
