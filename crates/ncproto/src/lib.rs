//! Register map of the NC axis module: its public interface over Modbus TCP.
//!
//! The simulated NC axis module serves this map and the gateway's FB3-style writer
//! speaks it, so this module is the single definition both sides share. A real NC
//! reached through a PLC that exposes the same block works with the gateway unchanged.
//!
//! All addresses are **0-based Modbus PDU addresses of holding registers** (function
//! codes 0x03 read, 0x06/0x10 write). Holding register 0 is "40001" in 1-based
//! notation. `f64` values take four registers, most significant word first, big-endian
//! bytes in each word (order ABCDEFGH), so a value crosses the wire bit-exact and the
//! read-back check can compare for equality.
//!
//! # Job block (FB3 / PUT)
//!
//! | address | name | access | meaning |
//! |---|---|---|---|
//! | 0 | `REQ` | gateway writes | 0 -> 1 starts the latched job; gateway writes 0 to acknowledge DONE/ERROR |
//! | 1 | `STATE` | read | 0 idle, 1 busy, 2 done, 3 error |
//! | 2 | `DONE` | read | 1 when the job completed without error |
//! | 3 | `ERROR` | read | 1 when the job was refused; see `STATUS` |
//! | 4 | `STATUS` | read | error code, see [`JobStatus`] |
//! | 5 | `ERROR_INDEX` | read | 1-based index of the pair at fault, 0 when none |
//! | 6 | `JOB_ID` | gateway writes | echoed in `JOB_ID_DONE` when the job ends |
//! | 7 | `NUM_PAIRS` | gateway writes | number of (variable, value) pairs, 1..=8 |
//! | 8 + 5*i | `VAR_ID[i]` | gateway writes | variable id of pair i (see [`var`]) |
//! | 9 + 5*i .. 12 + 5*i | `VALUE[i]` | gateway writes | f64 value of pair i |
//! | 48 | `JOB_ID_DONE` | read | id of the last finished job |
//!
//! Handshake: the gateway writes `JOB_ID`, `NUM_PAIRS` and the pairs in one
//! write-multiple, then `REQ = 1`. The module latches the parameters on the rising edge,
//! shows `STATE = busy`, validates every pair and applies all of them or none, then sets
//! `DONE` or `ERROR` with `STATUS`. The gateway reads the result and writes `REQ = 0`,
//! which returns the module to idle. A write to the job block while busy does not alter
//! the latched job. One job at a time per module.
//!
//! # Read-back block
//!
//! | address | name | type |
//! |---|---|---|
//! | 100 | SD43900 `$SA_TEMP_COMP_ABS_VALUE` (mm) | f64 |
//! | 104 | SD43910 `$SA_TEMP_COMP_SLOPE` (mm/mm) | f64 |
//! | 108 | SD43920 `$SA_TEMP_COMP_REF_POSITION` (mm) | f64 |
//! | 112 | MD32760 `$MA_COMP_ADD_VELO_FACTOR` | f64 |
//! | 116 | MD32000 `$MA_MAX_AX_VELO` (mm/min) | f64 |
//! | 120 | actual position (mm) | f64 |
//! | 124 | applied temperature compensation (mm) | f64 |
//! | 128 | target temperature compensation at the actual position (mm) | f64 |
//! | 132 | MD32450 `$MA_BACKLASH` (mm) | f64 |
//! | 140 | MD32750 `$MA_TEMP_COMP_TYPE` | u16 |
//! | 141 | referenced (1 = axis referenced) | u16 |
//!
//! The read-back block is read-only: writes to it are refused with exception 0x02.
//! Registers 136..139 are not part of the map: a module may refuse a read that
//! includes them (exception 0x02), so a client reads the block in two requests,
//! [`READBACK`]`..+`[`RB_VALUES_LEN`] and [`RB_FLAGS`]`..+`[`RB_FLAGS_LEN`].
//!
//! # What the gateway's writer touches
//!
//! | when | function code | registers |
//! |---|---|---|
//! | every status interval (snapshot), and after each job (the guard's read-back) | FC03 read holding | 100..=135, then 140..=141 |
//! | job: is the module idle? | FC03 | 1..=48 (`STATE` .. `JOB_ID_DONE`) |
//! | job: clear a job left by an earlier run (only when `STATE` != 0) | FC06 write single | 0 (`REQ` = 0) |
//! | job: parameters | FC16 write multiple | 6..=7 + 5 per pair (`JOB_ID`, `NUM_PAIRS`, pairs) |
//! | job: start | FC06 | 0 (`REQ` = 1) |
//! | job: wait for the end, and its result | FC03 | 1..=48, every 2 ms while busy |
//! | job: acknowledge | FC06 | 0 (`REQ` = 0) |
//!
//! `STATUS` 16 (value out of range) is answered for a non-finite value or one
//! outside: |SD43900| <= [`SD43900_LIMIT_MM`] (10 mm), |SD43910| <=
//! [`SD43910_LIMIT`] (0.1), |SD43920| <= [`SD43920_LIMIT_MM`] (100 000 mm),
//! MD32450 in 0..=[`MD32450_LIMIT_MM`] (1 mm).
//!
//! # Servo block: move programme, servo trace, actual values (full-closed-loop axis)
//!
//! The module simulates a full-closed-loop axis (motor encoder and linear scale, see
//! `compgate_plc::axis`). A client commands a move programme and records both actual
//! positions with the servo trace, e.g. for the backlash test. `f64` values as above;
//! `u32` values take two registers, high word first.
//!
//! | address | name | access | meaning |
//! |---|---|---|---|
//! | 1000 | `MV_CMD` | write | 1 starts the programme in `MV_STEPS`, 2 aborts; reads 0 (a command, not a state) |
//! | 1001 | `MV_NUM_STEPS` | write | number of steps, 1..=8 |
//! | 1002 + 12*i | `MV_TARGET[i]` | write | f64 target position of step i, mm |
//! | 1006 + 12*i | `MV_FEED[i]` | write | f64 feed of step i, mm/min, in (0, MD32000] |
//! | 1010 + 12*i | `MV_DWELL[i]` | write | f64 dwell after step i, s, 0..=3600; starts when the interpolator reaches the target |
//! | 1100 | `MV_STATE` | read | 0 idle, 1 running, 2 done, 3 refused or aborted |
//! | 1101 | `MV_STATUS` | read | 0 ok; refusal code (below) of the last `MV_CMD = 1` |
//! | 1102 | `MV_STEP` | read | 1-based step running, 0 when none |
//! | 1110 | `TR_TRIGGER` | write | 0 immediate, 1 scale rises through threshold, 2 scale falls through it |
//! | 1112 | `TR_PERIOD_S` | write | f64 sample period, s: 1..=1000 servo cycles |
//! | 1116 | `TR_RECORD_S` | write | f64 record time, s; samples = floor(record / period) <= `TR_MAX_SAMPLES` |
//! | 1120 | `TR_THRESHOLD_MM` | write | f64 trigger threshold (scale actual position), mm |
//! | 1124 | `TR_DELAY_S` | write | f64 post-trigger delay before recording, s, 0..=3600 |
//! | 1128 | `TR_CMD` | write | 1 arms with the parameters above (earlier samples discarded), 2 stops; reads 0 |
//! | 1129 | `TR_PAGE` | write | page shown in `TR_WINDOW` |
//! | 1130 | `TR_STATE` | read | 0 idle, 1 armed, 2 post-trigger delay, 3 recording, 4 complete |
//! | 1131 | `TR_STATUS` | read | 0 ok; refusal code of the last `TR_CMD = 1` |
//! | 1132 | `TR_COUNT` | read | u32 samples recorded |
//! | 1134 | `TR_MAX_SAMPLES` | read | u32 capacity of the trace buffer |
//! | 1136 | `TR_TRIGGER_TIME_S` | read | f64 machine time of the trigger, s |
//! | 1140 | `TR_START_TIME_S` | read | f64 machine time of sample 0, s |
//! | 1144 | `ENCODER_POS` | read | f64 motor encoder actual position, mm |
//! | 1148 | `SCALE_POS` | read | f64 linear scale actual position, mm |
//! | 1152 | `AXIS_MIN` | read | f64 lower software limit, mm |
//! | 1156 | `AXIS_MAX` | read | f64 upper software limit, mm |
//! | 1160 | `MACHINE_TIME_S` | read | f64 machine time of the simulation, s |
//! | 1164 | `SERVO_CYCLE_S` | read | f64 servo cycle, s |
//! | 1168 | `MV_START_TIME_S` | read | f64 machine time the last programme started, s |
//! | 1172 | `MV_END_TIME_S` | read | f64 machine time it ended (done or aborted), s; NaN while running |
//! | 1200 + 8*k | `TR_WINDOW` | read | sample `TR_PAGE * 15 + k` (k = 0..15): f64 encoder then f64 scale, mm; NaN past `TR_COUNT` |
//!
//! Refusal codes (`MV_STATUS`, `TR_STATUS`): 1 step count, 2 target outside the
//! software limits, 3 feed, 4 dwell, 5 programme already running, 6 sample period,
//! 7 record time, 8 post-trigger delay, 9 trigger condition or threshold.
//!
//! A read holds at most 125 registers: 1100..1176 (status and actual values) is one.
//! Reads may span any registers of 1000..1176 and of the window 1200..1320 (unmapped
//! ones read 0). Writes must lie in 1000..1098 or 1110..1130; a write that includes
//! `MV_CMD` or `TR_CMD` acts after the whole write is stored, so a programme and its
//! start can go in one write-multiple. The simulation advances with tokio time times
//! the module's simulation speed (1 = real time).

