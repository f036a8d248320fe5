//! Grid evaluation: every commanded pose uncompensated and compensated, and the
//! statistics of the errors (pure, no I/O).

use super::kinematics::{
    angle_rad, distance_mm, nominal_pose, ErrorModel, Pole, PoleReach, VolumetricCompensator,
};
use super::{MM_PER_UM, RAD_PER_ARCSEC, TOL_ARCSEC};
use crate::stats::golden;

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
    /// Per pose: in the pole band near A = 0 ([`Solve::band`](super::Solve::band)),
    /// where the orientation is only partly correctable online; the statistics
    /// report these poses apart.
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
    /// Per pose: solved at the pole only because the drive loop would take C more
    /// than [`super::TRAVEL_MARGIN_DEG`] past its travel
    /// ([`super::PoleSolve::c_past_travel`]); such a pose is `singular` too.
    pub c_past_travel: Vec<bool>,
    /// Per axis: the poses whose drive position lies beyond the travel, and the
    /// largest excess (mm, deg), which the NC's software limits must leave.
    pub past_travel: [(usize, f64); 5],
    /// Per pose: the drive positions the compensated pose settles at.
    pub drives: Vec<[f64; 5]>,
    /// Per pose: iterations of the solve (drive loop steps, or fixed-C solves of a
    /// pole swing).
    pub iterations: Vec<usize>,
    /// Per pose: the least orientation error any drive positions leave (the floor),
    /// arc-seconds; 0 off the band. From [`super::ErrorModel::pole_reach`] (first
    /// order), or from [`pole_floor_brute_force`] where the compensated error is above
    /// the first-order floor plus [`ACCEPT_FLOOR_ARCSEC`].
    pub floor: Vec<f64>,
    /// Poses whose floor came from the brute force.
    pub floor_brute_force: usize,
    /// Per pose in the A = 0 band, what the pole allows ([`super::ErrorModel::pole_reach`]):
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

/// Least excess of a drive position over the travel that counts (mm, deg): below
/// a nanometre it is rounding, not a limit the NC needs.
const PAST_TRAVEL_MIN: f64 = 1e-6;

/// The acceptance's fraction of the uncompensated error.
pub const ACCEPT_FRACTION: f64 = 0.01;
/// The acceptance's margin over the floor, arc-seconds.
pub const ACCEPT_FLOOR_ARCSEC: f64 = 0.001;

/// Result of [`Evaluation::acceptance`].
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Acceptance {
    /// Poses checked.
    pub total: usize,
    /// Poses within the limits.
    pub passed: usize,
    /// Indices of the poses outside.
    pub failed: Vec<usize>,
    /// Largest compensated orientation error minus its limit, arc-seconds (negative:
    /// every pose is inside).
    pub worst_orient_margin_arcsec: f64,
}

