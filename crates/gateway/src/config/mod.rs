//! Configuration: TOML file + `COMPGATE__` environment overrides, checked against the
//! JSON Schema of the config structs, then validated by the stages that own them,
//! reporting every problem at once.
//!
//! # Who owns what
//!
//! Each stage owns its config struct, its `validate` and its `build`: devices in
//! [`crate::source::config`] (Modbus TCP/RTU in [`crate::source::modbus::config`],
//! CANopen in [`crate::source::can::config`]), channels in [`crate::channel`], NC
//! modules in [`crate::nc::config`], axes in [`crate::axis`]. This module keeps file
//! loading, the environment overlay, key paths ([`keys`]), the problem type
//! ([`problem`]) and the top-level [`Config`] that gathers the sections; [`schema`]
//! re-exports every section type and derives the JSON Schema.
//!
//! # Loading
//!
//! [`load`] reads one TOML file and layers environment overrides on top of it with
//! the `config` crate, then checks the result twice:
//!
//! 1. **Structure** (against [`schema::json_schema`]): every key must be known (a
//!    typo is an error, not a silently ignored key; so is a key of another transport),
//!    every value must have the right type and lie within its documented range (a
//!    number) or length (a text), and every required key must be present.
//!    All such problems of the file are collected, each with the file name and the
//!    dotted path of the key, e.g.
//!
//!    ```text
//!    config/plant.toml: devices.ain1.timeout: unknown key; did you mean `timeout_s`?
//!    config/plant.toml: axes.X.k0.terms[1].channel: required key is missing
//!    ```
//! 2. **Meaning** ([`validate`]): references between sections, ranges, shared serial
//!    lines and CAN interfaces. See [`validate`] for the list. It runs even when
//!    step 1 found problems: entries with structural problems are left out (their
//!    names still count as defined) and their references are checked on the raw
//!    values, so a type error never hides another problem.
//!
//! [`load`] returns the [`Config`] only when both found nothing; otherwise
//! [`ConfigError::Invalid`] carries every [`ConfigProblem`], so a `validate` command
//! (e.g. as `ExecStartPre=`) checks exactly what the service would load.
//!
//! # Environment overrides
//!
//! Any key holding one value can be set from the environment as
//! `COMPGATE__<SECTION>__<NAME>__<KEY>...`, with a double underscore between levels,
//! e.g. `COMPGATE__DEVICES__AIN1__TIMEOUT_S=0.5` or
//! `COMPGATE__CHANNELS__T_BED__FILTER__LOWPASS_TAU_S=20`. An array is not one value:
//! its elements take their 0-based index as a level, and only where the file has the
//! array: `COMPGATE__AXES__X__K0__TERMS__0__COEFF_MM_PER_DEGC=0.005`,
//! `COMPGATE__AXES__X__NC_WRITE__0=sd43900`.
//! Values are parsed as bool, integer or float where they look like one, otherwise
//! they are strings (a number given for a string key, e.g. a serial path `1`, is turned
//! back into the text that was set). An empty variable counts as unset.
//!
//! Names are matched **ignoring case**. The `config` crate lowercases environment
//! keys (`T_BED` arrives as `t_bed`), while it keeps the case of keys read from TOML
//! (`T_bed`). Left alone, an override of `channels.T_bed` would therefore create a
//! second channel `t_bed`. The loader takes the `config` crate's `Environment` source
//! as it is (prefix, separator, value parsing), then maps every lowercased key back
//! onto the spelling used in the file before the overrides are layered over the file
//! (see `load.rs`). A key the file does not have keeps the lowercase spelling, which is
//! right for every schema key. This is also why names must be unique ignoring case.
//!
//! # Defaults
//!
//! Timeouts, retries, backoff, filter settings and limits have defaults a shop-floor
//! engineer would expect (documented on every field, and shown by
//! `config/minimal.toml`); addresses, unit ids, register addresses, data types,
//! scaling ranges and model coefficients are required.

pub mod example;
pub mod keys;
mod load;
pub mod login;
pub mod problem;
mod root;
pub mod schema;
mod service;
mod sim;
mod structure;
mod warnings;

pub use load::{
    env_note, load, load_for_sim, load_listing_overrides, load_str, load_str_with_env,
    load_with_env, EnvOverride, MAX_FILE_BYTES,
};
pub use problem::{ConfigError, ConfigProblem};
pub use root::validate;
pub use schema::*;
pub use warnings::warnings;

/// Prefix of environment overrides, followed by [`ENV_SEPARATOR`].
pub const ENV_PREFIX: &str = "COMPGATE";
/// Separator between the levels of an environment override's name.
pub const ENV_SEPARATOR: &str = "__";
