//! Writing NC variables the way a Siemens PLC's FB3 (PUT) job does.
//!
//! A [`Job`] carries up to eight (variable, value) pairs that the NC applies all or
//! none. [`NcWriter`] is the transport-neutral interface; [`ModbusNcWriter`] speaks
//! the NC axis module's register map (`compgate_ncproto`) over Modbus TCP with
//! the REQ/DONE/ERROR/STATE handshake, a job timeout and read-back verification.

pub mod config;
pub mod s7;

use std::future::Future;
use std::time::Duration;

use compgate_ncproto::{self as ncmap, var, JobState, JobStatus};
use tokio::time::Instant;

use crate::source::modbus::ModbusLink;
use crate::source::plan::RegisterKind;
use crate::source::SourceError;
use compgate_core::comp::CompParams;

/// Errors of the NC layer.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NcError {
    /// The link to the NC failed.
    #[error("NC link: {0}")]
    Link(#[from] SourceError),
    /// The job did not finish within the job timeout.
    #[error("job {job_id} did not finish within {timeout:?} (STATE stayed {state:?})")]
    JobTimeout {
        /// Job id.
        job_id: u16,
        /// The job timeout.
        timeout: Duration,
        /// Last state seen.
        state: Option<JobState>,
    },
    /// The NC refused the job.
    #[error("job {job_id} refused: error {} ({}) at pair {index}", *status as u16, status.name())]
    Refused {
        /// Job id.
        job_id: u16,
        /// FB3 error code.
        status: JobStatus,
        /// 1-based pair index at fault, 0 when none.
        index: u16,
    },
    /// The value read back differs from the value written.
    #[error("read-back of variable {var}: wrote {written}, NC holds {read}")]
    ReadBack {
        /// Variable id.
        var: u16,
        /// Written value.
        written: f64,
        /// Value read back.
        read: f64,
    },
    /// The NC's answer makes no sense (unknown STATE or STATUS value, wrong job id).
    #[error("protocol: {0}")]
    Protocol(String),
    /// The job itself is malformed (no pairs or more than eight).
    #[error("invalid job: {0}")]
    InvalidJob(String),
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
}

/// What a finished job reports.
#[derive(Debug, Clone, PartialEq)]
pub struct JobReport {
    /// Job id used.
    pub job_id: u16,
    /// Time from the first request to the verified read-back.
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
    /// MD32750 mode bits.
    pub md32750: u16,
    /// MD32760 velocity factor.
    pub md32760: f64,
    /// MD32000, mm/min.
    pub max_ax_velo_mm_per_min: f64,
    /// MD32450 backlash, mm.
    pub md32450_mm: f64,
    /// Actual position, mm.
    pub position_mm: f64,
    /// Compensation the NC applies now, mm.
    pub applied_comp_mm: f64,
    /// Compensation the NC is moving towards at this position, mm.
    pub target_comp_mm: f64,
    /// Axis referenced.
    pub referenced: bool,
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
    /// Runs one job to completion, verified by read-back.
    fn write_job(&mut self, job: &Job) -> impl Future<Output = Result<JobReport, NcError>> + Send;
    /// Reads what the NC shows of the axis.
    fn read_snapshot(&mut self) -> impl Future<Output = Result<NcSnapshot, NcError>> + Send;
}

/// Read-back address of a variable, if the map has one.
fn readback_address(var_id: u16) -> Option<u16> {
    match var_id {
        var::SD43900 => Some(ncmap::RB_SD43900),
        var::SD43910 => Some(ncmap::RB_SD43910),
        var::SD43920 => Some(ncmap::RB_SD43920),
        var::MD32450 => Some(ncmap::RB_MD32450),
        _ => None,
    }
}

fn f64_at(regs: &[u16], base: u16, addr: u16) -> Result<f64, NcError> {
    let i = usize::from(addr - base);
    regs.get(i..i + 4)
        .and_then(|r| <[u16; 4]>::try_from(r).ok())
        .map(ncmap::regs_to_f64)
        .ok_or_else(|| NcError::Protocol(format!("register {addr} missing from read-back")))
}

/// FB3-style job client over Modbus TCP.
#[derive(Debug)]
pub struct ModbusNcWriter {
    link: ModbusLink,
    unit_id: u8,
    job_timeout: Duration,
    next_job_id: u16,
}

impl ModbusNcWriter {
    /// A writer on `link` addressing unit `unit_id`.
    pub fn new(link: ModbusLink, unit_id: u8, job_timeout: Duration) -> Self {
        Self {
            link,
            unit_id,
            job_timeout,
            next_job_id: 1,
        }
    }

    async fn read_holding(&mut self, start: u16, count: u16) -> Result<Vec<u16>, NcError> {
        Ok(self
            .link
            .read(self.unit_id, RegisterKind::Holding, start, count)
            .await?)
    }

    async fn state(&mut self) -> Result<JobState, NcError> {
        let r = self.read_holding(ncmap::STATE, 1).await?;
        let v = r.first().copied().unwrap_or(u16::MAX);
        JobState::from_u16(v).ok_or_else(|| NcError::Protocol(format!("STATE = {v}")))
    }

