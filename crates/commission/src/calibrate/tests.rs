use super::*;
use compgate_plc::thermal::{
    measurement_run, AmbientParams, DutyCycle, Effects, SweepPlan, ThermalMachine, ThermalParams,
};

/// A 24-hour commissioning run of the simulated machine.
fn commissioning(params: ThermalParams, seed: u64) -> (Measurements, ThermalMachine) {
    let mut machine = ThermalMachine::new(params, Effects::default(), seed);
    let cycle = DutyCycle::commissioning(24.0);
    let plan = SweepPlan::irregular(2000.0, 9, 1800.0);
    let s = measurement_run(&mut machine, &cycle, &plan, 30.0);
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
    };
    let report = run(&args).unwrap();
    assert!(report.contains("RMS residual"), "{report}");
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
    };
    let e = run(&args).unwrap_err().to_string();
    assert!(e.contains("bad.csv: line 3, column `err_um`"), "{e}");
    let (m, _) = commissioning(noiseless(), 1);
    let e = calibrate(&m, &names(&["spindle"]), None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("T_spindle") && e.contains("T_screw"), "{e}");
}
