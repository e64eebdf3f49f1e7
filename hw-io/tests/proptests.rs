//! Property tests: nothing panics on any input, and every codec round-trips.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use hw_io::can::candump::{CandumpReader, CandumpWriter, parse_line};
use hw_io::can::{
    CanFrame, CanId, CounterError, DecodeError, EncoderConfig, JointAssembler, JointEncoder, Message, NmtState, NodeId,
    SyncCounter, TimedFrame, next_sync_counter,
};
use proptest::prelude::*;

fn any_frame() -> impl Strategy<Value = CanFrame> {
    (any::<bool>(), any::<bool>(), 0u32..=0x1FFF_FFFF, 0u8..=8, any::<[u8; 8]>()).prop_map(
        |(ext, rtr, id, dlc, data)| {
            let id = if ext { id } else { id & 0x7FF };
            CanFrame::from_parts(id, ext, rtr, dlc, data).unwrap()
        },
    )
}

fn any_node() -> impl Strategy<Value = NodeId> {
    (1u8..=127).prop_map(|k| NodeId::new(k).unwrap())
}

fn any_message() -> impl Strategy<Value = Message> {
    let state = prop_oneof![
        Just(NmtState::BootUp),
        Just(NmtState::Stopped),
        Just(NmtState::Operational),
        Just(NmtState::PreOperational)
    ];
    prop_oneof![
        (1u8..=240).prop_map(|counter| Message::Sync { counter }),
        (any_node(), any::<[i32; 2]>()).prop_map(|(node, counts)| Message::Tpdo { node, counts }),
        (any_node(), state).prop_map(|(node, state)| Message::Heartbeat { node, state }),
        (any_node(), any::<u16>(), any::<u8>(), any::<[u8; 5]>())
            .prop_map(|(node, code, register, vendor)| Message::Emcy { node, code, register, vendor }),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 4096, ..ProptestConfig::default() })]

    /// Arbitrary raw id/flags/dlc/data: frame construction and decoding never panic, and
    /// the outcome is consistent with the frame.
    #[test]
    fn decoder_never_panics(id in any::<u32>(), ext in any::<bool>(), rtr in any::<bool>(),
                            dlc in any::<u8>(), data in any::<[u8; 8]>()) {
        let Ok(frame) = CanFrame::from_parts(id, ext, rtr, dlc, data) else {
            prop_assert!(dlc > 8 || (ext && id > 0x1FFF_FFFF) || (!ext && id > 0x7FF));
            return Ok(());
        };
        match Message::decode(&frame) {
            Ok(msg) => {
                prop_assert!(!ext && !rtr);
                // A decoded message re-encodes to the very same frame.
                prop_assert_eq!(msg.encode().unwrap(), frame);
            }
            Err(DecodeError::ExtendedId { .. }) => prop_assert!(ext && !rtr),
            Err(DecodeError::RemoteFrame { .. }) => prop_assert!(rtr),
            Err(DecodeError::WrongDlc { got, expected, .. }) => {
                prop_assert_eq!(got, dlc);
                prop_assert_ne!(got, expected);
            }
            Err(DecodeError::UnknownId { id: got }) => prop_assert_eq!(u32::from(got), id),
            Err(DecodeError::SyncCounterOutOfRange { counter }) => {
                prop_assert!(counter == 0 || counter > 240)
            }
            Err(DecodeError::UnknownNmtState { state, .. }) => {
                prop_assert!(![0x00, 0x04, 0x05, 0x7F].contains(&state))
            }
        }
    }

    #[test]
    fn messages_round_trip(msg in any_message()) {
        let frame = msg.encode().unwrap();
        prop_assert_eq!(Message::decode(&frame), Ok(msg));
        prop_assert_eq!(frame.id(), CanId::Standard(msg.cob_id()));
    }

    /// Arbitrary text never panics the candump parser.
    #[test]
    fn candump_parser_never_panics(line in ".{0,80}") {
        let _ = parse_line(&line);
    }

    /// Lines built from candump's alphabet (so that many of them get deep into the parser).
    #[test]
    fn candump_parser_never_panics_on_near_valid_lines(
        line in r"\(?[0-9.]{0,12}\)? ?[a-z0-9]{0,5} [0-9A-Fa-frR#._]{0,24}( [RTX])?"
    ) {
        let _ = parse_line(&line);
    }

    /// Any frame, written with our writer, reads back identically.
    #[test]
    fn candump_round_trip(frames in proptest::collection::vec((any_frame(), any::<u64>()), 0..20)) {
        let mut w = CandumpWriter::new(Vec::new(), "vcan0").unwrap();
        let timed: Vec<TimedFrame> = frames
            .into_iter()
            .map(|(frame, t)| TimedFrame { frame, unix_time_us: t % 10_000_000_000_000_000 })
            .collect();
        for t in &timed {
            w.write(t).unwrap();
        }
        let text = w.into_inner();
        let back: Vec<TimedFrame> = CandumpReader::new(&text[..]).collect::<Result<_, _>>().unwrap();
        prop_assert_eq!(back, timed);
    }

    /// counts -> rad -> counts is the identity for every joint configuration.
    #[test]
    fn counts_rad_round_trip(counts in any::<i32>(), cpr in 1u32..=(1 << 24),
                             offset in any::<i32>(), negative in any::<bool>()) {
        let j = JointEncoder { counts_per_rev: cpr, zero_offset_counts: offset, sign: if negative { -1 } else { 1 } };
        let rad = j.counts_to_rad(counts);
        prop_assert!(rad.is_finite());
        prop_assert_eq!(j.rad_to_counts(rad), Ok(counts));
    }

    /// rad -> counts never panics and is within half a count of the angle.
    #[test]
    fn rad_to_counts_rounds_to_nearest(rad in -100.0f64..100.0) {
        let j = JointEncoder::default();
        let c = j.rad_to_counts(rad).unwrap();
        let err_counts = (j.counts_to_rad(c) - rad) / (std::f64::consts::TAU / 131_072.0);
        prop_assert!(err_counts.abs() <= 0.5 + 1e-9);
    }

    /// The tracker flags exactly the counters that are not the successor of the previous one.
    #[test]
    fn sync_counter_flags_exactly_the_gaps(seq in proptest::collection::vec(any::<u8>(), 1..300)) {
        let mut t = SyncCounter::new();
        let mut last: Option<u8> = None;
        for c in seq {
            let r = t.observe(c);
            if !(1..=240).contains(&c) {
                prop_assert_eq!(r, Err(CounterError::OutOfRange { got: c }));
                continue;
            }
            match last {
                Some(l) if next_sync_counter(l) != c => {
                    prop_assert_eq!(r, Err(CounterError::Gap { expected: next_sync_counter(l), got: c }))
                }
                _ => prop_assert_eq!(r, Ok(())),
            }
            last = Some(c);
        }
    }

    /// The assembler never panics on any TPDO stream, and completes exactly when every
    /// configured node has answered since the last start_cycle.
    #[test]
    fn assembler_completes_exactly_when_all_nodes_answered(
        msgs in proptest::collection::vec((1u8..=5, any::<[i32; 2]>(), any::<bool>()), 0..30)
    ) {
        let mut a = JointAssembler::from_config(&EncoderConfig::default()).unwrap();
        let mut seen = [false; 3];
        for (k, counts, restart) in msgs {
            if restart {
                a.start_cycle();
                seen = [false; 3];
            }
            let _ = a.accept(&Message::Tpdo { node: NodeId::new(k).unwrap(), counts });
            if k <= 3 {
                seen[usize::from(k) - 1] = true;
            }
            prop_assert_eq!(a.is_complete(), seen.iter().all(|s| *s));
            prop_assert_eq!(a.missing().len(), seen.iter().filter(|s| !**s).count());
        }
    }
}
