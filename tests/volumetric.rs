//! The volumetric compensator between the scales and the drives of the simulated
//! 5-axis machine: the actual tool pose lands on the commanded nominal one.

use std::sync::Arc;

use compgate_commission::volumetric::{
    angle_rad, distance_mm, parse, VolumetricCompensator, MM_PER_UM, RAD_PER_ARCSEC,
};
use compgate_plc::machine5::{HeadGeometry, Machine5};

const EXAMPLE: &str = include_str!("../config/volumetric-example.errors");

fn setup() -> (Arc<VolumetricCompensator>, Machine5) {
    let comp = Arc::new(VolumetricCompensator::new(parse(EXAMPLE).expect("example")));
    let g = comp.model().geometry;
    let truth = Arc::clone(&comp);
    let machine = Machine5::new(
        HeadGeometry {
            pivot_mm: g.pivot_mm,
            tool_length_mm: g.tool_length_mm,
        },
        Box::new(move |q| truth.pose_error(q)),
    );
    (comp, machine)
}

#[test]
fn compensated_machine_puts_the_tool_on_the_command() {
    let (comp, machine) = setup();
    let mut worst_unc = (0.0f64, 0.0f64);
    let mut worst_comp = (0.0f64, 0.0f64);
    for u in [
        [100.0, 100.0, 100.0, 30.0, 0.0],
        [900.0, 700.0, 500.0, -60.0, 120.0],
        [500.0, 50.0, 550.0, 90.0, -170.0],
        [20.0, 780.0, 10.0, -15.0, 45.0],
        [640.0, 333.0, 222.0, 75.0, -90.0],
    ] {
        let nominal = machine.nominal_pose(&u);
        let unc = machine.move_to(&u, |q| *q).expect("settles");
        let cmp = machine.move_to(&u, |q| comp.feedback(q)).expect("settles");
        let e = |p: &compgate_plc::machine5::Pose| {
            (
                distance_mm(&p.tip_mm, &nominal.tip_mm) / MM_PER_UM,
                angle_rad(&p.axis, &nominal.axis) / RAD_PER_ARCSEC,
            )
        };
        let (a, b) = (e(&unc.pose), e(&cmp.pose));
        worst_unc = (worst_unc.0.max(a.0), worst_unc.1.max(a.1));
        worst_comp = (worst_comp.0.max(b.0), worst_comp.1.max(b.1));
        // The drives moved by the correction, not to the command.
        assert!(cmp.axes != u);
    }
    println!("uncompensated worst {worst_unc:?}, compensated worst {worst_comp:?} (um, arcsec)");
    assert!(worst_unc.0 > 10.0 && worst_unc.1 > 10.0, "{worst_unc:?}");
    assert!(worst_comp.0 < 0.001, "{worst_comp:?}");
    assert!(worst_comp.1 < 0.001, "{worst_comp:?}");
}

#[test]
fn servo_and_solver_agree() {
    let (comp, machine) = setup();
    let u = [300.0, 400.0, 200.0, 45.0, 60.0];
    let s = machine.move_to(&u, |q| comp.feedback(q)).expect("settles");
    let solve = comp.drive_positions(&u);
    for (q, d) in s.axes.iter().zip(&solve.drive) {
        assert!((q - d).abs() < 1e-5, "{s:?} {solve:?}");
    }
}

const BIN: &str = env!("CARGO_BIN_EXE_compgate");

#[test]
fn cli_reports_the_grid_and_writes_maps() {
    let dir = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(BIN)
        .args([
            "volumetric",
            "--errors",
            "config/volumetric-example.errors",
            "--grid",
            "3",
            "--out",
        ])
        .arg(dir.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // Every "remaining" figure (compensated over uncompensated) is under 1 %.
    let remaining: Vec<f64> = stdout
        .lines()
        .filter(|l| l.contains("max (") || l.contains("RMS ("))
        .map(|l| {
            let pct = l.split_whitespace().last().unwrap();
            pct.trim_end_matches('%').parse().unwrap()
        })
        .collect();
    assert_eq!(remaining.len(), 4, "{stdout}");
    assert!(remaining.iter().all(|&p| p < 1.0), "{stdout}");
    for svg in ["tip-error.svg", "orientation-error.svg", "tip-error-xy.svg"] {
        let text = std::fs::read_to_string(dir.path().join(svg)).unwrap();
        assert!(text.starts_with("<svg"), "{svg}");
    }
}

#[test]
fn cli_rejects_a_table_short_of_the_travel_naming_file_and_line() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("short.errors");
    // The X table ends at 900 mm, the travel at 1000 mm.
    let text = EXAMPLE.replacen("\n1000 9.0000", "\n#1000 9.0000", 1);
    std::fs::write(&path, text).unwrap();
    let out = std::process::Command::new(BIN)
        .args(["volumetric", "--errors"])
        .arg(&path)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains(&path.display().to_string()), "{err}");
    assert!(err.contains("line "), "{err}");
}
