//! A byte-driven frame-sequence harness with the bus-level invariants of a CANopen slave.
//!
//! Shared by the `node_frames` fuzz target (`fuzz/fuzz_targets/node_frames.rs` includes this
//! file by path) and the `frame_sequence_props` property test, so the invariants are written
//! once. Input bytes are decoded as a program: model and node-id, then operations (a frame, a
//! time step, a measurement sample, a power cycle). Byte-oriented decoding rather than a
//! structured `Arbitrary` lets libFuzzer's mutations (bit flips, splices) map to small program
//! changes.
//!
//! Invariants checked after every operation ([`Checker::run`] returns the first violation):
//!
//! - **own COB-IDs only**: 0x580 + id, 0x700 + id, the guarding COB-ID (0x100E), the EMCY
//!   COB-ID (0x1014), the valid TPDO COB-IDs (0x180x/1) and 0x7E4 — for the node-id before
//!   *or* after the step, since LSS (and
//!   a reset activating a pending node-id) legally change it; no extended frames; nothing while
//!   powered off or without a node-id except LSS.
//! - **DLC ≤ 8** and data length = DLC.
//! - **one SDO response per request**: a DLC-8 request in Pre-operational / Operational gets
//!   exactly one 0x580 frame — at once, or after the store delay (D7) — except the CiA 301
//!   no-reply cases: a client abort, segments inside a block download (≤ 1), and a block upload
//!   (≤ 127 segments); wrong DLC or Stopped: none. No 0x580 frame answers a non-SDO frame.
//!   Timers may only produce an SDO frame for a held answer or a timed-out transfer (abort).
//!   A store answer held back across Stopped → Operational is still that request's one answer.
//! - **NMT state machine legal**: NMT commands lead to their target state (Start may be refused
//!   by a TMI lock-out), resets to Pre-operational (Initialising when unconfigured); LSS may
//!   only take a node out of Initialising; time and samples may only leave Operational (error
//!   behaviour, TMI forced pre-operational), never enter it. Heartbeat / guarding bytes match the
//!   state, boot-ups are 0x00 and follow a reset.
#![allow(dead_code)]

use canpos_encoder::{Sample, MAX_CHANNELS};
use canpos_models::SensorNode;
use canpos_models::{self as models, Model};
use canpos_stack::nmt::NmtState;
use canpos_stack::sdo::TransferKind;
use canpos_stack::storage::RamStorage;
use canpos_stack::{Frame, Instant, Node};

const UNCONFIGURED: u8 = 0xFF;

/// Reads bytes off the front of the input; zeros once it is exhausted.
struct Input<'a>(&'a [u8]);

impl Input<'_> {
    fn u8(&mut self) -> u8 {
        match self.0.split_first() {
            Some((&b, rest)) => {
                self.0 = rest;
                b
            }
            None => 0,
        }
    }
    fn u16(&mut self) -> u16 {
        u16::from_le_bytes([self.u8(), self.u8()])
    }
    fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

/// The node under test and what the checker knows about it.
pub struct Checker {
    pub node: SensorNode<RamStorage>,
    pub model: &'static Model,
    pub now: Instant,
    powered: bool,
    /// SDO answers the node owes (a store delays them, D7).
    owed: u32,
    /// Operations run (to bound the work per input).
    pub steps: usize,
    /// Until when the node may be deaf: an LSS "activate bit timing" (0x15) silences it for
    /// twice the switch delay (CiA 305), which the checker cannot observe directly. Set on every
    /// 0x15 frame, so it only ever relaxes the NMT rule.
    deaf_until: Instant,
}

/// What one operation was, for the NMT and SDO rules.
enum Stimulus {
    Frame(Frame),
    Time,
    Sample,
    PowerCycle,
}

impl Checker {
    /// Decodes the model and configuration from the first bytes and powers the node on.
    fn new(inp: &mut Input) -> Checker {
        let all = models::all();
        let model = all[inp.u8() as usize % all.len()];
        let mut cfg = model.default_config;
        let sel = inp.u8();
        // Mostly the default id; sometimes another one or unconfigured (LSS only).
        cfg.node_id = match sel % 8 {
            0 => UNCONFIGURED,
            1 => (sel >> 3) % 127 + 1,
            _ => cfg.node_id,
        };
        let mut node = Node::new(model, cfg, RamStorage::default());
        node.power_on(Instant::ZERO);
        Checker {
            node,
            model,
            now: Instant::ZERO,
            powered: true,
            owed: 0,
            steps: 0,
            deaf_until: Instant::ZERO,
        }
    }

