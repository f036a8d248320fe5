//! Writing NC variables the way a Siemens PLC's FB3 (PUT) job does.
//!
//! A [`Job`] carries up to eight (variable, value) pairs that the NC applies all or
//! none. [`NcWriter`] is the transport-neutral interface, implemented once per target
//! kind: [`ModbusNcWriter`] (the NC axis module's register map over Modbus TCP),
//! [`ads::AdsNcWriter`] (Beckhoff ADS), [`opcua::OpcuaNcWriter`] (SINUMERIK OPC UA),
//! [`s7::S7NcWriter`] (a PLC data block and FB3 over S7comm). [`config::TargetConfig`] is the
//! `[targets.NAME]` table tagged by `kind`; [`guard::Guarded`] enforces, once for every
//! kind, what no target may skip: the allow-list, finite values, the job timeout and
//! the read-back check.

pub mod ads;
pub mod config;
pub mod guard;
pub mod modbus;
pub mod opcua;
pub mod s7;
pub mod signals;

use std::future::Future;
use std::time::Duration;

use compgate_ncproto::{JobState, JobStatus, MAX_PAIRS};

use crate::source::SourceError;
use compgate_core::comp::CompParams;

pub use compgate_ncproto::{thermal_limit, var};
pub use guard::{AnyNcWriter, Guarded};
pub use modbus::ModbusNcWriter;
pub use signals::StopSignals;

