//! The Modbus source against an independent implementation: pymodbus' server as a
//! field ADC module from another vendor (`tests/peers/modbus_device.py`), over Modbus
//! TCP on loopback and Modbus RTU over a pty line. Every value must be the documented
//! decoding and scaling of the peer's registers, bit for bit.

// Test helpers: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

mod common;

use std::time::Duration;

use common::peer::{self, Peer};
use compgate_core::channel::{Quality, Reason};
use compgate_gateway::config;
use compgate_gateway::runtime::{self, Status};
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;

const SCRIPT: &str = "modbus_device.py";
const MODULE: &str = "pymodbus.server";
/// RTU also needs pyserial (pymodbus opens the line with it).
const RTU_MODULES: &str = "pymodbus.server, serial";

/// How a channel's raw value becomes degC.
#[derive(Clone, Copy)]
enum Scale {
    /// `common::SCALING`: 4-20 mA over -50..150 degC on a 12-bit ADC at 24 mA.
    Transmitter,
    /// `degc = raw * gain` (offset 0).
    Direct(f64),
}

/// One channel of the peer: its registers and the value they hold, written out apart
/// from the peer's own table (`modbus_device.py`).
struct Expect {
    name: &'static str,
    register: &'static str,
    address: u16,
    data_type: &'static str,
    byte_order: &'static str,
    /// The raw value the registers hold, exactly.
    raw: f64,
    scale: Scale,
}

fn table() -> Vec<Expect> {
    let ch = |name, register, address, data_type, byte_order, raw, scale| Expect {
        name,
        register,
        address,
        data_type,
        byte_order,
        raw,
        scale,
    };
    use Scale::{Direct, Transmitter};
    vec![
        ch("T_in0", "input", 0, "u16", "ABCD", 1775.0, Transmitter),
        ch("T_in1", "input", 1, "u16", "ABCD", 2457.0, Transmitter),
        ch("T_in2", "input", 2, "u16", "ABCD", 2600.0, Transmitter),
        ch("T_i16", "input", 3, "i16", "ABCD", -123.0, Direct(0.1)),
        ch(
            "T_abcd",
            "holding",
            10,
            "f32",
            "ABCD",
            f64::from(23.45f32),
            Direct(1.0),
        ),
        ch(
            "T_cdab",
            "holding",
            12,
            "f32",
            "CDAB",
            f64::from(41.7f32),
            Direct(1.0),
        ),
        ch(
            "T_badc",
            "holding",
            14,
            "f32",
            "BADC",
            f64::from(18.52f32),
            Direct(1.0),
        ),
        ch(
            "T_dcba",
            "holding",
            16,
            "f32",
            "DCBA",
            f64::from(-7.37f32),
            Direct(1.0),
        ),
        ch(
            "T_u32",
            "holding",
            20,
            "u32",
            "CDAB",
            3_000_000_123.0,
            Direct(1e-8),
        ),
        ch(
            "T_i32",
            "holding",
            22,
            "i32",
            "ABCD",
            -98765.0,
            Direct(1e-4),
        ),
    ]
}

impl Expect {
    /// The temperature by the documented formulas (docs/reference/config.md, scaling).
    fn degc(&self) -> f64 {
        match self.scale {
            Scale::Transmitter => {
                let ma = self.raw * 24.0 / 4095.0;
                -50.0 + (ma - 4.0) / 16.0 * (150.0 - -50.0)
            }
            Scale::Direct(gain) => self.raw * gain + 0.0,
        }
    }

    fn toml(&self) -> String {
        let scaling = match self.scale {
            Scale::Transmitter => common::SCALING.to_string(),
            Scale::Direct(gain) => {
                format!("{{ kind = \"direct\", gain = {gain:?}, offset_degc = 0.0 }}")
            }
        };
        format!(
            "[channels.{}]\ndevice = \"adc\"\nregister = \"{}\"\naddress = {}\n\
             data_type = \"{}\"\nbyte_order = \"{}\"\nscaling = {scaling}\nfilter = {}\n\n",
            self.name,
            self.register,
            self.address,
            self.data_type,
            self.byte_order,
            common::FILTER
        )
    }
}

