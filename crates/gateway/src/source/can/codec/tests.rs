use super::*;
use proptest::prelude::*;

fn f(id: u16, d: &[u8]) -> RawFrame {
    RawFrame::new(id, d).expect("valid frame")
}

#[test]
fn raw_frame_limits() {
    assert!(RawFrame::new(0x800, &[]).is_none());
    assert!(RawFrame::new(0x7FF, &[0; 9]).is_none());
    assert_eq!(f(0x181, &[1, 2]).data(), &[1, 2]);
    assert_eq!(f(0x181, &[0xD0, 0x07]).to_string(), "181#D007");
    assert_eq!(sync().to_string(), "080#");
}

#[test]
fn encodes_master_frames() {
    assert_eq!(nmt(NmtCommand::Start, 5).to_string(), "000#0105");
    assert_eq!(nmt(NmtCommand::ResetNode, 0).to_string(), "000#8100");
    assert_eq!(
        sdo_upload_request(0x10, 0x6401, 2).to_string(),
        "610#4001640200000000"
    );
    assert_eq!(
        sdo_abort(5, 0x1008, 0, ABORT_TOO_LONG).to_string(),
        "605#8008100012000706"
    );
    assert_eq!(abort_name(ABORT_TIMED_OUT), "SDO protocol timed out");
    assert_eq!(tpdo_cob_id(1, 5), 0x185);
    assert_eq!(tpdo_cob_id(4, 0x7F), 0x4FF);
}

#[test]
fn decodes_each_kind() {
    assert_eq!(
        decode(&f(0, &[1, 5])),
        Ok(Message::Nmt {
            command: Some(NmtCommand::Start),
            code: 1,
            node: 5
        })
    );
    assert_eq!(decode(&f(0x80, &[])), Ok(Message::Sync { counter: None }));
    assert_eq!(
        decode(&f(0x80, &[7])),
        Ok(Message::Sync { counter: Some(7) })
    );
    assert_eq!(
        decode(&f(0x85, &[0x10, 0x42, 0x05, 1, 2, 3, 4, 5])),
        Ok(Message::Emcy {
            node: 5,
            code: 0x4210,
            register: 5,
            vendor: [1, 2, 3, 4, 5]
        })
    );
    match decode(&f(0x285, &[0xD0, 0x07, 0x01])) {
        Ok(Message::Tpdo {
            node: 5,
            pdo: 2,
            data,
            len: 3,
        }) => assert_eq!(&data[..3], &[0xD0, 0x07, 0x01]),
        other => panic!("{other:?}"),
    }
    assert_eq!(
        decode(&f(0x305, &[])),
        Ok(Message::Rpdo { node: 5, pdo: 2 })
    );
    assert_eq!(
        decode(&f(0x705, &[0x05])),
        Ok(Message::Heartbeat {
            node: 5,
            state: NmtState::Operational
        })
    );
    assert_eq!(
        decode(&f(0x705, &[0x00])),
        Ok(Message::Heartbeat {
            node: 5,
            state: NmtState::BootUp
        })
    );
    assert_eq!(decode(&f(0x100, &[1, 2, 3])), Ok(Message::Other));
    assert_eq!(decode(&f(0x7E5, &[1])), Ok(Message::Other));
}

