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
//! - C at angle c: `L_C Rz(c) E_C(c) L_C^-1`, where `L_C` is the location of the C
//!   axis line (offset XOC, YOC; tilts AOC about X, BOC about Y) and `E_C` the
//!   position-dependent errors (EXC, EYC, EZC; EAC, EBC, ECC);
//! - A at angle a: `T(pivot) L_A Rx(a) E_A(a) L_A^-1`, `L_A` from YOA, ZOA, BOA (about
//!   Y), COA (about Z), `E_A` from EXA..ECA.
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
//! plane's normal cannot be corrected without a large C move: within
//! [`SINGULAR_A_DEG`] of A = 0 C is not corrected and A' takes only the in-plane
//! part (`A' = atan2(-w_y, w_z)`, w the axis in the C frame). That is
//! [`PoleMode::Hold`], the default and the only behaviour of `feedback`.
//! [`PoleMode::Swing`] ([`VolumetricCompensator::drive_positions_pole`], offline)
//! solves such commands with C free within [`Pole::c_range`]: within a limit of the
//! commanded C and within the C travel.
//!
//! Not every tool axis near the pole can be reached. Turning A sweeps the tool over
//! a cone about the actual A axis, turning C turns that cone about the actual C
//! axis, and the cone misses the C axis by the cap radius
//!
//! ```text
//! cap(C) = EBA(A) - BOC + EBC(C)
//!        = (EBA - BOA)          tool tilted out of the plane normal to A
//!        + (BOA - BOC - EBC)    A tilted out of the plane normal to C
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
//! brute-force search over all drive positions within 0.002"). A file without
//! out-of-plane head errors (EBA, EBC, BOC zero) has cap radius 0, and a C move
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

mod format;
#[cfg(test)]
mod tests;

use std::f64::consts::PI;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::plot::{self, PlotError};
use crate::stats;

pub use format::{parse, write, LOCATION_A, LOCATION_C, MAGIC, SQUARENESS, VERSION};

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
/// Within this many degrees of A = 0 the C axis is not corrected (see module doc).
pub const SINGULAR_A_DEG: f64 = 1.0;
/// Convergence tolerance of the linear residual, um.
pub const TOL_UM: f64 = 0.01;
/// Convergence tolerance of the rotary residual, arc-seconds.
pub const TOL_ARCSEC: f64 = 0.001;
/// Most iterations of [`VolumetricCompensator::drive_positions`].
pub const MAX_ITERATIONS: usize = 20;

/// Errors of the volumetric module.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VolumetricError {
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
    /// Reading the file or writing the output failed.
    #[error("{0}")]
    Io(String),
}

/// Nominal geometry of the head.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Geometry {
    /// Offset from the C axis (at the Z slide's reference point) to the A axis, in the
    /// C frame, mm.
    pub pivot_mm: [f64; 3],
    /// Distance from the A axis to the tool tip along the tool, mm.
    pub tool_length_mm: f64,
}

/// One axis' error table; internal units mm and rad, positions in mm or deg.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Table {
    pos: Vec<f64>,
    val: Vec<[f64; 6]>,
}

impl Table {
    /// A table from positions and rows of (3 translations mm, 3 rotations rad).
    pub fn new(pos: Vec<f64>, val: Vec<[f64; 6]>) -> Self {
        Self { pos, val }
    }

    /// Linearly interpolated errors; the end rows are held outside (loading has
    /// checked that the table covers the travel); an empty table gives zeros.
    #[inline]
    pub fn eval(&self, x: f64) -> [f64; 6] {
        let n = self.pos.len();
        if n == 0 {
            return [0.0; 6];
        }
        if x <= self.pos[0] {
            return self.val[0];
        }
        if x >= self.pos[n - 1] {
            return self.val[n - 1];
        }
        let i = self.pos.partition_point(|p| *p <= x).clamp(1, n - 1);
        let (x0, x1) = (self.pos[i - 1], self.pos[i]);
        let t = (x - x0) / (x1 - x0);
        let (a, b) = (&self.val[i - 1], &self.val[i]);
        let mut out = [0.0; 6];
        for k in 0..6 {
            out[k] = a[k] + (b[k] - a[k]) * t;
        }
        out
    }
}

/// The measured geometric errors of one machine, in internal units (mm, rad).
#[derive(Debug, Clone, PartialEq)]
pub struct ErrorModel {
    /// Head geometry.
    pub geometry: Geometry,
    /// Travel (min, max) of X, Y, Z (mm), A, C (deg).
    pub travel: [(f64, f64); 5],
    tables: [Table; 5],
    /// EC0Y, EB0Z, EA0Z, rad.
    squareness_rad: [f64; 3],
    /// XOC, YOC (mm), AOC, BOC (rad).
    loc_c: [f64; 4],
    /// YOA, ZOA (mm), BOA, COA (rad).
    loc_a: [f64; 4],
    zero: bool,
}

impl ErrorModel {
    /// A model from its parts (tables in mm / rad, squareness in rad, locations in mm
    /// and rad, order as [`SQUARENESS`], [`LOCATION_C`], [`LOCATION_A`]).
    pub fn new(
        geometry: Geometry,
        travel: [(f64, f64); 5],
        tables: [Table; 5],
        squareness_rad: [f64; 3],
        loc_c: [f64; 4],
        loc_a: [f64; 4],
    ) -> Self {
        let zero = tables
            .iter()
            .all(|t| t.val.iter().all(|r| r.iter().all(|v| *v == 0.0)))
            && squareness_rad
                .iter()
                .chain(&loc_c)
                .chain(&loc_a)
                .all(|v| *v == 0.0);
        Self {
            geometry,
            travel,
            tables,
            squareness_rad,
            loc_c,
            loc_a,
            zero,
        }
    }

    /// True when every error is zero (the compensator then passes positions through).
    pub fn is_zero(&self) -> bool {
        self.zero
    }

    /// Actual tool tip (mm) and unit tool axis in the workpiece frame at axis
    /// positions q (mm, deg).
    #[inline]
    pub fn actual_pose(&self, q: &[f64; 5]) -> ([f64; 3], [f64; 3]) {
        let g = &self.geometry;
        let mut p = [0.0, 0.0, -g.tool_length_mm];
        let mut v = [0.0, 0.0, 1.0];
        // A: T(pivot) L_A Rx(a) E_A L_A^-1
        let [yoa, zoa, boa, coa] = self.loc_a;
        let la_r = [0.0, boa, coa];
        let la_t = [0.0, yoa, zoa];
        inv_small(&la_r, &la_t, &mut p, &mut v);
        let e = self.tables[3].eval(q[3]);
        small(&e, &mut p, &mut v);
        let (sa, ca) = q[3].to_radians().sin_cos();
        rot_x(sa, ca, &mut p, &mut v);
        small(
            &[la_t[0], la_t[1], la_t[2], la_r[0], la_r[1], la_r[2]],
            &mut p,
            &mut v,
        );
        for (pk, dk) in p.iter_mut().zip(&g.pivot_mm) {
            *pk += dk;
        }
        // C: L_C Rz(c) E_C L_C^-1
        let [xoc, yoc, aoc, boc] = self.loc_c;
        let lc_r = [aoc, boc, 0.0];
        let lc_t = [xoc, yoc, 0.0];
        inv_small(&lc_r, &lc_t, &mut p, &mut v);
        let e = self.tables[4].eval(q[4]);
        small(&e, &mut p, &mut v);
        let (sc, cc) = q[4].to_radians().sin_cos();
        rot_z(sc, cc, &mut p, &mut v);
        small(
            &[lc_t[0], lc_t[1], lc_t[2], lc_r[0], lc_r[1], lc_r[2]],
            &mut p,
            &mut v,
        );
        // Z, Y, X slides.
        let [c0y, b0z, a0z] = self.squareness_rad;
        let dirs = [[1.0, 0.0, 0.0], [-c0y, 1.0, 0.0], [b0z, -a0z, 1.0]];
        for j in (0..3).rev() {
            let mut e = self.tables[j].eval(q[j]);
            for k in 0..3 {
                e[k] += q[j] * dirs[j][k];
            }
            small(&e, &mut p, &mut v);
        }
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        (p, [v[0] / n, v[1] / n, v[2] / n])
    }

