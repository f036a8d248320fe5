//! Pure request planning and register decoding: no I/O.
//!
//! Channels on the same device and register kind are merged into as few reads as
//! possible. Two channels share a read when the gap between them is at most
//! `max_gap_registers` and the read stays within `max_read_registers` (at most the
//! Modbus limit of 125).

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Most registers one Modbus read may return (function codes 0x03/0x04).
pub const MAX_READ_REGISTERS: u16 = 125;

/// Which register table a channel lives in.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize, JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum RegisterKind {
    /// Input registers, function code 0x04 (read-only, the usual place for measurements).
    Input,
    /// Holding registers, function code 0x03.
    Holding,
}

/// How a channel's registers encode its value.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum DataType {
    /// One register, unsigned.
    U16,
    /// One register, two's complement.
    I16,
    /// Two registers, unsigned.
    U32,
    /// Two registers, two's complement.
    I32,
    /// Two registers, IEEE 754 single precision.
    F32,
}

impl DataType {
    /// Every type, e.g. for a probe that tries them all.
    pub const ALL: [Self; 5] = [Self::U16, Self::I16, Self::U32, Self::I32, Self::F32];

    /// Registers the type occupies.
    pub fn registers(self) -> u16 {
        match self {
            Self::U16 | Self::I16 => 1,
            Self::U32 | Self::I32 | Self::F32 => 2,
        }
    }

    /// The name used in the configuration (`u16`, `f32`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Self::U16 => "u16",
            Self::I16 => "i16",
            Self::U32 => "u32",
            Self::I32 => "i32",
            Self::F32 => "f32",
        }
    }
}

/// Byte order of a value, A = most significant byte. Registers are read in address
/// order; inside each register the first byte on the wire is its high byte.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize, JsonSchema)]
pub enum ByteOrder {
    /// Big-endian: register 0 holds A B, register 1 holds C D.
    #[default]
    #[serde(rename = "ABCD")]
    Abcd,
    /// Word swap: register 0 holds C D, register 1 holds A B.
    #[serde(rename = "CDAB")]
    Cdab,
    /// Byte swap inside each register: B A, D C.
    #[serde(rename = "BADC")]
    Badc,
    /// Little-endian: D C, B A.
    #[serde(rename = "DCBA")]
    Dcba,
}

impl ByteOrder {
    /// Every order, e.g. for a probe that names the plausible one.
    pub const ALL: [Self; 4] = [Self::Abcd, Self::Cdab, Self::Badc, Self::Dcba];

    /// The name used in the configuration (`ABCD`, `CDAB`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Self::Abcd => "ABCD",
            Self::Cdab => "CDAB",
            Self::Badc => "BADC",
            Self::Dcba => "DCBA",
        }
    }
}

/// Decodes a value from its registers (`regs.len()` must equal `ty.registers()`).
/// Returns `None` when the slice has the wrong length.
pub fn decode(regs: &[u16], ty: DataType, order: ByteOrder) -> Option<f64> {
    let swap_bytes = matches!(order, ByteOrder::Badc | ByteOrder::Dcba);
    let fix = |w: u16| if swap_bytes { w.swap_bytes() } else { w };
    match (ty, regs) {
        (DataType::U16, [w]) => Some(f64::from(fix(*w))),
        (DataType::I16, [w]) => Some(f64::from(fix(*w) as i16)),
        (DataType::U32 | DataType::I32 | DataType::F32, [w0, w1]) => {
            let (hi, lo) = match order {
                ByteOrder::Abcd | ByteOrder::Badc => (fix(*w0), fix(*w1)),
                ByteOrder::Cdab | ByteOrder::Dcba => (fix(*w1), fix(*w0)),
            };
            let bits = (u32::from(hi) << 16) | u32::from(lo);
            Some(match ty {
                DataType::U32 => f64::from(bits),
                DataType::I32 => f64::from(bits as i32),
                _ => f64::from(f32::from_bits(bits)),
            })
        }
        _ => None,
    }
}

