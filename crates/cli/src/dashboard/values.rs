//! The values the dashboard's SDO reads brought in, kept for the DCF export, and the remaps
//! running (issue 38 items 3, 4). A leaf: the object browser's endpoints ([`super::od`]) and
//! the dashboard's state both hold it.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Mutex;

use canpos_stack::od::Entry;

/// A value longer than this is shown but not kept for the export (a DCF holds numbers and
/// short strings; the tables' DOMAIN objects are not configuration).
pub const KEEP_MAX: usize = 1024;
/// Mapping entries a remap may name (CiA 301: 0x1A0n has sub-indices 1…64; the 8 data bytes
/// of a classic CAN frame hold 64 one-bit objects at most).
pub const MAP_MAX: usize = 64;

/// The values the dashboard's SDO reads brought in, per node: only objects of the node's
/// table are read (an unknown one is refused before the bus), so each node holds at most its
/// table's entries of at most [`KEEP_MAX`] bytes each.
#[derive(Default)]
pub struct Values(Mutex<BTreeMap<u8, NodeValues>>, Mutex<BTreeSet<u8>>);

/// A remap running on a node: a second one would interleave its SDO steps with the first's
/// and leave a mix of both mappings, so it is refused (409) until this is dropped.
pub struct Remapping<'a>(&'a Values, u8);

impl Drop for Remapping<'_> {
    fn drop(&mut self) {
        self.0 .1.lock().unwrap().remove(&self.1);
    }
}

impl Values {
    /// Marks a remap of node `id` as running, unless one already is.
    pub fn start_remap(&self, id: u8) -> Option<Remapping<'_>> {
        let free = self.1.lock().unwrap().insert(id);
        free.then(|| Remapping(self, id))
    }
}

/// One node's values by (index, sub).
type NodeValues = BTreeMap<(u16, u8), Vec<u8>>;

impl Values {
    /// Keeps what a read of `e` on node `id` answered.
    pub fn remember(&self, id: u8, e: &Entry, data: &[u8]) {
        let mut v = self.0.lock().unwrap();
        let node = v.entry(id).or_default();
        if data.len() <= KEEP_MAX {
            node.insert((e.index, e.sub), data.to_vec());
        } else {
            node.remove(&(e.index, e.sub));
        }
    }

    /// Forgets `e` on node `id` (a read the node refused: it has no value now).
    pub fn forget(&self, id: u8, e: &Entry) {
        if let Some(node) = self.0.lock().unwrap().get_mut(&id) {
            node.remove(&(e.index, e.sub));
        }
    }

    pub fn of(&self, id: u8) -> Vec<(u16, u8, Vec<u8>)> {
        self.0
            .lock()
            .unwrap()
            .get(&id)
            .map(|m| m.iter().map(|((i, s), d)| (*i, *s, d.clone())).collect())
            .unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One remap per node at a time; another node's may run; the mark ends with its guard.
    #[test]
    fn a_second_remap_of_a_node_waits_for_the_first() {
        let v = Values::default();
        let first = v.start_remap(5).expect("the first remap");
        assert!(v.start_remap(5).is_none(), "two remaps of node 5 at once");
        let other = v.start_remap(6).expect("node 6 is free");
        drop(first);
        assert!(v.start_remap(5).is_some(), "node 5 free again");
        drop(other);
    }
}
