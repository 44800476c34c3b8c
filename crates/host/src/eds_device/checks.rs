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
}
