//! Simulated NC axis module: the target of the gateway's FB3-style PUT jobs.
//!
//! [`NcAxis`] is the pure axis state of a Siemens 840D axis as far as temperature
//! compensation goes: the setting data SD43900/43910/43920, the machine data
//! MD32750/32760/32000/32450, the referenced flag and the actual position. It validates
//! and applies jobs ([`NcAxis::execute_job`]) and advances one interpolation cycle at a
//! time ([`NcAxis::ipo_tick`]), slewing the applied compensation toward
//! `dK = K0 + tan(beta) * (Px - P0)` no faster than MD32760 x MAX_AX_VELO.
//!
//! [`NcAxisModule`] serves that state over Modbus TCP with exactly the register map and
//! REQ/DONE/ERROR/STATE handshake of [`compgate_ncproto`], and runs the interpolation loop
//! in tokio time while it serves. Behind the servo block of the map it also holds a
//! full-closed-loop axis ([`crate::axis::ServoSim`]) that runs move programmes and the
//! servo trace, advanced on each request by the tokio time elapsed times the
//! simulation speed ([`NcAxisModule::set_sim_speed`]). Once a programme has run,
//! `RB_POSITION` shows that axis's scale position (unless the axis oscillates).
//!
//! Handshake details beyond the map's doc, as the module implements them:
//! - A rising edge is a write of a non-zero `REQ` while the stored `REQ` is 0 and
//!   `STATE` is idle; any other `REQ` write only stores the value. A second edge while
//!   busy, done or error starts nothing.
//! - Writing `REQ = 0` in done or error acknowledges: `STATE` idle, `DONE`, `ERROR`,
//!   `STATUS` and `ERROR_INDEX` cleared. `JOB_ID_DONE` keeps the last finished job.
//! - The job is latched (copied) on the edge, so later writes to `JOB_ID`,
//!   `NUM_PAIRS` or the pairs are stored but do not alter it.
//! - A write (0x06 or 0x10) must lie entirely in the writable registers: `REQ` alone,
//!   or inside `JOB_ID ..= VALUE[7]`. Anything else is refused whole with 0x02.

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use tokio::net::{TcpListener, TcpStream};
use tokio::time::Instant;
use tokio_modbus::server::Service;
use tokio_modbus::{ExceptionCode, Request, Response};
use tokio_util::sync::CancellationToken;

use crate::axis::{AxisParams, ServoSim, SimRefusal};
use compgate_ncproto::servo::{MoveStep, TraceConfig, Trigger, MAX_STEPS};
use compgate_ncproto::{self as ncmap, var, JobState, JobStatus};
use compgate_ncproto::{MD32450_LIMIT_MM, SD43900_LIMIT_MM, SD43910_LIMIT, SD43920_LIMIT_MM};

/// Shortest interpolation cycle the module runs, s (guards a zero or bad `ipo_cycle_s`).
pub const MIN_IPO_CYCLE_S: f64 = 0.0005;
/// Longest interpolation cycle the module runs, s.
pub const MAX_IPO_CYCLE_S: f64 = 1.0;
/// How often a standby serve task checks whether the IPO loop needs a runner.
const IPO_STANDBY_POLL: Duration = Duration::from_millis(100);

/// MD32750 bit 0: position-independent part (SD43900).
pub const TEMP_COMP_ABS: u16 = 1 << 0;
/// MD32750 bit 1: position-dependent part (SD43910, SD43920).
pub const TEMP_COMP_SLOPE: u16 = 1 << 1;
/// MD32750 bit 2: compensation in tool direction (not simulated).
pub const TEMP_COMP_TOOL: u16 = 1 << 2;

/// A refused job: the FB3 status code and the 1-based index of the pair at fault
/// (0 when the fault is not one pair's, e.g. a bad pair count).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("job refused: {} (status {}) at pair {index_1based}", .status.name(), *.status as u16)]
pub struct JobError {
    /// FB3 status code.
    pub status: JobStatus,
    /// 1-based index of the pair at fault; 0 when none.
    pub index_1based: u16,
}

/// Errors of the NC module's server.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum NcError {
    /// The TCP listener failed.
    #[error("NC Modbus TCP server failed ({kind:?}): {message}")]
    Tcp {
        /// Kind of the I/O error.
        kind: io::ErrorKind,
        /// Its message.
        message: String,
    },
}

/// Motion of the simulated axis, advanced by [`NcAxis::ipo_tick`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Motion {
    /// Standing still.
    #[default]
    Stopped,
    /// Moving back and forth between two positions at constant speed.
    Oscillate {
        /// Lower reversal point, mm.
        min_mm: f64,
        /// Upper reversal point, mm.
        max_mm: f64,
        /// Speed, mm/s (> 0).
        speed_mm_per_s: f64,
    },
}

/// Pure state of one NC axis (no I/O, no clock).
#[derive(Debug, Clone, PartialEq)]
pub struct NcAxis {
    /// SD43900 `$SA_TEMP_COMP_ABS_VALUE`: K0, mm.
    pub sd43900_mm: f64,
    /// SD43910 `$SA_TEMP_COMP_SLOPE`: tan(beta), mm/mm.
    pub sd43910: f64,
    /// SD43920 `$SA_TEMP_COMP_REF_POSITION`: P0, mm.
    pub sd43920_mm: f64,
    /// MD32750 `$MA_TEMP_COMP_TYPE` bits.
    pub md32750: u16,
    /// MD32760 `$MA_COMP_ADD_VELO_FACTOR`: compensation velocity as a fraction of
    /// MAX_AX_VELO.
    pub md32760: f64,
    /// MD32000 `$MA_MAX_AX_VELO`, mm/min.
    pub max_ax_velo_mm_per_min: f64,
    /// MD32450 `$MA_BACKLASH`, mm.
    pub md32450_mm: f64,
    /// Compensation acts only once the axis is referenced.
    pub referenced: bool,
    /// Actual position Px, mm.
    pub position_mm: f64,
    /// Temperature compensation currently applied, mm.
    pub applied_comp_mm: f64,
    /// Interpolation cycle, s.
    pub ipo_cycle_s: f64,
    /// Whether a job may write MD32450 (normally machine data, denied).
    pub allow_md32450_write: bool,
    /// Axis motion.
    pub motion: Motion,
    /// Direction of an oscillation: true toward `max_mm`. Public, like every field,
    /// so callers can build an axis with `..NcAxis::default()`.
    pub moving_positive: bool,
}

