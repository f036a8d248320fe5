//! The OPC UA NC target against an independent server: `OpcuaNcWriter` driven directly
//! against the SINUMERIK-like asyncua peer (`tests/peers/opcua_server.py`) on loopback.
//! Without the peer installed the tests skip with a message; with `CI` set they fail.
// Test code: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

mod common;

use std::time::Duration;

use common::opcua_peer::{self, OpcuaPeer};
use compgate_core::comp::CompParams;
use compgate_gateway::nc::guard::THERMAL_VARS;
use compgate_gateway::nc::opcua::{
    OpcuaNcWriter, OpcuaSecurityMode, OpcuaSecurityPolicy, OpcuaTargetConfig,
};
use compgate_gateway::nc::{Guarded, Job, NcError, NcWriter};

const ABS: &str = "$SA_TEMP_COMP_ABS_VALUE";
const SLOPE: &str = "$SA_TEMP_COMP_SLOPE";
const REF: &str = "$SA_TEMP_COMP_REF_POSITION";

/// A target on `peer` without security, logging in with the credentials file `cred`.
fn target(
    peer: &OpcuaPeer,
    dir: &tempfile::TempDir,
    user: Option<(&str, &str)>,
) -> OpcuaTargetConfig {
    let credentials_file = user.map(|(u, p)| {
        let path = dir.path().join(format!("cred-{u}"));
        std::fs::write(&path, format!("{u}\n{p}\n")).unwrap();
        path.display().to_string()
    });
    OpcuaTargetConfig {
        security_policy: OpcuaSecurityPolicy::None,
        security_mode: OpcuaSecurityMode::None,
        pki_dir: dir.path().join("pki").display().to_string(),
        credentials_file,
        ..OpcuaTargetConfig::new(peer.endpoint.clone())
    }
}

fn writer_of(cfg: &OpcuaTargetConfig, axis: u16) -> OpcuaNcWriter {
    cfg.build(&format!("A{axis}"), axis).unwrap()
}

/// The bits the peer holds for the three setting data of `axis`.
fn held(peer: &mut OpcuaPeer, axis: u16) -> [u64; 3] {
    let dump = peer.dump();
    [ABS, SLOPE, REF].map(|name| {
        let node = peer.node(name, axis);
        *dump
            .get(&node)
            .unwrap_or_else(|| panic!("{node} not in the peer's dump {dump:?}"))
    })
}

fn bits(p: &CompParams) -> [u64; 3] {
    [p.k0_mm.to_bits(), p.tan_beta.to_bits(), p.p0_mm.to_bits()]
}

#[tokio::test]
async fn values_land_bit_for_bit_on_the_right_axis() {
    let Some(mut peer) = OpcuaPeer::start(&[]) else {
        return;
    };
    // The namespace sits behind decoys: a client that assumed ns=2 would miss.
    assert!(peer.ns > 2, "peer ns {}", peer.ns);
    let dir = tempfile::tempdir().unwrap();
    let cfg = target(&peer, &dir, Some(("writer", "writer-pw")));
    let mut w = writer_of(&cfg, 2);

    // Values whose decimal round trip or sign a lossy path would change.
    let jobs = [
        CompParams {
            k0_mm: 0.1 + 0.2,
            tan_beta: -1.234_567_890_123_456_7e-5,
            p0_mm: -0.0,
        },
        CompParams {
            k0_mm: -0.012_345_678_901_234_5,
            tan_beta: 5e-324,
            p0_mm: 1_234.567_890_123_45,
        },
    ];
    for p in &jobs {
        let report = w.write_job(&Job::thermal(p)).await.unwrap();
        assert!(report.elapsed < cfg.job_timeout());
        assert_eq!(held(&mut peer, 2), bits(p), "peer holds what was written");
        let snap = w.read_snapshot().await.unwrap();
        assert_eq!(bits(&snap.thermal()), bits(p), "snapshot reads it back");
        // The setting data are all it reads: no position, applied compensation or
        // axis state (0 and false had looked like a standing, unreferenced axis).
        assert_eq!(
            (
                snap.position_mm,
                snap.applied_comp_mm,
                snap.md32750,
                snap.referenced
            ),
            (None, None, None, None)
        );
    }
    // The other axes are untouched.
    assert_eq!(held(&mut peer, 1), [0; 3]);
    assert_eq!(held(&mut peer, 3), [0; 3]);
    assert!(w.may_write().await.unwrap(), "writer holds SeaWrite");
    assert_eq!(w.connects(), 1, "one session for every call");
    let nodes = w.node_ids().unwrap();
    assert_eq!(nodes[0], peer.node(ABS, 2));
}