/// A monitoring-only config: device `adc` (`device` holds its transport keys) with the
/// channels of [`table`] and `extra` appended.
fn config_text(device: &str, extra: &str) -> String {
    let channels: String = table().iter().map(Expect::toml).collect();
    format!(
        "[gateway]\nstatus_interval_s = 0.05\n\n[devices.adc]\n{device}\n\
         timeout_s = 2.0\npoll_interval_s = 0.1\ndegrade_after_cycles = 2\n\n{channels}{extra}"
    )
}

/// The TCP device keys for a peer.
fn tcp_device(peer: &Peer) -> String {
    format!(
        "transport = \"tcp\"\naddress = \"{}\"\nunit_id = 1\nconnect_timeout_s = 1.0",
        peer.address()
    )
}

/// The peer serving Modbus TCP as unit 1; `None` (skip) when pymodbus is missing.
fn tcp_peer() -> Option<Peer> {
    let args = ["tcp", "--port", "0", "--unit", "1"].map(String::from);
    peer::start(SCRIPT, MODULE, &args)
}

/// The gateway in-process on `text`; dropping the token stops it.
struct Gateway {
    status: watch::Receiver<Status>,
    shutdown: CancellationToken,
    task: tokio::task::JoinHandle<()>,
}

impl Gateway {
    fn start(text: &str) -> Self {
        let cfg = config::load_str(text, "modbus-peer.toml").expect("test config is valid");
        let (tx, status) = watch::channel(Status::default());
        let shutdown = CancellationToken::new();
        let sd = shutdown.clone();
        let task = tokio::spawn(async move {
            runtime::run(&cfg, sd, tx).await.expect("gateway runs");
        });
        Self {
            status,
            shutdown,
            task,
        }
    }

    /// Waits until `pred` holds; panics with the last status after `secs`.
    async fn wait_for(&mut self, secs: f64, what: &str, pred: impl Fn(&Status) -> bool) -> Status {
        common::wait_status(&mut self.status, secs, what, pred).await
    }

    async fn stop(self) {
        self.shutdown.cancel();
        tokio::time::timeout(Duration::from_secs(10), self.task)
            .await
            .expect("gateway stops within 10 s")
            .expect("gateway task did not panic");
    }
}

fn quality(s: &Status, name: &str) -> Quality {
    common::Rig::quality(s, name)
}

/// Every channel of [`table`] good, its raw value and temperature the documented ones
/// bit for bit.
fn assert_table_read(s: &Status) {
    for e in table() {
        let r = &common::Rig::channel(s, e.name).reading;
        let raw = r.raw.unwrap_or(f64::NAN);
        assert_eq!(
            raw.to_bits(),
            e.raw.to_bits(),
            "{}: raw {raw:e}, the peer holds {:e}",
            e.name,
            e.raw
        );
        assert_eq!(r.quality, Quality::Good, "{}", e.name);
        let degc = r.value_degc.unwrap_or(f64::NAN);
        assert_eq!(
            degc.to_bits(),
            e.degc().to_bits(),
            "{}: {degc} degC, the documented scaling gives {}",
            e.name,
            e.degc()
        );
    }
}

