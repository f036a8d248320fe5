//! Simulated full-closed-loop feed axis with backlash, drive-train elasticity and a
//! two-channel servo trace.
//!
//! Pure and deterministic for a seed: no I/O, no clock. [`ServoSim::step`] advances
//! one servo cycle, so a 20 s test programme takes a few milliseconds of CPU.
//!
//! The drive train, per servo cycle `dt`:
//!
//! ```text
//!  interpolator --x_cmd--> position loop (closed on the SCALE, no feedforward)
//!                                   v_motor = Kv * (x_cmd - table)
//!                                   (or on the encoder: Feedback::Encoder)
//!  motor  m  (motor encoder)        m += v_motor * dt
//!  nut    n  backlash:              |m - n| <= backlash / 2   (the nut stands still
//!                                   while the motor crosses the gap)
//!  table  t  (linear scale)         spring + viscous friction: dt/dt = (n - t) / tau
//!                                   -> table lag = friction / stiffness = v * tau while
//!                                   moving; it relaxes to 0 at standstill
//! ```
//!
//! The loop is closed on the scale, so the table settles on the target and the motor
//! ends half the gap beyond it, on the side it came from: this is the lost motion the
//! encoder-vs-scale method measures. Both measured channels carry Gaussian noise; the
//! loop itself runs on the true table position.
//!
//! Moves follow a trapezoidal velocity profile at the programmed feed and the axis
//! acceleration; a dwell starts when the interpolator reaches the target.

use crate::SimRng;
use compgate_ncproto::servo::{MoveStep, TraceConfig, Trigger, MAX_STEPS};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

/// Most samples one trace holds (both channels).
pub const MAX_TRACE_SAMPLES: usize = 200_000;

/// Physical parameters of the simulated axis.
#[derive(Debug, Clone, PartialEq)]
pub struct AxisParams {
    /// Lost motion at each reversal (backlash), mm.
    pub backlash_mm: f64,
    /// Drive-train elasticity: time constant of the spring + viscous friction
    /// between nut and table, s. The table lags `v * tau` while moving.
    pub elastic_tau_s: f64,
    /// Standard deviation of the motor encoder's measurement noise, mm.
    pub encoder_noise_mm: f64,
    /// Standard deviation of the linear scale's measurement noise, mm.
    pub scale_noise_mm: f64,
    /// Position loop gain Kv, 1/s. Below `kv_per_s * elastic_tau_s = 0.25` the loop is
    /// overdamped; above it the table overshoots the target and the motor creeps back
    /// across the gap during the dwell (what the backlash test must refuse).
    pub kv_per_s: f64,
    /// Axis acceleration, mm/s^2.
    pub accel_mm_per_s2: f64,
    /// Lower software limit, mm.
    pub min_mm: f64,
    /// Upper software limit, mm.
    pub max_mm: f64,
    /// Highest programmable feed (MD32000), mm/min.
    pub max_feed_mm_per_min: f64,
    /// Servo (position controller) cycle, s.
    pub servo_cycle_s: f64,
    /// Seed of the measurement noise.
    pub seed: u64,
    /// Position of motor and table at start, mm.
    pub start_mm: f64,
    /// Which measuring system closes the position loop.
    pub feedback: Feedback,
}

/// The measuring system the position loop is closed on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Feedback {
    /// Full closed loop: the linear scale. The table settles on the target and the
    /// backlash shows only between encoder and scale.
    #[default]
    Scale,
    /// Semi-closed loop: the motor encoder. The motor settles on the target and the
    /// table stops half the gap short of it, on the side it came from: the reversal
    /// error a laser interferometer sees in an ISO 230-2 test.
    Encoder,
}

impl Default for AxisParams {
    fn default() -> Self {
        Self {
            backlash_mm: 0.02,
            elastic_tau_s: 0.008,
            encoder_noise_mm: 0.000_3,
            scale_noise_mm: 0.000_3,
            kv_per_s: 20.0,
            accel_mm_per_s2: 1000.0,
            min_mm: -10.0,
            max_mm: 1000.0,
            max_feed_mm_per_min: 10_000.0,
            servo_cycle_s: 0.001,
            seed: 1,
            start_mm: 0.0,
            feedback: Feedback::Scale,
        }
    }
}

