//! CANopen (CiA 301) frame encoding and decoding, the subset the gateway uses: NMT,
//! SYNC, EMCY, TPDO1..4, expedited SDO upload and abort, heartbeat. Pure: no sockets, no tokio.
//!
//! Every decoder takes any frame (any COB-ID, any length 0..=8) and returns a value or
//! an error naming what is wrong; none panics.

use crate::source::plan::DataType;

/// Largest data length of a classic CAN frame.
pub const MAX_DATA_BYTES: usize = 8;

/// A classic CAN data frame with an 11-bit identifier, as CANopen uses it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RawFrame {
    /// 11-bit identifier (COB-ID), 0..=0x7FF.
    pub cob_id: u16,
    len: u8,
    bytes: [u8; MAX_DATA_BYTES],
}

impl RawFrame {
    /// A frame; `None` when the identifier has more than 11 bits or the data more
    /// than 8 bytes.
    pub fn new(cob_id: u16, data: &[u8]) -> Option<Self> {
        if cob_id > 0x7FF || data.len() > MAX_DATA_BYTES {
            return None;
        }
        let mut bytes = [0u8; MAX_DATA_BYTES];
        bytes[..data.len()].copy_from_slice(data);
        Some(Self {
            cob_id,
            // <= 8 after the check above.
            len: data.len() as u8,
            bytes,
        })
    }

    /// The data bytes.
    pub fn data(&self) -> &[u8] {
        &self.bytes[..usize::from(self.len)]
    }
}

impl std::fmt::Display for RawFrame {
    /// candump's notation: `181#D0070000`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:03X}#", self.cob_id)?;
        for b in self.data() {
            write!(f, "{b:02X}")?;
        }
        Ok(())
    }
}

/// Errors of decoding a frame or a value.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CodecError {
    /// The frame has the wrong number of data bytes for its kind.
    #[error("{kind} frame {cob_id:03X}h has {got} data bytes, expected {expected}")]
    Length {
        /// Kind of frame the COB-ID says it is.
        kind: &'static str,
        /// Its COB-ID.
        cob_id: u16,
        /// Bytes expected.
        expected: &'static str,
        /// Bytes received.
        got: usize,
    },
    /// A heartbeat with a state byte CiA 301 does not define.
    #[error("heartbeat of node {node} has unknown state {state:#04x}")]
    HeartbeatState {
        /// Node id.
        node: u8,
        /// The state byte.
        state: u8,
    },
    /// A mapped value reaches past the end of the PDO.
    #[error("a {size}-byte value at byte offset {offset} does not fit in a PDO of {len} bytes")]
    OutsidePdo {
        /// Byte offset of the value.
        offset: usize,
        /// Size of the value in bytes.
        size: usize,
        /// Data bytes of the PDO.
        len: usize,
    },
    /// An expedited SDO answer carries fewer bytes than the value's type needs.
    #[error("SDO answer has {got} data bytes, a {ty:?} needs {need}")]
    SdoTooShort {
        /// Value type.
        ty: DataType,
        /// Bytes needed.
        need: usize,
        /// Bytes carried.
        got: usize,
    },
    /// An expedited SDO answer carries a wider value than the type holds: the object
    /// is of another type than `data_type` says.
    #[error(
        "SDO answer has {got} data bytes ({bytes}), a value wider than data_type = \"{}\": \
         set data_type to the object's type",
        ty.name()
    )]
    SdoTooLong {
        /// Value type.
        ty: DataType,
        /// Bytes carried.
        got: usize,
        /// The bytes, hex, in bus order.
        bytes: String,
    },
}

/// NMT command specifiers (CiA 301 7.2.8.3.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NmtCommand {
    /// Start remote node: to operational.
    Start,
    /// Stop remote node: to stopped.
    Stop,
    /// Enter pre-operational.
    EnterPreOperational,
    /// Reset node (application and communication).
    ResetNode,
    /// Reset communication.
    ResetCommunication,
}