#[tokio::test]
async fn user_without_write_rights_gets_the_named_error_and_nothing_changes() {
    let Some(mut peer) = OpcuaPeer::start(&[]) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    // A writer's session asks first: what it may do must not carry over to the reader.
    let mut writer = writer_of(&target(&peer, &dir, Some(("writer", "writer-pw"))), 1);
    assert!(writer.may_write().await.unwrap(), "writer holds SeaWrite");
    // The reader's credentials come from the environment (names unique to this test).
    std::env::set_var("COMPGATE_TEST_OPCUA_READER_USER", "reader");
    std::env::set_var("COMPGATE_TEST_OPCUA_READER_PW", "reader-pw");
    let cfg = OpcuaTargetConfig {
        user_env: Some("COMPGATE_TEST_OPCUA_READER_USER".into()),
        password_env: Some("COMPGATE_TEST_OPCUA_READER_PW".into()),
        ..target(&peer, &dir, None)
    };
    let mut w = writer_of(&cfg, 1);
    let before = peer.dump();
    let err = w
        .write_job(&Job::thermal(&CompParams {
            k0_mm: 0.5,
            tan_beta: 1e-5,
            p0_mm: 100.0,
        }))
        .await
        .expect_err("the reader may not write");
    assert!(
        matches!(&err, NcError::OpcuaAccessDenied { user, .. } if user.contains("reader")),
        "{err:?}"
    );
    let msg = err.to_string();
    for needle in [
        "BadUserAccessDenied",
        "SeaWrite",
        "GiveUserAccess",
        "reader",
    ] {
        assert!(msg.contains(needle), "`{needle}` missing from: {msg}");
    }
    assert!(!msg.contains("reader-pw"), "password leaked: {msg}");
    assert_eq!(peer.dump(), before, "no value changed");
    assert!(!w.may_write().await.unwrap(), "reader lacks SeaWrite");

    // Anonymous: the same.
    let mut anon = writer_of(&target(&peer, &dir, None), 1);
    assert!(!anon.may_write().await.unwrap());
    let err = anon
        .write_job(&Job::thermal(&CompParams::default()))
        .await
        .expect_err("anonymous may not write");
    assert!(err.to_string().contains("anonymous"), "{err}");

    // A wrong password is refused at connect, named, and the password is not shown.
    let mut bad = writer_of(&target(&peer, &dir, Some(("writer", "not-the-pw"))), 1);
    let err = bad.read_snapshot().await.expect_err("wrong password");
    let msg = err.to_string();
    assert!(msg.contains("Bad") && msg.contains("writer"), "{msg}");
    assert!(!msg.contains("not-the-pw"), "password leaked: {msg}");
    assert_eq!(peer.dump(), before, "still no value changed");
}

