//! The Modbus NC target against a module that serves exactly the documented register
//! map (issue 23, trap 1), and what the status says when an NC answers with an
//! exception.
#![allow(clippy::unwrap_used)]

mod common;

use std::time::Duration;

use common::{config, start};
use compgate_core::comp::CompParams;
use compgate_gateway::nc::guard::THERMAL_VARS;
use compgate_gateway::nc::modbus::ModbusTargetConfig;
use compgate_gateway::nc::{Guarded, Job, NcWriter};
use compgate_plc::nc::{NcAxis, NcAxisModule};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_module_serving_only_the_documented_registers_is_written() {
    let mut rig = start(&config("hold", "", "")).await;
    let nc = rig.plant.nc["nc_x"].clone();
    nc.set_documented_only(true);
    // Reading 100..141 in one request is refused by such a module: the writer must
    // read only what the map documents.
    let s = rig
        .wait_for(10.0, "a verified job on the strict module", |s| {
            s.axes[0].jobs_ok >= 1
                && s.axes[0]
                    .nc
                    .is_some_and(|n| n.md32750 == Some(3) && n.referenced == Some(true))
        })
        .await;
    assert_eq!(
        nc.state().sd43900_mm.to_bits(),
        s.axes[0].written.unwrap().k0_mm.to_bits()
    );
    assert!(s.axes[0].warning.is_none(), "{:?}", s.axes[0].warning);
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_nc_answering_with_an_exception_is_not_called_unreachable() {
    // A Modbus server that answers, but has no read-back block: the plant's field
    // device refuses the holding-register reads with an exception.
    let rig = start(&config("hold", "", "")).await;
    let field_addr = rig.plant.config.devices["ain1"]
        .tcp()
        .unwrap()
        .address
        .clone();
    let mut cfg = rig.plant.config.clone();
    cfg.nc_modules.get_mut("nc_x").unwrap().address = field_addr;
    rig.shutdown.cancel();
    let (tx, mut rx) = tokio::sync::watch::channel(Default::default());
    let stop = tokio_util::sync::CancellationToken::new();
    let sd = stop.clone();
    let gw = tokio::spawn(async move {
        compgate_gateway::runtime::run(&cfg, sd, tx).await.unwrap();
    });
    let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(10);
    let warning = loop {
        let w = rx
            .borrow_and_update()
            .axes
            .first()
            .and_then(|a| a.warning.clone());
        if let Some(w) = w {
            break w;
        }
        tokio::time::timeout_at(deadline, rx.changed())
            .await
            .expect("a warning within 10 s")
            .unwrap();
    };
    assert!(!warning.contains("unreachable"), "{warning}");
    assert!(warning.contains("answered"), "{warning}");
    assert!(warning.contains("exception"), "{warning}");
    stop.cancel();
    gw.await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_modbus_target_table_is_the_same_module_as_nc_modules() {
    // `[targets.nc_x] kind = "modbus"` instead of `[nc_modules.nc_x]`: the plant serves
    // it and the chain lands on it bit for bit.
    let cfg = config("hold", "", "")
        .replace("[nc_modules.nc_x]\n", "[targets.nc_x]\nkind = \"modbus\"\n");
    let mut rig = start(&cfg).await;
    assert!(rig.plant.config.nc_modules.is_empty());
    let s = rig
        .wait_for(10.0, "a verified job on the target", |s| {
            s.axes[0].jobs_ok >= 1
        })
        .await;
    let nc = rig.plant.nc["nc_x"].state();
    let w = s.axes[0].written.unwrap();
    assert_eq!(nc.sd43900_mm.to_bits(), w.k0_mm.to_bits());
    assert_eq!(nc.sd43910.to_bits(), w.tan_beta.to_bits());
    rig.stop().await;
}

#[tokio::test]
async fn a_guarded_job_costs_the_module_seven_requests() {
    // Is the module idle, the job block, REQ, the read that sees DONE with the result,
    // the acknowledge, and the guard's read-back (values, then MD32750 and the
    // referenced flag): the read-back is checked once.
    let module = NcAxisModule::new(NcAxis {
        referenced: true,
        md32750: 3,
        ..NcAxis::default()
    });
    let (address, stop) = module.serve_loopback().await.unwrap();
    let target: ModbusTargetConfig =
        toml::from_str(&format!("address = \"{address}\"\nunit_id = 1\n")).unwrap();
    let mut w = Guarded::new(
        target.writer(),
        THERMAL_VARS.to_vec(),
        Duration::from_secs(5),
    );
    for k in 1..=3 {
        let before = module.requests_served();
        let p = CompParams {
            k0_mm: 0.01 * f64::from(k),
            tan_beta: 1e-5,
            p0_mm: 10.0,
        };
        w.write_job(&Job::thermal(&p)).await.unwrap();
        assert_eq!(module.requests_served() - before, 7, "job {k}");
        assert_eq!(module.state().sd43900_mm.to_bits(), p.k0_mm.to_bits());
    }
    stop.cancel();
}
