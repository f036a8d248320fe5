//! The servo block of the NC axis module over a real loopback socket: a move programme,
//! the servo trace armed on a scale threshold, and the paged trace upload.

use std::net::SocketAddr;
use std::time::Duration;

use compgate_ncproto as ncmap;
use compgate_plc::axis::{AxisParams, ProgramState, TraceState};
use compgate_plc::nc::{NcAxis, NcAxisModule};
use tokio::net::TcpListener;
use tokio::time::timeout;
use tokio_modbus::client::Context;
use tokio_modbus::prelude::*;
use tokio_util::sync::CancellationToken;

const STEP: Duration = Duration::from_secs(5);

async fn start(params: AxisParams) -> (NcAxisModule, Context, CancellationToken) {
    let module = NcAxisModule::new(NcAxis::default());
    module.set_servo(params);
    module.set_sim_speed(2000.0);
    let listener = TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind loopback");
    let addr: SocketAddr = listener.local_addr().expect("local addr");
    let shutdown = CancellationToken::new();
    tokio::spawn(module.clone().serve_tcp(listener, shutdown.clone()));
    let ctx = timeout(STEP, tcp::connect(addr))
        .await
        .expect("connect in time")
        .expect("connect");
    (module, ctx, shutdown)
}

async fn read(ctx: &mut Context, address: u16, count: u16) -> Vec<u16> {
    timeout(STEP, ctx.read_holding_registers(address, count))
        .await
        .expect("in time")
        .expect("transport")
        .expect("no exception")
}

async fn write(ctx: &mut Context, address: u16, words: &[u16]) {
    timeout(STEP, ctx.write_multiple_registers(address, words))
        .await
        .expect("in time")
        .expect("transport")
        .expect("no exception");
}

fn f64_at(regs: &[u16], at: usize) -> f64 {
    ncmap::regs_to_f64([regs[at], regs[at + 1], regs[at + 2], regs[at + 3]])
}

fn program_words(steps: &[(f64, f64, f64)]) -> Vec<u16> {
    let mut words = vec![1, steps.len() as u16];
    for &(target_mm, feed, dwell_s) in steps {
        for v in [target_mm, feed, dwell_s] {
            words.extend_from_slice(&ncmap::f64_to_regs(v));
        }
    }
    words
}

