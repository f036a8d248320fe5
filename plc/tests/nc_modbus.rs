//! The NC axis module over a real loopback socket, driven through the FB3-style
//! handshake of `ncmap` with tokio-modbus's TCP client.

use std::net::SocketAddr;
use std::time::Duration;

use compgate_ncproto::{self as ncmap, var, JobState, JobStatus};
use compgate_plc::nc::{JobFault, NcAxis, NcAxisModule, NcError};
use tokio::net::TcpListener;
use tokio::time::timeout;
use tokio_modbus::client::Context;
use tokio_modbus::prelude::*;
use tokio_util::sync::CancellationToken;

const STEP: Duration = Duration::from_secs(5);

struct Running {
    module: NcAxisModule,
    ctx: Context,
    shutdown: CancellationToken,
    task: tokio::task::JoinHandle<Result<(), NcError>>,
}

/// A referenced axis with MD32750 = 3 at X = 50 mm, served on loopback.
async fn start() -> Running {
    let module = NcAxisModule::new(NcAxis {
        md32750: 3,
        referenced: true,
        position_mm: 50.0,
        ..NcAxis::default()
    });
    let listener = TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind loopback");
    let addr: SocketAddr = listener.local_addr().expect("local addr");
    let shutdown = CancellationToken::new();
    let task = tokio::spawn(module.clone().serve_tcp(listener, shutdown.clone()));
    let ctx = timeout(STEP, tcp::connect(addr))
        .await
        .expect("connect in time")
        .expect("connect");
    Running {
        module,
        ctx,
        shutdown,
        task,
    }
}

/// `JOB_ID`, `NUM_PAIRS` and the pair table as one write-multiple.
fn job_words(job_id: u16, pairs: &[(u16, f64)]) -> Vec<u16> {
    let mut words = vec![job_id, pairs.len() as u16];
    for &(var_id, value) in pairs {
        words.push(var_id);
        words.extend_from_slice(&ncmap::f64_to_regs(value));
    }
    words
}

/// The job block's status registers, `REQ ..= ERROR_INDEX`, and `JOB_ID_DONE`.
#[derive(Debug, PartialEq, Eq)]
struct Status {
    req: u16,
    state: JobState,
    done: u16,
    error: u16,
    status: JobStatus,
    error_index: u16,
    job_id_done: u16,
}

async fn status(ctx: &mut Context) -> Status {
    let r = ctx
        .read_holding_registers(0, ncmap::JOB_BLOCK_LEN)
        .await
        .expect("transport")
        .expect("no exception");
    Status {
        req: r[0],
        state: JobState::from_u16(r[1]).expect("valid STATE"),
        done: r[2],
        error: r[3],
        status: JobStatus::from_u16(r[4]).expect("valid STATUS"),
        error_index: r[5],
        job_id_done: r[usize::from(ncmap::JOB_ID_DONE)],
    }
}

async fn write_job(ctx: &mut Context, job_id: u16, pairs: &[(u16, f64)]) {
    ctx.write_multiple_registers(ncmap::JOB_ID, &job_words(job_id, pairs))
        .await
        .expect("transport")
        .expect("no exception");
}

async fn set_req(ctx: &mut Context, req: u16) {
    ctx.write_single_register(ncmap::REQ, req)
        .await
        .expect("transport")
        .expect("no exception");
}

async fn read_f64(ctx: &mut Context, address: u16) -> f64 {
    let r = ctx
        .read_holding_registers(address, 4)
        .await
        .expect("transport")
        .expect("no exception");
    ncmap::regs_to_f64([r[0], r[1], r[2], r[3]])
}