/// Every channel of [`table`] has read a sample (good or not: [`assert_table_read`]
/// says what is wrong with one that is not).
fn all_read(s: &Status) -> bool {
    table()
        .iter()
        .all(|e| common::Rig::channel(s, e.name).reading.raw.is_some())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_data_type_and_byte_order_from_pymodbus_over_tcp_reads_bit_for_bit() {
    let Some(peer) = tcp_peer() else { return };
    let mut gw = Gateway::start(&config_text(&tcp_device(&peer), ""));
    let s = gw
        .wait_for(20.0, "a sample of every channel", all_read)
        .await;
    assert_table_read(&s);
    assert_eq!(s.devices[0].connects, 1, "{:?}", s.devices[0].last_error);
    gw.stop().await;
}

/// The peer serving Modbus RTU as unit 17 on a pty line, and the RTU device keys for
/// it (8E1 at 115200 baud, as a shop floor line would be); `None` (skip) when pymodbus
/// is missing.
fn rtu_peer() -> Option<(Peer, String)> {
    let python = peer::python(RTU_MODULES)?;
    let args = ["rtu", "--unit", "17", "--baud", "115200"].map(String::from);
    let (peer, path) = Peer::start_reading(&python, SCRIPT, &args, "PATH");
    assert!(path.starts_with("/dev/"), "a serial path: {path}");
    let device = format!(
        "transport = \"rtu\"\nserial_path = \"{path}\"\nbaud = 115200\nparity = \"even\"\n\
         stop_bits = 1\nunit_id = 17"
    );
    Some((peer, device))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_data_type_and_byte_order_from_pymodbus_over_rtu_reads_bit_for_bit() {
    let Some((_peer, device)) = rtu_peer() else {
        return;
    };
    let mut gw = Gateway::start(&config_text(&device, ""));
    let s = gw
        .wait_for(20.0, "a sample of every channel over RTU", all_read)
        .await;
    assert_table_read(&s);
    // No reply was ever misread (a CRC, a length, a unit id).
    assert!(
        !s.devices[0].errors.contains_key("frame"),
        "{:?}",
        s.devices[0].errors
    );
    gw.stop().await;
}

/// A channel on an input register the peer does not have.
fn missing_channel() -> String {
    format!(
        "[channels.T_missing]\ndevice = \"adc\"\nregister = \"input\"\naddress = 1000\n\
         data_type = \"u16\"\nscaling = {}\nfilter = {}\n",
        common::SCALING,
        common::FILTER
    )
}

/// The gateway's wording of pymodbus' answer to a read of that channel.
const MISSING_ERROR: &str = "function 0x04 (input registers), address 1000, count 1 (T_missing): \
                             device exception 0x02 illegal data address";

/// Runs the gateway on `text` (the peer's device with [`missing_channel`]) until
/// T_missing is bad; asserts that the device's error names the read and pymodbus'
/// exception, and that the other channels read on, bit for bit, on the same link.
async fn exception_is_named_and_the_rest_runs_on(text: &str) {
    let mut gw = Gateway::start(text);
    let s = gw
        .wait_for(
            20.0,
            "T_missing bad, a sample of every other channel",
            |s| all_read(s) && quality(s, "T_missing") == Quality::Bad(Reason::DeviceDegraded),
        )
        .await;
    let device = &s.devices[0];
    assert_eq!(device.name, "adc");
    assert_eq!(device.last_error.as_deref(), Some(MISSING_ERROR));
    // The device answered: an exception, never a transport or frame fault, and the
    // link was never rebuilt.
    assert!(device.link_up);
    assert_eq!(device.connects, 1);
    assert_eq!(
        device.errors.keys().copied().collect::<Vec<_>>(),
        ["exception"],
        "{:?}",
        device.errors
    );
    assert_table_read(&s);
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_illegal_data_address_from_pymodbus_over_tcp_is_named_and_probe_shows_it() {
    let Some(peer) = tcp_peer() else { return };
    let text = config_text(&tcp_device(&peer), &missing_channel());
    exception_is_named_and_the_rest_runs_on(&text).await;

    // `compgate probe` on the same file names the device, the channel's register and
    // the exception, and fails.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("compgate.toml");
    std::fs::write(&file, &text).unwrap();
    let out = std::process::Command::new(common::process::BIN)
        .args(["probe", "--config"])
        .arg(&file)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success(),
        "a bad channel fails the probe\n{stdout}{stderr}"
    );
    assert!(stdout.contains("device adc: tcp://"), "{stdout}");
    assert!(
        stdout.contains(
            "  T_missing: input register 1000, u16 ABCD\n    \
             error      device exception 0x02 illegal data address\n"
        ),
        "{stdout}"
    );
    assert!(stderr.contains("1 channel bad: T_missing"), "{stderr}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_illegal_data_address_from_pymodbus_over_rtu_keeps_the_line_in_step() {
    let Some((_peer, device)) = rtu_peer() else {
        return;
    };
    exception_is_named_and_the_rest_runs_on(&config_text(&device, &missing_channel())).await;
}