    /// Which tool axes the head can reach near the pole, from the error parameters alone
    /// (first order in the errors and in the nominal axis' tilt; module doc, "The A = 0
    /// pole"), for a command u with C limited to `c_range_deg`.
    ///
    /// Turning A sweeps the tool over a cone about the actual A axis; turning C turns
    /// that cone about the actual C axis. The cone misses the C axis by
    /// `EBA(A) - BOC + EBC(C)`: the tool's tilt out of the plane normal to A
    /// (`EBA - BOA`) plus A's tilt out of the plane normal to C (`BOA - BOC - EBC`). So
    /// the directions within that angle of the actual C axis (a cap) are reached by no
    /// (A, C). With the nominal axis at `offset` from the actual C axis and at azimuth
    /// `phi` in the C rotor frame at C = 0, the tool misses it by
    /// `|offset cos(phi - C) - cap(C)|` once A has taken the in-plane part.
    pub fn pole_reach(&self, u: &[f64; 5], c_range_deg: (f64, f64)) -> PoleReach {
        let [_, _, aoc, boc] = self.loc_c;
        let (mut sx, mut sy) = (0.0, 0.0);
        for (t, x) in self.tables.iter().zip(u).take(3) {
            let e = t.eval(*x);
            sx += e[3];
            sy += e[4];
        }
        // Nominal axis tilt minus the actual C axis' tilt (slides, then C location).
        let (sa, _) = u[3].to_radians().sin_cos();
        let (sc, cc) = u[4].to_radians().sin_cos();
        let t = [sc * sa - (boc + sy), -cc * sa - (-aoc - sx)];
        let eba = self.tables[3].eval(u[3])[4];
        let cap = |c_deg: f64| eba - boc + self.tables[4].eval(c_deg)[4];
        let miss = |c_deg: f64| {
            let (s, c) = c_deg.to_radians().sin_cos();
            t[0] * c + t[1] * s - cap(c_deg)
        };
        let (lo, hi) = (c_range_deg.0.min(c_range_deg.1), c_range_deg.1);
        let best = least_abs_root(
            &mut |c| Some(miss(c)),
            u[4].clamp(lo, hi),
            (lo, hi),
            POLE_SCAN_DEG,
        )
        .unwrap_or((u[4], miss(u[4])));
        PoleReach {
            offset_arcsec: t[0].hypot(t[1]) / RAD_PER_ARCSEC,
            cap_arcsec: cap(best.0).abs() / RAD_PER_ARCSEC,
            min_arcsec: best.1.abs() / RAD_PER_ARCSEC,
            c_deg: best.0,
        }
    }
}

/// Result of [`ErrorModel::pole_reach`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoleReach {
    /// Angle between the nominal tool axis and the actual C axis, arc-seconds.
    pub offset_arcsec: f64,
    /// Radius of the cap around the actual C axis that no (A, C) reaches, at `c_deg`
    /// (it changes with C by EBC), arc-seconds.
    pub cap_arcsec: f64,
    /// Least orientation error over C in the range, arc-seconds; 0 where the nominal
    /// axis is reached.
    pub min_arcsec: f64,
    /// C of that least error (where reached, the root nearest the command), deg.
    pub c_deg: f64,
}

/// Scan step over C of the pole solves, deg.
const POLE_SCAN_DEG: f64 = 1.0;

/// For a continuous f over [lo, hi]: the root nearest `from` if f changes sign on a
/// scan of `step` outwards from it (then bisected), else the point of least |f|
/// (golden-section search in the scan cells either side of the least sample).
/// Returns (x, f(x)); None as soon as f fails.
fn least_abs_root(
    f: &mut impl FnMut(f64) -> Option<f64>,
    from: f64,
    (lo, hi): (f64, f64),
    step: f64,
) -> Option<(f64, f64)> {
    let f0 = f(from)?;
    let mut least = (from, f0);
    if f0 == 0.0 {
        return Some(least);
    }
    let mut prev = [(from, f0); 2];
    for k in 1.. {
        let mut moved = false;
        for (side, dir) in [1.0, -1.0].into_iter().enumerate() {
            let (x0, y0) = prev[side];
            if (dir > 0.0 && x0 >= hi) || (dir < 0.0 && x0 <= lo) {
                continue;
            }
            moved = true;
            let x1 = (from + dir * step * k as f64).clamp(lo, hi);
            let y1 = f(x1)?;
            prev[side] = (x1, y1);
            if y1.abs() < least.1.abs() {
                least = (x1, y1);
            }
            if y1 == 0.0 {
                return Some((x1, y1));
            }
            if y0.signum() != y1.signum() {
                let (mut a, mut b, mut ya) = (x0, x1, y0);
                for _ in 0..80 {
                    let m = 0.5 * (a + b);
                    let ym = f(m)?;
                    if ym == 0.0 || (b - a).abs() < 1e-12 {
                        return Some((m, ym));
                    }
                    if ym.signum() == ya.signum() {
                        (a, ya) = (m, ym);
                    } else {
                        b = m;
                    }
                }
                let m = 0.5 * (a + b);
                return Some((m, f(m)?));
            }
        }
        if !moved {
            break;
        }
    }
    // No root: |f| is smooth but for the kinks of the tables, so its least value is
    // within a scan step of the least sample.
    let (a, b) = ((least.0 - step).max(lo), (least.0 + step).min(hi));
    let (m, _) = stats::try_golden(a, b, 60, &mut |x| f(x).map(f64::abs).ok_or(())).ok()?;
    let ym = f(m)?;
    Some(if ym.abs() < least.1.abs() {
        (m, ym)
    } else {
        least
    })
}

/// Nominal tip (mm) and tool axis at q.
#[inline]
pub fn nominal_pose(g: &Geometry, q: &[f64; 5]) -> ([f64; 3], [f64; 3]) {
    let (sa, ca) = q[3].to_radians().sin_cos();
    let (sc, cc) = q[4].to_radians().sin_cos();
    let off = head_offset(g, sa, ca, sc, cc);
    (
        [q[0] + off[0], q[1] + off[1], q[2] + off[2]],
        [sc * sa, -cc * sa, ca],
    )
}

/// `Rz(C) (pivot + Rx(A) (0, 0, -L))` from the sines and cosines.
#[inline]
fn head_offset(g: &Geometry, sa: f64, ca: f64, sc: f64, cc: f64) -> [f64; 3] {
    let l = g.tool_length_mm;
    let h = [
        g.pivot_mm[0],
        g.pivot_mm[1] + sa * l,
        g.pivot_mm[2] - ca * l,
    ];
    [cc * h[0] - sc * h[1], sc * h[0] + cc * h[1], h[2]]
}

