//! The full chain on each real-control peer: transmitters on Modbus -> filter ->
//! compensation -> an OPC UA or S7 target, the values landing bit for bit (the ADS
//! chain is in `tests/nc_ads.rs`, the Modbus NC module's in `tests/gateway.rs`).
#![allow(clippy::unwrap_used)]

mod common;

use common::opcua_peer::OpcuaPeer;
use common::s7_peer::{self, S7Peer};
use common::{start, with_target, written_by_model};
use compgate_gateway::nc::s7::S7TargetConfig;
use compgate_gateway::nc::NcWriter;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn full_chain_lands_bit_for_bit_on_the_opcua_peer() {
    let Some(mut peer) = OpcuaPeer::start(&[]) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let target = peer.target_table(dir.path(), "writer");
    let mut rig = start(&with_target(&target, 2)).await;
    let s = rig
        .wait_for(20.0, "a verified job on the OPC UA peer", |s| {
            s.axes[0].jobs_ok >= 1
        })
        .await;
    let w = written_by_model(&s);
    assert_eq!(w.p0_mm, 100.0);
    let dump = peer.dump();
    let held = |name: &str| dump[&peer.node(name, 2)];
    assert_eq!(held("$SA_TEMP_COMP_ABS_VALUE"), w.k0_mm.to_bits());
    assert_eq!(held("$SA_TEMP_COMP_SLOPE"), w.tan_beta.to_bits());
    assert_eq!(held("$SA_TEMP_COMP_REF_POSITION"), w.p0_mm.to_bits());
    // Axis 1's nodes are untouched.
    assert_eq!(
        dump[&peer.node("$SA_TEMP_COMP_ABS_VALUE", 1)],
        0.0_f64.to_bits()
    );
    rig.stop_without_failed_jobs().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn full_chain_lands_bit_for_bit_on_the_s7_peer() {
    if !s7_peer::available() {
        return;
    }
    for (value_type, real) in [("lreal", false), ("real", true)] {
        let peer = S7Peer::start(&["--value-type", value_type, "--axes", "2", "--mode", "done"]);
        let target = format!(
            "[targets.nc_x]\nkind = \"s7\"\naddress = \"{}\"\ndb_number = 100\n\
             value_type = \"{value_type}\"\ntimeout_s = 0.5\n",
            peer.address()
        );
        let mut rig = start(&with_target(&target, 2)).await;
        let s = rig
            .wait_for(20.0, "a verified job on the S7 peer", |s| {
                s.axes[0].jobs_ok >= 1
            })
            .await;
        let w = written_by_model(&s);
        assert_eq!(w.p0_mm, 100.0);
        // What the block holds, read by a reader of the test's own.
        let reader: S7TargetConfig = toml::from_str(&format!(
            "address = \"{}\"\ndb_number = 100\nvalue_type = \"{value_type}\"\n",
            peer.address()
        ))
        .unwrap();
        let held = reader.build("X", 2).unwrap().read_snapshot().await.unwrap();
        let stored = |x: f64| if real { f64::from(x as f32) } else { x };
        assert_eq!(
            held.sd43900_mm.to_bits(),
            stored(w.k0_mm).to_bits(),
            "{value_type}"
        );
        assert_eq!(
            held.sd43910.to_bits(),
            stored(w.tan_beta).to_bits(),
            "{value_type}"
        );
        assert_eq!(held.sd43920_mm, 100.0);
        rig.stop_without_failed_jobs().await;
    }
}

// A rotated password: the credentials file rewritten and the service reloaded. The
// reload kept the OPC UA writer of the unchanged target, built with the credentials
// read at start, so its next session logged in as before (review Y). Here the file
// names another user, who may not write: after the reload and a session expiry the
// jobs must fail as that user's, not land as the old one's.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reload_takes_up_credentials_rewritten_in_their_file() {
    let Some(mut peer) = OpcuaPeer::start(&[]) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let target = peer.target_table(dir.path(), "writer");
    let cfg = compgate_gateway::config::load_str(&with_target(&target, 2), "test.toml").unwrap();
    let plant = compgate::plant::Plant::start(&cfg, compgate::plant::Bind::Ephemeral)
        .await
        .unwrap();
    let cfg = plant.config.clone();
    let (tx, mut status) = tokio::sync::watch::channel(Default::default());
    let (reload, reloads) = tokio::sync::mpsc::channel(1);
    let shutdown = tokio_util::sync::CancellationToken::new();
    let (sd, run_cfg) = (shutdown.clone(), cfg.clone());
    let gateway = tokio::spawn(async move {
        let hooks = compgate_gateway::runtime::Hooks {
            reload: Some(reloads),
            ..Default::default()
        };
        compgate_gateway::runtime::run_with(&run_cfg, sd, tx, hooks)
            .await
            .unwrap();
    });
    common::wait_status(&mut status, 20.0, "a verified job as `writer`", |s| {
        s.axes[0].jobs_ok >= 1
    })
    .await;

    std::fs::write(dir.path().join("cred-writer"), "reader\nreader-pw\n").unwrap();
    reload.send(cfg).await.unwrap();
    // The new writer has read the NC (once a second at most), and the old one's
    // session is gone (a control admits only a few): one open.
    tokio::time::sleep(std::time::Duration::from_millis(1500)).await;
    assert_eq!(peer.expire_sessions(), 1, "sessions open after the reload");
    plant.field["ain1"]
        .set_temperature_override(0, Some(35.0))
        .unwrap();
    // (A job that met the expired session fails first, as a link fault.)
    common::wait_status(&mut status, 20.0, "a job refused to `reader`", |s| {
        s.axes[0]
            .last_job_error
            .as_deref()
            .is_some_and(|e| e.contains("BadUserAccessDenied"))
    })
    .await;
    shutdown.cancel();
    gateway.await.unwrap();
}
