//! `compgate volumetric`: online volumetric error compensation of a 5-axis machine with
//! an AC swivel head (DOMAIN.md section 4).
//!
//! The compensator sits between the scales and the drives: it reads the five scale
//! positions, computes where the tool really is from the error parameter file and
//! hands the drives the corrected feedback: the axis positions at which the *ideal*
//! machine would put the tool where the real one has it. A drive closing its loop on
//! that feedback therefore settles where the actual tool pose equals the commanded
//! nominal pose.
//!
//! # Kinematics
//!
//! X, Y, Z are linear, in mm; A (tilt, about X) and C (swivel, about Z) are in the
//! head, in degrees. The workpiece frame is the machine base; the tool chain is
//! base -> X slide -> Y slide -> Z slide -> C -> A -> tool, each link a rigid
//! transform (rotation and translation, a 4x4 homogeneous matrix applied as 3x3 plus
//! offset). Nominally
//!
//! ```text
//! tip  = (X, Y, Z) + Rz(C) (pivot + Rx(A) (0, 0, -tool_length))
//! axis = Rz(C) Rx(A) (0, 0, 1)        (unit vector from tip towards the spindle)
//! ```
//!
//! With errors each link is `nominal * error`, small rotations taken to first order
//! (`I + skew(a, b, c)`):
//!
//! - linear axis j at position q: translation `q * d_j + (EXj, EYj, EZj)`, rotation
//!   `(EAj, EBj, ECj)`, with the direction `d_X = (1, 0, 0)`,
//!   `d_Y = (-EC0Y, 1, 0)`, `d_Z = (EB0Z, -EA0Z, 1)` (squareness);
//! - C at angle c: `L_C E_C(c) Rz(c) L_C^-1`, where `L_C` is the location of the C
//!   axis line (offset XOC, YOC; tilts AOC about X, BOC about Y) and `E_C` the
//!   error motions over the angle (EXC, EYC, EZC; EAC, EBC, ECC);
//! - A at angle a: `T(pivot) L_A E_A(a) Rx(a) L_A^-1`, `L_A` from YOA, ZOA, BOA (about
//!   Y), COA (about Z), `E_A` from EXA..ECA.
//!
//! A rotary axis' error motions act in the frame of its stator (the body that carries
//! it), not in the turning rotor's: they are what an instrument fixed to the stator
//! reads (ISO 230-7), so EXC is along the machine's X at every C, and a constant
//! EAC/EBC tilts the C axis line itself, like AOC/BOC. `E` therefore comes after the
//! rotation. For C the stator frame is the machine frame; for A it is the C rotor's
//! (the head housing), which C turns.
//!
//! Location errors thus vanish at the axis' zero angle and grow with the angle (the
//! zero-angle offset belongs to the tool offsets).
//!
//! # Compensation (the seed's two steps)
//!
//! For scale positions q:
//!
//! 1. Actual tool axis v in the workpiece frame; the rotary angles that give v on the
//!    ideal machine: `A' = k * atan2(sqrt(vx^2 + vy^2), vz)` (k the sign of A,
//!    equivalent to the seed's `k * arccos(vz)`), `C' = atan2(k vx, -k vy)`, unwrapped
//!    to the turn nearest C.
//! 2. Actual tip p; with A', C': `(X', Y', Z') = p - Rz(C') (pivot + Rx(A') (0, 0, -L))`.
//!
//! `(X', Y', Z', A', C')` is the corrected feedback ([`VolumetricCompensator::feedback`]).
//! For a commanded pose u, [`VolumetricCompensator::drive_positions`] iterates
//! `q <- q - (feedback(q) - u)`, each step doing both stages, which is what the drive
//! loop does physically; the report gives iterations and residual.
//!
//! # The A = 0 pole
//!
//! Near A = 0 the tool axis is parallel to C and an orientation error about the A
//! plane's normal needs a C move that grows as 1/sin(A). `feedback` uses step 1 as
//! above while it moves C by at most half of [`MAX_ONLINE_C_CORRECTION_DEG`]; beyond
//! the limit it holds C and A' takes only the in-plane part (`A' = atan2(-w_y, w_z)`,
//! w the axis in the C frame), and between the two it blends linearly, so that the
//! feedback stays continuous and a servo loop on it settles. Where the drive loop
//! ends in that band (or takes C more than `TRAVEL_MARGIN_DEG` past its travel),
//! [`PoleMode::Swing`], the default of [`VolumetricCompensator::drive_positions_pole`],
//! solves the command with C free within [`Pole::c_range`]: within a limit of the
//! commanded C and within the C travel. [`PoleMode::Hold`] keeps what the drive loop
//! gives.
//!
//! Not every tool axis near the pole can be reached. Turning A sweeps the tool over
//! a cone about the actual A axis, turning C turns that cone about the actual C
//! axis, and the cone misses the C axis by the cap radius
//!
//! ```text
//! cap(C) = EBA(A) - BOC + EBC'(C)
//!        = (EBA - BOA)          tool tilted out of the plane normal to A
//!        + (BOA - BOC + EBC')   A tilted out of the plane normal to C
//! EBC'(C) = cos(C) EBC(C) - sin(C) EAC(C)   (C's tilt error motion, machine frame,
//!                                            about the C rotor's Y axis)
//! ```
//!
//! No (A, C) puts the tool within `cap` of the actual C axis. The nominal axis lies
//! at `offset` from the actual C axis (C location AOC, BOC; the slides' angular
//! errors; the commanded tilt), at azimuth `phi` in the C rotor frame at C = 0; once
//! A has taken the in-plane part, the tool misses it by
//! `|offset cos(phi - C) - cap(C)|`. Where that has no root over the C range the
//! least orientation error is its minimum, about `cap - offset`, and X, Y, Z still
//! put the tip on the command. [`ErrorModel::pole_reach`] evaluates this from the
//! parameters (first order in the errors; on the example file it agrees with a
//! brute-force search over all drive positions within 0.01"). A file without
//! out-of-plane head errors (EBA, EAC, EBC, BOC zero) has cap radius 0, and a C move
//! reaches every axis at the pole.
//!
//! # Error parameter file, version 1
//!
//! Text, one item per line, `#` starts a comment, blank lines ignored. Translations
//! in um, rotations in arc-seconds (1" = 4.848 urad); positions of X, Y, Z in mm,
//! angles of A, C in degrees. ISO 230-1 / 230-7 names.
//!
//! ```text
//! compgate-volumetric-errors 1          # header: magic and version (required, first)
//! pivot_mm 0 0 150                      # C axis to A axis offset in the C frame, mm
//! tool_length_mm 250                    # A axis to tool tip along the tool, mm
//! travel X 0 1000                       # travel of every axis (all five required)
//! travel Y 0 800
//! travel Z 0 600
//! travel A -100 100                     # deg
//! travel C -200 200                     # deg
//! squareness EC0Y 6.0                   # arcsec: EC0Y (Y to X), EB0Z (Z to X), EA0Z (Z to Y)
//! location XOC 8                        # um:     XOC YOC (C), YOA ZOA (A)
//! location BOA -4                       # arcsec: AOC BOC (C), BOA COA (A)
//! table X EXX EYX EZX EAX EBX ECX       # column names fixed per axis, in this order
//! 0    0.0  0.0  0.0  0.0  0.0  0.0     # position, 3 translations (um), 3 rotations (")
//! 1000 12.5 -3.1 4.0  2.2  -5.0 1.5
//! end
//! table A EXA EYA EZA EAA EBA ECA       # rotary tables over the angle in deg
//! ...
//! end
//! ```
//!
//! Tables are interpolated linearly, positions strictly increasing, at least two
//! rows. A table must cover the axis travel: it is rejected otherwise, never
//! extrapolated. A missing table, squareness or location value means zero. Every
//! error names the line and field at fault ([`VolumetricError::Parse`]).