impl NmtCommand {
    /// The command specifier byte.
    pub fn code(self) -> u8 {
        match self {
            Self::Start => 0x01,
            Self::Stop => 0x02,
            Self::EnterPreOperational => 0x80,
            Self::ResetNode => 0x81,
            Self::ResetCommunication => 0x82,
        }
    }

    /// The command for a specifier byte.
    pub fn from_code(code: u8) -> Option<Self> {
        Some(match code {
            0x01 => Self::Start,
            0x02 => Self::Stop,
            0x80 => Self::EnterPreOperational,
            0x81 => Self::ResetNode,
            0x82 => Self::ResetCommunication,
            _ => return None,
        })
    }
}

/// NMT state a heartbeat reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NmtState {
    /// Boot-up message: the node has just (re)started and is pre-operational.
    BootUp,
    /// Stopped.
    Stopped,
    /// Operational: sends PDOs.
    Operational,
    /// Pre-operational: SDO only.
    PreOperational,
}

impl NmtState {
    /// The heartbeat state byte.
    pub fn code(self) -> u8 {
        match self {
            Self::BootUp => 0x00,
            Self::Stopped => 0x04,
            Self::Operational => 0x05,
            Self::PreOperational => 0x7F,
        }
    }

    /// The state for a heartbeat byte (the toggle bit 7 is ignored, as for node
    /// guarding replies).
    pub fn from_code(code: u8) -> Option<Self> {
        Some(match code & 0x7F {
            0x00 => Self::BootUp,
            0x04 => Self::Stopped,
            0x05 => Self::Operational,
            0x7F => Self::PreOperational,
            _ => return None,
        })
    }
}

/// An expedited SDO upload answer or an abort, as a client sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SdoAnswer {
    /// Expedited upload: the object's value in 1..=4 bytes (4 when the server does
    /// not indicate the size).
    Upload {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Data bytes, little-endian.
        data: [u8; 4],
        /// Valid bytes of `data`.
        len: u8,
    },
    /// The server starts a segmented transfer (object longer than 4 bytes), which the
    /// gateway does not support.
    Segmented {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
    },
    /// Abort transfer with an abort code ([`abort_name`]).
    Abort {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Abort code.
        code: u32,
    },
    /// Any other server command specifier (a download answer, a segment).
    Other {
        /// The command byte.
        command: u8,
    },
}

/// What a frame is, by its COB-ID (predefined connection set, CiA 301 7.3.5).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Message {
    /// NMT node control from the master (COB-ID 0); node 0 = all nodes.
    Nmt {
        /// Command.
        command: Option<NmtCommand>,
        /// Raw command byte.
        code: u8,
        /// Addressed node, 0 = all.
        node: u8,
    },
    /// SYNC (COB-ID 0x080), optionally with a counter.
    Sync {
        /// Counter byte, if present.
        counter: Option<u8>,
    },
    /// Emergency of node `node` (0x080 + node).
    Emcy {
        /// Node id.
        node: u8,
        /// Emergency error code (0 = error reset / no error).
        code: u16,
        /// Error register (object 0x1001).
        register: u8,
        /// Manufacturer-specific bytes.
        vendor: [u8; 5],
    },
    /// Transmit PDO `pdo` (1..=4) of node `node`.
    Tpdo {
        /// Node id.
        node: u8,
        /// PDO number 1..=4.
        pdo: u8,
        /// The PDO bytes (all 8; `len` are valid).
        data: [u8; MAX_DATA_BYTES],
        /// Data length.
        len: u8,
    },
    /// Receive PDO `pdo` (1..=4) to node `node`.
    Rpdo {
        /// Node id.
        node: u8,
        /// PDO number 1..=4.
        pdo: u8,
    },
    /// SDO answer from server `node` (0x580 + node).
    SdoResponse {
        /// Node id.
        node: u8,
        /// The answer.
        answer: SdoAnswer,
    },
    /// SDO request to server `node` (0x600 + node).
    SdoRequest {
        /// Node id.
        node: u8,
        /// Command byte.
        command: u8,
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Bytes 4..8.
        data: [u8; 4],
    },
    /// Heartbeat or boot-up of node `node` (0x700 + node).
    Heartbeat {
        /// Node id.
        node: u8,
        /// Reported state.
        state: NmtState,
    },
    /// Any other COB-ID (TIME, LSS, unused ranges).
    Other,
}

