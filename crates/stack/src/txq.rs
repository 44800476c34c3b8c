//! The node's transmit queue: a fixed ring of frames waiting for the host to send them.

use crate::wire::Frame;

pub use crate::config::TXQ_LEN;
/// Ring index mask (the capacity is a power of two: masks instead of `%` and bounds checks).
const MASK: usize = TXQ_LEN - 1;

/// Fixed-capacity FIFO of frames; when full, new frames are dropped and counted (the CAN
/// overrun condition a real controller reports).
#[derive(Clone)]
pub struct TxQueue {
    buf: [Frame; TXQ_LEN],
    head: usize,
    len: usize,
    /// Frames dropped because the queue was full.
    pub overruns: u32,
}

impl core::default::Default for TxQueue {
    fn default() -> Self {
        TxQueue {
            buf: [Frame::std_len(0, [0; 8], 0); TXQ_LEN],
            head: 0,
            len: 0,
            overruns: 0,
        }
    }
}

impl TxQueue {
    /// Queues a frame; false (and counted) if full.
    #[inline(always)]
    pub fn push(&mut self, f: Frame) -> bool {
        match self.reserve() {
            Some(slot) => {
                *slot = f;
                true
            }
            None => false,
        }
    }
    /// Queues a standard data frame of `len` bytes; false (and counted) if full. A firmware's
    /// call sites share one out-of-line copy instead of each building the frame.
    #[cfg_attr(feature = "inline-hot-paths", inline(always))]
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    pub fn push_std(&mut self, id: u16, data: [u8; 8], len: u8) -> bool {
        self.push(Frame::std_len(id, data, len))
    }
    /// The slot of the next frame, now counted as queued; `None` (and counted) if full. A
    /// firmware's call sites share one out-of-line copy and write their frames straight into
    /// the slot.
    #[cfg_attr(feature = "inline-hot-paths", inline)]
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    fn reserve(&mut self) -> Option<&mut Frame> {
        if self.len == TXQ_LEN {
            self.overruns = self.overruns.wrapping_add(1);
            return None;
        }
        let i = (self.head + self.len) & MASK;
        self.len += 1;
        Some(&mut self.buf[i])
    }
    /// Takes the oldest frame.
    #[inline]
    pub fn pop(&mut self) -> Option<Frame> {
        if self.len == 0 {
            return None;
        }
        let f = self.buf[self.head & MASK];
        self.head = (self.head + 1) & MASK;
        self.len -= 1;
        Some(f)
    }
    /// How many frames wait.
    #[inline]
    pub fn len(&self) -> usize {
        self.len
    }
    /// Whether nothing waits.
    #[cfg_attr(not(feature = "inline-hot-paths"), allow(dead_code))] // the host's fast path
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
    /// Drops everything waiting.
    pub fn clear(&mut self) {
        self.len = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(n: usize) -> Frame {
        Frame::std_len(0x100 + (n % 0x400) as u16, [n as u8; 8], 1)
    }

    /// A FIFO of exactly `TXQ_LEN` frames: all kept in order; one more is dropped and counted
    /// (the controller's overrun), and the queue still holds the first `TXQ_LEN`.
    #[test]
    fn holds_txq_len_frames_in_order_and_counts_the_overrun() {
        let mut q = TxQueue::default();
        assert!(q.is_empty());
        for n in 0..TXQ_LEN {
            assert!(q.push(frame(n)), "frame {n} fits");
        }
        assert!(!q.is_empty());
        assert!(!q.push(frame(TXQ_LEN)), "full");
        assert_eq!(q.overruns, 1);
        for n in 0..TXQ_LEN {
            assert_eq!(q.pop(), Some(frame(n)), "frame {n}");
        }
        assert_eq!(q.pop(), None);
        assert!(q.is_empty());
    }

    /// Order is kept across the ring's wrap-around, at every fill level.
    #[test]
    fn order_survives_wrap_around() {
        let mut q = TxQueue::default();
        let (mut pushed, mut popped) = (0, 0);
        for fill in 1..=TXQ_LEN {
            for _ in 0..3 * TXQ_LEN {
                while pushed - popped < fill {
                    assert!(q.push(frame(pushed)));
                    pushed += 1;
                }
                assert_eq!(q.pop(), Some(frame(popped)));
                popped += 1;
            }
        }
        while let Some(f) = q.pop() {
            assert_eq!(f, frame(popped));
            popped += 1;
        }
        assert_eq!(popped, pushed);
        assert_eq!(q.overruns, 0);
    }

    /// `clear` drops everything waiting; the queue then works as new.
    #[test]
    fn clear_empties_the_queue() {
        let mut q = TxQueue::default();
        for n in 0..5 {
            q.push(frame(n));
        }
        q.clear();
        assert!(q.is_empty());
        assert_eq!(q.pop(), None);
        q.push(frame(7));
        assert_eq!(q.pop(), Some(frame(7)));
    }
}
