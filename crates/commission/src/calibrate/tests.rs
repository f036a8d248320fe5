use super::*;
use compgate_plc::thermal::{
    measurement_run, AmbientParams, DutyCycle, Effects, SweepPlan, ThermalMachine, ThermalParams,
};

/// A 24-hour commissioning run of the simulated machine.
fn commissioning(params: ThermalParams, seed: u64) -> (Measurements, ThermalMachine) {
    let mut machine = ThermalMachine::new(params, Effects::default(), seed);
    let cycle = DutyCycle::commissioning(24.0);
    let plan = SweepPlan::irregular(2000.0, 9, 1800.0);
    let s = measurement_run(&mut machine, &cycle, &plan);
    (Measurements::from(&s), machine)
}

fn noiseless() -> ThermalParams {
    ThermalParams {
        ambient: AmbientParams {
            wander_degc: 0.0,
            ..AmbientParams::default()
        },
        sensor_noise_degc: 0.0,
        sensor_tau_s: 0.0,
        interferometer_noise_um: 0.0,
        ..ThermalParams::default()
    }
}

fn names(v: &[&str]) -> Vec<String> {
    v.iter().map(|s| s.to_string()).collect()
}

/// Relative error of `got` against `want`, or of a coefficient that should be zero
/// against the scale of the non-zero one.
fn rel(got: f64, want: f64, scale: f64) -> f64 {
    (got - want).abs() / if want != 0.0 { want.abs() } else { scale }
}

fn check(f: &Fit, machine: &ThermalMachine, tol: f64) {
    let truth = machine.true_model();
    assert_eq!(f.p0_mm, truth.p0_mm);
    let col = f
        .terms
        .iter()
        .find(|t| t.name == "column")
        .expect("column term");
    let screw = f
        .terms
        .iter()
        .find(|t| t.name == "screw")
        .expect("screw term");
    let k = truth.k0_um_per_degc_column;
    let tb = truth.tan_beta_per_degc_screw;
    let errs = [
        ("K0 column", rel(col.k0_um_per_degc, k, k)),
        ("K0 screw", rel(screw.k0_um_per_degc, 0.0, k)),
        ("tan_beta screw", rel(screw.tan_beta_per_degc, tb, tb)),
        ("tan_beta column", rel(col.tan_beta_per_degc, 0.0, tb)),
    ];
    for (what, e) in errs {
        assert!(
            e < tol,
            "{what}: relative error {e:.4} >= {tol}\n{}",
            report(f)
        );
    }
}

#[test]
fn recovers_true_coefficients_within_5_percent_on_noiseless_data() {
    let (m, machine) = commissioning(noiseless(), 11);
    let f = calibrate(&m, &names(&["column", "screw"]), None).unwrap();
    // The figures, for the README (`-- --nocapture`).
    eprintln!("noiseless, sensors column,screw:\n{}", report(&f));
    check(&f, &machine, 0.05);
    assert!(f.rms_um < 0.05, "{}", report(&f));
    // With every sensor the extra terms must come out ~0 as well.
    let f = calibrate(&m, &[], None).unwrap();
    assert_eq!(f.terms.len(), 5);
    check(&f, &machine, 0.05);
}

#[test]
fn recovers_true_coefficients_within_3_percent_with_noise() {
    // Default instruments: sensor noise 0.02 K and 20 s lag, interferometer 0.3 um,
    // ambient wander. Three seeds.
    for seed in [1, 2, 3] {
        let (m, machine) = commissioning(ThermalParams::default(), seed);
        let f = calibrate(&m, &names(&["T_column", "screw"]), None).unwrap();
        check(&f, &machine, 0.03);
        assert!(f.rms_um < 1.0, "{}", report(&f));
    }
}

