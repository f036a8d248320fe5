//! The `compgate` binary as an operator meets it: validate, and the demo run as a
//! real process with stdout on a pipe, stopped by SIGTERM.

mod common;

use std::io::{BufRead, BufReader, Read};
use std::process::{Command, Output, Stdio};
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
    // One seed, one result: the noise no longer depends on how long the simulated
    // axis stood before the programme (7.313, 7.316, 7.299, 7.305 um on four runs).
    let seeded = || {
        let out = Command::new(BIN)
            .args([
                "backlash",
                "--sim",
                "--sim-seed",
                "2",
                "--sim-backlash-um",
                "7.3",
            ])
            .output()
            .unwrap();
        let text = assert_success(&out);
        text.lines()
            .filter(|l| l.contains(" F1 ") || l.contains(" F2 "))
            .map(str::to_string)
            .collect::<Vec<_>>()
    };
    let first = seeded();
    assert_eq!(first.len(), 2, "{first:?}");
    for _ in 0..2 {
        assert_eq!(seeded(), first);
    }
    let none = Command::new(BIN).arg("backlash").output().unwrap();
    assert_eq!(none.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&none.stderr).contains("give --nc ADDRESS or --sim"),
        "{}",
        String::from_utf8_lossy(&none.stderr)
    );
}

// A signal during the backlash test (Ctrl-C, the unit stopped, a closed SSH session)
// ended the process at once with the axis still running its programme: a rerun was
// refused ("a programme is running"). Each now aborts the programme and says so.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_signal_during_the_backlash_test_aborts_the_move_programme() {
    use compgate_plc::axis::{AxisParams, ProgramState};
    use compgate_plc::nc::{NcAxis, NcAxisModule};
    for signal in ["INT", "TERM", "HUP"] {
        let module = NcAxisModule::new(NcAxis {
            referenced: true,
            ..NcAxis::default()
        });
        // In real time: the programme's four dwells alone take 8 s.
        module.set_servo(AxisParams::default());
        let (address, shutdown) = module.serve_loopback().await.unwrap();
        let mut child = Command::new(BIN)
            .args(["backlash", "--nc", &address])
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let mut stderr = BufReader::new(child.stderr.take().unwrap());
        let mut log = String::new();
        tokio::task::block_in_place(|| {
            while !log.contains("programme started") {
                assert!(stderr.read_line(&mut log).unwrap() > 0, "{log}");
            }
        });
        assert_eq!(
            module.with_servo(|s| s.program_state()),
            ProgramState::Running
        );
        let kill = Command::new("kill")
            .arg(format!("-{signal}"))
            .arg(child.id().to_string())
            .status()
            .unwrap();
        assert!(kill.success());
        let status = tokio::task::block_in_place(|| {
            stderr.read_to_string(&mut log).unwrap();
            child.wait().unwrap()
        });
        assert_eq!(status.code(), Some(1), "SIG{signal}: {log}");
        assert!(
            log.contains(&format!(
                "error: stopped by SIG{signal}; the move programme was aborted (MV_STATE 3)"
            )),
            "{log}"
        );
        assert_eq!(
            module.with_servo(|s| s.program_state()),
            ProgramState::Refused,
            "SIG{signal}"
        );
        shutdown.cancel();
    }
}

