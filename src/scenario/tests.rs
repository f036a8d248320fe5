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
    a.effects.clear();
    a.plant = "lab".into();
    let e = run(&a).await.unwrap_err().to_string();
    assert!(e.contains("--plant: unknown plant `lab`"), "{e}");
    a.plant = "shop".into();
    a.closed_loop = true;
    a.record_hours = 0.0;
    let e = run(&a).await.unwrap_err().to_string();
    assert!(
        e.starts_with("--record-hours 0: 0 s simulated is shorter"),
        "{e}"
    );
}

/// `--hours 0.01` (36 s, before the first sweep at 60 s) hung for ever in the plot of
/// an empty series; `--hours 1e9` ran for ever; `--hours inf` was "must be > 0".
/// Each is refused naming the flag, before anything is written.
#[tokio::test]
async fn runs_too_short_or_too_long_are_refused_naming_the_flag_and_the_range() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let mut a = args(&out, 0.01);
    let e = run(&a).await.unwrap_err().to_string();
    assert_eq!(
        e,
        "--hours 0.01: 36 s simulated is shorter than the start-up (60 s) plus one \
         interferometer sweep (36 s): give at least 0.0267 h"
    );
    for (hours, want) in [
        (
            1e9,
            "--hours 1000000000.0: outside the plausible range 0..=168 h",
        ),
        (f64::INFINITY, "--hours inf: not a finite number"),
        (f64::NAN, "--hours NaN: not a finite number"),
    ] {
        a.hours = hours;
        assert_eq!(run(&a).await.unwrap_err().to_string(), want);
    }
    a.hours = 1.0;
    a.record_hours = f64::INFINITY;
    let e = run(&a).await.unwrap_err().to_string();
    assert_eq!(e, "--record-hours inf: not a finite number");
    a.record_hours = 24.0;
    a.sample_every_s = 1e9;
    let e = run(&a).await.unwrap_err().to_string();
    assert_eq!(
        e,
        "--sample-every-s 1000000000.0: outside the plausible range 0..=86400 s"
    );
    a.sample_every_s = 600.0;
    a.sensors = vec!["column".into(), "T_column".into()];
    let e = run(&a).await.unwrap_err().to_string();
    assert_eq!(e, "--sensors: T_column named twice");
    assert!(!out.exists(), "refused before anything is written");
}

/// The shortest run --hours accepts has its one sweep, and its plots are drawn.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_shortest_run_has_one_sweep_and_its_plots() {
    let dir = tempfile::tempdir().unwrap();
    let r = run(&args(dir.path(), 0.0267)).await.unwrap();
    assert_eq!(r.off.series.len(), 2 * TARGETS, "{}", r.text());
    for f in ["error_vs_time.svg", "error_vs_position.svg"] {
        let svg = std::fs::read_to_string(dir.path().join(f)).unwrap();
        assert!(svg.trim_end().ends_with("</svg>"), "{f}");
    }
}

fn files(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| {
            let e = e.unwrap();
            let name = e.file_name().to_string_lossy().into_owned();
            (name, std::fs::read(e.path()).unwrap())
        })
        .collect();
    v.sort();
    v
}

/// A run into a directory of good results replaced them one by one, so a run that
/// failed left files of two runs side by side. A run that fails (here the loop's
/// calibrate, after the recording) now leaves every file as it was, and no
/// temporary file; an output that is a directory is refused before anything runs.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failed_run_leaves_the_last_good_files_as_they_were() {
    let dir = tempfile::tempdir().unwrap();
    let mut a = args(dir.path(), 0.03);
    // A loop run first: a run of another mode would find its files in the way.
    a.closed_loop = true;
    a.record_hours = 0.5;
    run(&a).await.unwrap();
    let before = files(dir.path());
    assert!(before.iter().any(|(n, _)| n == "report.md"), "{before:?}");
    a.record_hours = 0.03;
    a.sensors = vec!["column".into(), "bogus".into()];
    let e = run(&a).await.unwrap_err().to_string();
    assert!(e.contains("no column T_bogus"), "{e}");
    assert_eq!(files(dir.path()), before);
    a.closed_loop = false;
    a.sensors = vec!["column".into(), "screw".into()];
    std::fs::remove_file(dir.path().join("on.csv")).unwrap();
    std::fs::create_dir(dir.path().join("on.csv")).unwrap();
    let e = run(&a).await.unwrap_err().to_string();
    assert!(
        e.ends_with("on.csv: is a directory; give a file name"),
        "{e}"
    );
}

