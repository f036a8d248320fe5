//! The Modbus NC target against a module that serves exactly the documented register
//! map (issue 23, trap 1), and what the status says when an NC answers with an
//! exception.
#![allow(clippy::unwrap_used)]

mod common;

use common::{config, start};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_module_serving_only_the_documented_registers_is_written() {
    let mut rig = start(&config("hold", "", "")).await;
    let nc = rig.plant.nc["nc_x"].clone();
    nc.set_documented_only(true);
    // Reading 100..141 in one request is refused by such a module: the writer must
    // read only what the map documents.
    let s = rig
        .wait_for(10.0, "a verified job on the strict module", |s| {
            s.axes[0].jobs_ok >= 1 && s.axes[0].nc.is_some_and(|n| n.md32750 == 3 && n.referenced)
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