/// Applies `[I + skew(e[3..]), e[..3]]` to a point and a vector.
#[inline]
fn small(e: &[f64; 6], p: &mut [f64; 3], v: &mut [f64; 3]) {
    let [a, b, c] = [e[3], e[4], e[5]];
    let r = |x: &[f64; 3]| {
        [
            x[0] - c * x[1] + b * x[2],
            c * x[0] + x[1] - a * x[2],
            -b * x[0] + a * x[1] + x[2],
        ]
    };
    let rp = r(p);
    *p = [rp[0] + e[0], rp[1] + e[1], rp[2] + e[2]];
    *v = r(v);
}

/// Applies the first-order inverse of `[I + skew(r), t]`: `x -> (I - skew(r)) (x - t)`.
#[inline]
fn inv_small(r: &[f64; 3], t: &[f64; 3], p: &mut [f64; 3], v: &mut [f64; 3]) {
    let q = [p[0] - t[0], p[1] - t[1], p[2] - t[2]];
    let e = [0.0, 0.0, 0.0, -r[0], -r[1], -r[2]];
    *p = q;
    small(&e, p, v);
}

#[inline]
fn rot_x(s: f64, c: f64, p: &mut [f64; 3], v: &mut [f64; 3]) {
    let f = |x: &[f64; 3]| [x[0], c * x[1] - s * x[2], s * x[1] + c * x[2]];
    *p = f(p);
    *v = f(v);
}

#[inline]
fn rot_z(s: f64, c: f64, p: &mut [f64; 3], v: &mut [f64; 3]) {
    let f = |x: &[f64; 3]| [c * x[0] - s * x[1], s * x[0] + c * x[1], x[2]];
    *p = f(p);
    *v = f(v);
}

/// Angle between two unit vectors, rad (robust for tiny angles).
#[inline]
pub fn angle_rad(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    let c = [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ];
    let s = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
    s.atan2(a[0] * b[0] + a[1] * b[1] + a[2] * b[2])
}

/// Distance between two points, mm.
#[inline]
pub fn distance_mm(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Result of solving for the drive positions of one commanded pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Solve {
    /// Axis positions (scale values) at which the actual pose is the commanded one.
    pub drive: [f64; 5],
    /// Corrections applied (iterations of both steps).
    pub iterations: usize,
    /// Remaining linear residual `|feedback(drive) - command|` of X, Y, Z, um.
    pub residual_um: f64,
    /// Remaining rotary residual of A, C, arc-seconds.
    pub residual_arcsec: f64,
}

/// What the compensator does with a command within [`SINGULAR_A_DEG`] of A = 0 (the
/// pole, tool axis parallel to C), where an orientation error about the A plane's
/// normal can only be removed by a finite C move.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum PoleMode {
    /// C is not corrected, A takes the in-plane part only: safe in a moving servo loop
    /// (the online `feedback` path).
    #[default]
    Hold,
    /// Solve for the drive positions that put the actual pose on the nominal one, even
    /// if C must swing (bounded by [`Pole::max_c_swing_deg`]).
    Swing,
}

/// The pole policy.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pole {
    /// Hold or swing.
    pub mode: PoleMode,
    /// Largest C move from the command a swing may make, deg; the swing also stays
    /// within the C travel ([`Pole::c_range`]).
    pub max_c_swing_deg: f64,
}

impl Pole {
    /// The C positions a swing may use for a command at `c_deg`: within
    /// `max_c_swing_deg` of it and within the C `travel`; None if that is empty.
    pub fn c_range(&self, c_deg: f64, travel: (f64, f64)) -> Option<(f64, f64)> {
        let lo = (c_deg - self.max_c_swing_deg).max(travel.0);
        let hi = (c_deg + self.max_c_swing_deg).min(travel.1);
        (lo <= hi).then_some((lo, hi))
    }
}

impl Default for Pole {
    fn default() -> Self {
        Self {
            mode: PoleMode::Hold,
            max_c_swing_deg: 180.0,
        }
    }
}

/// Result of [`VolumetricCompensator::drive_positions_pole`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoleSolve {
    /// The drive positions; in a swing the residuals are the pose residuals (tip um,
    /// tool axis arc-seconds) and `iterations` the Newton steps.
    pub solve: Solve,
    /// Newton steps of the swing solve (0 when not swung).
    pub newton_iterations: usize,
    /// C move from the command, deg (0 when not swung).
    pub c_swing_deg: f64,
    /// A swing was wanted but failed or did no better than Hold; Hold was kept.
    pub fallback: bool,
    /// The nominal pose was reached; false after a fallback and when no C in the range
    /// reaches the nominal tool axis (see
    /// [`VolumetricCompensator::drive_positions_pole`]), where the drive positions
    /// give the least orientation error with the tip on the command.
    pub reached: bool,
}

/// The online compensator: scale positions in, corrected feedback out.
#[derive(Debug, Clone)]
pub struct VolumetricCompensator {
    model: ErrorModel,
}

impl VolumetricCompensator {
    /// A compensator for a machine's error model.
    pub fn new(model: ErrorModel) -> Self {
        Self { model }
    }

    /// The error model.
    pub fn model(&self) -> &ErrorModel {
        &self.model
    }

    /// Corrected feedback for scale positions q (X, Y, Z mm; A, C deg): the two-step
    /// calculation of the module doc. Allocation-free. A zero model returns q
    /// unchanged, bit for bit.
    #[inline]
    pub fn feedback(&self, q: &[f64; 5]) -> [f64; 5] {
        if self.model.zero {
            return *q;
        }
        let g = &self.model.geometry;
        let (p, v) = self.model.actual_pose(q);
        // Step 1: rotary angles giving the actual tool axis on the ideal machine.
        let k = if q[3] < 0.0 { -1.0 } else { 1.0 };
        let rho = (v[0] * v[0] + v[1] * v[1]).sqrt();
        let (a, c) = if q[3].abs() < SINGULAR_A_DEG {
            let (sc, cc) = q[4].to_radians().sin_cos();
            let wy = -sc * v[0] + cc * v[1];
            ((-wy).atan2(v[2]), q[4].to_radians())
        } else {
            let a = k * rho.atan2(v[2]);
            let mut c = (k * v[0]).atan2(-k * v[1]);
            let c_q = q[4].to_radians();
            c += 2.0 * PI * ((c_q - c) / (2.0 * PI)).round();
            (a, c)
        };
        // Step 2: linear positions putting the ideal tip there with A', C'.
        let (sa, ca) = a.sin_cos();
        let (sc, cc) = c.sin_cos();
        let off = head_offset(g, sa, ca, sc, cc);
        [
            p[0] - off[0],
            p[1] - off[1],
            p[2] - off[2],
            a.to_degrees(),
            c.to_degrees(),
        ]
    }

    /// Correction of each axis at scale positions q: `q - feedback(q)` (mm, deg).
    #[inline]
    pub fn correction(&self, q: &[f64; 5]) -> [f64; 5] {
        let f = self.feedback(q);
        std::array::from_fn(|i| q[i] - f[i])
    }

    /// Drive positions for a commanded pose u: iterates `q <- q - (feedback(q) - u)`
    /// until the residual is within [`TOL_UM`] and [`TOL_ARCSEC`].
    pub fn drive_positions(&self, u: &[f64; 5]) -> Solve {
        let mut q = *u;
        let mut iterations = 0;
        loop {
            let f = self.feedback(&q);
            let r: [f64; 5] = std::array::from_fn(|i| f[i] - u[i]);
            let lin_um = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt() / MM_PER_UM;
            let rot_as = r[3].abs().max(r[4].abs()) * 3600.0;
            if (lin_um <= TOL_UM && rot_as <= TOL_ARCSEC) || iterations >= MAX_ITERATIONS {
                return Solve {
                    drive: q,
                    iterations,
                    residual_um: lin_um,
                    residual_arcsec: rot_as,
                };
            }
            for i in 0..5 {
                q[i] -= r[i];
            }
            iterations += 1;
        }
    }

