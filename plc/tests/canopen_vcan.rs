//! The simulated CANopen node on a real SocketCAN interface, driven by a raw socket
//! as a CANopen master would. Needs `vcan0` (or `VCAN_IF`): ignored in a plain
//! `cargo test`; `tests/vcan/run.sh` runs them natively or in a VM with vcan.

use std::time::Duration;

use compgate_plc::canopen::{CanopenNode, NmtState};
use compgate_plc::field::{FieldModule, FieldModuleSpec, Profile, TransmitterSpec};
use socketcan::tokio::CanSocket;
use socketcan::{CanFrame, EmbeddedFrame, Id, StandardId};
use tokio::time::{timeout, Instant};

fn interface() -> String {
    std::env::var("VCAN_IF").unwrap_or_else(|_| "vcan0".into())
}

fn module(temps_degc: &[f64]) -> FieldModule {
    let transmitters = temps_degc
        .iter()
        .map(|&degc| TransmitterSpec::new(Profile::Constant { degc }, 0.0, 100.0))
        .collect();
    FieldModule::new(FieldModuleSpec::new(transmitters, 1)).expect("module")
}

async fn send(s: &CanSocket, id: u16, data: &[u8]) {
    let frame = CanFrame::new(StandardId::new(id).expect("id"), data).expect("frame");
    s.write_frame(frame).await.expect("send");
}

/// The next frame with COB-ID `id` within `wait`.
async fn expect(s: &CanSocket, id: u16, wait: Duration) -> Option<Vec<u8>> {
    let deadline = Instant::now() + wait;
    loop {
        let frame = tokio::time::timeout_at(deadline, s.read_frame())
            .await
            .ok()?
            .ok()?;
        if let Id::Standard(sid) = frame.id() {
            if sid.as_raw() == id {
                return Some(frame.data().to_vec());
            }
        }
    }
}

async fn upload(s: &CanSocket, node: u8, index: u16, sub: u8) -> Vec<u8> {
    let [lo, hi] = index.to_le_bytes();
    send(s, 0x600 + u16::from(node), &[0x40, lo, hi, sub, 0, 0, 0, 0]).await;
    expect(s, 0x580 + u16::from(node), Duration::from_secs(2))
        .await
        .expect("SDO answer")
}

/// Expected ADC counts for a noiseless transmitter on 0..100 degC, 4095 counts at 24 mA.
fn counts(degc: f64) -> u16 {
    let ma = 4.0 + 16.0 * degc / 100.0;
    (ma / 24.0 * 4095.0).round() as u16
}

#[tokio::test]
#[ignore = "needs vcan0; tests/vcan/run.sh runs it"]
async fn boots_starts_and_answers_sync_and_sdo() {
    let bus = CanSocket::open(&interface()).expect("open vcan");
    let temps = [20.0, 25.0, 30.0, 35.0, 40.0, 45.0];
    let node = CanopenNode::spawn(&interface(), 5, 100, module(&temps)).expect("node");
    // Boot-up, then pre-operational heartbeats.
    assert_eq!(
        expect(&bus, 0x705, Duration::from_secs(2)).await,
        Some(vec![0x00])
    );
    assert_eq!(
        expect(&bus, 0x705, Duration::from_secs(2)).await,
        Some(vec![0x7F])
    );
    // No PDOs before NMT start.
    send(&bus, 0x080, &[]).await;
    assert_eq!(expect(&bus, 0x185, Duration::from_millis(300)).await, None);
    send(&bus, 0x000, &[0x01, 5]).await;
    // A pre-operational heartbeat sent before the node saw the NMT start may still
    // be queued on our socket: the next operational one must follow within 2 s.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(2);
    let mut states = Vec::new();
    let mut operational = false;
    while !operational && tokio::time::Instant::now() < deadline {
        match expect(&bus, 0x705, Duration::from_millis(500)).await {
            Some(d) if d == [0x05] => operational = true,
            Some(d) => states.push(d),
            None => {}
        }
    }
    assert!(
        operational,
        "no operational heartbeat within 2 s: {states:?}"
    );
    assert!(
        states.iter().all(|d| d == &[0x7F]) && states.len() <= 2,
        "heartbeats before operational: {states:?}"
    );
    assert_eq!(node.nmt_state(), NmtState::Operational);

    send(&bus, 0x080, &[]).await;
    let pdo1 = expect(&bus, 0x185, Duration::from_secs(2))
        .await
        .expect("TPDO1");
    let pdo2 = expect(&bus, 0x285, Duration::from_secs(2))
        .await
        .expect("TPDO2");
    assert_eq!(pdo1.len(), 8);
    assert_eq!(pdo2.len(), 4, "transmitters 4 and 5 only");
    let got: Vec<u16> = pdo1
        .chunks(2)
        .chain(pdo2.chunks(2))
        .map(|c| u16::from_le_bytes([c[0], c[1]]))
        .collect();
    let want: Vec<u16> = temps.iter().map(|&t| counts(t)).collect();
    assert_eq!(got, want);

    // SDO: counts, float temperature, heartbeat time, aborts.
    let a = upload(&bus, 5, 0x6401, 2).await;
    assert_eq!(a[..4], [0x4B, 0x01, 0x64, 0x02]);
    assert_eq!(u16::from_le_bytes([a[4], a[5]]), counts(25.0));
    let a = upload(&bus, 5, 0x9130, 3).await;
    assert_eq!(a[0], 0x43);
    let degc = f32::from_le_bytes([a[4], a[5], a[6], a[7]]);
    assert!((degc - 30.0).abs() < 0.05, "{degc}");
    let a = upload(&bus, 5, 0x1017, 0).await;
    assert_eq!(u16::from_le_bytes([a[4], a[5]]), 100);
    let a = upload(&bus, 5, 0x2000, 0).await;
    assert_eq!(a[0], 0x80);
    assert_eq!(u32::from_le_bytes([a[4], a[5], a[6], a[7]]), 0x0602_0000);
    let a = upload(&bus, 5, 0x6401, 7).await;
    assert_eq!(u32::from_le_bytes([a[4], a[5], a[6], a[7]]), 0x0609_0011);
    node.set_sdo_abort(Some((0x6401, 1, 0x0606_0000)));
    let a = upload(&bus, 5, 0x6401, 1).await;
    assert_eq!(
        (a[0], u32::from_le_bytes([a[4], a[5], a[6], a[7]])),
        (0x80, 0x0606_0000)
    );
    let c = node.counters();
    assert!(
        c.syncs >= 2 && c.pdos_sent == 2 && c.sdo_answers == 6,
        "{c:?}"
    );
    node.stop();
}