/// The registers `value` occupies as `ty` in `order`: the inverse of [`decode`].
/// `None` when `value` is not exactly a `ty` (a fraction for an integer type, a number
/// out of its range, a double that is no `f32`).
pub fn encode(value: f64, ty: DataType, order: ByteOrder) -> Option<Vec<u16>> {
    let swap_bytes = matches!(order, ByteOrder::Badc | ByteOrder::Dcba);
    let fix = |w: u16| if swap_bytes { w.swap_bytes() } else { w };
    let exact =
        |v: f64, lo: f64, hi: f64| (v.fract() == 0.0 && (lo..=hi).contains(&v)).then_some(v);
    let bits: u32 = match ty {
        DataType::U16 => return Some(vec![fix(exact(value, 0.0, 65535.0)? as u16)]),
        DataType::I16 => {
            let v = exact(value, -32768.0, 32767.0)? as i16;
            return Some(vec![fix(v as u16)]);
        }
        DataType::U32 => exact(value, 0.0, f64::from(u32::MAX))? as u32,
        DataType::I32 => exact(value, f64::from(i32::MIN), f64::from(i32::MAX))? as i32 as u32,
        DataType::F32 => {
            let f = value as f32;
            if f64::from(f).to_bits() != value.to_bits() && !value.is_nan() {
                return None;
            }
            f.to_bits()
        }
    };
    let (hi, lo) = (fix((bits >> 16) as u16), fix(bits as u16));
    Some(match order {
        ByteOrder::Abcd | ByteOrder::Badc => vec![hi, lo],
        ByteOrder::Cdab | ByteOrder::Dcba => vec![lo, hi],
    })
}

/// The byte order in which `regs` most likely hold a `ty` value: of the orders whose
/// value `plausible` turns into a temperature, `configured` if it is one, else the one
/// closest to `reference_degc` (e.g. the middle of the plausible range). `None` when
/// no order gives a plausible value. A 16-bit value has only its byte order to get
/// wrong: `ABCD` or `BADC` (a module that sends the low byte first).
pub fn likely_order(
    regs: &[u16],
    ty: DataType,
    configured: ByteOrder,
    plausible: impl Fn(f64) -> Option<f64>,
    reference_degc: f64,
) -> Option<(ByteOrder, f64)> {
    let swapped = match configured {
        ByteOrder::Abcd | ByteOrder::Cdab => ByteOrder::Badc,
        ByteOrder::Badc | ByteOrder::Dcba => ByteOrder::Abcd,
    };
    let one_register = [configured, swapped];
    let orders: &[ByteOrder] = if ty.registers() == 2 {
        &ByteOrder::ALL
    } else {
        &one_register
    };
    let candidates = orders.iter().filter_map(|&o| {
        let degc = decode(regs, ty, o).and_then(&plausible)?;
        Some((o, degc))
    });
    let mut best: Option<(ByteOrder, f64)> = None;
    for (o, degc) in candidates {
        if o == configured {
            return Some((o, degc));
        }
        let closer =
            best.is_none_or(|(_, b)| (degc - reference_degc).abs() < (b - reference_degc).abs());
        if closer {
            best = Some((o, degc));
        }
    }
    best
}

/// One channel's place in the register space.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Slot {
    /// Caller's channel index.
    pub channel: usize,
    /// Register table.
    pub kind: RegisterKind,
    /// 0-based address of the first register.
    pub address: u16,
    /// Registers occupied.
    pub len: u16,
}

/// One Modbus read and the channels it serves.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReadBlock {
    /// Register table.
    pub kind: RegisterKind,
    /// First register read.
    pub start: u16,
    /// Registers read.
    pub count: u16,
    /// Channels served: (slot, offset of its first register in the block).
    pub members: Vec<(Slot, u16)>,
}

