//! What `volumetric` shows and writes: the text report and the SVG error maps.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::evaluation::{
    Evaluation, ACCEPT_FLOOR_ARCSEC, ACCEPT_FRACTION, POLE_TOL_ARCSEC, POLE_TOL_FRACTION,
};
use super::kinematics::PoleMode;
use super::{
    VolumetricError, AXES, MAX_ONLINE_C_CORRECTION_DEG, TOL_ARCSEC, TOL_UM, TRAVEL_MARGIN_DEG,
};
use crate::plot;
use crate::table::{plain_line, Column};

/// Failing poses the report names one by one.
const SHOWN_FAILURES: usize = 5;

/// The report of an evaluation.
pub fn report(ev: &Evaluation) -> String {
    let (u, c) = ev.all_stats();
    let pct = |a: f64, b: f64| if b > 0.0 { 100.0 * a / b } else { 0.0 };
    let mut s = String::new();
    let (n_sing, su, sc) = ev.singular_stats();
    // Why poses are solved at the pole: the band as `--pole`'s help states it, and
    // poses whose C would leave its travel (they are not in that band).
    let n_travel = ev.pole_c_past_travel();
    let why = [
        (
            n_sing - n_travel,
            format!(
                "where step 1 would move C by more than {} deg",
                MAX_ONLINE_C_CORRECTION_DEG / 2.0
            ),
        ),
        (
            n_travel,
            format!(
                "where the drive loop would take C more than {TRAVEL_MARGIN_DEG} deg past \
                 its travel"
            ),
        ),
    ]
    .into_iter()
    .filter(|(n, _)| *n > 0)
    .map(|(n, what)| format!("{n} {what}"))
    .collect::<Vec<_>>();
    let _ = writeln!(
        s,
        "volumetric compensation over {} grid poses{}",
        ev.poses.len(),
        if n_sing > 0 {
            format!(
                " ({n_sing} of them near the A = 0 pole: {}; also below)",
                why.join(", ")
            )
        } else {
            String::new()
        }
    );
    let past: Vec<String> = ev
        .past_travel
        .iter()
        .enumerate()
        .filter(|(_, (n, _))| *n > 0)
        .map(|(k, (n, most))| {
            let unit = if k < 3 { "mm" } else { "deg" };
            format!("{} {most:.4} {unit} ({n} poses)", AXES[k])
        })
        .collect();
    if !past.is_empty() {
        let _ = writeln!(
            s,
            "drive positions past the travel of the error file (the NC's software limits \
             must leave this margin), by up to:\n  {}",
            past.join(", ")
        );
    }
    const COLUMNS: [Column; 4] = [
        Column::left(0, 20),
        Column::right(1, 13),
        Column::right(1, 13),
        Column::right(1, 11),
    ];
    let header = ["", "uncompensated", "compensated", "remaining"];
    let _ = writeln!(s, "{}", plain_line(&COLUMNS, header));
    for (label, uncomp, comp) in [
        ("tip max (um)", u.max_tip_um, c.max_tip_um),
        ("tip RMS (um)", u.rms_tip_um, c.rms_tip_um),
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
        let cells = [
            label.to_string(),
            format!("{uncomp:.4}"),
            format!("{comp:.6}"),
            format!("{:.4}%", pct(comp, uncomp)),
        ];
        let _ = writeln!(s, "{}", plain_line(&COLUMNS, cells));
    }
    let acc = ev.acceptance();
    // In full: a failure by 4e-5" printed as "+0.0000" with four decimals.
    let _ = writeln!(
        s,
        "acceptance: {} of {} poses within {} % of their uncompensated error (the tip at \
         least {TOL_UM} um), or the achievable minimum + {ACCEPT_FLOOR_ARCSEC}\" where the pole \
         limits it (worst \
         orientation margin {:+.2e}\"; minimum from the parameters, by brute force for {} poses)",
        acc.passed,
        acc.total,
        100.0 * ACCEPT_FRACTION,
        acc.worst_orient_margin_arcsec,
        ev.floor_brute_force
    );
    if !acc.failed.is_empty() {
        let _ = writeln!(
            s,
            "ACCEPTANCE FAILED for {} poses{}:",
            acc.failed.len(),
            if acc.failed.len() > SHOWN_FAILURES {
                format!(" (the first {SHOWN_FAILURES})")
            } else {
                String::new()
            }
        );
        for &i in acc.failed.iter().take(SHOWN_FAILURES) {
            let [x, y, z, a, c] = ev.poses[i];
            let (tip, orient) = ev.compensated[i];
            let (tip_limit, orient_limit) = ev.acceptance_limits(i);
            let _ = writeln!(
                s,
                "  X {x} Y {y} Z {z} A {a} C {c}: tip {tip:.6} um (limit {tip_limit:.6}), \
                 orientation {orient:.7}\" (limit {orient_limit:.7}), {} iterations",
                ev.iterations[i]
            );
        }
    }
    if n_sing > 0 {
        let (uo, co) = (ev.uncompensated_stats(), ev.compensated_stats());
        let _ = writeln!(
            s,
            "off the band ({} poses): tip max {:.4} -> {:.6} um, orientation max {:.4} -> \
             {:.6}\"",
            ev.poses.len() - n_sing,
            uo.max_tip_um,
            co.max_tip_um,
            uo.max_orient_arcsec,
            co.max_orient_arcsec
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
        let kinds = if n_travel > 0 {
            format!(
                ": {} in the band, {n_travel} where C would leave its travel",
                n_sing - n_travel
            )
        } else {
            String::new()
        };
        if ev.pole.mode == PoleMode::Swing {
            let _ = writeln!(
                s,
                "near the A = 0 pole ({n_sing} poses{kinds}, pole mode swing, C within {} deg of \
                 the command \
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
                 over the minimum {:+.4}\")",
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
                "near the A = 0 pole ({n_sing} poses, pole mode hold, C not corrected): tip max {:.4} -> {:.6} um, \
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

/// The per-pose CSV's header: the commanded pose, the drive positions it settles at,
/// the iterations, the compensated (residual) and uncompensated tip and orientation
/// errors, whether the pose was solved at the pole, the floor there, and whether it
/// was so because C would leave its travel.
pub const POSES_CSV_HEADER: &str = "x_mm,y_mm,z_mm,a_deg,c_deg,\
drive_x_mm,drive_y_mm,drive_z_mm,drive_a_deg,drive_c_deg,iterations,\
tip_um,orient_arcsec,uncomp_tip_um,uncomp_orient_arcsec,pole_band,floor_arcsec,\
c_past_travel";

/// Writes one row per grid pose ([`POSES_CSV_HEADER`]), every number in full
/// precision (shortest round-trip form), so that the result can be checked by an
/// independent kinematic model.
pub fn write_poses_csv(path: &Path, ev: &Evaluation) -> Result<(), VolumetricError> {
    let mut s = String::with_capacity(200 * (ev.poses.len() + 1));
    s.push_str(POSES_CSV_HEADER);
    s.push('\n');
    for (i, u) in ev.poses.iter().enumerate() {
        let d = ev.drives[i];
        let (comp, unc) = (ev.compensated[i], ev.uncompensated[i]);
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            u[0],
            u[1],
            u[2],
            u[3],
            u[4],
            d[0],
            d[1],
            d[2],
            d[3],
            d[4],
            ev.iterations[i],
            comp.0,
            comp.1,
            unc.0,
            unc.1,
            u8::from(ev.singular[i]),
            ev.floor_arcsec(i),
            u8::from(ev.c_past_travel[i])
        );
    }
    compgate_core::outputs::write(path, s)
        .map_err(|e| VolumetricError::Io(format!("{}: {e}", path.display())))
}

/// The maps [`write_svgs`] writes.
pub const SVG_FILES: [&str; 3] = ["tip-error.svg", "orientation-error.svg", "tip-error-xy.svg"];

/// Writes the SVG error maps into `dir` (which must exist): `tip-error.svg` and
/// `orientation-error.svg` (error per grid pose, uncompensated and compensated) and
/// `tip-error-xy.svg` (the uncompensated tip error over X and Y, worst over the other
/// axes).
pub fn write_svgs(dir: &Path, ev: &Evaluation) -> Result<Vec<PathBuf>, VolumetricError> {
    let [tip, orientation, tip_xy] = SVG_FILES;
    let mut written = Vec::new();
    for (name, pick, unit) in [
        (tip, 0usize, "tip error (um)"),
        (orientation, 1, "orientation error (arcsec)"),
    ] {
        let path = dir.join(name);
        let get = |t: &(f64, f64)| if pick == 0 { t.0 } else { t.1 };
        let n = ev.poses.len().max(2);
        plot::svg(&path, (1000, 700), |root| {
            let (upper, lower) = root.split_vertically(350);
            for (area, series, color, label) in [
                (&upper, &ev.uncompensated, plot::RED, "uncompensated"),
                (&lower, &ev.compensated, plot::BLUE, "compensated"),
            ] {
                let hi = series.iter().map(get).fold(1e-12, f64::max) * 1.05;
                let caption = format!("{label} {unit} per grid pose (max {:.4})", hi / 1.05);
                let mut chart = plot::Frame::new("grid pose (X outermost, C innermost)", unit)
                    .caption(caption, 18)
                    .label_areas(30, 80)
                    .draw(area, 0.0..(n - 1) as f64, 0.0..hi)?;
                let pts = series.iter().enumerate().map(|(i, t)| (i as f64, get(t)));
                plot::line(&mut chart, pts, color, None)?;
            }
            Ok(())
        })?;
        written.push(path.clone());
    }
    // X-Y map of the worst uncompensated tip error.
    let path = dir.join(tip_xy);
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
        let mut rects = Vec::with_capacity(cell.len());
        for i in 0..xs.len() {
            for j in 0..ys.len() {
                let v = (cell[i * ys.len() + j] - bottom) / (top - bottom).max(1e-12);
                let (a0, a1) = half(&xs, i);
                let (b0, b1) = half(&ys, j);
                rects.push(((a0, b0), (a1, b1), plot::blue_to_red(v, 64)));
            }
        }
        let caption = format!(
            "uncompensated tip error over X-Y, worst over Z, A, C \
             (blue {bottom:.1} .. red {top:.1} um)"
        );
        plot::svg(&path, (800, 700), |root| {
            let mut chart = plot::Frame::new("X (mm)", "Y (mm)")
                .caption(caption, 18)
                .draw(root, x0..x1, y0..y1)?;
            plot::cells(&mut chart, rects)
        })?;
        written.push(path.clone());
    }
    Ok(written)
}