/// Holding register of `REQ`.
pub const REQ: u16 = 0;
/// Holding register of `STATE`.
pub const STATE: u16 = 1;
/// Holding register of `DONE`.
pub const DONE: u16 = 2;
/// Holding register of `ERROR`.
pub const ERROR: u16 = 3;
/// Holding register of `STATUS`.
pub const STATUS: u16 = 4;
/// Holding register of `ERROR_INDEX`.
pub const ERROR_INDEX: u16 = 5;
/// Holding register of `JOB_ID`.
pub const JOB_ID: u16 = 6;
/// Holding register of `NUM_PAIRS`.
pub const NUM_PAIRS: u16 = 7;
/// First register of the pair table.
pub const PAIRS: u16 = 8;
/// Registers per pair: variable id + f64 value.
pub const PAIR_REGS: u16 = 5;
/// Most pairs in one job, as FB3 allows.
pub const MAX_PAIRS: usize = 8;
/// Holding register of `JOB_ID_DONE`.
pub const JOB_ID_DONE: u16 = 48;
/// Registers of the job block (0..JOB_BLOCK_LEN).
pub const JOB_BLOCK_LEN: u16 = 49;

/// Start of the read-back block.
pub const READBACK: u16 = 100;
/// SD43900 read-back.
pub const RB_SD43900: u16 = 100;
/// SD43910 read-back.
pub const RB_SD43910: u16 = 104;
/// SD43920 read-back.
pub const RB_SD43920: u16 = 108;
/// MD32760 read-back.
pub const RB_MD32760: u16 = 112;
/// MD32000 MAX_AX_VELO read-back (mm/min).
pub const RB_MAX_AX_VELO: u16 = 116;
/// Actual position (mm).
pub const RB_POSITION: u16 = 120;
/// Applied compensation (mm).
pub const RB_APPLIED_COMP: u16 = 124;
/// Target compensation at the actual position (mm).
pub const RB_TARGET_COMP: u16 = 128;
/// MD32450 backlash read-back (mm).
pub const RB_MD32450: u16 = 132;
/// MD32750 read-back (u16).
pub const RB_MD32750: u16 = 140;
/// Referenced flag (u16).
pub const RB_REFERENCED: u16 = 141;
/// Registers of the read-back block (READBACK..READBACK+READBACK_LEN), 136..139
/// included; a client reads only the mapped parts (below).
pub const READBACK_LEN: u16 = 42;
/// Registers of the f64 part of the read-back block, SD43900 .. MD32450
/// (100..=135).
pub const RB_VALUES_LEN: u16 = 36;
/// Start of the u16 part of the read-back block (MD32750, referenced).
pub const RB_FLAGS: u16 = RB_MD32750;
/// Registers of the u16 part (140..=141).
pub const RB_FLAGS_LEN: u16 = 2;