/// Why a programme or trace configuration was refused. The discriminant is the
/// status register value (see `ncmap`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum SimRefusal {
    /// 1: step count outside 1..=8.
    #[error("step count outside 1..={MAX_STEPS}")]
    BadStepCount = 1,
    /// 2: a target lies outside the software limits (or is not finite).
    #[error("target outside the software limits")]
    OutOfLimits = 2,
    /// 3: a feed is not in (0, MD32000].
    #[error("feed outside (0, max feed]")]
    BadFeed = 3,
    /// 4: a dwell is negative, not finite or longer than an hour.
    #[error("dwell outside 0..=3600 s")]
    BadDwell = 4,
    /// 5: a programme is running.
    #[error("a programme is running")]
    Busy = 5,
    /// 6: trace sample period not a whole number (1..=1000) of servo cycles.
    #[error("trace period is not 1..=1000 servo cycles")]
    BadPeriod = 6,
    /// 7: record time not positive, or more samples than the buffer holds.
    #[error("trace record time outside the buffer")]
    BadRecordTime = 7,
    /// 8: post-trigger delay negative or not finite.
    #[error("bad post-trigger delay")]
    BadDelay = 8,
    /// 9: unknown trigger condition, or a threshold that is not finite.
    #[error("bad trigger")]
    BadTrigger = 9,
}

/// Servo trace state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum TraceState {
    /// 0: not armed (never armed, or stopped).
    #[default]
    Idle = 0,
    /// 1: armed, waiting for the trigger.
    Armed = 1,
    /// 2: triggered, waiting out the post-trigger delay.
    Delay = 2,
    /// 3: recording.
    Recording = 3,
    /// 4: record time reached; samples ready.
    Complete = 4,
}

/// Move programme state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ProgramState {
    /// 0: no programme.
    #[default]
    Idle = 0,
    /// 1: running.
    Running = 1,
    /// 2: finished.
    Done = 2,
    /// 3: refused (see the status) or aborted.
    Refused = 3,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Phase {
    Moving { from_mm: f64, elapsed_s: f64 },
    Dwelling { left_s: f64 },
}

#[derive(Debug, Clone, PartialEq)]
struct Running {
    steps: Vec<MoveStep>,
    index: usize,
    phase: Phase,
}

/// Position and velocity at `t` of a trapezoidal move over `dist` (>= 0) at cruise
/// speed `v` and acceleration `a`; `None` once the move is over.
fn trapezoid(dist: f64, v: f64, a: f64, t: f64) -> Option<(f64, f64)> {
    if dist <= 0.0 {
        return None;
    }
    // Triangle when the cruise speed cannot be reached.
    let v = v.min((dist * a).sqrt());
    let t_acc = v / a;
    let d_acc = 0.5 * a * t_acc * t_acc;
    let t_cruise = (dist - 2.0 * d_acc) / v;
    let total = 2.0 * t_acc + t_cruise;
    if t >= total {
        None
    } else if t < t_acc {
        Some((0.5 * a * t * t, a * t))
    } else if t < t_acc + t_cruise {
        Some((d_acc + v * (t - t_acc), v))
    } else {
        let r = total - t;
        Some((dist - 0.5 * a * r * r, a * r))
    }
}

/// Duration of a trapezoidal move, s.
pub fn move_time_s(dist_mm: f64, feed_mm_per_min: f64, accel_mm_per_s2: f64) -> f64 {
    let dist = dist_mm.abs();
    if dist <= 0.0 {
        return 0.0;
    }
    let v = (feed_mm_per_min / 60.0).min((dist * accel_mm_per_s2).sqrt());
    dist / v + v / accel_mm_per_s2
}