    /// Runs the whole program in `data`; `Err` describes the first broken invariant.
    pub fn run(data: &[u8]) -> Result<(), String> {
        let mut inp = Input(data);
        let mut c = Checker::new(&mut inp);
        let boot = c.drain();
        let ids = c.own_ids();
        c.check_frames(&boot, &[ids], "power-on")?;
        // Bound the work per input so libFuzzer explores breadth, not one long program.
        while !inp.is_empty() && c.steps < 400 {
            c.steps += 1;
            c.step(&mut inp)?;
        }
        Ok(())
    }

    fn drain(&mut self) -> Vec<Frame> {
        let mut v = Vec::new();
        while let Some(f) = self.node.poll_transmit() {
            v.push(f);
            if v.len() > 4096 {
                break;
            }
        }
        v
    }

    fn node_id(&self) -> u8 {
        self.node.device().node_id()
    }

    /// Every COB-ID the node may send on with its present configuration.
    fn own_ids(&mut self) -> Vec<u16> {
        let mut ids = vec![0x7E4];
        let id = self.node_id();
        if !self.powered || id == UNCONFIGURED || id == 0 || id > 127 {
            return ids;
        }
        let id = u16::from(id);
        ids.extend([0x580 + id, 0x700 + id]);
        if let Ok(v) = self.node.read_object(0x1014, 0) {
            if v & 0x8000_0000 == 0 {
                ids.push((v & 0x7FF) as u16);
            }
        }
        // Guarding answers on the COB-ID of 0x100E where the model has it (TH).
        if let Ok(v) = self.node.read_object(0x100E, 0) {
            ids.push((v & 0x7FF) as u16);
        }
        for n in 0..u16::from(self.model.features.tpdos) {
            if let Ok(v) = self.node.read_object(0x1800 + n, 1) {
                if v & 0x8000_0000 == 0 {
                    ids.push((v & 0x7FF) as u16);
                }
            }
        }
        ids
    }

    fn check_frames(&self, out: &[Frame], allowed: &[Vec<u16>], what: &str) -> Result<(), String> {
        for f in out {
            if f.dlc() > 8 || (!f.is_remote() && f.data().len() != usize::from(f.dlc())) {
                return Err(format!("{what}: bad DLC in {f:?}"));
            }
            let Some(id) = f.std_id() else {
                return Err(format!("{what}: extended frame sent: {f:?}"));
            };
            if !allowed.iter().any(|a| a.contains(&id)) {
                return Err(format!(
                    "{what}: sent on a foreign COB-ID {id:03X}: {f:?} (own: {allowed:03X?})"
                ));
            }
        }
        Ok(())
    }

    /// Decodes and runs one operation, then checks it.
    fn step(&mut self, inp: &mut Input) -> Result<(), String> {
        let op = inp.u8();
        let id_before = self.node_id();
        let nmt_before = self.node.device().nmt_state();
        let ids_before = self.own_ids();
        let sdo_before = self.node.sdo_server().transfer().map(|(k, _)| k);
        let sdo_busy = self.node.sdo_server().busy();
        let stim = match op {
            0x00..=0x9F => {
                let f = self.frame(op, inp);
                if f.std_id() == Some(0x7E5) && f.data().first() == Some(&0x15) {
                    let d = f.data();
                    let delay = u64::from(u16::from_le_bytes([
                        d.get(1).copied().unwrap_or(0),
                        d.get(2).copied().unwrap_or(0),
                    ]));
                    // A deaf node ignores a later, shorter switch: keep the longest.
                    let until = Instant::from_micros(self.now.micros() + 2 * delay * 1000 + 1000);
                    self.deaf_until = self.deaf_until.max(until);
                }
                self.node.handle_frame(&f, self.now);
                Stimulus::Frame(f)
            }
            0xA0..=0xDF => {
                self.advance(op, inp);
                Stimulus::Time
            }
            0xE0..=0xEF => {
                let mut s = Sample::default();
                for (k, p) in s.positions_nm.iter_mut().enumerate().take(MAX_CHANNELS) {
                    let raw = inp.u16();
                    // Low bit of the op byte per channel: magnet missing.
                    *p = (op >> (k % 4) & 1 == 0).then(|| i64::from(raw) * 20_000 - 50_000_000);
                }
                s.temperature_c = inp.u8() as i8;
                self.node.update_sample(&s, self.now);
                Stimulus::Sample
            }
            0xF0..=0xF7 => {
                self.node.power_off();
                self.powered = false;
                Stimulus::PowerCycle
            }
            _ => {
                self.node.power_on(self.now);
                self.powered = true;
                self.owed = 0;
                self.deaf_until = Instant::ZERO;
                Stimulus::PowerCycle
            }
        };
        let out = self.drain();
        if std::env::var_os("CANPOS_HARNESS_TRACE").is_some() {
            // Diagnosing a fuzz crash: every step with its effect.
            eprintln!(
                "{:>9} µs op {op:02X} id {id_before}→{} {nmt_before:?}→{:?} out {out:02X?}",
                self.now.micros(),
                self.node_id(),
                self.node.device().nmt_state()
            );
        }
        let ids_after = self.own_ids();
        let what = format!("op {op:02X} at {} µs", self.now.micros());
        self.check_frames(&out, &[ids_before, ids_after], &what)?;
        if !self.powered && !out.is_empty() {
            return Err(format!("{what}: powered off but sent {out:?}"));
        }
        let nmt_after = self.node.device().nmt_state();
        self.check_nmt(&stim, id_before, nmt_before, nmt_after, &out, &what)?;
        self.check_sdo(
            &stim, id_before, nmt_before, sdo_before, sdo_busy, &out, &what,
        )
    }