#[test]
fn written_model_loads_into_a_gateway_config() {
    let (m, _) = commissioning(ThermalParams::default(), 5);
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("m.csv");
    m.write(std::fs::File::create(&csv).unwrap()).unwrap();
    let args = CalibrateArgs {
        data: csv,
        out: dir.path().join("model.toml"),
        sensors: names(&["column", "screw"]),
        p0_mm: None,
        axis: "X".into(),
        nc_module: "nc_x".into(),
        plot: Some(dir.path().join("fit.svg")),
        accept_weak_fit: false,
    };
    let calibrated = run(&args).unwrap();
    let report = calibrated.report();
    assert!(report.contains("RMS residual"), "{report}");
    assert!(calibrated.warnings().is_empty(), "{report}");
    calibrated.write().unwrap();
    let fragment = std::fs::read_to_string(&args.out).unwrap();
    let mut cfg = String::from(
        "[devices.ain]\ntransport = \"tcp\"\naddress = \"127.0.0.1:1\"\nunit_id = 1\ntimeout_s = 1.0\npoll_interval_s = 1.0\n\n\
         [nc_modules.nc_x]\naddress = \"127.0.0.1:2\"\nunit_id = 1\n\n",
    );
    for (i, ch) in ["column", "screw"].iter().enumerate() {
        cfg.push_str(&format!(
            "[channels.{ch}]\ndevice = \"ain\"\nregister = \"input\"\naddress = {i}\ndata_type = \"u16\"\n\
             scaling = {{ kind = \"direct\", gain = 0.01, offset_degc = 0.0 }}\n\n"
        ));
    }
    cfg.push_str(&fragment);
    let loaded =
        compgate_gateway::config::load_str(&cfg, "test").unwrap_or_else(|e| panic!("{e}\n{cfg}"));
    let ax = &loaded.axes["X"];
    let f = calibrate(&m, &names(&["column", "screw"]), None).unwrap();
    let model = AxisModel::from_fit(&f);
    assert_eq!(ax.k0, model.k0);
    assert_eq!(ax.tan_beta, model.tan_beta);
    assert_eq!(ax.p0_mm, model.p0_mm);
    assert_eq!(ax.md32750, 3);
    // And load_model reads it back alike.
    let (name, back) = load_model(&args.out).unwrap();
    assert_eq!((name.as_str(), &back), ("X", &model));
    let svg = std::fs::read_to_string(dir.path().join("fit.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("fitted model"));
}

#[test]
fn bad_input_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("bad.csv");
    std::fs::write(&csv, "t_s,pos_mm,err_um,T_a\n0,0,1,20\n1,10,oops,20\n").unwrap();
    let args = CalibrateArgs {
        data: csv,
        out: dir.path().join("m.toml"),
        sensors: vec![],
        p0_mm: None,
        axis: "X".into(),
        nc_module: "nc_x".into(),
        plot: None,
        accept_weak_fit: false,
    };
    let e = run(&args).unwrap_err().to_string();
    assert!(e.contains("bad.csv: line 3, column `err_um`"), "{e}");
    let (m, _) = commissioning(noiseless(), 1);
    let e = calibrate(&m, &names(&["spindle"]), None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("T_spindle") && e.contains("T_screw"), "{e}");
    // A sensor named twice was "linearly dependent ... moves with the position".
    for twice in [&["column", "column"][..], &["column", "T_column"]] {
        let e = calibrate(&m, &names(twice), None).unwrap_err().to_string();
        assert_eq!(e, "--sensors: T_column named twice");
    }
}

/// Arguments fitting `column` and `screw` of `m`, written to `dir/name`.
fn column_and_screw(dir: &std::path::Path, m: &Measurements, name: &str) -> CalibrateArgs {
    let csv = dir.join(name);
    m.write(std::fs::File::create(&csv).unwrap()).unwrap();
    let mut args = args_for(dir, csv);
    args.sensors = names(&["column", "screw"]);
    args
}

fn args_for(dir: &std::path::Path, csv: std::path::PathBuf) -> CalibrateArgs {
    CalibrateArgs {
        data: csv,
        out: dir.join("m.toml"),
        sensors: vec![],
        p0_mm: None,
        axis: "X".into(),
        nc_module: "nc_x".into(),
        plot: None,
        accept_weak_fit: false,
    }
}

/// `--p0-mm nan` made the SVD spin for ever; now it is refused, naming the flag.
#[test]
fn non_finite_or_absurd_p0_is_refused_naming_the_flag() {
    let (m, _) = commissioning(noiseless(), 1);
    for (p0, what) in [
        (f64::NAN, "--p0-mm NaN: not a finite number"),
        (f64::INFINITY, "--p0-mm inf: not a finite number"),
        (1e300, "--p0-mm 1e300: outside"),
    ] {
        let e = calibrate(&m, &[], Some(p0)).unwrap_err().to_string();
        assert!(e.contains(what), "{e}");
    }
}

/// 1e300 in the data once gave "linearly dependent" without a line; the reader now
/// names the line and the column.
#[test]
fn huge_value_in_the_data_is_refused_with_line_and_column() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("huge.csv");
    std::fs::write(
        &csv,
        "t_s,pos_mm,err_um,T_a\n0,0,1,20\n1,10,2,21\n2,1e300,3,22\n3,30,4,23\n",
    )
    .unwrap();
    let e = run(&args_for(dir.path(), csv)).unwrap_err().to_string();
    assert!(e.contains("huge.csv: line 4, column `pos_mm`"), "{e}");
}