    /// Drive positions for a commanded pose u under a pole policy: outside the
    /// A = 0 band, and always in [`PoleMode::Hold`], exactly [`Self::drive_positions`].
    /// In [`PoleMode::Swing`] a command inside the band is solved with C free within
    /// [`Pole::c_range`]: C is the root, nearest the command, of the out-of-plane axis
    /// residual (tip and in-plane axis by Newton with C held). Where no C in the range
    /// reaches the nominal axis (an out-of-plane head error makes the tool sweep a cone
    /// that misses it, [`ErrorModel::pole_reach`]) the C of least orientation error is
    /// taken and `reached` is false. If the solve fails or does no better than Hold,
    /// the Hold result is returned and `fallback` is set.
    pub fn drive_positions_pole(&self, u: &[f64; 5], pole: &Pole) -> PoleSolve {
        let hold = self.drive_positions(u);
        let plain = PoleSolve {
            solve: hold,
            newton_iterations: 0,
            c_swing_deg: 0.0,
            fallback: false,
            reached: true,
        };
        if pole.mode == PoleMode::Hold || self.model.zero || u[3].abs() >= SINGULAR_A_DEG {
            return plain;
        }
        let swung = pole
            .c_range(u[4], self.model.travel[4])
            .and_then(|range| self.swing(u, &hold.drive, range));
        match swung {
            Some(s) if (s.solve.drive[4] - u[4]).abs() <= pole.max_c_swing_deg => s,
            _ => PoleSolve {
                fallback: true,
                reached: false,
                ..plain
            },
        }
    }

    /// The swing solve. At the pole the C-dependent errors (C location, EAC, EBC) vary
    /// with C as much as the tilt to be made, so the tilt's azimuth is found as a root
    /// of a function of C: for C held, Newton on (X, Y, Z, A) zeroes the tip residual
    /// and the in-plane tool axis residual; what is left is the out-of-plane residual
    /// f(C), which is the orientation error. The root nearest the command is bracketed
    /// on a scan within `c_range` and bisected; without a root, |f| is minimised.
    fn swing(&self, u: &[f64; 5], start: &[f64; 5], c_range: (f64, f64)) -> Option<PoleSolve> {
        let mut evals = 0usize;
        let mut f = |c: f64| {
            evals += 1;
            self.hold_c(u, start, c).map(|r| r.1)
        };
        let from = u[4].clamp(c_range.0, c_range.1);
        let (c, fc) = least_abs_root(&mut f, from, c_range, POLE_SCAN_DEG)?;
        let (drive, _) = self.hold_c(u, start, c)?;
        evals += 1;
        let reached = fc.abs() <= 0.1 * TOL_ARCSEC * RAD_PER_ARCSEC;
        let (p, v) = self.model.actual_pose(&drive);
        let (pn, vn) = nominal_pose(&self.model.geometry, u);
        let tip_um = distance_mm(&p, &pn) / MM_PER_UM;
        let orient_as = angle_rad(&v, &vn) / RAD_PER_ARCSEC;
        let hold_as = {
            let (_, vh) = self.model.actual_pose(start);
            angle_rad(&vh, &vn) / RAD_PER_ARCSEC
        };
        let ok = tip_um <= TOL_UM && (orient_as <= TOL_ARCSEC || (!reached && orient_as < hold_as));
        ok.then_some(PoleSolve {
            solve: Solve {
                drive,
                iterations: evals,
                residual_um: tip_um,
                residual_arcsec: orient_as,
            },
            newton_iterations: evals,
            c_swing_deg: (drive[4] - u[4]).abs(),
            fallback: false,
            reached,
        })
    }

    /// With C held at `c_deg`: Newton on (X, Y, Z, A) for the tip and the in-plane
    /// axis residual (nominal Jacobian by central differences); returns the drive
    /// positions and the out-of-plane axis residual, rad, signed so that it turns
    /// with C.
    fn hold_c(&self, u: &[f64; 5], start: &[f64; 5], c_deg: f64) -> Option<([f64; 5], f64)> {
        use nalgebra::{SMatrix, SVector};
        let g = &self.model.geometry;
        let (pn, vn) = nominal_pose(g, u);
        let res = |x: &SVector<f64, 4>, actual: bool| -> SVector<f64, 5> {
            let q = [x[0], x[1], x[2], x[3], c_deg];
            let (p, v) = if actual {
                self.model.actual_pose(&q)
            } else {
                nominal_pose(g, &q)
            };
            let d = [v[0] - vn[0], v[1] - vn[1], v[2] - vn[2]];
            SVector::from([p[0] - pn[0], p[1] - pn[1], p[2] - pn[2], d[0], d[1]])
        };
        let mut x = SVector::from([start[0], start[1], start[2], start[3]]);
        for _ in 0..MAX_ITERATIONS {
            let mut jac = SMatrix::<f64, 5, 4>::zeros();
            for k in 0..4 {
                let h = 1e-6; // mm or deg
                let (mut xp, mut xm) = (x, x);
                xp[k] += h;
                xm[k] -= h;
                jac.set_column(k, &((res(&xp, false) - res(&xm, false)) / (2.0 * h)));
            }
            // In-plane direction of the axis motion under A, in the x-y components
            // (the axis is near Z at the pole), and its normal.
            let m = jac.fixed_view::<2, 1>(3, 3).normalize();
            let n = [-m[1], m[0]];
            let r = res(&x, true);
            let r4 = SVector::from([r[0], r[1], r[2], r[3] * m[0] + r[4] * m[1]]);
            let out = r[3] * n[0] + r[4] * n[1];
            let q = [x[0], x[1], x[2], x[3], c_deg];
            if r4.fixed_rows::<3>(0).norm() / MM_PER_UM <= 0.1 * TOL_UM
                && r4[3].abs() / RAD_PER_ARCSEC <= 0.1 * TOL_ARCSEC
            {
                return Some((q, out));
            }
            let mut j4 = SMatrix::<f64, 4, 4>::zeros();
            j4.fixed_view_mut::<3, 4>(0, 0)
                .copy_from(&jac.fixed_view::<3, 4>(0, 0));
            for k in 0..4 {
                j4[(3, k)] = jac[(3, k)] * m[0] + jac[(4, k)] * m[1];
            }
            x -= j4.lu().solve(&r4)?;
        }
        None
    }

    /// Tip error (mm, actual minus nominal) and orientation error (rotation vector
    /// `nominal x actual`, rad) at axis positions q, as the simulated machine of
    /// `compgate-plc` wants them.
    pub fn pose_error(&self, q: &[f64; 5]) -> ([f64; 3], [f64; 3]) {
        let (p, v) = self.model.actual_pose(q);
        let (pn, vn) = nominal_pose(&self.model.geometry, q);
        let w = [
            vn[1] * v[2] - vn[2] * v[1],
            vn[2] * v[0] - vn[0] * v[2],
            vn[0] * v[1] - vn[1] * v[0],
        ];
        ([p[0] - pn[0], p[1] - pn[1], p[2] - pn[2]], w)
    }
}

