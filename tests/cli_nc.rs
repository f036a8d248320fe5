//! `compgate nc read` / `compgate nc write` as an operator meets them, against the
//! simulated NC axis module on loopback.
#![allow(clippy::unwrap_used)]

mod common;

use std::io::Write;
use std::path::Path;
use std::process::{Command, Output, Stdio};

use common::opcua_peer::OpcuaPeer;
use common::{config, plant_and_file, with_target};

const BIN: &str = env!("CARGO_BIN_EXE_compgate");

/// Runs `compgate nc ARGS --config FILE` with `stdin` fed, off the runtime's threads.
async fn nc(file: &Path, args: &[&str], stdin: &str) -> Output {
    let mut cmd = Command::new(BIN);
    cmd.arg("nc")
        .args(args)
        .arg("--config")
        .arg(file)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
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

    let out = nc(&file, &args, "n\n").await;
    let t = text_of(&out);
    assert!(out.status.success(), "{t}");
    assert!(t.contains("SD43900: 0 -> 0.02"), "{t}");
    assert!(t.contains("SD43910: 0 -> -0.0001"), "{t}");
    assert!(t.contains("nothing written"), "{t}");
    assert_eq!(module.state().sd43900_mm, 0.0);
    assert_eq!(module.jobs_executed(), 0);

    let out = nc(&file, &args, "y\n").await;
    let t = text_of(&out);
    assert!(out.status.success(), "{t}");
    assert!(t.contains("written and read back"), "{t}");
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
        text_of(&out).contains("beyond the axis's limit"),
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
        text_of(&out).contains("not a finite number"),
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
        let text = with_target(&peer.target_table(dir.path(), user), 1);
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
    }
}
