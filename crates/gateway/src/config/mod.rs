//! Configuration: TOML file + `COMPGATE__` environment overrides, serde structs that
//! refuse unknown keys, and a validation that reports every problem at once.
//!
//! # Loading
//!
//! [`load`] reads one TOML file and layers environment overrides on top of it with
//! the `config` crate, then checks the result twice:
//!
//! 1. **Structure** ([`schema`]): every key must be known (a typo is an error, not a
//!    silently ignored key), every value must have the right type and every required
//!    key must be present. All such problems of the file are collected, each with the
//!    file name and the dotted path of the key, e.g.
//!
//!    ```text
//!    config/plant.toml: devices.ain1.timeout: unknown key; did you mean `timeout_s`?
//!    config/plant.toml: axes.X.k0.terms[1].channel: required key is missing
//!    ```
//! 2. **Meaning** ([`validate`]): references between sections, ranges, transport
//!    rules, shared serial lines. See [`validate`] for the list.
//!
//! [`load`] returns the [`Config`] only when both found nothing; otherwise
//! [`ConfigError::Invalid`] carries every [`ConfigProblem`], so a `validate` command
//! (e.g. as `ExecStartPre=`) checks exactly what the service would load.
//!
//! # Environment overrides
//!
//! Any key can be set from the environment as `COMPGATE__<SECTION>__<KEY>...`, with a
//! double underscore between levels, e.g. `COMPGATE__DEVICES__AIN1__TIMEOUT_S=0.5` or
//! `COMPGATE__CHANNELS__T_BED__FILTER__LOWPASS_TAU_S=20`. Array elements take their
//! 0-based index as a level: `COMPGATE__AXES__X__K0__TERMS__0__COEFF_MM_PER_DEGC=0.005`.
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

mod load;
pub mod schema;
mod validate;
mod validate_service;

use std::fmt;

pub use load::{load, load_str, load_str_with_env, load_with_env};
pub use schema::*;
pub use validate::validate;

/// Prefix of environment overrides, followed by [`ENV_SEPARATOR`].
pub const ENV_PREFIX: &str = "COMPGATE";
/// Separator between the levels of an environment override's name.
pub const ENV_SEPARATOR: &str = "__";

/// One thing wrong with a configuration.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ConfigProblem {
    /// The file (or origin, e.g. `demo.toml (embedded)`) the configuration came from.
    pub file: String,
    /// Dotted path of the key, e.g. `devices.ain1.timeout_s` or
    /// `axes.X.k0.terms[1].channel`. For a TOML syntax error: `line L, column C`.
    pub key: String,
    /// What is wrong and what is expected.
    pub message: String,
}

impl ConfigProblem {
    /// A problem of `key` in `file`.
    pub fn new(
        file: impl Into<String>,
        key: impl Into<String>,
        message: impl Into<String>,
    ) -> Self {
        ConfigProblem {
            file: file.into(),
            key: key.into(),
            message: message.into(),
        }
    }
}

impl fmt::Display for ConfigProblem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}: {}", self.file, self.key, self.message)
    }
}

/// Why a configuration could not be loaded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("{file}: cannot read the configuration: {message}")]
    Read {
        /// The file.
        file: String,
        /// The operating system's reason.
        message: String,
    },
    /// The file was read but is not a valid configuration: every problem found.
    #[error("{}", ProblemList(.0))]
    Invalid(Vec<ConfigProblem>),
}

impl ConfigError {
    /// Every problem: the problems of [`ConfigError::Invalid`], or one for
    /// [`ConfigError::Read`].
    pub fn problems(&self) -> Vec<ConfigProblem> {
        match self {
            ConfigError::Read { file, message } => {
                vec![ConfigProblem::new(
                    file,
                    "(file)",
                    format!("cannot read: {message}"),
                )]
            }
            ConfigError::Invalid(problems) => problems.clone(),
        }
    }
}

struct ProblemList<'a>(&'a [ConfigProblem]);

impl fmt::Display for ProblemList<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let n = self.0.len();
        write!(
            f,
            "{n} configuration problem{}:",
            if n == 1 { "" } else { "s" }
        )?;
        for p in self.0 {
            write!(f, "\n  {p}")?;
        }
        Ok(())
    }
}