/// The simulated axis with its interpolator, move programme and servo trace.
#[derive(Debug, Clone)]
pub struct ServoSim {
    params: AxisParams,
    rng: SimRng,
    noise_enc: Option<Normal<f64>>,
    noise_scale: Option<Normal<f64>>,
    /// Machine time, s.
    time_s: f64,
    /// Interpolator output.
    cmd_mm: f64,
    motor_mm: f64,
    nut_mm: f64,
    table_mm: f64,
    /// Last measured values.
    enc_meas_mm: f64,
    scale_meas_mm: f64,
    program: Option<Running>,
    program_state: ProgramState,
    program_status: u16,
    program_start_s: f64,
    program_end_s: f64,
    trace_cfg: TraceConfig,
    trace_state: TraceState,
    trace_status: u16,
    trace_countdown: u64,
    trace_target: usize,
    trace_period_cycles: u64,
    trace_trigger_time_s: f64,
    trace_start_time_s: f64,
    trace: Vec<(f64, f64)>,
    /// The position command at each trace sample, mm.
    trace_command: Vec<f64>,
}

impl ServoSim {
    /// An axis standing at `params.start_mm`, no programme, trace idle.
    pub fn new(params: AxisParams) -> Self {
        let normal = |sd: f64| Normal::new(0.0, sd).ok().filter(|_| sd > 0.0);
        let start = params.start_mm;
        let mut sim = Self {
            rng: SimRng::seed_from_u64(params.seed),
            noise_enc: normal(params.encoder_noise_mm),
            noise_scale: normal(params.scale_noise_mm),
            params,
            time_s: 0.0,
            cmd_mm: start,
            motor_mm: start,
            nut_mm: start,
            table_mm: start,
            enc_meas_mm: start,
            scale_meas_mm: start,
            program: None,
            program_state: ProgramState::Idle,
            program_status: 0,
            program_start_s: 0.0,
            program_end_s: 0.0,
            trace_cfg: TraceConfig::default(),
            trace_state: TraceState::Idle,
            trace_status: 0,
            trace_countdown: 0,
            trace_target: 0,
            trace_period_cycles: 1,
            trace_trigger_time_s: 0.0,
            trace_start_time_s: 0.0,
            trace: Vec::new(),
            trace_command: Vec::new(),
        };
        sim.measure();
        sim
    }

    /// The axis parameters.
    pub fn params(&self) -> &AxisParams {
        &self.params
    }

    /// Machine time since start, s.
    pub fn time_s(&self) -> f64 {
        self.time_s
    }

    /// Measured motor encoder actual position, mm.
    pub fn encoder_mm(&self) -> f64 {
        self.enc_meas_mm
    }

    /// Measured linear scale actual position, mm.
    pub fn scale_mm(&self) -> f64 {
        self.scale_meas_mm
    }

    /// True table position (no noise), mm.
    pub fn table_true_mm(&self) -> f64 {
        self.table_mm
    }

    /// True motor position (no noise), mm.
    pub fn motor_true_mm(&self) -> f64 {
        self.motor_mm
    }

    /// Programme state.
    pub fn program_state(&self) -> ProgramState {
        self.program_state
    }

    /// Status of the last programme command (0 ok, else a [`SimRefusal`] value).
    pub fn program_status(&self) -> u16 {
        self.program_status
    }

    /// 1-based index of the step running, 0 when none.
    pub fn program_step(&self) -> u16 {
        self.program
            .as_ref()
            .map_or(0, |r| u16::try_from(r.index + 1).unwrap_or(u16::MAX))
    }

    /// Machine time the last programme started, s.
    pub fn program_start_s(&self) -> f64 {
        self.program_start_s
    }

    /// Machine time the last programme ended, s; NaN while it runs.
    pub fn program_end_s(&self) -> f64 {
        self.program_end_s
    }

    /// Trace state.
    pub fn trace_state(&self) -> TraceState {
        self.trace_state
    }

    /// Status of the last arm command (0 ok, else a [`SimRefusal`] value).
    pub fn trace_status(&self) -> u16 {
        self.trace_status
    }

    /// The trace configuration last armed.
    pub fn trace_config(&self) -> TraceConfig {
        self.trace_cfg
    }

    /// Recorded samples: (encoder mm, scale mm).
    pub fn trace(&self) -> &[(f64, f64)] {
        &self.trace
    }

    /// The position command (interpolator output) at each recorded sample, mm: the
    /// third channel a control's servo trace can record.
    pub fn trace_command(&self) -> &[f64] {
        &self.trace_command
    }

    /// Machine time of the trigger, s.
    pub fn trace_trigger_time_s(&self) -> f64 {
        self.trace_trigger_time_s
    }

