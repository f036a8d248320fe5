//! `compgate probe` (and `run`, where the fault is in how devices share a peer) against
//! Modbus TCP devices that misbehave: slow, garbled, a float transmitter reporting its
//! fault value, a unit missing behind a TCP-to-RTU gateway. The devices are a few
//! lines each, on loopback sockets.

#![allow(clippy::unwrap_used)]

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

use compgate_core::channel::Quality;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

mod common;

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

// A replacement module that sends each register's low byte first: 24.6 degC in
// tenths (0x00F6) arrives as 0xF600. The probe hinted "as 0.001 degC counts it reads
// -2.560 degC: set scaling gain = 0.001", a plausible, wrong, good reading (review W).
// It names the byte order now, and no scaling.
#[tokio::test]
async fn probe_names_a_swapped_byte_order_of_a_16_bit_register() {
    let (address, dev) = device(|f, _, _, _| (Duration::ZERO, registers(f, &[0xF600]))).await;
    let text =
        config(&address, "", &[("t", "input", 0, "i16")]).replace("gain = 1.0", "gain = 0.1");
    let report = probe(&text).await;
    let text = &report.text;
    assert!(
        text.contains(
            "hint       as BADC (low byte first) it reads 24.60 degC: set byte_order = \"BADC\""
        ),
        "{text}"
    );
    assert!(!text.contains("scaling gain"), "{text}");
    // As BADC it reads good.
    let swapped = config(&address, "", &[("t", "input", 0, "i16")])
        .replace("gain = 1.0", "gain = 0.1")
        .replace(
            "data_type = \"i16\"",
            "data_type = \"i16\"\nbyte_order = \"BADC\"",
        );
    let report = probe(&swapped).await;
    assert!(report.bad.is_empty(), "{}", report.text);
    assert!(!report.text.contains("hint"), "{}", report.text);
    dev.abort();
}

// A module whose map has holes answers each channel's own read, and refuses `run`'s
// read across the hole with 0x02: `probe` showed every channel good, and `run` failed
// them all every cycle. Now the probe makes `run`'s merged reads too and names the key.
#[tokio::test]
async fn probe_makes_the_merged_reads_of_run_and_names_a_refused_one() {
    let (address, dev) = device(|f, _, count, _| {
        let pdu = if count == 1 {
            registers(f, &[25])
        } else {
            vec![f | 0x80, 0x02]
        };
        (Duration::ZERO, pdu)
    })
    .await;
    let channels = [
        ("a", "input", 0, "u16"),
        ("b", "input", 1, "u16"),
        ("c", "input", 8, "u16"),
        ("far", "input", 100, "u16"),
    ];
    let report = probe(&config(&address, "", &channels)).await;
    let text = &report.text;
    assert!(
        text.contains(
            "warning: device d: `run` reads a, b, c in one request (9 registers from 0), \
             and the module refused it: device exception 0x02 illegal data address: the \
             read merges channels across registers 2..=7, which no channel uses"
        ) && text.contains("set devices.d.max_gap_registers = 0"),
        "{text}"
    );
    assert_eq!(report.bad, ["a", "b", "c"], "{text}");
    // As configured to fit the module, nothing is refused.
    let report = probe(&config(
        &address,
        "max_gap_registers = 0\nmax_read_registers = 1",
        &channels,
    ))
    .await;
    assert!(report.bad.is_empty(), "{}", report.text);
    dev.abort();
}

/// The gateway in-process on the config `text`, reloaded with what `reloads` sends:
/// its status, its stopper and its task.
fn run(
    text: &str,
    reloads: Option<tokio::sync::mpsc::Receiver<compgate_gateway::config::Config>>,
) -> (
    tokio::sync::watch::Receiver<compgate_gateway::runtime::Status>,
    tokio_util::sync::CancellationToken,
    tokio::task::JoinHandle<()>,
) {
    let cfg = compgate_gateway::config::load_str(text, "units.toml").expect("config");
    let (tx, status) = tokio::sync::watch::channel(Default::default());
    let shutdown = tokio_util::sync::CancellationToken::new();
    let sd = shutdown.clone();
    let gw = tokio::spawn(async move {
        let hooks = compgate_gateway::runtime::Hooks {
            reload: reloads,
            ..Default::default()
        };
        compgate_gateway::runtime::run_with(&cfg, sd, tx, hooks)
            .await
            .expect("runs");
    });
    (status, shutdown, gw)
}

