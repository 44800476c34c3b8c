//! The control requests of a plain device ([`super::PlainRuntime`]): `state` (NMT state and the
//! process objects of the device profile area), `set-input` (an input as the device's own
//! process sets it) and `nmt`. A plain device has no magnets, motion or faults: those
//! requests are refused with the list of the ones it takes.

use canpos_stack::nmt::NmtState;
use canpos_stack::od::{Access, DataType, Entry};
use canpos_stack::{Frame, Instant, Node, Plain};
use serde_json::{json, Value};

use crate::control::request::{nmt_command, Request};
use canpos_stack::storage::Storage;

/// The device profile area (CiA 301): the objects a profile such as CiA 401 defines, the
/// inputs and outputs among them.
pub const PROFILE_AREA: std::ops::RangeInclusive<u16> = 0x6000..=0x9FFF;

/// The requests a plain device takes, for messages.
const TAKES: &str = "state, set-input, nmt";

/// What a process object is to the device, from its access and mapping.
fn direction(e: &Entry) -> &'static str {
    match e.access {
        // Only the device's process changes it: an input.
        Access::Ro => "input",
        Access::Const => "constant",
        // The master writes it: by PDO an output, by SDO only a parameter.
        Access::Rw | Access::Wo if e.pdo => "output",
        Access::Rw | Access::Wo => "parameter",
    }
}

/// The CiA 301 name of a numeric data type.
fn type_name(t: DataType) -> &'static str {
    match t {
        DataType::Boolean => "BOOLEAN",
        DataType::Integer8 => "INTEGER8",
        DataType::Integer16 => "INTEGER16",
        DataType::Integer32 => "INTEGER32",
        DataType::Unsigned8 => "UNSIGNED8",
        DataType::Unsigned16 => "UNSIGNED16",
        DataType::Unsigned32 => "UNSIGNED32",
        DataType::VisibleString => "VISIBLE_STRING",
        DataType::Domain => "DOMAIN",
    }
}

/// Whether `e` is sub-index 0 of an object with more sub-indices (its number of entries,
/// no process value).
fn is_count<S: Storage>(node: &Node<Plain, S>, e: &Entry) -> bool {
    e.sub == 0
        && node
            .device()
            .od()
            .entries()
            .iter()
            .any(|o| o.index == e.index && o.sub != 0)
}

/// `0x6000/1`, as messages name an object.
fn object(index: u16, sub: u8) -> String {
    format!("0x{index:04X}/{sub}")
}

/// The NMT state's name, as a sensor's state gives it.
pub fn nmt_name(s: NmtState) -> &'static str {
    match s {
        NmtState::Initialising => "initialising",
        NmtState::PreOperational => "pre-operational",
        NmtState::Operational => "operational",
        NmtState::Stopped => "stopped",
    }
}

/// The process objects of `node`: every numeric entry of [`PROFILE_AREA`] but the number of
/// entries of an array, with its value as the dictionary holds it (an output as the master
/// last wrote it).
pub fn process_objects<S: Storage>(node: &Node<Plain, S>) -> Vec<Value> {
    let od = node.device().od();
    od.entries()
        .iter()
        .enumerate()
        .filter(|(_, e)| PROFILE_AREA.contains(&e.index) && e.ty.size().is_some())
        .filter(|(_, e)| !is_count(node, e))
        .map(|(slot, e)| {
            json!({
                "index": format!("0x{:04X}", e.index),
                "sub": e.sub,
                "name": e.name,
                "type": type_name(e.ty),
                "access": e.access.eds(),
                "direction": direction(e),
                "value": e.ty.to_i64(od.get(slot)),
            })
        })
        .collect()
}