/// Merges slots into reads. Slots are sorted by (kind, address); a slot joins the
/// current block when the gap is at most `max_gap` and the block stays within
/// `max_read` registers (capped at [`MAX_READ_REGISTERS`]; a slot longer than that is
/// read alone). Overlapping slots (two channels on the same register) share.
pub fn plan(slots: &[Slot], max_gap: u16, max_read: u16) -> Vec<ReadBlock> {
    let max_read = u32::from(max_read.min(MAX_READ_REGISTERS));
    let mut sorted = slots.to_vec();
    sorted.sort_by_key(|s| (s.kind, s.address, s.len));
    let mut blocks: Vec<ReadBlock> = Vec::new();
    for slot in sorted {
        let end = u32::from(slot.address) + u32::from(slot.len);
        if let Some(b) = blocks.last_mut() {
            let b_end = u32::from(b.start) + u32::from(b.count);
            let gap_ok = u32::from(slot.address) <= b_end + u32::from(max_gap);
            let new_count = end.max(b_end) - u32::from(b.start);
            if b.kind == slot.kind && gap_ok && new_count <= max_read {
                b.count = new_count as u16;
                b.members.push((slot, slot.address - b.start));
                continue;
            }
        }
        blocks.push(ReadBlock {
            kind: slot.kind,
            start: slot.address,
            count: slot.len,
            members: vec![(slot, 0)],
        });
    }
    blocks
}

#[cfg(test)]
mod tests {
    use super::*;

    fn slot(channel: usize, kind: RegisterKind, address: u16, len: u16) -> Slot {
        Slot {
            channel,
            kind,
            address,
            len,
        }
    }

    #[test]
    fn decodes_every_byte_order_of_the_same_f32() {
        // 123.456f32 = 0x42F6E979: A=42 B=F6 C=E9 D=79
        let v = 123.456f32;
        let cases = [
            (ByteOrder::Abcd, [0x42F6, 0xE979]),
            (ByteOrder::Cdab, [0xE979, 0x42F6]),
            (ByteOrder::Badc, [0xF642, 0x79E9]),
            (ByteOrder::Dcba, [0x79E9, 0xF642]),
        ];
        for (order, regs) in cases {
            assert_eq!(
                decode(&regs, DataType::F32, order),
                Some(f64::from(v)),
                "{order:?}"
            );
        }
    }

    #[test]
    fn encode_is_the_inverse_of_decode() {
        for ty in DataType::ALL {
            for order in ByteOrder::ALL {
                for v in [0.0, 1.0, 1501.0, -2.0, 23.45f32 as f64, 65535.0] {
                    let Some(regs) = encode(v, ty, order) else {
                        continue;
                    };
                    assert_eq!(decode(&regs, ty, order), Some(v), "{ty:?} {order:?} {v}");
                }
            }
        }
        assert_eq!(encode(-1.0, DataType::U16, ByteOrder::Abcd), None);
        assert_eq!(encode(0.5, DataType::I32, ByteOrder::Abcd), None);
        assert_eq!(encode(0.1, DataType::F32, ByteOrder::Abcd), None);
        assert_eq!(
            encode(f64::from(123.456f32), DataType::F32, ByteOrder::Cdab),
            Some(vec![0xE979, 0x42F6])
        );
    }

    #[test]
    fn the_likely_order_of_a_swapped_float() {
        // 23.45 degC as CDAB; read as ABCD it is -1.6e-23, as BADC -0.003, as DCBA
        // -1.6e-23 again.
        let regs = [0x999A, 0x41BB];
        let plausible = |raw: f64| {
            (raw == 0.0 || raw.abs() >= 1e-6)
                .then_some(raw)
                .filter(|d| (-20.0..=80.0).contains(d))
        };
        let (order, degc) =
            likely_order(&regs, DataType::F32, ByteOrder::Abcd, plausible, 30.0).expect("an order");
        assert_eq!(order, ByteOrder::Cdab);
        assert!((degc - 23.45).abs() < 1e-5, "{degc}");
        // Configured right: stays.
        assert_eq!(
            likely_order(&regs, DataType::F32, ByteOrder::Cdab, plausible, 30.0).map(|o| o.0),
            Some(ByteOrder::Cdab)
        );
        // Nothing plausible.
        assert_eq!(
            likely_order(&[0x7FC0, 0], DataType::F32, ByteOrder::Abcd, |_| None, 30.0),
            None
        );
    }