impl Default for NcAxis {
    fn default() -> Self {
        Self {
            sd43900_mm: 0.0,
            sd43910: 0.0,
            sd43920_mm: 0.0,
            md32750: 0,
            md32760: 0.01,
            max_ax_velo_mm_per_min: 10_000.0,
            md32450_mm: 0.0,
            referenced: false,
            position_mm: 0.0,
            applied_comp_mm: 0.0,
            ipo_cycle_s: 0.004,
            allow_md32450_write: false,
            motion: Motion::Stopped,
            moving_positive: true,
        }
    }
}

impl NcAxis {
    /// Validates every pair, then applies all of them, or none if any is refused.
    /// Pairs apply in order, so a variable written twice keeps the last value.
    pub fn execute_job(&mut self, pairs: &[(u16, f64)]) -> Result<(), JobError> {
        if pairs.is_empty() || pairs.len() > ncmap::MAX_PAIRS {
            return Err(JobError {
                status: JobStatus::InvalidAddress,
                index_1based: 0,
            });
        }
        for (i, &(var_id, value)) in pairs.iter().enumerate() {
            self.check_pair(var_id, value).map_err(|status| JobError {
                status,
                // i < MAX_PAIRS = 8, so this fits.
                index_1based: i as u16 + 1,
            })?;
        }
        for &(var_id, value) in pairs {
            match var_id {
                var::SD43900 => self.sd43900_mm = value,
                var::SD43910 => self.sd43910 = value,
                var::SD43920 => self.sd43920_mm = value,
                var::MD32450 => self.md32450_mm = value,
                // check_pair let nothing else through.
                _ => {}
            }
        }
        Ok(())
    }

    fn check_pair(&self, var_id: u16, value: f64) -> Result<(), JobStatus> {
        let in_range = match var_id {
            var::SD43900 => value.abs() <= SD43900_LIMIT_MM,
            var::SD43910 => value.abs() <= SD43910_LIMIT,
            var::SD43920 => value.abs() <= SD43920_LIMIT_MM,
            var::MD32450 if self.allow_md32450_write => (0.0..=MD32450_LIMIT_MM).contains(&value),
            var::MD32450 | var::MD32750 | var::MD32760 | var::MD32000 => {
                return Err(JobStatus::AccessDenied)
            }
            _ => return Err(JobStatus::ObjectDoesNotExist),
        };
        // NaN fails every comparison above; infinities fail the limits.
        if in_range && value.is_finite() {
            Ok(())
        } else {
            Err(JobStatus::ValueOutOfRange)
        }
    }

    /// Compensation the NC aims at, at the actual position, mm: 0 until referenced;
    /// then SD43900 if MD32750 bit 0, plus SD43910 * (Px - SD43920) if bit 1.
    /// Bit 2 (tool direction) is not simulated.
    pub fn target_comp_mm(&self) -> f64 {
        if !self.referenced {
            return 0.0;
        }
        let mut comp_mm = 0.0;
        if self.md32750 & TEMP_COMP_ABS != 0 {
            comp_mm += self.sd43900_mm;
        }
        if self.md32750 & TEMP_COMP_SLOPE != 0 {
            comp_mm += self.sd43910 * (self.position_mm - self.sd43920_mm);
        }
        comp_mm
    }

    /// Largest change of the applied compensation in one interpolation cycle, mm:
    /// MD32760 x MAX_AX_VELO, per cycle.
    pub fn max_comp_step_mm(&self) -> f64 {
        self.md32760 * self.max_ax_velo_mm_per_min / 60.0 * self.ipo_cycle_s
    }

    /// One interpolation cycle: moves the axis, then slews the applied compensation
    /// toward the target at the new position by at most [`Self::max_comp_step_mm`].
    pub fn ipo_tick(&mut self) {
        self.advance_motion();
        let target_mm = self.target_comp_mm();
        let step_mm = self.max_comp_step_mm().max(0.0);
        let diff_mm = target_mm - self.applied_comp_mm;
        if diff_mm.abs() <= step_mm {
            // Land exactly on the target rather than dithering around it.
            self.applied_comp_mm = target_mm;
        } else if step_mm.is_finite() && diff_mm.is_finite() {
            self.applied_comp_mm += step_mm.copysign(diff_mm);
        }
    }

    fn advance_motion(&mut self) {
        let Motion::Oscillate {
            min_mm,
            max_mm,
            speed_mm_per_s,
        } = self.motion
        else {
            return;
        };
        let step_mm = speed_mm_per_s * self.ipo_cycle_s;
        if !(min_mm <= max_mm && step_mm.is_finite() && step_mm > 0.0) {
            return;
        }
        // Reverse at (or beyond) a reversal point; never jump to the range.
        if self.position_mm >= max_mm {
            self.moving_positive = false;
        } else if self.position_mm <= min_mm {
            self.moving_positive = true;
        }
        self.position_mm = if self.moving_positive {
            (self.position_mm + step_mm).min(max_mm)
        } else {
            (self.position_mm - step_mm).max(min_mm)
        };
    }

