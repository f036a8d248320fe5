//! The S7 data-block target against a real S7 server: python-snap7's server holding
//! the data block and `tests/peers/s7_plc.py` playing the PLC program's handshake,
//! on 127.0.0.1. Without the peer the tests skip (fail under `CI`).
// Test code: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

mod common;

use std::time::{Duration, Instant};

use common::s7_peer::{self, S7Peer};
use compgate_core::comp::CompParams;
use compgate_gateway::nc::guard::THERMAL_VARS;
use compgate_gateway::nc::s7::{S7NcWriter, S7TargetConfig};
use compgate_gateway::nc::{Guarded, Job, NcError, NcWriter};
use compgate_gateway::source::SourceError;
use compgate_ncproto::{var, JobState, JobStatus};

fn writer(peer: &S7Peer, extra: &str, axis_number: u16) -> S7NcWriter {
    let text = format!(
        "address = \"{}\"\ndb_number = 100\ntimeout_s = 0.5\n{extra}",
        peer.address()
    );
    let cfg: S7TargetConfig = toml::from_str(&text).unwrap();
    let mut p = compgate_gateway::config::problem::Problems::new("test.toml");
    cfg.validate("targets.plc", &mut p);
    assert!(p.into_vec().is_empty(), "config problems in {text}");
    cfg.build("X1", axis_number).unwrap()
}

