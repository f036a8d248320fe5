use proptest::prelude::*;

use super::*;

const EXAMPLE: &str = include_str!("../../config/volumetric-example.errors");

fn grid4(model: &ErrorModel) -> [Vec<f64>; 5] {
    parse_grid("4", &model.travel).expect("grid")
}

#[test]
fn example_file_is_the_synthetic_model() {
    if std::env::var_os("COMPGATE_REGEN_EXAMPLE").is_some() {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/config/volumetric-example.errors"
        );
        std::fs::write(path, write(&synthetic_model(1.0))).expect("regenerate");
        return;
    }
    assert_eq!(EXAMPLE, write(&synthetic_model(1.0)));
    let m = parse(EXAMPLE).expect("example parses");
    let s = synthetic_model(1.0);
    assert_eq!(m.travel, s.travel);
    for (a, b) in m.tables.iter().zip(&s.tables) {
        assert_eq!(a.pos, b.pos);
        for (ra, rb) in a.val.iter().zip(&b.val) {
            for (x, y) in ra.iter().zip(rb) {
                assert!((x - y).abs() < 1e-15, "{x} {y}");
            }
        }
    }
}

#[test]
fn compensation_leaves_under_one_percent_and_converges_in_three() {
    let comp = VolumetricCompensator::new(parse(EXAMPLE).expect("example"));
    let ev = evaluate(&comp, &grid4(comp.model()));
    let (u, c) = (ev.uncompensated_stats(), ev.compensated_stats());
    println!("{}", report(&ev));
    assert!(u.max_tip_um > 20.0 && u.max_orient_arcsec > 20.0, "{u:?}");
    assert!(c.max_tip_um <= 0.01 * u.max_tip_um, "{c:?} vs {u:?}");
    assert!(
        c.max_orient_arcsec <= 0.01 * u.max_orient_arcsec,
        "{c:?} vs {u:?}"
    );
    assert!(c.rms_tip_um <= 0.01 * u.rms_tip_um);
    assert!(c.rms_orient_arcsec <= 0.01 * u.rms_orient_arcsec);
    assert!(ev.max_iterations <= 3, "{}", ev.max_iterations);
    assert!(ev.max_residual.0 <= TOL_UM && ev.max_residual.1 <= TOL_ARCSEC);
}

#[test]
fn zero_file_gives_identity_to_the_last_bit() {
    let mut m = synthetic_model(0.0);
    // -0.0 scaled errors compare equal to zero; the model must count as zero.
    assert!(m.is_zero());
    m = parse(&write(&m)).expect("zero file");
    assert!(m.is_zero());
    let comp = VolumetricCompensator::new(m);
    for q in [
        [0.0, 0.0, 0.0, 0.0, 0.0],
        [-0.0, 123.456, 599.999, -0.0, 1e-300],
        [1000.0, 0.1, 0.3, 37.3, -199.9],
    ] {
        let f = comp.feedback(&q);
        assert_eq!(f.map(f64::to_bits), q.map(f64::to_bits));
        let s = comp.drive_positions(&q);
        assert_eq!(s.drive.map(f64::to_bits), q.map(f64::to_bits));
        assert_eq!(s.iterations, 0);
    }
}

#[test]
fn nominal_pose_matches_the_chain_without_errors() {
    let m = synthetic_model(0.0);
    for q in [
        [10.0, 20.0, 30.0, 45.0, 30.0],
        [500.0, 1.0, 2.0, -80.0, 170.0],
    ] {
        let (p, v) = m.actual_pose(&q);
        let (pn, vn) = nominal_pose(&m.geometry, &q);
        assert!(distance_mm(&p, &pn) < 1e-12);
        assert!(angle_rad(&v, &vn) < 1e-14);
    }
    // A = 90 deg, C = 0: tool along -Y of the head, axis (0, -1, 0).
    let (p, v) = nominal_pose(&m.geometry, &[0.0, 0.0, 0.0, 90.0, 0.0]);
    assert!(distance_mm(&p, &[0.0, 250.0, -150.0]) < 1e-12, "{p:?}");
    assert!(angle_rad(&v, &[0.0, -1.0, 0.0]) < 1e-12);
}