/// The `state` answer of a plain device.
pub fn state<S: Storage>(node: &Node<Plain, S>, storage: &str) -> Value {
    let dev = node.device();
    let model = dev.model();
    json!({
        "ok": true,
        "device": "eds",
        "model": model.name,
        "name": model.product,
        "vendor": model.vendor,
        "node_id": dev.node_id(),
        "bitrate_kbps": dev.bitrate(),
        "serial": dev.config().serial,
        "nmt": nmt_name(dev.nmt_state()),
        "powered": dev.powered(),
        "error_register": dev.od().value(0x1001, 0),
        "storage": storage,
        "faults": [],
        "process": process_objects(node),
    })
}

/// Checks a `set-input` of `v` to `index`/`sub` against the object: it exists, is an input of
/// the device profile area, and `v` suits its type and range. Returns the raw value to write.
pub fn check_input<S: Storage>(
    node: &Node<Plain, S>,
    index: u16,
    sub: u8,
    v: i64,
) -> Result<u32, String> {
    let obj = object(index, sub);
    let od = node.device().od();
    let slot = od
        .find(index, sub)
        .map_err(|_| format!("{obj} does not exist in the device's dictionary"))?;
    let e = od.entry(slot);
    if !PROFILE_AREA.contains(&index) {
        // Said as it is: the master writes a writable one; a read-only one (0x1001, 0x1018)
        // is the stack's own.
        let who = if e.access.writable() {
            "the master sets it by SDO"
        } else {
            "it is read-only, kept by the device's CANopen services"
        };
        return Err(format!(
            "{obj} `{}` is no process object (those are 0x6000 … 0x9FFF, the device profile area): {who}",
            e.name
        ));
    }
    if is_count(node, e) {
        return Err(format!(
            "{obj} is the number of entries of 0x{index:04X}, not an input"
        ));
    }
    let Some(size) = e.ty.size() else {
        return Err(format!(
            "{obj} `{}` is a {}, not a number",
            e.name,
            type_name(e.ty)
        ));
    };
    match direction(e) {
        "input" => {}
        "constant" => return Err(format!("{obj} `{}` is a constant", e.name)),
        d => {
            return Err(format!(
                "{obj} `{}` is an {d} ({}): the master writes it (SDO{}), the device does not",
                e.name,
                e.access.eds(),
                if d == "output" { " or an RPDO" } else { "" }
            ))
        }
    }
    let (lo, hi) = e.ty.natural_range();
    if !(lo..=hi).contains(&v) {
        return Err(format!(
            "value {v} is out of range for {obj} `{}` ({} {lo} … {hi})",
            e.name,
            type_name(e.ty)
        ));
    }
    if let Some((lo, hi)) = e.limits() {
        if !(lo..=hi).contains(&v) {
            return Err(format!(
                "value {v} is out of the range of {obj} `{}` ({lo} … {hi}, its LowLimit / HighLimit)",
                e.name
            ));
        }
    }
    // Two's complement in the type's bytes, as an SDO write or a PDO carries it.
    let mask = if size >= 4 {
        u32::MAX
    } else {
        (1u32 << (8 * size)) - 1
    };
    Ok(v as u32 & mask)
}

/// The inputs `set-input` set: the module's terminals, which its process reads, not values
/// of its dictionary. A reset node reloads the dictionary's defaults; a real module reads its
/// terminals again at once, so [`Inputs::after_reset`] writes them back.
#[derive(Clone, Debug, Default)]
pub struct Inputs {
    /// (index, sub) → raw value, one per input set (bounded by the dictionary's entries).
    held: std::collections::BTreeMap<(u16, u8), u32>,
    /// The node's reset count when the inputs were last in its dictionary.
    resets: u8,
}

impl Inputs {
    /// Writes the held inputs back into `node` at `now` if it was reset since the last call
    /// (an input is read-only to the bus: only a reset changes it behind the process's back).
    /// Returns whether it was.
    pub fn after_reset<S: Storage>(&mut self, node: &mut Node<Plain, S>, now: Instant) -> bool {
        let resets = node.device().stats().resets;
        if resets == self.resets {
            return false;
        }
        self.resets = resets;
        for (&(index, sub), &raw) in &self.held {
            // Checked when it was set; the table has not changed since.
            let _ = node.write_process_value(index, sub, raw, now);
        }
        true
    }
}