mod command;
mod evaluation;
mod format;
mod kinematics;
mod report;
mod synthetic;
#[cfg(test)]
mod tests;

use std::f64::consts::PI;

use crate::plot::PlotError;

pub use command::{parse_grid, run, Evaluated, VolumetricArgs};
pub use evaluation::{
    evaluate, evaluate_pole, pole_floor_brute_force, Acceptance, Evaluation, PoleClasses, Stats,
    ACCEPT_FLOOR_ARCSEC, ACCEPT_FRACTION, POLE_TOL_ARCSEC, POLE_TOL_FRACTION,
};
pub use format::{parse, write, LOCATION_A, LOCATION_C, MAGIC, SQUARENESS, VERSION};
pub use kinematics::{
    angle_rad, distance_mm, nominal_pose, ErrorModel, Geometry, Pole, PoleMode, PoleReach,
    PoleSolve, Solve, Table, VolumetricCompensator, TRAVEL_MARGIN_DEG,
};
pub use report::{report, write_poses_csv, write_svgs, POSES_CSV_HEADER};
pub use synthetic::{synthetic_model, synthetic_model_in_plane};

/// Axis names in the order of every `[f64; 5]` (X, Y, Z in mm; A, C in degrees).
pub const AXES: [&str; 5] = ["X", "Y", "Z", "A", "C"];
/// Column names of each axis' error table.
pub const COLUMNS: [[&str; 6]; 5] = [
    ["EXX", "EYX", "EZX", "EAX", "EBX", "ECX"],
    ["EXY", "EYY", "EZY", "EAY", "EBY", "ECY"],
    ["EXZ", "EYZ", "EZZ", "EAZ", "EBZ", "ECZ"],
    ["EXA", "EYA", "EZA", "EAA", "EBA", "ECA"],
    ["EXC", "EYC", "EZC", "EAC", "EBC", "ECC"],
];
/// mm per um.
pub const MM_PER_UM: f64 = 1e-3;
/// rad per arc-second.
pub const RAD_PER_ARCSEC: f64 = PI / (180.0 * 3600.0);
/// The per-cycle feedback holds C where step 1 would move it by more than this, deg:
/// the pole band, within about 0.01 deg of A = 0 on the example (module doc).
pub const MAX_ONLINE_C_CORRECTION_DEG: f64 = 10.0;
/// Convergence tolerance of the linear residual, um.
pub const TOL_UM: f64 = 0.01;
/// Convergence tolerance of the rotary residual, arc-seconds: the hypot of the A
/// and C residuals, which bounds the angle they turn the tool axis by.
pub const TOL_ARCSEC: f64 = 0.001;
/// Most iterations of [`VolumetricCompensator::drive_positions`].
pub const MAX_ITERATIONS: usize = 20;

