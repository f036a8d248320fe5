//! What every target guarantees, enforced here once rather than in each kind's writer:
//! a job goes out only with 1..=8 finite values of allowed variables, finishes within
//! the job timeout, and counts as written only when the target's read-back holds the
//! values (bit for bit for f64, for REAL within one float32 step of the REAL sent).
//! A job of the running gateway goes out only while the NC still holds the values its
//! step was limited from ([`Guarded::write_job_from`]).
//!
//! The rest is the runtime's: step limits and the deadband start from what the target
//! holds (its first snapshot), a refused or failed job is reported and not confirmed
//! (the next update writes again), and each axis's writer runs in its own task, so a
//! dead target never stops the polling.

use std::time::Duration;

use compgate_core::comp::CompParams;
use compgate_ncproto::var;
use tokio::time::Instant;

use super::ads::AdsNcWriter;
use super::opcua::OpcuaNcWriter;
use super::s7::S7NcWriter;
use super::{Job, JobIds, JobReport, ModbusNcWriter, NcError, NcSnapshot, NcWriter, Precision};

/// The three thermal setting data: the default allow-list.
pub const THERMAL_VARS: [u16; 3] = [var::SD43900, var::SD43910, var::SD43920];

/// A writer of any target kind.
#[derive(Debug)]
pub enum AnyNcWriter {
    /// Modbus NC axis module.
    Modbus(ModbusNcWriter),
    /// SINUMERIK OPC UA (boxed: the session state is large).
    Opcua(Box<OpcuaNcWriter>),
    /// S7 data block + FB3.
    S7(S7NcWriter),
    /// Beckhoff ADS.
    Ads(AdsNcWriter),
}

impl AnyNcWriter {
    /// The credentials it logs in with (OPC UA), read from their file or variables
    /// when it was built: a reload compares them, so a changed password is taken up.
    pub fn credentials(&self) -> Option<&crate::config::login::Credentials> {
        match self {
            Self::Opcua(w) => w.credentials(),
            _ => None,
        }
    }
}

impl NcWriter for AnyNcWriter {
    async fn write_job(&mut self, job: &Job) -> Result<JobReport, NcError> {
        match self {
            Self::Modbus(w) => w.write_job(job).await,
            Self::Opcua(w) => w.write_job(job).await,
            Self::S7(w) => w.write_job(job).await,
            Self::Ads(w) => w.write_job(job).await,
        }
    }

    async fn read_snapshot(&mut self) -> Result<NcSnapshot, NcError> {
        match self {
            Self::Modbus(w) => w.read_snapshot().await,
            Self::Opcua(w) => w.read_snapshot().await,
            Self::S7(w) => w.read_snapshot().await,
            Self::Ads(w) => w.read_snapshot().await,
        }
    }

    async fn may_write(&mut self) -> Result<Option<bool>, NcError> {
        match self {
            Self::Modbus(w) => w.may_write().await,
            // The session's UserAccessLevel on the three nodes.
            Self::Opcua(w) => w.may_write().await.map(Some),
            Self::S7(w) => w.may_write().await,
            Self::Ads(w) => w.may_write().await,
        }
    }

    fn precision(&self) -> Precision {
        match self {
            Self::Modbus(w) => w.precision(),
            Self::Opcua(w) => w.precision(),
            Self::S7(w) => w.precision(),
            Self::Ads(w) => w.precision(),
        }
    }

    async fn close(&mut self) {
        if let Self::Opcua(w) = self {
            w.close().await;
        }
    }
}

/// A writer behind the guarantees every target shares (see the module docs).
#[derive(Debug)]
pub struct Guarded<W = AnyNcWriter> {
    writer: W,
    allow: Vec<u16>,
    job_timeout: Duration,
    job_ids: JobIds,
}

impl<W: NcWriter> Guarded<W> {
    /// `writer` allowed to write the variables in `allow`, each job within
    /// `job_timeout`.
    pub fn new(writer: W, allow: Vec<u16>, job_timeout: Duration) -> Self {
        Self {
            writer,
            allow,
            job_timeout,
            job_ids: JobIds::default(),
        }
    }