    /// Registers of the read-back block, `ncmap::READBACK ..+ READBACK_LEN`; unused
    /// registers read 0.
    pub fn readback_regs(&self) -> [u16; ncmap::READBACK_LEN as usize] {
        let mut regs = [0; ncmap::READBACK_LEN as usize];
        let mut put_f64 = |address: u16, value: f64| {
            let at = usize::from(address - ncmap::READBACK);
            regs[at..at + 4].copy_from_slice(&ncmap::f64_to_regs(value));
        };
        put_f64(ncmap::RB_SD43900, self.sd43900_mm);
        put_f64(ncmap::RB_SD43910, self.sd43910);
        put_f64(ncmap::RB_SD43920, self.sd43920_mm);
        put_f64(ncmap::RB_MD32760, self.md32760);
        put_f64(ncmap::RB_MAX_AX_VELO, self.max_ax_velo_mm_per_min);
        put_f64(ncmap::RB_POSITION, self.position_mm);
        put_f64(ncmap::RB_APPLIED_COMP, self.applied_comp_mm);
        put_f64(ncmap::RB_TARGET_COMP, self.target_comp_mm());
        put_f64(ncmap::RB_MD32450, self.md32450_mm);
        regs[usize::from(ncmap::RB_MD32750 - ncmap::READBACK)] = self.md32750;
        regs[usize::from(ncmap::RB_REFERENCED - ncmap::READBACK)] = u16::from(self.referenced);
        regs
    }
}

/// Fault injected into job execution.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum JobFault {
    /// Jobs finish in the request that raises `REQ`.
    #[default]
    None,
    /// Jobs stay busy forever (the gateway's job timeout). Clearing the fault lets a
    /// stuck job finish (at once for `None`, after the delay for `Delay`).
    NeverFinish,
    /// Jobs stay busy this long, then finish.
    Delay(Duration),
    /// Jobs finish at once with ERROR and this STATUS (`ERROR_INDEX` 0: the refusal
    /// is the module's, not one pair's) and change nothing, however valid they are.
    /// `Refuse(JobStatus::Ok)` gives the inconsistent ERROR = 1 with STATUS = 0.
    Refuse(JobStatus),
}

/// A job latched on the rising edge of `REQ`.
#[derive(Debug, Clone)]
struct LatchedJob {
    job_id: u16,
    /// The decoded pairs, or the error a malformed pair table gives.
    pairs: Result<Vec<(u16, f64)>, JobError>,
    /// When the job finishes; `None` = never (NeverFinish).
    due: Option<Instant>,
}

#[derive(Debug)]
struct ModuleState {
    axis: NcAxis,
    job_regs: [u16; ncmap::JOB_BLOCK_LEN as usize],
    job: Option<LatchedJob>,
    job_fault: JobFault,
    jobs_executed: u64,
    jobs_refused: u64,
    /// Modbus requests answered (with data or an exception).
    requests_served: u64,
    /// When the last job that ended with DONE was applied.
    last_done_at: Option<Instant>,
    /// The full-closed-loop axis behind the servo block.
    servo: ServoSim,
    /// Writable registers of the servo block as last written (SERVO..+SERVO_LEN).
    servo_regs: Vec<u16>,
    /// Machine seconds per tokio second.
    sim_speed: f64,
    /// When the servo simulation was last advanced; `None` before the first request.
    servo_clock: Option<Instant>,
    /// Machine time owed to the simulation but less than one servo cycle, s.
    servo_carry_s: f64,
    /// Set once a move programme ran: `RB_POSITION` then shows the scale position.
    servo_drives_position: bool,
    /// Reads including 136..139 are refused (see `set_documented_only`).
    documented_only: bool,
}

/// Most servo cycles one request advances (guards a huge simulation speed).
const MAX_CYCLES_PER_ADVANCE: f64 = 5_000_000.0;

impl ModuleState {
    /// Advances the servo simulation to `now`.
    fn advance_servo(&mut self, now: Instant) {
        let Some(last) = self.servo_clock.replace(now) else {
            return;
        };
        let cycle_s = self.servo.params().servo_cycle_s;
        let owed_s = now.saturating_duration_since(last).as_secs_f64() * self.sim_speed.max(0.0)
            + self.servo_carry_s;
        let cycles = (owed_s / cycle_s).floor();
        if !(cycles.is_finite() && cycles >= 1.0) {
            self.servo_carry_s = if owed_s.is_finite() { owed_s } else { 0.0 };
            return;
        }
        let run = cycles.min(MAX_CYCLES_PER_ADVANCE);
        self.servo_carry_s = if run < cycles {
            0.0
        } else {
            owed_s - run * cycle_s
        };
        // 0 < run <= MAX_CYCLES_PER_ADVANCE: fits.
        self.servo.run_cycles(run as u64);
        if self.servo_drives_position && self.axis.motion == Motion::Stopped {
            self.axis.position_mm = self.servo.scale_mm();
        }
    }

    fn servo_f64(&self, address: u16) -> f64 {
        let at = usize::from(address - ncmap::SERVO);
        ncmap::regs_to_f64([
            self.servo_regs[at],
            self.servo_regs[at + 1],
            self.servo_regs[at + 2],
            self.servo_regs[at + 3],
        ])
    }