/// The closed loop on the shop plant, through the gateway's recorder, export,
/// calibrate and diagnose: the diagnosed model, applied by the gateway, beats the
/// baseline calibrated from the same records.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_closed_loop_improves_on_the_baseline() {
    let dir = tempfile::tempdir().unwrap();
    let mut a = args(dir.path(), 2.0);
    a.plant = "shop".into();
    a.closed_loop = true;
    a.record_hours = 8.0;
    let r = run(&a).await.unwrap();
    let text = r.text();
    let l = r.closed_loop.clone().unwrap();
    // The records are complete and went through export.
    assert_eq!(l.dropped, 0, "{text}");
    assert!(l.records.0 > 10_000 && l.records.2 > 1_000, "{text}");
    let rec = Measurements::read_path(&dir.path().join("recorded.csv")).unwrap();
    assert_eq!(rec.len(), l.rows);
    assert!(rec.temp("spindle").is_some() && rec.temp(LASER_CHANNEL).is_none());
    let travel_mm: f64 = rec.travel_mm.iter().sum();
    assert!(travel_mm > 100_000.0);
    // The travel is every recorded move, whatever the export's step.
    let coarse = compgate_service::record::export::measurements(
        &compgate_service::record::export::ExportArgs {
            db: dir.path().join("record.sqlite"),
            since: "0".into(),
            until: "9999999999".into(),
            csv: true,
            out: None,
            axis: Some("X".into()),
            err_channel: Some(LASER_CHANNEL.into()),
            step_s: 60.0,
            max_hold_s: 60.0,
            add_applied_comp: false,
        },
    )
    .unwrap()
    .0;
    let coarse_mm: f64 = coarse.travel_mm.iter().sum();
    assert!(
        (coarse_mm - travel_mm).abs() < 0.01 * travel_mm,
        "{coarse_mm} {travel_mm}"
    );
    // The shop plant is beyond the baseline; the loop closes most of the gap.
    let off = r.off.stats.peak_to_peak_um;
    assert!(r.on.stats.peak_to_peak_um < off, "{text}");
    assert!(
        l.updated.stats.peak_to_peak_um < 0.5 * r.on.stats.peak_to_peak_um,
        "{text}"
    );
    assert!(l.updated.stats.rms_um < 0.5 * r.on.stats.rms_um, "{text}");
    assert!(
        l.updated.jobs_ok > 5 && l.updated.jobs_failed == 0,
        "{text}"
    );
    // What diagnose named is what the gateway ran: its model file, read back.
    let mf = ModelFile::read_path(&dir.path().join("model_diagnosed.toml")).unwrap();
    assert_eq!(mf, l.model);
    assert!(!mf.applied.is_empty(), "{text}");
    let dynamic = mf.axis.motion_heat.is_some()
        || mf
            .axis
            .k0
            .terms
            .iter()
            .any(|t| t.lag_tau_s > 0.0 || !["column", "screw"].contains(&t.channel.as_str()));
    assert!(dynamic, "{mf:?}");
    for f in ["loop_vs_time.svg", "loop_vs_position.svg", "record.sqlite"] {
        assert!(dir.path().join(f).exists(), "{f}");
    }
    let md = std::fs::read_to_string(dir.path().join("report.md")).unwrap();
    assert!(
        md.contains("closed loop") && md.contains("loop_vs_time.svg"),
        "{md}"
    );
    // The export as the report prints it writes recorded.csv again, byte for byte.
    let printed = md
        .split("the export again, in this directory: `")
        .nth(1)
        .and_then(|rest| rest.split('`').next())
        .unwrap_or_else(|| panic!("no export command in the report:\n{md}"));
    use clap::Parser;
    let cli = crate::cli::Cli::try_parse_from(printed.split_whitespace())
        .unwrap_or_else(|e| panic!("{printed}: {e}"));
    let Some(crate::cli::Command::Export(mut again)) = cli.command else {
        panic!("{printed}: not an export");
    };
    again.db = dir.path().join(&again.db);
    again.out = Some(dir.path().join("again.csv"));
    compgate_service::record::export::run(&again).unwrap();
    assert!(
        std::fs::read(dir.path().join("again.csv")).unwrap()
            == std::fs::read(dir.path().join("recorded.csv")).unwrap(),
        "{printed} wrote another file"
    );
}

