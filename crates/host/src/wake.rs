//! How a bus member served by another thread's event loop (a TCP client of the socketcand hub)
//! is told that its queue has frames: the in-process bus ([`crate::mem`]) wakes it, the hub
//! ([`crate::socketcand::hub`]) builds and serves it. Below both, so neither names the other
//! for it.

use std::sync::atomic::{AtomicBool, AtomicU8, Ordering};
use std::sync::{Arc, Mutex};

use mio::Waker;

use crate::can::BusState;

/// How a bus member that is a TCP client tells the hub's I/O thread that its queue has frames.
pub(crate) struct Wake {
    /// Frames the client's queue may hold; more are dropped (and counted).
    pub(crate) cap: usize,
    pub(crate) token: usize,
    /// Set while the token is in the ready list, so a burst wakes the thread once.
    pub(crate) pending: AtomicBool,
    /// The client cannot take frames: its socket refused more and [`HubConfig::out_limit`](crate::socketcand::HubConfig::out_limit) bytes wait
    /// for it. Senders then drop its frames (counted) without queueing them or waking the I/O
    /// thread, until the socket is writable again: such a client costs nothing per frame.
    pub(crate) blocked: AtomicBool,
    /// The client is slow (see the hub's `SLOW_QUEUE`): its frames are queued without waking the I/O
    /// thread, which writes it on its own schedule.
    pub(crate) quiet: AtomicBool,
    /// Its controller's error state changed (a [`BusState`] code + 1; 0: nothing new), to be
    /// reported to it as socketcand reports its interface's state.
    pub(crate) ctl_state: AtomicU8,
    /// Frames its transmit queue lost when they joined it at their time (frames kept for
    /// their stamps while the bus waited for a timed participant, docs/CLOCK.md), to be
    /// reported to it (TX overflow).
    pub(crate) tx_overflowed: AtomicBool,
    pub(crate) ready: Arc<Mutex<Vec<usize>>>,
    pub(crate) waker: Arc<Waker>,
}

impl Wake {
    /// Whether frames for the client are to be dropped at once (see `blocked`).
    pub(crate) fn is_blocked(&self) -> bool {
        self.blocked.load(Ordering::Relaxed)
    }

    /// A frame was queued for the client: wakes the I/O thread unless the client is slow.
    pub(crate) fn queued(&self) {
        // Pairs with the fence in `Conn::check_pace`: either this sees `quiet` cleared, or the
        // I/O thread sees this frame in the queue after clearing it (store-load both ways: a
        // frame must not wait in the queue of a client nobody will serve).
        std::sync::atomic::fence(Ordering::SeqCst);
        if !self.quiet.load(Ordering::Relaxed) {
            self.notify();
        }
    }

    pub(crate) fn notify(&self) {
        if !self.pending.swap(true, Ordering::AcqRel) {
            let mut ready = self.ready.lock().unwrap_or_else(|e| e.into_inner());
            let first = ready.is_empty();
            ready.push(self.token);
            drop(ready);
            // The I/O thread takes the whole list per wake-up: whoever made it non-empty has
            // woken it (one eventfd write per burst, not one per client).
            if first {
                let _ = self.waker.wake();
            }
        }
    }

    /// Its transmit queue lost a frame that joined it later than it was sent (on the bus's
    /// driver thread): reported to the client as an overflow at submission is.
    pub(crate) fn tx_overflow(&self) {
        self.tx_overflowed.store(true, Ordering::Release);
        self.notify();
    }

    /// The state [`Wake::controller_state`] left, if not yet reported; taken.
    pub(crate) fn take_state(&self) -> Option<BusState> {
        match self.ctl_state.swap(0, Ordering::AcqRel) {
            1 => Some(BusState::ErrorActive),
            2 => Some(BusState::ErrorPassive),
            3 => Some(BusState::BusOff),
            _ => None,
        }
    }

    /// Its controller's error state changed (on the bus's driver thread).
    pub(crate) fn controller_state(&self, s: BusState) {
        let code = match s {
            BusState::ErrorActive => 1,
            BusState::ErrorPassive => 2,
            BusState::BusOff => 3,
        };
        self.ctl_state.store(code, Ordering::Release);
        self.notify();
    }
}
