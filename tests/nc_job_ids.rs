//! The job id the gateway reports (status, recorder, MQTT) is the one the NC saw.

use std::time::Duration;

use compgate_core::comp::CompParams;
use compgate_gateway::nc::guard::THERMAL_VARS;
use compgate_gateway::nc::modbus::ModbusTargetConfig;
use compgate_gateway::nc::{Guarded, Job, NcError};
use compgate_plc::nc::{NcAxis, NcAxisModule};
use tokio_modbus::client::Reader;

/// `JOB_ID_DONE` of the module at `address`: the id of its last finished job.
async fn job_id_done(address: &str) -> u16 {
    let mut ctx = tokio_modbus::client::tcp::connect(address.parse().expect("address"))
        .await
        .expect("connect");
    ctx.read_holding_registers(compgate_ncproto::JOB_ID_DONE, 1)
        .await
        .expect("transport")
        .expect("no exception")[0]
}

fn params(k0_mm: f64) -> CompParams {
    CompParams {
        k0_mm,
        tan_beta: 1e-5,
        p0_mm: 10.0,
    }
}

// A job refused before it went out (the NC changed at the HMI since the step was
// limited) used to take an id the NC never saw: every later job was then reported
// one ahead of the NC's JOB_ID_DONE.
#[tokio::test]
async fn a_job_not_sent_takes_no_id() {
    let module = NcAxisModule::new(NcAxis {
        referenced: true,
        md32750: 3,
        ..NcAxis::default()
    });
    let (address, stop) = module.serve_loopback().await.expect("serves");
    let target: ModbusTargetConfig =
        toml::from_str(&format!("address = \"{address}\"\nunit_id = 1\n")).expect("target");
    let mut w = Guarded::new(
        target.writer(),
        THERMAL_VARS.to_vec(),
        Duration::from_secs(5),
    );
    let first = w
        .write_job_from(&Job::thermal(&params(0.01)), None)
        .await
        .expect("first job");
    assert_eq!(first.job_id, job_id_done(&address).await);

    module.with_state(|a| a.sd43900_mm = 0.2);
    let e = w
        .write_job_from(&Job::thermal(&params(0.02)), Some(&params(0.01)))
        .await
        .expect_err("the NC no longer holds 0.01");
    assert!(matches!(e, NcError::NotHeld { .. }), "{e}");

    let next = w
        .write_job_from(&Job::thermal(&params(0.19)), Some(&params(0.2)))
        .await
        .expect("a job from what the NC holds");
    assert_eq!(next.job_id, job_id_done(&address).await);
    assert_eq!(next.job_id, first.job_id + 1);
    stop.cancel();
}
