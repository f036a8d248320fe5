//! Fuzz body: arbitrary bytes as a Modbus device's reply to a read of holding or
//! input registers, through the gateway's real client path: a [`DevicePoller`] on a
//! [`ModbusLink`] whose tokio-modbus context (TCP or RTU framing) runs over an
//! in-memory stream, in a current-thread runtime with a paused clock (so a reply that
//! never completes ends in the link's timeout at once).
//!
//! Input: `flags unit channels descriptors... reply...`
//! - `flags`: bit 0 RTU (else TCP), bit 1 input registers (else holding), bit 2 fix-up
//!   (TCP: write transaction id 0 and the MBAP length; RTU: append the CRC) so that
//!   the fuzzer reaches the payload checks, bit 3 close the stream after the reply.
//! - `channels`: 1 + `channels % 8` channels, one descriptor byte each (data type
//!   `d % 5`, byte order `d / 5 % 4`), at consecutive addresses from 0: one read.
//!
//! Checked: no panic; every channel gets exactly one result; a channel gets a value
//! only when the bytes hold a well-formed reply frame (matching header, byte count,
//! CRC or MBAP length), and then it is the value of the frame's registers.

use std::sync::Arc;
use std::time::Duration;

use compgate_gateway::source::modbus::{LinkSpec, ModbusLink};
use compgate_gateway::source::plan::{self, ByteOrder, DataType, RegisterKind};
use compgate_gateway::source::{ChannelSpec, DevicePoller, PollParams};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_modbus::client::{rtu, tcp};
use tokio_modbus::Slave;

/// CRC-16/MODBUS, as it goes on the wire (low byte first).
fn crc16(bytes: &[u8]) -> [u8; 2] {
    crc::Crc::<u16>::new(&crc::CRC_16_MODBUS)
        .checksum(bytes)
        .to_le_bytes()
}

/// The registers of the first well-formed reply in `sent` for `unit`, `function` and
/// `count` registers: TCP only at the start (transaction id 0, protocol 0, exact
/// length), RTU at any offset (the decoder skips garbage before a frame).
fn well_formed(sent: &[u8], rtu: bool, unit: u8, function: u8, count: u16) -> Vec<Vec<u16>> {
    let bytes = usize::from(count) * 2;
    let Ok(byte_count) = u8::try_from(bytes) else {
        return Vec::new();
    };
    let head = [unit, function, byte_count];
    let regs = |payload: &[u8]| -> Vec<u16> {
        payload
            .chunks_exact(2)
            .map(|w| u16::from_be_bytes([w[0], w[1]]))
            .collect()
    };
    let mut found = Vec::new();
    if rtu {
        for k in 0..sent.len() {
            let Some(frame) = sent.get(k..k + 3 + bytes + 2) else {
                break;
            };
            let (body, crc) = frame.split_at(3 + bytes);
            if body[..3] == head && crc == crc16(body) {
                found.push(regs(&body[3..]));
            }
        }
    } else if let Some(frame) = sent.get(..7 + 2 + bytes) {
        let len = u16::try_from(3 + bytes).unwrap_or(u16::MAX).to_be_bytes();
        if frame[..6] == [0, 0, 0, 0, len[0], len[1]] && frame[6..9] == head {
            found.push(regs(&frame[9..]));
        }
    }
    found
}

/// Both NaN, or the same bits.
fn same(a: f64, b: f64) -> bool {
    (a.is_nan() && b.is_nan()) || a.to_bits() == b.to_bits()
}