    /// Waits until `done(state)` or the deadline; the module is polled briefly
    /// because a job takes one or two IPO cycles.
    async fn wait_state(
        &mut self,
        deadline: Instant,
        job_id: u16,
        done: impl Fn(JobState) -> bool,
    ) -> Result<JobState, NcError> {
        loop {
            let s = self.state().await?;
            if done(s) {
                return Ok(s);
            }
            if Instant::now() >= deadline {
                return Err(NcError::JobTimeout {
                    job_id,
                    timeout: self.job_timeout,
                    state: Some(s),
                });
            }
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    }

    async fn run_job(&mut self, job: &Job, job_id: u16, deadline: Instant) -> Result<(), NcError> {
        // A job left unacknowledged by an earlier run (crash, timeout) is cleared
        // first; a busy module is waited for, never interrupted.
        if self.state().await? != JobState::Idle {
            self.link.write(self.unit_id, ncmap::REQ, &[0]).await?;
            self.wait_state(deadline, job_id, |s| s == JobState::Idle)
                .await?;
        }
        let mut block = vec![job_id, job.pairs.len() as u16];
        for (var_id, value) in &job.pairs {
            block.push(*var_id);
            block.extend_from_slice(&ncmap::f64_to_regs(*value));
        }
        self.link.write(self.unit_id, ncmap::JOB_ID, &block).await?;
        self.link.write(self.unit_id, ncmap::REQ, &[1]).await?;
        self.wait_state(deadline, job_id, |s| {
            matches!(s, JobState::Done | JobState::Error)
        })
        .await?;
        let r = self
            .read_holding(ncmap::STATE, ncmap::JOB_ID_DONE - ncmap::STATE + 1)
            .await?;
        let reg = |a: u16| r[usize::from(a - ncmap::STATE)];
        // Acknowledge before judging, so the module is idle whatever happens next.
        self.link.write(self.unit_id, ncmap::REQ, &[0]).await?;
        if reg(ncmap::JOB_ID_DONE) != job_id {
            return Err(NcError::Protocol(format!(
                "JOB_ID_DONE = {}, expected {job_id}",
                reg(ncmap::JOB_ID_DONE)
            )));
        }
        let status = JobStatus::from_u16(reg(ncmap::STATUS))
            .ok_or_else(|| NcError::Protocol(format!("STATUS = {}", reg(ncmap::STATUS))))?;
        if reg(ncmap::ERROR) != 0 || status != JobStatus::Ok {
            return Err(NcError::Refused {
                job_id,
                status,
                index: reg(ncmap::ERROR_INDEX),
            });
        }
        self.verify(job).await
    }

    async fn verify(&mut self, job: &Job) -> Result<(), NcError> {
        let rb = self
            .read_holding(ncmap::READBACK, ncmap::READBACK_LEN)
            .await?;
        for (var_id, written) in &job.pairs {
            if let Some(addr) = readback_address(*var_id) {
                let read = f64_at(&rb, ncmap::READBACK, addr)?;
                if read.to_bits() != written.to_bits() {
                    return Err(NcError::ReadBack {
                        var: *var_id,
                        written: *written,
                        read,
                    });
                }
            }
        }
        Ok(())
    }
}

impl NcWriter for ModbusNcWriter {
    async fn write_job(&mut self, job: &Job) -> Result<JobReport, NcError> {
        if job.pairs.is_empty() || job.pairs.len() > ncmap::MAX_PAIRS {
            return Err(NcError::InvalidJob(format!(
                "{} pairs; a job carries 1 to {}",
                job.pairs.len(),
                ncmap::MAX_PAIRS
            )));
        }
        let job_id = self.next_job_id;
        // Skip 0 so a fresh module's JOB_ID_DONE = 0 never matches.
        self.next_job_id = self.next_job_id.checked_add(1).unwrap_or(1);
        let started = Instant::now();
        let deadline = started + self.job_timeout;
        match tokio::time::timeout_at(deadline, self.run_job(job, job_id, deadline)).await {
            Ok(Ok(())) => Ok(JobReport {
                job_id,
                elapsed: started.elapsed(),
            }),
            Ok(Err(e)) => Err(e),
            Err(_) => {
                // Cut off mid-request: the stream may hold a late reply.
                self.link.disconnect();
                Err(NcError::JobTimeout {
                    job_id,
                    timeout: self.job_timeout,
                    state: None,
                })
            }
        }
    }

    async fn read_snapshot(&mut self) -> Result<NcSnapshot, NcError> {
        let base = ncmap::READBACK;
        let rb = self.read_holding(base, ncmap::READBACK_LEN).await?;
        let u = |a: u16| rb.get(usize::from(a - base)).copied().unwrap_or(0);
        Ok(NcSnapshot {
            sd43900_mm: f64_at(&rb, base, ncmap::RB_SD43900)?,
            sd43910: f64_at(&rb, base, ncmap::RB_SD43910)?,
            sd43920_mm: f64_at(&rb, base, ncmap::RB_SD43920)?,
            md32760: f64_at(&rb, base, ncmap::RB_MD32760)?,
            max_ax_velo_mm_per_min: f64_at(&rb, base, ncmap::RB_MAX_AX_VELO)?,
            md32450_mm: f64_at(&rb, base, ncmap::RB_MD32450)?,
            position_mm: f64_at(&rb, base, ncmap::RB_POSITION)?,
            applied_comp_mm: f64_at(&rb, base, ncmap::RB_APPLIED_COMP)?,
            target_comp_mm: f64_at(&rb, base, ncmap::RB_TARGET_COMP)?,
            md32750: u(ncmap::RB_MD32750),
            referenced: u(ncmap::RB_REFERENCED) != 0,
        })
    }
}