#[test]
fn squareness_and_location_act_as_documented() {
    let z: [Table; 5] = Default::default();
    let g = Geometry {
        pivot_mm: [0.0; 3],
        tool_length_mm: 0.0,
    };
    let t = synthetic_model(1.0).travel;
    let m = ErrorModel::new(g, t, z, [RAD_PER_ARCSEC, 0.0, 0.0], [0.0; 4], [0.0; 4]);
    let (p, _) = m.actual_pose(&[0.0, 500.0, 0.0, 0.0, 0.0]);
    // EC0Y = 1": Y motion of 500 mm drifts -500 * 4.85e-6 mm in X.
    assert!((p[0] + 500.0 * RAD_PER_ARCSEC).abs() < 1e-12, "{p:?}");
}

#[test]
fn bad_input_names_line_and_field() {
    let cases: &[(&str, usize, &str)] = &[
        ("", 1, "header"),
        ("compgate-volumetric-errors 2\n", 1, "version"),
        ("nonsense 1\n", 1, "header"),
        ("compgate-volumetric-errors 1\ntravel Q 0 1\n", 2, "axis"),
        ("compgate-volumetric-errors 1\n\n# c\ntravel X 0 abc\n", 4, "X max (mm)"),
        ("compgate-volumetric-errors 1\ntravel X 5 1\n", 2, "max"),
        ("compgate-volumetric-errors 1\nsquareness ECXY 1\n", 2, "name"),
        ("compgate-volumetric-errors 1\nlocation XOC\n", 2, "XOC"),
        ("compgate-volumetric-errors 1\nfoo 1\n", 2, "keyword"),
        (
            "compgate-volumetric-errors 1\ntable X EXX EYX EZX EAX EBX EYY\n",
            2,
            "column 7",
        ),
        (
            "compgate-volumetric-errors 1\ntable A EXA EYA EZA EAA EBA ECA\n0 1 2 3 4 5 x\nend\n",
            3,
            "ECA",
        ),
        (
            "compgate-volumetric-errors 1\ntable A EXA EYA EZA EAA EBA ECA\n0 1 2 3 4 5 6\n0 1 2 3 4 5 6\nend\n",
            4,
            "angle (deg)",
        ),
        (
            "compgate-volumetric-errors 1\ntable A EXA EYA EZA EAA EBA ECA\n0 1 2 3 4 5 6 7\nend\n",
            3,
            "end of line",
        ),
        (
            "compgate-volumetric-errors 1\ntable A EXA EYA EZA EAA EBA ECA\n0 1 2 3 4 5 6\n",
            2,
            "end",
        ),
    ];
    for (text, line, field) in cases {
        match parse(text) {
            Err(VolumetricError::Parse {
                line: l, field: f, ..
            }) => assert_eq!((l, f.as_str()), (*line, *field), "{text:?}"),
            other => panic!("{text:?}: {other:?}"),
        }
    }
}

#[test]
fn table_not_covering_travel_is_rejected() {
    let text = EXAMPLE.replace("travel X 0 1000", "travel X 0 1200");
    let e = parse(&text).expect_err("must reject");
    let VolumetricError::Parse {
        line,
        field,
        message,
    } = &e
    else {
        panic!("{e:?}")
    };
    let table_line = EXAMPLE
        .lines()
        .position(|l| l.starts_with("table X"))
        .expect("table X")
        + 1;
    assert_eq!((*line, field.as_str()), (table_line, "X"), "{message}");
    assert!(message.contains("not extrapolated"), "{message}");
}

#[test]
fn missing_travel_is_rejected() {
    let text: String = EXAMPLE
        .lines()
        .filter(|l| !l.starts_with("travel C"))
        .map(|l| format!("{l}\n"))
        .collect();
    let e = parse(&text).expect_err("must reject");
    assert!(
        matches!(e, VolumetricError::Parse { ref field, .. } if field == "travel"),
        "{e}"
    );
}

#[test]
fn grid_spec() {
    let t = synthetic_model(1.0).travel;
    let g = parse_grid("X=0:1000:5,A=-90:90:4", &t).expect("grid");
    assert_eq!(g[0], vec![0.0, 250.0, 500.0, 750.0, 1000.0]);
    assert_eq!(g[3], vec![-90.0, -30.0, 30.0, 90.0]);
    assert_eq!(g[1].len(), 3);
    assert!(parse_grid("X=0:2000:5", &t).is_err());
    assert!(parse_grid("Q=0:1:2", &t).is_err());
    assert!(parse_grid("0", &t).is_err());
    assert_eq!(parse_grid("2", &t).expect("n")[4], vec![-200.0, 200.0]);
}