#[test]
fn decodes_sdo_answers() {
    // 0x4B: expedited, size indicated, 2 bytes unused -> 2 bytes.
    let up = decode(&f(0x585, &[0x4B, 0x01, 0x64, 0x02, 0xD0, 0x07, 0xAA, 0xBB]));
    assert_eq!(
        up,
        Ok(Message::SdoResponse {
            node: 5,
            answer: SdoAnswer::Upload {
                index: 0x6401,
                sub: 2,
                data: [0xD0, 0x07, 0xAA, 0xBB],
                len: 2
            }
        })
    );
    // 0x43: 4 bytes; 0x42: size not indicated -> 4; 0x4F: 1 byte.
    for (cs, len) in [(0x43u8, 4u8), (0x42, 4), (0x4F, 1), (0x47, 3)] {
        match decode(&f(0x585, &[cs, 0, 0x10, 0, 1, 2, 3, 4])) {
            Ok(Message::SdoResponse {
                answer: SdoAnswer::Upload { len: l, index, .. },
                ..
            }) => {
                assert_eq!((l, index), (len, 0x1000), "command {cs:#x}");
            }
            other => panic!("{cs:#x}: {other:?}"),
        }
    }
    assert_eq!(
        decode(&f(0x585, &[0x41, 0x18, 0x10, 0x01, 20, 0, 0, 0])),
        Ok(Message::SdoResponse {
            node: 5,
            answer: SdoAnswer::Segmented {
                index: 0x1018,
                sub: 1
            }
        })
    );
    let abort = decode(&f(0x585, &[0x80, 0x00, 0x20, 0x00, 0x00, 0x00, 0x02, 0x06]));
    assert_eq!(
        abort,
        Ok(Message::SdoResponse {
            node: 5,
            answer: SdoAnswer::Abort {
                index: 0x2000,
                sub: 0,
                code: 0x0602_0000
            }
        })
    );
    assert_eq!(
        abort_name(0x0602_0000),
        "object does not exist in the object dictionary"
    );
    assert_eq!(abort_name(0x0609_0011), "sub-index does not exist");
    assert_eq!(abort_name(0x1234_5678), "unknown abort code");
    assert_eq!(
        decode(&f(0x585, &[0x60, 0, 0, 0, 0, 0, 0, 0])),
        Ok(Message::SdoResponse {
            node: 5,
            answer: SdoAnswer::Other { command: 0x60 }
        })
    );
}

#[test]
fn every_malformed_length_is_an_error() {
    // (COB-ID, lengths that are valid)
    let kinds: [(u16, &[usize]); 6] = [
        (0x000, &[2]),
        (0x080, &[0, 1]),
        (0x085, &[8]),
        (0x585, &[8]),
        (0x605, &[8]),
        (0x705, &[1]),
    ];
    for (id, valid) in kinds {
        for len in 0..=8usize {
            let data = vec![0x05u8; len];
            let r = decode(&f(id, &data));
            if valid.contains(&len) {
                assert!(r.is_ok(), "{id:03X} len {len}: {r:?}");
            } else {
                match r {
                    Err(CodecError::Length { cob_id, got, .. }) => {
                        assert_eq!((cob_id, got), (id, len));
                    }
                    other => panic!("{id:03X} len {len}: {other:?}"),
                }
            }
        }
    }
    // A PDO may be any length.
    for len in 0..=8usize {
        assert!(decode(&f(0x185, &vec![0; len])).is_ok());
    }
    assert_eq!(
        decode(&f(0x705, &[0x33])),
        Err(CodecError::HeartbeatState {
            node: 5,
            state: 0x33
        })
    );
    assert!(decode(&f(0x085, &[0; 7]))
        .expect_err("short EMCY")
        .to_string()
        .contains("EMCY frame 085h has 7 data bytes, expected 8"));
}