/// Move programme command (write 1 start, 2 abort).
pub const MV_CMD: u16 = 1000;
/// Number of programme steps.
pub const MV_NUM_STEPS: u16 = 1001;
/// First register of the step table.
pub const MV_STEPS: u16 = 1002;
/// Registers per step: target, feed, dwell (f64 each).
pub const MV_STEP_REGS: u16 = 12;
/// End (exclusive) of the writable programme registers.
pub const MV_WRITABLE_END: u16 = MV_STEPS + MV_STEP_REGS * 8;
/// Programme state (see `compgate_plc::axis::ProgramState`).
pub const MV_STATE: u16 = 1100;
/// Programme refusal code.
pub const MV_STATUS: u16 = 1101;
/// 1-based step running.
pub const MV_STEP: u16 = 1102;
/// Trace trigger condition.
pub const TR_TRIGGER: u16 = 1110;
/// Trace sample period, s (f64).
pub const TR_PERIOD_S: u16 = 1112;
/// Trace record time, s (f64).
pub const TR_RECORD_S: u16 = 1116;
/// Trace trigger threshold, mm (f64).
pub const TR_THRESHOLD_MM: u16 = 1120;
/// Trace post-trigger delay, s (f64).
pub const TR_DELAY_S: u16 = 1124;
/// Trace command (write 1 arm, 2 stop).
pub const TR_CMD: u16 = 1128;
/// Trace page shown in the window.
pub const TR_PAGE: u16 = 1129;
/// Start of the writable trace registers.
pub const TR_WRITABLE_START: u16 = 1110;
/// End (exclusive) of the writable trace registers.
pub const TR_WRITABLE_END: u16 = 1130;
/// Trace state (see `compgate_plc::axis::TraceState`).
pub const TR_STATE: u16 = 1130;
/// Trace refusal code.
pub const TR_STATUS: u16 = 1131;
/// Samples recorded (u32).
pub const TR_COUNT: u16 = 1132;
/// Trace buffer capacity (u32).
pub const TR_MAX_SAMPLES: u16 = 1134;
/// Machine time of the trigger, s (f64).
pub const TR_TRIGGER_TIME_S: u16 = 1136;
/// Machine time of sample 0, s (f64).
pub const TR_START_TIME_S: u16 = 1140;
/// Motor encoder actual position, mm (f64).
pub const ENCODER_POS: u16 = 1144;
/// Linear scale actual position, mm (f64).
pub const SCALE_POS: u16 = 1148;
/// Lower software limit, mm (f64).
pub const AXIS_MIN: u16 = 1152;
/// Upper software limit, mm (f64).
pub const AXIS_MAX: u16 = 1156;
/// Machine time of the simulation, s (f64).
pub const MACHINE_TIME_S: u16 = 1160;
/// Servo cycle, s (f64).
pub const SERVO_CYCLE_S: u16 = 1164;
/// Machine time the last programme started, s (f64).
pub const MV_START_TIME_S: u16 = 1168;
/// Machine time the last programme ended, s (f64; NaN while running).
pub const MV_END_TIME_S: u16 = 1172;
/// Start of the servo block.
pub const SERVO: u16 = 1000;
/// Start of the servo status part (`MV_STATE` ..= `MV_END_TIME_S`), readable in one
/// request of `SERVO_STATUS_LEN` registers.
pub const SERVO_STATUS: u16 = 1100;
/// Registers of the servo status part.
pub const SERVO_STATUS_LEN: u16 = 76;
/// Registers of the servo block (SERVO..SERVO+SERVO_LEN).
pub const SERVO_LEN: u16 = 176;
/// First register of the trace window.
pub const TR_WINDOW: u16 = 1200;
/// Samples per trace page.
pub const TR_PAGE_SAMPLES: u16 = 15;
/// Registers per trace sample: encoder f64, scale f64.
pub const TR_SAMPLE_REGS: u16 = 8;
/// Registers of the trace window.
pub const TR_WINDOW_LEN: u16 = TR_PAGE_SAMPLES * TR_SAMPLE_REGS;