// `--version` names the commit and its date besides the version number: after an
// update, builds of one version number are told apart on the PC.
#[test]
fn version_names_the_commit_it_was_built_from() {
    let out = Command::new(BIN).arg("--version").output().unwrap();
    assert_success(&out);
    let text = String::from_utf8_lossy(&out.stdout);
    let head = Command::new("git")
        .args(["log", "-1", "--format=%h %cs"])
        .output()
        .ok()
        .filter(|o| o.status.success())
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string());
    let want = match head {
        Some(commit) => format!("compgate {} ({commit})", env!("CARGO_PKG_VERSION")),
        // Not a checkout: the version number alone.
        None => format!("compgate {}", env!("CARGO_PKG_VERSION")),
    };
    assert_eq!(text.trim(), want);
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
    assert!(!text.contains("WARNING"), "{text}");
    // The encoder and scale columns swapped: the same F1, F2, and a warning that the
    // table cannot have moved further than the motor.
    let swapped = dir.path().join("swapped.csv");
    let trace = std::fs::read_to_string(&csv).unwrap();
    let (header, rows) = trace.split_once('\n').unwrap();
    let header = header
        .replace("encoder_mm", "ENC")
        .replace("scale_mm", "encoder_mm")
        .replace("ENC", "scale_mm");
    std::fs::write(&swapped, format!("{header}\n{rows}")).unwrap();
    let out = Command::new(BIN)
        .args(["backlash", "--trace"])
        .arg(&swapped)
        .output()
        .unwrap();
    let swapped_text = assert_success(&out);
    assert!(
        swapped_text.contains("WARNING: in B->C the scale moved")
            && swapped_text.contains("Are the encoder and the scale swapped"),
        "{swapped_text}"
    );
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

/// `calibrate --plot` into a directory no one can write: the model was replaced,
/// then the command failed with no report. Now the report comes first, the error
/// after it, and the model stays as it was.
#[test]
fn calibrate_prints_its_report_before_an_output_error_and_keeps_the_model() {
    let dir = tempfile::tempdir().unwrap();
    let data = measurement_csv(dir.path());
    let model = dir.path().join("prev.toml");
    std::fs::write(&model, "# previous good model\n").unwrap();
    let out = Command::new(BIN)
        .args(["calibrate", "--sensors", "a,b", "--data"])
        .arg(&data)
        .arg("--out")
        .arg(&model)
        .args(["--plot", "/proc/self/calib.svg"])
        .output()
        .unwrap();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stdout.contains("quality: RMS residual"), "{stdout}");
    assert!(
        stderr.starts_with("error: /proc/self/calib.svg: "),
        "{stderr}"
    );
    assert_eq!(
        std::fs::read_to_string(&model).unwrap(),
        "# previous good model\n"
    );
}

/// The write end of a pipe whose reader is already gone: every write fails with EPIPE.
fn closed_pipe() -> std::io::PipeWriter {
    let (reader, writer) = std::io::pipe().expect("a pipe");
    drop(reader);
    writer
}

/// `/dev/full`: every write fails with ENOSPC.
fn full() -> Stdio {
    std::fs::OpenOptions::new()
        .write(true)
        .open("/dev/full")
        .expect("/dev/full opens")
        .into()
}

/// Runs the binary with `args`, stdout on `stdout`, stderr collected.
fn run_to(args: &[&str], stdout: impl Into<Stdio>) -> Output {
    Command::new(BIN)
        .args(args)
        .stdout(stdout)
        .stderr(Stdio::piped())
        .output()
        .expect("the binary runs")
}

/// A recorder database of one channel, a reading a second for `seconds` from Unix
/// time 1e9 s: an export of it is about 20 bytes a row.
fn recording(dir: &std::path::Path, seconds: i64) -> std::path::PathBuf {
    let db = dir.join("rec.db");
    let mut conn = compgate_service::record::open(&db).expect("a new recording");
    let tx = conn.transaction().expect("a transaction");
    tx.execute("INSERT INTO channels(id, name) VALUES (1, 'T_bed')", [])
        .expect("the channel");
    for i in 0..seconds {
        tx.execute(
            "INSERT INTO readings VALUES (?1, 1, 12000.0, 20.5, 20.5, 0, NULL)",
            [1_000_000_000_000 + i * 1000],
        )
        .expect("a reading");
    }
    tx.commit().expect("committed");
    db
}