/// Carries out a control request on the plain device `node` at `now`; `storage` names its
/// state file, `inputs` holds what `set-input` set. The frames it causes are left in the node
/// for the caller to send.
pub fn handle<S: Storage>(
    node: &mut Node<Plain, S>,
    req: Request,
    storage: &str,
    inputs: &mut Inputs,
    now: Instant,
) -> Result<Value, String> {
    req.validate()?;
    if let Some(s) = req.sensor().filter(|&s| s != 0) {
        return Err(format!(
            "sensor {s} does not exist (a --eds / --dcf process serves one device, sensor 0)"
        ));
    }
    match req {
        Request::State { .. } => Ok(state(node, storage)),
        Request::SetInput { .. } => {
            let (index, sub, v) = req.input_target()?;
            let raw = check_input(node, index, sub, v)?;
            let changed = node
                .write_process_value(index, sub, raw, now)
                .map_err(|a| format!("{}: {}", object(index, sub), a.meaning()))?;
            inputs.held.insert((index, sub), raw);
            Ok(json!({"ok": true, "changed": changed, "value": v}))
        }
        Request::Nmt { command, .. } => {
            let cs = nmt_command(&command)?;
            let id = node.device().node_id();
            if !(1..=127).contains(&id) {
                return Err(
                    "the device has no node-id yet (LSS unconfigured); it cannot take NMT commands"
                        .into(),
                );
            }
            // Handed to this node alone: nothing goes on the bus.
            let f = Frame::new(0x000, &[cs, id]).map_err(|e| format!("{e:?}"))?;
            node.handle_frame(&f, now);
            Ok(json!({"ok": true}))
        }
        other => {
            let cmd = serde_json::to_value(&other).unwrap_or_default()["cmd"]
                .as_str()
                .unwrap_or("?")
                .to_string();
            Err(format!(
                "a plain (EDS / DCF) device has no `{cmd}` request; it takes {TAKES}"
            ))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eds_device::{build, FileKind, Overrides};
    use canpos_stack::storage::RamStorage;

    const IO401: &str = include_str!(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../examples/io-401.eds"
    ));
    const ID: u8 = 5;

    /// The I/O module of examples/io-401.eds, booted at t = 0 on the virtual clock, its
    /// boot-up taken.
    fn io401() -> Node<Plain, RamStorage> {
        let o = Overrides {
            node_id: Some(ID),
            bitrate_kbps: None,
            serial: None,
        };
        let d = build(IO401, "io-401.eds", FileKind::Eds, &o).unwrap();
        let mut n = Node::with_app(d.model, d.cfg, Plain, RamStorage::default());
        n.power_on(Instant::from_micros(0));
        while n.poll(Instant::from_micros(0)).is_some() {}
        n
    }

    fn req(line: &str) -> Request {
        crate::control::parse_request(line).unwrap()
    }

    /// Every frame the node sends at `t`.
    fn sent(n: &mut Node<Plain, RamStorage>, t: u64) -> Vec<Frame> {
        std::iter::from_fn(|| n.poll(Instant::from_micros(t))).collect()
    }

    fn ask(n: &mut Node<Plain, RamStorage>, line: &str, t: u64) -> Result<Value, String> {
        handle(
            n,
            req(line),
            "ram",
            &mut Inputs::default(),
            Instant::from_micros(t),
        )
    }

    fn object_of<'a>(st: &'a Value, index: &str, sub: u64) -> &'a Value {
        st["process"]
            .as_array()
            .unwrap()
            .iter()
            .find(|o| o["index"] == index && o["sub"] == sub)
            .unwrap_or_else(|| panic!("{index}/{sub} not in {st}"))
    }

    #[test]
    fn the_state_shows_nmt_and_the_process_objects_by_direction() {
        let mut n = io401();
        let st = ask(&mut n, r#"{"cmd":"state"}"#, 10).unwrap();
        assert_eq!(st["device"], "eds", "{st}");
        assert_eq!(st["nmt"], "pre-operational", "{st}");
        assert_eq!(st["node_id"], ID, "{st}");
        let p = st["process"].as_array().unwrap();
        // 2 + 2 digital groups, 12 + 12 analogue channels; no "number of entries".
        assert_eq!(p.len(), 28, "{st}");
        assert!(p.iter().all(|o| o["sub"] != 0), "{st}");
        let di = object_of(&st, "0x6000", 1);
        assert_eq!(
            (&di["direction"], &di["type"], &di["name"]),
            (
                &json!("input"),
                &json!("UNSIGNED8"),
                &json!("Read input 1h to 8h")
            )
        );
        assert_eq!(object_of(&st, "0x6200", 2)["direction"], "output");
        assert_eq!(object_of(&st, "0x6401", 12)["type"], "INTEGER16");
        assert_eq!(object_of(&st, "0x6411", 1)["direction"], "output");
        ask(&mut n, r#"{"cmd":"nmt","command":"start"}"#, 20).unwrap();
        let st = ask(&mut n, r#"{"cmd":"state"}"#, 30).unwrap();
        assert_eq!(st["nmt"], "operational", "{st}");
    }

    #[test]
    fn a_set_input_is_a_change_of_state_event_for_the_tpdo_that_maps_it() {
        let mut n = io401();
        // Pre-operational: stored, shown, no PDO.
        let r = ask(
            &mut n,
            r#"{"cmd":"set-input","index":"0x6000","sub":2,"value":"0xA5"}"#,
            10,
        );
        assert_eq!(r.unwrap()["changed"], true);
        assert!(sent(&mut n, 10).is_empty());
        assert_eq!(n.read_object(0x6000, 2), Ok(0xA5));
        ask(&mut n, r#"{"cmd":"nmt","command":"start"}"#, 20).unwrap();
        sent(&mut n, 20);
        let r = ask(
            &mut n,
            r#"{"cmd":"set-input","index":24576,"sub":1,"value":3}"#,
            30,
        );
        assert_eq!(r.unwrap()["changed"], true);
        let f = sent(&mut n, 30);
        assert_eq!(f.len(), 1, "{f:?}");
        assert_eq!(f[0].std_id(), Some(0x180 + u16::from(ID)));
        assert_eq!(f[0].data(), &[3, 0xA5]);
        // The same value again is no change: nothing is sent.
        let r = ask(
            &mut n,
            r#"{"cmd":"set-input","index":"0x6000","sub":1,"value":3}"#,
            40,
        );
        assert_eq!(r.unwrap()["changed"], false);
        assert!(sent(&mut n, 40).is_empty());
        // Analogue input 6 (INTEGER16) in TPDO3 (channels 5…8), two's complement.
        ask(
            &mut n,
            r#"{"cmd":"set-input","index":"0x6401","sub":6,"value":-2}"#,
            50,
        )
        .unwrap();
        let f = sent(&mut n, 50);
        assert_eq!(f.len(), 1, "{f:?}");
        assert_eq!(f[0].std_id(), Some(0x380 + u16::from(ID)));
        assert_eq!(f[0].data(), &[0, 0, 0xFE, 0xFF, 0, 0, 0, 0]);
        let st = ask(&mut n, r#"{"cmd":"state"}"#, 60).unwrap();
        assert_eq!(object_of(&st, "0x6401", 6)["value"], -2);
        assert_eq!(object_of(&st, "0x6000", 2)["value"], 0xA5);
        // The range ends of the type are taken.
        for v in [-32768, 32767] {
            let line = format!(r#"{{"cmd":"set-input","index":"0x6401","sub":1,"value":{v}}}"#);
            assert_eq!(ask(&mut n, &line, 70).unwrap()["changed"], true);
        }
    }

    #[test]
    fn a_refused_set_input_says_why_and_changes_nothing() {
        let mut n = io401();
        ask(&mut n, r#"{"cmd":"nmt","command":"start"}"#, 0).unwrap();
        sent(&mut n, 0);
        let before = ask(&mut n, r#"{"cmd":"state"}"#, 1).unwrap()["process"].clone();
        let cases = [
            (r#""index":"0x6000","sub":3,"value":1"#, "does not exist"),
            (r#""index":"0x6200","sub":1,"value":1"#, "is an output (rw)"),
            (r#""index":"0x1017","value":100"#, "no process object"),
            (
                r#""index":"0x1017","value":100"#,
                "the master sets it by SDO",
            ),
            (
                r#""index":"0x1001","value":1"#,
                "read-only, kept by the device",
            ),
            (
                r#""index":"0x1018","sub":1,"value":1"#,
                "read-only, kept by the device",
            ),
            (r#""index":"0x1A00","sub":1,"value":0"#, "no process object"),
            (r#""index":"0x6000","sub":0,"value":1"#, "number of entries"),
            (r#""index":"0x6000","sub":1,"value":256"#, "out of range"),
            (r#""index":"0x6000","sub":1,"value":-1"#, "out of range"),
            (r#""index":"0x6401","sub":1,"value":32768"#, "out of range"),
            (r#""index":"0x6401","sub":1,"value":-32769"#, "out of range"),
            (
                r#""index":"0x6401","sub":1,"value":1.5"#,
                "not a whole number",
            ),
            (
                r##""index":"0x6401","sub":1,"value":"ten""##,
                "not a whole number",
            ),
            (
                r#""index":"0x6401","sub":1,"value":null"#,
                "not a whole number",
            ),
            (r#""index":"0x10000","value":1"#, "not an object index"),
            (r#""index":"0x6000","sub":256,"value":1"#, "not a sub-index"),
            (
                r#""sensor":1,"index":"0x6000","sub":1,"value":1"#,
                "sensor 1 does not exist",
            ),
        ];
        for (args, why) in cases {
            let line = format!(r#"{{"cmd":"set-input",{args}}}"#);
            let e = ask(&mut n, &line, 2).expect_err(&line);
            assert!(e.contains(why), "{line}: {e}");
            assert!(sent(&mut n, 2).is_empty(), "{line}");
        }
        let after = ask(&mut n, r#"{"cmd":"state"}"#, 3).unwrap()["process"].clone();
        assert_eq!(before, after);
        let e = ask(&mut n, r#"{"cmd":"magnet","mm":10}"#, 4).unwrap_err();
        assert!(
            e.contains("no `magnet` request; it takes state, set-input, nmt"),
            "{e}"
        );
    }

    /// The stack's entry point itself: the entry's rules, whatever a host checked before.
    #[test]
    fn the_stack_refuses_a_process_value_the_entry_cannot_hold() {
        let mut n = io401();
        let t = Instant::from_micros(5);
        use canpos_stack::od::Abort;
        assert_eq!(
            n.write_process_value(0x6000, 1, 0x100, t),
            Err(Abort::InvalidValue)
        );
        assert_eq!(
            n.write_process_value(0x6401, 1, 0x1_0000, t),
            Err(Abort::InvalidValue)
        );
        assert_eq!(n.write_process_value(0x6000, 9, 1, t), Err(Abort::NoSub));
        assert_eq!(n.write_process_value(0x6001, 0, 1, t), Err(Abort::NoObject));
        // A service's object is the service's.
        assert_eq!(
            n.write_process_value(0x1017, 0, 5, t),
            Err(Abort::UnsupportedAccess)
        );
        assert_eq!(n.read_object(0x6000, 1), Ok(0));
        assert_eq!(n.write_process_value(0x6401, 1, 0xFFFF, t), Ok(true));
        assert_eq!(n.read_object(0x6401, 1), Ok(0xFFFF));
    }
}