#[tokio::test]
async fn server_restart_mid_run_reconnects_and_the_next_job_lands() {
    let Some(mut peer) = OpcuaPeer::start(&[]) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let cfg = target(&peer, &dir, Some(("writer", "writer-pw")));
    let mut w = writer_of(&cfg, 3);
    let first = CompParams {
        k0_mm: 0.011,
        tan_beta: 2e-6,
        p0_mm: 50.0,
    };
    w.write_job(&Job::thermal(&first)).await.unwrap();
    assert_eq!(held(&mut peer, 3), bits(&first));

    // Crash; the control comes back on the same port with its namespaces in another
    // order, so the old namespace index would now address nothing.
    let port = peer.port;
    let old_ns = peer.ns;
    peer.kill();
    let second = CompParams {
        k0_mm: -0.007,
        tan_beta: -3e-6,
        p0_mm: 75.25,
    };
    let err = w
        .write_job(&Job::thermal(&second))
        .await
        .expect_err("the server is down");
    assert!(!matches!(err, NcError::ReadBack { .. }), "{err:?}");
    let Some(mut peer) = OpcuaPeer::start_on(port, &["--decoys", "3"]) else {
        return;
    };
    assert_ne!(peer.ns, old_ns);
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    loop {
        match w.write_job(&Job::thermal(&second)).await {
            Ok(_) => break,
            Err(e) => assert!(
                tokio::time::Instant::now() < deadline,
                "no reconnect within 30 s; last error: {e}"
            ),
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(
        held(&mut peer, 3),
        bits(&second),
        "the job after the restart landed"
    );
    assert_eq!(w.connects(), 2, "a new session after the restart");
}

#[tokio::test]
async fn slow_server_hits_the_job_timeout_and_the_job_is_not_taken_as_written() {
    let Some(mut peer) = OpcuaPeer::start(&["--write-delay-s", "3"]) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let cfg = OpcuaTargetConfig {
        job_timeout_s: 0.5,
        request_timeout_s: 5.0,
        ..target(&peer, &dir, Some(("writer", "writer-pw")))
    };
    let mut w = writer_of(&cfg, 1);
    // Connect first so the timeout below is the write's, not the connect's.
    w.read_snapshot().await.unwrap();
    let started = std::time::Instant::now();
    let err = w
        .write_job(&Job::thermal(&CompParams {
            k0_mm: 0.25,
            tan_beta: 0.0,
            p0_mm: 0.0,
        }))
        .await
        .expect_err("the write answer comes after the job timeout");
    assert!(
        matches!(err, NcError::JobTimeout { timeout, .. } if timeout == Duration::from_millis(500)),
        "{err:?}"
    );
    assert!(
        started.elapsed() < Duration::from_secs(3),
        "the job gave up before the server answered"
    );
    assert!(
        !w.is_connected(),
        "the session with the hanging write is dropped"
    );

    // Once the server is quick again the next job lands on a fresh session.
    peer.set_write_delay(0.0);
    let next = CompParams {
        k0_mm: -0.125,
        tan_beta: 1e-6,
        p0_mm: 10.0,
    };
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    loop {
        match w.write_job(&Job::thermal(&next)).await {
            Ok(_) => break,
            Err(e) => assert!(tokio::time::Instant::now() < deadline, "{e}"),
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(held(&mut peer, 1), bits(&next));
}

// A control slower than request_timeout_s: every job timed out, and each opened a new
// session while the old one's close timed out too, so sessions piled up on the
// server (11 in 25 s). The session stays; the job is reported as maybe landed.
#[tokio::test]
async fn a_request_timeout_keeps_the_session() {
    let Some(mut peer) = OpcuaPeer::start(&["--write-delay-s", "1.5"]) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let cfg = OpcuaTargetConfig {
        job_timeout_s: 5.0,
        request_timeout_s: 0.5,
        ..target(&peer, &dir, Some(("writer", "writer-pw")))
    };
    let mut w = writer_of(&cfg, 1);
    w.read_snapshot().await.unwrap();
    for k0_mm in [0.25, 0.5] {
        let err = w
            .write_job(&Job::thermal(&CompParams {
                k0_mm,
                tan_beta: 0.0,
                p0_mm: 0.0,
            }))
            .await
            .expect_err("the write answer comes after the request timeout");
        assert!(
            matches!(err, NcError::JobTimeout { sent: true, .. }),
            "{err:?}"
        );
        // The server is done with the write before the next one.
        tokio::time::sleep(Duration::from_secs(2)).await;
    }
    assert!(w.is_connected(), "the session is kept");
    assert_eq!(w.connects(), 1, "no session per job");
    // Quick again: the next job lands on the same session.
    peer.set_write_delay(0.0);
    w.write_job(&Job::thermal(&CompParams::default()))
        .await
        .unwrap();
    assert_eq!(w.connects(), 1);
}

#[tokio::test]
async fn unknown_namespace_or_node_is_named() {
    let Some(mut peer) = OpcuaPeer::start(&["--axes", "2"]) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let base = target(&peer, &dir, Some(("writer", "writer-pw")));
    let cfg = OpcuaTargetConfig {
        namespace_uri: "NoSuchVarProvider".into(),
        ..base.clone()
    };
    let err = writer_of(&cfg, 1)
        .read_snapshot()
        .await
        .expect_err("no such namespace");
    let msg = err.to_string();
    assert!(
        msg.contains("NoSuchVarProvider") && msg.contains("SinumerikVarProvider"),
        "{msg}"
    );

    // Axis 9 does not exist on the server: the status is named, nothing is written.
    let before = peer.dump();
    let err = writer_of(&base, 9)
        .write_job(&Job::thermal(&CompParams::default()))
        .await
        .expect_err("no such node");
    let msg = err.to_string();
    assert!(
        msg.contains("BadNodeIdUnknown") && msg.contains("[u9]"),
        "{msg}"
    );
    // The key it comes from, to correct (with axis_number).
    assert!(msg.contains("(from sd43900_node)"), "{msg}");
    assert_eq!(peer.dump(), before);
}

#[tokio::test]
async fn a_value_the_server_does_not_hold_as_written_fails_the_read_back() {
    // The peer keeps what it is given as float32, as a REAL store would.
    let Some(mut peer) = OpcuaPeer::start(&["--lossy", "--axes", "1"]) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    // Through the guard, as the gateway writes: the read-back check is its.
    let mut w = Guarded::new(
        writer_of(&target(&peer, &dir, Some(("writer", "writer-pw"))), 1),
        THERMAL_VARS.to_vec(),
        Duration::from_secs(5),
    );
    let p = CompParams {
        k0_mm: 0.1,
        tan_beta: 0.5,
        p0_mm: 0.25,
    };
    let err = w
        .write_job(&Job::thermal(&p))
        .await
        .expect_err("0.1 is not a float32");
    match err {
        NcError::ReadBack { var, written, read } => {
            assert_eq!(var, compgate_ncproto::var::SD43900);
            assert_eq!(written.to_bits(), 0.1f64.to_bits());
            assert_eq!(read.to_bits(), f64::from(0.1f32).to_bits());
        }
        other => panic!("expected a read-back error, got {other:?}"),
    }
    assert_eq!(held(&mut peer, 1)[0], f64::from(0.1f32).to_bits());
}

#[tokio::test]
async fn an_idle_session_is_kept_alive_and_a_closed_one_is_renewed() {
    let Some(mut peer) = OpcuaPeer::start(&["--min-session-timeout-s", "0.5"]) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let cfg = OpcuaTargetConfig {
        session_timeout_s: 1.0,
        ..target(&peer, &dir, Some(("writer", "writer-pw")))
    };
    let mut w = writer_of(&cfg, 2);
    let p = |k0_mm: f64| CompParams {
        k0_mm,
        tan_beta: 0.0,
        p0_mm: 0.0,
    };
    w.write_job(&Job::thermal(&p(0.001))).await.unwrap();
    // Idle for more than twice the session timeout: keep-alives must hold it open.
    tokio::time::sleep(Duration::from_millis(2500)).await;
    w.write_job(&Job::thermal(&p(0.002))).await.unwrap();
    assert_eq!(w.connects(), 1, "the same session served both jobs");

    // The server closes the session anyway: the writer opens a new one.
    assert!(peer.expire_sessions() >= 1);
    let deadline = tokio::time::Instant::now() + Duration::from_secs(15);
    loop {
        match w.write_job(&Job::thermal(&p(0.003))).await {
            Ok(_) => break,
            Err(e) => assert!(
                tokio::time::Instant::now() < deadline,
                "no new session within 15 s: {e}"
            ),
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(w.connects(), 2);
    assert_eq!(held(&mut peer, 2)[0], 0.003f64.to_bits());
}

#[tokio::test]
async fn signed_and_encrypted_once_the_server_certificate_is_trusted() {
    if opcua_peer::python().is_none() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let pki = dir.path().join("pki");
    opcua_peer::make_client_cert(&pki);
    let server_dir = dir.path().display().to_string();
    let Some(mut peer) = OpcuaPeer::start(&["--secure", &server_dir]) else {
        return;
    };
    let plain = target(&peer, &dir, Some(("writer", "writer-pw")));
    let secure = OpcuaTargetConfig {
        security_policy: OpcuaSecurityPolicy::Basic256Sha256,
        security_mode: OpcuaSecurityMode::SignAndEncrypt,
        ..plain.clone()
    };
    let p = CompParams {
        k0_mm: 0.031_25,
        tan_beta: -7e-6,
        p0_mm: 250.0,
    };

    // The server offers no unsecured endpoint.
    let err = writer_of(&plain, 1)
        .write_job(&Job::thermal(&p))
        .await
        .expect_err("no None endpoint");
    assert!(err.to_string().contains("security_policy"), "{err}");

    // The server's certificate is not trusted yet: refused, and kept in rejected/.
    let err = writer_of(&secure, 1)
        .write_job(&Job::thermal(&p))
        .await
        .expect_err("untrusted server certificate");
    let rejected: Vec<_> = std::fs::read_dir(pki.join("rejected"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert_eq!(rejected.len(), 1, "{err}");
    let msg = err.to_string();
    assert!(
        msg.contains("BadCertificateUntrusted") && msg.contains("pki_dir"),
        "{msg}"
    );
    assert_eq!(held(&mut peer, 1), [0; 3], "nothing written: {err}");

    // The administrator moves it to trusted/: the next session is signed and encrypted.
    std::fs::create_dir_all(pki.join("trusted")).unwrap();
    for cert in &rejected {
        std::fs::rename(cert, pki.join("trusted").join(cert.file_name().unwrap())).unwrap();
    }
    let mut w = writer_of(&secure, 1);
    w.write_job(&Job::thermal(&p)).await.unwrap();
    assert_eq!(held(&mut peer, 1), bits(&p));
    assert!(w.may_write().await.unwrap());
}

#[tokio::test]
async fn a_connect_outlasting_the_callers_timeout_is_kept_not_restarted() {
    // Every session takes 0.4 s to create, as a busy control's might.
    let Some(mut peer) = OpcuaPeer::start(&["--session-delay-s", "0.4"]) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let mut w = writer_of(&target(&peer, &dir, Some(("writer", "writer-pw"))), 1);
    let p = CompParams {
        k0_mm: 0.042,
        tan_beta: 0.0,
        p0_mm: 1.0,
    };
    // A caller (the runtime's guard) that gives up after 100 ms, less than a connect
    // takes: every cut-off call leaves the connect running for the next one.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    let mut cut_off = 0;
    loop {
        match tokio::time::timeout(Duration::from_millis(100), w.write_job(&Job::thermal(&p))).await
        {
            Ok(Ok(_)) => break,
            Ok(Err(e)) => panic!("{e}"),
            Err(_) => cut_off += 1,
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "never connected within 20 s ({cut_off} calls cut off)"
        );
    }
    assert!(
        cut_off > 0,
        "the first call was not cut off: the test proves nothing"
    );
    assert_eq!(w.connects(), 1, "one session, not one per cut-off call");
    assert_eq!(held(&mut peer, 1), bits(&p));
}

#[test]
fn validation_refuses_two_axes_on_one_node() {
    let problems = |text: &str| match compgate_gateway::config::load_str(text, "opcua.toml") {
        Ok(_) => String::new(),
        Err(e) => e.to_string(),
    };
    let target = |extra: &str| {
        format!(
            "[targets.nc_x]\nkind = \"opcua\"\nendpoint_url = \"opc.tcp://127.0.0.1:4840\"\n\
             security_policy = \"None\"\nsecurity_mode = \"None\"\n{extra}"
        )
    };
    let second_axis = "\n[axes.Y]\nnc_module = \"nc_x\"\naxis_number = 2\nmd32750 = 3\n";
    // The default templates carry {axis_number}: two axes, six nodes.
    assert_eq!(
        problems(&(common::with_target(&target(""), 1) + second_axis)),
        ""
    );
    // A template without the axis: both axes would write one node.
    let fixed = format!("sd43900_node = \"ns={{ns}};s=/NC/_N_AX_SEA_ACX/{ABS}[u1]\"\n");
    let p = problems(&(common::with_target(&target(&fixed), 1) + second_axis));
    assert!(
        p.contains(&format!(
            "opcua.toml: targets.nc_x.sd43900_node: axes X and Y both resolve sd43900_node to \
             `ns={{ns}};s=/NC/_N_AX_SEA_ACX/{ABS}[u1]`"
        )),
        "{p}"
    );
    // Two setting data on one node of one axis.
    let same =
        format!("sd43910_node = \"ns={{ns}};s=/NC/_N_AX_SEA_ACX/{ABS}[u{{axis_number}}]\"\n");
    let p = problems(&common::with_target(&target(&same), 1));
    assert!(
        p.contains("targets.nc_x.sd43910_node: axis X: sd43910_node and sd43900_node both resolve"),
        "{p}"
    );
}
