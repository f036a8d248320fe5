use super::*;

fn args(dir: &Path, hours: f64) -> ScenarioArgs {
    ScenarioArgs {
        hours,
        seed: 3,
        plant: "ideal".into(),
        effects: vec![],
        closed_loop: false,
        record_hours: 24.0,
        model: None,
        sensors: vec!["column".into(), "screw".into()],
        out: dir.to_path_buf(),
        sample_every_s: 300.0,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_hour_with_the_gateway_in_the_loop_cuts_the_error() {
    let dir = tempfile::tempdir().unwrap();
    let r = run(&args(dir.path(), 1.0)).await.unwrap();
    let text = r.text();
    // The screw warms up in the first hour: a clear error without compensation.
    assert!(r.off.stats.peak_to_peak_um > 10.0, "{text}");
    assert!(r.reduction_pp_percent() > 70.0, "{text}");
    assert!(r.reduction_rms_percent() > 70.0, "{text}");
    // The compensation came through real FB3 jobs; the off run wrote none.
    assert!(r.on.jobs_ok > 5 && r.on.jobs_failed == 0, "{text}");
    assert_eq!(r.off.jobs_ok, 0);
    assert!(r.on.applied_um.iter().any(|a| a.abs() > 5.0), "{text}");
    assert!(r.off.applied_um.iter().all(|a| *a == 0.0));
    // Both runs saw the same machine: identical temperatures.
    assert_eq!(r.off.series.temps, r.on.series.temps);
    // The closing ISO 230-2 test: 5 runs each way at every target.
    let iso_on = r.iso_on.clone().unwrap();
    assert!(iso_on
        .targets
        .iter()
        .all(|t| t.runs_up == ISO_RUNS && t.runs_down == ISO_RUNS));
    assert!(
        iso_on.e_um < r.iso_off.clone().unwrap().e_um / 3.0,
        "{text}"
    );
    // The outputs can be read back.
    for f in ["off.csv", "on.csv", "commissioning.csv", "iso230_on.csv"] {
        let m = Measurements::read_path(&dir.path().join(f)).unwrap();
        assert!(m.len() >= 18 && m.temp("screw").is_some(), "{f}");
    }
    let back = Measurements::read_path(&dir.path().join("on.csv")).unwrap();
    assert_eq!(back.len(), r.on.series.len());
    let (_, model) = calibrate::load_model(&dir.path().join("model.toml")).unwrap();
    assert_eq!(model, r.model);
    for f in ["error_vs_time.svg", "error_vs_position.svg"] {
        let svg = std::fs::read_to_string(dir.path().join(f)).unwrap();
        assert!(svg.starts_with("<svg"), "{f}");
    }
    assert!(std::fs::read_to_string(dir.path().join("report.md"))
        .unwrap()
        .contains("reduction"));
}

#[tokio::test]
async fn a_model_reading_an_unknown_channel_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("m.toml");
    std::fs::write(
        &model,
        "[axes.X]\nnc_module = \"nc\"\nmd32750 = 3\n[axes.X.k0]\nterms = [{ channel = \"spindle\", coeff_mm_per_degc = 0.001 }]\n",
    )
    .unwrap();
    let mut a = args(dir.path(), 0.1);
    a.model = Some(model);
    let e = run(&a).await.unwrap_err().to_string();
    assert!(e.contains("`spindle`") && e.contains("screw"), "{e}");
    a.sample_every_s = 10.0;
    let e = run(&a).await.unwrap_err().to_string();
    assert!(e.contains("--sample-every-s must be at least 36 s"), "{e}");
    a.sample_every_s = 600.0;
    a.effects = vec!["warp".into()];
    let e = run(&a).await.unwrap_err().to_string();
    assert!(e.contains("unknown effect `warp`"), "{e}");
}