/// A measurement CSV `diagnose` accepts: 10 bidirectional runs over 9 targets, a row
/// every 10 s, the error growing with one temperature and the position.
fn measurement_csv(dir: &std::path::Path) -> std::path::PathBuf {
    let mut text = String::from("t_s,pos_mm,dir,err_um,T_a,T_b\n");
    let mut t_s = 0.0_f64;
    for _ in 0..10 {
        for (dir, targets) in [
            (1, [0, 1, 2, 3, 4, 5, 6, 7, 8]),
            (-1, [8, 7, 6, 5, 4, 3, 2, 1, 0]),
        ] {
            for k in targets {
                let pos_mm = -1000.0 + f64::from(k) * 250.0;
                t_s += 10.0;
                let t_a = 20.0 + t_s / 60.0;
                let t_b = 22.0 + 3.0 * (t_s / 400.0).sin();
                let err_um = 5.0 * (t_a - 20.0) + 0.01 * pos_mm;
                text.push_str(&format!("{t_s},{pos_mm},{dir},{err_um},{t_a},{t_b}\n"));
            }
        }
    }
    let path = dir.join("measured.csv");
    std::fs::write(&path, text).expect("the CSV written");
    path
}

/// A configuration whose NC axis module is at a loopback port where nothing listens:
/// `nc read` prints the axis's failure on stdout, then fails.
fn dead_nc_config(dir: &std::path::Path) -> std::path::PathBuf {
    // A port just freed: nothing listens on it.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free loopback port")
        .port();
    // Every address (port 0 is refused outside the simulated plant); `nc read` polls
    // no device.
    let text =
        common::config("hold", "", "").replace("\"127.0.0.1:0\"", &format!("\"127.0.0.1:{port}\""));
    assert!(
        text.contains(&format!(":{port}")),
        "the NC address replaced"
    );
    let path = dir.join("dead_nc.toml");
    std::fs::write(&path, text).expect("the config written");
    path
}

// `compgate config schema | head -1`, `... > /dev/full`: a closed pipe ends quietly
// with 141 (128 + SIGPIPE, as a tool the signal ended), a failed write with one error
// naming stdout and 1; never the panic of `print!` (101 and a backtrace).
#[test]
fn a_closed_or_full_stdout_ends_quietly_or_with_one_error_never_a_panic() {
    let dir = tempfile::tempdir().unwrap();
    let db = recording(dir.path(), 20_000);
    let data = measurement_csv(dir.path());
    let diagnose = ["diagnose", "--data", data.to_str().unwrap()];
    let nc_config = dead_nc_config(dir.path());
    let nc_read = ["nc", "read", "--config", nc_config.to_str().unwrap()];
    // Both print on a normal stdout: what the closed one refuses.
    for (args, printed) in [(&diagnose[..], "verdict"), (&nc_read, "axis X")] {
        let out = Command::new(BIN).args(args).output().unwrap();
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(text.contains(printed), "{args:?}: {text}");
    }
    let export = [
        "export",
        "--csv",
        "--since",
        "1000000000",
        "--until",
        "1000020000",
        "--db",
        db.to_str().unwrap(),
    ];
    for args in [
        &["config", "schema"][..],
        &["config", "example"],
        &export,
        &diagnose,
        &nc_read,
    ] {
        let out = run_to(args, closed_pipe());
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(141), "{args:?}: {err}");
        assert_eq!(err, "", "{args:?}: nothing on stderr");

        let out = run_to(args, full());
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {err}");
        assert_eq!(
            err.lines().collect::<Vec<_>>(),
            ["error: cannot write to standard output: No space left on device (os error 28)"],
            "{args:?}"
        );
    }

    // As `| head -1`: the reader takes a line and goes; the export (about 400 kB, far more
    // than a pipe holds) is still writing then.
    let mut child = Command::new(BIN)
        .args(export)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut first = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut first)
        .unwrap();
    assert!(first.starts_with("t_s,pos_mm,"), "{first}");
    let mut err = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    let status = child.wait().unwrap();
    assert_eq!((status.code(), err.as_str()), (Some(141), ""));

    // `validate 2>&1 | head`: a report of thousands of problems to a closed pipe on
    // stderr ends the same way.
    let config = dir.path().join("many.toml");
    let keys: String = (0..3000).map(|i| format!("bogus_{i} = 1\n")).collect();
    std::fs::write(&config, format!("[gateway]\n{keys}")).unwrap();
    let pipe = closed_pipe();
    let status = Command::new(BIN)
        .args(["validate", "--config"])
        .arg(&config)
        .stdout(pipe.try_clone().unwrap())
        .stderr(pipe)
        .status()
        .unwrap();
    assert_eq!(status.code(), Some(141));
}

