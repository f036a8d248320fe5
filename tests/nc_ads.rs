//! The ADS target against pyads' own test server (tests/peers/ads_server.py): the full
//! chain lands bit for bit, and each guarantee of the target path holds on it.
#![allow(clippy::unwrap_used)]

mod common;

use std::time::Duration;

use ads::{AmsAddr, Source, Timeouts};
use common::peer::{self, Peer};
use common::{start, with_target, written_by_model, Rig};

/// Where the values sit for axis number 1: index group 0x5000 + axis, offsets 0, 8, 16.
const GROUP: u32 = 0x5001;

/// The test peer with the three values of axis 1 (`kind`: `"lreal"` or `"real"`)
/// holding `k0`, 0 and 100; `more` are extra arguments.
fn ads_peer(kind: &str, k0: f64, more: &[&str]) -> Option<Peer> {
    let mut args: Vec<String> = [(0, k0), (8, 0.0), (16, 100.0)]
        .iter()
        .flat_map(|(o, v)| [format!("--{kind}"), format!("{GROUP:#x}:{o}={v}")])
        .collect();
    args.extend(more.iter().map(|s| s.to_string()));
    peer::start("ads_server.py", "pyads", &args)
}

/// The common test config with its NC module replaced by an ADS target at `address`.
fn ads_config(address: &str, target_extra: &str) -> String {
    let at = |o: u32| format!("{{ index_group = 0x5000, index_offset = {o}, group_per_axis = 1 }}");
    let target = format!(
        "[targets.nc_x]\nkind = \"ads\"\naddress = \"{address}\"\nams_net_id = \"127.0.0.1.1.1\"\n\
         timeout_s = 1.0\njob_timeout_s = 1.0\nsd43900 = {}\nsd43910 = {}\nsd43920 = {}\n{target_extra}",
        at(0),
        at(8),
        at(16)
    );
    with_target(&target, 1)
}