/// How often the interferometer samples does not change the machine: the rows both
/// runs share have the same temperatures and (up to the interferometer's noise) the
/// same error.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_sampling_rates_see_the_same_machine() {
    let (d1, d2) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let mut a = args(d1.path(), 1.0);
    a.plant = "shop".into();
    a.sample_every_s = 600.0;
    let sparse = run(&a).await.unwrap();
    a.out = d2.path().to_path_buf();
    a.sample_every_s = 120.0;
    let dense = run(&a).await.unwrap();
    let (s, d) = (&sparse.off.series, &dense.off.series);
    assert!(d.len() > 4 * s.len());
    for i in 0..s.len() {
        let j = (0..d.len())
            .find(|&j| d.t_s[j] == s.t_s[i] && d.pos_mm[j] == s.pos_mm[i])
            .unwrap_or_else(|| panic!("row {i} missing"));
        for (a, b) in s.temps.iter().zip(&d.temps) {
            assert_eq!(a.degc[i], b.degc[j]);
        }
        assert!((s.err_um[i] - d.err_um[j]).abs() < 3.0);
        assert!((sparse.on.series.err_um[i] - dense.on.series.err_um[j]).abs() < 3.0);
    }
}

/// A `--model` run into the directory of an earlier default run left that run's
/// model.toml and commissioning.csv beside its report, which seemed to name them.
/// Such a directory is refused, naming the files, before anything runs; nothing is
/// deleted, and the `--model` file itself may live there.
#[tokio::test]
async fn outputs_of_another_mode_in_out_are_refused_not_left_beside_the_report() {
    let dir = tempfile::tempdir().unwrap();
    for f in ["model.toml", "commissioning.csv", "report.md"] {
        std::fs::write(dir.path().join(f), "earlier run\n").unwrap();
    }
    let mut a = args(dir.path(), 1.0);
    a.model = Some(dir.path().join("other.toml"));
    let e = run(&a).await.unwrap_err().to_string();
    assert_eq!(
        e,
        format!(
            "--out {}: holds commissioning.csv, model.toml from another scenario run, which \
             this run does not write and would leave beside its report; use an empty \
             directory or remove them",
            dir.path().display()
        )
    );
    // The model given is an input, not a stale output; the loop's files are stale.
    a.model = Some(dir.path().join("model.toml"));
    std::fs::write(dir.path().join("loop_vs_time.svg"), "<svg/>").unwrap();
    let e = run(&a).await.unwrap_err().to_string();
    assert!(
        e.contains("holds commissioning.csv, loop_vs_time.svg from another"),
        "{e}"
    );
    let mut left: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|f| f.unwrap().file_name().into_string().unwrap())
        .collect();
    left.sort();
    assert_eq!(
        left,
        [
            "commissioning.csv",
            "loop_vs_time.svg",
            "model.toml",
            "report.md"
        ]
    );
    // A default run writes model.toml and commissioning.csv itself: only the loop's
    // file is in its way.
    a.model = None;
    let e = run(&a).await.unwrap_err().to_string();
    assert!(e.contains("holds loop_vs_time.svg from another"), "{e}");
}

/// The closed loop's export step in the guide, `compgate export --axis X
/// --err-channel laser_um --step-s 10`, exited 2: --db, --since, --until and --csv
/// are required. The command as the guide prints it parses.
#[test]
fn the_guides_export_step_is_a_whole_command() {
    use clap::Parser;
    let guide = include_str!("../../docs/guide/commissioning.md");
    let step = &guide[guide.find("2. **Export.**").expect("the export step")..];
    let command = &step[step.find("compgate export").expect("the command")..];
    let command = command
        .split('`')
        .next()
        .and_then(|c| c.split("\n\n").next())
        .unwrap_or_default()
        .replace("\\\n", " ");
    let args: Vec<&str> = command
        .split_whitespace()
        .map(|a| match a {
            "START" => "1764000000",
            "END" => "1764086401",
            a => a,
        })
        .collect();
    if let Err(e) = crate::cli::Cli::try_parse_from(&args) {
        panic!("{command}: {e}");
    }
}