    /// Builds a frame aimed mostly at the node's own services (so the fuzzer reaches deep
    /// protocol states) and sometimes anywhere.
    fn frame(&mut self, op: u8, inp: &mut Input) -> Frame {
        let own = u16::from(self.node_id() & 0x7F);
        let len_rtr = inp.u8();
        let len = usize::from(len_rtr & 0x0F).min(8);
        let rtr = len_rtr & 0x10 != 0 && op % 16 >= 6;
        let mut data = [0u8; 8];
        for b in data.iter_mut().take(len) {
            *b = inp.u8();
        }
        let id: u32 = match op % 16 {
            0 | 1 => 0x000,
            2..=5 => 0x600 + u32::from(own),
            6 => 0x7E5,
            7 => 0x700 + u32::from(own),
            8 => 0x080,
            9 => 0x180 + u32::from(own) + 0x100 * u32::from(inp.u8() % 4),
            10 => u32::from(inp.u16() & 0x7FF),
            11 => {
                return Frame::with_id(u32::from(inp.u16()) << 13 | 0x600, true, &data[..len])
                    .unwrap_or(Frame::std8(0x7FF, data))
            }
            _ => 0x600 + u32::from(own),
        };
        if op % 16 <= 1 && len >= 2 {
            // NMT: mostly a command byte the node knows, for this node or all.
            const CMDS: [u8; 6] = [0x01, 0x02, 0x80, 0x81, 0x82, 0x03];
            data[0] = CMDS[usize::from(data[0]) % CMDS.len()];
            if data[1] & 0x80 == 0 {
                data[1] = if data[1] & 1 == 0 { 0 } else { own as u8 };
            }
        }
        if rtr {
            Frame::remote(id, false, len as u8).unwrap_or(Frame::std8(0x7FF, data))
        } else {
            Frame::with_id(id, false, &data[..len]).unwrap_or(Frame::std8(0x7FF, data))
        }
    }

    /// Advances time. Either in order through every deadline (as a runtime does) or in one
    /// jump (a stalled host), at µs, ms or s scale.
    fn advance(&mut self, op: u8, inp: &mut Input) {
        let raw = u64::from(inp.u16());
        let dt = match op & 3 {
            0 => raw,
            1 => raw * 1000 / 16,
            2 => raw * 1000,
            _ => raw * 100_000,
        };
        let end = Instant::from_micros(self.now.micros() + dt);
        if op & 4 != 0 {
            self.now = end;
            self.node.handle_timeout(end);
            return;
        }
        let mut guard = 0;
        while let Some(d) = self.node.poll_timeout() {
            if d > end || guard > 10_000 {
                break;
            }
            guard += 1;
            self.now = d.max(self.now);
            self.node.handle_timeout(self.now);
        }
        self.now = end;
        self.node.handle_timeout(end);
    }

    fn check_nmt(
        &self,
        stim: &Stimulus,
        id_before: u8,
        before: NmtState,
        after: NmtState,
        out: &[Frame],
        what: &str,
    ) -> Result<(), String> {
        use NmtState::*;
        let id = self.node_id();
        let reset_target = if id == UNCONFIGURED {
            Initialising
        } else {
            PreOperational
        };
        let legal = match stim {
            Stimulus::PowerCycle => true,
            Stimulus::Frame(_) if !self.powered => before == after,
            // A node switching bit rate hears nothing.
            Stimulus::Frame(_) if self.now < self.deaf_until && after == before => true,
            Stimulus::Frame(f) if f.std_id() == Some(0) && !f.is_remote() => {
                let d = f.data();
                let for_us =
                    id_before != UNCONFIGURED && d.len() == 2 && (d[1] == 0 || d[1] == id_before);
                match (for_us, d.first()) {
                    (true, Some(0x01)) => after == Operational || after == before,
                    (true, Some(0x02)) => after == Stopped,
                    (true, Some(0x80)) => after == PreOperational,
                    (true, Some(0x81 | 0x82)) => after == reset_target,
                    _ => after == before,
                }
            }
            Stimulus::Frame(f) if f.std_id() == Some(0x7E5) => {
                after == before || (before == Initialising && after == PreOperational)
            }
            // Guarding, SDO (a write to 0x1029 does not change the state by itself), SYNC, RTR.
            Stimulus::Frame(_) => after == before,
            Stimulus::Time | Stimulus::Sample => {
                after == before
                    || (before == Operational && matches!(after, PreOperational | Stopped))
                    || (before == Initialising && after == PreOperational)
            }
        };
        if !legal {
            return Err(format!(
                "{what}: illegal NMT transition {before:?} → {after:?}"
            ));
        }
        for f in out {
            if f.std_id() == Some(0x700 + u16::from(id & 0x7F)) && !f.is_remote() {
                let ok = match f.data() {
                    [0x00] => true, // boot-up (after a reset; the state is then Pre-op)
                    [b] => (b & 0x7F) == after.code() || (b & 0x7F) == before.code(),
                    _ => false,
                };
                if !ok {
                    return Err(format!(
                        "{what}: error-control byte {:02X?} does not match {before:?}/{after:?}",
                        f.data()
                    ));
                }
            }
        }
        Ok(())
    }