    /// Machine time of the first sample, s.
    pub fn trace_start_time_s(&self) -> f64 {
        self.trace_start_time_s
    }

    /// Sets the backlash (e.g. to emulate wear), mm.
    pub fn set_backlash_mm(&mut self, backlash_mm: f64) {
        self.params.backlash_mm = backlash_mm.max(0.0);
    }

    /// Checks a programme against the limits.
    pub fn check_program(&self, steps: &[MoveStep]) -> Result<(), SimRefusal> {
        if steps.is_empty() || steps.len() > MAX_STEPS {
            return Err(SimRefusal::BadStepCount);
        }
        let p = &self.params;
        for s in steps {
            if !(s.target_mm >= p.min_mm && s.target_mm <= p.max_mm) {
                return Err(SimRefusal::OutOfLimits);
            }
            if !(s.feed_mm_per_min > 0.0 && s.feed_mm_per_min <= p.max_feed_mm_per_min) {
                return Err(SimRefusal::BadFeed);
            }
            if !(0.0..=3600.0).contains(&s.dwell_s) {
                return Err(SimRefusal::BadDwell);
            }
        }
        Ok(())
    }

    /// Starts a move programme; refused (state `Refused`, status set) when invalid or
    /// while one runs.
    pub fn start_program(&mut self, steps: &[MoveStep]) -> Result<(), SimRefusal> {
        let checked = if self.program.is_some() {
            Err(SimRefusal::Busy)
        } else {
            self.check_program(steps)
        };
        match checked {
            Ok(()) => {
                self.program = Some(Running {
                    steps: steps.to_vec(),
                    index: 0,
                    phase: Phase::Moving {
                        from_mm: self.cmd_mm,
                        elapsed_s: 0.0,
                    },
                });
                self.program_state = ProgramState::Running;
                self.program_status = 0;
                // The noise from here on depends on the seed alone, not on how many
                // cycles the axis stood before (wall-clock time in the NC module).
                self.rng = SimRng::seed_from_u64(self.params.seed);
                self.program_start_s = self.time_s;
                self.program_end_s = f64::NAN;
                Ok(())
            }
            Err(e) => {
                // A refused start leaves a running programme running.
                if self.program.is_none() {
                    self.program_state = ProgramState::Refused;
                }
                self.program_status = e as u16;
                Err(e)
            }
        }
    }

    /// Aborts a running programme: the interpolator stops where it is (no ramp).
    pub fn abort_program(&mut self) {
        if self.program.take().is_some() {
            self.program_state = ProgramState::Refused;
            self.program_end_s = self.time_s;
        }
    }

    /// Arms the trace with `cfg`, discarding earlier samples.
    pub fn arm_trace(&mut self, cfg: TraceConfig) -> Result<(), SimRefusal> {
        let checked = self.check_trace(&cfg);
        match checked {
            Ok((period_cycles, samples)) => {
                self.trace_cfg = cfg;
                self.trace_period_cycles = period_cycles;
                self.trace_target = samples;
                self.trace.clear();
                self.trace_command.clear();
                self.trace_status = 0;
                self.trace_trigger_time_s = 0.0;
                self.trace_start_time_s = 0.0;
                self.trace_state = TraceState::Armed;
                if cfg.trigger == Trigger::Immediate {
                    self.fire_trigger();
                }
                Ok(())
            }
            Err(e) => {
                self.trace_status = e as u16;
                self.trace_state = TraceState::Idle;
                Err(e)
            }
        }
    }

    /// Records a refused arm command decoded outside (e.g. an unknown trigger code).
    pub fn refuse_trace(&mut self, refusal: SimRefusal) {
        self.trace_status = refusal as u16;
        self.trace_state = TraceState::Idle;
    }

    /// Stops the trace; samples recorded so far stay readable.
    pub fn stop_trace(&mut self) {
        if self.trace_state != TraceState::Complete {
            self.trace_state = TraceState::Idle;
        }
    }