/// A synthetic but realistic error set (tens of um, tens of arc-seconds) of a
/// machine with 1000 x 800 x 600 mm travel, A +-100 deg, C +-200 deg; the source of
/// `config/volumetric-example.errors`. `scale` multiplies every error.
pub fn synthetic_model(scale: f64) -> ErrorModel {
    let travel = [
        (0.0, 1000.0),
        (0.0, 800.0),
        (0.0, 600.0),
        (-100.0, 100.0),
        (-200.0, 200.0),
    ];
    // Per axis and column: amplitude (um or arcsec) of a linear and a wave term.
    let amp: [[(f64, f64); 6]; 5] = [
        [
            (18.0, 4.0),
            (-6.0, 3.0),
            (5.0, 2.0),
            (3.0, 2.0),
            (-8.0, 4.0),
            (6.0, 3.0),
        ],
        [
            (-14.0, 5.0),
            (4.0, 2.0),
            (-7.0, 3.0),
            (-5.0, 3.0),
            (4.0, 2.0),
            (7.0, 2.0),
        ],
        [
            (10.0, 3.0),
            (-5.0, 2.0),
            (6.0, 2.0),
            (6.0, 3.0),
            (-4.0, 3.0),
            (3.0, 1.0),
        ],
        [
            (6.0, 4.0),
            (-8.0, 5.0),
            (5.0, 3.0),
            (20.0, 8.0),
            (-10.0, 5.0),
            (8.0, 4.0),
        ],
        [
            (-7.0, 5.0),
            (6.0, 4.0),
            (4.0, 3.0),
            (-9.0, 4.0),
            (7.0, 3.0),
            (25.0, 10.0),
        ],
    ];
    let tables: [Table; 5] = std::array::from_fn(|i| {
        let (lo, hi) = travel[i];
        let n = if i < 3 { 11 } else { 21 };
        let mut pos = Vec::with_capacity(n);
        let mut val = Vec::with_capacity(n);
        for j in 0..n {
            let s = j as f64 / (n - 1) as f64;
            pos.push(lo + s * (hi - lo));
            val.push(std::array::from_fn(|c| {
                let (l, w) = amp[i][c];
                let e = l * (s - 0.5) + w * (2.0 * PI * s * 1.5 + c as f64).sin();
                let unit = if c < 3 { MM_PER_UM } else { RAD_PER_ARCSEC };
                (e * 1e4).round() / 1e4 * unit * scale
            }));
        }
        Table::new(pos, val)
    });
    ErrorModel::new(
        Geometry {
            pivot_mm: [0.0, 0.0, -150.0],
            tool_length_mm: 250.0,
        },
        travel,
        tables,
        [6.0, -4.0, 5.0].map(|v| v * RAD_PER_ARCSEC * scale),
        [
            8.0 * MM_PER_UM,
            -6.0 * MM_PER_UM,
            5.0 * RAD_PER_ARCSEC,
            -7.0 * RAD_PER_ARCSEC,
        ]
        .map(|v| v * scale),
        [
            5.0 * MM_PER_UM,
            9.0 * MM_PER_UM,
            -4.0 * RAD_PER_ARCSEC,
            6.0 * RAD_PER_ARCSEC,
        ]
        .map(|v| v * scale),
    )
}

/// [`synthetic_model`] without the head's out-of-plane errors (EBA, EBC, BOA, BOC
/// zero): the cone the tool sweeps about A then passes through the C axis (cap
/// radius 0, [`ErrorModel::pole_reach`]), so a C move reaches every tool axis at the
/// pole; the source of `config/volumetric-in-plane.errors`.
pub fn synthetic_model_in_plane(scale: f64) -> ErrorModel {
    let m = synthetic_model(scale);
    let mut tables = m.tables.clone();
    for t in &mut tables[3..] {
        for row in &mut t.val {
            row[4] = 0.0;
        }
    }
    let [xoc, yoc, aoc, _] = m.loc_c;
    let [yoa, zoa, _, coa] = m.loc_a;
    ErrorModel::new(
        m.geometry,
        m.travel,
        tables,
        m.squareness_rad,
        [xoc, yoc, aoc, 0.0],
        [yoa, zoa, 0.0, coa],
    )
}

/// Arguments of `compgate volumetric`.
#[derive(Debug, Clone, clap::Args)]
pub struct VolumetricArgs {
    /// Error parameter file (format: `compgate-volumetric-errors 1`).
    #[arg(long, value_name = "FILE")]
    pub errors: PathBuf,
    /// Evaluation grid: a count of points per axis over its travel (e.g. `4`), or
    /// per-axis ranges `X=0:1000:5,A=-90:90:4` (start:end:count; axes not named get 3
    /// points over their travel).
    #[arg(long, default_value = "4")]
    pub grid: String,
    /// Directory for the SVG error maps (created if missing).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Within 1 deg of A = 0 (the pole): `hold` leaves C alone (safe online), `swing`
    /// solves for the drive positions even if C must swing.
    #[arg(long, value_enum, default_value_t = PoleMode::Hold)]
    pub pole: PoleMode,
    /// Largest C move a pole swing may make, deg (beyond it Hold is kept).
    #[arg(long = "max-c-swing", value_name = "DEG", default_value_t = 180.0)]
    pub max_c_swing_deg: f64,
}

/// Grid axes: the values of each of the five axes.
pub fn parse_grid(spec: &str, travel: &[(f64, f64); 5]) -> Result<[Vec<f64>; 5], VolumetricError> {
    let lin = |lo: f64, hi: f64, n: usize| -> Vec<f64> {
        if n == 1 {
            vec![(lo + hi) / 2.0]
        } else {
            (0..n)
                .map(|i| lo + (hi - lo) * i as f64 / (n - 1) as f64)
                .collect()
        }
    };
    let count = |s: &str| -> Result<usize, VolumetricError> {
        match s.trim().parse::<usize>() {
            Ok(n) if (1..=1000).contains(&n) => Ok(n),
            _ => Err(VolumetricError::Grid(format!("bad count {s:?} (1..=1000)"))),
        }
    };
    let spec = spec.trim();
    if !spec.contains('=') {
        let n = count(spec)?;
        return Ok(std::array::from_fn(|i| lin(travel[i].0, travel[i].1, n)));
    }
    let mut out: [Option<Vec<f64>>; 5] = Default::default();
    for part in spec.split(',') {
        let (name, range) = part.split_once('=').ok_or_else(|| {
            VolumetricError::Grid(format!("expected AXIS=start:end:count, got {part:?}"))
        })?;
        let i = AXES
            .iter()
            .position(|a| a.eq_ignore_ascii_case(name.trim()))
            .ok_or_else(|| VolumetricError::Grid(format!("unknown axis {name:?}")))?;
        let f: Vec<&str> = range.split(':').collect();
        if f.len() != 3 {
            return Err(VolumetricError::Grid(format!(
                "{name}: expected start:end:count, got {range:?}"
            )));
        }
        let num = |s: &str| {
            s.trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| VolumetricError::Grid(format!("{name}: not a number {s:?}")))
        };
        let (lo, hi, n) = (num(f[0])?, num(f[1])?, count(f[2])?);
        let (tlo, thi) = travel[i];
        if lo < tlo || hi > thi || lo > hi {
            return Err(VolumetricError::Grid(format!(
                "{name}: {lo}..{hi} outside the travel {tlo}..{thi}"
            )));
        }
        out[i] = Some(lin(lo, hi, n));
    }
    Ok(std::array::from_fn(|i| {
        out[i]
            .take()
            .unwrap_or_else(|| lin(travel[i].0, travel[i].1, 3))
    }))
}