    /// The writer inside.
    pub fn inner(&self) -> &W {
        &self.writer
    }

    /// The variables this writer may write.
    pub fn allowed(&self) -> &[u16] {
        &self.allow
    }

    /// Refuses a job that must not go out, before anything is sent.
    pub fn check(&self, job: &Job) -> Result<(), NcError> {
        job.check_pair_count()?;
        for &(var_id, value) in &job.pairs {
            if !self.allow.contains(&var_id) {
                return Err(NcError::NotAllowed { var: var_id });
            }
            if !value.is_finite() {
                return Err(NcError::InvalidJob(format!(
                    "{} = {value}: not a finite number; nothing was written",
                    super::var_name(var_id)
                )));
            }
        }
        Ok(())
    }

    /// Checks the read-back `snap` against what `job` wrote.
    fn verify(&self, job: &Job, snap: &NcSnapshot) -> Result<(), NcError> {
        self.writer
            .precision()
            .check_read_back(job.pairs.iter().filter_map(|&(var_id, written)| {
                let read = match var_id {
                    var::SD43900 => snap.sd43900_mm,
                    var::SD43910 => snap.sd43910,
                    var::SD43920 => snap.sd43920_mm,
                    var::MD32450 => snap.md32450_mm,
                    _ => return None,
                };
                Some((var_id, written, read))
            }))
    }
}

impl<W: NcWriter> Guarded<W> {
    /// Runs `job` as [`NcWriter::write_job`] does, after checking that the NC still
    /// holds `from` (the values the job's step was limited from) in every variable of
    /// the job: [`NcError::NotHeld`], and nothing written, when it does not. The
    /// gateway's last read of the NC may be a second old, and a value changed since
    /// would let this job make a step of any size.
    pub async fn write_job_from(
        &mut self,
        job: &Job,
        from: Option<&CompParams>,
    ) -> Result<JobReport, NcError> {
        self.check(job)?;
        let started = Instant::now();
        let deadline = started + self.job_timeout;
        let timeout = self.job_timeout;
        if let Some(from) = from {
            let before = match tokio::time::timeout_at(deadline, self.writer.read_snapshot()).await
            {
                Ok(result) => result?,
                // Nothing sent: the id stays the next job's.
                Err(_) => {
                    return Err(NcError::CheckTimeout {
                        job_id: self.job_ids.peek(),
                        timeout,
                    })
                }
            };
            let held = before.thermal();
            let want = Job::thermal(from);
            let now = Job::thermal(&held);
            for (&(var, value), &(_, held_value)) in want.pairs.iter().zip(&now.pairs) {
                let in_job = job.pairs.iter().any(|&(v, _)| v == var);
                if in_job && !Precision::F32.holds(value, held_value) {
                    return Err(NcError::NotHeld {
                        var,
                        from: value,
                        held: held_value,
                        snapshot: held,
                    });
                }
            }
        }
        self.write_checked(job, started, deadline).await
    }

    /// The write and its read-back within `deadline`.
    async fn write_checked(
        &mut self,
        job: &Job,
        started: Instant,
        deadline: Instant,
    ) -> Result<JobReport, NcError> {
        // Issued only for a job handed to the writer: a writer with a handshake id
        // (Modbus, S7) issues one per job handed to it, so the two stay equal and the
        // id recorded is the one the NC saw (one issued for a job refused before it
        // went out put every later id one ahead of the NC's JOB_ID_DONE).
        let job_id = self.job_ids.issue();
        let timeout = self.job_timeout;
        // One deadline, two phases: a write the target acknowledged and whose
        // read-back ran late is told apart from a write that never finished.
        match tokio::time::timeout_at(deadline, self.writer.write_job(job)).await {
            Ok(result) => result?,
            Err(_) => {
                return Err(NcError::JobTimeout {
                    job_id,
                    timeout,
                    state: None,
                    sent: true,
                })
            }
        };
        let snap = match tokio::time::timeout_at(deadline, self.writer.read_snapshot()).await {
            Ok(Err(NcError::Link(cause))) => return Err(NcError::ReadBackFailed { job_id, cause }),
            Ok(result) => result?,
            Err(_) => return Err(NcError::ReadBackTimeout { job_id, timeout }),
        };
        self.verify(job, &snap)?;
        Ok(JobReport {
            job_id,
            elapsed: started.elapsed(),
        })
    }
}