#[test]
fn decodes_values() {
    let d = [0xD0, 0x07, 0xFF, 0xFF, 0x00, 0x00, 0xC8, 0x41];
    assert_eq!(decode_value(&d, 0, DataType::U16), Ok(2000.0));
    assert_eq!(decode_value(&d, 2, DataType::I16), Ok(-1.0));
    assert_eq!(decode_value(&d, 2, DataType::U16), Ok(65535.0));
    assert_eq!(decode_value(&d, 4, DataType::F32), Ok(25.0));
    assert_eq!(
        decode_value(&d, 0, DataType::U32),
        Ok(f64::from(0xFFFF_07D0u32))
    );
    assert_eq!(
        decode_value(&d, 0, DataType::I32),
        Ok(f64::from(0xFFFF_07D0u32 as i32))
    );
    assert_eq!(
        decode_value(&d, 6, DataType::F32),
        Err(CodecError::OutsidePdo {
            offset: 6,
            size: 4,
            len: 8
        })
    );
    assert!(decode_value(&d[..3], 2, DataType::U16).is_err());
    assert!(decode_value(&d, usize::MAX, DataType::U16).is_err());
    assert_eq!(
        decode_sdo_value(&[0xD0, 0x07, 0, 0], 2, DataType::U16),
        Ok(2000.0)
    );
    assert_eq!(
        decode_sdo_value(&[0xD0, 0x07, 0, 0], 4, DataType::U16),
        Ok(2000.0)
    );
    assert_eq!(
        decode_sdo_value(&[0xD0, 0, 0, 0], 1, DataType::U16),
        Err(CodecError::SdoTooShort {
            ty: DataType::U16,
            need: 2,
            got: 1
        })
    );
    // A wider object is cut only when that keeps its value.
    assert_eq!(
        decode_sdo_value(&[0xFF, 0xFF, 0xFF, 0xFF], 4, DataType::I16),
        Ok(-1.0)
    );
    assert_eq!(
        decode_sdo_value(&[0xFF, 0xFF, 0, 0], 4, DataType::U16),
        Ok(65535.0)
    );
    assert_eq!(
        decode_sdo_value(&[0xFF, 0xFF, 0, 0], 4, DataType::I16),
        Err(CodecError::SdoTooLong {
            ty: DataType::I16,
            got: 4,
            bytes: "FFFF0000".into()
        })
    );
    // 25.0 degC as f32 (a CiA 404 REAL32 object) read as i16 would give 0.
    let e = decode_sdo_value(&25.0f32.to_le_bytes(), 4, DataType::I16).expect_err("f32 as i16");
    assert!(
        e.to_string()
            .contains("4 data bytes (0000C841), a value wider than data_type = \"i16\""),
        "{e}"
    );
    assert!(decode_sdo_value(&[0xD0, 0x07, 0x01, 0], 3, DataType::U16).is_err());
    assert_eq!(
        decode_sdo_value(&[0xD0, 0x07, 0x01, 0x99], 3, DataType::U16),
        Err(CodecError::SdoTooLong {
            ty: DataType::U16,
            got: 3,
            bytes: "D00701".into()
        }),
        "bytes past the indicated size do not count"
    );
    assert_eq!(emcy_class(0x4210), "temperature");
    assert_eq!(emcy_class(0x0000), "error reset or no error");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(20_000))]

    /// Any frame at all decodes to a value or an error, never a panic, and the
    /// decoders of values accept any offset.
    #[test]
    fn random_frames_never_panic(id in 0u16..=0x7FF, data in proptest::collection::vec(any::<u8>(), 0..=8), offset in 0usize..16) {
        let frame = RawFrame::new(id, &data).expect("within limits");
        let _ = decode(&frame);
        for ty in [DataType::U16, DataType::I16, DataType::U32, DataType::I32, DataType::F32] {
            let r = decode_value(frame.data(), offset, ty);
            prop_assert_eq!(r.is_ok(), offset + value_size(ty) <= data.len());
            if data.len() >= 4 {
                let mut d4 = [0u8; 4];
                d4.copy_from_slice(&data[..4]);
                let _ = decode_sdo_value(&d4, data[0], ty);
            }
        }
    }

    /// Frames built by the encoders decode to what was encoded.
    #[test]
    fn encoders_round_trip(node in 1u8..=127, index in any::<u16>(), sub in any::<u8>()) {
        match decode(&sdo_upload_request(node, index, sub)) {
            Ok(Message::SdoRequest { node: n, command: 0x40, index: i, sub: s, .. }) => {
                prop_assert_eq!((n, i, s), (node, index, sub));
            }
            other => prop_assert!(false, "{:?}", other),
        }
        prop_assert_eq!(decode(&nmt(NmtCommand::Start, node)), Ok(Message::Nmt { command: Some(NmtCommand::Start), code: 1, node }));
    }
}
