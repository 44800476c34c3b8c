//! COB-IDs: the function codes of the CiA 301 pre-defined connection set, and the CAN-IDs no
//! service object may be set to (the restricted ones), shared by EMCY, SYNC, guarding and the PDOs.

/// NMT node control (master → all).
pub const NMT: u16 = 0x000;
/// Default SYNC COB-ID.
pub const SYNC: u16 = 0x080;
/// EMCY base; + node-id.
pub const EMCY: u16 = 0x080;
/// TPDO1 base; TPDO n uses `TPDO1 + 0x100 * (n - 1)` + node-id.
pub const TPDO1: u16 = 0x180;
/// SDO server → client base; + node-id.
pub const SDO_TX: u16 = 0x580;
/// SDO client → server base; + node-id.
pub const SDO_RX: u16 = 0x600;
/// Error control (boot-up, heartbeat, node guarding) base; + node-id.
pub const ERRCTL: u16 = 0x700;
/// LSS master → slave.
pub const LSS_RX: u16 = 0x7E5;
/// LSS slave → master.
pub const LSS_TX: u16 = 0x7E4;

/// COB-ID bits 11–28: part of a 29-bit identifier only, so 0 in every COB-ID of an 11-bit
/// frame (CiA 301 §7.5.2.5, 7.5.2.17, 7.5.2.35: a value with them set is refused, 0x06090030).
pub const COB_ID_HIGH_BITS: u32 = 0x1FFF_F800;

/// Whether a COB-ID value of EMCY, SYNC or guarding is refused (abort 0x06090030): bit 30 (SYNC:
/// generate, which this device does not; EMCY: reserved), bit 29 (29-bit ids, not supported),
/// bits 11–28, or a restricted CAN-ID where the service's own rule (`may_be_restricted`) does
/// not allow one (conformance OTH-10).
#[inline(always)]
pub(crate) fn service_cob_id_refused(raw: u32, may_be_restricted: bool) -> bool {
    raw & (0x6000_0000 | COB_ID_HIGH_BITS) != 0 || !may_be_restricted && restricted_id(raw & 0x7FF)
}

/// The CiA 301 restricted CAN-IDs (Table 72): no PDO may use them, nor EMCY, SYNC or guarding but
/// where their own rule allows it (an EMCY marked not valid, guarding's pre-defined 0x700 +
/// node-id).
#[cfg_attr(feature = "inline-hot-paths", inline)]
#[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
pub fn restricted_id(id: u32) -> bool {
    // A host looks up one bit per 11-bit CAN-ID: the eight range compares would make an SDO
    // download of a COB-ID slower. A firmware compares: the bitmap would take flash for a check
    // only COB-ID writes make (both figures in the options file, config.rs).
    if crate::config::INLINE_HOT_PATHS {
        restricted_by_table(id)
    } else {
        restricted_by_range(id)
    }
}

/// [`restricted_id`] by one bit of [`RESTRICTED`].
#[inline(always)]
fn restricted_by_table(id: u32) -> bool {
    id < 0x800 && RESTRICTED[(id >> 6) as usize] >> (id & 63) & 1 != 0
}

const fn restricted_by_range(id: u32) -> bool {
    matches!(id, 0x000 | 0x001..=0x07F | 0x101..=0x180 | 0x581..=0x5FF | 0x601..=0x67F | 0x6E0..=0x6FF | 0x701..=0x77F | 0x780..=0x7FF)
}

/// Bit `id % 64` of word `id / 64`: [`restricted_by_range`] of `id` (a firmware build links it
/// not: its `restricted_id` never reads it).
static RESTRICTED: [u64; 32] = {
    let mut t = [0u64; 32];
    let mut id = 0u32;
    while id < 0x800 {
        // Every CAN-ID indexes the table, without a branch: a loop bound past 0x7FF then fails
        // to compile (index 32 is out of bounds) instead of adding an iteration that does nothing.
        t[(id >> 6) as usize] |= (restricted_by_range(id) as u64) << (id & 63);
        id += 1;
    }
    t
};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn restricted_table_matches_ranges() {
        // Both ways in every build (the table is the host's, the ranges the firmware's).
        for id in 0..0x1_0000u32 {
            assert_eq!(restricted_by_table(id), restricted_by_range(id), "{id:#X}");
            assert_eq!(restricted_id(id), restricted_by_range(id), "{id:#X}");
        }
    }
}