/// Errors of the volumetric module.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VolumetricError {
    /// A problem of the error parameter file `path` (a [`Self::Parse`]).
    #[error("{path}: {source}")]
    InFile {
        /// The file as given.
        path: String,
        /// What is wrong in it.
        source: Box<VolumetricError>,
    },
    /// The error parameter file is malformed.
    #[error("line {line}, {field}: {message}")]
    Parse {
        /// 1-based line number.
        line: usize,
        /// The field at fault.
        field: String,
        /// What is wrong.
        message: String,
    },
    /// The `--grid` specification is malformed or outside the travel.
    #[error("grid: {0}")]
    Grid(String),
    /// A numeric flag is not usable (it names the flag).
    #[error("{0}")]
    Arg(#[from] crate::args::ArgError),
    /// Reading the file or writing the output failed.
    #[error("{0}")]
    Io(String),
    /// Drawing an error map failed.
    #[error("{0}")]
    Plot(#[from] PlotError),
    /// Poses failed the acceptance ([`Evaluation::acceptance`]); the report names
    /// them.
    #[error(
        "acceptance failed: {failed} of {total} poses outside the limits (named in the report)"
    )]
    Acceptance {
        /// Poses outside.
        failed: usize,
        /// Every pose.
        total: usize,
    },
    /// An output path names an input or another output, or a missing directory.
    #[error("{0}")]
    Output(#[from] compgate_core::outputs::OutputError),
}