#[tokio::test]
async fn job_through_the_handshake_is_applied_and_reads_back_bit_exact() {
    let mut run = start().await;
    let ctx = &mut run.ctx;
    let idle = status(ctx).await;
    assert_eq!(idle.state, JobState::Idle);

    // Values that are not exact in binary, to prove the bit-exact path.
    let pairs = [
        (var::SD43900, 0.1),
        (var::SD43920, 10.0),
        (var::SD43910, 0.0001),
    ];
    write_job(ctx, 7, &pairs).await;
    set_req(ctx, 1).await;
    let done = status(ctx).await;
    assert_eq!(
        done,
        Status {
            req: 1,
            state: JobState::Done,
            done: 1,
            error: 0,
            status: JobStatus::Ok,
            error_index: 0,
            job_id_done: 7,
        }
    );
    for (address, value) in [
        (ncmap::RB_SD43900, 0.1_f64),
        (ncmap::RB_SD43920, 10.0),
        (ncmap::RB_SD43910, 0.0001),
    ] {
        assert_eq!(read_f64(ctx, address).await.to_bits(), value.to_bits());
    }
    // The whole read-back block in one read, MD32750 and referenced included.
    let rb = ctx
        .read_holding_registers(ncmap::READBACK, ncmap::READBACK_LEN)
        .await
        .unwrap()
        .unwrap();
    assert_eq!(rb[usize::from(ncmap::RB_MD32750 - ncmap::READBACK)], 3);
    assert_eq!(rb[usize::from(ncmap::RB_REFERENCED - ncmap::READBACK)], 1);

    // REQ = 0 acknowledges; JOB_ID_DONE stays.
    set_req(ctx, 0).await;
    let acked = status(ctx).await;
    assert_eq!(acked.state, JobState::Idle);
    assert_eq!((acked.done, acked.error, acked.job_id_done), (0, 0, 7));
    assert_eq!(run.module.jobs_executed(), 1);

    // The IPO loop slews the applied compensation to 0.104 mm at X = 50 mm.
    let target_mm = read_f64(ctx, ncmap::RB_TARGET_COMP).await;
    assert!((target_mm - 0.104).abs() < 1e-12);
    let settled = timeout(STEP, async {
        loop {
            if read_f64(ctx, ncmap::RB_APPLIED_COMP).await == target_mm {
                break;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
    assert!(settled.is_ok(), "applied compensation never reached target");
    assert_eq!(run.module.state().applied_comp_mm, target_mm);

    run.shutdown.cancel();
    run.task.await.unwrap().unwrap();
}

#[tokio::test]
async fn refused_jobs_report_status_and_index_and_change_nothing() {
    let mut run = start().await;
    let ctx = &mut run.ctx;
    write_job(ctx, 1, &[(var::SD43900, 0.05)]).await;
    set_req(ctx, 1).await;
    set_req(ctx, 0).await;
    // The IPO loop slews the applied compensation over a few cycles, longer on a loaded
    // machine: compare with the axis at rest.
    let settled = timeout(STEP, async {
        while run.module.state().applied_comp_mm != 0.05 {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await;
    assert!(
        settled.is_ok(),
        "applied compensation never reached 0.05 mm"
    );
    let before = run.module.state();

    // (pairs, expected STATUS, expected ERROR_INDEX)
    type Case = (Vec<(u16, f64)>, JobStatus, u16);
    let cases: Vec<Case> = vec![
        (
            vec![(var::SD43900, 0.2), (var::MD32750, 1.0)],
            JobStatus::AccessDenied,
            2,
        ),
        (vec![], JobStatus::InvalidAddress, 0),
        (
            vec![(var::SD43900, 0.2), (var::SD43910, 0.0), (4711, 1.0)],
            JobStatus::ObjectDoesNotExist,
            3,
        ),
        (vec![(var::SD43910, 0.5)], JobStatus::ValueOutOfRange, 1),
    ];
    for (n, (pairs, code, index)) in cases.iter().enumerate() {
        let job_id = 100 + n as u16;
        write_job(ctx, job_id, pairs).await;
        set_req(ctx, 1).await;
        let s = status(ctx).await;
        assert_eq!(
            (
                s.state,
                s.done,
                s.error,
                s.status,
                s.error_index,
                s.job_id_done
            ),
            (JobState::Error, 0, 1, *code, *index, job_id),
            "{pairs:?}"
        );
        set_req(ctx, 0).await;
        let s = status(ctx).await;
        assert_eq!(
            (s.state, s.error, s.status),
            (JobState::Idle, 0, JobStatus::Ok)
        );
    }
    // A pair count above 8 is refused too (the table has room for 8).
    ctx.write_single_register(ncmap::NUM_PAIRS, 9)
        .await
        .unwrap()
        .unwrap();
    set_req(ctx, 1).await;
    let s = status(ctx).await;
    assert_eq!((s.status, s.error_index), (JobStatus::InvalidAddress, 0));
    set_req(ctx, 0).await;

    assert_eq!(run.module.state(), before, "refused jobs changed the axis");
    assert_eq!(run.module.jobs_executed(), 6);
    assert_eq!(run.module.jobs_refused(), 5);
}

#[tokio::test]
async fn busy_module_ignores_a_second_req_edge_and_keeps_the_latched_job() {
    let mut run = start().await;
    let ctx = &mut run.ctx;
    run.module.set_job_fault(JobFault::NeverFinish);
    write_job(ctx, 1, &[(var::SD43900, 0.25)]).await;
    set_req(ctx, 1).await;
    assert_eq!(status(ctx).await.state, JobState::Busy);

    // A second edge with a different job while busy, and new parameters.
    set_req(ctx, 0).await;
    write_job(ctx, 2, &[(var::SD43900, 0.5)]).await;
    set_req(ctx, 1).await;
    tokio::time::sleep(Duration::from_millis(50)).await;
    let s = status(ctx).await;
    assert_eq!((s.state, s.done, s.error), (JobState::Busy, 0, 0));
    assert_eq!(run.module.jobs_executed(), 0);
    assert_eq!(run.module.state().sd43900_mm, 0.0);

    // Clearing the fault lets the stuck job finish: job 1, not job 2.
    run.module.set_job_fault(JobFault::None);
    let s = status(ctx).await;
    assert_eq!((s.state, s.done, s.job_id_done), (JobState::Done, 1, 1));
    assert_eq!(run.module.state().sd43900_mm, 0.25);
    // REQ is still 1: no new edge, so acknowledging needs REQ = 0.
    set_req(ctx, 1).await;
    assert_eq!(status(ctx).await.state, JobState::Done);
    set_req(ctx, 0).await;
    assert_eq!(status(ctx).await.state, JobState::Idle);
    assert_eq!(run.module.jobs_executed(), 1);
}

#[tokio::test]
async fn delayed_job_is_busy_for_a_while_then_done() {
    let mut run = start().await;
    let ctx = &mut run.ctx;
    run.module
        .set_job_fault(JobFault::Delay(Duration::from_millis(300)));
    write_job(ctx, 9, &[(var::SD43920, 12.5)]).await;
    let raised_at = tokio::time::Instant::now();
    set_req(ctx, 1).await;
    assert_eq!(status(ctx).await.state, JobState::Busy);
    assert_eq!(run.module.sd43900_and_last_done(), (0.0, None));
    let finished = timeout(STEP, async {
        loop {
            let s = status(ctx).await;
            if s.state != JobState::Busy {
                return s;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await
    .expect("the delayed job never finished");
    assert!(raised_at.elapsed() >= Duration::from_millis(300));
    assert_eq!((finished.state, finished.job_id_done), (JobState::Done, 9));
    assert_eq!(run.module.state().sd43920_mm, 12.5);
    // The instant the job took effect: not before its delay, not after it was seen.
    let done_at = run.module.sd43900_and_last_done().1.expect("a job done");
    assert!(done_at >= raised_at + Duration::from_millis(300));
    assert!(done_at <= tokio::time::Instant::now());
}

#[tokio::test]
async fn register_access_outside_the_map_is_refused() {
    let mut run = start().await;
    let ctx = &mut run.ctx;
    const ILLEGAL_ADDRESS: ExceptionCode = ExceptionCode::IllegalDataAddress;
    // Read-only registers of the job block, the read-back block, unmapped registers.
    assert_eq!(
        ctx.write_single_register(ncmap::STATE, 0).await.unwrap(),
        Err(ILLEGAL_ADDRESS)
    );
    assert_eq!(
        ctx.write_single_register(ncmap::JOB_ID_DONE, 0)
            .await
            .unwrap(),
        Err(ILLEGAL_ADDRESS)
    );
    assert_eq!(
        ctx.write_multiple_registers(ncmap::REQ, &[1, 0, 0, 0, 0, 0, 5])
            .await
            .unwrap(),
        Err(ILLEGAL_ADDRESS),
        "a write spanning REQ and JOB_ID covers read-only registers"
    );
    assert_eq!(
        ctx.write_multiple_registers(ncmap::RB_SD43900, &ncmap::f64_to_regs(1.0))
            .await
            .unwrap(),
        Err(ILLEGAL_ADDRESS)
    );
    assert_eq!(
        ctx.write_single_register(200, 1).await.unwrap(),
        Err(ILLEGAL_ADDRESS)
    );
    assert_eq!(
        ctx.read_holding_registers(40, 20).await.unwrap(),
        Err(ILLEGAL_ADDRESS)
    );
    assert_eq!(
        ctx.read_holding_registers(ncmap::READBACK, ncmap::READBACK_LEN + 1)
            .await
            .unwrap(),
        Err(ILLEGAL_ADDRESS)
    );
    assert_eq!(
        ctx.read_input_registers(0, 1).await.unwrap(),
        Err(ExceptionCode::IllegalFunction)
    );
    // Nothing of the above started or changed anything.
    let s = status(ctx).await;
    assert_eq!((s.req, s.state), (0, JobState::Idle));
    assert_eq!(run.module.state().sd43900_mm, 0.0);
}

#[tokio::test(start_paused = true)]
async fn ipo_loop_runs_in_tokio_time() {
    let module = NcAxisModule::new(NcAxis {
        md32750: 1,
        referenced: true,
        // 0.01 x 6000 mm/min = 1 mm/s = 0.004 mm per 4 ms cycle.
        max_ax_velo_mm_per_min: 6000.0,
        ..NcAxis::default()
    });
    module.with_state(|axis| axis.execute_job(&[(var::SD43900, 0.099)]).unwrap());
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let shutdown = CancellationToken::new();
    let task = tokio::spawn(module.clone().serve_tcp(listener, shutdown.clone()));
    // 12 cycles in 50 ms; 25 cycles (24.75 needed) land on the target by 102 ms.
    tokio::time::sleep(Duration::from_millis(50)).await;
    assert!((module.state().applied_comp_mm - 0.048).abs() < 1e-12);
    tokio::time::sleep(Duration::from_millis(52)).await;
    assert_eq!(module.state().applied_comp_mm, 0.099);
    shutdown.cancel();
    task.await.unwrap().unwrap();
}

#[tokio::test(start_paused = true)]
async fn two_serve_tasks_share_one_ipo_loop() {
    let module = NcAxisModule::new(NcAxis {
        md32750: 1,
        referenced: true,
        max_ax_velo_mm_per_min: 6000.0, // 0.004 mm per cycle
        ..NcAxis::default()
    });
    module.with_state(|axis| axis.execute_job(&[(var::SD43900, 0.5)]).unwrap());
    let first_stop = CancellationToken::new();
    let second_stop = CancellationToken::new();
    let first = tokio::spawn(module.clone().serve_tcp(
        TcpListener::bind("127.0.0.1:0").await.unwrap(),
        first_stop.clone(),
    ));
    let second = tokio::spawn(module.clone().serve_tcp(
        TcpListener::bind("127.0.0.1:0").await.unwrap(),
        second_stop.clone(),
    ));
    tokio::time::sleep(Duration::from_millis(42)).await;
    // 10 cycles, not 20: the axis does not run twice as fast.
    assert!((module.state().applied_comp_mm - 0.040).abs() < 1e-12);
    first_stop.cancel();
    first.await.unwrap().unwrap();
    // The standby task takes over within its 100 ms poll.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let applied_mm = module.state().applied_comp_mm;
    assert!(applied_mm > 0.3 && applied_mm <= 0.5, "{applied_mm}");
    second_stop.cancel();
    second.await.unwrap().unwrap();
}

#[tokio::test]
async fn refuse_fault_refuses_valid_jobs_until_cleared() {
    let mut run = start().await;
    let ctx = &mut run.ctx;
    run.module
        .set_job_fault(JobFault::Refuse(JobStatus::AccessDenied));
    write_job(ctx, 3, &[(var::SD43900, 0.05)]).await;
    set_req(ctx, 1).await;
    let s = status(ctx).await;
    assert_eq!(
        (s.state, s.error, s.status, s.error_index, s.job_id_done),
        (JobState::Error, 1, JobStatus::AccessDenied, 0, 3)
    );
    assert_eq!(run.module.state().sd43900_mm, 0.0);
    set_req(ctx, 0).await;
    run.module.set_job_fault(JobFault::None);
    set_req(ctx, 1).await;
    let s = status(ctx).await;
    assert_eq!((s.state, s.done), (JobState::Done, 1));
    assert_eq!(run.module.state().sd43900_mm, 0.05);
}