/// Statistics of one evaluation.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Stats {
    /// Largest tip error, um.
    pub max_tip_um: f64,
    /// RMS tip error, um.
    pub rms_tip_um: f64,
    /// Largest orientation error, arc-seconds.
    pub max_orient_arcsec: f64,
    /// RMS orientation error, arc-seconds.
    pub rms_orient_arcsec: f64,
}

/// Per-pose errors of a grid evaluation.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Evaluation {
    /// The commanded poses.
    pub poses: Vec<[f64; 5]>,
    /// Uncompensated (tip um, orientation arcsec) per pose.
    pub uncompensated: Vec<(f64, f64)>,
    /// Compensated (tip um, orientation arcsec) per pose.
    pub compensated: Vec<(f64, f64)>,
    /// Most iterations needed.
    pub max_iterations: usize,
    /// Largest final residual, um and arc-seconds.
    pub max_residual: (f64, f64),
    /// Per pose: within [`SINGULAR_A_DEG`] of A = 0, where the orientation is only
    /// partly correctable; the statistics report these poses apart.
    pub singular: Vec<bool>,
    /// The pole policy used.
    pub pole: Pole,
    /// Largest C swing made at the pole, deg.
    pub max_c_swing_deg: f64,
    /// Most Newton steps of a pole swing.
    pub max_pole_iterations: usize,
    /// Band poses where a swing was wanted but Hold was kept.
    pub pole_fallbacks: usize,
    /// Band poses whose nominal tool axis no C reaches (least error taken).
    pub pole_unreachable: usize,
    /// Per pose in the A = 0 band, what the pole allows ([`ErrorModel::pole_reach`]):
    /// with C in the policy's range ([`Pole::c_range`]) and with C over its whole
    /// travel; None off the band.
    pub pole_reach: Vec<Option<(PoleReach, PoleReach)>>,
}

/// Tolerance of "at the achievable minimum" at the pole: this many arc-seconds or
/// [`POLE_TOL_FRACTION`] of the pose's uncompensated orientation error, the larger.
pub const POLE_TOL_ARCSEC: f64 = 0.01;
/// See [`POLE_TOL_ARCSEC`].
pub const POLE_TOL_FRACTION: f64 = 0.01;

/// The A = 0 band poses against the achievable minimum of their orientation error
/// (C in the policy's range). Reachable: the minimum is within [`TOL_ARCSEC`] of 0;
/// at the minimum: the compensated error exceeds it by at most the tolerance of
/// [`POLE_TOL_ARCSEC`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PoleClasses {
    /// Reachable and reached.
    pub reached: usize,
    /// Reachable but not reached (a solver defect, or the Hold policy).
    pub missed: usize,
    /// Unreachable, at the minimum.
    pub at_minimum: usize,
    /// Unreachable, above the minimum (a solver defect, or the Hold policy).
    pub above_minimum: usize,
    /// Largest compensated orientation error minus the minimum, arc-seconds.
    pub max_excess_arcsec: f64,
    /// Largest and RMS achievable minimum, C in the policy's range, arc-seconds.
    pub min_max_arcsec: f64,
    /// See `min_max_arcsec`.
    pub min_rms_arcsec: f64,
    /// Largest achievable minimum with C over its whole travel, arc-seconds.
    pub travel_min_max_arcsec: f64,
    /// Poses whose minimum is lower (by more than the tolerance) with C over its
    /// whole travel than in the policy's range.
    pub lower_over_travel: usize,
    /// Over the unreachable poses: range of the cap radius and of the nominal axis'
    /// distance from the actual C axis, arc-seconds.
    pub cap_arcsec: (f64, f64),
    /// See `cap_arcsec`.
    pub offset_arcsec: (f64, f64),
}

fn stats<'a>(e: impl Iterator<Item = &'a (f64, f64)>) -> Stats {
    let mut n = 0usize;
    let mut s = Stats::default();
    let (mut st, mut so) = (0.0, 0.0);
    for (t, o) in e {
        n += 1;
        s.max_tip_um = s.max_tip_um.max(*t);
        s.max_orient_arcsec = s.max_orient_arcsec.max(*o);
        st += t * t;
        so += o * o;
    }
    let n = n.max(1) as f64;
    s.rms_tip_um = (st / n).sqrt();
    s.rms_orient_arcsec = (so / n).sqrt();
    s
}

impl Evaluation {
    fn pick<'a>(
        &'a self,
        e: &'a [(f64, f64)],
        singular: bool,
    ) -> impl Iterator<Item = &'a (f64, f64)> + 'a {
        e.iter()
            .zip(&self.singular)
            .filter(move |(_, s)| **s == singular)
            .map(|(e, _)| e)
    }
    /// Statistics of the uncompensated errors (poses outside the A = 0 band).
    pub fn uncompensated_stats(&self) -> Stats {
        stats(self.pick(&self.uncompensated, false))
    }
    /// Statistics of the compensated errors (poses outside the A = 0 band).
    pub fn compensated_stats(&self) -> Stats {
        stats(self.pick(&self.compensated, false))
    }
    /// The band poses sorted against their achievable minimum ([`PoleClasses`]).
    pub fn pole_classes(&self) -> PoleClasses {
        let mut k = PoleClasses {
            cap_arcsec: (f64::INFINITY, 0.0),
            offset_arcsec: (f64::INFINITY, 0.0),
            ..PoleClasses::default()
        };
        let mut sum_sq = 0.0;
        let mut n = 0usize;
        for ((reach, unc), comp) in self
            .pole_reach
            .iter()
            .zip(&self.uncompensated)
            .zip(&self.compensated)
        {
            let Some((r, rt)) = reach else { continue };
            let tol = POLE_TOL_ARCSEC.max(POLE_TOL_FRACTION * unc.1);
            let excess = comp.1 - r.min_arcsec;
            let at_min = excess <= tol;
            let reachable = r.min_arcsec <= TOL_ARCSEC;
            match (reachable, at_min) {
                (true, true) => k.reached += 1,
                (true, false) => k.missed += 1,
                (false, true) => k.at_minimum += 1,
                (false, false) => k.above_minimum += 1,
            }
            if !reachable {
                k.cap_arcsec = (
                    k.cap_arcsec.0.min(r.cap_arcsec),
                    k.cap_arcsec.1.max(r.cap_arcsec),
                );
                k.offset_arcsec = (
                    k.offset_arcsec.0.min(r.offset_arcsec),
                    k.offset_arcsec.1.max(r.offset_arcsec),
                );
            }
            k.max_excess_arcsec = k.max_excess_arcsec.max(excess);
            k.min_max_arcsec = k.min_max_arcsec.max(r.min_arcsec);
            k.travel_min_max_arcsec = k.travel_min_max_arcsec.max(rt.min_arcsec);
            k.lower_over_travel += usize::from(rt.min_arcsec < r.min_arcsec - tol);
            sum_sq += r.min_arcsec * r.min_arcsec;
            n += 1;
        }
        k.min_rms_arcsec = (sum_sq / n.max(1) as f64).sqrt();
        if k.at_minimum + k.above_minimum == 0 {
            k.cap_arcsec = (0.0, 0.0);
            k.offset_arcsec = (0.0, 0.0);
        }
        k
    }

    /// Poses within the A = 0 band: their count and (uncompensated, compensated)
    /// statistics.
    pub fn singular_stats(&self) -> (usize, Stats, Stats) {
        (
            self.singular.iter().filter(|s| **s).count(),
            stats(self.pick(&self.uncompensated, true)),
            stats(self.pick(&self.compensated, true)),
        )
    }
}

