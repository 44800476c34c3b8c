//! What a network simulator needs beyond the in-process buses: cancelling a member's transmit
//! requests (SIL Kit's `CancelTransmitRequests`, a controller that stops) and the frame on the
//! wire whose outcome is settled, as a further `impl` block of [`Timeline`].

use super::*;

impl Timeline {
    /// Takes every frame of member `id` that is not on the wire out of its transmit queue and
    /// returns them in submission order; a frame already on the wire finishes (a controller
    /// cannot pull back bits it is sending). Cancelled frames are not counted as lost: the
    /// member asked for it.
    pub fn cancel_queued(&mut self, id: MemberId) -> Vec<Frame> {
        let Some(m) = self.members.get_mut(id.0 as usize).filter(|m| m.live) else {
            return Vec::new();
        };
        let mut gone: Vec<Queued> = Vec::new();
        m.queue.retain(|q| {
            if q.on_wire {
                true
            } else {
                gone.push(*q);
                false
            }
        });
        if m.queue.is_empty() {
            self.active.retain(|&i| i != id.0);
        }
        gone.sort_by_key(|q| q.seq);
        gone.into_iter().map(|q| q.frame).collect()
    }

    /// The start and end of the frame on the wire (end of EOF, or of the error delimiter of
    /// a collision) when nothing can change it any more: no stuck-dominant interval or error
    /// flag pending and no member with a failed transceiver (whose attempts are its own).
    /// Frames submitted meanwhile only queue for the next arbitration, after its end, so the
    /// bus may be advanced to that end before they are known.
    pub fn settled_frame(&self) -> Option<(Nanos, Nanos)> {
        if self.stuck.is_some() || !self.failed.is_empty() {
            return None;
        }
        self.current.as_ref().map(|c| (c.start, c.end))
    }
}
