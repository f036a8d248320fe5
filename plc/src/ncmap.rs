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
/// Registers of the read-back block (READBACK..READBACK+READBACK_LEN).
pub const READBACK_LEN: u16 = 42;

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
    }
}