/// Values no decimal shortcut survives: every mantissa bit matters.
fn awkward() -> CompParams {
    CompParams {
        k0_mm: 0.123_456_789_012_345_67,
        tan_beta: -1.234_567_890_123_456_7e-5,
        p0_mm: -123.456_789_012_345_6,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lreal_values_land_bit_for_bit_in_each_axis_block() {
    if !s7_peer::available() {
        return;
    }
    let peer = S7Peer::start(&["--value-type", "lreal", "--axes", "2", "--mode", "done"]);
    let p = awkward();
    // Axis 2 sits one stride into the block: its values must not touch axis 1's.
    let mut w2 = writer(&peer, "value_type = \"lreal\"", 2);
    let report = w2.write_job(&Job::thermal(&p)).await.unwrap();
    assert_eq!(report.job_id, 1);
    let held = w2.read_snapshot().await.unwrap();
    assert_eq!(held.sd43900_mm.to_bits(), p.k0_mm.to_bits());
    assert_eq!(held.sd43910.to_bits(), p.tan_beta.to_bits());
    assert_eq!(held.sd43920_mm.to_bits(), p.p0_mm.to_bits());
    assert_eq!((held.md32750, held.referenced), (Some(3), Some(true)));
    assert_eq!(held.md32760, 0.01);
    // The FB3 program leaves RbApplied and RbTarget 0: not read as "applies none".
    assert!(held.position_mm.is_some());
    assert_eq!((held.applied_comp_mm, held.target_comp_mm), (None, None));

    let mut w1 = writer(&peer, "value_type = \"lreal\"", 1);
    assert_eq!(
        w1.read_snapshot().await.unwrap().thermal(),
        CompParams::default()
    );
    // A second job on the same connection gets the next id and lands too.
    let q = CompParams {
        k0_mm: -0.000_000_1,
        ..p
    };
    assert_eq!(w2.write_job(&Job::thermal(&q)).await.unwrap().job_id, 2);
    assert_eq!(w2.read_snapshot().await.unwrap().thermal(), q);
    assert_eq!(w2.connects(), 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn real_values_land_as_their_float32_rounding() {
    if !s7_peer::available() {
        return;
    }
    let peer = S7Peer::start(&["--value-type", "real", "--mode", "done"]);
    let mut w = writer(&peer, "", 1);
    let p = awkward();
    w.write_job(&Job::thermal(&p)).await.unwrap();
    let held = w.read_snapshot().await.unwrap();
    for (read, sent) in [
        (held.sd43900_mm, p.k0_mm),
        (held.sd43910, p.tan_beta),
        (held.sd43920_mm, p.p0_mm),
    ] {
        assert_eq!(read.to_bits(), f64::from(sent as f32).to_bits(), "{sent}");
        assert_ne!(
            read, sent,
            "{sent} is no float32: the REAL path must have rounded it"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refused_job_is_reported_by_name_and_not_taken_as_written() {
    if !s7_peer::available() {
        return;
    }
    let peer = S7Peer::start(&["--mode", "error", "--status", "3", "--error-index", "2"]);
    let mut w = writer(&peer, "", 1);
    let e = w.write_job(&Job::thermal(&awkward())).await.unwrap_err();
    assert!(
        matches!(
            e,
            NcError::Refused {
                job_id: 1,
                status: JobStatus::AccessDenied,
                index: 2,
                var: Some(var::SD43910),
            }
        ),
        "{e:?}"
    );
    // The pair at fault by its name, not its index.
    assert!(
        e.to_string()
            .ends_with("refused: error 3 (access denied) for SD43910"),
        "{e}"
    );
    assert_eq!(
        w.read_snapshot().await.unwrap().thermal(),
        CompParams::default()
    );
    // The refusal was acknowledged: the next job runs the handshake again.
    let e = w.write_job(&Job::thermal(&awkward())).await.unwrap_err();
    assert!(matches!(e, NcError::Refused { job_id: 2, .. }), "{e:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_plc_programs_own_checks_refuse_out_of_range_and_unknown_variables() {
    if !s7_peer::available() {
        return;
    }
    let peer = S7Peer::start(&["--value-type", "lreal", "--mode", "done"]);
    let mut w = writer(&peer, "value_type = \"lreal\"", 1);
    let e = common::refused_all_or_none(&mut w).await;
    assert!(
        e.to_string().contains("(value out of range) for SD43900"),
        "{e}"
    );
    let machine_data = Job {
        pairs: vec![(var::MD32760, 0.5)],
    };
    let e = w.write_job(&machine_data).await.unwrap_err();
    assert!(e.to_string().contains("object does not exist"), "{e}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_plc_that_never_answers_hits_the_job_timeout() {
    if !s7_peer::available() {
        return;
    }
    let peer = S7Peer::start(&["--mode", "silent"]);
    let mut w = writer(&peer, "job_timeout_s = 0.3", 1);
    let t0 = Instant::now();
    let e = w.write_job(&Job::thermal(&awkward())).await.unwrap_err();
    let waited = t0.elapsed();
    assert!(
        matches!(
            e,
            NcError::JobTimeout {
                job_id: 1,
                state: Some(JobState::Idle),
                ..
            }
        ),
        "{e:?}"
    );
    // REQ was set: the PLC program may still take the job.
    assert_eq!(
        e.to_string(),
        "job 1 did not finish within 300ms (STATE stayed idle): the values may have landed; \
         check with `compgate nc read`"
    );
    // Bounded by the job timeout plus one request, not by the link's patience.
    assert!(
        waited >= Duration::from_millis(300) && waited < Duration::from_secs(2),
        "{waited:?}"
    );
    assert_eq!(
        w.read_snapshot().await.unwrap().thermal(),
        CompParams::default()
    );
    // The timeout fell between two requests: the connection stays.
    assert_eq!(w.connects(), 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restarted_plc_is_reconnected() {
    if !s7_peer::available() {
        return;
    }
    let mut peer = S7Peer::start(&["--value-type", "lreal", "--mode", "done"]);
    let mut w = writer(&peer, "value_type = \"lreal\"", 1);
    let p = awkward();
    w.write_job(&Job::thermal(&p)).await.unwrap();
    peer.kill();
    let e = w.write_job(&Job::thermal(&p)).await.unwrap_err();
    assert!(matches!(e, NcError::Link(_)), "{e:?}");
    assert!(!w.is_connected());
    // While the PLC is off, every connect fails and the next one backs off.
    let e = w.write_job(&Job::thermal(&p)).await.unwrap_err();
    assert!(matches!(e, NcError::Link(_)), "{e:?}");
    peer.restart();
    let deadline = Instant::now() + Duration::from_secs(15);
    let mut last = None;
    while Instant::now() < deadline {
        match w.write_job(&Job::thermal(&p)).await {
            Ok(_) => {
                last = None;
                break;
            }
            Err(e) => last = Some(e),
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(last.is_none(), "no reconnect within 15 s: {last:?}");
    assert_eq!(w.connects(), 2);
    // The restarted PLC started from an empty block: the values are the new job's.
    assert_eq!(w.read_snapshot().await.unwrap().thermal(), p);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_missing_data_block_is_named() {
    if !s7_peer::available() {
        return;
    }
    let peer = S7Peer::start(&["--mode", "done"]);
    let cfg: S7TargetConfig = toml::from_str(&format!(
        "address = \"{}\"\ndb_number = 101",
        peer.address()
    ))
    .unwrap();
    let mut w = cfg.build("X1", 1).unwrap();
    let e = w.write_job(&Job::thermal(&awkward())).await.unwrap_err();
    assert!(
        e.to_string()
            .contains("DB101 does not exist in the PLC (db_number)"),
        "{e}"
    );
    // A block shorter than the layout (axis 2 of a one-axis block) is named too.
    let cfg: S7TargetConfig = toml::from_str(&format!(
        "address = \"{}\"\ndb_number = 100",
        peer.address()
    ))
    .unwrap();
    let e = cfg
        .build("Y1", 2)
        .unwrap()
        .read_snapshot()
        .await
        .unwrap_err();
    assert!(e.to_string().contains("DB100 bytes"), "{e}");
    assert!(e.to_string().contains("Optimized block access"), "{e}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nothing_listening_is_a_link_error() {
    // No peer needed: a port nobody listens on.
    let sock = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = sock.local_addr().unwrap();
    drop(sock);
    let cfg: S7TargetConfig =
        toml::from_str(&format!("address = \"{addr}\"\ndb_number = 100")).unwrap();
    let mut w = cfg.build("X1", 1).unwrap();
    let e = w.write_job(&Job::thermal(&awkward())).await.unwrap_err();
    assert!(matches!(e, NcError::Link(SourceError::Connect(_))), "{e:?}");
    // While the reconnect waits, the error still says why the PLC is unreachable.
    let e = w.write_job(&Job::thermal(&awkward())).await.unwrap_err();
    assert!(
        matches!(&e, NcError::Link(SourceError::BackingOffAfter { cause, .. })
            if matches!(**cause, SourceError::Connect(_))),
        "{e:?}"
    );
    assert!(e.to_string().contains(&addr.to_string()), "{e}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn read_back_tolerates_one_float32_step_for_real_and_none_for_lreal() {
    if !s7_peer::available() {
        return;
    }
    let p = awkward();
    for (value_type, skew, ok) in [
        ("real", "1", true),
        ("real", "2", false),
        ("lreal", "1", false),
    ] {
        let peer = S7Peer::start(&[
            "--value-type",
            value_type,
            "--mode",
            "done",
            "--readback-skew-ulps",
            skew,
        ]);
        // Through the guard, as the gateway writes: the read-back check is its.
        let w = writer(&peer, &format!("value_type = \"{value_type}\""), 1);
        let mut w = Guarded::new(w, THERMAL_VARS.to_vec(), Duration::from_secs(5));
        let r = w.write_job(&Job::thermal(&p)).await;
        match (r, ok) {
            (Ok(_), true) => {}
            (Err(NcError::ReadBack { var, written, .. }), false) => {
                assert_eq!((var, written.to_bits()), (var::SD43900, p.k0_mm.to_bits()));
            }
            (r, _) => panic!("{value_type} read-back {skew} step(s) off: {r:?}"),
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_left_unacknowledged_is_waited_for_and_cleared_first() {
    if !s7_peer::available() {
        return;
    }
    // FB3 takes ~200 PLC cycles here: the first writer gives up while the PLC is busy
    // and never acknowledges what the PLC then answers.
    let peer = S7Peer::start(&["--value-type", "lreal", "--busy-scans", "200"]);
    let mut quick = writer(&peer, "value_type = \"lreal\"\njob_timeout_s = 0.05", 1);
    let e = quick
        .write_job(&Job::thermal(&awkward()))
        .await
        .unwrap_err();
    assert!(
        matches!(
            e,
            NcError::JobTimeout {
                state: Some(JobState::Busy),
                ..
            }
        ),
        "{e:?}"
    );
    let mut w = writer(&peer, "value_type = \"lreal\"\njob_timeout_s = 5.0", 1);
    let q = CompParams {
        k0_mm: 0.25,
        tan_beta: 2e-5,
        p0_mm: 100.0,
    };
    w.write_job(&Job::thermal(&q)).await.unwrap();
    assert_eq!(w.read_snapshot().await.unwrap().thermal(), q);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_block_of_the_other_value_type_is_named_and_never_gets_a_job() {
    if !s7_peer::available() {
        return;
    }
    // (the PLC's block, the config's value_type, what the check trips on)
    for (plc, configured, trips_on) in [
        // MD32750 = 3 and REFERENCED = 1 of the LREAL block read as REAL values.
        ("lreal", "real", "a subnormal number"),
        // MD32000 = 10000.0 of the REAL block read as STATE.
        ("real", "lreal", "STATE = 17948, not a job state 0..=3"),
    ] {
        let peer = S7Peer::start(&["--value-type", plc, "--axes", "2", "--mode", "done"]);
        let mut wrong = writer(&peer, &format!("value_type = \"{configured}\""), 1);
        let e = wrong.read_snapshot().await.unwrap_err();
        let text = e.to_string();
        assert!(matches!(e, NcError::Implausible(_)), "{e:?}");
        for needle in [
            "DB100 byte ",
            trips_on,
            &format!("value_type = \"{configured}\""),
            "the likely cause is value_type",
        ] {
            assert!(
                text.contains(needle),
                "{plc} as {configured}: `{needle}` missing: {text}"
            );
        }
        let e = wrong
            .write_job(&Job::thermal(&awkward()))
            .await
            .unwrap_err();
        assert!(matches!(e, NcError::Implausible(_)), "{e:?}");
        // The PLC never saw REQ: with the right layout the block still holds nothing.
        let mut right = writer(&peer, &format!("value_type = \"{plc}\""), 1);
        assert_eq!(
            right.read_snapshot().await.unwrap().thermal(),
            CompParams::default(),
            "{plc} as {configured}"
        );
    }
}

// A one-axis REAL block read as LREAL, or for an axis it does not have, ends past
// the block: the message blamed only the block's length or its optimized access.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reading_past_the_block_names_value_type_and_axis_number() {
    if !s7_peer::available() {
        return;
    }
    let peer = S7Peer::start(&["--value-type", "real", "--axes", "1", "--mode", "done"]);
    for (configured, axis) in [("lreal", 1), ("real", 2)] {
        let mut w = writer(&peer, &format!("value_type = \"{configured}\""), axis);
        let text = w.read_snapshot().await.unwrap_err().to_string();
        assert!(
            text.contains("invalid address")
                && text.contains(&format!(
                    "axis_number {axis} of the layout with value_type = \"{configured}\""
                )),
            "{configured}, axis {axis}: {text}"
        );
    }
}

#[test]
fn validation_names_the_axis_whose_block_passes_byte_65535() {
    let target = "[targets.nc_x]\nkind = \"s7\"\naddress = \"127.0.0.1:102\"\n\
                  db_number = 120\nblock_stride_bytes = 400\n";
    let text = common::with_target(target, 200);
    let e = compgate_gateway::config::load_str(&text, "s7.toml").unwrap_err();
    let text = e.to_string();
    assert!(
        text.contains("s7.toml: axes.X.axis_number: no room for NC axis 200's block in DB120"),
        "{text}"
    );
    assert!(text.contains("block_stride_bytes 400"), "{text}");
    assert!(!text.contains("invalid job"), "{text}");
    // Axis 164 still fits: 163 * 400 + 108 <= 65535.
    let ok = common::with_target(target, 164);
    compgate_gateway::config::load_str(&ok, "s7.toml").unwrap();
}