impl<W: NcWriter> NcWriter for Guarded<W> {
    async fn write_job(&mut self, job: &Job) -> Result<JobReport, NcError> {
        self.write_job_from(job, None).await
    }

    async fn read_snapshot(&mut self) -> Result<NcSnapshot, NcError> {
        self.writer.read_snapshot().await
    }

    async fn may_write(&mut self) -> Result<Option<bool>, NcError> {
        self.writer.may_write().await
    }

    fn precision(&self) -> Precision {
        self.writer.precision()
    }

    async fn close(&mut self) {
        self.writer.close().await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A target that records what reaches it and holds what it is told to hold.
    #[derive(Debug, Default)]
    struct Fake {
        written: Vec<Job>,
        holds: NcSnapshot,
        /// Added to what it holds after a write (a target that rounds or corrupts).
        skew: f64,
        slow: Option<Duration>,
        /// How long a read takes.
        slow_read: Option<Duration>,
        /// A read that fails on the link after the write.
        read_fails: bool,
        precision: Precision,
    }

    impl NcWriter for Fake {
        async fn write_job(&mut self, job: &Job) -> Result<JobReport, NcError> {
            if let Some(d) = self.slow {
                tokio::time::sleep(d).await;
            }
            self.written.push(job.clone());
            for &(v, x) in &job.pairs {
                let x = match self.precision {
                    Precision::F64 => x,
                    Precision::F32 => f64::from(x as f32),
                } + self.skew;
                match v {
                    var::SD43900 => self.holds.sd43900_mm = x,
                    var::SD43910 => self.holds.sd43910 = x,
                    var::SD43920 => self.holds.sd43920_mm = x,
                    _ => {}
                }
            }
            Ok(JobReport {
                job_id: 0,
                elapsed: Duration::ZERO,
            })
        }
        async fn read_snapshot(&mut self) -> Result<NcSnapshot, NcError> {
            if let Some(d) = self.slow_read {
                tokio::time::sleep(d).await;
            }
            if self.read_fails && !self.written.is_empty() {
                return Err(NcError::Link(crate::source::SourceError::Timeout(
                    Duration::from_millis(500),
                )));
            }
            Ok(self.holds)
        }
        fn precision(&self) -> Precision {
            self.precision
        }
    }

    fn thermal(k0: f64) -> Job {
        Job {
            pairs: vec![
                (var::SD43900, k0),
                (var::SD43910, 1e-5),
                (var::SD43920, 100.0),
            ],
        }
    }

    #[tokio::test]
    async fn bad_jobs_never_reach_the_target() {
        let mut g = Guarded::new(
            Fake::default(),
            THERMAL_VARS.to_vec(),
            Duration::from_secs(1),
        );
        for (job, want) in [
            (thermal(f64::NAN), "not a finite number"),
            (thermal(f64::INFINITY), "not a finite number"),
            (Job { pairs: vec![] }, "0 pairs"),
            (
                Job {
                    pairs: vec![(var::MD32450, 0.01)],
                },
                "MD32450 is not in the allow-list",
            ),
        ] {
            let e = g.write_job(&job).await.expect_err("refused");
            assert!(e.to_string().contains(want), "{e}");
        }
        let mut only_k0 = Guarded::new(Fake::default(), vec![var::SD43900], Duration::from_secs(1));
        let e = only_k0
            .write_job(&thermal(0.01))
            .await
            .expect_err("refused");
        assert_eq!(e, NcError::NotAllowed { var: var::SD43910 });
        assert!(g.inner().written.is_empty());
        assert!(only_k0.inner().written.is_empty());
    }

    #[tokio::test]
    async fn read_back_is_exact_for_f64_and_one_ulp_for_real() {
        let mut g = Guarded::new(
            Fake::default(),
            THERMAL_VARS.to_vec(),
            Duration::from_secs(1),
        );
        g.write_job(&thermal(0.0123456789)).await.expect("exact");
        // One f64 ulp off is a failed read-back on an f64 target.
        g.writer.skew = 1e-18;
        let e = g.write_job(&thermal(0.0123456789)).await.expect_err("off");
        assert!(
            matches!(
                e,
                NcError::ReadBack {
                    var: var::SD43900,
                    ..
                }
            ),
            "{e}"
        );

        let real = Fake {
            precision: Precision::F32,
            ..Fake::default()
        };
        let mut g = Guarded::new(real, THERMAL_VARS.to_vec(), Duration::from_secs(1));
        g.write_job(&thermal(0.0123456789))
            .await
            .expect("rounded to REAL");
        // Two float32 ulps off is not what the REAL holds.
        g.writer.skew = 2.0 * f64::from(f32::EPSILON) * 0.0123456789;
        assert!(g.write_job(&thermal(0.0123456789)).await.is_err());
    }

    #[tokio::test(start_paused = true)]
    async fn a_slow_target_hits_the_job_timeout() {
        let slow = Fake {
            slow: Some(Duration::from_secs(5)),
            ..Fake::default()
        };
        let mut g = Guarded::new(slow, THERMAL_VARS.to_vec(), Duration::from_millis(200));
        let e = g.write_job(&thermal(0.01)).await.expect_err("timeout");
        assert!(matches!(e, NcError::JobTimeout { sent: true, .. }), "{e}");
        assert!(e.is_unreachable());
        let text = e.to_string();
        assert!(text.contains("may have landed"), "{text}");
        assert!(!text.contains("None"), "{text}");
    }

    #[tokio::test(start_paused = true)]
    async fn a_write_taken_whose_read_back_runs_late_says_it_was_written() {
        // The write answers in 0.6 s, the read-back would end at 1.8 s: past the 1 s
        // job timeout.
        let slow = Fake {
            slow: Some(Duration::from_millis(600)),
            slow_read: Some(Duration::from_millis(1200)),
            ..Fake::default()
        };
        let mut g = Guarded::new(slow, THERMAL_VARS.to_vec(), Duration::from_secs(1));
        let e = g
            .write_job(&thermal(0.01))
            .await
            .expect_err("read-back late");
        assert_eq!(
            e,
            NcError::ReadBackTimeout {
                job_id: 1,
                timeout: Duration::from_secs(1)
            }
        );
        assert_eq!(
            e.to_string(),
            "job 1 written; read-back not finished within job_timeout_s = 1s: check with `compgate nc read`"
        );
        assert_eq!(g.inner().written.len(), 1);
    }

    // The target took the job and the read-back's link failed: it read as a job
    // that failed on the link ("NC link: no reply within 500ms").
    #[tokio::test]
    async fn a_write_taken_whose_read_back_fails_says_it_was_written() {
        let fails = Fake {
            read_fails: true,
            ..Fake::default()
        };
        let mut g = Guarded::new(fails, THERMAL_VARS.to_vec(), Duration::from_secs(1));
        let e = g
            .write_job(&thermal(0.01))
            .await
            .expect_err("read-back failed");
        assert_eq!(
            e.to_string(),
            "job 1 written; reading it back failed: NC link: no reply within 500ms: check \
             with `compgate nc read`"
        );
        assert!(e.is_unreachable());
    }

    #[test]
    fn precision_bounds() {
        let w = 0.1_f64;
        assert!(Precision::F32.holds(w, f64::from(w as f32)));
        assert!(!Precision::F64.holds(w, f64::from(w as f32)));
        assert!(!Precision::F32.holds(w, f64::NAN));
    }
}
