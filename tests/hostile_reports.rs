//! Hostile but accepted measurement files through the commissioning commands as an
//! operator runs them: each command either refuses with a message or reports finite
//! numbers. No report, model file or JSON may ever carry NaN or infinity.

use std::path::Path;
use std::process::Command;

const BIN: &str = env!("CARGO_BIN_EXE_compgate");

/// A measurement CSV of 10 bidirectional runs over 9 targets within +-`span_mm`, one
/// row every 10 s, with the error and the two temperatures as functions of time and
/// position.
fn runs(
    span_mm: f64,
    err_um: impl Fn(f64, f64) -> f64,
    t_a: impl Fn(f64) -> f64,
    t_b: impl Fn(f64) -> f64,
) -> String {
    let mut text = String::from("t_s,pos_mm,dir,err_um,T_a,T_b\n");
    let mut t_s = 0.0;
    for _ in 0..10 {
        for (dir, targets) in [
            (1, [0, 1, 2, 3, 4, 5, 6, 7, 8]),
            (-1, [8, 7, 6, 5, 4, 3, 2, 1, 0]),
        ] {
            for k in targets {
                let pos_mm = -span_mm + f64::from(k) * span_mm / 4.0;
                t_s += 10.0;
                text.push_str(&format!(
                    "{t_s},{pos_mm},{dir},{},{},{}\n",
                    err_um(t_s, pos_mm),
                    t_a(t_s),
                    t_b(t_s)
                ));
            }
        }
    }
    text
}

/// The data sets: each passes the reader's plausibility bounds, and at least the
/// first two are accepted by every command, so their reports are checked.
fn data_sets() -> Vec<(&'static str, String)> {
    vec![
        (
            // Every value near the reader's bounds.
            "extreme",
            runs(
                90_000.0,
                |t, _| (99_999.0 * (t / 37.0).sin()).clamp(-99_999.0, 99_999.0),
                |t| -99.0 + (t % 1800.0) / 1800.0 * 598.0,
                |t| 200.0 + 290.0 * (t / 300.0).sin(),
            ),
        ),
        (
            "linear",
            runs(
                1000.0,
                |t, p| 5.0 * (t / 1800.0) * 30.0 + 0.01 * p,
                |t| 20.0 + t / 1800.0 * 30.0,
                |t| 22.0 + 3.0 * (t / 400.0).sin(),
            ),
        ),
        (
            // Everything at the edge of f64 resolution.
            "tiny",
            runs(
                1e-6,
                |t, _| 1e-9 * t,
                |t| 20.0 + 1e-9 * t,
                |t| 20.0 + 2e-9 * t.sin(),
            ),
        ),
        (
            "constant_temperatures",
            runs(500.0, |t, _| (t / 50.0).sin(), |_| 20.0, |_| 20.0),
        ),
        (
            "two_rows",
            "t_s,pos_mm,err_um,T_a,T_b\n0,0,0,20,20\n1,500,3,21,20.5\n".into(),
        ),
    ]
}

/// True when the text holds a word NaN, inf or infinity (any case).
fn non_finite_word(text: &str) -> Option<String> {
    text.split(|c: char| !c.is_ascii_alphanumeric())
        .map(str::to_ascii_lowercase)
        .find(|w| w == "nan" || w == "inf" || w == "infinity")
}

/// Runs `compgate args`, then checks its output and every file in `out_dir`; true
/// when the command succeeded.
fn check(what: &str, args: &[&str], out_dir: &Path) -> bool {
    let out = Command::new(BIN).args(args).output().expect("runs");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_ne!(out.status.code(), Some(101), "{what}: panicked: {stderr}");
    assert!(
        out.status.success() || !stderr.trim().is_empty(),
        "{what}: failed without a message"
    );
    if let Some(w) = non_finite_word(&stdout) {
        panic!("{what}: `{w}` in the report:\n{stdout}");
    }
    for entry in std::fs::read_dir(out_dir).expect("out dir").flatten() {
        let path = entry.path();
        if !path.is_file() || path.extension().is_some_and(|e| e == "csv") {
            continue;
        }
        let text = std::fs::read_to_string(&path).unwrap_or_default();
        if let Some(w) = non_finite_word(&text) {
            panic!("{what}: `{w}` in {}", path.display());
        }
    }
    out.status.success()
}

