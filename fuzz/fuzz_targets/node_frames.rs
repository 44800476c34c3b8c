//! The device core of every model fed arbitrary frame sequences, time steps, samples and power
//! cycles; the CANopen invariants are checked inside (see `crates/models/tests/suite/common/harness.rs`,
//! shared with the `frame_sequence_props` property test).
#![no_main]

#[path = "../../crates/models/tests/suite/common/harness.rs"]
mod harness;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    if let Err(e) = harness::Checker::run(data) {
        panic!("invariant broken: {e}");
    }
});
