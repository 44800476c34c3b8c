//! The builder's whole-file checks: the object lists of `[MandatoryObjects]` … agree with the
//! sections, and every PDO's default mapping names objects that exist and fit.

use super::*;

impl Builder<'_> {
    /// Every CiA 301 object of the table carries the hook of the service whose rules it
    /// follows ([`cia301::missing_hook`]): a table without one would serve, say, a 0x1014 that
    /// accepts any COB-ID, so it is refused with the object's line.
    pub(super) fn check_hooks(
        &self,
        entries: &[Entry],
        value_lines: &BTreeMap<u32, usize>,
    ) -> Result<(), EdsError> {
        match cia301::missing_hook(entries) {
            None => Ok(()),
            Some((index, sub)) => Err(self.err(
                value_lines
                    .get(&canpos_stack::od::key(index, sub))
                    .copied()
                    .unwrap_or(0),
                format!(
                    "0x{index:04X} sub {sub} lacks its CiA 301 rule ({:?}): the table would \
                     accept any value there",
                    cia301::hook_of(index, sub)
                ),
            )),
        }
    }

    /// `[MandatoryObjects]` / `[OptionalObjects]` / `[ManufacturerObjects]`: counts agree,
    /// every listed object has a section; a section nobody lists is only warned about.
    pub(super) fn check_lists(
        &mut self,
        ini: &Ini,
        objects: &BTreeMap<u16, &Section>,
    ) -> Result<(), EdsError> {
        let mut listed: BTreeMap<u16, usize> = BTreeMap::new();
        for name in ["MandatoryObjects", "OptionalObjects", "ManufacturerObjects"] {
            let Some(sec) = ini.section(name) else {
                continue;
            };
            let k = sec
                .key("SupportedObjects")
                .ok_or_else(|| self.err(sec.line, format!("[{name}] without SupportedObjects")))?;
            let n = self.num(k)?;
            let items: Vec<&Key> = sec
                .keys
                .iter()
                .filter(|x| !x.name.eq_ignore_ascii_case("SupportedObjects"))
                .collect();
            if n < 0 || n as usize != items.len() {
                return Err(self.err(
                    k.line,
                    format!(
                        "SupportedObjects={} but [{name}] lists {}",
                        k.value,
                        items.len()
                    ),
                ));
            }
            for it in items {
                match parse_int(&it.name) {
                    Some(p) if (1..=n).contains(&p) => {}
                    _ => {
                        return Err(
                            self.err(it.line, format!("[{name}] key `{}` is not 1…{n}", it.name))
                        )
                    }
                }
                let v = self.num(it)?;
                let index = u16::try_from(v)
                    .map_err(|_| self.err(it.line, format!("0x{v:X} is not an object index")))?;
                if let Some(first) = listed.insert(index, it.line) {
                    return Err(self.err(
                        it.line,
                        format!("0x{index:04X} listed again (first on line {first})"),
                    ));
                }
                if !objects.contains_key(&index) {
                    return Err(self.err(
                        it.line,
                        format!("0x{index:04X} is listed but has no [{index:04X}] section"),
                    ));
                }
            }
        }
        for (index, sec) in objects {
            if *index >= 0x1000 && !listed.contains_key(index) {
                self.warnings.push(format!(
                    "[{}] (line {}) is in no object list; served anyway",
                    sec.name, sec.line
                ));
            }
        }
        Ok(())
    }

    /// A PDO's communication parameters (`index` 0x1400… / 0x1800…) come with its mapping
    /// (0x1600… / 0x1A00…) and the other way round.
    pub(super) fn check_pdo_pair(
        &self,
        objects: &BTreeMap<u16, &Section>,
        sec: &Section,
        index: u16,
        what: &str,
    ) -> Result<(), EdsError> {
        // The mapping record is 0x200 above its communication record, on both sides.
        let other = if index & 0x200 == 0 {
            index + 0x200
        } else {
            index - 0x200
        };
        if objects.contains_key(&other) {
            return Ok(());
        }
        Err(self.err(
            sec.line,
            format!(
                "[{}]: {what} {} has no [{other:04X}] section",
                sec.name,
                (index & 0x1FF) + 1
            ),
        ))
    }

    /// The default mapping of every PDO names objects that exist, may be mapped (and, for an
    /// RPDO, written; or is a dummy entry of an integer type), and fit.
    pub(super) fn check_mappings(
        &self,
        entries: &[Entry],
        value_lines: &BTreeMap<u32, usize>,
    ) -> Result<(), EdsError> {
        let tpdos = (0..pdo::MAX_TPDOS as u16).map(|n| (0x1A00 + n, false));
        let rpdos = (0..rpdo::MAX_RPDOS as u16).map(|n| (0x1600 + n, true));
        for (mi, rx) in tpdos.chain(rpdos) {
            self.check_mapping(entries, value_lines, mi, rx)?;
        }
        Ok(())
    }

    /// [`Builder::check_mappings`] of the mapping record `mi`, of an RPDO when `rx`.
    fn check_mapping(
        &self,
        entries: &[Entry],
        value_lines: &BTreeMap<u32, usize>,
        mi: u16,
        rx: bool,
    ) -> Result<(), EdsError> {
        let find = |i: u16, s: u8| entries.iter().find(|e| e.index == i && e.sub == s);
        // The line of the entry's value (or of its section).
        let line = |e: &Entry| value_lines.get(&e.key()).copied().unwrap_or(0);
        let Some(e0) = find(mi, 0) else {
            return Ok(());
        };
        let DefaultValue::Const(count) = e0.default else {
            return Err(self.err(line(e0), "a mapping count must be a number"));
        };
        let have = (1..=pdo::MAX_MAP as u8)
            .take_while(|&k| find(mi, k).is_some())
            .count() as u32;
        if count > have {
            return Err(self.err(
                line(e0),
                format!(
                    "0x{mi:04X} maps {count} objects but has no sub {}",
                    have + 1
                ),
            ));
        }
        let mut bits = 0u32;
        for k in 1..=count {
            let Some(m) = u8::try_from(k).ok().and_then(|k| find(mi, k)) else {
                return Err(self.err(
                    line(e0),
                    format!("0x{mi:04X} maps {count} objects but has no sub {k}"),
                ));
            };
            let DefaultValue::Const(v) = m.default else {
                return Err(self.err(line(m), "a mapping entry must be a number"));
            };
            let (ti, ts, tb) = ((v >> 16) as u16, (v >> 8) as u8, v & 0xFF);
            let at = line(m);
            // A dummy entry (RPDOs): the integer types' indices, sub 0, their own length.
            let dummy = match (ti, ts) {
                (2 | 5, 0) => Some(8),
                (3 | 6, 0) => Some(16),
                (4 | 7, 0) => Some(32),
                _ => None,
            };
            if let (true, Some(b)) = (rx, dummy) {
                if tb != b {
                    return Err(self.err(
                        at,
                        format!("0x{mi:04X} sub {k}: a dummy of 0x{ti:04X} has {b} bits, not {tb}"),
                    ));
                }
                bits += tb;
                continue;
            }
            let Some(t) = find(ti, ts) else {
                return Err(self.err(
                    at,
                    format!("0x{mi:04X} sub {k} maps 0x{ti:04X} sub {ts}, which does not exist"),
                ));
            };
            if !t.pdo {
                return Err(self.err(
                    at,
                    format!(
                        "0x{mi:04X} sub {k} maps 0x{ti:04X} sub {ts}, which has no PDOMapping=1"
                    ),
                ));
            }
            if rx && !t.access.writable() {
                return Err(self.err(
                    at,
                    format!(
                        "0x{mi:04X} sub {k} maps 0x{ti:04X} sub {ts} into an RPDO, which is \
                         not writable"
                    ),
                ));
            }
            if tb != u32::from(t.ty.bits()) {
                return Err(self.err(
                    at,
                    format!(
                        "0x{mi:04X} sub {k} maps 0x{ti:04X} sub {ts} with {tb} bits; it has {}",
                        t.ty.bits()
                    ),
                ));
            }
            bits += tb;
        }
        if bits > 64 {
            let what = if rx { "RPDO" } else { "TPDO" };
            return Err(self.err(
                line(e0),
                format!(
                    "{what} {} maps {bits} bits; a CAN frame holds 64",
                    (mi & 0x1FF) + 1
                ),
            ));
        }
        Ok(())
    }

    /// The start values of 0x1016 and 0x1029 follow the rules an SDO write of them must: each
    /// node-id watched by one entry (the stack would watch the first only), reserved bits 0,
    /// reactions 0, 1 or 2. Refused with the value's line.
    pub(super) fn check_error_control(
        &self,
        entries: &[Entry],
        value_lines: &BTreeMap<u32, usize>,
    ) -> Result<(), EdsError> {
        use canpos_stack::{errbehav, hbcons};
        let mut watched: BTreeMap<u8, u8> = BTreeMap::new();
        for e in entries {
            let DefaultValue::Const(v) = e.default else {
                continue;
            };
            let line = || {
                value_lines
                    .get(&canpos_stack::od::key(e.index, e.sub))
                    .copied()
                    .unwrap_or(0)
            };
            let bad = match e.hook {
                Hook::HbConsumer => hbcons::value_allowed(v)
                    .err()
                    .map(|_| format!("0x1016 sub {}: bits 31–24 are reserved (0)", e.sub))
                    .or_else(|| {
                        let node = hbcons::watched(v)?;
                        watched.insert(node, e.sub).map(|first| {
                            format!(
                                "0x1016 sub {} watches node {node}, as sub {first} does (CiA 301: \
                             one entry per node-id)",
                                e.sub
                            )
                        })
                    }),
                Hook::ErrorBehaviour => errbehav::value_allowed(v)
                    .err()
                    .map(|_| format!("0x1029 sub {}: {v} is no reaction (0, 1 or 2)", e.sub)),
                _ => None,
            };
            if let Some(msg) = bad {
                return Err(self.err(line(), msg));
            }
        }
        Ok(())
    }
}