fn hand_model() -> AxisModel {
    AxisModel {
        p0_mm: 0.0,
        accepted_doubts: Vec::new(),
        k0: compgate_gateway::config::K0Model {
            offset_mm: 0.001,
            terms: vec![compgate_gateway::config::K0Term {
                channel: "a".into(),
                ref_degc: 20.0,
                coeff_mm_per_degc: 0.001,
                lag_tau_s: 0.0,
            }],
        },
        tan_beta: compgate_gateway::config::TanBetaModel {
            offset: 1e-5,
            terms: vec![compgate_gateway::config::TanBetaTerm {
                channel: "a".into(),
                ref_degc: 20.0,
                coeff_per_degc: 1e-6,
                lag_tau_s: 0.0,
            }],
        },
        motion_heat: None,
        fitted_degc: Default::default(),
    }
}

/// `err_um = 1e308` once wrote `offset_mm = -inf`, `coeff_mm_per_degc = nan`: the
/// writer now refuses any non-finite or out-of-range value, naming the key.
#[test]
fn model_writer_refuses_non_finite_and_implausible_values() {
    assert!(model_toml("X", "nc_x", &hand_model(), "").is_ok());
    type Spoil = fn(&mut AxisModel);
    let cases: [(Spoil, &str); 5] = [
        (
            |m| m.k0.offset_mm = f64::NEG_INFINITY,
            "axes.X.k0.offset_mm = -inf",
        ),
        (
            |m| m.k0.terms[0].coeff_mm_per_degc = f64::NAN,
            "axes.X.k0.terms[0].coeff_mm_per_degc = NaN",
        ),
        (|m| m.tan_beta.offset = 0.2, "axes.X.tan_beta.offset = 0.2"),
        (
            |m| m.tan_beta.terms[0].coeff_per_degc = 0.02,
            "axes.X.tan_beta.terms[0].coeff_per_degc",
        ),
        (|m| m.p0_mm = 1e6, "axes.X.p0_mm = 1000000.0"),
    ];
    for (spoil, key) in cases {
        let mut m = hand_model();
        spoil(&mut m);
        let e = model_toml("X", "nc_x", &m, "").unwrap_err().to_string();
        assert!(e.contains(key), "{e}");
    }
}

/// The reader refuses `nan` and out-of-range values, naming the file and the key.
#[test]
fn model_reader_refuses_non_finite_values_naming_file_and_key() {
    let dir = tempfile::tempdir().unwrap();
    let good = model_toml("X", "nc_x", &hand_model(), "").unwrap();
    for (from, to, key) in [
        (
            "offset_mm = 0.001",
            "offset_mm = nan",
            "axes.X.k0.offset_mm = NaN",
        ),
        ("p0_mm = 0.0", "p0_mm = inf", "axes.X.p0_mm = inf"),
        ("ref_degc = 20.0", "ref_degc = 1e300", "ref_degc = 1e300"),
    ] {
        assert!(good.contains(from), "{good}");
        let path = dir.path().join("bad_model.toml");
        std::fs::write(&path, good.replacen(from, to, 1)).unwrap();
        let e = load_model(&path).unwrap_err().to_string();
        assert!(e.contains("bad_model.toml") && e.contains(key), "{e}");
    }
}

/// What `compgate export` writes without --err-channel (err_um 0 on every row) was
/// fitted with "R^2 1.000000, RMS 0.000" and an all-zero model written: now refused,
/// and no model file is written.
#[test]
fn an_export_without_the_error_channel_is_refused_and_no_model_written() {
    let (m, _) = commissioning(noiseless(), 1);
    let zero = Measurements {
        err_um: vec![0.0; m.len()],
        ..m
    };
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("export.csv");
    zero.write(std::fs::File::create(&csv).unwrap()).unwrap();
    let args = args_for(dir.path(), csv);
    let e = run(&args).unwrap_err().to_string();
    assert!(
        e.contains("column `err_um` is constant (0 um on every row)")
            && e.contains("--err-channel"),
        "{e}"
    );
    assert!(!args.out.exists());
}