/// COB-ID of NMT.
pub const NMT_COB_ID: u16 = 0x000;
/// COB-ID of SYNC.
pub const SYNC_COB_ID: u16 = 0x080;
/// Base COB-ID of EMCY (+ node id).
pub const EMCY_BASE: u16 = 0x080;
/// Base COB-ID of TPDO1 (+ node id); TPDO n is at `0x180 + 0x100 * (n - 1)`.
pub const TPDO1_BASE: u16 = 0x180;
/// Base COB-ID of SDO answers (+ node id).
pub const SDO_TX_BASE: u16 = 0x580;
/// Base COB-ID of SDO requests (+ node id).
pub const SDO_RX_BASE: u16 = 0x600;
/// Base COB-ID of heartbeats (+ node id).
pub const HEARTBEAT_BASE: u16 = 0x700;

/// COB-ID of TPDO `pdo` (1..=4) of `node`.
pub fn tpdo_cob_id(pdo: u8, node: u8) -> u16 {
    TPDO1_BASE + 0x100 * u16::from(pdo.saturating_sub(1)) + u16::from(node)
}

/// NMT command frame for `node` (0 = all nodes).
pub fn nmt(command: NmtCommand, node: u8) -> RawFrame {
    frame(NMT_COB_ID, &[command.code(), node])
}

/// SYNC frame without counter.
pub fn sync() -> RawFrame {
    frame(SYNC_COB_ID, &[])
}

/// Expedited SDO upload request (initiate upload, ccs = 2) for `index`/`sub` of `node`.
pub fn sdo_upload_request(node: u8, index: u16, sub: u8) -> RawFrame {
    let [lo, hi] = index.to_le_bytes();
    frame(
        SDO_RX_BASE + u16::from(node & 0x7F),
        &[0x40, lo, hi, sub, 0, 0, 0, 0],
    )
}

/// Abort code the client sends when an upload's answer does not come in time.
pub const ABORT_TIMED_OUT: u32 = 0x0504_0000;
/// Abort code the client sends when the server starts a segmented upload: the object
/// is longer than the 4 bytes the gateway reads.
pub const ABORT_TOO_LONG: u32 = 0x0607_0012;

/// SDO abort transfer (cs = 4) of `index`/`sub` from the client to server `node`.
pub fn sdo_abort(node: u8, index: u16, sub: u8, code: u32) -> RawFrame {
    let [lo, hi] = index.to_le_bytes();
    let [c0, c1, c2, c3] = code.to_le_bytes();
    frame(
        SDO_RX_BASE + u16::from(node & 0x7F),
        &[0x80, lo, hi, sub, c0, c1, c2, c3],
    )
}

fn frame(cob_id: u16, data: &[u8]) -> RawFrame {
    // Every caller passes an 11-bit COB-ID and at most 8 bytes.
    RawFrame::new(cob_id & 0x7FF, data).unwrap_or(RawFrame {
        cob_id: cob_id & 0x7FF,
        len: 0,
        bytes: [0; MAX_DATA_BYTES],
    })
}

fn need(
    frame: &RawFrame,
    kind: &'static str,
    expected: &'static str,
    ok: bool,
) -> Result<(), CodecError> {
    if ok {
        Ok(())
    } else {
        Err(CodecError::Length {
            kind,
            cob_id: frame.cob_id,
            expected,
            got: frame.data().len(),
        })
    }
}