/// Runs the binary with `args`; its exit status and standard error. A run still going
/// after a minute is killed (status `None`): a command that should have refused its
/// arguments, such as the demo, would otherwise run for ever.
fn run(args: &[&str]) -> (Option<i32>, String) {
    let mut child = Command::new(BIN)
        .args(args)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("the binary runs");
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    while child.try_wait().expect("wait").is_none() && std::time::Instant::now() < deadline {
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let _ = child.kill();
    let out = child.wait_with_output().expect("the binary's output");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// ISO 230-2 needs position, direction and error only: a laser's file without time or
/// temperatures (it was refused for want of `t_s` and a `T_` column) gives the same
/// figures, and a bad cell of a sensor it does not read does not stop it.
#[test]
fn iso230_reads_a_file_of_positions_alone() {
    let dir = tempfile::tempdir().unwrap();
    let full = measurement_csv(dir.path());
    let text = std::fs::read_to_string(&full).unwrap();
    let keep = |line: &str, with_nan: bool| {
        let c: Vec<&str> = line.split(',').collect();
        match with_nan {
            false => format!("{},{},{}\n", c[1], c[2], c[3]),
            true => format!("{},NaN\n", line.rsplit_once(',').unwrap().0),
        }
    };
    let mut lines = text.lines();
    let header = lines.next().unwrap();
    let laser: String = std::iter::once("pos_mm,dir,err_um\n".to_string())
        .chain(lines.clone().map(|l| keep(l, false)))
        .collect();
    let nan: String = std::iter::once(format!("{header}\n"))
        .chain(lines.map(|l| keep(l, true)))
        .collect();
    let iso230 = |name: &str, text: &str| {
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        let out = Command::new(BIN)
            .args(["iso230", "--data"])
            .arg(&path)
            .output()
            .unwrap();
        assert_success(&out)
    };
    let want = iso230("full.csv", &text);
    assert!(want.contains("A "), "{want}");
    assert_eq!(iso230("laser.csv", &laser), want);
    assert_eq!(iso230("nan.csv", &nan), want);
    // calibrate still needs them, and says so.
    let path = dir.path().join("laser.csv");
    let out = Command::new(BIN)
        .args(["calibrate", "--out", "m.toml", "--data"])
        .arg(&path)
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("required column `t_s` is missing"),
        "{out:?}"
    );
}

// A negative number is the value of a numeric flag, not an unknown flag: before,
// `--p0-mm -100`, `--targets -500,0,500` and `--a -10` ended with exit 2 and
// "unexpected argument '-1' found", naming neither the flag nor the value.
#[test]
fn numeric_flags_take_negative_values() {
    let dir = tempfile::tempdir().unwrap();
    let data = measurement_csv(dir.path());
    let data = data.to_str().unwrap();
    let model = dir.path().join("m.toml");
    let out = Command::new(BIN)
        .args(["calibrate", "--data", data, "--p0-mm", "-1000", "--out"])
        .arg(&model)
        .output()
        .unwrap();
    assert_success(&out);
    let toml = std::fs::read_to_string(&model).unwrap();
    assert!(toml.contains("p0_mm = -1000"), "{toml}");
    let targets = "-1000,-750,-500,-250,0,250,500,750,1000";
    let out = Command::new(BIN)
        .args(["iso230", "--data", data, "--targets", targets])
        .output()
        .unwrap();
    assert!(assert_success(&out).contains("-1000"));
    let out = Command::new(BIN)
        .args(["backlash", "--sim", "--a", "-5", "--c", "-2"])
        .output()
        .unwrap();
    assert!(assert_success(&out).contains("F2"));
    // Out of range: refused by the flag's own check, which names it (exit 1).
    for (args, message) in [
        (
            &["backlash", "--sim", "--feed", "-1"][..],
            "--feed -1.0: outside the plausible range",
        ),
        (
            &["volumetric", "--errors", "none.txt", "--max-c-swing", "-5"],
            "--max-c-swing -5.0: outside the plausible range",
        ),
        (
            &["scenario", "--out", "none", "--hours", "-1"],
            "--hours -1.0: outside the plausible range",
        ),
    ] {
        let (code, err) = run(args);
        assert_eq!(code, Some(1), "{args:?}: {err}");
        assert!(err.contains(message), "{args:?}: {err}");
    }
    // An integer flag names itself too.
    let (code, err) = run(&["backlash", "--sim", "--unit", "-1"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("invalid value '-1' for '--unit"), "{err}");
    assert!(!dir.path().join("none").exists() && !std::path::Path::new("none").exists());
}

// A database export cannot read is reported as the database's fault, naming --db and
// the path. Before, the first query (parsing --since) failed on it:
// "error: --since: file is not a database", "error: --until: unable to open database
// file", and a directory gave "disk I/O error".
#[test]
fn export_names_the_database_it_cannot_read() {
    let dir = tempfile::tempdir().unwrap();
    let export = |db: &std::path::Path| {
        run(&[
            "export",
            "--csv",
            "--since",
            "2026-11-26T17:13:00Z",
            "--until",
            "2030-01-01T00:00:00Z",
            "--db",
            db.to_str().unwrap(),
        ])
    };
    let garbage = dir.path().join("garbage.db");
    std::fs::write(&garbage, [0x5a_u8; 5000]).unwrap();
    let (code, err) = export(&garbage);
    assert_eq!(code, Some(1), "{err}");
    assert_eq!(
        err,
        format!(
            "error: --db {}: file is not a database\n",
            garbage.display()
        )
    );
    let (code, err) = export(dir.path());
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.starts_with(&format!(
            "error: --db {}: is a directory",
            dir.path().display()
        )),
        "{err}"
    );
    // A WAL database SQLite cannot open its -shm file for (as in a read-only
    // directory, which root does not see as one): the message says why.
    let wal = dir.path().join("copy");
    std::fs::create_dir(&wal).unwrap();
    let db = recording(&wal, 10);
    assert!(
        !wal.join("rec.db-shm").exists(),
        "the recorder closed cleanly"
    );
    std::os::unix::fs::symlink(dir.path().join("gone/rec.db-shm"), wal.join("rec.db-shm")).unwrap();
    let (code, err) = export(&db);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.starts_with(&format!(
            "error: --db {}: cannot be opened read-only here: it is in WAL mode",
            db.display()
        )),
        "{err}"
    );
    assert!(err.contains(&format!("in {}", wal.display())), "{err}");
    // A bad time is still the flag's.
    let (code, err) = run(&[
        "export",
        "--csv",
        "--since",
        "yesterday",
        "--until",
        "1",
        "--db",
        db.to_str().unwrap(),
    ]);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.starts_with("error: --since: `yesterday` is not a time"),
        "{err}"
    );
}

