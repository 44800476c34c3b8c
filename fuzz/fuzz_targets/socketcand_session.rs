//! The hub's command handling (a socketcand `Session`) on arbitrary client input, as the hub
//! drives it (`Decoder::next`, over-long elements reported, statistics and send jobs polled on
//! a virtual clock).
//!
//! Beyond "no panic": every element draws at most one reply of at most `MAX_REPLY` bytes, made
//! of whole elements (so the hub's bound, twice `out_limit` and one reply, holds whatever the
//! client sends); a poll adds at most one statistics line and one frame per send job; error
//! frames go on the bus only for the classes seen on the wire; frames have a DLC of at most 8.
#![no_main]

use std::time::{Duration, Instant};

use canpos_host::socketcand::codec::{err_class, Decoder, Element, Piece};
use canpos_host::socketcand::session::{Effect, Session, MAX_JOBS};

/// The longest reply of one element (`< error element longer than 256 bytes >` and the
/// statistics line of four 32-bit counters are under it).
const MAX_REPLY: usize = 128;

fn whole_elements(bytes: &[u8]) -> bool {
    if bytes.is_empty() {
        return true;
    }
    let mut d = Decoder::new();
    let n = d.feed_parse(bytes).len();
    n >= 1 && d.skipped() == 0 && !d.is_partial()
}

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let t0 = Instant::now();
    let mut s = Session::new();
    let mut d = Decoder::new();
    let mut out = Vec::new();
    let mut frames = Vec::new();
    let mut rest = data;
    let mut step = 0u64;
    while !rest.is_empty() {
        let (n, piece) = d.next(rest);
        assert!(n > 0 && n <= rest.len());
        rest = &rest[n..];
        let el = match piece {
            Some(Piece::Body(b)) => Element::parse(b),
            Some(Piece::TooLong) => Element::TooLong,
            None => continue,
        };
        step += 1;
        // Elements 0.37 ms apart: statistics (10 ms at least) and send jobs come due.
        let now = t0 + Duration::from_micros(step * 370);
        out.clear();
        let fx = s.handle(el, now, &mut out, |c| !c.is_empty() && c.len() <= 64);
        assert!(out.len() <= MAX_REPLY, "a reply of {} bytes", out.len());
        assert!(whole_elements(&out), "{:?}", String::from_utf8_lossy(&out));
        assert!(fx.len() <= 2, "{fx:?}");
        for e in fx {
            match e {
                Effect::Send(f) => assert!(f.dlc() <= 8),
                Effect::ErrorFlag(e) => assert_ne!(e.class & err_class::ON_THE_WIRE, 0),
                _ => {}
            }
        }
        out.clear();
        frames.clear();
        if s.next_deadline().is_some_and(|t| t <= now) {
            s.poll(now, &mut out, &mut frames);
        }
        assert!(out.len() <= MAX_REPLY && whole_elements(&out));
        assert!(frames.len() <= MAX_JOBS);
    }
});