/// Feeds `data` to the client as described in the module docs.
pub fn run(data: &[u8]) {
    let [flags, unit, channels, rest @ ..] = data else {
        return;
    };
    let n = usize::from(channels % 8) + 1;
    if rest.len() < n {
        return;
    }
    let (descriptors, reply) = rest.split_at(n);
    let is_rtu = flags & 1 != 0;
    let kind = if flags & 2 != 0 {
        RegisterKind::Input
    } else {
        RegisterKind::Holding
    };
    let function = match kind {
        RegisterKind::Holding => 0x03,
        RegisterKind::Input => 0x04,
    };
    let mut specs = Vec::with_capacity(n);
    let mut address = 0u16;
    for (i, d) in descriptors.iter().enumerate() {
        let data_type = DataType::ALL[usize::from(d % 5)];
        specs.push(ChannelSpec {
            channel: i,
            name: format!("c{i}").into(),
            kind,
            address,
            data_type,
            byte_order: ByteOrder::ALL[usize::from(d / 5 % 4)],
        });
        address += data_type.registers();
    }
    let count = address;

    let mut sent = reply.to_vec();
    if flags & 4 != 0 {
        if is_rtu {
            let crc = crc16(&sent);
            sent.extend_from_slice(&crc);
        } else if sent.len() >= 6 {
            let len = u16::try_from(sent.len() - 6).unwrap_or(u16::MAX);
            sent[..4].fill(0);
            sent[4..6].copy_from_slice(&len.to_be_bytes());
        }
    }
    let close = flags & 8 != 0;

    let Ok(runtime) = tokio::runtime::Builder::new_current_thread()
        .enable_time()
        .start_paused(true)
        .build()
    else {
        return;
    };
    let timeout = Duration::from_millis(500);
    let sample = runtime.block_on(async {
        let (client, mut device) = tokio::io::duplex(4096);
        let request_len = if is_rtu { 8 } else { 12 };
        let reply = sent.clone();
        let device_task = tokio::spawn(async move {
            let mut request = vec![0u8; request_len];
            if device.read_exact(&mut request).await.is_err() {
                return;
            }
            if device.write_all(&reply).await.is_err() {
                return;
            }
            if !close {
                // Hold the stream open: the client waits for the rest until its timeout.
                std::future::pending::<()>().await;
            }
        });
        let ctx = if is_rtu {
            rtu::attach_slave(client, Slave(*unit))
        } else {
            tcp::attach_slave(client, Slave(*unit))
        };
        // Only used to reconnect, which one poll never does.
        let spec = LinkSpec::Tcp {
            address: "fuzz:502".into(),
            connect_timeout: timeout,
        };
        let link = ModbusLink::attached(spec, timeout, ctx);
        let params = PollParams {
            unit_id: *unit,
            timeout,
            retries: 0,
            degrade_after_cycles: 1,
            max_gap_registers: 0,
            max_read_registers: 125,
            cycle_deadline: timeout,
            settle: Duration::ZERO,
        };
        let mut poller = DevicePoller::new(
            0,
            "fuzz".into(),
            params,
            Arc::new(tokio::sync::Mutex::new(link)),
            specs.clone(),
        );
        let sample = poller.poll().await;
        device_task.abort();
        sample
    });

    assert_eq!(sample.values.len(), n, "one result per channel");
    let mut seen = vec![false; n];
    for (ch, _) in &sample.values {
        assert!(
            !std::mem::replace(&mut seen[*ch], true),
            "channel {ch} twice"
        );
    }
    let values: Vec<(usize, f64)> = sample
        .values
        .iter()
        .filter_map(|(ch, r)| r.as_ref().ok().map(|v| (*ch, *v)))
        .collect();
    if values.is_empty() {
        return;
    }
    let frames = well_formed(&sent, is_rtu, *unit, function, count);
    let explained = frames.iter().any(|regs| {
        values.iter().all(|&(ch, v)| {
            let s = &specs[ch];
            let at = usize::from(s.address);
            let expected = regs
                .get(at..at + usize::from(s.data_type.registers()))
                .and_then(|r| plan::decode(r, s.data_type, s.byte_order));
            expected.is_some_and(|e| same(e, v))
        })
    });
    assert!(
        explained,
        "values {values:?} from a reply that holds no well-formed frame: {sent:02x?}"
    );
}