/// The model was replaced, then the plot failed (a directory, or a directory that
/// cannot be written): the command said "error" with a new model in place, and no
/// report. Now a plot path that is a directory is refused before the data is read,
/// and one that cannot be written leaves the model as it was.
#[test]
fn a_plot_that_cannot_be_written_leaves_the_model_as_it_was() {
    let (m, _) = commissioning(noiseless(), 1);
    let dir = tempfile::tempdir().unwrap();
    let mut args = column_and_screw(dir.path(), &m, "m.csv");
    std::fs::write(&args.out, "# previous good model\n").unwrap();
    args.plot = Some(dir.path().to_path_buf());
    let e = run(&args).unwrap_err().to_string();
    assert!(e.ends_with("is a directory; give a file name"), "{e}");
    // A directory no one may create files in (even root): /proc/self.
    args.plot = Some("/proc/self/calib.svg".into());
    let calibrated = run(&args).unwrap();
    assert!(calibrated.report().contains("RMS residual"));
    let e = calibrated.write().unwrap_err().to_string();
    assert!(e.starts_with("/proc/self/calib.svg: "), "{e}");
    let model = std::fs::read_to_string(&args.out).unwrap();
    assert_eq!(model, "# previous good model\n");
    let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert_eq!(left.len(), 2, "a temporary file is left: {left:?}");
}