/// Errors of the NC layer.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NcError {
    /// The link to the NC failed.
    #[error("NC link: {0}")]
    Link(#[from] SourceError),
    /// The job did not finish within the job timeout.
    #[error(
        "job {job_id} did not finish within {timeout:?}{}{}",
        state.map(|s| format!(" (STATE stayed {})", s.name())).unwrap_or_default(),
        if *sent {
            ": the values may have landed; check with `compgate nc read`"
        } else {
            ": the target was still busy with an earlier job; nothing was sent"
        }
    )]
    JobTimeout {
        /// Job id.
        job_id: u16,
        /// The job timeout.
        timeout: Duration,
        /// Last state seen.
        state: Option<JobState>,
        /// Whether the job had been handed over (or may have been) when time ran out.
        sent: bool,
    },
    /// The link failed once the job request had gone out: the target may have taken
    /// it.
    #[error(
        "job {job_id}: NC link: {cause}, after the job request went out: the values may \
         have landed; check with `compgate nc read`"
    )]
    HandedOver {
        /// Job id.
        job_id: u16,
        /// The link's fault.
        cause: SourceError,
    },
    /// The target took the job, and reading the values back failed.
    #[error("job {job_id} written; reading it back failed: NC link: {cause}: check with `compgate nc read`")]
    ReadBackFailed {
        /// Job id.
        job_id: u16,
        /// The link's fault.
        cause: SourceError,
    },
    /// The read of the NC before a job (does it hold what the step was limited from?)
    /// did not end within the job timeout; nothing was sent.
    #[error("the read before job {job_id} did not end within job_timeout_s = {timeout:?}; nothing was sent")]
    CheckTimeout {
        /// Job id.
        job_id: u16,
        /// The job timeout.
        timeout: Duration,
    },
    /// The target took the job, and reading the values back did not end within the job
    /// timeout.
    #[error(
        "job {job_id} written; read-back not finished within job_timeout_s = {timeout:?}: \
         check with `compgate nc read`"
    )]
    ReadBackTimeout {
        /// Job id.
        job_id: u16,
        /// The job timeout.
        timeout: Duration,
    },
    /// The NC refused the job.
    #[error(
        "job {job_id} refused: error {} ({}){}",
        *status as u16,
        status.name(),
        match var {
            Some(v) => format!(" for {}", var_name(*v)),
            None if *index > 0 => format!(" at pair {index}"),
            None => String::new(),
        }
    )]
    Refused {
        /// Job id.
        job_id: u16,
        /// FB3 error code.
        status: JobStatus,
        /// 1-based pair index at fault, 0 when none.
        index: u16,
        /// The variable of that pair, when the index names one of the job.
        var: Option<u16>,
    },
    /// The value read back differs from the value written.
    #[error(
        "read-back of {}: wrote {}, NC holds {}",
        var_name(*var),
        number(*written),
        number(*read)
    )]
    ReadBack {
        /// Variable id.
        var: u16,
        /// Written value.
        written: f64,
        /// Value read back.
        read: f64,
    },
    /// Before the job the NC held another value than the one its step was limited
    /// from (changed at the HMI, by a part program, or restarted): a write would make
    /// a step of any size, so nothing was written.
    #[error(
        "not written: the NC holds {} = {}, the step was limited from {}",
        var_name(*var),
        number(*held),
        number(*from)
    )]
    NotHeld {
        /// The first variable that differs.
        var: u16,
        /// What the step was limited from.
        from: f64,
        /// What the NC holds.
        held: f64,
        /// Everything the NC holds of the three, to start the next step from.
        snapshot: CompParams,
    },
    /// What the target holds cannot be what the NC has (a value that is not finite,
    /// subnormal or beyond the NC's own limit; an S7 block word out of its range):
    /// most likely the layout or value type in the config is not the control's.
    #[error("{0}")]
    Implausible(String),
    /// The target's config cannot address this axis (validation names the key; this
    /// is what a writer built without it reports).
    #[error("config: {0}")]
    Config(String),
    /// The NC's answer makes no sense (unknown STATE or STATUS value, wrong job id).
    #[error("protocol: {0}")]
    Protocol(String),
    /// The job itself is malformed (no pairs or more than eight).
    #[error("invalid job: {0}")]
    InvalidJob(String),
    /// The job names a variable the axis's allow-list (`axes.NAME.nc_write`) leaves
    /// out; nothing was sent.
    #[error("variable {} is not in the allow-list (nc_write); nothing was written", var_name(*var))]
    NotAllowed {
        /// Variable id.
        var: u16,
    },
    /// A target other than a Modbus NC module cannot be reached (connect, transport,
    /// timeout of one request).
    #[error("NC link: {0}")]
    Unreachable(String),
    /// The target answered, and refused the write or read of one value, with its own
    /// code (an ADS error, an OPC UA status code).
    #[error("{what}: {answer}")]
    Answered {
        /// What was asked, e.g. `write of SD43900 (ADS 0x4020:0x0)`.
        what: String,
        /// What the target answered, by name and code.
        answer: String,
    },
    /// An OPC UA service, or one node of it, answered with a status other than Good.
    #[error("OPC UA {service} {target}: {status}")]
    OpcuaStatus {
        /// The service ("write", "read").
        service: &'static str,
        /// What it addressed ("of NODE", "for axis X1").
        target: String,
        /// The status code's name.
        status: String,
    },
    /// The OPC UA session's user may not write the setting data.
    #[error(
        "OPC UA write of {node}: BadUserAccessDenied: user {user} lacks the SeaWrite right \
         (setting data); an administrator grants it by calling the server's method \
         GiveUserAccess(user, \"SeaWrite\") (Sinumerik/Methods)"
    )]
    OpcuaAccessDenied {
        /// The node refused.
        node: String,
        /// The session's user.
        user: String,
    },
    /// The OPC UA target cannot be set up (credentials, namespace, node ids, client).
    #[error("OPC UA target: {0}")]
    OpcuaSetup(String),
}

/// A value as an operator reads it: `0.0219`, `-0.000025`, `100000`, `1e300`,
/// `1.4616e-30` (shortest round-trip digits, an exponent for tiny or huge values,
/// never hundreds of digits).
pub fn number(x: f64) -> String {
    let a = x.abs();
    if a != 0.0 && a.is_finite() && !(1e-6..1e15).contains(&a) {
        format!("{x:e}")
    } else {
        format!("{x}")
    }
}

/// An NC variable's value as `nc read` and the job log show it: lengths
/// ([`shown_mm`]) to 1 nm, other values (SD43910, a ratio) to 6 significant digits,
/// so that a computed value reads as `0.028`, not `0.027999999999999997`. The
/// recorder's `jobs` table keeps every written value exactly, and a read-back
/// mismatch is told with all digits ([`number`]).
pub fn shown(var_id: u16, x: f64) -> String {
    match var_id {
        var::SD43900 | var::SD43920 | var::MD32450 => shown_mm(x),
        _ => number(format!("{x:.5e}").parse().unwrap_or(x)),
    }
}