    #[allow(clippy::too_many_arguments)]
    fn check_sdo(
        &mut self,
        stim: &Stimulus,
        id_before: u8,
        nmt_before: NmtState,
        kind_before: Option<TransferKind>,
        busy_before: bool,
        out: &[Frame],
        what: &str,
    ) -> Result<(), String> {
        let sdo_tx = |id: u8| 0x580 + u16::from(id & 0x7F);
        let n = out
            .iter()
            .filter(|f| id_before != UNCONFIGURED && f.std_id() == Some(sdo_tx(id_before)))
            .count() as u32;
        match stim {
            Stimulus::Frame(f)
                if id_before != UNCONFIGURED
                    && f.std_id() == Some(0x600 + u16::from(id_before))
                    && !f.is_remote()
                    && self.powered =>
            {
                if !nmt_before.sdo_allowed() || f.dlc() != 8 {
                    if n != 0 {
                        return Err(format!(
                            "{what}: SDO answered in {nmt_before:?} / DLC {}",
                            f.dlc()
                        ));
                    }
                    return Ok(());
                }
                // An answer still held back from an earlier request (a store) stays owed: it
                // answers that request, not this one.
                // Inside a block transfer a request may be a silent segment, or a new
                // initiate (a store) whose answer is held back: allow one answer later.
                let in_block = matches!(
                    kind_before,
                    Some(TransferKind::BlockDownload | TransferKind::BlockUpload)
                );
                if in_block && n == 0 {
                    self.owed = 1;
                }
                match kind_before {
                    Some(TransferKind::BlockDownload) if n <= 1 => return Ok(()),
                    Some(TransferKind::BlockUpload) if n <= 127 => return Ok(()),
                    Some(TransferKind::BlockDownload | TransferKind::BlockUpload) => {
                        return Err(format!("{what}: {n} SDO frames in a block transfer"))
                    }
                    _ => {}
                }
                if f.data()[0] >> 5 == 4 {
                    if n != 0 {
                        return Err(format!("{what}: client abort answered"));
                    }
                } else if n == 0 {
                    // Only a store holds the answer back (D7); it must come later. The node
                    // holds one answer at most: a second store replaces the first.
                    self.owed = 1;
                } else if n != 1 {
                    return Err(format!(
                        "{what}: {n} answers to one SDO request {:02X?}",
                        f.data()
                    ));
                }
            }
            Stimulus::Frame(f) if f.std_id() == Some(0) || f.std_id() == Some(0x7E5) => {
                // NMT / LSS may reset the node: held answers are dropped with the transfer.
                if n != 0 {
                    return Err(format!("{what}: SDO frame in answer to NMT/LSS"));
                }
                // Only a reset drops a held answer (a boot-up or a new node-id shows one); a
                // stopped node keeps it and sends it if started again before it is due.
                let boot = out
                    .iter()
                    .any(|f| f.id() & 0x780 == 0x700 && f.data() == [0]);
                if self.node_id() != id_before || boot {
                    self.owed = 0;
                }
            }
            Stimulus::Frame(_) | Stimulus::Sample => {
                if n != 0 {
                    return Err(format!("{what}: unsolicited SDO frame"));
                }
            }
            Stimulus::Time => {
                // A held answer, or one abort of a transfer that timed out.
                let allowed = self.owed + u32::from(busy_before);
                if n > allowed {
                    return Err(format!(
                        "{what}: {n} SDO frames from timers (owed {}, busy {busy_before})",
                        self.owed
                    ));
                }
                self.owed = self.owed.saturating_sub(n);
            }
            Stimulus::PowerCycle => self.owed = 0,
        }
        Ok(())
    }
}
