//! `compgate backlash`: backlash of a full-closed-loop axis from the servo trace of its
//! motor encoder and linear scale (DOMAIN.md section 3).
//!
//! Procedure: the axis moves at feed v positively to A, dwells S s; positively to B,
//! dwells; negatively to C, dwells; positively to D, dwells. The servo trace records
//! the encoder and scale actual positions from the arrival at A. At B, C, D the scale
//! reads L1..L3 and the encoder M1..M3, and
//!
//! ```text
//! H1 = |L1 - L2|   H2 = |L2 - L3|   h1 = |M1 - M2|   h2 = |M2 - M3|
//! F1 = |h1 - H1|   (positive-direction backlash)
//! F2 = |h2 - H2|   (negative-direction backlash)
//! ```
//!
//! The scale is the reference; no external instrument is needed.
//!
//! L and M are not single samples: the drive train is elastic, so while the axis
//! still creeps into position the motor leads the table by more than the gap. Each
//! value is the mean over the settled part of the dwell at the point (the dwell found
//! from the command channel where the trace has one, else from the scale velocity),
//! from where both channels stand still to the dwell's end ([`extract`]).
//!
//! A point's values are taken only where encoder *and* scale stand still: on an
//! underdamped or creeping axis the motor can still be crossing the gap while the
//! table stands, and a plateau taken from the scale alone then reads the wrong gap
//! (issue 25: 7.3 um read 4.11 um). A dwell that never settles, or in which the motor
//! went back against the move (an overshooting loop), is refused with the reason,
//! and F1 and F2 that differ by more than max(0.5 um, 2 %) are flagged.
//!
//! The parts: `math` (validation, extraction, the seed's formulas; pure, no tokio),
//! `input` (`--trace FILE.csv`, a trace recorded on a real control),
//! `report` (the table, the trace CSV, the SVG) and `command` (the arguments and the
//! servo client): [`run`] drives an NC axis module over Modbus TCP: it commands the
//! programme, arms and uploads the trace through the servo block of
//! `compgate_ncproto`, and with `--write` writes MD32450 through the FB3 job
//! ([`compgate_gateway::nc::ModbusNcWriter`]).

mod command;
mod input;
mod math;
mod report;
#[cfg(test)]
mod tests;

use std::path::PathBuf;

use compgate_gateway::nc::NcError;
use compgate_gateway::source::SourceError;
use compgate_ncproto::servo::TraceConfig;

use crate::plot::PlotError;

pub use command::{check_args, run, run_file, run_on, BacklashArgs};
pub use input::{read_trace, PERIOD_TOLERANCE};
pub use math::{extract, Backlash, Extraction, PointValue, Points, Procedure, Trace};
pub use report::{report, write_csv, write_svg};

/// Shortest dwell, s: the loop must settle and leave a plateau to average.
pub const MIN_DWELL_S: f64 = 0.5;
/// Fewest samples averaged on one plateau.
pub const MIN_PLATEAU_SAMPLES: usize = 25;
/// Shortest stroke B->C and C->D, mm: longer than the largest MD32450, so each
/// reversal takes the whole gap up.
pub const MIN_STROKE_MM: f64 = 1.0;
/// The axis first goes this far below A, so A is approached positively, mm.
pub const PRE_TRAVEL_MM: f64 = 1.0;
/// Trigger threshold below A: the trace starts as the axis arrives at A, mm.
pub const TRIGGER_BELOW_A_MM: f64 = 0.002;
/// Span of the velocity estimate used to find standstill, s.
pub const VELOCITY_SPAN_S: f64 = 0.05;
/// A plateau's scale value must lie this close to its point, mm.
pub const POINT_TOLERANCE_MM: f64 = 0.1;
/// In-position window of the single-sample extraction, mm.
pub const ARRIVAL_WINDOW_MM: f64 = 0.005;
/// Window over which a channel's drift is fitted when looking for the settled part of
/// a dwell, s.
pub const SETTLE_WINDOW_S: f64 = 0.2;
/// A channel stands still when its fitted drift over the window (and over the rest of
/// the dwell) stays below this, mm, or below three standard errors of the fit.
pub const SETTLED_DRIFT_MM: f64 = 0.000_1;
/// Smoothing of the encoder when checking that the motor never went back against the
/// move during a dwell, s.
pub const SMOOTH_S: f64 = 0.05;
/// The motor may go back against the move by at most this (or five standard errors of
/// its smoothed noise), mm.
pub const BACKOFF_MM: f64 = 0.000_25;
/// A command channel that changes by less than this between samples stands still, mm.
pub const COMMAND_STILL_MM: f64 = 1e-6;
/// Acceptance tolerance of F1 and F2: this, or [`TOLERANCE_FRACTION`] of the backlash,
/// the larger; F1 and F2 further apart than it are flagged.
pub const TOLERANCE_MM: f64 = 0.000_5;
/// See [`TOLERANCE_MM`].
pub const TOLERANCE_FRACTION: f64 = 0.02;

