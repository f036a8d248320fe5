//! The field I/O module over real transports: Modbus TCP on loopback and Modbus RTU
//! over a pseudo-terminal pair, spoken to with tokio-modbus's clients.

use std::net::SocketAddr;
use std::time::Duration;

use compgate_plc::field::{
    pty_pair, regs_abcd_to_f32, regs_cdab_to_f32, serve_rtu, CommFault, FieldModule,
    FieldModuleSpec, Profile, SensorFault, TransmitterSpec,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::time::timeout;
use tokio_modbus::client::Context;
use tokio_modbus::prelude::*;
use tokio_util::sync::CancellationToken;

const STEP: Duration = Duration::from_secs(5);

/// Two transmitters: 25 degC on 0..100 and 80 degC on -50..150, with noise.
fn two_channel_spec() -> FieldModuleSpec {
    FieldModuleSpec::new(
        vec![
            TransmitterSpec {
                noise_degc: 0.05,
                ..TransmitterSpec::new(Profile::Constant { degc: 25.0 }, 0.0, 100.0)
            },
            TransmitterSpec {
                noise_degc: 0.02,
                ..TransmitterSpec::new(
                    Profile::Sine {
                        mean_degc: 80.0,
                        amplitude_degc: 1.0,
                        period_s: 3600.0,
                    },
                    -50.0,
                    150.0,
                )
            },
        ],
        42,
    )
}

struct Running {
    module: FieldModule,
    addr: SocketAddr,
    shutdown: CancellationToken,
    task: tokio::task::JoinHandle<Result<(), compgate_plc::field::FieldError>>,
}

async fn start(spec: FieldModuleSpec) -> Running {
    let module = FieldModule::new(spec).expect("valid spec");
    let listener = TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind loopback");
    let addr = listener.local_addr().expect("local addr");
    let shutdown = CancellationToken::new();
    let task = tokio::spawn(module.clone().serve_tcp(listener, shutdown.clone()));
    Running {
        module,
        addr,
        shutdown,
        task,
    }
}

async fn connect(addr: SocketAddr) -> Context {
    timeout(STEP, tcp::connect_slave(addr, Slave(17)))
        .await
        .expect("connect in time")
        .expect("connect")
}

/// Tolerance of a decoded temperature: half an ADC count plus 5 sigma of noise.
fn tolerance_degc(t: &TransmitterSpec, spec: &FieldModuleSpec) -> f64 {
    let count_ma = spec.adc_full_scale_ma / f64::from(spec.adc_full_scale_counts);
    let count_degc = count_ma / 16.0 * (t.range_max_degc - t.range_min_degc);
    0.5 * count_degc + 5.0 * t.noise_degc + 1e-6
}

#[tokio::test]
async fn counts_and_floats_decode_to_the_profile_temperature() {
    let run = start(two_channel_spec()).await;
    let spec = run.module.spec();
    let mut ctx = connect(run.addr).await;
    for _ in 0..20 {
        let counts = ctx.read_input_registers(0, 2).await.unwrap().unwrap();
        let cdab = ctx.read_input_registers(1000, 4).await.unwrap().unwrap();
        let abcd = ctx.read_holding_registers(2000, 4).await.unwrap().unwrap();
        for (i, t) in spec.transmitters.iter().enumerate() {
            let true_degc = run.module.true_temperature_degc(i).unwrap();
            let degc = t.ma_to_degc(spec.counts_to_ma(counts[i]));
            assert!(
                (degc - true_degc).abs() <= tolerance_degc(t, &spec),
                "transmitter {i}: {degc} vs {true_degc}"
            );
            let from_cdab = regs_cdab_to_f32([cdab[2 * i], cdab[2 * i + 1]]);
            let from_abcd = regs_abcd_to_f32([abcd[2 * i], abcd[2 * i + 1]]);
            // Separate reads are separate conversions, so compare each with the truth.
            for v in [from_cdab, from_abcd] {
                assert!(
                    (f64::from(v) - true_degc).abs() <= tolerance_degc(t, &spec) + 1e-4,
                    "transmitter {i}: float {v} vs {true_degc}"
                );
            }
        }
    }
    // Holding registers mirror the input registers.
    run.module.set_sensor_fault(0, SensorFault::Frozen).unwrap();
    let input = ctx.read_input_registers(0, 1).await.unwrap().unwrap();
    let holding = ctx.read_holding_registers(0, 1).await.unwrap().unwrap();
    assert_eq!(input, holding);
    assert_eq!(run.module.requests_served(), 62);
    run.shutdown.cancel();
    run.task.await.unwrap().unwrap();
}

#[tokio::test]
async fn open_sensor_gives_ne43_downscale_counts() {
    let run = start(two_channel_spec()).await;
    let mut ctx = connect(run.addr).await;
    run.module.set_sensor_fault(1, SensorFault::Open).unwrap();
    let counts = ctx.read_input_registers(0, 2).await.unwrap().unwrap();
    // 3.5 mA of 24 mA on 4095 counts = 597.19.
    assert_eq!(counts[1], 597);
    assert!(counts[0] > 1300 && counts[0] < 1430, "{counts:?}");
    run.module.set_sensor_fault(1, SensorFault::Short).unwrap();
    let counts = ctx.read_input_registers(1, 1).await.unwrap().unwrap();
    assert_eq!(counts, vec![3668]); // 21.5 mA
}

#[tokio::test]
async fn bad_requests_get_modbus_exceptions() {
    let run = start(two_channel_spec()).await;
    let mut ctx = connect(run.addr).await;
    assert_eq!(
        ctx.read_input_registers(1, 2).await.unwrap(),
        Err(ExceptionCode::IllegalDataAddress)
    );
    assert_eq!(
        ctx.read_holding_registers(1003, 2).await.unwrap(),
        Err(ExceptionCode::IllegalDataAddress)
    );
    assert_eq!(
        ctx.write_single_register(0, 1).await.unwrap(),
        Err(ExceptionCode::IllegalFunction)
    );
}

#[tokio::test]
async fn exception_fault_returns_that_exception() {
    let run = start(two_channel_spec()).await;
    let mut ctx = connect(run.addr).await;
    run.module
        .set_comm_fault(CommFault::Exception(ExceptionCode::ServerDeviceBusy));
    assert_eq!(
        ctx.read_input_registers(0, 2).await.unwrap(),
        Err(ExceptionCode::ServerDeviceBusy)
    );
    run.module.set_comm_fault(CommFault::None);
    assert!(ctx.read_input_registers(0, 2).await.unwrap().is_ok());
}

#[tokio::test]
async fn drop_connections_closes_sockets_and_reconnect_works_after_clearing() {
    let run = start(two_channel_spec()).await;
    let mut ctx = connect(run.addr).await;
    assert!(ctx.read_input_registers(0, 1).await.unwrap().is_ok());

    run.module.set_comm_fault(CommFault::DropConnections);
    // The open connection is closed by the module: a transport error, not a timeout.
    let res = timeout(STEP, ctx.read_input_registers(0, 1)).await.unwrap();
    assert!(
        matches!(res, Err(tokio_modbus::Error::Transport(_))),
        "{res:?}"
    );
    // New connections are closed at once while the fault is set.
    let mut refused = connect(run.addr).await;
    let res = timeout(STEP, refused.read_input_registers(0, 1))
        .await
        .unwrap();
    assert!(
        matches!(res, Err(tokio_modbus::Error::Transport(_))),
        "{res:?}"
    );

    run.module.set_comm_fault(CommFault::None);
    let mut fresh = connect(run.addr).await;
    assert!(fresh.read_input_registers(0, 1).await.unwrap().is_ok());
}

#[tokio::test]
async fn drop_connections_cuts_a_delayed_reply_short() {
    let run = start(two_channel_spec()).await;
    let mut raw = TcpStream::connect(run.addr).await.unwrap();
    run.module
        .set_comm_fault(CommFault::Delay(Duration::from_secs(30)));
    raw.write_all(&read_input_adu(1, 0, 1)).await.unwrap();
    tokio::time::sleep(Duration::from_millis(100)).await;
    run.module.set_comm_fault(CommFault::DropConnections);
    let mut buf = [0u8; 64];
    // EOF (0 bytes) or a reset, long before the 30 s delay.
    let n = timeout(STEP, raw.read(&mut buf))
        .await
        .unwrap()
        .unwrap_or(0);
    assert_eq!(n, 0);
}

/// A raw Modbus TCP "read input registers" request.
fn read_input_adu(transaction_id: u16, address: u16, quantity: u16) -> Vec<u8> {
    let mut adu = Vec::new();
    adu.extend_from_slice(&transaction_id.to_be_bytes());
    adu.extend_from_slice(&[0, 0, 0, 6, 1, 0x04]);
    adu.extend_from_slice(&address.to_be_bytes());
    adu.extend_from_slice(&quantity.to_be_bytes());
    adu
}

#[tokio::test]
async fn delayed_reply_arrives_after_the_client_gave_up() {
    let run = start(two_channel_spec()).await;
    let delay = Duration::from_millis(400);
    run.module.set_comm_fault(CommFault::Delay(delay));
    let mut raw = TcpStream::connect(run.addr).await.unwrap();
    let sent_at = tokio::time::Instant::now();
    raw.write_all(&read_input_adu(0x1234, 0, 1)).await.unwrap();
    let mut buf = [0u8; 64];
    // A client with a 100 ms timeout gives up...
    assert!(timeout(Duration::from_millis(100), raw.read(&mut buf))
        .await
        .is_err());
    // ...and the reply still comes, late, with the old transaction id.
    let n = timeout(STEP, raw.read_exact(&mut buf[..11]))
        .await
        .unwrap()
        .unwrap();
    assert_eq!(n, 11);
    assert!(sent_at.elapsed() >= delay);
    assert_eq!(&buf[..2], &[0x12, 0x34]);
    assert_eq!(buf[7], 0x04, "function code");
    assert_eq!(run.module.requests_served(), 1);

    // The same through tokio-modbus: a timed-out request leaves a late reply on the
    // connection, which is why the gateway must reconnect after a timeout.
    let mut ctx = connect(run.addr).await;
    assert!(
        timeout(Duration::from_millis(100), ctx.read_input_registers(0, 1))
            .await
            .is_err()
    );
    run.module.set_comm_fault(CommFault::None);
    tokio::time::sleep(delay).await;
    let res = timeout(STEP, ctx.read_input_registers(0, 1)).await.unwrap();
    assert!(
        matches!(
            res,
            Err(tokio_modbus::Error::Protocol(
                ProtocolError::HeaderMismatch { .. }
            ))
        ),
        "the late reply is read as the answer to the next request: {res:?}"
    );
}

#[tokio::test]
async fn silent_module_reads_but_never_answers() {
    let run = start(two_channel_spec()).await;
    let mut ctx = connect(run.addr).await;
    run.module.set_comm_fault(CommFault::Silent);
    assert!(
        timeout(Duration::from_millis(200), ctx.read_input_registers(0, 1))
            .await
            .is_err()
    );
    assert_eq!(run.module.requests_received(), 1);
    assert_eq!(run.module.requests_served(), 0);
    run.module.set_comm_fault(CommFault::None);
    let mut fresh = connect(run.addr).await;
    assert!(fresh.read_input_registers(0, 1).await.unwrap().is_ok());
}

#[tokio::test]
async fn shutdown_stops_the_server_and_closes_connections() {
    let run = start(two_channel_spec()).await;
    let mut ctx = connect(run.addr).await;
    assert!(ctx.read_input_registers(0, 1).await.unwrap().is_ok());
    run.shutdown.cancel();
    timeout(STEP, run.task).await.unwrap().unwrap().unwrap();
    let res = timeout(STEP, ctx.read_input_registers(0, 1)).await.unwrap();
    assert!(res.is_err(), "{res:?}");
}

#[tokio::test(start_paused = true)]
async fn profile_time_is_tokio_time() {
    let module = FieldModule::new(FieldModuleSpec::new(
        vec![TransmitterSpec::new(
            Profile::Steps(vec![(0.0, 20.0), (60.0, 30.0)]),
            0.0,
            100.0,
        )],
        1,
    ))
    .unwrap();
    assert_eq!(module.true_temperature_degc(0), Some(20.0));
    tokio::time::advance(Duration::from_secs(61)).await;
    assert_eq!(module.true_temperature_degc(0), Some(30.0));
    module.set_temperature_override(0, Some(45.0)).unwrap();
    assert_eq!(module.true_temperature_degc(0), Some(45.0));
}

#[tokio::test]
async fn rtu_line_answers_only_its_unit_ids() {
    let constant = |degc: f64| {
        FieldModule::new(FieldModuleSpec::new(
            vec![TransmitterSpec::new(Profile::Constant { degc }, 0.0, 100.0)],
            3,
        ))
        .unwrap()
    };
    let (master, _slave_keepalive, path) = pty_pair().unwrap();
    let shutdown = CancellationToken::new();
    let server = tokio::spawn(serve_rtu(
        vec![(1, constant(25.0)), (2, constant(50.0))],
        master,
        shutdown.clone(),
    ));

    let port = tokio_serial::SerialStream::open(&tokio_serial::new(&path, 19_200)).unwrap();
    let mut ctx = rtu::attach_slave(port, Slave(1));
    let counts = timeout(STEP, ctx.read_input_registers(0, 1))
        .await
        .unwrap()
        .unwrap()
        .unwrap();
    assert_eq!(counts, vec![1365]); // 8 mA
    ctx.set_slave(Slave(2));
    let counts = timeout(STEP, ctx.read_holding_registers(0, 1))
        .await
        .unwrap()
        .unwrap()
        .unwrap();
    assert_eq!(counts, vec![2048]); // 12 mA
    ctx.set_slave(Slave(3));
    assert!(
        timeout(Duration::from_millis(300), ctx.read_input_registers(0, 1))
            .await
            .is_err(),
        "unit 3 is not on the line: no answer"
    );
    // Reopen the port by path (a reconnect) and talk to unit 1 again.
    drop(ctx);
    let port = tokio_serial::SerialStream::open(&tokio_serial::new(&path, 19_200)).unwrap();
    let mut ctx = rtu::attach_slave(port, Slave(1));
    let counts = timeout(STEP, ctx.read_input_registers(0, 1))
        .await
        .unwrap()
        .unwrap()
        .unwrap();
    assert_eq!(counts, vec![1365]);

    shutdown.cancel();
    timeout(STEP, server).await.unwrap().unwrap().unwrap();
}
