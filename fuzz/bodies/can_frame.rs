//! Fuzz body: the CANopen frame codec on arbitrary identifier, length and data.
//!
//! Input: `id_hi id_lo len data...` (the identifier and length are taken as given, so
//! invalid ones reach `RawFrame::new`), then the value decoders on what a frame
//! carries: every data type at every offset of a PDO (and past its end), and the
//! expedited SDO answer with its indicated size.

use compgate_gateway::source::can::codec::{self, Message, RawFrame, SdoAnswer};
use compgate_gateway::source::plan::DataType;

/// Decodes the frame and the values in it; any result but a panic is fine.
pub fn run(data: &[u8]) {
    let [id_hi, id_lo, len, rest @ ..] = data else {
        return;
    };
    let cob_id = u16::from_be_bytes([*id_hi, *id_lo]);
    let len = usize::from(*len).min(rest.len());
    let Some(frame) = RawFrame::new(cob_id, &rest[..len]) else {
        assert!(cob_id > 0x7FF || len > codec::MAX_DATA_BYTES);
        return;
    };
    assert_eq!(frame.data(), &rest[..len]);
    let _ = frame.to_string();
    let Ok(message) = codec::decode(&frame) else {
        return;
    };
    match message {
        Message::Tpdo { data, len, .. } => {
            let payload = data.get(..usize::from(len)).unwrap_or(&data);
            for ty in DataType::ALL {
                for offset in [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, usize::MAX - 1, usize::MAX] {
                    if let Ok(v) = codec::decode_value(payload, offset, ty) {
                        assert!(offset + codec::value_size(ty) <= payload.len());
                        assert!(ty == DataType::F32 || v.is_finite());
                    }
                }
            }
        }
        Message::SdoResponse {
            answer: SdoAnswer::Upload { data, len, .. },
            ..
        } => {
            for ty in DataType::ALL {
                let _ = codec::decode_sdo_value(&data, len, ty);
            }
            // Any indicated size, not only the ones the decoder lets through.
            for l in [0, 1, 2, 3, 4, 5, 0xFF] {
                for ty in DataType::ALL {
                    let _ = codec::decode_sdo_value(&data, l, ty);
                }
            }
        }
        Message::SdoResponse {
            answer: SdoAnswer::Abort { code, .. },
            ..
        } => {
            let _ = codec::abort_name(code);
        }
        Message::Emcy { code, .. } => {
            let _ = codec::emcy_class(code);
        }
        _ => {}
    }
}