    #[test]
    fn decodes_integers_with_sign_and_order() {
        assert_eq!(
            decode(&[0xFFFF], DataType::I16, ByteOrder::Abcd),
            Some(-1.0)
        );
        assert_eq!(
            decode(&[0xFFFF], DataType::U16, ByteOrder::Abcd),
            Some(65535.0)
        );
        assert_eq!(decode(&[0x0100], DataType::U16, ByteOrder::Badc), Some(1.0));
        assert_eq!(
            decode(&[0x0001, 0x0000], DataType::U32, ByteOrder::Abcd),
            Some(65536.0)
        );
        assert_eq!(
            decode(&[0x0000, 0x0001], DataType::U32, ByteOrder::Cdab),
            Some(65536.0)
        );
        assert_eq!(
            decode(&[0xFFFF, 0xFFFE], DataType::I32, ByteOrder::Abcd),
            Some(-2.0)
        );
        assert_eq!(
            decode(&[0xFEFF, 0xFFFF], DataType::I32, ByteOrder::Dcba),
            Some(-2.0)
        );
        assert_eq!(decode(&[1, 2], DataType::U16, ByteOrder::Abcd), None);
    }

    #[test]
    fn merges_contiguous_and_small_gaps_only() {
        use RegisterKind::*;
        let slots = [
            slot(0, Input, 0, 1),
            slot(1, Input, 1, 1),
            slot(2, Input, 5, 2),   // gap 3: merged with max_gap 4
            slot(3, Input, 20, 1),  // gap 13: new block
            slot(4, Holding, 1, 1), // other kind: new block
        ];
        let blocks = plan(&slots, 4, MAX_READ_REGISTERS);
        assert_eq!(blocks.len(), 3);
        assert_eq!((blocks[0].start, blocks[0].count), (0, 7));
        assert_eq!(
            blocks[0].members.iter().map(|m| m.1).collect::<Vec<_>>(),
            [0, 1, 5]
        );
        assert_eq!((blocks[1].start, blocks[1].count), (20, 1));
        assert_eq!(
            (blocks[2].kind, blocks[2].start),
            (Input, 1).max((Holding, 1))
        );
    }

    #[test]
    fn never_exceeds_125_registers() {
        let slots: Vec<Slot> = (0..300)
            .map(|i| slot(i, RegisterKind::Input, i as u16, 1))
            .collect();
        let blocks = plan(&slots, 0, MAX_READ_REGISTERS);
        assert_eq!(
            blocks.iter().map(|b| b.count).collect::<Vec<_>>(),
            [125, 125, 50]
        );
        assert_eq!(blocks.iter().map(|b| b.members.len()).sum::<usize>(), 300);
    }

    // A module that takes at most 16 registers a read (`max_read_registers`).
    #[test]
    fn a_smaller_read_limit_splits_the_reads() {
        let mut slots: Vec<Slot> = (0..20)
            .map(|i| slot(i, RegisterKind::Input, i as u16, 1))
            .collect();
        let blocks = plan(&slots, 8, 16);
        assert_eq!(blocks.iter().map(|b| b.count).collect::<Vec<_>>(), [16, 4]);
        // A 32-bit value never splits, even with a limit below it.
        slots.push(slot(20, RegisterKind::Holding, 0, 2));
        let blocks = plan(&slots, 8, 1);
        assert_eq!(blocks.len(), 21);
        assert_eq!((blocks[20].start, blocks[20].count), (0, 2));
    }

    #[test]
    fn shared_registers_and_unsorted_input() {
        let slots = [
            slot(0, RegisterKind::Input, 10, 2),
            slot(1, RegisterKind::Input, 10, 1),
            slot(2, RegisterKind::Input, 3, 1),
        ];
        let blocks = plan(&slots, 0, MAX_READ_REGISTERS);
        assert_eq!(blocks.len(), 2);
        assert_eq!((blocks[1].start, blocks[1].count), (10, 2));
    }
}