#[test]
fn run_writes_report_and_svgs() {
    let dir = tempfile::tempdir().expect("tempdir");
    let errors = dir.path().join("m.errors");
    std::fs::write(&errors, EXAMPLE).expect("write");
    let out = dir.path().join("maps");
    let report = run(&VolumetricArgs {
        errors,
        grid: "3".into(),
        out: Some(out.clone()),
        pole: PoleMode::Hold,
        max_c_swing_deg: 180.0,
    })
    .expect("run");
    assert!(report.contains("tip max"), "{report}");
    for f in ["tip-error.svg", "orientation-error.svg", "tip-error-xy.svg"] {
        let s = std::fs::read_to_string(out.join(f)).expect(f);
        assert!(s.starts_with("<svg"), "{f}");
    }
    let bad = dir.path().join("bad.errors");
    std::fs::write(&bad, "compgate-volumetric-errors 1\ntravel X 0 x\n").expect("write");
    let e = run(&VolumetricArgs {
        errors: bad,
        grid: "3".into(),
        out: None,
        pole: PoleMode::Hold,
        max_c_swing_deg: 180.0,
    })
    .expect_err("bad file");
    assert!(e.to_string().contains("line 2"), "{e}");
}

#[test]
fn a_zero_band_is_reported_apart() {
    let comp = VolumetricCompensator::new(synthetic_model(1.0));
    let grid = parse_grid("3", &comp.model().travel).expect("grid");
    let ev = evaluate(&comp, &grid);
    let (n, u, c) = ev.singular_stats();
    assert_eq!(n, 81);
    // Tip still corrected in the band; orientation only in part.
    assert!(c.max_tip_um <= 0.01 * u.max_tip_um, "{c:?} {u:?}");
    assert!(c.max_orient_arcsec < u.max_orient_arcsec, "{c:?} {u:?}");
    let (cu, cc) = (ev.uncompensated_stats(), ev.compensated_stats());
    assert!(cc.max_orient_arcsec <= 0.01 * cu.max_orient_arcsec);
    assert!(
        report(&ev).contains("A = 0 band (81 poses"),
        "{}",
        report(&ev)
    );
}

#[test]
fn singular_band_keeps_c() {
    let comp = VolumetricCompensator::new(synthetic_model(1.0));
    let f = comp.feedback(&[100.0, 100.0, 100.0, 0.0, 45.0]);
    assert!((f[4] - 45.0).abs() < 1e-12);
    assert!(f[3].abs() < 0.01);
}

#[test]
fn bench_runs() {
    let seconds = std::env::var("COMPGATE_BENCH_S")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(0.05);
    let b = bench_per_s(seconds);
    println!(
        "{:.0} compensations/s, {:.1} ns each; {:.0} per 125 us cycle, {:.0} per 500 us",
        b.per_s,
        b.ns_each,
        125e3 / b.ns_each,
        500e3 / b.ns_each
    );
    assert!(b.per_s > 1000.0, "{b:?}");
}

