//! The problem type: one thing wrong with a configuration, and a collector the
//! stages' `validate` functions report into.

use std::fmt;
use std::net::{Ipv4Addr, SocketAddr};

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

/// How [`Problems::host_port`] takes port 0.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PortZero {
    /// Refused: nothing listens there.
    #[default]
    Refused,
    /// Refused in a file with `[sim]` loaded for `run`, with the hint that port 0 is
    /// for the simulated plant (`config/demo.toml`).
    RefusedInSimFile,
    /// Passes: the simulated plant binds a free port for it and writes the port it
    /// got into the address before the gateway connects (`compgate demo`, `compgate
    /// sim`).
    ForSim,
}

/// Collects the problems of one file; the checks every stage uses.
#[derive(Debug)]
pub struct Problems<'a> {
    file: &'a str,
    out: Vec<ConfigProblem>,
    port_zero: PortZero,
}

impl<'a> Problems<'a> {
    /// An empty list for `file`.
    pub fn new(file: &'a str) -> Self {
        Problems {
            file,
            out: Vec::new(),
            port_zero: PortZero::Refused,
        }
    }

    /// How [`Problems::host_port`] takes port 0 (default: refused).
    pub fn port_zero(mut self, port_zero: PortZero) -> Self {
        self.port_zero = port_zero;
        self
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

    /// `addr` is `host:port` the gateway connects to (see [`check_host_port`]).
    pub fn host_port(&mut self, key: &str, addr: &str) {
        match (check_host_port(addr), self.port_zero) {
            (Ok(()), _) | (Err(HostPortError::PortZero(_)), PortZero::ForSim) => {}
            (Err(why @ HostPortError::PortZero(_)), PortZero::RefusedInSimFile) => self.push(
                key,
                format!(
                    "{why}; port 0 is for `compgate demo` and `compgate sim`, whose \
                     simulated plant picks a free port"
                ),
            ),
            (Err(why), _) => self.push(key, why.to_string()),
        }
    }
}

/// Largest unit id of a Modbus RTU device (248..=255 are reserved on a serial line).
pub const MAX_RTU_UNIT_ID: u8 = 247;

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
    /// A URL's scheme before the address.
    #[error("`{0}`: no scheme: write host:port, e.g. \"192.168.0.10:502\"")]
    Scheme(String),
    /// Brackets that do not hold an IPv6 address.
    #[error("`{0}` is not an IPv6 address in brackets; expected e.g. \"[fe80::1]:502\"")]
    NotIpv6(String),
    /// A link-local address's zone given as an interface name, which the socket
    /// address parser does not take (nor does the resolver, in brackets).
    #[error(
        "`{0}`: give the zone of the IPv6 address as the interface's index, e.g. \
         \"[fe80::1%2]:502\" (`ip link` lists it), not its name"
    )]
    ZoneName(String),
    /// Not a host name.
    #[error(
        "`{0}` is not a valid host name or IP address; expected host:port, e.g. \"192.168.0.10:502\""
    )]
    BadHost(String),
    /// Ends in a number but is not an IPv4 address.
    #[error(
        "`{0}` is not an IPv4 address: four numbers 0..=255 without leading zeros, e.g. \
         \"192.168.0.10:502\" (a host name does not end in a number)"
    )]
    NotIpv4(String),
    /// Port 0: nothing listens there.
    #[error("`{0}`: port 0 cannot be connected to; give the port the peer listens on, e.g. \"192.168.0.10:502\"")]
    PortZero(String),
}

/// `host:port` reduced to the peer it names, to find one peer configured twice under
/// two spellings: the host case-folded, `localhost` as `127.0.0.1`, an IP address and
/// the port in their canonical forms (`[::1]:0502` as `[::1]:502`). Text that is not
/// `host:port` is only case-folded.
pub fn peer_identity(addr: &str) -> String {
    let addr = addr.trim().to_ascii_lowercase();
    let Some((host, port)) = addr.rsplit_once(':') else {
        return addr;
    };
    let bare = host.trim_start_matches('[').trim_end_matches(']');
    let host = match bare.parse::<std::net::IpAddr>() {
        Ok(std::net::IpAddr::V6(ip)) => format!("[{ip}]"),
        Ok(ip) => ip.to_string(),
        Err(_) if bare == "localhost" => "127.0.0.1".to_string(),
        Err(_) => host.to_string(),
    };
    let port = port
        .parse::<u16>()
        .map_or(port.to_string(), |p| p.to_string());
    format!("{host}:{port}")
}

/// Accepts `host:port` the gateway connects to: a host name, an IPv4 address or a
/// bracketed IPv6 address, and a port 1..=65535.
///
/// A host whose last label is a number must be an IPv4 address: top-level domains are
/// never numeric (RFC 3696), and the resolver would not refuse `192.168.0` or
/// `3232235530` but read them its own way (`inet_aton`: 192.168.0.0, 192.168.0.10).
pub fn check_host_port(addr: &str) -> Result<(), HostPortError> {
    let port = match addr.parse::<SocketAddr>() {
        Ok(a) => a.port(),
        Err(_) => host_name_port(addr)?,
    };
    if port == 0 {
        return Err(HostPortError::PortZero(addr.into()));
    }
    Ok(())
}