#[tokio::test]
async fn programme_and_trace_over_modbus() {
    let backlash_mm = 0.03;
    let (module, mut ctx, shutdown) = start(AxisParams {
        backlash_mm,
        encoder_noise_mm: 0.0,
        scale_noise_mm: 0.0,
        ..AxisParams::default()
    })
    .await;
    // Trace: 4 ms, 6 s, trigger when the scale rises through 4.999 mm, no delay.
    let mut cfg = vec![1u16, 0];
    for v in [0.004, 6.0, 4.999, 0.0] {
        cfg.extend_from_slice(&ncmap::f64_to_regs(v));
    }
    cfg.push(1); // TR_CMD = arm
    write(&mut ctx, ncmap::TR_TRIGGER, &cfg).await;
    let status = read(&mut ctx, ncmap::TR_STATE, 2).await;
    assert_eq!(status, [TraceState::Armed as u16, 0]);
    // Programme and MV_CMD = 1 in one write.
    let words = program_words(&[(5.0, 1000.0, 1.0), (10.0, 1000.0, 1.0), (7.0, 1000.0, 1.0)]);
    write(&mut ctx, ncmap::MV_CMD, &words).await;
    assert_eq!(
        read(&mut ctx, ncmap::MV_CMD, 1).await,
        [0],
        "a command reads 0"
    );
    let finished = timeout(Duration::from_secs(20), async {
        loop {
            let s = read(&mut ctx, ncmap::SERVO_STATUS, ncmap::SERVO_STATUS_LEN).await;
            let reg = |a: u16| s[usize::from(a - ncmap::SERVO_STATUS)];
            if reg(ncmap::MV_STATE) == ProgramState::Done as u16
                && reg(ncmap::TR_STATE) == TraceState::Complete as u16
            {
                return s;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await
    .expect("programme and trace finish");
    let reg = |a: u16| finished[usize::from(a - ncmap::SERVO_STATUS)];
    let count = ncmap::regs_to_u32([reg(ncmap::TR_COUNT), reg(ncmap::TR_COUNT + 1)]);
    assert_eq!(count, 1500);
    let at = |a: u16| usize::from(a - ncmap::SERVO_STATUS);
    assert_eq!(f64_at(&finished, at(ncmap::AXIS_MAX)), 1000.0);
    assert_eq!(f64_at(&finished, at(ncmap::SERVO_CYCLE_S)), 0.001);
    assert!((f64_at(&finished, at(ncmap::SCALE_POS)) - 7.0).abs() < 1e-6);
    // Upload every page and compare with the simulator's own buffer.
    let mut samples = Vec::new();
    let pages = count.div_ceil(u32::from(ncmap::TR_PAGE_SAMPLES));
    for page in 0..pages {
        write(&mut ctx, ncmap::TR_PAGE, &[page as u16]).await;
        let w = read(&mut ctx, ncmap::TR_WINDOW, ncmap::TR_WINDOW_LEN).await;
        for k in 0..usize::from(ncmap::TR_PAGE_SAMPLES) {
            let enc = f64_at(&w, 8 * k);
            let scale = f64_at(&w, 8 * k + 4);
            if enc.is_nan() {
                continue;
            }
            samples.push((enc, scale));
        }
    }
    assert_eq!(samples, module.with_servo(|s| s.trace().to_vec()));
    // Standing after a negative move: the motor is half the gap below the table.
    let (enc, scale) = samples[samples.len() - 1];
    assert!((scale - 7.0).abs() < 1e-6);
    assert!((enc - (7.0 - backlash_mm / 2.0)).abs() < 1e-6, "{enc}");
    shutdown.cancel();
}

#[tokio::test]
async fn bad_programmes_and_traces_are_refused_with_a_code() {
    let (_module, mut ctx, shutdown) = start(AxisParams::default()).await;
    write(
        &mut ctx,
        ncmap::MV_CMD,
        &program_words(&[(5000.0, 1000.0, 1.0)]),
    )
    .await;
    assert_eq!(read(&mut ctx, ncmap::MV_STATE, 2).await, [3, 2]);
    write(&mut ctx, ncmap::MV_CMD, &program_words(&[(5.0, 1e6, 1.0)])).await;
    assert_eq!(read(&mut ctx, ncmap::MV_STATE, 2).await, [3, 3]);
    // Period of 1.5 servo cycles.
    let mut cfg = vec![0u16, 0];
    for v in [0.0015, 1.0, 0.0, 0.0] {
        cfg.extend_from_slice(&ncmap::f64_to_regs(v));
    }
    cfg.push(1);
    write(&mut ctx, ncmap::TR_TRIGGER, &cfg).await;
    assert_eq!(read(&mut ctx, ncmap::TR_STATE, 2).await, [0, 6]);
    // Unknown trigger code.
    cfg[0] = 7;
    write(&mut ctx, ncmap::TR_TRIGGER, &cfg).await;
    assert_eq!(read(&mut ctx, ncmap::TR_STATE, 2).await, [0, 9]);
    // Status registers are read-only; a write spanning the gap is refused.
    assert_eq!(
        ctx.write_single_register(ncmap::MV_STATE, 0).await.unwrap(),
        Err(ExceptionCode::IllegalDataAddress)
    );
    assert_eq!(
        ctx.write_multiple_registers(ncmap::MV_WRITABLE_END - 1, &[0, 0])
            .await
            .unwrap(),
        Err(ExceptionCode::IllegalDataAddress)
    );
    assert_eq!(
        ctx.read_holding_registers(ncmap::TR_WINDOW, ncmap::TR_WINDOW_LEN + 1)
            .await
            .unwrap(),
        Err(ExceptionCode::IllegalDataAddress)
    );
    shutdown.cancel();
}