/// A length in mm to 1 nm (finer than any NC's input resolution), as [`number`]
/// writes it; beyond 1e9 mm, where 1 nm is below an f64's resolution, unrounded.
pub fn shown_mm(x: f64) -> String {
    if x.abs() < 1e9 {
        // + 0.0: a value rounded to -0 reads as 0.
        number((x * 1e6).round() / 1e6 + 0.0)
    } else {
        number(x)
    }
}

/// `SD43900` for a known variable id, the number otherwise.
pub fn var_name(var_id: u16) -> String {
    match var_id {
        var::SD43900 | var::SD43910 | var::SD43920 => format!("SD{var_id}"),
        var::MD32750 | var::MD32760 | var::MD32000 | var::MD32450 => format!("MD{var_id}"),
        _ => format!("variable {var_id}"),
    }
}

impl NcError {
    /// Whether the target could not be reached at all (no answer), as opposed to
    /// an answer that refused the request: the status says "unreachable" only then.
    pub fn is_unreachable(&self) -> bool {
        match self {
            Self::Link(SourceError::Exception(_))
            | Self::HandedOver {
                cause: SourceError::Exception(_),
                ..
            }
            | Self::ReadBackFailed {
                cause: SourceError::Exception(_),
                ..
            } => false,
            Self::Link(_)
            | Self::HandedOver { .. }
            | Self::ReadBackFailed { .. }
            | Self::Unreachable(_)
            | Self::JobTimeout { .. }
            | Self::CheckTimeout { .. }
            | Self::ReadBackTimeout { .. } => true,
            _ => false,
        }
    }
}

/// How a target stores the values: the precision the read-back is checked to, the one
/// tolerance of every target kind and of [`Guarded`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Precision {
    /// f64 / LREAL: the value read back must be bit for bit the value written.
    #[default]
    F64,
    /// f32 / REAL: the value read back must be the REAL the value written rounds to,
    /// or one of its two neighbours (one float32 step either way).
    F32,
}

impl Precision {
    /// Why `x`, read from a store of this precision as variable `var_id` (0: no
    /// setting datum), cannot be a value the NC holds: not finite, subnormal (a
    /// REAL's bytes read as an LREAL or the other way round give these), or beyond
    /// the NC's own limit of a thermal setting datum. `None` when it can.
    pub fn implausible(self, var_id: u16, x: f64) -> Option<String> {
        let smallest = match self {
            Self::F64 => f64::MIN_POSITIVE,
            Self::F32 => f64::from(f32::MIN_POSITIVE),
        };
        if !x.is_finite() {
            Some("not a finite number".into())
        } else if x != 0.0 && x.abs() < smallest {
            Some("a subnormal number".into())
        } else {
            compgate_ncproto::thermal_limit(var_id)
                .filter(|limit| x.abs() > *limit)
                .map(|limit| format!("beyond the NC's own limit of {}", number(limit)))
        }
    }

    /// Whether `read` is what a target of this precision holds after `written`.
    pub fn holds(self, written: f64, read: f64) -> bool {
        match self {
            Self::F64 => read.to_bits() == written.to_bits(),
            Self::F32 => {
                // Ordered integer image of a float32: adjacent floats differ by 1.
                let key = |f: f32| {
                    let b = f.to_bits() as i32;
                    if b < 0 {
                        i64::from(i32::MIN) - i64::from(b)
                    } else {
                        i64::from(b)
                    }
                };
                let (w, r) = (written as f32, read as f32);
                w.is_finite() && r.is_finite() && (key(w) - key(r)).abs() <= 1
            }
        }
    }

    /// Checks `(variable, written, read back)` triples: the first value the target
    /// does not hold is the error.
    pub fn check_read_back(
        self,
        values: impl IntoIterator<Item = (u16, f64, f64)>,
    ) -> Result<(), NcError> {
        for (var, written, read) in values {
            if !self.holds(written, read) {
                return Err(NcError::ReadBack { var, written, read });
            }
        }
        Ok(())
    }
}

/// One FB3-style job: up to eight variables written atomically.
#[derive(Debug, Clone, PartialEq)]
pub struct Job {
    /// (variable id, value) pairs; ids from `compgate_ncproto::var`.
    pub pairs: Vec<(u16, f64)>,
}