/// Evaluates every grid pose uncompensated (drives at the command) and compensated
/// (drives where the feedback equals the command).
pub fn evaluate(comp: &VolumetricCompensator, grid: &[Vec<f64>; 5]) -> Evaluation {
    evaluate_pole(comp, grid, &Pole::default())
}

/// [`evaluate`] under a pole policy.
pub fn evaluate_pole(
    comp: &VolumetricCompensator,
    grid: &[Vec<f64>; 5],
    pole: &Pole,
) -> Evaluation {
    let model = comp.model();
    let g = &model.geometry;
    let mut ev = Evaluation {
        pole: *pole,
        ..Evaluation::default()
    };
    let err = |q: &[f64; 5], u: &[f64; 5]| {
        let (p, v) = model.actual_pose(q);
        let (pn, vn) = nominal_pose(g, u);
        (
            distance_mm(&p, &pn) / MM_PER_UM,
            angle_rad(&v, &vn) / RAD_PER_ARCSEC,
        )
    };
    for &x in &grid[0] {
        for &y in &grid[1] {
            for &z in &grid[2] {
                for &a in &grid[3] {
                    for &c in &grid[4] {
                        let u = [x, y, z, a, c];
                        let ps = comp.drive_positions_pole(&u, pole);
                        let s = ps.solve;
                        ev.max_c_swing_deg = ev.max_c_swing_deg.max(ps.c_swing_deg);
                        ev.max_pole_iterations = ev.max_pole_iterations.max(ps.newton_iterations);
                        ev.pole_fallbacks += usize::from(ps.fallback);
                        ev.pole_unreachable += usize::from(!ps.reached);
                        ev.poses.push(u);
                        ev.singular.push(a.abs() < SINGULAR_A_DEG);
                        let travel_c = model.travel[4];
                        ev.pole_reach
                            .push((a.abs() < SINGULAR_A_DEG && !model.zero).then(|| {
                                let range = pole.c_range(c, travel_c).unwrap_or((c, c));
                                (model.pole_reach(&u, range), model.pole_reach(&u, travel_c))
                            }));
                        ev.uncompensated.push(err(&u, &u));
                        ev.compensated.push(err(&s.drive, &u));
                        // Swing solves count apart (Newton steps, pose residuals).
                        if ps.newton_iterations == 0 {
                            ev.max_iterations = ev.max_iterations.max(s.iterations);
                            ev.max_residual.0 = ev.max_residual.0.max(s.residual_um);
                            ev.max_residual.1 = ev.max_residual.1.max(s.residual_arcsec);
                        }
                    }
                }
            }
        }
    }
    ev
}

/// The report of an evaluation.
pub fn report(ev: &Evaluation) -> String {
    let (u, c) = (ev.uncompensated_stats(), ev.compensated_stats());
    let pct = |a: f64, b: f64| if b > 0.0 { 100.0 * a / b } else { 0.0 };
    let mut s = String::new();
    let (n_sing, su, sc) = ev.singular_stats();
    let _ = writeln!(
        s,
        "volumetric compensation over {} grid poses{}",
        ev.poses.len() - n_sing,
        if n_sing > 0 {
            format!(" ({n_sing} more within {SINGULAR_A_DEG} deg of A = 0, below)")
        } else {
            String::new()
        }
    );
    let _ = writeln!(
        s,
        "                     uncompensated   compensated   remaining"
    );
    for (label, uncomp, comp) in [
        ("tip max (um)        ", u.max_tip_um, c.max_tip_um),
        ("tip RMS (um)        ", u.rms_tip_um, c.rms_tip_um),
        (
            "orientation max (\")",
            u.max_orient_arcsec,
            c.max_orient_arcsec,
        ),
        (
            "orientation RMS (\")",
            u.rms_orient_arcsec,
            c.rms_orient_arcsec,
        ),
    ] {
        let _ = writeln!(
            s,
            "{label} {uncomp:>13.4} {comp:>13.6} {:>10.4}%",
            pct(comp, uncomp)
        );
    }
    let _ = writeln!(
        s,
        "iterations: at most {} (tolerance {TOL_UM} um, {TOL_ARCSEC}\"); largest residual {:.2e} um, {:.2e}\"",
        ev.max_iterations, ev.max_residual.0, ev.max_residual.1
    );
    if n_sing > 0 {
        let k = ev.pole_classes();
        let travel = if k.lower_over_travel > 0 {
            format!(
                ", {:.4}\" with C over its whole travel (lower for {} poses)",
                k.travel_min_max_arcsec, k.lower_over_travel
            )
        } else {
            String::new()
        };
        let why = if k.at_minimum + k.above_minimum > 0 {
            format!(
                " (no A/C reaches the nominal axis for {} poses: the cone the tool sweeps \
                 about A misses the actual C axis by a cap radius of {:.2}..{:.2}\", the \
                 nominal axis lies {:.2}..{:.2}\" from the actual C axis)",
                k.at_minimum + k.above_minimum,
                k.cap_arcsec.0,
                k.cap_arcsec.1,
                k.offset_arcsec.0,
                k.offset_arcsec.1
            )
        } else {
            String::new()
        };
        if ev.pole.mode == PoleMode::Swing {
            let _ = writeln!(
                s,
                "A = 0 band ({n_sing} poses, pole mode swing, C within {} deg of the command \
                 and its travel): tip max {:.4} -> {:.6} um ({:.4} %)",
                ev.pole.max_c_swing_deg,
                su.max_tip_um,
                sc.max_tip_um,
                pct(sc.max_tip_um, su.max_tip_um)
            );
            let _ = writeln!(
                s,
                "  orientation max {:.4} -> {:.4}\" = achievable minimum {:.4}\"{why}; RMS \
                 {:.4} -> {:.4}\" (minimum {:.4}\"){travel}",
                su.max_orient_arcsec,
                sc.max_orient_arcsec,
                k.min_max_arcsec,
                su.rms_orient_arcsec,
                sc.rms_orient_arcsec,
                k.min_rms_arcsec
            );
            let _ = writeln!(
                s,
                "  against the minimum (within {POLE_TOL_ARCSEC}\" or {} % of the \
                 uncompensated error): {} reachable and reached, {} reachable but missed, {} \
                 unreachable and at the minimum, {} unreachable and above it (largest excess \
                 {:+.4}\")",
                100.0 * POLE_TOL_FRACTION,
                k.reached,
                k.missed,
                k.at_minimum,
                k.above_minimum,
                k.max_excess_arcsec
            );
            let _ = writeln!(
                s,
                "  largest C swing {:.2} deg, fixed-C solves at most {}, {} poses kept on \
                 hold (no C did better)",
                ev.max_c_swing_deg, ev.max_pole_iterations, ev.pole_fallbacks
            );
        } else {
            let _ = writeln!(
                s,
                "A = 0 band ({n_sing} poses, pole mode hold, C not corrected): tip max {:.4} -> {:.6} um, \
                 orientation max {:.4} -> {:.4}\" (the part about the A plane's normal needs \
                 a C move)",
                su.max_tip_um, sc.max_tip_um, su.max_orient_arcsec, sc.max_orient_arcsec
            );
            let _ = writeln!(
                s,
                "  with --pole swing (C within {} deg): achievable minimum {:.4}\"{why}{travel}",
                ev.pole.max_c_swing_deg, k.min_max_arcsec
            );
        }
    }
    s
}

