//! `compgate nc read` / `compgate nc write` as an operator meets them, against the
//! simulated NC axis module on loopback.
#![allow(clippy::unwrap_used)]

mod common;

use std::io::Write;
use std::path::Path;
use std::process::{Command, Output, Stdio};

use common::opcua_peer::OpcuaPeer;
use common::s7_peer::{self, S7Peer};
use common::{config, plant_and_file, with_target};

const BIN: &str = env!("CARGO_BIN_EXE_compgate");

fn nc_command(file: &Path, args: &[&str]) -> Command {
    let mut cmd = Command::new(BIN);
    cmd.arg("nc")
        .args(args)
        .arg("--config")
        .arg(file)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    cmd
}

/// Runs `compgate nc ARGS --config FILE` with `stdin` fed through a pipe, off the
/// runtime's threads.
async fn nc(file: &Path, args: &[&str], stdin: &str) -> Output {
    let mut cmd = nc_command(file, args);
    cmd.stdin(Stdio::piped());
    let stdin = stdin.to_string();
    tokio::task::spawn_blocking(move || {
        let mut child = cmd.spawn().unwrap();
        child
            .stdin
            .take()
            .unwrap()
            .write_all(stdin.as_bytes())
            .unwrap();
        child.wait_with_output().unwrap()
    })
    .await
    .unwrap()
}

/// Runs `compgate nc ARGS --config FILE` with a terminal (a pty) as standard input,
/// on which `answer` has been typed.
async fn nc_at_terminal(file: &Path, args: &[&str], answer: &str) -> Output {
    // Kept open until the command ends: the terminal lives while one side is open.
    let (mut master, _slave, path) = compgate_plc::field::pty_pair().unwrap();
    Write::write_all(&mut master, answer.as_bytes()).unwrap();
    let mut cmd = nc_command(file, args);
    cmd.stdin(Stdio::from(std::fs::File::open(&path).unwrap()));
    tokio::task::spawn_blocking(move || cmd.output().unwrap())
        .await
        .unwrap()
}