impl Job {
    /// The job that writes a thermal parameter set to SD43900/43910/43920.
    pub fn thermal(p: &CompParams) -> Self {
        Self {
            pairs: vec![
                (var::SD43900, p.k0_mm),
                (var::SD43910, p.tan_beta),
                (var::SD43920, p.p0_mm),
            ],
        }
    }

    /// Refuses a job without pairs or with more than eight, before anything is sent.
    pub fn check_pair_count(&self) -> Result<(), NcError> {
        if self.pairs.is_empty() || self.pairs.len() > MAX_PAIRS {
            return Err(NcError::InvalidJob(format!(
                "{} pairs; a job carries 1 to {MAX_PAIRS}",
                self.pairs.len()
            )));
        }
        Ok(())
    }

    /// The variable of 1-based pair `index`, as an NC names the pair at fault.
    pub fn var_at(&self, index: u16) -> Option<u16> {
        let i = usize::from(index.checked_sub(1)?);
        self.pairs.get(i).map(|&(v, _)| v)
    }

    /// [`Job::thermal`] with only the variables in `allowed`.
    pub fn thermal_allowed(p: &CompParams, allowed: &[u16]) -> Self {
        let mut job = Self::thermal(p);
        job.pairs.retain(|(v, _)| allowed.contains(v));
        job
    }
}

/// The ids a writer gives its jobs: 1, 2, .. 65535, then 1 again, never 0, so a fresh
/// target's `JOB_ID_DONE` of 0 never matches a job.
#[derive(Debug, Clone)]
pub struct JobIds(u16);

impl Default for JobIds {
    fn default() -> Self {
        Self(1)
    }
}

impl JobIds {
    /// The id of the next job.
    pub fn issue(&mut self) -> u16 {
        let id = self.0;
        self.0 = self.0.checked_add(1).unwrap_or(1);
        id
    }

    /// The id the next job will get, not issued.
    pub fn peek(&self) -> u16 {
        self.0
    }
}

/// What a finished job reports.
#[derive(Debug, Clone, PartialEq)]
pub struct JobReport {
    /// Job id used.
    pub job_id: u16,
    /// Time from the first request to the end of the job (through [`Guarded`]: to
    /// the verified read-back).
    pub elapsed: Duration,
}

/// What the NC shows of the axis.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct NcSnapshot {
    /// SD43900, mm.
    pub sd43900_mm: f64,
    /// SD43910, mm/mm.
    pub sd43910: f64,
    /// SD43920, mm.
    pub sd43920_mm: f64,
    /// MD32750 mode bits; `None` where the target does not report them (OPC UA, ADS).
    pub md32750: Option<u16>,
    /// MD32760 velocity factor.
    pub md32760: f64,
    /// MD32000, mm/min.
    pub max_ax_velo_mm_per_min: f64,
    /// MD32450 backlash, mm.
    pub md32450_mm: f64,
    /// Actual position, mm; `None` where the target does not report it (OPC UA, ADS):
    /// a 0 there fed the motion heat term and the recording a standing axis.
    pub position_mm: Option<f64>,
    /// Compensation the NC applies now, mm; `None` where the target does not report it.
    pub applied_comp_mm: Option<f64>,
    /// Compensation the NC is moving towards at this position, mm; `None` where the
    /// target does not report it.
    pub target_comp_mm: Option<f64>,
    /// Axis referenced; `None` where the target does not report it.
    pub referenced: Option<bool>,
}

impl NcSnapshot {
    /// The thermal parameters the NC holds.
    pub fn thermal(&self) -> CompParams {
        CompParams {
            k0_mm: self.sd43900_mm,
            tan_beta: self.sd43910,
            p0_mm: self.sd43920_mm,
        }
    }
}

/// Writes jobs to an NC and reads its state. One job at a time: `&mut self`.
pub trait NcWriter: Send {
    /// Runs one job until the target has taken it (or refused it). The read-back
    /// check is [`Guarded`]'s, once for every kind.
    fn write_job(&mut self, job: &Job) -> impl Future<Output = Result<JobReport, NcError>> + Send;
    /// Reads what the NC shows of the axis. A value the target does not have stays at
    /// its default.
    fn read_snapshot(&mut self) -> impl Future<Output = Result<NcSnapshot, NcError>> + Send;
    /// Whether this connection may write the values, when the target can tell
    /// (an OPC UA session's access level); `None` when it cannot. Default: `None`.
    fn may_write(&mut self) -> impl Future<Output = Result<Option<bool>, NcError>> + Send {
        std::future::ready(Ok(None))
    }
    /// How the target stores the values (the read-back tolerance). Default: f64.
    fn precision(&self) -> Precision {
        Precision::F64
    }
    /// Ends the connection politely, so the target frees its session now and not
    /// after its own timeout (a control admits only a few sessions). Default: nothing
    /// to end; dropping the writer closes its socket.
    fn close(&mut self) -> impl Future<Output = ()> + Send {
        std::future::ready(())
    }
}