/// What the peer holds at `offset` of axis 1, read with a client of the test's own.
fn held(peer: &Peer, offset: u32, real: bool) -> f64 {
    let client = ads::Client::new(
        peer.address(),
        Timeouts::new(Duration::from_secs(1)),
        Source::Auto,
    )
    .unwrap();
    let dev = client.device(AmsAddr::new("127.0.0.1.1.1".parse().unwrap(), 851));
    if real {
        let mut b = [0; 4];
        dev.read_exact(GROUP, offset, &mut b).unwrap();
        f64::from(f32::from_le_bytes(b))
    } else {
        let mut b = [0; 8];
        dev.read_exact(GROUP, offset, &mut b).unwrap();
        f64::from_le_bytes(b)
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn full_chain_lands_bit_for_bit_on_the_ads_peer() {
    for (kind, real) in [("lreal", false), ("real", true)] {
        let Some(peer) = ads_peer(kind, 0.0, &[]) else {
            return;
        };
        let cfg = ads_config(&peer.address(), &format!("value_type = \"{kind}\"\n"));
        let mut rig = start(&cfg).await;
        let s = rig
            .wait_for(10.0, "a verified job on the ADS peer", |s| {
                s.axes[0].jobs_ok >= 1
            })
            .await;
        let written = written_by_model(&s);
        let stored = |x: f64| if real { f64::from(x as f32) } else { x };
        let peer_k0 = held(&peer, 0, real);
        // Bit for bit: LREAL holds the f64 written, REAL its float32 rounding.
        assert_eq!(peer_k0.to_bits(), stored(written.k0_mm).to_bits(), "{kind}");
        assert_eq!(
            held(&peer, 8, real).to_bits(),
            stored(written.tan_beta).to_bits(),
            "{kind}"
        );
        assert_eq!(held(&peer, 16, real), 100.0);
        rig.stop_without_failed_jobs().await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refused_write_is_reported_retried_and_not_taken_as_written() {
    // SD43910 is read-only on this control: the sum-up write is refused as a whole.
    let Some(peer) = ads_peer("lreal", 0.0, &["--read-only", "0x5001:8"]) else {
        return;
    };
    let mut rig = start(&ads_config(&peer.address(), "")).await;
    let s = rig
        .wait_for(10.0, "two refused jobs", |s| s.axes[0].jobs_failed >= 2)
        .await;
    let err = s.axes[0].last_job_error.clone().unwrap();
    assert!(err.contains("ADS error 0x704"), "{err}");
    assert!(err.contains("SD43910"), "{err}");
    assert_eq!(s.axes[0].jobs_ok, 0);
    // Not confirmed: the gateway still shows what the control held at start.
    assert_eq!(s.axes[0].written.unwrap().k0_mm, 0.0);
    assert_eq!(held(&peer, 0, false), 0.0);
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn step_limits_start_from_what_the_control_holds() {
    // The control holds K0 = 0.3 mm; the model wants 0.04 mm; one step is 0.01 mm.
    let Some(peer) = ads_peer("lreal", 0.3, &[]) else {
        return;
    };
    let cfg =
        ads_config(&peer.address(), "").replace("max_step_k0_mm = 0.5", "max_step_k0_mm = 0.01");
    let mut rig = start(&cfg).await;
    let s = rig
        .wait_for(10.0, "a first job", |s| s.axes[0].jobs_ok >= 1)
        .await;
    let first = held(&peer, 0, false);
    assert!(
        (first - 0.29).abs() < 0.0100001 && first < 0.3,
        "first write {first} is one step from 0.3, not the model's 0.04"
    );
    assert!(s.axes[0].written.unwrap().k0_mm >= 0.28);
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_slow_control_hits_the_job_timeout() {
    // Every answer takes 0.15 s: a job (three reads to check what the NC holds, the
    // write, three reads back) needs 1.05 s of a 0.8 s job timeout. The check and the
    // write are answered in time; the read-back is not.
    let Some(peer) = ads_peer("lreal", 0.0, &["--delay-s", "0.15"]) else {
        return;
    };
    let cfg = ads_config(&peer.address(), "").replace("job_timeout_s = 1.0", "job_timeout_s = 0.8");
    let mut rig = start(&cfg).await;
    let s = rig
        .wait_for(15.0, "a job timeout", |s| {
            s.axes[0].last_job_error.as_deref().is_some_and(|e| {
                e.ends_with(
                    "written; read-back not finished within job_timeout_s = 800ms: check with `compgate nc read`",
                )
            })
        })
        .await;
    assert_eq!(s.axes[0].jobs_ok, 0);
    rig.stop().await;
    // It was written indeed.
    assert_ne!(held(&peer, 0, false), 0.0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_value_type_is_named_and_nothing_is_written() {
    // LREAL variables read as REAL: the low half of 0.02 reads 89128.96, no value an
    // NC holds as SD43900. (Not every value shows it: the low half of 0.0 or 100.0 is
    // 0, and that of 0.3 reads 4.2e-8.)
    let Some(peer) = ads_peer("lreal", 0.02, &[]) else {
        return;
    };
    let cfg = ads_config(&peer.address(), "value_type = \"real\"\n");
    let mut rig = start(&cfg).await;
    let s = rig
        .wait_for(10.0, "the snapshot refused", |s| {
            s.axes[0].warning.as_deref().is_some_and(|w| {
                w.contains("SD43900 (ADS 0x5001:0x0) reads")
                    && w.contains("the likely cause is value_type = \"real\"")
            })
        })
        .await;
    assert!(
        !s.axes[0]
            .warning
            .as_deref()
            .unwrap_or_default()
            .contains("unreachable"),
        "{:?}",
        s.axes[0].warning
    );
    // Several updates went by: none wrote.
    rig.wait_for(10.0, "more samples", |t| t.samples >= s.samples + 20)
        .await;
    assert_eq!(held(&peer, 0, false), 0.02);
    rig.stop().await;

    // REAL variables read as LREAL: the control answers 4 bytes; named, and an answer,
    // not an unreachable target.
    let Some(peer) = ads_peer("real", 0.25, &[]) else {
        return;
    };
    let target: compgate_gateway::config::Config = compgate_gateway::config::load_str(
        &ads_config(&peer.address(), "value_type = \"lreal\"\n"),
        "ads.toml",
    )
    .unwrap();
    let mut w = target.target("nc_x").unwrap().build("X", 1).unwrap();
    let e = compgate_gateway::nc::NcWriter::read_snapshot(&mut w)
        .await
        .unwrap_err();
    assert!(!e.is_unreachable(), "{e:?}");
    assert_eq!(
        e.to_string(),
        "read of SD43900 (ADS 0x5001:0x0): the control answered 4 bytes where value_type = \
         \"lreal\" reads 8: check value_type (REAL is 4 bytes, LREAL 8)"
    );

    // An index offset the control does not have: its ADS error names what to check.
    let text = ads_config(&peer.address(), "value_type = \"real\"\n")
        .replace("index_offset = 16", "index_offset = 24");
    let target = compgate_gateway::config::load_str(&text, "ads.toml").unwrap();
    let mut w = target.target("nc_x").unwrap().build("X", 1).unwrap();
    let e = compgate_gateway::nc::NcWriter::read_snapshot(&mut w)
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.starts_with("read of SD43920 (ADS 0x5001:0x18): ADS error 0x703")
            && e.ends_with(": check the value's index_group and index_offset"),
        "{e}"
    );
}

#[test]
fn validation_refuses_two_axes_on_one_variable_and_an_index_that_overflows() {
    let problems = |text: &str| match compgate_gateway::config::load_str(text, "ads.toml") {
        Ok(_) => String::new(),
        Err(e) => e.to_string(),
    };
    // Offsets without a per-axis step: axis 2 would write axis 1's variables.
    let fixed = |o: u32| format!("{{ index_group = 0x4020, index_offset = {o} }}");
    let target = format!(
        "[targets.nc_x]\nkind = \"ads\"\naddress = \"127.0.0.1:48898\"\nams_net_id = \
         \"127.0.0.1.1.1\"\nsd43900 = {}\nsd43910 = {}\nsd43920 = {}\n",
        fixed(0),
        fixed(8),
        fixed(16)
    );
    let second_axis = "\n[axes.Y]\nnc_module = \"nc_x\"\naxis_number = 2\nmd32750 = 3\n";
    let p = problems(&(with_target(&target, 1) + second_axis));
    for var in ["sd43900", "sd43910", "sd43920"] {
        let name = var.to_uppercase();
        assert!(
            p.contains(&format!(
                "ads.toml: targets.nc_x.{var}: {name} (ADS 0x4020:0x{:x}) of axis Y overlaps \
                 {name} (ADS 0x4020:0x{:x}) of axis X",
                (var.as_bytes()[5] - b'0') * 8,
                (var.as_bytes()[5] - b'0') * 8
            )),
            "{var}: {p}"
        );
    }
    // A per-axis step apart from each other: fine.
    let stepped = target
        .replace(
            "index_offset = 0 }",
            "index_offset = 0, offset_per_axis = 24 }",
        )
        .replace(
            "index_offset = 8 }",
            "index_offset = 8, offset_per_axis = 24 }",
        )
        .replace(
            "index_offset = 16 }",
            "index_offset = 16, offset_per_axis = 24 }",
        );
    assert_eq!(problems(&(with_target(&stepped, 1) + second_axis)), "");
    // An LREAL at offset 4 shares bytes with SD43900's at 0.
    let p = problems(&with_target(
        &target.replace("index_offset = 8", "index_offset = 4"),
        1,
    ));
    assert!(
        p.contains("targets.nc_x.sd43910: SD43910 (ADS 0x4020:0x4) of axis X overlaps SD43900"),
        "{p}"
    );
    // An index group past 32 bits at this axis number: the axis' key, not "invalid job".
    let p = problems(&with_target(
        &target.replace(
            "index_group = 0x4020, index_offset = 0 }",
            "index_group = 0xFFFFFFFF, index_offset = 0, group_per_axis = 1 }",
        ),
        1,
    ));
    assert!(
        p.contains("ads.toml: axes.X.axis_number: the index group or offset of SD43900 overflows"),
        "{p}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dead_control_never_stops_the_polling() {
    // Nothing listens there.
    let dead = format!("127.0.0.1:{}", common::free_port());
    let mut rig = start(&ads_config(&dead, "")).await;
    let s = rig
        .wait_for(10.0, "the target shown unreachable", |s| {
            s.axes[0]
                .warning
                .as_deref()
                .is_some_and(|w| w.contains("NC unreachable"))
        })
        .await;
    let before = s.samples;
    let s = rig
        .wait_for(10.0, "20 more samples", |s| s.samples >= before + 20)
        .await;
    assert_eq!(
        Rig::channel(&s, "T_bed").reading.quality,
        compgate_core::channel::Quality::Good
    );
    assert_eq!(s.axes[0].jobs_ok, 0);
    rig.stop().await;
}
