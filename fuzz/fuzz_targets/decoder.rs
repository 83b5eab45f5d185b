//! Fuzzes the Teensy protocol decoder: arbitrary bytes, fed in data-driven chunks, must never
//! panic, never grow the buffer without bound, and only ever yield packets present in the input.
//! Run: `cd fuzz && cargo +nightly fuzz run decoder` (the same invariants run on stable as the
//! property tests in services/coilbus/tests/protocol_props.rs).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    millinav_teensy_protocol::check_decoder_invariants(data);
});