/// The port of `host:port` whose host is not an IP address literal.
fn host_name_port(addr: &str) -> Result<u16, HostPortError> {
    if addr.contains("://") {
        return Err(HostPortError::Scheme(addr.into()));
    }
    if let Some(rest) = addr.strip_prefix('[') {
        // Would have parsed as a SocketAddr if the brackets held an IPv6 address.
        let (ip, port) = rest.split_once(']').unwrap_or((rest, ""));
        let Some(port) = port.strip_prefix(':') else {
            return Err(HostPortError::NotIpv6(addr.into()));
        };
        if port.parse::<u16>().is_err() {
            return Err(HostPortError::BadPort(port.into()));
        }
        return match ip.split_once('%') {
            Some((ip, _)) if ip.parse::<std::net::Ipv6Addr>().is_ok() => {
                Err(HostPortError::ZoneName(addr.into()))
            }
            _ => Err(HostPortError::NotIpv6(addr.into())),
        };
    }
    let Some((host, port)) = addr.rsplit_once(':') else {
        return Err(HostPortError::NoPort(addr.into()));
    };
    let Ok(port) = port.parse::<u16>() else {
        return Err(HostPortError::BadPort(port.into()));
    };
    if host.is_empty() {
        return Err(HostPortError::NoHost(addr.into()));
    }
    if host.contains(':') {
        return Err(HostPortError::Ipv6(addr.into()));
    }
    let last = host.rsplit('.').next().unwrap_or_default();
    if !last.is_empty() && last.bytes().all(|b| b.is_ascii_digit()) {
        // A valid address with this port would have parsed as a SocketAddr.
        return match host.parse::<Ipv4Addr>() {
            Ok(_) => Ok(port),
            Err(_) => Err(HostPortError::NotIpv4(host.into())),
        };
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
    Ok(port)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_peer_under_two_spellings_has_one_identity() {
        let same = [
            ("127.0.0.1:502", "localhost:502"),
            ("127.0.0.1:502", " LocalHost:0502"),
            ("[::1]:502", "[0:0:0:0:0:0:0:1]:502"),
            ("plc-1.Hall2:102", "PLC-1.hall2:102"),
        ];
        for (a, b) in same {
            assert_eq!(peer_identity(a), peer_identity(b), "{a} and {b}");
        }
        let other = [
            ("127.0.0.1:502", "127.0.0.1:503"),
            ("127.0.0.1:502", "127.0.0.2:502"),
            ("127.0.0.1:502", "[::1]:502"),
        ];
        for (a, b) in other {
            assert_ne!(peer_identity(a), peer_identity(b), "{a} and {b}");
        }
    }

    #[test]
    fn host_port_forms() {
        for ok in [
            "127.0.0.1:502",
            "[::1]:5020",
            "plc-7.hall2.local:502",
            "localhost:1502",
            "192.168.0.255:502",
            "4plc.hall2:502",
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

    #[test]
    fn a_scheme_or_bad_brackets_get_their_own_reason() {
        for (bad, want) in [
            (
                "tcp://127.0.0.1:502",
                HostPortError::Scheme("tcp://127.0.0.1:502".into()),
            ),
            (
                "mqtt://broker:1883",
                HostPortError::Scheme("mqtt://broker:1883".into()),
            ),
            (
                "[fe80::1%eth0]:502",
                HostPortError::ZoneName("[fe80::1%eth0]:502".into()),
            ),
            ("[::1:1883", HostPortError::NotIpv6("[::1:1883".into())),
            ("[plc]:502", HostPortError::NotIpv6("[plc]:502".into())),
            ("[::1]:x", HostPortError::BadPort("x".into())),
        ] {
            assert_eq!(check_host_port(bad), Err(want), "{bad}");
        }
        // A zone by index is what the socket address parser takes.
        assert_eq!(check_host_port("[fe80::1%2]:502"), Ok(()));
        let why = check_host_port("tcp://127.0.0.1:502")
            .unwrap_err()
            .to_string();
        assert!(why.contains("no scheme: write host:port"), "{why}");
    }

    #[test]
    fn a_numeric_host_must_be_an_ipv4_address() {
        for bad in [
            "192.168.0.300:502",
            "999.1.1.1:502",
            "192.168.0:502",
            "192.168.0.010:502",
            "3232235530:502",
            "plc.7:502",
        ] {
            let host = bad.rsplit_once(':').map_or("", |(h, _)| h);
            assert_eq!(
                check_host_port(bad),
                Err(HostPortError::NotIpv4(host.into())),
                "{bad}"
            );
        }
        let why = check_host_port("192.168.0.300:502")
            .unwrap_err()
            .to_string();
        assert!(
            why.contains("`192.168.0.300` is not an IPv4 address"),
            "{why}"
        );
    }

    #[test]
    fn port_0_is_refused_unless_the_simulated_plant_binds_it() {
        for zero in ["127.0.0.1:0", "[::1]:0", "plc:0"] {
            assert_eq!(
                check_host_port(zero),
                Err(HostPortError::PortZero(zero.into())),
                "{zero}"
            );
        }
        let mut out = Problems::new("t.toml");
        out.host_port("devices.ain1.address", "127.0.0.1:0");
        let p = out.into_vec();
        assert_eq!(p.len(), 1, "{p:?}");
        assert!(p[0].message.contains("port 0"), "{}", p[0]);
        let mut out = Problems::new("t.toml").port_zero(PortZero::ForSim);
        out.host_port("devices.ain1.address", "127.0.0.1:0");
        out.host_port("devices.ain2.address", "999.1.1.1:0");
        assert_eq!(
            out.into_vec()
                .iter()
                .map(|p| p.key.as_str())
                .collect::<Vec<_>>(),
            ["devices.ain2.address"],
            "only port 0 is left to the simulator"
        );
    }
}