    fn check_trace(&self, cfg: &TraceConfig) -> Result<(u64, usize), SimRefusal> {
        let cycles = cfg.period_s / self.params.servo_cycle_s;
        let whole = cycles.round();
        if !(cycles.is_finite() && (1.0..=1000.0).contains(&whole)) || (cycles - whole).abs() > 1e-6
        {
            return Err(SimRefusal::BadPeriod);
        }
        let samples = (cfg.record_s / cfg.period_s).floor();
        if !(samples >= 1.0 && samples <= MAX_TRACE_SAMPLES as f64) {
            return Err(SimRefusal::BadRecordTime);
        }
        if !(cfg.delay_s >= 0.0 && cfg.delay_s <= 3600.0) {
            return Err(SimRefusal::BadDelay);
        }
        if !cfg.threshold_mm.is_finite() {
            return Err(SimRefusal::BadTrigger);
        }
        // Both are in range: checked above.
        Ok((whole as u64, samples as usize))
    }

    fn fire_trigger(&mut self) {
        self.trace_trigger_time_s = self.time_s;
        let delay_cycles = (self.trace_cfg.delay_s / self.params.servo_cycle_s).round();
        // delay_s <= 3600 s was checked, so this fits.
        self.trace_countdown = delay_cycles as u64;
        if self.trace_countdown == 0 {
            self.begin_recording();
        } else {
            self.trace_state = TraceState::Delay;
        }
    }

    fn begin_recording(&mut self) {
        self.trace_state = TraceState::Recording;
        self.trace_start_time_s = self.time_s;
        self.trace_countdown = 0;
        self.record_sample();
    }

    fn record_sample(&mut self) {
        if self.trace_countdown == 0 {
            self.trace.push((self.enc_meas_mm, self.scale_meas_mm));
            self.trace_command.push(self.cmd_mm);
            self.trace_countdown = self.trace_period_cycles;
            if self.trace.len() >= self.trace_target {
                self.trace_state = TraceState::Complete;
            }
        }
        self.trace_countdown = self.trace_countdown.saturating_sub(1);
    }

    fn measure(&mut self) {
        let ne = self.noise_enc.map_or(0.0, |n| n.sample(&mut self.rng));
        let ns = self.noise_scale.map_or(0.0, |n| n.sample(&mut self.rng));
        self.enc_meas_mm = self.motor_mm + ne;
        self.scale_meas_mm = self.table_mm + ns;
    }

    /// Interpolator: advances the programme by `dt`, returns (x_cmd, v_cmd).
    fn interpolate(&mut self, dt: f64) -> (f64, f64) {
        let accel = self.params.accel_mm_per_s2;
        let Some(run) = &mut self.program else {
            return (self.cmd_mm, 0.0);
        };
        let step = run.steps[run.index];
        match &mut run.phase {
            Phase::Moving { from_mm, elapsed_s } => {
                *elapsed_s += dt;
                let dist = step.target_mm - *from_mm;
                let sign = dist.signum();
                match trapezoid(dist.abs(), step.feed_mm_per_min / 60.0, accel, *elapsed_s) {
                    Some((s, v)) => {
                        self.cmd_mm = *from_mm + sign * s;
                        (self.cmd_mm, sign * v)
                    }
                    None => {
                        self.cmd_mm = step.target_mm;
                        run.phase = Phase::Dwelling {
                            left_s: step.dwell_s,
                        };
                        (self.cmd_mm, 0.0)
                    }
                }
            }
            Phase::Dwelling { left_s } => {
                *left_s -= dt;
                if *left_s <= 1e-12 {
                    run.index += 1;
                    if run.index >= run.steps.len() {
                        self.program = None;
                        self.program_state = ProgramState::Done;
                        self.program_end_s = self.time_s + dt;
                    } else {
                        run.phase = Phase::Moving {
                            from_mm: self.cmd_mm,
                            elapsed_s: 0.0,
                        };
                    }
                }
                (self.cmd_mm, 0.0)
            }
        }
    }