// Two units behind one TCP-to-RTU gateway, which serves one request at a time on its
// serial line: unit 1 answers in 5 ms, unit 2 is absent and the gateway answers 0x0B
// after 100 ms. Unit 2, asked every cycle, held the line so that unit 1's requests
// (timeout_s 0.08) failed in about half its cycles, and it showed as link up (an
// exception counted as an answer). Now 0x0A/0x0B mean the unit did not answer, and a
// silent unit at an address other devices share is asked only when its backoff allows.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_absent_unit_behind_a_tcp_gateway_does_not_hold_up_the_present_one() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap().to_string();
    let line = Arc::new(tokio::sync::Mutex::new(()));
    let peer = tokio::spawn(async move {
        while let Ok((mut s, _)) = listener.accept().await {
            let line = line.clone();
            tokio::spawn(async move {
                let mut req = [0u8; 12];
                while s.read_exact(&mut req).await.is_ok() {
                    let count = u16::from_be_bytes([req[10], req[11]]);
                    let pdu = {
                        let _on_the_line = line.lock().await;
                        if req[6] == 1 {
                            tokio::time::sleep(Duration::from_millis(5)).await;
                            registers(req[7], &vec![1775; usize::from(count)])
                        } else {
                            tokio::time::sleep(Duration::from_millis(100)).await;
                            vec![req[7] | 0x80, 0x0B]
                        }
                    };
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
    // Unit 1 may time out behind unit 2 in the cycles before unit 2 is demoted: it is
    // demoted itself only after 5 failed cycles in a row, so that two such collisions
    // (the first two cycles, in a loaded run) do not back it off for a second.
    let device = |name: &str, unit: u8, timeout_s: f64, degrade: u32| {
        format!(
            "[devices.{name}]\ntransport = \"tcp\"\naddress = \"{address}\"\nunit_id = {unit}\n\
             timeout_s = {timeout_s}\npoll_interval_s = 0.1\nretries = 0\ndegrade_after_cycles = {degrade}\n\
             backoff_initial_s = 1.0\nbackoff_max_s = 4.0\n\n[channels.T_{name}]\ndevice = \"{name}\"\n\
             register = \"input\"\naddress = 0\ndata_type = \"u16\"\n\
             scaling = {{ kind = \"direct\", gain = 0.01, offset_degc = 0.0 }}\n\n"
        )
    };
    let text = format!(
        "[gateway]\nstatus_interval_s = 0.05\n\n{}{}",
        device("here", 1, 0.08, 5),
        device("gone", 2, 0.5, 2)
    );
    let (mut status, shutdown, gw) = run(&text, None);
    let of = |s: &compgate_gateway::runtime::Status, name: &str| {
        s.devices.iter().find(|d| d.name == name).cloned().unwrap()
    };
    let s = common::wait_status(&mut status, 20.0, "60 cycles of unit 1", |s| {
        of(s, "here").cycles >= 60
    })
    .await;
    shutdown.cancel();
    gw.await.unwrap();
    peer.abort();
    let (here, gone) = (of(&s, "here"), of(&s, "gone"));
    let failed: u64 = here.errors.values().sum();
    assert!(
        failed <= 8,
        "unit 1 failed {failed} of {} requests: {:?}",
        here.cycles,
        here.errors
    );
    assert!(!gone.link_up, "{gone:?}");
    let error = gone.last_error.unwrap_or_default();
    assert!(
        error.contains("0x0B gateway target device failed to respond"),
        "{error}"
    );
}

// A replacement module that answers 0 until its inputs have settled (8 s on the
// reviewer's): 0.0 degC was a good reading, and the axis wrote compensation for it
// for about 25 s (review W). With settle_s its values after a connect are no data.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_module_that_answers_0_until_it_settles_gives_no_reading_during_settle_s() {
    let started = std::time::Instant::now();
    let (address, dev) = device(move |f, _, _, _| {
        let raw: u16 = if started.elapsed() < Duration::from_millis(800) {
            0
        } else {
            245
        };
        (Duration::ZERO, registers(f, &[raw]))
    })
    .await;
    let text = format!(
        "[gateway]\nstatus_interval_s = 0.05\n\n{}",
        config(
            &address,
            "poll_interval_s = 0.05\nsettle_s = 1.2\n",
            &[("t", "input", 0, "i16")]
        )
        .replace("gain = 1.0", "gain = 0.1")
    );
    let (mut status, shutdown, gw) = run(&text, None);
    let mut seen = Vec::new();
    let end = tokio::time::Instant::now() + Duration::from_secs(4);
    while tokio::time::Instant::now() < end {
        let _ = tokio::time::timeout(Duration::from_millis(100), status.changed()).await;
        let s = status.borrow_and_update().clone();
        if let Some(c) = s.channels.first() {
            seen.push((c.reading.quality, c.reading.value_degc));
        }
    }
    shutdown.cancel();
    gw.await.unwrap();
    dev.abort();
    assert!(
        !seen
            .iter()
            .any(|(q, v)| *q == Quality::Good && *v == Some(0.0)),
        "a settling 0 was read good: {seen:?}"
    );
    let last = seen.last().copied();
    assert!(
        last.is_some_and(|(q, v)| q == Quality::Good && v.is_some_and(|v| (v - 24.5).abs() < 1e-9)),
        "{seen:?}"
    );
}

/// A TCP-to-RTU gateway on loopback that takes one connection at a time (a second
/// client is closed at once, as small gateways do) and serves its requests one after
/// the other on its serial line: a unit answers its registers with 1000 + its unit id
/// after 5 ms; for a unit in `absent` it answers 0x0B after `response_timeout`, its
/// own timeout. Returns its address, the connections it accepted and its task.
async fn one_connection_gateway(
    absent: &'static [u8],
    response_timeout: Duration,
) -> (String, Arc<AtomicUsize>, tokio::task::JoinHandle<()>) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap().to_string();
    let accepted = Arc::new(AtomicUsize::new(0));
    let count = accepted.clone();
    let peer = tokio::spawn(async move {
        let open = Arc::new(AtomicUsize::new(0));
        while let Ok((mut s, _)) = listener.accept().await {
            if open.load(Ordering::SeqCst) > 0 {
                drop(s);
                continue;
            }
            count.fetch_add(1, Ordering::SeqCst);
            open.fetch_add(1, Ordering::SeqCst);
            let open = open.clone();
            tokio::spawn(async move {
                let mut req = [0u8; 12];
                while s.read_exact(&mut req).await.is_ok() {
                    let n = u16::from_be_bytes([req[10], req[11]]);
                    let pdu = if absent.contains(&req[6]) {
                        tokio::time::sleep(response_timeout).await;
                        vec![req[7] | 0x80, 0x0B]
                    } else {
                        tokio::time::sleep(Duration::from_millis(5)).await;
                        registers(req[7], &vec![1000 + u16::from(req[6]); usize::from(n)])
                    };
                    let mut reply = req[..7].to_vec();
                    reply[4..6].copy_from_slice(&(pdu.len() as u16 + 1).to_be_bytes());
                    reply.extend(pdu);
                    if s.write_all(&reply).await.is_err() {
                        break;
                    }
                }
                open.fetch_sub(1, Ordering::SeqCst);
            });
        }
    });
    (address, accepted, peer)
}

// Three units behind a TCP-to-RTU gateway that takes one connection at a time (a
// second client is closed at once, as small gateways do). Each device opened its own
// connection, so all but one were closed every cycle: two of three units never read.
// Devices at one address now share one connection, as units on one serial line do,
// and a reload that changes one unit and adds another keeps it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn units_behind_a_gateway_that_takes_one_connection_share_it() {
    let (address, accepted, peer) = one_connection_gateway(&[], Duration::ZERO).await;
    let units = |units: &[(u8, f64)]| {
        let text: String = units
            .iter()
            .map(|(unit, poll_s)| {
                format!(
                    "[devices.u{unit}]\ntransport = \"tcp\"\naddress = \"{address}\"\nunit_id = {unit}\n\
                     timeout_s = 1.0\npoll_interval_s = {poll_s}\n\n[channels.T_u{unit}]\ndevice = \"u{unit}\"\n\
                     register = \"input\"\naddress = 0\ndata_type = \"u16\"\n\
                     scaling = {{ kind = \"direct\", gain = 0.01, offset_degc = 0.0 }}\n\n"
                )
            })
            .collect();
        format!("[gateway]\nstatus_interval_s = 0.05\n\n{text}")
    };
    let (reload, reloads) = tokio::sync::mpsc::channel(1);
    let (mut status, shutdown, gw) = run(&units(&[(1, 0.05), (2, 0.05), (3, 0.05)]), Some(reloads));
    common::wait_status(&mut status, 20.0, "20 cycles of each unit", |s| {
        s.devices.iter().all(|d| d.cycles >= 20)
    })
    .await;
    let changed = units(&[(1, 0.05), (2, 0.1), (3, 0.05), (4, 0.05)]);
    reload
        .send(compgate_gateway::config::load_str(&changed, "units.toml").expect("config"))
        .await
        .unwrap();
    let s = common::wait_status(&mut status, 20.0, "20 cycles of the added unit", |s| {
        s.devices.iter().any(|d| d.name == "u4" && d.cycles >= 20)
    })
    .await;
    shutdown.cancel();
    gw.await.unwrap();
    peer.abort();
    for d in &s.devices {
        assert!(
            d.errors.is_empty() && d.link_up,
            "{}: {:?}, {:?}",
            d.name,
            d.errors,
            d.last_error
        );
    }
    for (unit, c) in s.channels.iter().enumerate() {
        let want = f64::from(1001 + unit as u16) * 0.01;
        assert_eq!(&*c.name, format!("T_u{}", unit + 1));
        let got = c.reading.value_degc.unwrap_or(f64::NAN);
        assert!((got - want).abs() < 1e-9, "{}: {:?}", c.name, c.reading);
    }
    assert_eq!(accepted.load(Ordering::SeqCst), 1, "connections accepted");
}

// Behind the same gateway a fourth unit is absent, and the gateway answers 0x0B only
// after its own response timeout, 1 s, longer than the units' timeout_s (0.5 s). The
// timeout dropped the shared connection; the gateway, still busy with the request,
// closed the new one, and the reconnect backoff took the three present units down
// with the absent one, every time it was asked. The connection now outlives the
// timeout, and the late 0x0B is dropped by its transaction id.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_absent_unit_does_not_take_down_the_others_behind_a_one_connection_gateway() {
    absent_unit_behind_a_one_connection_gateway(false).await;
}

// The same, with unit 1 alone at the address at start and the others added by a
// reload: unit 1, unchanged, kept its link, which was not marked as shared, so the
// absent unit's timeout dropped the connection as above (review S, F6).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn units_a_reload_adds_at_an_address_share_its_connection_as_at_start() {
    absent_unit_behind_a_one_connection_gateway(true).await;
}