/// A loopback address nobody listens on (a port just freed).
#[cfg(test)]
pub(crate) fn refused_address() -> String {
    let l = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    l.local_addr().expect("address").to_string()
}

/// The errors of `w`'s first snapshot, against a [`refused_address`], and of the next
/// one, made while the reconnect waits.
#[cfg(test)]
pub(crate) async fn refused_then_waiting(w: &mut impl NcWriter) -> (String, String) {
    let first = w.read_snapshot().await.expect_err("nobody listens");
    let waiting = w.read_snapshot().await.expect_err("backing off");
    (first.to_string(), waiting.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn job_ids_skip_zero_when_they_wrap() {
        let mut ids = JobIds(u16::MAX - 1);
        let got: Vec<u16> = (0..3).map(|_| ids.issue()).collect();
        assert_eq!(got, [u16::MAX - 1, u16::MAX, 1]);
        assert_eq!(JobIds::default().issue(), 1);
    }

    #[test]
    fn numbers_read_as_an_operator_writes_them() {
        for (x, shown) in [
            (0.0, "0"),
            (0.0219, "0.0219"),
            (-0.000025, "-0.000025"),
            (100_000.0, "100000"),
            (1e300, "1e300"),
            (1.4616014943717506e-30, "1.4616014943717506e-30"),
            (f64::NAN, "NaN"),
        ] {
            assert_eq!(number(x), shown);
        }
    }

    #[test]
    fn values_are_shown_without_float_noise() {
        let noisy = 0.1 * 0.28;
        assert_ne!(noisy, 0.028, "the test needs a value with float noise");
        assert_eq!(shown(var::SD43900, noisy), "0.028");
        assert_eq!(shown_mm(0.1 + 0.004), "0.104");
        assert_eq!(shown_mm(-1e-7), "0");
        assert_eq!(shown_mm(1e300), "1e300");
        assert_eq!(shown(var::SD43910, -6e-5 * (1.0 + 1e-15)), "-0.00006");
        assert_eq!(shown(var::SD43910, 1e-30), "1e-30");
        assert_eq!(shown(var::SD43910, 2.4567891234e-5), "0.0000245679");
    }

    #[test]
    fn implausible_values_are_the_ones_no_nc_holds() {
        let f32_tiny = f64::from(f32::from_bits(0x0001_0000));
        assert_eq!(
            Precision::F32.implausible(0, f32_tiny).as_deref(),
            Some("a subnormal number")
        );
        // A REAL store's smallest normal value is fine; an LREAL's subnormal is not.
        assert!(Precision::F32
            .implausible(0, f64::from(f32::MIN_POSITIVE))
            .is_none());
        assert!(Precision::F64.implausible(0, 5e-324).is_some());
        assert!(Precision::F64.implausible(0, f64::INFINITY).is_some());
        let beyond = Precision::F32.implausible(var::SD43900, 89128.96);
        assert_eq!(beyond.as_deref(), Some("beyond the NC's own limit of 10"));
        assert!(Precision::F64
            .implausible(var::SD43920, -100_000.0)
            .is_none());
        assert!(Precision::F64.implausible(var::SD43910, 0.0).is_none());
    }

    #[test]
    fn a_job_carries_one_to_eight_pairs() {
        let job = |n: usize| Job {
            pairs: vec![(var::SD43900, 0.0); n],
        };
        assert!(job(1).check_pair_count().is_ok());
        assert!(job(MAX_PAIRS).check_pair_count().is_ok());
        for n in [0, MAX_PAIRS + 1] {
            let e = job(n).check_pair_count().expect_err("refused");
            assert!(e.to_string().contains(&format!("{n} pairs")), "{e}");
        }
    }
}
