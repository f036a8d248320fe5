//! `compgate probe` against Modbus TCP devices that misbehave: slow, garbled, a float
//! transmitter reporting its fault value. The devices are a few lines each, on
//! loopback sockets.

#![allow(clippy::unwrap_used)]

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// A read reply's PDU holding `regs`.
fn registers(function: u8, regs: &[u16]) -> Vec<u8> {
    let mut pdu = vec![function, (regs.len() * 2) as u8];
    for r in regs {
        pdu.extend_from_slice(&r.to_be_bytes());
    }
    pdu
}

/// A Modbus TCP device on loopback: each read request (function, first register,
/// count, the request's number from 0) is answered after a delay with the PDU
/// `answer` gives. Returns its address.
async fn device(
    answer: impl Fn(u8, u16, u16, usize) -> (Duration, Vec<u8>) + Send + Sync + 'static,
) -> (String, tokio::task::JoinHandle<()>) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap().to_string();
    let answer = Arc::new(answer);
    let requests = Arc::new(AtomicUsize::new(0));
    let task = tokio::spawn(async move {
        while let Ok((mut s, _)) = listener.accept().await {
            let (answer, requests) = (answer.clone(), requests.clone());
            tokio::spawn(async move {
                // MBAP header (7 bytes) + function, first register, count.
                let mut req = [0u8; 12];
                while s.read_exact(&mut req).await.is_ok() {
                    let start = u16::from_be_bytes([req[8], req[9]]);
                    let count = u16::from_be_bytes([req[10], req[11]]);
                    let n = requests.fetch_add(1, Ordering::SeqCst);
                    let (delay, pdu) = answer(req[7], start, count, n);
                    tokio::time::sleep(delay).await;
                    let mut reply = req[..7].to_vec();
                    reply[4..6].copy_from_slice(&(pdu.len() as u16 + 1).to_be_bytes());
                    reply.extend(pdu);
                    if s.write_all(&reply).await.is_err() {
                        break;
                    }
                }
            });
        }
    });
    (address, task)
}

/// A config of device `d` at `address` with `extra` device keys and the channels
/// `channels` (`name = (register table, address, data type)`).
fn config(address: &str, extra: &str, channels: &[(&str, &str, u16, &str)]) -> String {
    let mut text = format!(
        "[devices.d]\ntransport = \"tcp\"\naddress = \"{address}\"\nunit_id = 1\n{extra}\n"
    );
    for (name, table, at, ty) in channels {
        text.push_str(&format!(
            "[channels.{name}]\ndevice = \"d\"\nregister = \"{table}\"\naddress = {at}\n\
             data_type = \"{ty}\"\nscaling = {{ kind = \"direct\", gain = 1.0, offset_degc = 0.0 }}\n"
        ));
    }
    text
}

async fn probe(text: &str) -> compgate::probe::ProbeReport {
    let cfg = compgate_gateway::config::load_str(text, "probe.toml").expect("config");
    compgate::probe::probe(&cfg, None, None)
        .await
        .expect("probed")
}

// A device answering each read in 0.3 s read good in `probe`, while `run` cut its
// second read every cycle (poll_interval_s = 0.5): the probe says so.
#[tokio::test]
async fn probe_warns_when_a_devices_reads_take_longer_than_its_poll_interval() {
    let (address, dev) = device(|f, _, count, _| {
        (
            Duration::from_millis(300),
            registers(f, &vec![25; usize::from(count)]),
        )
    })
    .await;
    let channels = [("a", "input", 0, "u16"), ("b", "input", 5, "u16")];
    let extra = "timeout_s = 1.0\npoll_interval_s = 0.5\nmax_gap_registers = 0\n";
    let report = probe(&config(&address, extra, &channels)).await;
    let text = &report.text;
    assert!(report.bad.is_empty(), "{text}");
    let warning = text
        .lines()
        .find(|l| l.contains("warning: device d: its 2 read(s) of a poll cycle took 0."))
        .unwrap_or_else(|| panic!("{text}"));
    assert!(
        warning.contains("longer than poll_interval_s = 0.5 s")
            && warning.contains("raise poll_interval_s"),
        "{warning}"
    );
    // Merged into one read (max_gap_registers default 10), one round trip fits.
    let report = probe(&config(&address, "poll_interval_s = 0.5\n", &channels)).await;
    assert!(!report.text.contains("warning"), "{}", report.text);
    dev.abort();
}

// A wrong byte count was "not read, the device did not answer" for the channels after
// it; the refused connection too. Each is worded by its cause.
#[tokio::test]
async fn probe_words_a_failed_read_by_its_cause() {
    // The first request's reply holds one register more than asked for.
    let (address, dev) = device(|f, _, count, n| {
        let count = usize::from(count) + usize::from(n == 0);
        (Duration::ZERO, registers(f, &vec![25; count]))
    })
    .await;
    let channels = [("a", "input", 0, "u16"), ("b", "input", 5, "u16")];
    let report = probe(&config(&address, "", &channels)).await;
    let text = &report.text;
    assert!(
        text.contains(&format!(
            "error      bad reply on {address}: the reply holds 2 registers, the request \
             asked for 1 at 0"
        )),
        "{text}"
    );
    assert!(!text.contains("did not answer"), "{text}");
    assert_eq!(report.bad, ["a"], "{text}");
    dev.abort();

    let closed = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let address = closed.local_addr().unwrap().to_string();
    drop(closed);
    let report = probe(&config(&address, "", &channels)).await;
    let text = &report.text;
    assert_eq!(
        text.matches("not read, the link to the device could not be opened (connect failed:")
            .count(),
        2,
        "{text}"
    );
    assert!(!text.contains("did not answer"), "{text}");
}

// A float transmitter's fault value, NaN (0x7FC00000), was hinted as a byte order:
// "as BADC it reads -3.98 degC: set byte_order = "BADC"".
#[tokio::test]
async fn probe_gives_no_byte_order_hint_for_a_nan() {
    let (address, dev) = device(|f, _, _, _| (Duration::ZERO, registers(f, &[0x7FC0, 0]))).await;
    let report = probe(&config(&address, "", &[("t", "holding", 100, "f32")])).await;
    let text = &report.text;
    assert!(text.contains("registers  0x7FC0 0x0000"), "{text}");
    assert!(
        !text.contains("set byte_order") && !text.contains("<- plausible"),
        "{text}"
    );
    assert!(
        text.contains("not finite: the transmitter reports a fault"),
        "{text}"
    );
    assert_eq!(report.bad, ["t"]);
    dev.abort();
}
