//! The slots of the objects the per-frame paths touch, found once per node.

use crate::emcy;
use crate::model::Model;
use crate::od::{self, Dictionary};

/// No such object in this model's table.
const NO_SLOT: u16 = u16::MAX;

/// Slots of the objects that per-frame paths read or write, found once per node: the model
/// table is static, so a slot never moves, and a frame then costs no dictionary search.
#[derive(Clone, Copy, Debug)]
pub(super) struct HotSlots {
    /// 0x1005 COB-ID SYNC.
    pub(super) sync: u16,
    /// 0x1014 COB-ID EMCY.
    pub(super) emcy_cob: u16,
    /// 0x1001 error register.
    pub(super) err_reg: u16,
    /// 0x1003 sub 0.
    pub(super) hist: u16,
    /// 0x1029 sub 1, the reaction to a communication error (none where the build has no error
    /// behaviour, [`crate::config::ERROR_BEHAVIOUR`]).
    pub(super) comm_error: u16,
    /// How many of 0x1003 sub 1…8 the table has: they follow sub 0 in the slots.
    pub(super) hist_subs: u8,
}

impl HotSlots {
    /// From the model's table (not the dictionary, which would then have to be in memory
    /// before the node it is part of: in firmware, a stack temporary the size of the value
    /// array).
    pub(super) fn new<C, X>(model: &Model<C, X>) -> Self {
        // Out of line: six lookups share it (this runs once per node).
        #[inline(never)]
        fn find<C, X>(model: &Model<C, X>, index: u16, sub: u8) -> u16 {
            model
                .search(od::key(index, sub))
                .map_or(NO_SLOT, |s| s as u16)
        }
        let slot = |index: u16, sub: u8| find(model, index, sub);
        let hist = slot(0x1003, 0);
        let hist_subs = (1..=emcy::HISTORY_LEN as u16)
            .take_while(|&i| hist != NO_SLOT && slot(0x1003, i as u8) == hist + i)
            .count() as u8;
        HotSlots {
            sync: slot(0x1005, 0),
            emcy_cob: slot(0x1014, 0),
            err_reg: slot(0x1001, 0),
            hist,
            hist_subs,
            comm_error: if crate::config::ERROR_BEHAVIOUR {
                slot(crate::errbehav::INDEX, 1)
            } else {
                NO_SLOT
            },
        }
    }
}

impl Dictionary {
    /// Value of a slot from [`HotSlots`], `None` when the model lacks the object.
    #[inline]
    pub(super) fn hot(&self, slot: u16) -> Option<u32> {
        (slot != NO_SLOT).then(|| self.get(slot as usize))
    }

    /// Sets a slot from [`HotSlots`] if the model has the object.
    #[inline]
    pub(super) fn set_hot(&mut self, slot: u16, raw: u32) {
        if slot != NO_SLOT {
            self.set(slot as usize, raw);
        }
    }
}