/// Encodes a u32 into two registers, high word first.
pub fn u32_to_regs(v: u32) -> [u16; 2] {
    [(v >> 16) as u16, v as u16]
}

/// Decodes two registers, high word first, into a u32.
pub fn regs_to_u32(r: [u16; 2]) -> u32 {
    (u32::from(r[0]) << 16) | u32::from(r[1])
}

/// Variable ids used in `VAR_ID[i]`: the Siemens parameter number.
pub mod var {
    /// SD43900 `$SA_TEMP_COMP_ABS_VALUE`, mm. Writable.
    pub const SD43900: u16 = 43900;
    /// SD43910 `$SA_TEMP_COMP_SLOPE`, mm/mm. Writable.
    pub const SD43910: u16 = 43910;
    /// SD43920 `$SA_TEMP_COMP_REF_POSITION`, mm. Writable.
    pub const SD43920: u16 = 43920;
    /// MD32750 `$MA_TEMP_COMP_TYPE`. Machine data: readable, write denied.
    pub const MD32750: u16 = 32750;
    /// MD32760 `$MA_COMP_ADD_VELO_FACTOR`. Machine data: write denied.
    pub const MD32760: u16 = 32760;
    /// MD32000 `$MA_MAX_AX_VELO`. Machine data: write denied.
    pub const MD32000: u16 = 32000;
    /// MD32450 `$MA_BACKLASH`, mm. Write denied unless the module allows it.
    pub const MD32450: u16 = 32450;
}

