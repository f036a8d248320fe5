//! Quality of a channel's reading and the reasons behind it.

use std::fmt;

/// Why a reading is not [`Quality::Good`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Reason {
    /// The transport to the device failed (timeout, connection, framing).
    Comm,
    /// The device answered with a Modbus exception.
    DeviceException,
    /// The device failed for several cycles in a row: its channels are not trusted.
    DeviceDegraded,
    /// Loop current below 3.6 mA (NAMUR NE43): open circuit or sensor fault.
    Ne43Low,
    /// Loop current above 21 mA (NAMUR NE43): short circuit or sensor fault.
    Ne43High,
    /// The raw value or the scaled value is NaN or infinite.
    NotFinite,
    /// The scaled value is outside the channel's plausible range.
    OutOfRange,
    /// The raw value is one no sensor produces (a float of magnitude below 1e-6 but
    /// not 0): most likely a 32-bit value read in the wrong word order.
    Implausible,
    /// The value changed faster than the plausible rate (a spike or a jump).
    RateRejected,
    /// The raw value stayed bit-identical for too long: a frozen transmitter.
    Stale,
    /// There has never been a value.
    NoData,
}

impl Reason {
    /// A short lower-case name for logs and the status line.
    pub fn as_str(&self) -> &'static str {
        match self {
            Self::Comm => "comm",
            Self::DeviceException => "device exception",
            Self::DeviceDegraded => "device degraded",
            Self::Ne43Low => "NE43 low",
            Self::Ne43High => "NE43 high",
            Self::NotFinite => "not finite",
            Self::OutOfRange => "out of range",
            Self::Implausible => "implausible raw value",
            Self::RateRejected => "rate rejected",
            Self::Stale => "stale",
            Self::NoData => "no data",
        }
    }
}

impl fmt::Display for Reason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Quality of a reading.
///
/// `Uncertain` values may be used (a held value during a short outage, a single
/// rejected spike); `Bad` values must not feed the compensation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Quality {
    /// A fresh, plausible value.
    Good,
    /// A usable but not fresh value (held over a gap or a rejected sample).
    Uncertain(Reason),
    /// No usable value.
    Bad(Reason),
}

impl Quality {
    /// `Good` or `Uncertain`: the value may feed the compensation.
    pub fn is_usable(&self) -> bool {
        !matches!(self, Self::Bad(_))
    }

    /// Exactly `Good`.
    pub fn is_good(&self) -> bool {
        matches!(self, Self::Good)
    }

    /// The reason, if the quality is not `Good`.
    pub fn reason(&self) -> Option<Reason> {
        match self {
            Self::Good => None,
            Self::Uncertain(r) | Self::Bad(r) => Some(*r),
        }
    }
}

impl fmt::Display for Quality {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Good => f.write_str("good"),
            Self::Uncertain(r) => write!(f, "uncertain ({r})"),
            Self::Bad(r) => write!(f, "bad ({r})"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn usable_is_good_or_uncertain() {
        assert!(Quality::Good.is_usable());
        assert!(Quality::Uncertain(Reason::Comm).is_usable());
        assert!(!Quality::Bad(Reason::Comm).is_usable());
        assert!(Quality::Good.is_good());
        assert!(!Quality::Uncertain(Reason::Comm).is_good());
        assert!(!Quality::Bad(Reason::Stale).is_good());
    }

    #[test]
    fn reason_of_quality() {
        assert_eq!(Quality::Good.reason(), None);
        assert_eq!(Quality::Bad(Reason::Stale).reason(), Some(Reason::Stale));
        assert_eq!(
            Quality::Uncertain(Reason::RateRejected).reason(),
            Some(Reason::RateRejected)
        );
    }

    #[test]
    fn display() {
        assert_eq!(Quality::Good.to_string(), "good");
        assert_eq!(Quality::Bad(Reason::Ne43Low).to_string(), "bad (NE43 low)");
        assert_eq!(
            Quality::Uncertain(Reason::Comm).to_string(),
            "uncertain (comm)"
        );
    }
}