    /// Stores a write to the servo block, then runs `MV_CMD` / `TR_CMD` if written.
    fn servo_write(&mut self, address: u16, words: &[u16]) {
        let at = usize::from(address - ncmap::SERVO);
        self.servo_regs[at..at + words.len()].copy_from_slice(words);
        let end = address + words.len() as u16;
        let covers = |reg: u16| address <= reg && reg < end;
        if covers(ncmap::MV_CMD) {
            let cmd =
                std::mem::take(&mut self.servo_regs[usize::from(ncmap::MV_CMD - ncmap::SERVO)]);
            match cmd {
                1 => {
                    let n = usize::from(
                        self.servo_regs[usize::from(ncmap::MV_NUM_STEPS - ncmap::SERVO)],
                    );
                    let steps: Vec<MoveStep> = if (1..=MAX_STEPS).contains(&n) {
                        (0..n as u16)
                            .map(|i| {
                                let base = ncmap::MV_STEPS + ncmap::MV_STEP_REGS * i;
                                MoveStep {
                                    target_mm: self.servo_f64(base),
                                    feed_mm_per_min: self.servo_f64(base + 4),
                                    dwell_s: self.servo_f64(base + 8),
                                }
                            })
                            .collect()
                    } else {
                        Vec::new()
                    };
                    if self.servo.start_program(&steps).is_ok() {
                        self.servo_drives_position = true;
                    }
                }
                2 => self.servo.abort_program(),
                _ => {}
            }
        }
        if covers(ncmap::TR_CMD) {
            let cmd =
                std::mem::take(&mut self.servo_regs[usize::from(ncmap::TR_CMD - ncmap::SERVO)]);
            match cmd {
                1 => {
                    let trigger = self.servo_regs[usize::from(ncmap::TR_TRIGGER - ncmap::SERVO)];
                    match Trigger::from_u16(trigger) {
                        Some(trigger) => {
                            let cfg = TraceConfig {
                                period_s: self.servo_f64(ncmap::TR_PERIOD_S),
                                record_s: self.servo_f64(ncmap::TR_RECORD_S),
                                trigger,
                                threshold_mm: self.servo_f64(ncmap::TR_THRESHOLD_MM),
                                delay_s: self.servo_f64(ncmap::TR_DELAY_S),
                            };
                            // A refusal shows in TR_STATUS.
                            let _ = self.servo.arm_trace(cfg);
                        }
                        None => self.servo.refuse_trace(SimRefusal::BadTrigger),
                    }
                }
                2 => self.servo.stop_trace(),
                _ => {}
            }
        }
    }

    /// The servo block as read: stored writable registers and live values.
    fn servo_block(&self) -> Vec<u16> {
        let mut regs = self.servo_regs.clone();
        let mut put = |address: u16, words: &[u16]| {
            let at = usize::from(address - ncmap::SERVO);
            regs[at..at + words.len()].copy_from_slice(words);
        };
        let sim = &self.servo;
        let count = u32::try_from(sim.trace().len()).unwrap_or(u32::MAX);
        put(ncmap::MV_STATE, &[sim.program_state() as u16]);
        put(ncmap::MV_STATUS, &[sim.program_status()]);
        put(ncmap::MV_STEP, &[sim.program_step()]);
        put(ncmap::TR_STATE, &[sim.trace_state() as u16]);
        put(ncmap::TR_STATUS, &[sim.trace_status()]);
        put(ncmap::TR_COUNT, &ncmap::u32_to_regs(count));
        put(
            ncmap::TR_MAX_SAMPLES,
            &ncmap::u32_to_regs(crate::axis::MAX_TRACE_SAMPLES as u32),
        );
        put(
            ncmap::TR_TRIGGER_TIME_S,
            &ncmap::f64_to_regs(sim.trace_trigger_time_s()),
        );
        put(
            ncmap::TR_START_TIME_S,
            &ncmap::f64_to_regs(sim.trace_start_time_s()),
        );
        put(ncmap::ENCODER_POS, &ncmap::f64_to_regs(sim.encoder_mm()));
        put(ncmap::SCALE_POS, &ncmap::f64_to_regs(sim.scale_mm()));
        put(ncmap::AXIS_MIN, &ncmap::f64_to_regs(sim.params().min_mm));
        put(ncmap::AXIS_MAX, &ncmap::f64_to_regs(sim.params().max_mm));
        put(ncmap::MACHINE_TIME_S, &ncmap::f64_to_regs(sim.time_s()));
        put(
            ncmap::SERVO_CYCLE_S,
            &ncmap::f64_to_regs(sim.params().servo_cycle_s),
        );
        put(
            ncmap::MV_START_TIME_S,
            &ncmap::f64_to_regs(sim.program_start_s()),
        );
        put(
            ncmap::MV_END_TIME_S,
            &ncmap::f64_to_regs(sim.program_end_s()),
        );
        regs
    }

    /// The trace window for the current page.
    fn trace_window(&self) -> Vec<u16> {
        let page = usize::from(self.servo_regs[usize::from(ncmap::TR_PAGE - ncmap::SERVO)]);
        let per_page = usize::from(ncmap::TR_PAGE_SAMPLES);
        let trace = self.servo.trace();
        let mut regs = Vec::with_capacity(usize::from(ncmap::TR_WINDOW_LEN));
        for k in 0..per_page {
            let (enc, scale) = trace
                .get(page * per_page + k)
                .copied()
                .unwrap_or((f64::NAN, f64::NAN));
            regs.extend_from_slice(&ncmap::f64_to_regs(enc));
            regs.extend_from_slice(&ncmap::f64_to_regs(scale));
        }
        regs
    }

    fn job_state(&self) -> JobState {
        JobState::from_u16(self.job_regs[usize::from(ncmap::STATE)]).unwrap_or(JobState::Idle)
    }

    fn set(&mut self, address: u16, value: u16) {
        self.job_regs[usize::from(address)] = value;
    }

    fn due_after_now(&self, now: Instant) -> Option<Instant> {
        match self.job_fault {
            JobFault::None | JobFault::Refuse(_) => Some(now),
            JobFault::NeverFinish => None,
            JobFault::Delay(delay) => Some(now + delay),
        }
    }

    /// Latches the job from the parameter registers and goes busy.
    fn latch(&mut self, now: Instant) {
        let regs = &self.job_regs;
        let num_pairs = usize::from(regs[usize::from(ncmap::NUM_PAIRS)]);
        let pairs = if (1..=ncmap::MAX_PAIRS).contains(&num_pairs) {
            Ok((0..num_pairs)
                .map(|i| {
                    let at = usize::from(ncmap::PAIRS) + i * usize::from(ncmap::PAIR_REGS);
                    let value = ncmap::regs_to_f64([
                        regs[at + 1],
                        regs[at + 2],
                        regs[at + 3],
                        regs[at + 4],
                    ]);
                    (regs[at], value)
                })
                .collect())
        } else {
            Err(JobError {
                status: JobStatus::InvalidAddress,
                index_1based: 0,
            })
        };
        self.job = Some(LatchedJob {
            job_id: regs[usize::from(ncmap::JOB_ID)],
            pairs,
            due: self.due_after_now(now),
        });
        self.set(ncmap::STATE, JobState::Busy as u16);
        for address in [ncmap::DONE, ncmap::ERROR, ncmap::STATUS, ncmap::ERROR_INDEX] {
            self.set(address, 0);
        }
    }