pub(super) fn stats<'a>(e: impl Iterator<Item = &'a (f64, f64)>) -> Stats {
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

    /// Statistics of every pose, the A = 0 band included: (uncompensated,
    /// compensated).
    pub fn all_stats(&self) -> (Stats, Stats) {
        (
            stats(self.uncompensated.iter()),
            stats(self.compensated.iter()),
        )
    }

    /// The least orientation error any drive positions leave at pose `i`, arc-seconds
    /// ([`Evaluation::floor`]).
    pub fn floor_arcsec(&self, i: usize) -> f64 {
        self.floor.get(i).copied().unwrap_or(0.0)
    }

    /// The acceptance's limits at pose `i`: the compensated tip error at most
    /// [`ACCEPT_FRACTION`] of the uncompensated one (or [`super::TOL_UM`]), and the
    /// orientation error at most that fraction or the floor plus
    /// [`ACCEPT_FLOOR_ARCSEC`], the larger. (tip um, orientation arc-seconds).
    pub fn acceptance_limits(&self, i: usize) -> (f64, f64) {
        let unc = self.uncompensated[i];
        (
            (ACCEPT_FRACTION * unc.0).max(super::TOL_UM),
            (ACCEPT_FRACTION * unc.1).max(self.floor_arcsec(i) + ACCEPT_FLOOR_ARCSEC),
        )
    }

    /// The acceptance, pose by pose ([`Evaluation::acceptance_limits`]).
    pub fn acceptance(&self) -> Acceptance {
        let mut a = Acceptance {
            worst_orient_margin_arcsec: f64::NEG_INFINITY,
            ..Acceptance::default()
        };
        for (i, comp) in self.compensated.iter().enumerate() {
            let (tip_limit, limit) = self.acceptance_limits(i);
            let tip_ok = comp.0 <= tip_limit;
            let orient_ok = comp.1 <= limit;
            a.total += 1;
            if tip_ok && orient_ok {
                a.passed += 1;
            } else {
                a.failed.push(i);
            }
            a.worst_orient_margin_arcsec = a.worst_orient_margin_arcsec.max(comp.1 - limit);
        }
        a
    }

    /// Poses solved at the pole because C would leave its travel
    /// ([`Evaluation::c_past_travel`]).
    pub fn pole_c_past_travel(&self) -> usize {
        self.c_past_travel.iter().filter(|c| **c).count()
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
    ev.poses.reserve(grid.iter().map(Vec::len).product());
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
                        let band = ps.solve.band || ps.newton_iterations > 0 || ps.fallback;
                        ev.singular.push(band);
                        ev.c_past_travel.push(band && ps.c_past_travel);
                        for (k, (n, most)) in ev.past_travel.iter_mut().enumerate() {
                            let (lo, hi) = model.travel[k];
                            let excess = (lo - s.drive[k]).max(s.drive[k] - hi);
                            if excess > PAST_TRAVEL_MIN {
                                *n += 1;
                                *most = most.max(excess);
                            }
                        }
                        let travel_c = model.travel[4];
                        ev.pole_reach.push((band && !model.zero).then(|| {
                            let range = pole.c_range(c, travel_c).unwrap_or((c, c));
                            (model.pole_reach(&u, range), model.pole_reach(&u, travel_c))
                        }));
                        ev.drives.push(s.drive);
                        ev.iterations.push(s.iterations);
                        let unc = err(&u, &u);
                        let comp = err(&s.drive, &u);
                        let mut floor = match ev.pole_reach.last() {
                            Some(Some((r, _))) => r.min_arcsec,
                            _ => 0.0,
                        };
                        if band
                            && comp.1 > (ACCEPT_FRACTION * unc.1).max(floor + ACCEPT_FLOOR_ARCSEC)
                        {
                            let range = pole.c_range(c, model.travel[4]).unwrap_or((c, c));
                            floor = pole_floor_brute_force(model, &u, range);
                            ev.floor_brute_force += 1;
                        }
                        ev.floor.push(floor);
                        ev.uncompensated.push(unc);
                        ev.compensated.push(comp);
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

/// The least orientation error at the command u over C in `c_range` and A within
/// 0.05 deg of u's, with the tip on the command, arc-seconds, by brute force on the
/// forward kinematics alone: a 2 deg scan of C, the best A for each by golden
/// section, then golden section over C around the six best cells; then X, Y, Z are
/// solved for the tip (they move by up to a tenth of a millimetre, which turns the
/// slides' angular errors by thousandths of an arc-second) and C and A refined again.
pub fn pole_floor_brute_force(model: &ErrorModel, u: &[f64; 5], c_range: (f64, f64)) -> f64 {
    let (pn, vn) = nominal_pose(&model.geometry, u);
    let orient = |xyz: &[f64; 3], a: f64, c: f64| {
        angle_rad(&model.actual_pose(&[xyz[0], xyz[1], xyz[2], a, c]).1, &vn) / RAD_PER_ARCSEC
    };
    let span_deg = 0.05;
    let best_a = |xyz: &[f64; 3], c: f64| {
        golden(u[3] - span_deg, u[3] + span_deg, 40, &mut |a| {
            orient(xyz, a, c)
        })
    };
    let (lo, hi) = c_range;
    let n = (((hi - lo) / 2.0).ceil() as usize).max(1);
    let step = (hi - lo) / n as f64;
    let mut xyz = [u[0], u[1], u[2]];
    let mut scan: Vec<(f64, f64)> = (0..=n)
        .map(|i| {
            let c = lo + step * i as f64;
            (c, best_a(&xyz, c).1)
        })
        .collect();
    scan.sort_by(|a, b| a.1.total_cmp(&b.1));
    let refine = |xyz: &[f64; 3], c0: f64, e0: f64, half: f64| -> (f64, f64) {
        let (a, b) = ((c0 - half).max(lo), (c0 + half).min(hi));
        if b <= a {
            return (c0, e0);
        }
        let (c, e) = golden(a, b, 40, &mut |c| best_a(xyz, c).1);
        if e < e0 {
            (c, e)
        } else {
            (c0, e0)
        }
    };
    let mut best = scan
        .iter()
        .take(6)
        .map(|&(c0, e0)| refine(&xyz, c0, e0, step))
        .fold((u[4], f64::INFINITY), |b, x| if x.1 < b.1 { x } else { b });
    for _ in 0..2 {
        let a = best_a(&xyz, best.0).0;
        let mut q = [xyz[0], xyz[1], xyz[2], a, best.0];
        for _ in 0..5 {
            let (p, _) = model.actual_pose(&q);
            for k in 0..3 {
                q[k] -= p[k] - pn[k];
            }
        }
        xyz = [q[0], q[1], q[2]];
        let e0 = best_a(&xyz, best.0).1;
        best = refine(&xyz, best.0, e0, 0.5 * step);
    }
    best.1
}