/// Values of `STATE`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JobState {
    /// No job; ready for `REQ`.
    Idle = 0,
    /// Job latched, executing.
    Busy = 1,
    /// Job finished without error; waiting for `REQ = 0`.
    Done = 2,
    /// Job refused; waiting for `REQ = 0`.
    Error = 3,
}

impl JobState {
    /// Decodes a `STATE` register.
    pub fn from_u16(v: u16) -> Option<Self> {
        match v {
            0 => Some(Self::Idle),
            1 => Some(Self::Busy),
            2 => Some(Self::Done),
            3 => Some(Self::Error),
            _ => None,
        }
    }

    /// Name, for messages: `idle`, `busy`, `done`, `error`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Idle => "idle",
            Self::Busy => "busy",
            Self::Done => "done",
            Self::Error => "error",
        }
    }
}

/// Values of `STATUS`: the FB3 error codes, plus one compgate extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum JobStatus {
    /// 0: no error.
    Ok = 0,
    /// 3: access denied (variable is read-only, or the axis is not in a state to accept it).
    AccessDenied = 3,
    /// 5: invalid address (pair count outside 1..=8, or a malformed pair table).
    InvalidAddress = 5,
    /// 10: object does not exist (unknown variable id).
    ObjectDoesNotExist = 10,
    /// 16 (compgate extension): value outside the variable's range, or not finite.
    ValueOutOfRange = 16,
}

impl JobStatus {
    /// Decodes a `STATUS` register.
    pub fn from_u16(v: u16) -> Option<Self> {
        match v {
            0 => Some(Self::Ok),
            3 => Some(Self::AccessDenied),
            5 => Some(Self::InvalidAddress),
            10 => Some(Self::ObjectDoesNotExist),
            16 => Some(Self::ValueOutOfRange),
            _ => None,
        }
    }

    /// Human-readable name, for logs and status lines.
    pub fn name(self) -> &'static str {
        match self {
            Self::Ok => "OK",
            Self::AccessDenied => "access denied",
            Self::InvalidAddress => "invalid address",
            Self::ObjectDoesNotExist => "object does not exist",
            Self::ValueOutOfRange => "value out of range",
        }
    }
}

/// Encodes an f64 into four registers, most significant word first.
pub fn f64_to_regs(v: f64) -> [u16; 4] {
    let b = v.to_bits();
    [
        (b >> 48) as u16,
        (b >> 32) as u16,
        (b >> 16) as u16,
        b as u16,
    ]
}

/// Decodes four registers, most significant word first, into an f64.
pub fn regs_to_f64(r: [u16; 4]) -> f64 {
    f64::from_bits(
        (u64::from(r[0]) << 48)
            | (u64::from(r[1]) << 32)
            | (u64::from(r[2]) << 16)
            | u64::from(r[3]),
    )
}

/// The NC's own sanity limit on |SD43900|, mm.
pub const SD43900_LIMIT_MM: f64 = 10.0;
/// The NC's own sanity limit on |SD43910| (mm/mm).
pub const SD43910_LIMIT: f64 = 0.1;
/// Limit on |SD43920|, mm.
pub const SD43920_LIMIT_MM: f64 = 100_000.0;
/// Upper limit of MD32450 (backlash), mm; the lower limit is 0.
pub const MD32450_LIMIT_MM: f64 = 1.0;