    /// One servo cycle.
    pub fn step(&mut self) {
        let p = &self.params;
        let dt = p.servo_cycle_s;
        let (kv, half_gap, tau) = (p.kv_per_s, 0.5 * p.backlash_mm, p.elastic_tau_s);
        let feedback = p.feedback;
        let (x_cmd, _v_cmd) = self.interpolate(dt);
        // Position loop, proportional, no feedforward: with Kv * tau < 1/4 the loop is
        // overdamped and never overshoots, so every target is approached from the side
        // the move came from.
        let actual_mm = match feedback {
            Feedback::Scale => self.table_mm,
            Feedback::Encoder => self.motor_mm,
        };
        let v_motor = kv * (x_cmd - actual_mm);
        self.motor_mm += v_motor * dt;
        // Backlash: the nut follows the motor only once the gap is taken up.
        self.nut_mm = self
            .nut_mm
            .clamp(self.motor_mm - half_gap, self.motor_mm + half_gap);
        // Spring + viscous friction between nut and table.
        let k = if tau > 0.0 {
            1.0 - (-dt / tau).exp()
        } else {
            1.0
        };
        self.table_mm += (self.nut_mm - self.table_mm) * k;
        self.time_s += dt;
        let previous_scale_mm = self.scale_meas_mm;
        self.measure();
        self.trace_tick(previous_scale_mm);
    }

    fn trace_tick(&mut self, previous_scale_mm: f64) {
        match self.trace_state {
            TraceState::Armed => {
                let thr = self.trace_cfg.threshold_mm;
                let fired = match self.trace_cfg.trigger {
                    Trigger::Immediate => true,
                    // Edges, not levels: an axis already beyond the threshold when
                    // armed waits for the next crossing.
                    Trigger::ScaleRising => previous_scale_mm < thr && self.scale_meas_mm >= thr,
                    Trigger::ScaleFalling => previous_scale_mm > thr && self.scale_meas_mm <= thr,
                };
                if fired {
                    self.fire_trigger();
                }
            }
            TraceState::Delay => {
                self.trace_countdown = self.trace_countdown.saturating_sub(1);
                if self.trace_countdown == 0 {
                    self.begin_recording();
                }
            }
            TraceState::Recording => self.record_sample(),
            TraceState::Idle | TraceState::Complete => {}
        }
    }

    /// Runs `cycles` servo cycles.
    pub fn run_cycles(&mut self, cycles: u64) {
        for _ in 0..cycles {
            self.step();
        }
    }