/// Temperatures that hold one level (noise of 0.01 K: no sensor sees the drift)
/// were fitted with R^2 0.10 and coefficients ten times smaller than their standard
/// errors, and the model written without a word. Now the report and the warnings
/// say so, and the model is written only with --accept-weak-fit.
#[test]
fn a_fit_the_temperatures_do_not_explain_is_warned_about_and_not_written() {
    use rand::{Rng, SeedableRng};
    let (mut m, _) = commissioning(ThermalParams::default(), 1);
    let mut rng = rand::rngs::SmallRng::seed_from_u64(1);
    for c in &mut m.temps {
        for v in &mut c.degc {
            *v = 20.0 + 0.01 * (rng.random::<f64>() - 0.5) * 3.46;
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let mut args = column_and_screw(dir.path(), &m, "onelevel.csv");
    let calibrated = run(&args).unwrap();
    let warnings = calibrated.warnings();
    // Each sensor's span, the slopes the noise gave, and the fit itself.
    assert_eq!(warnings.len(), 5, "{warnings:?}");
    assert!(
        warnings[0].starts_with("T_column spans only 0.0"),
        "{warnings:?}"
    );
    assert!(warnings[4].starts_with("the temperatures do not explain the error: beyond"));
    let report = calibrated.report();
    assert!(
        report.contains("\nwarning: the temperatures do not explain"),
        "{report}"
    );
    let e = calibrated.write().unwrap_err().to_string();
    assert!(
        e.contains("not written") && e.contains("--accept-weak-fit"),
        "{e}"
    );
    assert!(!args.out.exists());
    args.accept_weak_fit = true;
    run(&args).unwrap().write().unwrap();
    let doubts = written_doubts(&args.out);
    assert_eq!(doubts.len(), 5, "{doubts:?}");
    assert!(
        doubts[0].starts_with("T_column spans only 0.0"),
        "{doubts:?}"
    );
    // scenario runs (and writes) the model of its fit whatever it holds.
    let f = calibrate(&m, &names(&["column", "screw"]), None).unwrap();
    assert_eq!(AxisModel::from_fit(&f).accepted_doubts, doubts);
}

/// The doubts a forced model file lists as `accepted_doubts`, a key the gateway
/// warns of at start (a comment was all before, which nothing read).
fn written_doubts(path: &std::path::Path) -> Vec<String> {
    let text = std::fs::read_to_string(path).unwrap();
    let model: toml::Table = toml::from_str(&text).unwrap();
    model["axes"]["X"]["accepted_doubts"]
        .as_array()
        .unwrap_or_else(|| panic!("{text}"))
        .iter()
        .map(|d| d.as_str().unwrap().to_string())
        .collect()
}

/// A geometric slope (100 um/m) under the same temperatures that hold one level:
/// the slope raised R^2 above 0.5 and the model of noise was written. What the
/// temperature terms add over constant K0 and tan(beta) decides, so it is refused.
#[test]
fn a_geometric_slope_does_not_get_a_model_of_noise_written() {
    use rand::{Rng, SeedableRng};
    let (mut m, _) = commissioning(ThermalParams::default(), 1);
    let mut rng = rand::rngs::SmallRng::seed_from_u64(1);
    for c in &mut m.temps {
        for v in &mut c.degc {
            *v = 20.0 + 0.6 * (rng.random::<f64>() - 0.5) * 3.46;
        }
    }
    for (e, p) in m.err_um.iter_mut().zip(&m.pos_mm) {
        *e += 0.1 * p;
    }
    let dir = tempfile::tempdir().unwrap();
    let args = column_and_screw(dir.path(), &m, "slope.csv");
    let calibrated = run(&args).unwrap();
    let report = calibrated.report();
    let r2: f64 = report.split("R^2 ").nth(1).unwrap()[..8].parse().unwrap();
    assert!(r2 > 0.5, "{report}");
    let e = calibrated.write().unwrap_err().to_string();
    assert!(
        e.contains("not written") && e.contains("partial R^2"),
        "{e}"
    );
    assert!(!args.out.exists());
}

/// A header `t_screw` (lower case) was fitted without, and nothing said so: the report
/// names every column the fit did not read, as diagnose does.
#[test]
fn the_report_names_the_columns_the_fit_did_not_read() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("d.csv");
    let (m, _) = commissioning(noiseless(), 1);
    let mut buf = Vec::new();
    m.write(&mut buf).unwrap();
    let text: String = String::from_utf8(buf)
        .unwrap()
        .lines()
        .enumerate()
        .map(|(i, l)| format!("{l},{}\n", if i == 0 { "t_spare" } else { "1" }))
        .collect();
    std::fs::write(&csv, text).unwrap();
    let sensors: Vec<String> = m.temps.iter().map(|c| c.name.clone()).collect();
    assert!(sensors.len() >= 2, "{sensors:?}");
    let mut args = args_for(dir.path(), csv.clone());
    args.sensors = sensors.clone();
    let report = run(&args).unwrap().report();
    assert!(report.starts_with("ignored columns: t_spare\n"), "{report}");
    let all = report;

    // The last sensor left out, with a NaN in its third row.
    let text = std::fs::read_to_string(&csv).unwrap();
    let last = format!("T_{}", sensors[sensors.len() - 1]);
    let at = text
        .lines()
        .next()
        .unwrap()
        .split(',')
        .position(|h| h == last)
        .unwrap();
    let text: String = text
        .lines()
        .enumerate()
        .map(|(i, l)| {
            let mut c: Vec<&str> = l.split(',').collect();
            if i == 2 {
                c[at] = "NaN";
            }
            c.join(",") + "\n"
        })
        .collect();
    std::fs::write(&csv, text).unwrap();
    args.sensors = sensors[..sensors.len() - 1].to_vec();
    let report = run(&args).unwrap().report();
    assert!(
        report.starts_with(&format!("ignored columns: {last}, t_spare\n")),
        "{report}"
    );
    assert_ne!(report, all, "fitted without {last}");
    // Read, it is refused with its line.
    args.sensors = sensors.clone();
    let e = run(&args).unwrap_err().to_string();
    assert!(e.contains(&format!("line 3, column `{last}`")), "{e}");
    // A sensor the file lacks is named with every T_ column there is.
    args.sensors = vec!["nope".into()];
    let e = run(&args).unwrap_err().to_string();
    assert!(e.contains("nope") && e.contains(&last), "{e}");
}

/// A continuous capture of 100k rows gave a 10 MB plot of 100k dots: the sweeps' dots
/// are thinned to about 1000 in all.
#[test]
fn the_plot_of_a_long_capture_stays_small() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("long.csv");
    let mut text = String::from("t_s,pos_mm,err_um,T_a,T_b\n");
    for i in 0..20_000 {
        let t_s = f64::from(i);
        let pos_mm = (t_s * 0.37).sin() * 500.0;
        let (ta, tb) = (20.0 + t_s / 4000.0, 22.0 + (t_s / 900.0).sin());
        let err_um = 5.0 * (ta - 20.0) + 0.01 * pos_mm + 0.002 * pos_mm * (tb - 22.0);
        text.push_str(&format!("{t_s},{pos_mm},{err_um},{ta},{tb}\n"));
    }
    std::fs::write(&csv, text).unwrap();
    let mut args = args_for(dir.path(), csv);
    args.plot = Some(dir.path().join("p.svg"));
    run(&args).unwrap().write().unwrap();
    let svg = std::fs::read_to_string(dir.path().join("p.svg")).unwrap();
    let dots = svg.matches("<circle").count();
    assert!((500..=1100).contains(&dots), "{dots} dots");
}