/// `compgate export --csv` of `db` from Unix second 1000000000 to `until`.
fn export_from(db: &std::path::Path, until: &str) -> Command {
    let mut cmd = Command::new(BIN);
    cmd.args(["export", "--csv", "--since", "1000000000", "--until", until])
        .arg("--db")
        .arg(db);
    cmd
}

// The grid is in whole milliseconds: a step below 1 ms or between two is refused,
// naming the flag. Before, `--step-s 1e-9` and `0.0004` were silently 1 ms.
#[test]
fn export_refuses_a_step_that_is_no_whole_millisecond() {
    let dir = tempfile::tempdir().unwrap();
    let db = recording(dir.path(), 10);
    let export = |step: &str| {
        let out = export_from(&db, "1000000010")
            .args(["--step-s", step])
            .output()
            .unwrap();
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    for step in ["1e-9", "0.0004", "0.0015"] {
        let (code, err) = export(step);
        assert_eq!(code, Some(1), "{step}: {err}");
        assert!(
            err.starts_with("error: --step-s: ")
                && err.contains("not a whole number of milliseconds"),
            "{step}: {err}"
        );
    }
    for step in ["0.001", "0.007", "2.5"] {
        let (code, err) = export(step);
        assert_eq!(code, Some(0), "{step}: {err}");
    }
}

// Messages that name what is at fault: an empty --sensors list, a missing data file
// (once: it was "x.csv: x.csv: No such file"), --max-c-swing (it was under "grid:"),
// an effect named twice (it was accepted).
#[test]
fn argument_errors_name_the_flag_or_file_once() {
    let dir = tempfile::tempdir().unwrap();
    let data = measurement_csv(dir.path());
    let data = data.to_str().unwrap();
    let (code, err) = run(&[
        "calibrate",
        "--data",
        data,
        "--out",
        "m.toml",
        "--sensors",
        "",
    ]);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.starts_with("error: --sensors: the list is empty"),
        "{err}"
    );
    let (code, err) = run(&["diagnose", "--data", data, "--sensors", "a,,b"]);
    assert_eq!(code, Some(1), "{err}");
    assert!(err.starts_with("error: --sensors: an empty name"), "{err}");

    let missing = dir.path().join("x.csv");
    let missing = missing.to_str().unwrap();
    for args in [
        &["calibrate", "--data", missing, "--out", "m.toml"][..],
        &["iso230", "--data", missing],
        &["diagnose", "--data", missing],
    ] {
        let (code, err) = run(args);
        assert_eq!(code, Some(1), "{err}");
        assert_eq!(
            err,
            format!("error: {missing}: No such file or directory (os error 2)\n"),
            "{args:?}"
        );
    }

    // The flag before the file: the errors file does not exist.
    let (code, err) = run(&["volumetric", "--errors", missing, "--max-c-swing", "nan"]);
    assert_eq!(code, Some(1), "{err}");
    assert_eq!(err, "error: --max-c-swing NaN: not a finite number\n");

    let out = dir.path().join("scenario");
    let (code, err) = run(&[
        "scenario",
        "--effects",
        "reversal,thermal_lag,reversal",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, Some(1), "{err}");
    assert_eq!(err, "error: --effects: reversal named twice\n");
    assert!(!out.exists(), "refused before anything is made");
}

// `--http` takes IP:PORT or `off`: anything else is the command line's error (exit 2,
// naming the flag); before, the demo said "no status page (invalid socket address
// syntax)" and ran on. (A busy port is still reported and the demo runs on.)
#[test]
fn demo_refuses_an_http_address_that_is_no_address() {
    for http in ["nonsense", "127.0.0.1:99999", "localhost:9464"] {
        let (code, err) = run(&["demo", "--http", http]);
        assert_eq!(code, Some(2), "{http}: {err}");
        assert!(
            err.contains(&format!("invalid value '{http}' for '--http")),
            "{http}: {err}"
        );
    }
}

// `volumetric --help` states the pole band from the constants the kinematics use
// (it said 30 deg where the code blends from 5 deg and holds C beyond 10).
#[test]
fn volumetric_help_states_the_pole_band_the_code_uses() {
    use compgate_commission::volumetric::MAX_ONLINE_C_CORRECTION_DEG;
    let out = Command::new(BIN)
        .args(["volumetric", "--help"])
        .output()
        .unwrap();
    let help = assert_success(&out);
    let band = format!(
        "more than {} deg; the per-cycle feedback blends towards holding C there and \
         holds it beyond {MAX_ONLINE_C_CORRECTION_DEG} deg",
        MAX_ONLINE_C_CORRECTION_DEG / 2.0
    );
    assert!(help.contains(&band), "{help}");
}

// The field review's repro: a recording with compensation applied (nc.applied_comp_mm
// 0.03 mm, one ok job) exported byte for byte as one without, and stderr said only
// the row count. Now stderr names the span, --add-applied-comp adds the 30 um back,
// and the flag without --axis is refused, naming it.
#[test]
fn export_of_a_compensated_recording_says_so_and_adds_the_compensation_on_request() {
    let dir = tempfile::tempdir().unwrap();
    let db = recording(dir.path(), 100);
    let conn = compgate_service::record::open(&db).expect("the recording");
    conn.execute("INSERT INTO channels(id, name) VALUES (2, 'laser_um')", [])
        .expect("the laser channel");
    for i in 0..100i64 {
        let t_ms = 1_000_000_000_000 + i * 1000;
        conn.execute(
            "INSERT INTO readings VALUES (?1, 2, 0.0, 12.0, 12.0, 0, NULL)",
            [t_ms],
        )
        .expect("a laser reading");
        conn.execute(
            "INSERT INTO nc VALUES (?1, 'X', 100.0, 0.03, 0.03, 0, 0)",
            [t_ms],
        )
        .expect("an NC row");
    }
    conn.execute(
        "INSERT INTO jobs(t_unix_ms, axis, sd43900_mm, sd43910, sd43920_mm, ok) VALUES (999999999000, 'X', 0.03, 0, 0, 1)",
        [],
    )
    .expect("a job");
    drop(conn);
    let export = |extra: &[&str]| {
        let out = export_from(&db, "1000000100")
            .args(["--err-channel", "laser_um"])
            .args(["--step-s", "10"])
            .args(extra)
            .output()
            .unwrap();
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stdout).into_owned(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let err_um = |csv: &str| -> Vec<String> {
        let mut lines = csv.lines();
        let head: Vec<&str> = lines.next().unwrap_or_default().split(',').collect();
        let col = head.iter().position(|h| *h == "err_um").expect("err_um");
        lines
            .map(|l| l.split(',').nth(col).unwrap_or_default().to_string())
            .collect()
    };
    let (code, csv, err) = export(&["--axis", "X"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(
        err.contains(
            "the NC applied compensation to axis `X` from 2001-09-09T01:46:40.000Z to 2001-09-09T01:48:19.000Z (up to 30.0 um)"
        ) && err.contains("--add-applied-comp"),
        "{err}"
    );
    assert!(
        err_um(&csv).iter().all(|e| e.parse::<f64>() == Ok(12.0)),
        "{csv}"
    );
    let (code, csv, err) = export(&["--axis", "X", "--add-applied-comp"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(
        err_um(&csv)
            .iter()
            .all(|e| e.parse::<f64>().is_ok_and(|v| (v - 42.0).abs() < 1e-9)),
        "{csv}"
    );
    let (code, _, err) = export(&["--add-applied-comp"]);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.starts_with("error: --add-applied-comp: needs --axis"),
        "{err}"
    );
}

// Ctrl-C during a scenario left its staged outputs' temporary files behind for good
// (`record.sqlite.tmp<pid>` with its WAL), beside the earlier run's outputs. Now the
// run is dropped with them: exit 130, the directory as it was.
#[test]
fn a_scenario_stopped_by_ctrl_c_leaves_the_directory_as_it_was() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("scenario");
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("report.txt"), "an earlier run's report\n").unwrap();
    let scenario = |out: &std::path::Path| {
        Command::new(BIN)
            .args(["scenario", "--loop", "--out"])
            .arg(out)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    };
    let child = scenario(&out);
    let names = || -> Vec<String> {
        std::fs::read_dir(&out)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect()
    };
    // Stopped while it records into its staged database.
    let end = Instant::now() + Duration::from_secs(60);
    while !names().iter().any(|n| n.contains(".tmp")) {
        assert!(
            Instant::now() < end,
            "no staged file appeared: {:?}",
            names()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    common::process::signal(child.id(), "INT");
    let ended = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&ended.stderr);
    assert_eq!(ended.status.code(), Some(130), "{err}");
    assert!(
        err.contains("error: stopped by SIGINT; nothing was written"),
        "{err}"
    );
    assert_eq!(names(), ["report.txt"]);
    assert_eq!(
        std::fs::read_to_string(out.join("report.txt")).unwrap(),
        "an earlier run's report\n"
    );

    // An output directory the run made is gone again.
    let fresh = dir.path().join("fresh");
    let child = scenario(&fresh);
    let end = Instant::now() + Duration::from_secs(60);
    while !fresh.exists() {
        assert!(Instant::now() < end, "no output directory made");
        std::thread::sleep(Duration::from_millis(5));
    }
    common::process::signal(child.id(), "INT");
    let ended = child.wait_with_output().unwrap();
    assert_eq!(ended.status.code(), Some(130));
    assert!(!fresh.exists(), "the directory the run made is left");
}