#[test]
fn hostile_but_accepted_data_never_gives_nan_or_infinity() {
    for (name, text) in data_sets() {
        let dir = tempfile::tempdir().unwrap();
        let data = dir.path().join(format!("{name}.csv"));
        std::fs::write(&data, text).unwrap();
        let data = data.to_str().unwrap();
        let out = dir.path().join("out");
        std::fs::create_dir(&out).unwrap();
        // Not diagnose's `model.toml`: diagnose --out keeps a model it did not write.
        let model = out.join("calibrate_model.toml");
        let mut accepted = check(
            &format!("calibrate {name}"),
            &[
                "calibrate",
                "--data",
                data,
                "--out",
                model.to_str().unwrap(),
            ],
            &out,
        );
        accepted &= check(&format!("iso230 {name}"), &["iso230", "--data", data], &out);
        let json = out.join("result.json");
        accepted &= check(
            &format!("diagnose {name}"),
            &[
                "diagnose",
                "--data",
                data,
                "--out",
                out.to_str().unwrap(),
                "--json",
                json.to_str().unwrap(),
            ],
            &out,
        );
        // The reports of these two must have been checked, not just refusals.
        if name == "extreme" || name == "linear" {
            assert!(accepted, "{name}: every command should accept it");
            assert!(
                model.is_file() && json.is_file(),
                "{name}: no model or JSON"
            );
        }
    }
}

/// An output path that names an input (the easiest typo on a shop-floor PC) is
/// refused before anything is written, and the input keeps every byte; so is an
/// output in a directory that does not exist, before the other outputs are written.
#[test]
fn an_output_naming_an_input_is_refused_and_the_input_kept() {
    let dir = tempfile::tempdir().unwrap();
    let p = |name: &str| dir.path().join(name).to_str().unwrap().to_string();
    let data = p("m.csv");
    let measured = runs(
        1000.0,
        |t, p| 5.0 * (t / 1800.0) * 30.0 + 0.01 * p,
        |t| 20.0 + t / 1800.0 * 30.0,
        |t| 22.0 + 3.0 * (t / 400.0).sin(),
    );
    std::fs::write(&data, &measured).unwrap();
    let errors = p("machine.errors");
    let errors_text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/volumetric-example.errors"
    ))
    .unwrap();
    std::fs::write(&errors, &errors_text).unwrap();
    let out = p("out");
    std::fs::create_dir(&out).unwrap();
    let trace = format!("{out}/backlash_X1_trace.csv");
    let trace_text = "t_s,encoder_mm,scale_mm\n0,0,0\n0.001,0,0\n";
    std::fs::write(&trace, trace_text).unwrap();
    let model = p("model.toml");
    std::fs::write(&model, "kept").unwrap();
    let cases: [(&[&str], &str, &str); 7] = [
        (
            &["calibrate", "--data", &data, "--out", &data],
            &data,
            &measured,
        ),
        (
            &[
                "calibrate",
                "--data",
                &data,
                "--out",
                &model,
                "--plot",
                &data,
            ],
            &data,
            &measured,
        ),
        (
            &["diagnose", "--data", &data, "--json", &data],
            &data,
            &measured,
        ),
        (
            &["volumetric", "--errors", &errors, "--csv", &errors],
            &errors,
            &errors_text,
        ),
        (
            &["backlash", "--trace", &trace, "--out", &out],
            &trace,
            trace_text,
        ),
        (
            &[
                "export", "--db", &data, "--since", "0", "--until", "1", "--csv", "-o", &data,
            ],
            &data,
            &measured,
        ),
        // The plot's directory is missing: refused before the model is written.
        (
            &[
                "calibrate",
                "--data",
                &data,
                "--out",
                &model,
                "--plot",
                &p("no/p.svg"),
            ],
            &model,
            "kept",
        ),
    ];
    for (args, kept, text) in cases {
        let run = Command::new(BIN).args(args).output().expect("runs");
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert_eq!(run.status.code(), Some(1), "{args:?}: {stderr}");
        let why = if kept == model {
            "does not exist"
        } else {
            "refusing to overwrite"
        };
        assert!(stderr.contains(why), "{args:?}: {stderr}");
        assert_eq!(std::fs::read_to_string(kept).unwrap(), text, "{args:?}");
    }
}