/// Decodes any frame by its COB-ID.
pub fn decode(frame: &RawFrame) -> Result<Message, CodecError> {
    let d = frame.data();
    let id = frame.cob_id;
    let node = (id & 0x7F) as u8;
    let function = id & 0x780;
    Ok(match (function, node) {
        (0x000, 0) => {
            need(frame, "NMT", "2", d.len() == 2)?;
            Message::Nmt {
                command: NmtCommand::from_code(d[0]),
                code: d[0],
                node: d[1],
            }
        }
        (0x080, 0) => {
            need(frame, "SYNC", "0 or 1", d.len() <= 1)?;
            Message::Sync {
                counter: d.first().copied(),
            }
        }
        (0x080, n) => {
            need(frame, "EMCY", "8", d.len() == 8)?;
            let mut vendor = [0u8; 5];
            vendor.copy_from_slice(&d[3..8]);
            Message::Emcy {
                node: n,
                code: u16::from_le_bytes([d[0], d[1]]),
                register: d[2],
                vendor,
            }
        }
        (0x180 | 0x280 | 0x380 | 0x480, n) if n != 0 => {
            let mut data = [0u8; MAX_DATA_BYTES];
            data[..d.len()].copy_from_slice(d);
            Message::Tpdo {
                node: n,
                pdo: ((function - 0x180) / 0x100 + 1) as u8,
                data,
                len: d.len() as u8,
            }
        }
        (0x200 | 0x300 | 0x400 | 0x500, n) if n != 0 => Message::Rpdo {
            node: n,
            pdo: ((function - 0x200) / 0x100 + 1) as u8,
        },
        (0x580, n) if n != 0 => {
            need(frame, "SDO answer", "8", d.len() == 8)?;
            Message::SdoResponse {
                node: n,
                answer: sdo_answer(d),
            }
        }
        (0x600, n) if n != 0 => {
            need(frame, "SDO request", "8", d.len() == 8)?;
            Message::SdoRequest {
                node: n,
                command: d[0],
                index: u16::from_le_bytes([d[1], d[2]]),
                sub: d[3],
                data: [d[4], d[5], d[6], d[7]],
            }
        }
        (0x700, n) if n != 0 => {
            need(frame, "heartbeat", "1", d.len() == 1)?;
            Message::Heartbeat {
                node: n,
                state: NmtState::from_code(d[0]).ok_or(CodecError::HeartbeatState {
                    node: n,
                    state: d[0],
                })?,
            }
        }
        _ => Message::Other,
    })
}

/// The server's answer in an 8-byte SDO frame.
fn sdo_answer(d: &[u8]) -> SdoAnswer {
    let command = d[0];
    let index = u16::from_le_bytes([d[1], d[2]]);
    let sub = d[3];
    match command >> 5 {
        // scs = 2: initiate upload response.
        2 => {
            let expedited = command & 0x02 != 0;
            let size_indicated = command & 0x01 != 0;
            if !expedited {
                return SdoAnswer::Segmented { index, sub };
            }
            let len = if size_indicated {
                4 - ((command >> 2) & 0x03)
            } else {
                4
            };
            SdoAnswer::Upload {
                index,
                sub,
                data: [d[4], d[5], d[6], d[7]],
                len,
            }
        }
        // cs = 4: abort transfer.
        4 => SdoAnswer::Abort {
            index,
            sub,
            code: u32::from_le_bytes([d[4], d[5], d[6], d[7]]),
        },
        _ => SdoAnswer::Other { command },
    }
}

/// Bytes a value of `ty` takes in a PDO or an SDO answer (CANopen is little-endian).
pub fn value_size(ty: DataType) -> usize {
    usize::from(ty.registers()) * 2
}

/// Decodes a little-endian value of `ty` at `offset` in `data`.
pub fn decode_value(data: &[u8], offset: usize, ty: DataType) -> Result<f64, CodecError> {
    let size = value_size(ty);
    let b = offset
        .checked_add(size)
        .and_then(|end| data.get(offset..end))
        .ok_or(CodecError::OutsidePdo {
            offset,
            size,
            len: data.len(),
        })?;
    Ok(match ty {
        DataType::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
        DataType::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
        DataType::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
        DataType::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
        DataType::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
    })
}