/// Errors of the backlash test.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BacklashError {
    /// Parameters refused before anything moved; every problem is listed.
    #[error("invalid backlash test parameters: {}", .0.join("; "))]
    Invalid(Vec<String>),
    /// The Modbus link failed.
    #[error("NC link: {0}")]
    Link(#[from] SourceError),
    /// Nothing at `--nc` took the connection.
    #[error(
        "--nc {address}: {cause}: is the NC axis module on, and are the address and port right?"
    )]
    Unreachable {
        /// `--nc`.
        address: String,
        /// Why the connect failed.
        cause: SourceError,
    },
    /// The first read of `--nc` failed: most often not a Modbus NC axis module there.
    #[error("--nc {address}: {cause}; --nc is the Modbus NC axis module (compgate's register map, e.g. the simulated plant's), not the control: for a SINUMERIK, TwinCAT or S7 axis run the test programme on the control and give its trace with --trace")]
    FirstContact {
        /// `--nc`.
        address: String,
        /// Why the read failed.
        cause: SourceError,
    },
    /// The MD32450 job failed.
    #[error("MD32450 write: {0}")]
    Nc(#[from] NcError),
    /// The NC refused the move programme or the trace configuration.
    #[error("NC refused the {what}: code {code} ({})", refusal_name(*.code))]
    Refused {
        /// "move programme" or "servo trace".
        what: &'static str,
        /// Refusal code (`MV_STATUS` / `TR_STATUS`).
        code: u16,
    },
    /// The programme or the trace did not finish in time.
    #[error("timed out: {0}")]
    Timeout(String),
    /// A signal stopped the test while the axis moved.
    #[error("stopped by {0}")]
    Signal(&'static str),
    /// The test ended while the programme ran, and the programme was aborted (or
    /// could not be).
    #[error("{cause}; {abort}")]
    Aborted {
        /// What ended the test.
        cause: Box<BacklashError>,
        /// What the abort did.
        abort: String,
    },
    /// An output path names the trace read or a missing directory.
    #[error("{0}")]
    Output(#[from] compgate_core::outputs::OutputError),
    /// The trace does not show the plateaus the procedure needs.
    #[error("trace: {0}")]
    Extraction(String),
    /// A trace file (`--trace`) is malformed.
    #[error("{path}: line {line}, column `{column}`: {message}")]
    TraceFile {
        /// The file.
        path: String,
        /// 1-based line (the header is line 1).
        line: u64,
        /// The column at fault.
        column: String,
        /// What is wrong.
        message: String,
    },
    /// A trace file (`--trace`) is no CSV of the expected form (empty, another
    /// delimiter, rows of another length); the message names the line.
    #[error("{path}: {message}")]
    TraceFormat {
        /// The file.
        path: String,
        /// The reader's message.
        message: String,
    },
    /// F1 and F2 disagree; MD32450 was not written.
    #[error("F1 {f1_um:.3} um and F2 {f2_um:.3} um differ by more than the tolerance {tol_um:.3} um: MD32450 not written (see the report's warning)")]
    Disagree {
        /// F1, um.
        f1_um: f64,
        /// F2, um.
        f2_um: f64,
        /// The tolerance, um.
        tol_um: f64,
    },
    /// Writing the report files failed.
    #[error("output: {0}")]
    Io(String),
    /// Drawing the position-time SVG failed.
    #[error("output: {0}")]
    Plot(#[from] PlotError),
}

/// Names a refusal code of the servo block.
pub fn refusal_name(code: u16) -> &'static str {
    match code {
        1 => "step count",
        2 => "target outside the software limits",
        3 => "feed out of range",
        4 => "dwell out of range",
        5 => "a programme is running",
        6 => "sample period is not a whole number of servo cycles",
        7 => "record time exceeds the trace buffer",
        8 => "bad post-trigger delay",
        9 => "bad trigger",
        _ => "unknown",
    }
}

/// Everything one test produced.
#[derive(Debug, Clone, PartialEq)]
pub struct Outcome {
    /// The procedure run.
    pub procedure: Procedure,
    /// The trace parameters used.
    pub trace_config: TraceConfig,
    /// The uploaded trace.
    pub trace: Trace,
    /// The plateau values at B, C, D.
    pub points: [PointValue; 3],
    /// The result.
    pub backlash: Backlash,
    /// MD32450 written and read back, mm.
    pub md32450_written_mm: Option<f64>,
    /// Machine time of the move programme (approach to A through the dwell at D), s;
    /// for a trace file, its duration.
    pub machine_time_s: f64,
    /// The trace file analysed offline (`--trace`); None when the NC ran the test.
    pub trace_file: Option<PathBuf>,
    /// Files written.
    pub files: Vec<PathBuf>,
}