/// Records `hours` of the shop plant through the service's recorder into `db`, the
/// gateway running `model` with compensation on or off; the Unix ms of its start.
async fn record_run(db: &Path, model: &AxisModel, compensate: bool, hours: f64) -> i64 {
    use compgate_service::record::{self, Recorder};
    let (params, effects) = Plant::from_name("shop").unwrap().build();
    let rec = Recorder::start(&compgate_gateway::config::RecorderConfig {
        path: db.display().to_string(),
        queue_cycles: 1_000_000,
        ..Default::default()
    })
    .unwrap();
    // Whole seconds, so `--since` in Unix seconds is exact; near now, so that no
    // retention pass takes the records for old ones.
    let epoch_ms = record::now_unix_ms() / 1000 * 1000;
    let setup = Setup {
        params: &params,
        effects,
        seed: 11,
        hours,
        sample_every_s: 300.0,
    };
    let mode = Mode {
        model,
        compensate,
        cycle: DutyCycle::recording(hours),
        sweeps: false,
        record: Some((&rec, epoch_ms)),
    };
    run_once(&setup, &mode, &indicatif::ProgressBar::hidden())
        .await
        .unwrap();
    rec.finish();
    epoch_ms
}

/// A recording made with compensation on measures the error left after the NC's
/// compensation; export wrote it as the error, and a model calibrated on it was a
/// model of the residual. The same machine recorded with compensation off and on:
/// export names the compensated span, and with `--add-applied-comp` the on run's
/// err_um is the off run's (what proves the sign: the simulated interferometer reads
/// the error minus the compensation the NC applied).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_recording_with_compensation_on_exports_the_error_without_it_on_request() {
    use compgate_service::record::export::{self, ExportArgs};
    let dir = tempfile::tempdir().unwrap();
    let (params, effects) = Plant::from_name("shop").unwrap().build();
    let sensors = vec!["column".to_string(), "screw".to_string()];
    let (model, _, _) = commissioning_model(&params, &effects, 11, &sensors).unwrap();
    let hours = 1.0;
    let (off_db, on_db) = (dir.path().join("off.sqlite"), dir.path().join("on.sqlite"));
    let off_ms = record_run(&off_db, &model, false, hours).await;
    let on_ms = record_run(&on_db, &model, true, hours).await;
    let args = |db: &Path, epoch_ms: i64, add: bool| ExportArgs {
        db: db.to_path_buf(),
        since: (epoch_ms / 1000).to_string(),
        until: (epoch_ms / 1000 + (hours * 3600.0) as i64 + 1).to_string(),
        csv: true,
        out: None,
        axis: Some("X".into()),
        err_channel: Some(LASER_CHANNEL.into()),
        step_s: 10.0,
        max_hold_s: 60.0,
        add_applied_comp: add,
    };
    let (off, off_summary) = export::measurements(&args(&off_db, off_ms, false)).unwrap();
    let (on, on_summary) = export::measurements(&args(&on_db, on_ms, false)).unwrap();
    let (added, added_summary) = export::measurements(&args(&on_db, on_ms, true)).unwrap();
    // The off run applied nothing and says nothing of it.
    assert!(
        !off_summary.notes.iter().any(|n| n.contains("applied")),
        "{:?}",
        off_summary.notes
    );
    let note = on_summary
        .notes
        .iter()
        .find(|n| n.contains("compensation to axis `X` from "))
        .unwrap_or_else(|| panic!("{:?}", on_summary.notes));
    assert!(
        note.contains("is not the machine's model") && note.contains("--add-applied-comp"),
        "{note}"
    );
    assert!(
        added_summary
            .notes
            .iter()
            .any(|n| n.contains("the error without compensation")),
        "{:?}",
        added_summary.notes
    );
    // Same machine, same rows.
    assert_eq!(off.len(), on.len());
    assert_eq!(off.len(), added.len());
    // (The filters' last bits differ between runs now and then: within 1e-9 degC.)
    for (a, b) in off.temps.iter().zip(&added.temps) {
        assert_eq!(a.name, b.name);
        assert!(
            a.degc
                .iter()
                .zip(&b.degc)
                .all(|(x, y)| (x - y).abs() < 1e-9),
            "{}",
            a.name
        );
    }
    assert_eq!(off.pos_mm, added.pos_mm);
    let worst = |a: &Measurements| {
        off.err_um
            .iter()
            .zip(&a.err_um)
            .map(|(o, x)| (o - x).abs())
            .fold(0.0, f64::max)
    };
    // Compensated, the error differs from the machine's by what the NC applied ...
    assert!(worst(&on) > 10.0, "{}", worst(&on));
    // ... and with it added back it is the machine's, up to the laser module's
    // resolution (1000 um over 4/5 of 65535 counts: 0.02 um).
    assert!(worst(&added) < 0.1, "{}", worst(&added));
}