fn text_of(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nc_read_prints_what_the_nc_holds() {
    let dir = tempfile::tempdir().unwrap();
    let (plant, file) = plant_and_file(dir.path(), &config("hold", "", ""), "").await;
    plant.nc["nc_x"].with_state(|a| {
        a.sd43900_mm = 0.0123;
        a.sd43910 = -0.000025;
    });
    let out = nc(&file, &["read"], "").await;
    let t = text_of(&out);
    assert!(out.status.success(), "{t}");
    assert!(
        t.contains("axis X (target nc_x, kind = modbus): SD43900 = 0.0123 mm, SD43910 = -0.000025, SD43920 = 0 mm"),
        "{t}"
    );
    assert!(t.contains("MD32750 = 3, referenced = true"), "{t}");
    assert!(!t.contains("warning"), "{t}");

    let out = nc(&file, &["read", "--target", "nope"], "").await;
    assert_eq!(out.status.code(), Some(1));
    assert!(
        text_of(&out).contains("no target `nope`"),
        "{}",
        text_of(&out)
    );
    // A dead NC: the read fails with the reason, exit 1.
    drop(plant);
    let out = nc(&file, &["read"], "").await;
    assert_eq!(out.status.code(), Some(1), "{}", text_of(&out));
    assert!(
        text_of(&out).contains("could not be read"),
        "{}",
        text_of(&out)
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nc_write_shows_the_change_and_writes_once_after_yes() {
    let dir = tempfile::tempdir().unwrap();
    let (plant, file) = plant_and_file(dir.path(), &config("hold", "", ""), "").await;
    let module = plant.nc["nc_x"].clone();
    let args = [
        "write",
        "--axis",
        "X",
        "--k0-mm",
        "0.02",
        "--tan-beta",
        "-0.0001",
    ];

    let out = nc_at_terminal(&file, &args, "n\n").await;
    let t = text_of(&out);
    assert!(out.status.success(), "{t}");
    assert!(t.contains("SD43900: 0 -> 0.02"), "{t}");
    assert!(t.contains("SD43910: 0 -> -0.0001"), "{t}");
    assert!(t.contains("nothing written"), "{t}");
    assert_eq!(module.state().sd43900_mm, 0.0);
    assert_eq!(module.jobs_executed(), 0);

    // No terminal to answer on and no --yes (a script): refused, nothing written, even
    // with a "y" in the pipe.
    for piped in ["", "y\n"] {
        let out = nc(&file, &args, piped).await;
        let t = text_of(&out);
        assert_eq!(out.status.code(), Some(1), "{t}");
        assert!(t.contains("not a terminal") && t.contains("--yes"), "{t}");
        assert!(!t.contains("write? [y/N]"), "{t}");
    }
    assert_eq!(module.jobs_executed(), 0);

    let out = nc_at_terminal(&file, &args, "y\n").await;
    let t = text_of(&out);
    assert!(out.status.success(), "{t}");
    assert!(t.contains("written and read back"), "{t}");
    // A running gateway would replace the value: said, with the way to keep it.
    assert!(
        t.contains(
            "moves it back to its own value by at most max_step_k0_mm per update_interval_s"
        ) && t.contains("deadband_k0_mm")
            && t.contains("shadow = true"),
        "{t}"
    );
    let s = module.state();
    assert_eq!(s.sd43900_mm.to_bits(), 0.02_f64.to_bits());
    assert_eq!(s.sd43910.to_bits(), (-0.0001_f64).to_bits());
    assert_eq!(module.jobs_executed(), 1);

    // Beyond the axis's limit (max_abs_k0_mm = 0.5): refused, nothing sent.
    let out = nc(
        &file,
        &["write", "--axis", "X", "--k0-mm", "5", "--yes"],
        "",
    )
    .await;
    assert_eq!(out.status.code(), Some(1));
    assert!(
        text_of(&out).contains("--k0-mm 5: beyond the limit of 0.5 mm (axes.X.max_abs_k0_mm)"),
        "{}",
        text_of(&out)
    );
    let out = nc(
        &file,
        &["write", "--axis", "X", "--k0-mm", "NaN", "--yes"],
        "",
    )
    .await;
    assert_eq!(out.status.code(), Some(1));
    assert!(
        text_of(&out).contains("--k0-mm NaN: not a finite number"),
        "{}",
        text_of(&out)
    );
    let out = nc(
        &file,
        &["write", "--axis", "Y", "--k0-mm", "0.01", "--yes"],
        "",
    )
    .await;
    assert!(text_of(&out).contains("no axis `Y`"), "{}", text_of(&out));
    assert_eq!(module.jobs_executed(), 1);
    assert_eq!(module.state().sd43900_mm.to_bits(), 0.02_f64.to_bits());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nc_read_on_opcua_says_whether_the_session_may_write() {
    let Some(peer) = OpcuaPeer::start(&[]) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    for (user, may) in [
        ("writer", "this session may write them"),
        ("reader", "may NOT write"),
    ] {
        // The device's port 0 is for the simulated plant only; `nc` polls no device.
        let text = with_target(&peer.target_table(dir.path(), user), 1)
            .replace("127.0.0.1:0", &format!("127.0.0.1:{}", common::free_port()));
        let file = dir.path().join(format!("{user}.toml"));
        std::fs::write(&file, text).unwrap();
        let out = nc(&file, &["read"], "").await;
        let t = text_of(&out);
        assert!(out.status.success(), "{t}");
        assert!(
            t.contains("axis X (axis 1 on target nc_x, kind = opcua): SD43900 = 0 mm"),
            "{t}"
        );
        assert!(t.contains(may), "{user}: {t}");
        // Security None: no certificate, by design, and no ERROR lines about it.
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!stderr.contains("ERROR"), "{user}: {stderr}");
        assert!(!stderr.contains("certificate"), "{user}: {stderr}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nc_write_keeps_p0_in_its_range_and_shows_values_readably() {
    let dir = tempfile::tempdir().unwrap();
    let (plant, file) = plant_and_file(dir.path(), &config("hold", "", ""), "").await;
    let module = plant.nc["nc_x"].clone();
    module.with_state(|a| {
        a.sd43910 = 1e-30;
        a.sd43920_mm = 1e300;
    });
    // No value is printed with hundreds of digits.
    let out = nc(&file, &["read"], "").await;
    let t = text_of(&out);
    assert!(t.contains("SD43910 = 1e-30, SD43920 = 1e300 mm"), "{t}");

    for p0 in ["1e300", "100000.5", "-1e9"] {
        let out = nc(&file, &["write", "--axis", "X", "--p0-mm", p0, "--yes"], "").await;
        let t = text_of(&out);
        assert_eq!(out.status.code(), Some(1), "{t}");
        assert!(t.contains("--p0-mm ") && t.contains("axes.X.p0_mm"), "{t}");
        assert!(t.contains("beyond the limit of 100000 mm"), "{t}");
    }
    assert_eq!(module.jobs_executed(), 0);
    // The limit itself is allowed, and only the value given is written.
    let out = nc(
        &file,
        &["write", "--axis", "X", "--p0-mm", "-100000", "--yes"],
        "",
    )
    .await;
    let t = text_of(&out);
    assert!(out.status.success(), "{t}");
    assert!(t.contains("SD43920: 1e300 -> -100000"), "{t}");
    assert_eq!(module.state().sd43920_mm, -100_000.0);
    assert_eq!(module.state().sd43910, 1e-30);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nc_write_refuses_a_wrong_md32750_and_nc_read_and_write_warn_of_an_unreferenced_axis() {
    let dir = tempfile::tempdir().unwrap();
    let (plant, file) = plant_and_file(dir.path(), &config("hold", "", ""), "").await;
    let module = plant.nc["nc_x"].clone();
    let args = ["write", "--axis", "X", "--k0-mm", "0.04", "--yes"];
    module.with_state(|a| a.md32750 = 1);
    let out = nc(&file, &args, "").await;
    let t = text_of(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(
        t.contains(
            "axis X (target nc_x, kind = modbus): MD32750 is 1 on the NC, axes.X.md32750 expects 3"
        ),
        "{t}"
    );
    assert!(t.contains("nothing was written"), "{t}");
    assert_eq!(module.jobs_executed(), 0);
    // `nc read` reports it and names the key, but a read is not refused.
    let out = nc(&file, &["read"], "").await;
    let t = text_of(&out);
    assert!(out.status.success(), "{t}");
    assert!(
        t.contains("MD32750 = 1, referenced = true")
            && t.contains("warning: axes.X.md32750 expects 3: the gateway holds this axis"),
        "{t}"
    );

    // Not referenced: written, after a warning that says what it means.
    module.with_state(|a| {
        a.md32750 = 3;
        a.referenced = false;
    });
    let out = nc(&file, &args, "").await;
    let t = text_of(&out);
    assert!(out.status.success(), "{t}");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("warning: axis X (target nc_x, kind = modbus): the axis is not referenced: the NC applies no temperature compensation until it is"),
        "{stderr}"
    );
    assert_eq!(module.jobs_executed(), 1);
    assert_eq!(module.state().sd43900_mm, 0.04);
    let t = text_of(&nc(&file, &["read"], "").await);
    assert!(
        t.contains("warning: the axis is not referenced") && !t.contains("md32750 expects"),
        "{t}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nc_write_takes_any_of_the_three_values_and_checks_the_allow_list_first() {
    let dir = tempfile::tempdir().unwrap();
    // A slope-only axis: SD43900 is not to be written.
    let text = config("hold", "", "").replace(
        "k0 = { offset_mm = 0.0, terms = [{ channel = \"T_bed\", ref_degc = 20.0, coeff_mm_per_degc = 0.004 }] }\n",
        "nc_write = [\"sd43910\", \"sd43920\"]\n",
    );
    assert!(text.contains("nc_write"), "{text}");
    let (plant, file) = plant_and_file(dir.path(), &text, "").await;
    let module = plant.nc["nc_x"].clone();
    let out = nc(
        &file,
        &["write", "--axis", "X", "--tan-beta", "0.00001", "--yes"],
        "",
    )
    .await;
    let t = text_of(&out);
    assert!(out.status.success(), "{t}");
    assert!(
        t.contains("SD43910: 0 -> 0.00001") && !t.contains("SD43900:"),
        "{t}"
    );
    assert_eq!(module.state().sd43910, 0.00001);

    // SD43900 is refused before any old -> new line is shown.
    let out = nc(
        &file,
        &[
            "write",
            "--axis",
            "X",
            "--k0-mm",
            "0",
            "--tan-beta",
            "0.00002",
            "--yes",
        ],
        "",
    )
    .await;
    let t = text_of(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(
        t.contains("SD43900 is not in the allow-list") && t.contains("axes.X.nc_write"),
        "{t}"
    );
    assert!(!t.contains("->"), "{t}");
    assert_eq!(module.jobs_executed(), 1);

    // None of the three: a usage error.
    let out = nc(&file, &["write", "--axis", "X", "--yes"], "").await;
    let t = text_of(&out);
    assert_eq!(out.status.code(), Some(2), "{t}");
    assert!(t.contains("--k0-mm") && t.contains("--tan-beta"), "{t}");
}

// Ctrl-C (or SIGTERM, a closed SSH session) while a job was under way ended the
// process at once and silently: the values landed, and nobody was told. The command
// now waits for the job's outcome (at most the job timeout) and reports it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_signal_during_an_nc_write_waits_for_the_jobs_outcome() {
    use compgate_plc::nc::JobFault;
    let dir = tempfile::tempdir().unwrap();
    // A job of 2 s within a timeout of 5 s: a loaded machine may stall this test or
    // the command for a good part of a second between the job's start and the signal.
    let toml = config("hold", "", "").replace("job_timeout_s = 0.5", "job_timeout_s = 5");
    let (plant, file) = plant_and_file(dir.path(), &toml, "").await;
    let module = plant.nc["nc_x"].clone();
    module.set_job_fault(JobFault::Delay(std::time::Duration::from_secs(2)));
    let child = nc_command(&file, &["write", "--axis", "X", "--k0-mm", "0.02", "--yes"])
        .stdin(Stdio::null())
        .spawn()
        .unwrap();
    let end = std::time::Instant::now() + std::time::Duration::from_secs(10);
    while module.job_state() != compgate_ncproto::JobState::Busy {
        assert!(std::time::Instant::now() < end, "the job never started");
        tokio::time::sleep(std::time::Duration::from_millis(1)).await;
    }
    let kill = Command::new("kill")
        .arg("-INT")
        .arg(child.id().to_string())
        .status()
        .unwrap();
    assert!(kill.success());
    let out = tokio::task::spawn_blocking(move || child.wait_with_output().unwrap())
        .await
        .unwrap();
    let t = text_of(&out);
    assert!(out.status.success(), "{:?}: {t}", out.status);
    assert!(
        t.contains("SIGINT: the job is under way; stopping once its outcome is known"),
        "{t}"
    );
    assert!(t.contains("written and read back"), "{t}");
    assert_eq!(module.state().sd43900_mm, 0.02);
    drop(plant);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nc_write_errors_name_the_axis_and_say_a_late_job_may_have_landed() {
    if !s7_peer::available() {
        return;
    }
    // The PLC program does not run: REQ is set and never answered.
    let peer = S7Peer::start(&["--mode", "silent"]);
    let dir = tempfile::tempdir().unwrap();
    let target = format!(
        "[targets.nc_x]\nkind = \"s7\"\naddress = \"{}\"\ndb_number = 100\njob_timeout_s = 0.3\n",
        peer.address()
    );
    let file = dir.path().join("s7.toml");
    // The device's port 0 is for the simulated plant only; `nc` polls no device.
    let text = with_target(&target, 1)
        .replace("127.0.0.1:0", &format!("127.0.0.1:{}", common::free_port()));
    std::fs::write(&file, text).unwrap();
    let out = nc(
        &file,
        &["write", "--axis", "X", "--k0-mm", "0.01", "--yes"],
        "",
    )
    .await;
    let t = text_of(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    // Whether the PLC's STATE was read before the deadline depends on the machine's
    // load; the message names it when it was.
    assert!(
        t.contains(
            "error: axis X (axis 1 on target nc_x, kind = s7): job 1 did not finish within 300ms"
        ),
        "{t}"
    );
    assert!(
        t.contains("the values may have landed; check with `compgate nc read`"),
        "{t}"
    );
    assert!(!t.contains("Some("), "{t}");
}

// A value the NC holds is shown to a fixed resolution: lengths to 1 nm, SD43910 to 6
// significant digits. Before, a computed value showed its float noise
// (`SD43900 = 0.027999999999999997 mm`, `applied compensation = 0.10400000000000001 mm`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nc_read_shows_values_without_float_noise() {
    let dir = tempfile::tempdir().unwrap();
    let (plant, file) = plant_and_file(dir.path(), &config("hold", "", ""), "").await;
    let (k0, tan_beta, applied) = (0.1 * 0.28, -0.1 * 0.0006, 0.1 + 0.004);
    for noisy in [k0, tan_beta, applied] {
        assert!(noisy.to_string().len() > 18, "{noisy} shows no float noise");
    }
    plant.nc["nc_x"].with_state(|a| {
        a.sd43900_mm = k0;
        a.sd43910 = tan_beta;
        a.applied_comp_mm = applied;
    });
    let out = nc(&file, &["read"], "").await;
    let t = text_of(&out);
    assert!(out.status.success(), "{t}");
    assert!(
        t.contains("SD43900 = 0.028 mm, SD43910 = -0.00006, SD43920 = 0 mm"),
        "{t}"
    );
    // The module moves its applied compensation on its own: at most 6 decimals.
    let applied = t
        .split("applied compensation = ")
        .nth(1)
        .and_then(|r| r.split(" mm").next())
        .unwrap_or_else(|| panic!("no applied compensation in {t}"));
    let decimals = applied.split('.').nth(1).map_or(0, str::len);
    assert!(decimals <= 6, "applied compensation = {applied} mm");
}

/// Significant digits of a number as printed (`-0.0000245679`, `2.5e-7`: 6 and 2).
fn significant_digits(text: &str) -> usize {
    let mantissa = text.split('e').next().unwrap_or(text);
    mantissa
        .chars()
        .filter(char::is_ascii_digit)
        .skip_while(|c| *c == '0')
        .count()
}

// The gateway's job log line shows what it wrote as `nc read` shows it (the recorder
// keeps the exact values). Before, a computed value came with its float noise:
// `written="SD43900=0.027999999999999997 mm, SD43910=-0.00006000000000000001, ..."`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_job_log_shows_written_values_without_float_noise() {
    let dir = tempfile::tempdir().unwrap();
    let (plant, path) = plant_and_file(dir.path(), &config("hold", "", ""), "").await;
    let gw = common::process::Gateway::start(dir.path(), &path, &[]);
    let line = tokio::task::block_in_place(|| gw.wait_log(10.0, "NC job done"));
    let written = line
        .split("written=\"")
        .nth(1)
        .and_then(|r| r.split('"').next())
        .unwrap_or_else(|| panic!("no written=\"...\" in {line}"));
    for pair in written.split(", ") {
        let (name, value) = pair.split_once('=').unwrap();
        match value.strip_suffix(" mm") {
            Some(mm) => {
                let decimals = mm.split('.').nth(1).map_or(0, str::len);
                assert!(decimals <= 6, "{name} = {mm} mm in {line}");
            }
            None => assert!(significant_digits(value) <= 6, "{name} = {value} in {line}"),
        }
    }
    drop(gw);
    drop(plant);
}