    /// Finishes the latched job if it is due.
    fn poll_job(&mut self, now: Instant) {
        let Some(job) = &self.job else { return };
        if job.due.is_none_or(|due| due > now) {
            return;
        }
        let Some(job) = self.job.take() else { return };
        let result = match self.job_fault {
            JobFault::Refuse(status) => Err(JobError {
                status,
                index_1based: 0,
            }),
            _ => job.pairs.and_then(|pairs| self.axis.execute_job(&pairs)),
        };
        self.jobs_executed += 1;
        match result {
            Ok(()) => {
                tracing::debug!(job_id = job.job_id, "NC job done");
                self.last_done_at = Some(now);
                self.set(ncmap::STATE, JobState::Done as u16);
                self.set(ncmap::DONE, 1);
            }
            Err(err) => {
                tracing::debug!(job_id = job.job_id, %err, "NC job refused");
                self.jobs_refused += 1;
                self.set(ncmap::STATE, JobState::Error as u16);
                self.set(ncmap::ERROR, 1);
                self.set(ncmap::STATUS, err.status as u16);
                self.set(ncmap::ERROR_INDEX, err.index_1based);
            }
        }
        self.set(ncmap::JOB_ID_DONE, job.job_id);
    }

    /// Stores a write to the job block and runs the handshake on `REQ`.
    fn write(&mut self, address: u16, words: &[u16], now: Instant) -> Result<(), ExceptionCode> {
        if words.is_empty() || words.len() > 123 {
            return Err(ExceptionCode::IllegalDataValue);
        }
        let end = u32::from(address) + words.len() as u32;
        let inside = |from: u16, to: u16| address >= from && end <= u32::from(to);
        if inside(ncmap::MV_CMD, ncmap::MV_WRITABLE_END)
            || inside(ncmap::TR_WRITABLE_START, ncmap::TR_WRITABLE_END)
        {
            self.servo_write(address, words);
            return Ok(());
        }
        let only_req = address == ncmap::REQ && end == u32::from(ncmap::REQ) + 1;
        let in_params = address >= ncmap::JOB_ID && end <= u32::from(ncmap::JOB_ID_DONE);
        if !(only_req || in_params) {
            return Err(ExceptionCode::IllegalDataAddress);
        }
        self.poll_job(now);
        if only_req {
            let req = words[0];
            let old_req = self.job_regs[usize::from(ncmap::REQ)];
            self.set(ncmap::REQ, req);
            match self.job_state() {
                JobState::Idle if old_req == 0 && req != 0 => {
                    self.latch(now);
                    self.poll_job(now);
                }
                JobState::Done | JobState::Error if req == 0 => {
                    self.set(ncmap::STATE, JobState::Idle as u16);
                    for address in [ncmap::DONE, ncmap::ERROR, ncmap::STATUS, ncmap::ERROR_INDEX] {
                        self.set(address, 0);
                    }
                }
                _ => {}
            }
        } else {
            let at = usize::from(address);
            self.job_regs[at..at + words.len()].copy_from_slice(words);
        }
        Ok(())
    }

    fn read(
        &mut self,
        address: u16,
        quantity: u16,
        now: Instant,
    ) -> Result<Vec<u16>, ExceptionCode> {
        if quantity == 0 || quantity > 125 {
            return Err(ExceptionCode::IllegalDataValue);
        }
        self.poll_job(now);
        let start = usize::from(address);
        let end = start + usize::from(quantity);
        let job_len = usize::from(ncmap::JOB_BLOCK_LEN);
        let rb_start = usize::from(ncmap::READBACK);
        let rb_end = rb_start + usize::from(ncmap::READBACK_LEN);
        let gap = usize::from(ncmap::READBACK + ncmap::RB_VALUES_LEN)..usize::from(ncmap::RB_FLAGS);
        if self.documented_only && start < gap.end && gap.start < end {
            Err(ExceptionCode::IllegalDataAddress)
        } else if end <= job_len {
            Ok(self.job_regs[start..end].to_vec())
        } else if start >= rb_start && end <= rb_end {
            Ok(self.axis.readback_regs()[start - rb_start..end - rb_start].to_vec())
        } else if start >= usize::from(ncmap::SERVO)
            && end <= usize::from(ncmap::SERVO + ncmap::SERVO_LEN)
        {
            let base = usize::from(ncmap::SERVO);
            Ok(self.servo_block()[start - base..end - base].to_vec())
        } else if start >= usize::from(ncmap::TR_WINDOW)
            && end <= usize::from(ncmap::TR_WINDOW + ncmap::TR_WINDOW_LEN)
        {
            let base = usize::from(ncmap::TR_WINDOW);
            Ok(self.trace_window()[start - base..end - base].to_vec())
        } else {
            Err(ExceptionCode::IllegalDataAddress)
        }
    }

    fn reply(&mut self, request: &Request<'_>, now: Instant) -> Result<Response, ExceptionCode> {
        self.requests_served += 1;
        self.advance_servo(now);
        match request {
            Request::ReadHoldingRegisters(address, quantity) => self
                .read(*address, *quantity, now)
                .map(Response::ReadHoldingRegisters),
            Request::WriteSingleRegister(address, word) => self
                .write(*address, &[*word], now)
                .map(|()| Response::WriteSingleRegister(*address, *word)),
            Request::WriteMultipleRegisters(address, words) => {
                self.write(*address, words, now)?;
                // write() refused more than 123 words, so the count fits.
                Ok(Response::WriteMultipleRegisters(
                    *address,
                    words.len() as u16,
                ))
            }
            _ => Err(ExceptionCode::IllegalFunction),
        }
    }
}