/// The NC's own limit on |value| of thermal setting datum `var_id` (SD43900, SD43910,
/// SD43920); `None` for any other variable.
pub fn thermal_limit(var_id: u16) -> Option<f64> {
    match var_id {
        var::SD43900 => Some(SD43900_LIMIT_MM),
        var::SD43910 => Some(SD43910_LIMIT),
        var::SD43920 => Some(SD43920_LIMIT_MM),
        _ => None,
    }
}

/// Move programmes and servo traces of the servo block (`MV_*`, `TR_*`), as the
/// backlash test writes them and the simulated axis runs them.
pub mod servo {
    /// Most steps in one move programme.
    pub const MAX_STEPS: usize = 8;

    /// One step of a move programme: move to `target_mm` at `feed_mm_per_min`, then
    /// dwell `dwell_s`.
    #[derive(Debug, Clone, Copy, PartialEq)]
    pub struct MoveStep {
        /// Target position, mm.
        pub target_mm: f64,
        /// Feed, mm/min (> 0).
        pub feed_mm_per_min: f64,
        /// Dwell after arrival, s (>= 0).
        pub dwell_s: f64,
    }

    /// Trace trigger condition.
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub enum Trigger {
        /// 0: triggers on arming.
        Immediate = 0,
        /// 1: the scale actual position rises through the threshold (edge).
        ScaleRising = 1,
        /// 2: the scale actual position falls through the threshold (edge).
        ScaleFalling = 2,
    }

    impl Trigger {
        /// Decodes the trigger register.
        pub fn from_u16(v: u16) -> Option<Self> {
            match v {
                0 => Some(Self::Immediate),
                1 => Some(Self::ScaleRising),
                2 => Some(Self::ScaleFalling),
                _ => None,
            }
        }
    }

    /// Servo trace parameters, as set before arming.
    #[derive(Debug, Clone, Copy, PartialEq)]
    pub struct TraceConfig {
        /// Sample period, s (a whole number of servo cycles).
        pub period_s: f64,
        /// Record time, s.
        pub record_s: f64,
        /// Trigger condition.
        pub trigger: Trigger,
        /// Trigger threshold (scale position), mm.
        pub threshold_mm: f64,
        /// Post-trigger delay before recording starts, s.
        pub delay_s: f64,
    }

    impl Default for TraceConfig {
        fn default() -> Self {
            Self {
                period_s: 0.002,
                record_s: 10.0,
                trigger: Trigger::Immediate,
                threshold_mm: 0.0,
                delay_s: 0.0,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn f64_roundtrips_bit_exact() {
        for v in [0.0, -0.0, 0.1, -0.001, 1e-300, f64::MAX, 0.0001, 12345.678] {
            assert_eq!(regs_to_f64(f64_to_regs(v)).to_bits(), v.to_bits());
        }
        assert_eq!(f64_to_regs(1.0), [0x3FF0, 0, 0, 0]);
    }

    #[test]
    fn pair_table_fits_before_job_id_done() {
        assert_eq!(PAIRS + PAIR_REGS * MAX_PAIRS as u16, JOB_ID_DONE);
        const { assert!(RB_REFERENCED < READBACK + READBACK_LEN) };
        assert_eq!(READBACK + RB_VALUES_LEN, RB_MD32450 + 4);
        assert_eq!(RB_FLAGS + RB_FLAGS_LEN, READBACK + READBACK_LEN);
    }

    #[test]
    fn servo_block_is_consistent() {
        assert_eq!(MV_WRITABLE_END, 1098);
        const { assert!(MV_WRITABLE_END <= MV_STATE) };
        assert_eq!(MV_END_TIME_S + 4, SERVO + SERVO_LEN);
        assert_eq!(SERVO_STATUS + SERVO_STATUS_LEN, SERVO + SERVO_LEN);
        const { assert!(TR_WINDOW >= SERVO + SERVO_LEN) };
        // One read-holding request holds the window.
        const { assert!(TR_WINDOW_LEN <= 125) };
        assert_eq!(regs_to_u32(u32_to_regs(123_456_789)), 123_456_789);
    }
}