/// Writes the SVG error maps into `dir`: `tip-error.svg` and `orientation-error.svg`
/// (error per grid pose, uncompensated and compensated) and `tip-error-xy.svg` (the
/// uncompensated tip error over X and Y, worst over the other axes).
pub fn write_svgs(dir: &Path, ev: &Evaluation) -> Result<Vec<PathBuf>, VolumetricError> {
    std::fs::create_dir_all(dir)
        .map_err(|e| VolumetricError::Io(format!("{}: {e}", dir.display())))?;
    let mut written = Vec::new();
    for (name, pick, unit) in [
        ("tip-error.svg", 0usize, "tip error (um)"),
        ("orientation-error.svg", 1, "orientation error (arcsec)"),
    ] {
        let path = dir.join(name);
        let io = |e: PlotError| VolumetricError::Io(format!("{}: {e}", path.display()));
        let get = |t: &(f64, f64)| if pick == 0 { t.0 } else { t.1 };
        let n = ev.poses.len().max(2);
        let root = plot::canvas(&path, (1000, 700)).map_err(io)?;
        let (upper, lower) = root.split_vertically(350);
        for (area, series, color, label) in [
            (&upper, &ev.uncompensated, plot::RED, "uncompensated"),
            (&lower, &ev.compensated, plot::BLUE, "compensated"),
        ] {
            let hi = series.iter().map(get).fold(1e-12, f64::max) * 1.05;
            let mut chart = plot::Frame::new("grid pose (X outermost, C innermost)", unit)
                .caption(
                    format!("{label} {unit} per grid pose (max {:.4})", hi / 1.05),
                    18,
                )
                .label_areas(30, 80)
                .draw(area, 0.0..(n - 1) as f64, 0.0..hi)
                .map_err(io)?;
            let pts = series.iter().enumerate().map(|(i, t)| (i as f64, get(t)));
            plot::line(&mut chart, pts, color, None).map_err(io)?;
        }
        plot::finish(&root).map_err(io)?;
        written.push(path.clone());
    }
    // X-Y map of the worst uncompensated tip error.
    let path = dir.join("tip-error-xy.svg");
    let io = |e: PlotError| VolumetricError::Io(format!("{}: {e}", path.display()));
    let mut xs: Vec<f64> = ev.poses.iter().map(|p| p[0]).collect();
    let mut ys: Vec<f64> = ev.poses.iter().map(|p| p[1]).collect();
    for v in [&mut xs, &mut ys] {
        v.sort_by(f64::total_cmp);
        v.dedup();
    }
    let mut cell = vec![0.0f64; xs.len() * ys.len()];
    for (p, e) in ev.poses.iter().zip(&ev.uncompensated) {
        let i = xs.partition_point(|x| *x < p[0]);
        let j = ys.partition_point(|y| *y < p[1]);
        let k = i * ys.len() + j;
        if let Some(c) = cell.get_mut(k) {
            *c = c.max(e.0);
        }
    }
    let top = cell.iter().copied().fold(1e-9, f64::max);
    let bottom = cell.iter().copied().fold(top, f64::min);
    let half = |v: &[f64], i: usize| -> (f64, f64) {
        let w = if v.len() > 1 {
            (v[v.len() - 1] - v[0]) / (v.len() - 1) as f64
        } else {
            1.0
        };
        (v[i] - w / 2.0, v[i] + w / 2.0)
    };
    if !xs.is_empty() && !ys.is_empty() {
        let (x0, _) = half(&xs, 0);
        let (_, x1) = half(&xs, xs.len() - 1);
        let (y0, _) = half(&ys, 0);
        let (_, y1) = half(&ys, ys.len() - 1);
        let root = plot::canvas(&path, (800, 700)).map_err(io)?;
        let mut chart = plot::Frame::new("X (mm)", "Y (mm)")
            .caption(
                format!(
                    "uncompensated tip error over X-Y, worst over Z, A, C \
                     (blue {bottom:.1} .. red {top:.1} um)"
                ),
                18,
            )
            .draw(&root, x0..x1, y0..y1)
            .map_err(io)?;
        let mut rects = Vec::with_capacity(cell.len());
        for i in 0..xs.len() {
            for j in 0..ys.len() {
                let v = (cell[i * ys.len() + j] - bottom) / (top - bottom).max(1e-12);
                let (a0, a1) = half(&xs, i);
                let (b0, b1) = half(&ys, j);
                rects.push(((a0, b0), (a1, b1), plot::blue_to_red(v, 64)));
            }
        }
        plot::cells(&mut chart, rects).map_err(io)?;
        plot::finish(&root).map_err(io)?;
        written.push(path.clone());
    }
    Ok(written)
}

/// `compgate volumetric`: reads the error file, evaluates the grid uncompensated and
/// compensated, writes the SVG maps with `--out`, and returns the report.
pub fn run(args: &VolumetricArgs) -> Result<String, VolumetricError> {
    let text = std::fs::read_to_string(&args.errors)
        .map_err(|e| VolumetricError::Io(format!("{}: {e}", args.errors.display())))?;
    let model = parse(&text).map_err(|e| match e {
        VolumetricError::Parse {
            line,
            field,
            message,
        } => VolumetricError::Parse {
            line,
            field: format!("{}: {field}", args.errors.display()),
            message,
        },
        other => other,
    })?;
    let grid = parse_grid(&args.grid, &model.travel)?;
    let comp = VolumetricCompensator::new(model);
    let pole = Pole {
        mode: args.pole,
        max_c_swing_deg: args.max_c_swing_deg,
    };
    if !(pole.max_c_swing_deg >= 0.0 && pole.max_c_swing_deg.is_finite()) {
        return Err(VolumetricError::Grid(format!(
            "--max-c-swing: {} deg is not a finite angle >= 0",
            pole.max_c_swing_deg
        )));
    }
    let ev = evaluate_pole(&comp, &grid, &pole);
    let mut s = report(&ev);
    if let Some(dir) = &args.out {
        for p in write_svgs(dir, &ev)? {
            let _ = writeln!(s, "wrote {}", p.display());
        }
    }
    Ok(s)
}

/// Result of [`bench_per_s`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bench {
    /// Compensations ([`VolumetricCompensator::feedback`]) per second on one core.
    pub per_s: f64,
    /// Time of one compensation, ns.
    pub ns_each: f64,
}

/// Measures [`VolumetricCompensator::feedback`] on the synthetic model over a
/// pseudo-random sweep of poses for about `seconds`, on the calling thread.
pub fn bench_per_s(seconds: f64) -> Bench {
    let comp = VolumetricCompensator::new(synthetic_model(1.0));
    let t = comp.model().travel;
    let mut poses = [[0.0; 5]; 256];
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    for p in poses.iter_mut() {
        for (i, v) in p.iter_mut().enumerate() {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let s = (state >> 11) as f64 / (1u64 << 53) as f64;
            *v = t[i].0 + s * (t[i].1 - t[i].0);
        }
    }
    let start = Instant::now();
    let mut n = 0u64;
    let mut sink = 0.0;
    loop {
        for p in &poses {
            let f = comp.feedback(std::hint::black_box(p));
            sink += f[0];
        }
        n += poses.len() as u64;
        if start.elapsed().as_secs_f64() >= seconds {
            break;
        }
    }
    std::hint::black_box(sink);
    let el = start.elapsed().as_secs_f64();
    Bench {
        per_s: n as f64 / el,
        ns_each: el * 1e9 / n as f64,
    }
}
