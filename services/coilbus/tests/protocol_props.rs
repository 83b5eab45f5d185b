//! Property tests of the Teensy protocol: round trips, arbitrary bytes, frames in garbage,
//! corruption. The fuzz target (`fuzz/fuzz_targets/decoder.rs`) checks the same invariants.

use millinav_coilbus::protocol::{
    check_decoder_invariants, encode, CoilValues, Decoder, Message, Packet, MAX_COILS, MAX_FRAME,
    SYNC,
};
use proptest::prelude::*;

/// Any coil count the protocol allows (0 to MAX_COILS), any currents.
fn currents() -> impl Strategy<Value = CoilValues> {
    proptest::collection::vec(any::<i32>(), 0..=MAX_COILS)
        .prop_map(|values| CoilValues::new(&values).expect("at most MAX_COILS values"))
}

fn message() -> impl Strategy<Value = Message> {
    prop_oneof![
        (any::<u64>(), any::<u8>(), currents()).prop_map(|(frame_seq, flags, currents_ma)| {
            Message::SetCurrents {
                frame_seq,
                flags,
                currents_ma,
            }
        }),
        (any::<u32>(), any::<u8>())
            .prop_map(|(acked_seq, status)| Message::Ack { acked_seq, status }),
        (currents(), any::<bool>(), any::<u32>(), any::<u32>()).prop_map(
            |(applied_ma, watchdog_tripped, rx_errors, frames_received)| Message::Telemetry {
                applied_ma,
                watchdog_tripped,
                rx_errors,
                frames_received,
            }
        ),
    ]
}

fn packet() -> impl Strategy<Value = Packet> {
    (any::<u32>(), message()).prop_map(|(seq, message)| Packet { seq, message })
}

/// Feeds `stream` in chunks of the given sizes (cycled), collecting packets.
fn decode_chunked(decoder: &mut Decoder, stream: &[u8], chunks: &[usize]) -> Vec<Packet> {
    let mut out = Vec::new();
    let mut rest = stream;
    let mut i = 0;
    while !rest.is_empty() {
        let n = chunks
            .get(i % chunks.len().max(1))
            .copied()
            .unwrap_or(7)
            .clamp(1, rest.len());
        out.extend(decoder.push(&rest[..n]));
        rest = &rest[n..];
        i += 1;
    }
    out
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn every_message_round_trips(p in packet()) {
        let mut decoder = Decoder::new();
        prop_assert_eq!(decoder.push(&encode(&p)), vec![p]);
        prop_assert_eq!(decoder.counters.errors(), 0);
    }

    #[test]
    fn arbitrary_bytes_never_panic(data in proptest::collection::vec(any::<u8>(), 0..2048)) {
        check_decoder_invariants(&data);
    }

    #[test]
    fn sync_heavy_bytes_never_panic(
        data in proptest::collection::vec(prop_oneof![Just(0xA5u8), Just(0x5Au8), any::<u8>()], 0..2048)
    ) {
        check_decoder_invariants(&data);
    }

    #[test]
    fn frames_embedded_in_garbage_are_all_recovered(
        items in proptest::collection::vec(
            (packet(), proptest::collection::vec(any::<u8>(), 0..40)), 1..12),
        lead in proptest::collection::vec(any::<u8>(), 0..40),
        chunks in proptest::collection::vec(1usize..80, 1..8),
    ) {
        let mut stream = lead;
        let mut expected = Vec::new();
        for (p, garbage) in &items {
            stream.extend_from_slice(&encode(p));
            stream.extend(garbage);
            expected.push(p.clone());
        }
        let mut decoder = Decoder::new();
        let got = decode_chunked(&mut decoder, &stream, &chunks);
        // Garbage could in principle forge a frame (sync + valid CRC, p ≈ 2⁻³²): only the
        // expected packets, in order, may come out, and all of them must.
        prop_assert_eq!(got, expected);
        check_decoder_invariants(&stream);
    }

    #[test]
    fn corrupted_frames_are_rejected_and_counted(
        bad in packet(),
        good in packet(),
        bit in 0usize..8,
        at in any::<prop::sample::Index>(),
    ) {
        let mut corrupted = encode(&bad).to_vec();
        // Any byte after the sync word: version, kind, length, seq, payload or CRC.
        let i = SYNC.len() + at.index(corrupted.len() - SYNC.len());
        corrupted[i] ^= 1 << bit;
        let mut stream = corrupted.clone();
        stream.extend_from_slice(&encode(&good));
        // A corrupted length may make the decoder wait for more bytes: pad with zeros.
        stream.extend([0u8; 2 * MAX_FRAME]);
        let mut decoder = Decoder::new();
        let got = decoder.push(&stream);
        prop_assert_eq!(got, vec![good]);
        prop_assert!(decoder.counters.errors() >= 1, "corruption at byte {} not counted: {:?}", i, decoder.counters);
    }

    #[test]
    fn truncated_frames_never_decode(p in packet(), cut in any::<prop::sample::Index>()) {
        let bytes = encode(&p);
        let n = cut.index(bytes.len());
        let mut decoder = Decoder::new();
        prop_assert!(decoder.push(&bytes[..n]).is_empty());
        // ... and the rest completes it.
        prop_assert_eq!(decoder.push(&bytes[n..]), vec![p]);
    }
}