/// Positions in inches (the error curve's slope 25.4 times too steep) were fitted
/// with R^2 0.9999 and a tan(beta) coefficient 25 times steel's expansion, and the
/// model written: on the plant it made the error 19 times larger (review V). Now the
/// coefficient is named with the likely cause, and nothing is written.
#[test]
fn a_slope_coefficient_no_structure_has_is_refused_naming_the_units() {
    let (mut m, _) = commissioning(ThermalParams::default(), 1);
    for p in &mut m.pos_mm {
        *p /= 25.4;
    }
    let dir = tempfile::tempdir().unwrap();
    let args = column_and_screw(dir.path(), &m, "inches.csv");
    let calibrated = run(&args).unwrap();
    let warnings = calibrated.warnings().join("\n");
    assert!(
        warnings.contains("T_screw's tan(beta) coefficient") && warnings.contains("inches"),
        "{warnings}"
    );
    let e = calibrated.write().unwrap_err().to_string();
    assert!(
        e.contains("not written: T_screw's tan(beta) coefficient is 2.9"),
        "{e}"
    );
    assert!(!args.out.exists());
    // In millimetres the same run is written, without a warning.
    let (m, _) = commissioning(ThermalParams::default(), 1);
    written_without_a_warning(dir.path(), &m, "mm.csv");
}

/// Calibrates `m` on column and screw: no warning, and the model written.
fn written_without_a_warning(dir: &std::path::Path, m: &Measurements, name: &str) {
    let args = column_and_screw(dir, m, name);
    let calibrated = run(&args).unwrap();
    assert!(
        calibrated.warnings().is_empty(),
        "{:?}",
        calibrated.warnings()
    );
    calibrated.write().unwrap();
}

/// The first 30 minutes of a run (the column moved 0.08 K) gave a column K0
/// coefficient of the wrong sign, written with only a warning: the screw's term was
/// significant, so the fit did not count as undetermined (review V). A sensor that
/// barely moved now keeps the model from being written.
#[test]
fn a_run_cut_short_is_not_written_as_a_model() {
    let (mut m, _) = commissioning(ThermalParams::default(), 1);
    let n = 20;
    for v in [&mut m.t_s, &mut m.pos_mm, &mut m.err_um, &mut m.travel_mm] {
        v.truncate(n);
    }
    m.dir.truncate(n);
    for c in &mut m.temps {
        c.degc.truncate(n);
    }
    let dir = tempfile::tempdir().unwrap();
    let mut args = column_and_screw(dir.path(), &m, "short.csv");
    let calibrated = run(&args).unwrap();
    let e = calibrated.write().unwrap_err().to_string();
    assert!(e.contains("not written: T_column spans only 0."), "{e}");
    assert!(!args.out.exists());
    args.accept_weak_fit = true;
    run(&args).unwrap().write().unwrap();
    assert!(args.out.exists());
}

/// The model file carries the temperatures it was fitted over, which the gateway
/// flags a reading beyond (review V: a model fitted on 17..27 degC ran at 35 degC
/// without a word).
#[test]
fn the_model_names_the_temperatures_it_was_fitted_over() {
    let (m, _) = commissioning(ThermalParams::default(), 1);
    let dir = tempfile::tempdir().unwrap();
    let args = column_and_screw(dir.path(), &m, "run.csv");
    run(&args).unwrap().write().unwrap();
    let (_, model) = crate::calibrate::load_model(&args.out).unwrap();
    assert_eq!(model.fitted_degc.len(), 2, "{:?}", model.fitted_degc);
    assert!(
        model.fitted_degc.contains_key("column"),
        "{:?}",
        model.fitted_degc
    );
    for c in m
        .temps
        .iter()
        .filter(|c| model.fitted_degc.contains_key(&c.name))
    {
        let [lo, hi] = model.fitted_degc[&c.name];
        let min = c.degc.iter().copied().fold(f64::INFINITY, f64::min);
        let max = c.degc.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        assert!(lo <= min && min - lo < 0.01, "{}: {lo} {min}", c.name);
        assert!(hi >= max && hi - max < 0.01, "{}: {hi} {max}", c.name);
    }
}

/// err_um in millimetres (1000 times too small) was written as a model with an RMS
/// residual of 0.001 um, which passed nothing through the deadband (review V).
#[test]
fn an_error_column_in_millimetres_is_named_and_not_written() {
    let (mut m, _) = commissioning(ThermalParams::default(), 1);
    for e in &mut m.err_um {
        *e /= 1000.0;
    }
    let dir = tempfile::tempdir().unwrap();
    let args = column_and_screw(dir.path(), &m, "mm.csv");
    let calibrated = run(&args).unwrap();
    let warnings = calibrated.warnings().join("\n");
    assert!(warnings.contains("is it in mm?"), "{warnings}");
    let e = calibrated.write().unwrap_err().to_string();
    assert!(e.contains("not written: err_um spans only 0.28"), "{e}");
    assert!(!args.out.exists());
}