#[derive(Debug)]
struct Shared {
    state: Mutex<ModuleState>,
    /// Set while one serve task runs the interpolation loop, so serving the module on
    /// two listeners does not run the axis twice as fast.
    ipo_running: AtomicBool,
}

/// Cloneable handle of a simulated NC axis module; clones share one module.
#[derive(Debug, Clone)]
pub struct NcAxisModule {
    shared: Arc<Shared>,
}

impl NcAxisModule {
    /// A module around `axis`, idle, with no job fault.
    pub fn new(axis: NcAxis) -> Self {
        let state = ModuleState {
            axis,
            job_regs: [0; ncmap::JOB_BLOCK_LEN as usize],
            job: None,
            job_fault: JobFault::None,
            jobs_executed: 0,
            requests_served: 0,
            jobs_refused: 0,
            last_done_at: None,
            servo: ServoSim::new(AxisParams::default()),
            servo_regs: vec![0; usize::from(ncmap::SERVO_LEN)],
            sim_speed: 1.0,
            servo_clock: None,
            servo_carry_s: 0.0,
            servo_drives_position: false,
            documented_only: false,
        };
        Self {
            shared: Arc::new(Shared {
                state: Mutex::new(state),
                ipo_running: AtomicBool::new(false),
            }),
        }
    }

    fn lock(&self) -> MutexGuard<'_, ModuleState> {
        // Every update keeps the state consistent, so a panicked holder leaves
        // nothing half-done worth refusing over.
        self.shared
            .state
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    }

    /// Snapshot of the axis state.
    pub fn state(&self) -> NcAxis {
        self.lock().axis.clone()
    }

    /// Runs `f` on the axis state (e.g. to reference the axis or set MD32750).
    pub fn with_state<R>(&self, f: impl FnOnce(&mut NcAxis) -> R) -> R {
        f(&mut self.lock().axis)
    }

    /// Replaces the full-closed-loop axis behind the servo block (programme and trace
    /// start over).
    pub fn set_servo(&self, params: AxisParams) {
        let mut state = self.lock();
        state.servo = ServoSim::new(params);
        state.servo_carry_s = 0.0;
    }

    /// Sets the simulation speed of the servo axis: machine seconds per second of
    /// tokio time (1 = real time; tests and dry-runs use e.g. 1000).
    pub fn set_sim_speed(&self, machine_s_per_s: f64) {
        let mut state = self.lock();
        state.advance_servo(Instant::now());
        state.sim_speed = if machine_s_per_s.is_finite() {
            machine_s_per_s.max(0.0)
        } else {
            0.0
        };
    }

    /// Runs `f` on the servo axis, advanced to now.
    pub fn with_servo<R>(&self, f: impl FnOnce(&mut ServoSim) -> R) -> R {
        let mut state = self.lock();
        state.advance_servo(Instant::now());
        f(&mut state.servo)
    }

    /// Serves exactly the documented read-back registers: a read that includes one of
    /// 136..139 (not in the map) is answered with exception 2, as a module written
    /// from the map alone does. Off by default (reads of 100..141 in one request work).
    pub fn set_documented_only(&self, on: bool) {
        self.lock().documented_only = on;
    }

    /// `STATE` of the job block.
    pub fn job_state(&self) -> JobState {
        let mut state = self.lock();
        state.poll_job(Instant::now());
        state.job_state()
    }

    /// Sets the job fault. A job stuck under `NeverFinish` becomes due according to
    /// the new fault, counted from now.
    pub fn set_job_fault(&self, fault: JobFault) {
        let now = Instant::now();
        let mut state = self.lock();
        state.job_fault = fault;
        let due = state.due_after_now(now);
        if let Some(job) = &mut state.job {
            if job.due.is_none() {
                job.due = due;
            }
        }
        state.poll_job(now);
    }

    /// Jobs that ended, with DONE or with ERROR.
    pub fn jobs_executed(&self) -> u64 {
        self.lock().jobs_executed
    }

    /// Modbus requests answered, with data or an exception: what a client costs the
    /// module.
    pub fn requests_served(&self) -> u64 {
        self.lock().requests_served
    }

    /// Jobs that ended with ERROR.
    pub fn jobs_refused(&self) -> u64 {
        self.lock().jobs_refused
    }

    /// SD43900 (mm) and when the last job that ended with DONE was applied, read
    /// together: a latency measurement gets the instant a value took effect without
    /// polling as finely as it wants to resolve.
    pub fn sd43900_and_last_done(&self) -> (f64, Option<Instant>) {
        let state = self.lock();
        (state.axis.sd43900_mm, state.last_done_at)
    }

    /// Serves this module on a fresh loopback port until the returned token is
    /// cancelled; returns the address (`127.0.0.1:PORT`).
    pub async fn serve_loopback(&self) -> io::Result<(String, CancellationToken)> {
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let address = listener.local_addr()?.to_string();
        let shutdown = CancellationToken::new();
        tokio::spawn(self.clone().serve_tcp(listener, shutdown.clone()));
        Ok((address, shutdown))
    }

    /// Serves the register map over Modbus TCP on `listener`, for any unit id, and runs
    /// the interpolation loop, until `shutdown` is cancelled.
    pub async fn serve_tcp(
        self,
        listener: TcpListener,
        shutdown: CancellationToken,
    ) -> Result<(), NcError> {
        tracing::debug!(addr = ?listener.local_addr().ok(), "NC axis module serving Modbus TCP");
        let server = tokio_modbus::server::tcp::Server::new(listener);
        let on_connected = |stream: TcpStream, _peer| {
            let service = NcService {
                module: self.clone(),
            };
            // Replies are small and latency matters more than throughput.
            let _ = stream.set_nodelay(true);
            async move { Ok(Some((service, stream))) }
        };
        let on_process_error = |err: io::Error| {
            tracing::debug!(%err, "NC connection ended with an error");
        };
        tokio::select! {
            res = server.serve(&on_connected, on_process_error) => res.map_err(|e| NcError::Tcp {
                kind: e.kind(),
                message: e.to_string(),
            }),
            () = self.run_ipo() => Ok(()),
            () = shutdown.cancelled() => Ok(()),
        }
    }

    /// Calls [`NcAxis::ipo_tick`] every `ipo_cycle_s` of tokio time, forever. Only one
    /// serve task of a module runs the loop; the others stand by and take over when
    /// it stops.
    async fn run_ipo(&self) {
        loop {
            if !self.shared.ipo_running.swap(true, Ordering::AcqRel) {
                let _guard = IpoGuard(&self.shared.ipo_running);
                self.ipo_loop().await;
            }
            tokio::time::sleep(IPO_STANDBY_POLL).await;
        }
    }

    async fn ipo_loop(&self) {
        let mut next = Instant::now();
        loop {
            let cycle_s = self.lock().axis.ipo_cycle_s;
            // NaN falls to the minimum; a huge value must not overflow the Duration.
            let cycle_s = if cycle_s.is_nan() {
                MIN_IPO_CYCLE_S
            } else {
                cycle_s.clamp(MIN_IPO_CYCLE_S, MAX_IPO_CYCLE_S)
            };
            // Absolute deadlines: a late wake-up catches up instead of slowing the axis.
            next += Duration::from_secs_f64(cycle_s);
            tokio::time::sleep_until(next).await;
            let mut state = self.lock();
            state.axis.ipo_tick();
            state.poll_job(Instant::now());
        }
    }
}