    /// Runs until the programme is over and the trace is not recording or waiting,
    /// or `max_s` of machine time passed. Returns the machine time it ran, s.
    pub fn run_until_idle(&mut self, max_s: f64) -> f64 {
        let start = self.time_s;
        while self.time_s - start < max_s {
            let busy = self.program.is_some()
                || matches!(self.trace_state, TraceState::Delay | TraceState::Recording);
            if !busy {
                break;
            }
            self.step();
        }
        self.time_s - start
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quiet(backlash_mm: f64) -> AxisParams {
        AxisParams {
            backlash_mm,
            encoder_noise_mm: 0.0,
            scale_noise_mm: 0.0,
            ..AxisParams::default()
        }
    }

    fn step(target_mm: f64) -> MoveStep {
        MoveStep {
            target_mm,
            feed_mm_per_min: 1000.0,
            dwell_s: 1.0,
        }
    }

    #[test]
    fn trapezoid_reaches_the_distance() {
        let (dist, v, a) = (10.0, 16.0, 1000.0);
        let total = move_time_s(dist, v * 60.0, a);
        let (s, _) = trapezoid(dist, v, a, total - 1e-9).unwrap();
        assert!((s - dist).abs() < 1e-6);
        assert!(trapezoid(dist, v, a, total + 1e-9).is_none());
        // Short move: triangle.
        let total = move_time_s(0.01, 1000.0, a);
        assert!((total - 2.0 * (0.01_f64 / a).sqrt()).abs() < 1e-12);
    }

    #[test]
    fn table_settles_on_target_and_motor_is_half_a_gap_beyond() {
        let mut sim = ServoSim::new(quiet(0.04));
        sim.start_program(&[step(10.0), step(5.0)]).unwrap();
        // Run to the middle of the first dwell.
        while sim.program_step() == 1 {
            sim.step();
        }
        let mut sim2 = ServoSim::new(quiet(0.04));
        sim2.start_program(&[step(10.0)]).unwrap();
        sim2.run_until_idle(100.0);
        assert!((sim2.table_true_mm() - 10.0).abs() < 1e-6);
        assert!(
            (sim2.motor_true_mm() - 10.02).abs() < 1e-6,
            "{} {}",
            sim2.motor_true_mm(),
            sim2.table_true_mm()
        );
        sim.run_until_idle(100.0);
        assert_eq!(sim.program_state(), ProgramState::Done);
        assert!((sim.table_true_mm() - 5.0).abs() < 1e-6);
        assert!((sim.motor_true_mm() - 4.98).abs() < 1e-6);
    }

    #[test]
    fn table_lags_while_moving() {
        let mut sim = ServoSim::new(quiet(0.0));
        sim.start_program(&[step(20.0)]).unwrap();
        sim.run_cycles(600); // cruising at 16.7 mm/s
        let lag = sim.motor_true_mm() - sim.table_true_mm();
        let expected = 1000.0 / 60.0 * 0.008;
        assert!((lag - expected).abs() < 0.01, "lag {lag} {expected}");
    }

    #[test]
    fn refusals() {
        let mut sim = ServoSim::new(quiet(0.0));
        assert_eq!(sim.start_program(&[]), Err(SimRefusal::BadStepCount));
        assert_eq!(
            sim.start_program(&[step(5000.0)]),
            Err(SimRefusal::OutOfLimits)
        );
        let bad_feed = MoveStep {
            feed_mm_per_min: 0.0,
            ..step(1.0)
        };
        assert_eq!(sim.start_program(&[bad_feed]), Err(SimRefusal::BadFeed));
        assert_eq!(sim.program_state(), ProgramState::Refused);
        sim.start_program(&[step(1.0)]).unwrap();
        assert_eq!(sim.start_program(&[step(1.0)]), Err(SimRefusal::Busy));
        assert_eq!(sim.program_state(), ProgramState::Running);
        let cfg = TraceConfig {
            period_s: 0.0015,
            ..TraceConfig::default()
        };
        assert_eq!(sim.arm_trace(cfg), Err(SimRefusal::BadPeriod));
        let cfg = TraceConfig {
            record_s: 1e9,
            ..TraceConfig::default()
        };
        assert_eq!(sim.arm_trace(cfg), Err(SimRefusal::BadRecordTime));
    }

    #[test]
    fn trace_triggers_delays_and_records_the_set_count() {
        let mut sim = ServoSim::new(quiet(0.0));
        sim.arm_trace(TraceConfig {
            period_s: 0.004,
            record_s: 0.4,
            trigger: Trigger::ScaleRising,
            threshold_mm: 5.0,
            delay_s: 0.1,
        })
        .unwrap();
        sim.start_program(&[step(10.0)]).unwrap();
        sim.run_until_idle(100.0);
        assert_eq!(sim.trace_state(), TraceState::Complete);
        assert_eq!(sim.trace().len(), 100);
        let dt = sim.trace_start_time_s() - sim.trace_trigger_time_s();
        assert!((dt - 0.1).abs() < 1e-9, "{dt}");
        assert!(sim.trace()[0].1 > 5.0);
    }

    #[test]
    fn a_level_trigger_waits_for_the_next_edge() {
        let mut sim = ServoSim::new(AxisParams {
            start_mm: 20.0,
            ..quiet(0.0)
        });
        sim.arm_trace(TraceConfig {
            record_s: 0.1,
            trigger: Trigger::ScaleRising,
            threshold_mm: 10.0,
            ..TraceConfig::default()
        })
        .unwrap();
        // Above the threshold at arming: no trigger on the way down...
        sim.start_program(&[step(5.0)]).unwrap();
        sim.run_until_idle(100.0);
        assert_eq!(sim.trace_state(), TraceState::Armed);
        // ...but on the way up through it.
        sim.start_program(&[step(12.0)]).unwrap();
        sim.run_until_idle(100.0);
        assert_eq!(sim.trace_state(), TraceState::Complete);
        assert!(sim.trace()[0].1 >= 10.0);
    }

    #[test]
    fn deterministic_for_a_seed() {
        let run = || {
            let mut sim = ServoSim::new(AxisParams::default());
            sim.arm_trace(TraceConfig::default()).unwrap();
            sim.start_program(&[step(3.0)]).unwrap();
            sim.run_until_idle(20.0);
            sim.trace().to_vec()
        };
        assert_eq!(run(), run());
    }
}