/// Decodes the value of an expedited SDO upload answer as `ty`. A server that
/// indicates fewer bytes than the type needs is an error; more bytes (a wider
/// object, or a server that does not indicate the size) are cut to the type's size
/// only when that keeps the value (the extra bytes extend it with zeros, or with its
/// sign for a signed type), else an error: cutting would read another number.
pub fn decode_sdo_value(data: &[u8; 4], len: u8, ty: DataType) -> Result<f64, CodecError> {
    let need = value_size(ty);
    let got = usize::from(len.min(4));
    if got < need {
        return Err(CodecError::SdoTooShort { ty, need, got });
    }
    let negative = matches!(ty, DataType::I16 | DataType::I32) && data[need - 1] & 0x80 != 0;
    let extension = if negative { 0xFF } else { 0x00 };
    if data[need..got].iter().any(|&b| b != extension) {
        return Err(CodecError::SdoTooLong {
            ty,
            got,
            bytes: data[..got].iter().map(|b| format!("{b:02X}")).collect(),
        });
    }
    decode_value(&data[..got], 0, ty)
}

/// The name CiA 301 gives an SDO abort code, or "unknown abort code".
pub fn abort_name(code: u32) -> &'static str {
    match code {
        0x0503_0000 => "toggle bit not alternated",
        0x0504_0000 => "SDO protocol timed out",
        0x0504_0001 => "client/server command specifier not valid or unknown",
        0x0504_0002 => "invalid block size",
        0x0504_0003 => "invalid sequence number",
        0x0504_0004 => "CRC error",
        0x0504_0005 => "out of memory",
        0x0601_0000 => "unsupported access to an object",
        0x0601_0001 => "attempt to read a write only object",
        0x0601_0002 => "attempt to write a read only object",
        0x0602_0000 => "object does not exist in the object dictionary",
        0x0604_0041 => "object cannot be mapped to the PDO",
        0x0604_0042 => "the number and length of the objects to be mapped would exceed PDO length",
        0x0604_0043 => "general parameter incompatibility",
        0x0604_0047 => "general internal incompatibility in the device",
        0x0606_0000 => "access failed due to a hardware error",
        0x0607_0010 => "data type does not match, length of service parameter does not match",
        0x0607_0012 => "data type does not match, length of service parameter too high",
        0x0607_0013 => "data type does not match, length of service parameter too low",
        0x0609_0011 => "sub-index does not exist",
        0x0609_0030 => "invalid value for parameter",
        0x0609_0031 => "value of parameter written too high",
        0x0609_0032 => "value of parameter written too low",
        0x0609_0036 => "maximum value is less than minimum value",
        0x060A_0023 => "resource not available: SDO connection",
        0x0800_0000 => "general error",
        0x0800_0020 => "data cannot be transferred or stored to the application",
        0x0800_0021 => "data cannot be transferred or stored because of local control",
        0x0800_0022 => "data cannot be transferred or stored because of the present device state",
        0x0800_0023 => {
            "object dictionary dynamic generation fails or no object dictionary is present"
        }
        0x0800_0024 => "no data available",
        _ => "unknown abort code",
    }
}

/// A short description of an EMCY error code by its class (CiA 301 table 21).
pub fn emcy_class(code: u16) -> &'static str {
    match code & 0xFF00 {
        0x0000 => "error reset or no error",
        0x1000 => "generic error",
        0x2000..=0x2F00 => "current",
        0x3000..=0x3F00 => "voltage",
        0x4000..=0x4F00 => "temperature",
        0x5000..=0x5F00 => "device hardware",
        0x6000..=0x6F00 => "device software",
        0x7000..=0x7F00 => "additional modules",
        0x8000..=0x8F00 => "monitoring",
        0x9000..=0x9F00 => "external error",
        0xF000..=0xFE00 => "additional functions",
        0xFF00 => "device specific",
        _ => "unknown class",
    }
}

#[cfg(test)]
mod tests;
