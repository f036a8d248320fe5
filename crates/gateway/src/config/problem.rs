//! The problem type: one thing wrong with a configuration, and a collector the
//! stages' `validate` functions report into.

use std::fmt;
use std::net::SocketAddr;

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

/// Collects the problems of one file; the checks every stage uses.
#[derive(Debug)]
pub struct Problems<'a> {
    file: &'a str,
    out: Vec<ConfigProblem>,
}

impl<'a> Problems<'a> {
    /// An empty list for `file`.
    pub fn new(file: &'a str) -> Self {
        Problems {
            file,
            out: Vec::new(),
        }
    }

    /// Adds a problem of `key`.
    pub fn push(&mut self, key: impl Into<String>, message: impl Into<String>) {
        self.out.push(ConfigProblem::new(self.file, key, message));
    }

    /// The problems collected so far.
    pub fn into_vec(self) -> Vec<ConfigProblem> {
        self.out
    }

    /// `v` is finite (TOML allows `nan` and `inf`).
    pub fn finite(&mut self, key: &str, v: f64) -> bool {
        if v.is_finite() {
            true
        } else {
            self.push(key, format!("must be a finite number, got {v}"));
            false
        }
    }

    /// `v > 0`; `unit` names what the number is, e.g. "seconds".
    pub fn positive(&mut self, key: &str, v: f64, unit: &str) -> bool {
        if v.is_finite() && v > 0.0 {
            true
        } else {
            self.push(key, format!("must be > 0 ({unit}), got {v}"));
            false
        }
    }

    /// `v >= 0`; 0 usually means "off".
    pub fn non_negative(&mut self, key: &str, v: f64, unit: &str) -> bool {
        if v.is_finite() && v >= 0.0 {
            true
        } else {
            self.push(key, format!("must be >= 0 ({unit}), got {v}"));
            false
        }
    }

    /// `addr` is `host:port`.
    pub fn host_port(&mut self, key: &str, addr: &str) {
        if let Err(why) = check_host_port(addr) {
            self.push(key, why.to_string());
        }
    }

    /// A Modbus unit id addressing one device, 0..=247.
    pub fn unit_id(&mut self, key: &str, id: u8) {
        if id > MAX_UNIT_ID {
            self.push(key, format!("must be 0..=247 (Modbus unit id), got {id}"));
        }
    }
}

/// Largest Modbus unit id that addresses one device.
pub const MAX_UNIT_ID: u8 = 247;

/// Why a `host:port` text is not one.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum HostPortError {
    /// No `:port`.
    #[error("`{0}` has no port; expected host:port, e.g. \"192.168.0.10:502\"")]
    NoPort(String),
    /// The port is not a number 0..=65535.
    #[error("port `{0}` is not a number 0..=65535; expected host:port, e.g. \"192.168.0.10:502\"")]
    BadPort(String),
    /// Nothing before the `:`.
    #[error("`{0}` has no host; expected host:port, e.g. \"192.168.0.10:502\"")]
    NoHost(String),
    /// An IPv6 address without brackets.
    #[error("`{0}`: write an IPv6 address in brackets, e.g. \"[::1]:502\"")]
    Ipv6(String),
    /// Not a host name.
    #[error(
        "`{0}` is not a valid host name or IP address; expected host:port, e.g. \"192.168.0.10:502\""
    )]
    BadHost(String),
}

/// Accepts `host:port` with a host name, an IPv4 address or a bracketed IPv6
/// address, and a port 0..=65535.
pub fn check_host_port(addr: &str) -> Result<(), HostPortError> {
    if addr.parse::<SocketAddr>().is_ok() {
        return Ok(());
    }
    let Some((host, port)) = addr.rsplit_once(':') else {
        return Err(HostPortError::NoPort(addr.into()));
    };
    if port.parse::<u16>().is_err() {
        return Err(HostPortError::BadPort(port.into()));
    }
    if host.is_empty() {
        return Err(HostPortError::NoHost(addr.into()));
    }
    if host.contains(':') {
        return Err(HostPortError::Ipv6(addr.into()));
    }
    let label_ok = |l: &str| {
        !l.is_empty()
            && l.len() <= 63
            && l.chars().all(|c| c.is_ascii_alphanumeric() || c == '-')
            && !l.starts_with('-')
            && !l.ends_with('-')
    };
    if host.len() > 253 || !host.split('.').all(label_ok) {
        return Err(HostPortError::BadHost(host.into()));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn host_port_forms() {
        for ok in [
            "127.0.0.1:502",
            "127.0.0.1:0",
            "[::1]:5020",
            "plc-7.hall2.local:502",
            "localhost:1502",
        ] {
            assert_eq!(check_host_port(ok), Ok(()), "{ok}");
        }
        for bad in [
            "127.0.0.1",
            "127.0.0.1:70000",
            ":502",
            "::1:502",
            "bad host:502",
            "a..b:1",
        ] {
            assert!(check_host_port(bad).is_err(), "{bad}");
        }
    }
}
