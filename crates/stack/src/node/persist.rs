//! Persistence: loading values and the LSS configuration from the stored image, "save",
//! "load" / "kill" and the automatic store.

use super::lss_glue::{kbps_of_object, object_of_kbps};
use super::*;
use crate::storage::{follow_node_id, stored_node_id, Change};

/// The slot and entry of this model's object that a stored record's `key` names, if any (an
/// LSS or bookkeeping key names none). Out of line: every reading and writing of the image
/// looks its records up through it.
#[inline(never)]
fn stored_entry(od: &Dictionary, key: u32) -> Option<(usize, &'static Entry)> {
    if !storage::is_object_key(key) {
        return None;
    }
    // Firmware searches by the key itself: no index and sub-index to split it into, no abort
    // to work out for a key the table lacks.
    let slot = if crate::config::INLINE_HOT_PATHS {
        od.find((key >> 8) as u16, key as u8).ok()?
    } else {
        od::search_entries(od.entries(), key).ok()?
    };
    Some((slot, od.entries().get(slot)?))
}

struct Params<'a, C: 'static, X: 'static> {
    model: &'static Model<C, X>,
    cfg: &'a C,
}

impl<C, X> ParamSource for Params<'_, C, X> {
    fn param(&self, p: Param) -> u32 {
        (self.model.param)(self.cfg, p)
    }
}

impl<A: Application, S: Storage> Device<A, S> {
    /// Reloads values: the entries a reset communication covers always, every other one on
    /// reset node. Defaults first, then whatever the stored image holds for them (D6); stored
    /// COB-IDs that were pre-defined for the node-id they were saved under follow the active
    /// one (D15).
    #[inline(never)] // as `stored_lss_config`: the caller's frame stays small
    pub(super) fn load_values(&mut self, application: bool) {
        let p = Params {
            model: self.model,
            cfg: &self.cfg,
        };
        let node = self.node_id;
        let reloads = |e: &Entry| application || e.reset_by_comm();
        for (slot, e) in self.od.entries().iter().enumerate() {
            if reloads(e) {
                self.od.set(slot, crate::od::resolve_default(e, &p, node));
            }
        }
        let mut buf = [0u8; IMAGE_MAX];
        let tag = self.features().tag;
        let Ok(recs) = storage::load_image(&mut self.storage, tag, &mut buf) else {
            return;
        };
        let saved_node = recs
            .clone()
            .find(|&(k, _)| k == storage::KEY_SAVED_NODE_ID)
            .and_then(|(_, v)| stored_node_id(v));
        for (k, v) in recs {
            let Some((slot, e)) = stored_entry(&self.od, k) else {
                if let Some(n) = storage::app_record(k).filter(|_| application) {
                    self.app.load_stored(n, v);
                }
                continue;
            };
            if e.group != crate::od::Group::Volatile && reloads(e) {
                let v = follow_node_id(e, v, saved_node, node);
                // A checksummed image can still hold what no write would have been let in (a
                // hand-edited or foreign file; found by fuzzing): that object keeps its default.
                // The rule is a write's, less what relates the value to the one it replaces.
                if e.accepts(v) && self.value_allowed(e, v).is_ok() {
                    self.od.set(slot, v);
                }
            }
        }
        // The write rule that relates guarding to SYNC (`validate`), once both are loaded:
        // guarding on SYNC's CAN-ID keeps its default (0x700 + node-id, which SYNC cannot have).
        // 0x100E:0 by its record key: slot and entry in one look-up.
        if let Some((g, e)) = stored_entry(&self.od, 0x0010_0E00) {
            if errctl::sync_guarding_clash(self.od.get(g), self.sync_can_id()) {
                self.od.set(g, crate::od::resolve_default(e, &p, node));
            }
        }
    }

    /// The node-id and bit rate stored by LSS or in their object copies (TMI 0x2000 / 0x2001,
    /// R17, R19: written there and saved with "save", they apply at power-up too; LSS "store
    /// configuration" keeps both copies equal, so an object copy is the newer one), and
    /// whether the image failed its check.
    // Out of line: its image buffer is then gone before `power_on` calls `reset`, which loads
    // the image again (two buffers on the stack at once are too many for firmware).
    #[inline(never)]
    pub(super) fn stored_lss_config(&mut self) -> ((Option<u8>, Option<u16>), bool) {
        let mut buf = [0u8; IMAGE_MAX];
        let tag = self.features().tag;
        let recs = match storage::load_image(&mut self.storage, tag, &mut buf) {
            Ok(recs) => recs,
            Err(StorageError::Empty) => return ((None, None), false),
            Err(_) => return ((None, None), true),
        };
        // The last node-id and bit rate of each source: [LSS node-id, LSS bit rate, object
        // node-id, object bit rate].
        let mut last = [None; 4];
        for (k, v) in recs {
            let at = match k {
                storage::KEY_LSS_NODE_ID => 0,
                storage::KEY_LSS_BITRATE => 1,
                _ => match stored_entry(&self.od, k).map(|(_, e)| e.hook) {
                    Some(Hook::PendingNodeId) => 2,
                    Some(Hook::PendingBitRate) => 3,
                    _ => continue,
                },
            };
            // A checksummed image can still hold an impossible node-id (a hand-edited or
            // foreign file; found by fuzzing): ignore it rather than talk on COB-IDs of node 0
            // or 200.
            if at & 1 == 0 && stored_node_id(v).is_none() {
                continue;
            }
            last[at] = Some(v);
        }
        let [lss_id, lss_kbps, obj_id, obj_kbps] = last;
        let id = obj_id.or(lss_id).map(|v| v as u8);
        let kbps = obj_kbps.map(kbps_of_object).or(lss_kbps.map(|v| v as u16));
        ((id, kbps), false)
    }

