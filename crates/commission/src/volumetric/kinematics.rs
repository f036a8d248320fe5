//! The kinematics of the AC head with its errors and the compensator: pure math on
//! `[f64; 5]` poses, no I/O (see the module doc of [`super`]).

use std::f64::consts::PI;

use super::{
    MAX_ITERATIONS, MAX_ONLINE_C_CORRECTION_DEG, MM_PER_UM, RAD_PER_ARCSEC, TOL_ARCSEC, TOL_UM,
};
use crate::stats;

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
    pub(super) pos: Vec<f64>,
    pub(super) val: Vec<[f64; 6]>,
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
    pub(super) tables: [Table; 5],
    /// EC0Y, EB0Z, EA0Z, rad.
    pub(super) squareness_rad: [f64; 3],
    /// XOC, YOC (mm), AOC, BOC (rad).
    pub(super) loc_c: [f64; 4],
    /// YOA, ZOA (mm), BOA, COA (rad).
    pub(super) loc_a: [f64; 4],
    /// Every error is zero: the compensator passes positions through.
    pub(super) zero: bool,
}

impl ErrorModel {
    /// A model from its parts (tables in mm / rad, squareness in rad, locations in mm
    /// and rad, order as [`super::SQUARENESS`], [`super::LOCATION_C`], [`super::LOCATION_A`]).
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
        // A: T(pivot) L_A E_A Rx(a) L_A^-1
        let [yoa, zoa, boa, coa] = self.loc_a;
        let la = ([0.0, boa, coa], [0.0, yoa, zoa]);
        rotary_link(&self.tables[3], q[3], la, rot_x, &mut p, &mut v);
        for (pk, dk) in p.iter_mut().zip(&g.pivot_mm) {
            *pk += dk;
        }
        // C: L_C E_C Rz(c) L_C^-1
        let [xoc, yoc, aoc, boc] = self.loc_c;
        let lc = ([aoc, boc, 0.0], [xoc, yoc, 0.0]);
        rotary_link(&self.tables[4], q[4], lc, rot_z, &mut p, &mut v);
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
    /// `EBA(A) - BOC + EBC'(C)`: the tool's tilt out of the plane normal to A
    /// (`EBA - BOA`) plus A's tilt out of the plane normal to C (`BOA - BOC + EBC'`,
    /// `EBC' = cos(C) EBC - sin(C) EAC`, C's machine-frame tilt about its rotor's Y). So
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
        // EAC, EBC act in the machine frame: their part about the C rotor's Y axis
        // (normal to the A plane) is -sin(C) EAC + cos(C) EBC.
        let cap = |c_deg: f64| {
            let e = self.tables[4].eval(c_deg);
            let (s, c) = c_deg.to_radians().sin_cos();
            eba - boc - s * e[3] + c * e[4]
        };
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

/// How far beyond its programmed travel the drive loop may take C before the pose
/// counts as limited, deg: near the pole the C correction grows as 1/sin(A) (0.16
/// deg at A = 1 deg on the example), and the NC's software limits must leave this
/// margin beyond the travel of the error file.
pub const TRAVEL_MARGIN_DEG: f64 = 1.0;

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

/// Applies a rotary link `L E(angle) Rot(angle) L^-1` to a point and a vector: `loc`
/// is the location `L` (rotation, translation), `table` gives `E`, `rot` turns by the
/// angle's sine and cosine.
#[inline]
fn rotary_link(
    table: &Table,
    angle_deg: f64,
    (loc_r, loc_t): ([f64; 3], [f64; 3]),
    rot: fn(f64, f64, &mut [f64; 3], &mut [f64; 3]),
    p: &mut [f64; 3],
    v: &mut [f64; 3],
) {
    inv_small(&loc_r, &loc_t, p, v);
    let (s, c) = angle_deg.to_radians().sin_cos();
    rot(s, c, p, v);
    // The error motions after the rotation: they are measured in the stator's frame
    // (ISO 230-7), so a constant EAC/EBC tilts the axis line itself, like AOC/BOC.
    small(&table.eval(angle_deg), p, v);
    let [tx, ty, tz] = loc_t;
    let [rx, ry, rz] = loc_r;
    small(&[tx, ty, tz, rx, ry, rz], p, v);
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
    /// Remaining rotary residual: the hypot of the A and C residuals, arc-seconds.
    pub residual_arcsec: f64,
    /// The drive positions lie in the pole band ([`VolumetricCompensator::feedback_at_pole`]),
    /// where the feedback holds C: the orientation is only partly corrected.
    pub band: bool,
}

/// What the compensator does with a command in the pole band near A = 0 (the tool
/// axis so close to C that the feedback holds C, [`VolumetricCompensator::feedback_at_pole`]),
/// where an orientation error about the A plane's normal can only be removed by a
/// finite C move.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PoleMode {
    /// C is not corrected, A takes the in-plane part only: what the per-cycle
    /// `feedback` does in the band.
    Hold,
    /// Solve for the drive positions that put the actual pose on the nominal one, or
    /// at the least orientation error the head allows, even if C must swing (bounded
    /// by [`Pole::max_c_swing_deg`] and the C travel). The default.
    #[default]
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
            mode: PoleMode::Swing,
            max_c_swing_deg: 720.0,
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
    /// Off the band, the drive loop converged with C more than [`TRAVEL_MARGIN_DEG`]
    /// past its travel (near the pole, where the C correction grows): Swing solves it
    /// as a band pose, Hold keeps it there.
    pub c_past_travel: bool,
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
        self.feedback_at_pole(q).0
    }

    /// [`Self::feedback`], and whether q lies in the pole band: there the C' of step 1
    /// would differ from C by more than [`MAX_ONLINE_C_CORRECTION_DEG`] (the tool axis
    /// is so close to C that its azimuth is ill-conditioned), so C is held and A' takes
    /// the in-plane part only.
    #[inline]
    pub fn feedback_at_pole(&self, q: &[f64; 5]) -> ([f64; 5], bool) {
        if self.model.zero {
            return (*q, false);
        }
        let g = &self.model.geometry;
        let (p, v) = self.model.actual_pose(q);
        // Step 1: rotary angles giving the actual tool axis on the ideal machine.
        let k = if q[3] < 0.0 { -1.0 } else { 1.0 };
        let rho = (v[0] * v[0] + v[1] * v[1]).sqrt();
        let c_q = q[4].to_radians();
        let mut c_reg = (k * v[0]).atan2(-k * v[1]);
        c_reg += 2.0 * PI * ((c_q - c_reg) / (2.0 * PI)).round();
        // The regular step 1 up to half the limit of the C correction, hold beyond
        // the limit, blended linearly between: the feedback stays continuous, so a
        // servo loop on it does not chatter at the band's edge. (NaN: hold.)
        let limit = MAX_ONLINE_C_CORRECTION_DEG.to_radians();
        let w = (2.0 - 2.0 * (c_reg - c_q).abs() / limit).clamp(0.0, 1.0);
        let w = if w.is_nan() { 0.0 } else { w };
        let band = w < 1.0;
        // Hold: A' takes the in-plane part, -w_y with w the axis in the C frame.
        let a_hold = || {
            let (sc, cc) = c_q.sin_cos();
            (sc * v[0] - cc * v[1]).atan2(v[2])
        };
        let (a, c) = if !band {
            (k * rho.atan2(v[2]), c_reg)
        } else if w == 0.0 {
            (a_hold(), c_q)
        } else {
            let a_reg = k * rho.atan2(v[2]);
            (w * a_reg + (1.0 - w) * a_hold(), c_q + w * (c_reg - c_q))
        };
        // Step 2: linear positions putting the ideal tip there with A', C'.
        let (sa, ca) = a.sin_cos();
        let (sc, cc) = c.sin_cos();
        let off = head_offset(g, sa, ca, sc, cc);
        (
            [
                p[0] - off[0],
                p[1] - off[1],
                p[2] - off[2],
                a.to_degrees(),
                c.to_degrees(),
            ],
            band,
        )
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
            let (f, band) = self.feedback_at_pole(&q);
            let r: [f64; 5] = std::array::from_fn(|i| f[i] - u[i]);
            let lin_um = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt() / MM_PER_UM;
            // A and C turn the tool axis about perpendicular axes, C by up to its
            // residual (at A = 90 deg): together by at most their hypot. The larger
            // of the two alone let the tool axis stop up to 1.4 times the tolerance
            // off (0.00104" after one step at A = 62.5 deg).
            let rot_as = r[3].hypot(r[4]) * 3600.0;
            if (lin_um <= TOL_UM && rot_as <= TOL_ARCSEC) || iterations >= MAX_ITERATIONS {
                return Solve {
                    drive: q,
                    iterations,
                    residual_um: lin_um,
                    residual_arcsec: rot_as,
                    band,
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
    /// The band: the drive loop ends where the feedback holds C, does not converge, or
    /// leaves the C travel.
    /// In [`PoleMode::Swing`] a command inside the band is solved with C free within
    /// [`Pole::c_range`]: C is the root, nearest the command, of the out-of-plane axis
    /// residual (tip and in-plane axis by Newton with C held). Where no C in the range
    /// reaches the nominal axis (an out-of-plane head error makes the tool sweep a cone
    /// that misses it, [`ErrorModel::pole_reach`]) the C of least orientation error is
    /// taken and `reached` is false. If the solve fails or does no better than Hold,
    /// the Hold result is returned and `fallback` is set.
    pub fn drive_positions_pole(&self, u: &[f64; 5], pole: &Pole) -> PoleSolve {
        let hold = self.drive_positions(u);
        // Near the pole step 1 may move C out of its travel (or not converge): the
        // band, solved with C bounded. At the travel's ends a correction of
        // arc-seconds beyond it is what the NC's software limit margin is for.
        let (c_lo, c_hi) = self.model.travel[4];
        let converged = hold.residual_um <= TOL_UM && hold.residual_arcsec <= TOL_ARCSEC;
        let c_in_travel =
            (c_lo - TRAVEL_MARGIN_DEG..=c_hi + TRAVEL_MARGIN_DEG).contains(&hold.drive[4]);
        let off_band = !hold.band && converged && c_in_travel;
        let plain = PoleSolve {
            solve: hold,
            newton_iterations: 0,
            c_swing_deg: 0.0,
            fallback: false,
            reached: true,
            c_past_travel: !hold.band && converged && !c_in_travel,
        };
        if pole.mode == PoleMode::Hold || self.model.zero || off_band {
            return plain;
        }
        let swung = pole
            .c_range(u[4], self.model.travel[4])
            .and_then(|range| self.swing(u, &hold.drive, range));
        match swung {
            Some(s) if (s.solve.drive[4] - u[4]).abs() <= pole.max_c_swing_deg => PoleSolve {
                c_past_travel: plain.c_past_travel,
                ..s
            },
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
                band: true,
            },
            newton_iterations: evals,
            c_swing_deg: (drive[4] - u[4]).abs(),
            fallback: false,
            reached,
            c_past_travel: false,
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
