//! The `compgate` binary as an operator meets it: validate, and the demo run as a
//! real process with stdout on a pipe, stopped by SIGTERM.

mod common;

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::process::{assert_success, BIN};

#[test]
fn validate_reports_every_problem_with_file_and_key_and_exits_1() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("plant.toml");
    let text = std::fs::read_to_string("config/example.toml")
        .unwrap()
        .replacen("timeout_s = 0.5", "timeot_s = 0.5", 1)
        .replacen("device = \"ain1\"", "device = \"ain9\"", 1);
    std::fs::write(&path, text).unwrap();
    let out = Command::new(BIN)
        .args(["validate", "--config"])
        .arg(&path)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    let file = path.display().to_string();
    assert!(
        err.contains(&format!("{file}: devices.ain1.timeot_s: unknown key")),
        "{err}"
    );
    assert!(
        err.contains(&format!(
            "{file}: channels.T_bed.device: unknown device `ain9`"
        )),
        "{err}"
    );

    let ok = Command::new(BIN)
        .args(["validate", "--config", "config/example.toml"])
        .output()
        .unwrap();
    assert_success(&ok);
}

#[test]
fn backlash_with_sim_reports_the_table_and_without_a_target_exits_1() {
    let out = Command::new(BIN)
        .args(["backlash", "--sim", "--sim-backlash-um", "12"])
        .output()
        .unwrap();
    let text = assert_success(&out);
    assert!(
        text.contains("H1") && text.contains("h2") && text.contains("F2"),
        "{text}"
    );
    let none = Command::new(BIN).arg("backlash").output().unwrap();
    assert_eq!(none.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&none.stderr).contains("give --nc ADDRESS or --sim"),
        "{}",
        String::from_utf8_lossy(&none.stderr)
    );
}

#[test]
fn help_groups_the_commands() {
    let out = Command::new(BIN).arg("--help").output().unwrap();
    let help = String::from_utf8_lossy(&out.stdout);
    let at = |s: &str| {
        help.find(s)
            .unwrap_or_else(|| panic!("{s} missing:\n{help}"))
    };
    assert!(at("Service:") < at("  run "));
    assert!(at("  export ") < at("Commissioning:"));
    assert!(at("Commissioning:") < at("  calibrate "));
    assert!(at("  scenario ") < at("Tools:"));
    assert!(at("Tools:") < at("  demo "));
    assert_eq!(help.matches("  validate ").count(), 1, "{help}");
}

#[test]
fn demo_prints_plain_lines_when_piped_and_stops_on_sigterm() {
    let mut child = Command::new(BIN)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines() {
            if tx.send(line.unwrap()).is_err() {
                break;
            }
        }
    });
    // Wait for a line showing a verified write and the NC applying compensation.
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut seen = None;
    while Instant::now() < deadline {
        let Ok(line) = rx.recv_timeout(Duration::from_secs(1)) else {
            continue;
        };
        assert!(
            !line.contains('\r') && !line.contains('\x1b'),
            "plain line: {line:?}"
        );
        if line.contains("SD43900=0.") && line.contains("NC pos=") && !line.contains("jobs=0/") {
            seen = Some(line);
            break;
        }
    }
    let line = seen.expect("a status line with a written SD43900 within 30 s");
    assert!(line.contains("T_bed=") && line.contains("[good]"), "{line}");

    let pid = child.id().to_string();
    assert!(Command::new("kill")
        .args(["-TERM", &pid])
        .status()
        .unwrap()
        .success());
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            assert!(status.success(), "clean exit on SIGTERM, got {status}");
            break;
        }
        assert!(
            Instant::now() < deadline,
            "demo did not stop within 10 s of SIGTERM"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn backlash_trace_file_is_analysed_offline_and_a_creeping_axis_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    // A well-damped simulated axis; its trace written with --out and read back.
    let ok = Command::new(BIN)
        .args(["backlash", "--sim", "--sim-backlash-um", "23", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert_success(&ok);
    let csv = dir.path().join("backlash_X1_trace.csv");
    let offline = Command::new(BIN)
        .args(["backlash", "--trace"])
        .arg(&csv)
        .output()
        .unwrap();
    let text = assert_success(&offline);
    let f: Vec<f64> = text
        .lines()
        .filter_map(|l| l.split_once(" F1 ").or_else(|| l.split_once(" F2 ")))
        .map(|(_, rest)| rest.split_whitespace().next().unwrap().parse().unwrap())
        .collect();
    assert_eq!(f.len(), 2, "{text}");
    assert!(f.iter().all(|f| (f - 23.0).abs() <= 0.5), "{text}");
    // Kv x tau = 0.4 (20 ms at Kv 20 1/s): refused with the reason, the trace kept,
    // and the kept trace refused alike offline.
    let creep_dir = dir.path().join("creep");
    let creep = Command::new(BIN)
        .args(["backlash", "--sim", "--sim-backlash-um", "50"])
        .args(["--sim-elastic-ms", "20", "--out"])
        .arg(&creep_dir)
        .output()
        .unwrap();
    assert_eq!(creep.status.code(), Some(1));
    let err = String::from_utf8_lossy(&creep.stderr);
    assert!(
        err.contains("never both stood still") || err.contains("went back"),
        "{err}"
    );
    let again = Command::new(BIN)
        .args(["backlash", "--trace"])
        .arg(creep_dir.join("backlash_X1_trace.csv"))
        .output()
        .unwrap();
    assert_eq!(again.status.code(), Some(1));
    let err2 = String::from_utf8_lossy(&again.stderr);
    assert!(
        err2.contains("never both stood still") || err2.contains("went back"),
        "{err2}"
    );
}
