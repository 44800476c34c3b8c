//! The node's transmit queue: a fixed ring of frames waiting for the host to send them.

use crate::wire::Frame;

/// Capacity of the transmit queue.
pub const TXQ_LEN: usize = 64;
/// Ring index mask (the capacity is a power of two: masks instead of `%` and bounds checks).
const MASK: usize = TXQ_LEN - 1;
const _: () = assert!(TXQ_LEN.is_power_of_two());

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
    #[inline]
    pub fn push(&mut self, f: Frame) -> bool {
        if self.len == TXQ_LEN {
            self.overruns = self.overruns.wrapping_add(1);
            return false;
        }
        self.buf[(self.head + self.len) & MASK] = f;
        self.len += 1;
        true
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
    /// Whether nothing waits.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
    /// Drops everything waiting.
    pub fn clear(&mut self) {
        self.len = 0;
    }
}