/// A random small model: every table value and constant uniformly within +-`amp`
/// (um / arcsec).
fn random_model(seed: u64, amp: f64) -> ErrorModel {
    let mut s = seed | 1;
    let mut next = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        ((s >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    };
    let base = synthetic_model(1.0);
    let tables: [Table; 5] = std::array::from_fn(|i| {
        let (lo, hi) = base.travel[i];
        let n = 7;
        let pos = (0..n)
            .map(|j| lo + (hi - lo) * j as f64 / (n - 1) as f64)
            .collect();
        let val = (0..n)
            .map(|_| {
                std::array::from_fn(|c| {
                    amp * next() * if c < 3 { MM_PER_UM } else { RAD_PER_ARCSEC }
                })
            })
            .collect();
        Table::new(pos, val)
    });
    let sq = std::array::from_fn(|_| amp * next() * RAD_PER_ARCSEC);
    let loc = |n: &mut dyn FnMut() -> f64| {
        [
            amp * n() * MM_PER_UM,
            amp * n() * MM_PER_UM,
            amp * n() * RAD_PER_ARCSEC,
            amp * n() * RAD_PER_ARCSEC,
        ]
    };
    let lc = loc(&mut next);
    let la = loc(&mut next);
    ErrorModel::new(base.geometry, base.travel, tables, sq, lc, la)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn compensated_pose_matches_command(
        seed in any::<u64>(),
        amp in 1.0f64..40.0,
        x in 0.0f64..1000.0,
        y in 0.0f64..800.0,
        z in 0.0f64..600.0,
        a_mag in 5.0f64..100.0,
        a_neg in any::<bool>(),
        c in -200.0f64..200.0,
    ) {
        let comp = VolumetricCompensator::new(random_model(seed, amp));
        let a = if a_neg { -a_mag } else { a_mag };
        let u = [x, y, z, a, c];
        let s = comp.drive_positions(&u);
        prop_assert!(s.iterations <= 3, "{s:?}");
        let (p, v) = comp.model().actual_pose(&s.drive);
        let (pn, vn) = nominal_pose(&comp.model().geometry, &u);
        prop_assert!(distance_mm(&p, &pn) / MM_PER_UM <= 0.02, "{s:?}");
        prop_assert!(angle_rad(&v, &vn) / RAD_PER_ARCSEC <= 0.01, "{s:?}");
        // The correction is of the size of the errors, not a jump.
        let corr = comp.correction(&u);
        prop_assert!(corr[..3].iter().all(|d| d.abs() < 1.0));
        prop_assert!(corr[3..].iter().all(|d| d.abs() < 1.0));
    }

    #[test]
    fn zero_model_is_identity(
        x in -10.0f64..1100.0, y in -10.0f64..900.0, z in -10.0f64..700.0,
        a in -120.0f64..120.0, c in -400.0f64..400.0,
    ) {
        let comp = VolumetricCompensator::new(synthetic_model(0.0));
        let q = [x, y, z, a, c];
        prop_assert_eq!(comp.feedback(&q).map(f64::to_bits), q.map(f64::to_bits));
    }
}

#[test]
fn pole_modes_agree_off_the_band_and_on_a_zero_model() {
    let comp = VolumetricCompensator::new(synthetic_model(1.0));
    let swing = Pole {
        mode: PoleMode::Swing,
        max_c_swing_deg: 180.0,
    };
    let grid = parse_grid("3", &comp.model().travel).expect("grid");
    for &a in &[-100.0, -3.0, 1.0, 50.0] {
        for &c in &grid[4] {
            let u = [500.0, 400.0, 300.0, a, c];
            let h = comp.drive_positions(&u);
            for pole in [Pole::default(), swing] {
                let s = comp.drive_positions_pole(&u, &pole);
                assert_eq!(s.solve.drive.map(f64::to_bits), h.drive.map(f64::to_bits));
                assert_eq!(s.newton_iterations, 0);
            }
        }
    }
    let zero = VolumetricCompensator::new(synthetic_model(0.0));
    for q in [[0.0, 0.0, 0.0, 0.0, 0.0], [10.0, 20.0, 30.0, 0.5, -120.0]] {
        for pole in [Pole::default(), swing] {
            let s = zero.drive_positions_pole(&q, &pole);
            assert_eq!(s.solve.drive.map(f64::to_bits), q.map(f64::to_bits));
        }
    }
}

#[test]
fn swing_reaches_the_pole_pose_or_reduces_its_error() {
    let comp = VolumetricCompensator::new(synthetic_model(1.0));
    let swing = Pole {
        mode: PoleMode::Swing,
        max_c_swing_deg: 180.0,
    };
    let g = comp.model().geometry;
    let err = |q: &[f64; 5], u: &[f64; 5]| {
        let (p, v) = comp.model().actual_pose(q);
        let (pn, vn) = nominal_pose(&g, u);
        (
            distance_mm(&p, &pn) / MM_PER_UM,
            angle_rad(&v, &vn) / RAD_PER_ARCSEC,
        )
    };
    let (mut reached, mut unreachable) = (0, 0);
    for &x in &[0.0, 1000.0] {
        for &c in &[-200.0, -100.0, 0.0, 100.0, 200.0] {
            let u = [x, 400.0, 300.0, 0.0, c];
            let s = comp.drive_positions_pole(&u, &swing);
            let hold = comp.drive_positions(&u);
            let (t, o) = err(&s.solve.drive, &u);
            let (_, o_hold) = err(&hold.drive, &u);
            if s.fallback {
                continue;
            }
            assert!(t <= TOL_UM, "{u:?} {s:?}");
            assert!(s.c_swing_deg <= 180.0, "{s:?}");
            if s.reached {
                reached += 1;
                assert!(o <= TOL_ARCSEC, "{u:?} {s:?}");
            } else {
                unreachable += 1;
                assert!(o < o_hold, "{u:?} {o} {o_hold}");
            }
        }
    }
    println!("reached {reached}, unreachable {unreachable}");
    assert!(reached > 0, "{reached} {unreachable}");
}