    /// At power-on, the stored image failed its check: the application's reaction, else EMCY
    /// 0x6300. Sent by the epilogue that ends [`Node::power_on`] right after.
    pub(super) fn report_corrupt_storage(&mut self) {
        let now = self.now;
        let (app, mut cx) = self.app_ctx(now);
        if !app.storage_corrupt(&mut cx) {
            self.emcy.raise(emcy::code::DATA_SET, 0, [0; 5]);
        }
    }

    /// "save" (0x1010) of `scope`, or the automatic store of the values the device keeps by
    /// itself: the covered entries' current values replace what was stored for them; the
    /// rest of the image stays. A "save" records the active node-id with them (D15); the
    /// automatic store keeps the one recorded.
    pub(crate) fn store(&mut self, scope: Scope) -> Result<(), Abort> {
        self.change_stored(Change::Save(scope))
            .map_err(|_| Abort::CannotStore)
    }

    /// LSS "store configuration": keeps the pending node-id and bit rate, in the LSS records
    /// and in the objects that hold copies of them (TMI 0x2000 / 0x2001), so that every copy
    /// says the same after the next power-on.
    pub(crate) fn store_lss(&mut self) -> Result<(), StorageError> {
        self.change_stored(Change::Lss)?;
        self.stored_lss = (Some(self.pending_node_id), Some(self.pending_bitrate));
        Ok(())
    }

    /// Every change of the stored image: the records `change` covers are dropped and the
    /// values it stores written in their place; the rest of the image stays. One rule and one
    /// writer for all of them, as they differ only in which records those are.
    // Out of line: the image buffer of `change_image`, inlined here, is on the stack only
    // while a change runs.
    #[inline(never)]
    fn change_stored(&mut self, change: Change) -> Result<(), StorageError> {
        let od = &self.od;
        let (id, kbps) = (self.pending_node_id, self.pending_bitrate);
        let replaced = |k: u32| match (stored_entry(od, k), change) {
            (Some((_, e)), Change::Save(scope) | Change::Forget(scope)) => scope.covers(e),
            (Some((_, e)), Change::Lss) => {
                matches!(e.hook, Hook::PendingNodeId | Hook::PendingBitRate)
            }
            // A "save" replaces the saved node-id (the automatic store, of no COB-ID, keeps
            // it: D15); a "load" forgets the records of objects this model does not have too.
            (None, Change::Save(scope)) => {
                scope != Scope::Auto && k == storage::KEY_SAVED_NODE_ID
                    || scope.covers_app_values() && storage::app_record(k).is_some()
            }
            (None, Change::Forget(scope)) => {
                storage::is_object_key(k)
                    || scope.covers_app_values() && storage::app_record(k).is_some()
            }
            (None, Change::Lss) => k == storage::KEY_LSS_NODE_ID || k == storage::KEY_LSS_BITRATE,
        };
        // The value `change` stores for `e` in `slot`, if any.
        let value = |slot: usize, e: &Entry| match change {
            Change::Save(scope) => scope.covers(e).then(|| od.get(slot)),
            Change::Forget(_) => None,
            Change::Lss => match e.hook {
                Hook::PendingNodeId => Some(id as u32),
                Hook::PendingBitRate => Some(object_of_kbps(kbps)),
                _ => None,
            },
        };
        let node = self.node_id as u32;
        let app = &self.app;
        let put = &mut |w: &mut storage::ImageWriter<'_>| {
            (change != Change::Lss
                || w.push(storage::KEY_LSS_NODE_ID, id as u32)
                    && w.push(storage::KEY_LSS_BITRATE, kbps as u32))
                // Slots counted up to MAX_ENTRIES, which no table exceeds: no bounds check.
                && (0..od::MAX_ENTRIES)
                    .zip(od.entries())
                    .all(|(slot, e)| value(slot, e).is_none_or(|v| w.push(e.key(), v)))
                && match change {
                    Change::Save(scope) if scope != Scope::Auto => {
                        w.push(storage::KEY_SAVED_NODE_ID, node)
                            && (!scope.covers_app_values()
                                || (0..storage::APP_RECORDS).all(|k| {
                                    app.stored_value(k)
                                        .is_none_or(|v| w.push(storage::app_key(k), v))
                                }))
                    }
                    _ => true,
                }
        };
        let tag = self.features().tag;
        storage::change_image(&mut self.storage, tag, &replaced, put)
    }

    // Out of line: its image buffers would otherwise be in every write's stack frame (their
    // size in docs/FIRMWARE.md, "Build options in figures").
    #[inline(never)]
    pub(super) fn storage_command(&mut self, e: &Entry, raw: u32) -> Result<(), Abort> {
        let f = self.features();
        let save = e.hook == Hook::StoreParameters;
        let (kill, preop_only) = (f.kill_signature, f.store_preop_only);
        let change = storage::command(save, e.sub, raw, kill, preop_only, self.nmt)?;
        self.change_stored(change).map_err(|_| Abort::CannotStore)?;
        // A simulated device holds the answer for the store time (D7): it sees this count change.
        self.stats.stores = self.stats.stores.wrapping_add(1);
        Ok(())
    }
}
