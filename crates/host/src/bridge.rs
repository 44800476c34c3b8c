//! Two buses joined into one (`canpos bus bridge URL URL`): every frame received on one side
//! is sent on the other, remote frames with their RTR bit and DLC (SocketCAN natively, a
//! socketcand hub through canpos's RTR extension), in the order received. A SocketCAN
//! interface (a real adapter or vcan, and its gateways) and a hub channel then share one bus.
//!
//! A transport never echoes its own frames back, so nothing loops. A frame the other side
//! cannot carry (a remote frame with DLC > 0 towards a socketcand server without the RTR
//! extension) is counted in [`BridgeStats::unsendable`], never silently lost.

use std::io;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use crossbeam_channel::Select;

use crate::can::{BusState, Transport};

/// Counters of a bridge.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BridgeStats {
    /// Frames forwarded from the first bus to the second.
    pub a_to_b: u64,
    /// Frames forwarded from the second bus to the first.
    pub b_to_a: u64,
    /// Frames one side could not take (refused by the transport).
    pub unsendable: u64,
}

/// Forwards between `a` and `b` until `stop` is set (checked at least every 100 ms) or one side
/// dies; returns the counters, or the error of the side that died.
pub fn run(
    a: &mut dyn Transport,
    b: &mut dyn Transport,
    stop: &AtomicBool,
) -> io::Result<BridgeStats> {
    let mut st = BridgeStats::default();
    let mut states = (a.bus_state(), b.bus_state());
    while !stop.load(Ordering::Relaxed) {
        let ready = {
            let mut sel = Select::new();
            sel.recv(a.receiver());
            sel.recv(b.receiver());
            sel.ready_timeout(Duration::from_millis(100)).ok()
        };
        if let Some(side) = ready {
            // Drain what is there, one side after the other, each in its own order.
            let (from, to, count): (&mut dyn Transport, &mut dyn Transport, &mut u64) = if side == 0
            {
                (&mut *a, &mut *b, &mut st.a_to_b)
            } else {
                (&mut *b, &mut *a, &mut st.b_to_a)
            };
            for _ in 0..1024 {
                let Some(rx) = from.try_recv()? else { break };
                match to.send(&rx.frame) {
                    Ok(()) => *count += 1,
                    Err(e) if e.kind() == io::ErrorKind::InvalidInput => {
                        st.unsendable += 1;
                        if st.unsendable.is_power_of_two() {
                            tracing::warn!(frame = ?rx.frame, total = st.unsendable, "cannot forward: {e}");
                        }
                    }
                    Err(e) => return Err(e),
                }
            }
        }
        let now = (a.bus_state(), b.bus_state());
        if now != states {
            // Each side's controller confines its own errors (ISO 11898-1): a state change on
            // one side is logged, and is no part of the other side's nodes' state.
            if now.0 != states.0 {
                log_state("first", now.0);
            }
            if now.1 != states.1 {
                log_state("second", now.1);
            }
            states = now;
        }
    }
    Ok(st)
}

fn log_state(side: &str, s: BusState) {
    tracing::warn!(side, state = ?s, "bridge: CAN controller state changed");
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mem::MemBus;
    use canpos_stack::Frame;
    use std::sync::Arc;

    #[test]
    fn frames_cross_both_ways_in_order_with_rtr() {
        // Instant buses: this is about forwarding; on paced buses 100 frames at once would
        // arbitrate (and overflow a controller's queue) as on a real bus.
        let (x, y) = (MemBus::instant(), MemBus::instant());
        let (mut xa, mut ya) = (x.attach(), y.attach());
        let mut xb: Box<dyn Transport> = Box::new(x.attach());
        let mut yb: Box<dyn Transport> = Box::new(y.attach());
        let stop = Arc::new(AtomicBool::new(false));
        let s2 = stop.clone();
        let t = std::thread::spawn(move || run(&mut *xb, &mut *yb, &s2));
        let frames: Vec<Frame> = (0..100u16)
            .map(|i| Frame::new(0x100 + i, &[i as u8]).unwrap())
            .chain([Frame::remote(0x77F, false, 1).unwrap()])
            .collect();
        for f in &frames {
            xa.send(f).unwrap();
        }
        for f in &frames {
            let got = ya
                .recv_timeout(Some(Duration::from_secs(5)))
                .unwrap()
                .unwrap();
            assert_eq!(got.frame, *f);
        }
        ya.send(&Frame::new(0x5FF, &[1]).unwrap()).unwrap();
        let back = xa
            .recv_timeout(Some(Duration::from_secs(5)))
            .unwrap()
            .unwrap();
        assert_eq!(back.frame, Frame::new(0x5FF, &[1]).unwrap());
        // Nothing loops back to where it came from.
        assert_eq!(
            xa.recv_timeout(Some(Duration::from_millis(50))).unwrap(),
            None
        );
        stop.store(true, Ordering::Relaxed);
        let st = t.join().unwrap().unwrap();
        assert_eq!((st.a_to_b, st.b_to_a, st.unsendable), (101, 1, 0));
    }
}
