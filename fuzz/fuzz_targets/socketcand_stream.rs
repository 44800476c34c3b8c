//! The socketcand stream decoder and element parser on arbitrary bytes.
//!
//! Beyond "no panic": the elements must not depend on how TCP split the stream; every frame
//! parsed re-encodes (`write_send` / `write_frame`) to text that parses back to the same frame;
//! no frame has a DLC above 8.
#![no_main]

use std::time::{Duration, UNIX_EPOCH};

use canpos_host::socketcand::codec::{self, Decoder, Element};

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let Some((&cut_seed, stream)) = data.split_first() else {
        return;
    };
    let mut whole = Decoder::new();
    let elements = whole.feed_parse(stream);

    // The same bytes in chunks of 1…16 bytes (chosen by the first byte) decode identically.
    let chunk = usize::from(cut_seed % 16) + 1;
    let mut split = Decoder::new();
    let mut pieces = Vec::new();
    for c in stream.chunks(chunk) {
        pieces.extend(split.feed_parse(c));
    }
    assert_eq!(
        elements, pieces,
        "elements depend on the split (chunk {chunk})"
    );
    assert_eq!(whole.skipped(), split.skipped());
    assert_eq!(whole.is_partial(), split.is_partial());

    for e in &elements {
        match e {
            Element::Send(f) => {
                assert!(f.dlc() <= 8);
                let mut out = Vec::new();
                if codec::write_send(&mut out, f) {
                    let back = Decoder::new().feed_parse(&out);
                    assert_eq!(back, vec![Element::Send(*f)], "send round trip of {f:?}");
                }
            }
            Element::Frame(rx) => {
                assert!(rx.frame.dlc() <= 8);
                // The wire has µs resolution: compare with the timestamp truncated to µs.
                let t = rx.timestamp.duration_since(UNIX_EPOCH).unwrap_or_default();
                let t_us = UNIX_EPOCH + Duration::new(t.as_secs(), t.subsec_micros() * 1000);
                let mut out = Vec::new();
                if codec::write_frame(&mut out, &rx.frame, rx.timestamp) {
                    match Decoder::new().feed_parse(&out).as_slice() {
                        [Element::Frame(b)] => {
                            assert_eq!(b.frame, rx.frame, "frame round trip");
                            assert_eq!(b.timestamp, t_us, "timestamp round trip");
                        }
                        other => panic!("frame round trip of {rx:?} gave {other:?}"),
                    }
                }
            }
            _ => {}
        }
    }
});