impl Builder<'_> {
    /// Sub-index 0 of the records whose sub-indices the stack's services read (0x1016, 0x1029,
    /// the PDO communication records) is their highest sub-index (CiA 301): a master walks the
    /// record up to it, so a larger one sends it into aborts, a smaller one hides entries that
    /// still act (a heartbeat consumer entry it never configured). Refused with its line.
    pub(super) fn check_highest_sub(
        &self,
        entries: &[Entry],
        value_lines: &BTreeMap<u32, usize>,
    ) -> Result<(), EdsError> {
        let counted = |i: u16| matches!(i, 0x1016 | 0x1029 | 0x1400..=0x15FF | 0x1800..=0x19FF);
        for e in entries.iter().filter(|e| e.sub == 0 && counted(e.index)) {
            let highest = entries
                .iter()
                .filter(|x| x.index == e.index)
                .map(|x| x.sub)
                .max()
                .unwrap_or(0);
            match e.default {
                DefaultValue::Const(v) if highest > 0 && v != u32::from(highest) => {
                    return Err(self.err(
                        value_lines.get(&e.key()).copied().unwrap_or(0),
                        format!(
                            "0x{:04X} sub 0 is {v}, but the highest sub-index of 0x{:04X} is \
                             {highest} (CiA 301: sub 0 is the highest sub-index supported)",
                            e.index, e.index
                        ),
                    ))
                }
                _ => {}
            }
        }
        Ok(())
    }

    /// The PDO communication values a device starts with (`model`'s table; a node-id relative
    /// one on every node-id 1 … 127, as LSS may give it any) pass the rule an SDO write of them
    /// must ([`pdo::Tpdos::check_value`], [`rpdo::Rpdos::check_value`]): no reserved
    /// transmission type, no restricted or 29-bit CAN-ID on a valid PDO, a SYNC start value of
    /// at most 240. Served as they were, they would drive the PDO (an RPDO of type 241 taken
    /// at once, one listening on NMT's CAN-ID 0) where no master could have put it. Refused
    /// with the value's line.
    pub(super) fn check_pdo_comm(
        &self,
        model: &'static Model,
        value_lines: &BTreeMap<u32, usize>,
    ) -> Result<(), EdsError> {
        let od = canpos_stack::Dictionary::new(model);
        for e in model.entries {
            let (base, nodes) = match e.default {
                DefaultValue::Const(v) => (v, 0..=0u32),
                DefaultValue::NodeId(base) => (base, 1..=127),
                _ => continue,
            };
            let refused = |raw: u32| match e.hook {
                Hook::TpdoComm => pdo::Tpdos::check_value(&od, e.index, e.sub, raw).is_err(),
                Hook::RpdoComm => rpdo::Rpdos::check_value(&od, e.index, e.sub, raw).is_err(),
                _ => false,
            };
            let Some(node) = nodes.clone().find(|&n| refused(base.wrapping_add(n))) else {
                continue;
            };
            let raw = base.wrapping_add(node);
            let on = if node == 0 {
                String::new()
            } else {
                format!(" ($NODEID+0x{base:X} on node-id {node})")
            };
            let what = match e.sub {
                1 => format!(
                    "COB-ID 0x{raw:08X}{on} is refused: a valid PDO takes no restricted CAN-ID \
                     (CiA 301: NMT, SYNC, EMCY, TIME, SDO, heartbeat, LSS) and canpos no 29-bit one"
                ),
                2 => format!("transmission type {raw} is reserved (241 … 253, CiA 301)"),
                _ => format!("SYNC start value {raw} is above 240"),
            };
            return Err(self.err(
                value_lines.get(&e.key()).copied().unwrap_or(0),
                format!(
                    "0x{:04X} sub {}: {what}; an SDO write of it would be refused too",
                    e.index, e.sub
                ),
            ));
        }
        Ok(())
    }
}