#[tokio::test]
#[ignore = "needs vcan0; tests/vcan/run.sh runs it"]
async fn silence_emcy_and_reset() {
    let bus = CanSocket::open(&interface()).expect("open vcan");
    let node = CanopenNode::spawn(&interface(), 9, 50, module(&[20.0])).expect("node");
    assert_eq!(
        expect(&bus, 0x709, Duration::from_secs(2)).await,
        Some(vec![0x00])
    );
    node.set_silent(true);
    // Drain what was queued, then nothing for several heartbeat periods.
    let _ = timeout(
        Duration::from_millis(100),
        expect(&bus, 0x709, Duration::from_millis(100)),
    )
    .await;
    assert_eq!(expect(&bus, 0x709, Duration::from_millis(400)).await, None);
    node.set_silent(false);
    assert_eq!(
        expect(&bus, 0x709, Duration::from_secs(2)).await,
        Some(vec![0x7F])
    );
    node.send_emcy(0x4210, 0x09);
    assert_eq!(
        expect(&bus, 0x089, Duration::from_secs(2)).await,
        Some(vec![0x10, 0x42, 0x09, 0, 0, 0, 0, 0])
    );
    send(&bus, 0x000, &[0x81, 0]).await;
    assert_eq!(
        expect(&bus, 0x709, Duration::from_secs(2)).await,
        Some(vec![0x00])
    );
    assert!(CanopenNode::spawn(&interface(), 0, 50, module(&[20.0])).is_err());
    assert!(CanopenNode::spawn("nosuchcan9", 1, 50, module(&[20.0])).is_err());
    node.stop();
}

#[tokio::test]
#[ignore = "needs vcan0; tests/vcan/run.sh runs it"]
async fn segmented_upload_and_the_client_abort() {
    let bus = CanSocket::open(&interface()).expect("open vcan");
    let node = CanopenNode::spawn(&interface(), 7, 0, module(&[20.0])).expect("node");
    let name = compgate_plc::canopen::DEVICE_NAME.as_bytes();
    // Initiate: segmented, size indicated, then segments with alternating toggle.
    let a = upload(&bus, 7, 0x1008, 0).await;
    assert_eq!(a[..4], [0x41, 0x08, 0x10, 0x00]);
    assert_eq!(
        u32::from_le_bytes([a[4], a[5], a[6], a[7]]) as usize,
        name.len()
    );
    let mut got = Vec::new();
    let mut toggle = 0u8;
    loop {
        send(&bus, 0x607, &[0x60 | toggle, 0, 0, 0, 0, 0, 0, 0]).await;
        let seg = expect(&bus, 0x587, Duration::from_secs(2))
            .await
            .expect("segment");
        assert_eq!(seg[0] & 0xE0, 0x00, "upload segment response {seg:02X?}");
        assert_eq!(seg[0] & 0x10, toggle);
        let unused = usize::from((seg[0] >> 1) & 0x07);
        got.extend_from_slice(&seg[1..8 - unused]);
        toggle ^= 0x10;
        if seg[0] & 0x01 != 0 {
            break;
        }
    }
    assert_eq!(got, name);
    // An open segmented upload: another request aborts it, under its own index.
    let _ = upload(&bus, 7, 0x1008, 0).await;
    let a = upload(&bus, 7, 0x1017, 0).await;
    assert_eq!(a[..4], [0x80, 0x08, 0x10, 0x00]);
    assert_eq!(u32::from_le_bytes([a[4], a[5], a[6], a[7]]), 0x0504_0001);
    let a = upload(&bus, 7, 0x1017, 0).await;
    assert_eq!(a[0], 0x4B, "idle again: {a:02X?}");
    // The client's abort closes it and is not answered.
    let _ = upload(&bus, 7, 0x1008, 0).await;
    send(
        &bus,
        0x607,
        &[0x80, 0x08, 0x10, 0x00, 0x12, 0x00, 0x07, 0x06],
    )
    .await;
    assert_eq!(expect(&bus, 0x587, Duration::from_millis(300)).await, None);
    let a = upload(&bus, 7, 0x1017, 0).await;
    assert_eq!(a[0], 0x4B, "idle after the abort: {a:02X?}");
    assert_eq!(node.counters().sdo_aborts_received, 1);
    node.stop();
}