/// One err_um of -999 (a logger's mark for a missing value) turned a 2 um fit into 16
/// um, and a sensor that read 0 for ten minutes moved every coefficient; both models
/// were written without a word (field review). The rows are named by their line, and
/// the model is written only with --accept-weak-fit. An interferometer's single
/// glitch of a few um, which moves nothing, is named and the model written; a cold
/// start's rows off together are the machine, and a fast sensor no excursion
/// (second field review: both were refused).
#[test]
fn bad_readings_are_named_by_line_and_keep_the_model_from_being_written() {
    let (clean, _) = commissioning(ThermalParams::default(), 2);
    let dir = tempfile::tempdir().unwrap();
    let args = column_and_screw(dir.path(), &clean, "clean.csv");
    let calibrated = run(&args).unwrap();
    assert!(
        calibrated.warnings().is_empty(),
        "{:?}",
        calibrated.warnings()
    );

    let mut m = clean.clone();
    m.err_um[100] = -999.0;
    let mut args = column_and_screw(dir.path(), &m, "m999.csv");
    let calibrated = run(&args).unwrap();
    let w = calibrated.warnings();
    assert_eq!(w.len(), 1, "{w:?}");
    let row = format!(
        "line 102 (t_s {}, pos_mm {}, err_um -999, T_column ",
        m.t_s[100], m.pos_mm[100]
    );
    assert!(
        w[0].starts_with("1 row looks like bad readings") && w[0].contains(&row),
        "{w:?}"
    );
    assert!(
        calibrated
            .report()
            .contains(&format!("\nwarning: {}\n", w[0])),
        "{}",
        calibrated.report()
    );
    let e = calibrated.write().unwrap_err().to_string();
    assert!(
        e.contains("bad readings move the fitted error by up to"),
        "{e}"
    );
    assert!(!args.out.exists());
    args.accept_weak_fit = true;
    run(&args).unwrap().write().unwrap();
    let doubts = written_doubts(&args.out);
    assert_eq!(doubts.len(), 1, "{doubts:?}");
    assert!(
        doubts[0].starts_with("bad readings move the fitted error"),
        "{doubts:?}"
    );

    // The column sensor drops out to 0 for three rows.
    let i = 200;
    let mut m = clean.clone();
    let col = m.temps.iter_mut().find(|c| c.name == "column").unwrap();
    let before = col.degc[i - 1];
    col.degc[i..i + 3].fill(0.0);
    let args = column_and_screw(dir.path(), &m, "dropout.csv");
    let calibrated = run(&args).unwrap();
    let w = calibrated.warnings().join("\n");
    let named = format!(
        "T_column reads 0 on lines {}-{} ({before} degC before)",
        i + 2,
        i + 4
    );
    assert!(w.contains(&named), "{w}");
    let e = calibrate_error(&calibrated);
    assert!(e.contains("bad readings move the fitted error"), "{e}");

    // A 3 um glitch: named, and the model written.
    let mut m = clean.clone();
    let typical = calibrate(&m, &names(&["column", "screw"]), None)
        .unwrap()
        .rms_um;
    m.err_um[300] += 3.0_f64.max(15.0 * typical);
    let args = column_and_screw(dir.path(), &m, "glitch.csv");
    let calibrated = run(&args).unwrap();
    let w = calibrated.warnings().join("\n");
    assert!(
        w.contains("line 302 (") && w.contains("the model stands"),
        "{w}"
    );
    calibrated.write().unwrap();

    // A cold start: the first 15 rows off together, 10 um decaying.
    let mut m = clean.clone();
    for (k, e) in m.err_um.iter_mut().take(15).enumerate() {
        *e -= 10.0 * (-(k as f64) / 5.0).exp();
    }
    let args = column_and_screw(dir.path(), &m, "coldstart.csv");
    let calibrated = run(&args).unwrap();
    assert!(
        !calibrated.warnings().join("\n").contains("bad readings"),
        "{:?}",
        calibrated.warnings()
    );
}

/// The refusal of a write, as text.
fn calibrate_error(calibrated: &Calibrated<'_>) -> String {
    calibrated.write().unwrap_err().to_string()
}