async fn absent_unit_behind_a_one_connection_gateway(added_by_reload: bool) {
    let (address, accepted, peer) = one_connection_gateway(&[4], Duration::from_secs(1)).await;
    let units = |units: std::ops::RangeInclusive<u8>| {
        let text: String = units
            .map(|unit| {
                format!(
                    "[devices.u{unit}]\ntransport = \"tcp\"\naddress = \"{address}\"\nunit_id = {unit}\n\
                     timeout_s = 0.5\npoll_interval_s = 1.0\nbackoff_initial_s = 1.0\n\n\
                     [channels.T_u{unit}]\ndevice = \"u{unit}\"\nregister = \"input\"\naddress = 0\n\
                     data_type = \"u16\"\nscaling = {{ kind = \"direct\", gain = 0.01, offset_degc = 0.0 }}\n\n"
                )
            })
            .collect();
        format!("[gateway]\nstatus_interval_s = 0.05\n\n{text}")
    };
    let (reload, reloads) = tokio::sync::mpsc::channel(1);
    let first = if added_by_reload { 1..=1 } else { 1..=4 };
    let (mut status, shutdown, gw) = run(&units(first), Some(reloads));
    if added_by_reload {
        common::wait_status(&mut status, 10.0, "unit 1 reads", |s| {
            s.channels.len() == 1 && s.channels[0].reading.quality == Quality::Good
        })
        .await;
        let all = units(1..=4);
        reload
            .send(compgate_gateway::config::load_str(&all, "units.toml").expect("config"))
            .await
            .unwrap();
    }
    let present = |s: &compgate_gateway::runtime::Status| {
        s.channels
            .iter()
            .filter(|c| &*c.name != "T_u4")
            .map(|c| c.reading.quality)
            .collect::<Vec<_>>()
    };
    common::wait_status(&mut status, 10.0, "the present units read", |s| {
        s.channels.len() == 4 && present(s).iter().all(|q| *q == Quality::Good)
    })
    .await;
    // 12 s: the absent unit is asked at least 4 times (its backoff from 1 s, doubling).
    let end = tokio::time::Instant::now() + Duration::from_secs(12);
    let mut not_good = Vec::new();
    // A skipped cycle of the demoted unit reported 0 connects while another unit held
    // the line.
    let mut no_connects = 0;
    while tokio::time::Instant::now() < end {
        let _ = tokio::time::timeout(Duration::from_millis(200), status.changed()).await;
        let s = status.borrow_and_update().clone();
        if present(&s).iter().any(|q| *q != Quality::Good) {
            not_good.push(format!("{:?}", present(&s)));
        }
        // (A device still in its first cycle has reported nothing yet.)
        no_connects += s
            .devices
            .iter()
            .filter(|d| d.cycles > 0 && d.connects == 0)
            .count();
    }
    let s = status.borrow().clone();
    shutdown.cancel();
    gw.await.unwrap();
    peer.abort();
    let absent = s.devices.iter().find(|d| d.name == "u4").unwrap();
    assert!(absent.cycles >= 4 && !absent.link_up, "{absent:?}");
    assert!(
        not_good.is_empty(),
        "the present units were not good in {} status updates, e.g. {}; devices: {:#?}",
        not_good.len(),
        not_good[0],
        s.devices
    );
    assert_eq!(accepted.load(Ordering::SeqCst), 1, "connections accepted");
    assert_eq!(no_connects, 0, "status updates with a device at 0 connects");
}