/// Clears the IPO flag when the loop's future is dropped.
struct IpoGuard<'a>(&'a AtomicBool);

impl Drop for IpoGuard<'_> {
    fn drop(&mut self) {
        self.0.store(false, Ordering::Release);
    }
}

#[derive(Debug)]
struct NcService {
    module: NcAxisModule,
}

impl Service for NcService {
    type Request = Request<'static>;
    type Response = Response;
    type Exception = ExceptionCode;
    type Future = Pin<Box<dyn Future<Output = Result<Response, ExceptionCode>> + Send>>;

    fn call(&self, request: Self::Request) -> Self::Future {
        let reply = self.module.lock().reply(&request, Instant::now());
        Box::pin(std::future::ready(reply))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The seed's worked values: SD43900 = 0.1, SD43920 = 10, SD43910 = 0.0001.
    fn worked_axis(md32750: u16) -> NcAxis {
        let mut axis = NcAxis {
            md32750,
            referenced: true,
            ..NcAxis::default()
        };
        axis.execute_job(&[
            (var::SD43900, 0.1),
            (var::SD43920, 10.0),
            (var::SD43910, 0.0001),
        ])
        .unwrap();
        axis
    }

    fn settle(axis: &mut NcAxis) {
        // 0.104 mm at 0.00667 mm per cycle needs 16 cycles; run plenty.
        for _ in 0..1000 {
            axis.ipo_tick();
        }
    }

    fn check_worked(md32750: u16, expected: &[(f64, f64)]) {
        for &(x_mm, comp_mm) in expected {
            let mut axis = worked_axis(md32750);
            axis.position_mm = x_mm;
            assert!(
                (axis.target_comp_mm() - comp_mm).abs() < 1e-12,
                "MD32750={md32750} X={x_mm}: target {}",
                axis.target_comp_mm()
            );
            settle(&mut axis);
            assert!(
                (axis.applied_comp_mm - comp_mm).abs() < 1e-12,
                "MD32750={md32750} X={x_mm}: applied {}",
                axis.applied_comp_mm
            );
        }
    }

    #[test]
    fn worked_experiment_md32750_1() {
        check_worked(1, &[(0.0, 0.1), (10.0, 0.1), (50.0, 0.1), (-1234.5, 0.1)]);
    }

    #[test]
    fn worked_experiment_md32750_2() {
        check_worked(2, &[(0.0, -0.001), (10.0, 0.0), (50.0, 0.004)]);
    }

    #[test]
    fn worked_experiment_md32750_3() {
        check_worked(3, &[(0.0, 0.099), (10.0, 0.1), (50.0, 0.104)]);
    }

    #[test]
    fn no_compensation_until_referenced_or_without_bits() {
        let mut axis = worked_axis(3);
        axis.referenced = false;
        axis.position_mm = 50.0;
        assert_eq!(axis.target_comp_mm(), 0.0);
        settle(&mut axis);
        assert_eq!(axis.applied_comp_mm, 0.0);
        let mut axis = worked_axis(0);
        axis.position_mm = 50.0;
        assert_eq!(axis.target_comp_mm(), 0.0);
        // Bit 2 alone (tool direction) is out of scope: nothing on this axis.
        let axis = worked_axis(TEMP_COMP_TOOL);
        assert_eq!(axis.target_comp_mm(), 0.0);
    }

    #[test]
    fn rate_limit_per_cycle_is_respected_and_reached_in_the_expected_cycles() {
        let mut axis = worked_axis(3);
        // 0.01 x 6000 mm/min = 1 mm/s = 0.004 mm per 4 ms cycle.
        axis.max_ax_velo_mm_per_min = 6000.0;
        assert!((axis.max_comp_step_mm() - 0.004).abs() < 1e-15);
        axis.position_mm = 0.0; // target 0.099 mm: 24.75 steps -> 25 cycles
        let mut previous_mm = axis.applied_comp_mm;
        for cycle in 1..=24 {
            axis.ipo_tick();
            let step_mm = axis.applied_comp_mm - previous_mm;
            assert!(
                (step_mm - 0.004).abs() < 1e-12,
                "cycle {cycle}: step {step_mm}"
            );
            previous_mm = axis.applied_comp_mm;
        }
        assert!((axis.applied_comp_mm - 0.096).abs() < 1e-12);
        assert!(axis.applied_comp_mm < axis.target_comp_mm());
        axis.ipo_tick();
        assert_eq!(
            axis.applied_comp_mm,
            axis.target_comp_mm(),
            "cycle 25 lands"
        );
        assert!((axis.applied_comp_mm - 0.099).abs() < 1e-12);
        // And back down to the negative value at the same rate.
        axis.execute_job(&[(var::SD43900, -0.1005)]).unwrap(); // target -0.1015
        let mut cycles = 0;
        while axis.applied_comp_mm != axis.target_comp_mm() {
            let before_mm = axis.applied_comp_mm;
            axis.ipo_tick();
            assert!((axis.applied_comp_mm - before_mm).abs() <= 0.004 + 1e-15);
            cycles += 1;
            assert!(cycles < 1000);
        }
        assert_eq!(cycles, 51, "0.2005 mm at 0.004 mm per cycle");
    }

    #[test]
    fn oscillation_moves_the_axis_and_the_target_follows() {
        let mut axis = worked_axis(2);
        axis.motion = Motion::Oscillate {
            min_mm: 0.0,
            max_mm: 1.0,
            speed_mm_per_s: 100.0, // 0.4 mm per cycle
        };
        let positions: Vec<f64> = (0..6)
            .map(|_| {
                axis.ipo_tick();
                axis.position_mm
            })
            .collect();
        let expected = [0.4, 0.8, 1.0, 0.6, 0.2, 0.0];
        for (p, e) in positions.iter().zip(expected) {
            assert!((p - e).abs() < 1e-12, "{positions:?}");
        }
        assert!((axis.target_comp_mm() - 0.0001 * (0.0 - 10.0)).abs() < 1e-15);
    }

    #[test]
    fn bad_pairs_change_nothing_and_report_index_and_code() {
        type Case = (&'static [(u16, f64)], JobStatus, u16);
        let cases: &[Case] = &[
            (&[], JobStatus::InvalidAddress, 0),
            (&[(var::SD43900, 0.0); 9], JobStatus::InvalidAddress, 0),
            (
                &[(var::SD43900, 0.2), (12345, 1.0)],
                JobStatus::ObjectDoesNotExist,
                2,
            ),
            (
                &[(var::SD43900, 0.2), (var::MD32750, 3.0)],
                JobStatus::AccessDenied,
                2,
            ),
            (&[(var::MD32760, 0.02)], JobStatus::AccessDenied, 1),
            (
                &[(var::SD43900, 0.2), (var::MD32000, 1.0)],
                JobStatus::AccessDenied,
                2,
            ),
            (&[(var::MD32450, 0.01)], JobStatus::AccessDenied, 1),
            (&[(var::SD43900, 10.5)], JobStatus::ValueOutOfRange, 1),
            (
                &[(var::SD43900, 0.2), (var::SD43910, -0.11)],
                JobStatus::ValueOutOfRange,
                2,
            ),
            (
                &[
                    (var::SD43900, 0.2),
                    (var::SD43910, 0.0),
                    (var::SD43920, 1e6),
                ],
                JobStatus::ValueOutOfRange,
                3,
            ),
            (&[(var::SD43900, f64::NAN)], JobStatus::ValueOutOfRange, 1),
            (
                &[(var::SD43920, f64::INFINITY)],
                JobStatus::ValueOutOfRange,
                1,
            ),
        ];
        for (pairs, status, index_1based) in cases {
            let mut axis = worked_axis(3);
            let before = axis.clone();
            assert_eq!(
                axis.execute_job(pairs),
                Err(JobError {
                    status: *status,
                    index_1based: *index_1based
                }),
                "{pairs:?}"
            );
            assert_eq!(axis, before, "all-or-none: {pairs:?}");
        }
    }

    #[test]
    fn md32450_only_when_allowed_and_in_range() {
        let mut axis = NcAxis {
            allow_md32450_write: true,
            ..NcAxis::default()
        };
        assert_eq!(
            axis.execute_job(&[(var::MD32450, -0.001)]),
            Err(JobError {
                status: JobStatus::ValueOutOfRange,
                index_1based: 1
            })
        );
        axis.execute_job(&[(var::MD32450, 0.012), (var::SD43900, 0.05)])
            .unwrap();
        assert_eq!(axis.md32450_mm, 0.012);
        assert_eq!(axis.sd43900_mm, 0.05);
    }

    #[test]
    fn readback_regs_decode_bit_exact() {
        let mut axis = worked_axis(3);
        axis.position_mm = 50.0;
        let regs = axis.readback_regs();
        let f = |address: u16| {
            let at = usize::from(address - ncmap::READBACK);
            ncmap::regs_to_f64([regs[at], regs[at + 1], regs[at + 2], regs[at + 3]])
        };
        assert_eq!(f(ncmap::RB_SD43900).to_bits(), 0.1_f64.to_bits());
        assert_eq!(f(ncmap::RB_SD43910).to_bits(), 0.0001_f64.to_bits());
        assert_eq!(f(ncmap::RB_SD43920), 10.0);
        assert_eq!(f(ncmap::RB_MD32760), 0.01);
        assert_eq!(f(ncmap::RB_MAX_AX_VELO), 10_000.0);
        assert_eq!(f(ncmap::RB_POSITION), 50.0);
        assert_eq!(f(ncmap::RB_TARGET_COMP), axis.target_comp_mm());
        assert_eq!(regs[usize::from(ncmap::RB_MD32750 - ncmap::READBACK)], 3);
        assert_eq!(regs[usize::from(ncmap::RB_REFERENCED - ncmap::READBACK)], 1);
    }
}