/// Temperatures logged in kelvin (296 K read as degC) were fitted without a word, and
/// the model's fitted_degc lay beyond every channel's range (field review).
#[test]
fn temperatures_in_kelvin_keep_the_model_from_being_written() {
    let (mut m, _) = commissioning(ThermalParams::default(), 3);
    for c in &mut m.temps {
        for v in &mut c.degc {
            *v += 273.15;
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let args = column_and_screw(dir.path(), &m, "kelvin.csv");
    let calibrated = run(&args).unwrap();
    let w = calibrated.warnings();
    assert_eq!(w.len(), 2, "{w:?}");
    assert!(w[0].starts_with("T_column never reads below 29"), "{w:?}");
    assert!(w[0].contains("in kelvin?"), "{w:?}");
    let e = calibrated.write().unwrap_err().to_string();
    assert!(e.contains("T_screw never reads below"), "{e}");
}

/// `--sensors a` on a header `T_a [degC]` said only that there is no column T_a.
#[test]
fn a_sensor_header_with_units_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("units.csv");
    std::fs::write(&csv, "t_s,pos_mm,err_um,T_a [degC],T_b\n0,0,1,20,20\n").unwrap();
    let mut args = args_for(dir.path(), csv);
    args.sensors = names(&["a"]);
    let e = run(&args).unwrap_err().to_string();
    assert_eq!(
        e,
        "--sensors: no column T_a in the data (it has: T_a [degC], T_b); `T_a [degC]`: the \
         header holds the name alone, without units"
    );
}

/// Rows every 20 s over 24 h (an export with --step-s) were one sweep: the plot drew
/// one curve labelled with the first row's time and temperature (field review).
#[test]
fn regular_rows_are_split_into_hour_long_sweeps() {
    let t_s: Vec<f64> = (0..4320).map(|i| 20.0 * i as f64).collect();
    let s = sweeps(&t_s);
    assert_eq!(s.len(), 24, "{s:?}");
    assert!(s.iter().all(|r| r.len() == 180), "{s:?}");
    // Sweeps with pauses between them stay as they are.
    let t_s: Vec<f64> = (0..90)
        .map(|i| (i / 9) as f64 * 1800.0 + (i % 9) as f64 * 4.0)
        .collect();
    assert_eq!(sweeps(&t_s).len(), 10);
}

/// A transmitter frozen at a plausible value from hour 14 of a 24-hour run on was fitted
/// without a word (field review R5-D): the fit gave the screw the column's part. It
/// is named by its lines and the model is not written; a sensor that holds its value
/// without moving the fit is not named.
#[test]
fn a_frozen_sensor_that_moves_the_fit_is_named_and_keeps_the_model_from_being_written() {
    let (clean, _) = commissioning(ThermalParams::default(), 2);
    let dir = tempfile::tempdir().unwrap();
    let mut m = clean.clone();
    let from = m.t_s.iter().position(|&t| t >= 14.0 * 3600.0).unwrap();
    let col = m.temps.iter_mut().find(|c| c.name == "column").unwrap();
    let held = col.degc[from];
    col.degc[from..].fill(held);
    let args = column_and_screw(dir.path(), &m, "frozen.csv");
    let calibrated = run(&args).unwrap();
    let w = calibrated.warnings().join("\n");
    let named = format!(
        "T_column holds {held} degC exactly on lines {}-{} (",
        from + 2,
        m.len() + 1
    );
    assert!(w.contains(&named), "{w}");
    let e = calibrate_error(&calibrated);
    assert!(e.contains("bad readings move the fitted error"), "{e}");

    // The same hold on a sensor the fit does not read is not named.
    let mut args = column_and_screw(dir.path(), &m, "frozen_other.csv");
    args.sensors = names(&["screw", "motor"]);
    let calibrated = run(&args).unwrap();
    assert!(
        !calibrated.warnings().join("\n").contains("holds"),
        "{:?}",
        calibrated.warnings()
    );

    // A column logged to 0.5 K holds each value for hours while the screw warms,
    // which leaving out does not change: not named, the model written.
    let mut m = clean.clone();
    let col = m.temps.iter_mut().find(|c| c.name == "column").unwrap();
    col.degc
        .iter_mut()
        .for_each(|v| *v = (*v * 2.0).round() / 2.0);
    assert!(!m.frozen_readings().is_empty());
    written_without_a_warning(dir.path(), &m, "coarse.csv");
}
