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
