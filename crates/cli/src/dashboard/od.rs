//! The object dictionary as a bus tool reads it (issue 38 items 3, 4 and 8): the values the
//! page's SDO reads brought in (kept per node, exported as a DCF that `canpos run --dcf`
//! starts a unit from), the model's EDS, each TPDO's communication and mapping parameters
//! read over SDO, and a remap by the CiA 301 procedure (D45, D46).
//!
//! Every transfer goes through the dashboard's bus queue, one command at a time, like the
//! object browser's reads and writes.

use axum::extract::{Path, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, put};
use axum::{Json, Router};
use canpos_models as models;
use canpos_stack::od::{DataType, Entry, Range};
use canpos_stack::Table;
use serde_json::{json, Value};

use super::answer::{fail, ApiError};
use super::app::{
    asset, bus_result, known_node, model_of, refused, type_name, value_type, Answer, App,
};
use super::page::OD_JS;
use super::values::MAP_MAX;
use super::watch::BusCmd;
use crate::client::decode::NodeInfo;
use crate::client::sdo::{format_auto, hex_string};

/// The routes of this module (state-changing ones pass the dashboard's guard like the rest).
pub(super) fn routes() -> Router<App> {
    Router::new()
        .route("/od.js", get(|| asset("text/javascript", OD_JS)))
        .route("/api/nodes/{node}/values", get(values))
        .route("/api/nodes/{node}/dcf", get(dcf))
        .route("/api/nodes/{node}/eds", get(eds))
        .route("/api/nodes/{node}/pdo", get(pdo_view))
        .route("/api/nodes/{node}/pdo/{tpdo}", put(remap))
}

/// The values an entry of type `ty` may take: its range in the table, else the type's.
pub(super) fn range_json(e: &Entry) -> Value {
    let signed = e.ty.is_signed();
    let bits = u32::from(e.ty.bits());
    let num = |raw: u32| -> i64 {
        if signed && bits > 0 {
            let shift = 64 - bits;
            (i64::from(raw) << shift) >> shift
        } else {
            i64::from(raw)
        }
    };
    match (e.ty, e.range) {
        (DataType::VisibleString, _) => json!({"text": "text"}),
        (DataType::Domain, _) => json!({"text": "bytes (hex)"}),
        (_, Range::MinMax(lo, hi)) => {
            let (lo, hi) = (num(*lo), num(*hi));
            json!({"min": lo, "max": hi, "text": format!("{lo} … {hi}")})
        }
        (_, Range::OneOf(list)) => {
            let vals: Vec<i64> = list.iter().map(|v| num(*v)).collect();
            let text = vals
                .iter()
                .map(|v| v.to_string())
                .collect::<Vec<_>>()
                .join(", ");
            json!({"one_of": vals, "text": format!("one of {text}")})
        }
        (DataType::Boolean, Range::Any) => json!({"min": 0, "max": 1, "text": "0 … 1"}),
        (_, Range::Any) => {
            let (lo, hi) = if signed {
                (-(1i64 << (bits - 1)), (1i64 << (bits - 1)) - 1)
            } else {
                (0, (1i64 << bits) - 1)
            };
            json!({"min": lo, "max": hi, "text": format!("{lo} … {hi}")})
        }
    }
}

/// Decimals that show a value of resolution `step` units of 10^-`exp` exactly: a 5 µm
/// position step (5000 nm, exp 6 for mm) gives 3, 0.5 µm gives 4, 20 µm gives 2.
pub(super) fn decimals(step: u32, exp: u32) -> u32 {
    let mut d = exp;
    let mut s = step;
    while d > 0 && s != 0 && s.is_multiple_of(10) {
        s /= 10;
        d -= 1;
    }
    d
}

/// The resolution of a node's position (mm) and velocity (mm/s) figures, from its measuring
/// steps (0x6005/1 in nm, 0x6005/2 in 0.01 mm/s): what the page rounds them to.
pub(super) fn resolution(info: Option<&NodeInfo>) -> Value {
    let pos = info.and_then(|i| i.position_step_nm);
    let vel = info.and_then(|i| i.velocity_step);
    json!({
        "position_step_nm": pos,
        "position_decimals": pos.map_or(3, |s| decimals(s, 6)),
        "velocity_decimals": vel.map_or(2, |s| decimals(s, 2)),
    })
}

fn entry_of(table: &Table, index: u16, sub: u8) -> Option<&'static Entry> {
    let entries: &'static [Entry] = table.entries;
    entries.iter().find(|e| e.index == index && e.sub == sub)
}

/// `GET /api/nodes/N/values`: what the SDO reads of node N brought in.
async fn values(State(app): State<App>, Path(node): Path<String>) -> Answer {
    let id = known_node(&app, &node)?;
    let model = model_of(&app, id)?;
    let list: Vec<Value> = app
        .od
        .of(id)
        .iter()
        .map(|(index, sub, d)| {
            let e = entry_of(model, *index, *sub);
            let value = e
                .and_then(|e| value_type(e.ty).decode(d).ok())
                .unwrap_or_else(|| format_auto(d));
            json!({
                "index": format!("0x{index:04X}"), "sub": sub,
                "name": e.map(|e| e.name), "value": value, "hex": hex_string(d),
            })
        })
        .collect();
    Ok(Json(json!({"ok": true, "node": id, "values": list})))
}

/// The canpos model behind node `id`'s table (a node whose table came from an EDS file has
/// none: that file is its description).
fn canpos_model(app: &App, id: u8) -> Result<&'static models::Model, ApiError> {
    let table = model_of(app, id)?;
    models::all()
        .into_iter()
        .find(|m| std::ptr::eq(&models::widest(m).table, table))
        .ok_or_else(|| {
            fail(
                StatusCode::CONFLICT,
                format!(
                    "node {id}: its table ({}) is not a canpos model's: the EDS file it came from is its description",
                    table.product
                ),
            )
        })
}

fn text_file(name: String, text: String) -> Response {
    (
        [
            (
                header::CONTENT_TYPE,
                "text/plain; charset=utf-8".to_string(),
            ),
            (
                header::CONTENT_DISPOSITION,
                format!("attachment; filename=\"{name}\""),
            ),
            (header::CACHE_CONTROL, "no-store".to_string()),
        ],
        text,
    )
        .into_response()
}

/// `GET /api/nodes/N/dcf`: the DCF of node N with the values read so far (what `canpos dcf
/// --node N` writes after reading them all; `canpos run --dcf FILE` starts a unit from it).
async fn dcf(State(app): State<App>, Path(node): Path<String>) -> Result<Response, ApiError> {
    let id = known_node(&app, &node)?;
    let model = canpos_model(&app, id)?;
    let values = app.od.of(id);
    if values.is_empty() {
        return Err(fail(
            StatusCode::CONFLICT,
            format!("node {id}: no value read yet (read all first: the DCF holds the values read)"),
        ));
    }
    let cfg = crate::cmd::dcf::unit_of_reads(model, model.default_config.with_node_id(id), &values);
    let name = format!("canpos-{}-{id}.dcf", model.name);
    let text = crate::cmd::dcf::render(model, &cfg, "", Some(std::path::Path::new(&name)), &values)
        .map_err(|e| fail(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
    Ok(text_file(name, text))
}

/// `GET /api/nodes/N/eds`: the EDS of node N's model (`canpos eds --model M`; a TMI whose
/// channel 2 answered, the two-channel unit's).
async fn eds(State(app): State<App>, Path(node): Path<String>) -> Result<Response, ApiError> {
    let id = known_node(&app, &node)?;
    let model = canpos_model(&app, id)?;
    let cfg = crate::cmd::dcf::unit_of_reads(model, model.default_config, &app.od.of(id));
    let name = format!("canpos-{}.eds", model.name);
    let (date, time) = crate::capture::eds_date_time(std::time::SystemTime::now());
    let info = canpos_stack::eds::EdsInfo {
        file_name: &name,
        date: &date,
        time: &time,
        ..Default::default()
    };
    let mut text = String::new();
    canpos_stack::eds::write_eds(&mut text, model, &cfg, &info).map_err(|_| {
        fail(
            StatusCode::INTERNAL_SERVER_ERROR,
            "formatting the EDS failed".into(),
        )
    })?;
    Ok(text_file(name, text))
}

/// Whether a failed transfer had no answer (an SDO timeout): on a loaded host a node may
/// answer one transfer later than the dashboard's SDO timeout, so such a transfer is tried once
/// more (D45); an abort is the node's answer and is never retried.
fn no_answer(e: &ApiError) -> bool {
    e.0 == StatusCode::BAD_GATEWAY && e.1.contains("SDO timeout")
}

/// One SDO upload through the bus queue, as a number (tried again once without an answer).
async fn read_u32(app: &App, id: u8, index: u16, sub: u8) -> Result<u32, ApiError> {
    let once = || async {
        let p = app
            .cmds
            .submit(|job| BusCmd::Read(id, index, sub, job))
            .map_err(|r| refused(app, r))?;
        bus_result(app, id, p).await
    };
    let d = match once().await {
        Err(e) if no_answer(&e) => once().await,
        r => r,
    }
    .map_err(|e| step_error(e, format!("reading 0x{index:04X}/{sub}")))?;
    let mut b = [0u8; 4];
    let n = d.len().min(4);
    b[..n].copy_from_slice(&d[..n]);
    Ok(u32::from_le_bytes(b))
}

/// One SDO download through the bus queue of a value `bytes` long (tried again once without an
/// answer: the PDO parameters a remap writes take the same value twice alike).
async fn write(
    app: &App,
    id: u8,
    index: u16,
    sub: u8,
    v: u32,
    bytes: usize,
) -> Result<(), ApiError> {
    let once = || async {
        let data = v.to_le_bytes()[..bytes].to_vec();
        let p = app
            .cmds
            .submit(|job| BusCmd::Write(id, index, sub, data, job))
            .map_err(|r| refused(app, r))?;
        bus_result(app, id, p).await
    };
    match once().await {
        Err(e) if no_answer(&e) => once().await,
        r => r,
    }
    .map_err(|e| step_error(e, format!("writing 0x{index:04X}/{sub} = 0x{v:X}")))
}

fn step_error(e: ApiError, step: String) -> ApiError {
    fail(e.0, format!("{step}: {}", e.1))
}

/// The TPDOs a table has: numbers 1… of its 0x1800+n/1 entries.
fn tpdos(table: &Table) -> Vec<u16> {
    table
        .entries
        .iter()
        .filter(|e| (0x1800..0x1A00).contains(&e.index) && e.sub == 1)
        .map(|e| e.index - 0x1800 + 1)
        .collect()
}

/// A mapping entry `index<<16 | sub<<8 | bits` with the name its table gives it.
fn mapped(table: &Table, m: u32) -> Value {
    let (index, sub, bits) = ((m >> 16) as u16, (m >> 8) as u8, m as u8);
    let name = entry_of(table, index, sub).map(|e| e.name);
    json!({
        "raw": format!("0x{m:08X}"), "index": format!("0x{index:04X}"), "sub": sub,
        "bits": bits, "name": name,
    })
}

/// The parameters of TPDO `n` of node `id`, read over SDO.
async fn read_tpdo(app: &App, id: u8, table: &Table, n: u16) -> Result<Value, ApiError> {
    let comm = 0x1800 + n - 1;
    let map = 0x1A00 + n - 1;
    let has = |sub: u8| entry_of(table, comm, sub).is_some();
    let cob = read_u32(app, id, comm, 1).await?;
    let ty = read_u32(app, id, comm, 2).await?;
    let inhibit = if has(3) {
        Some(read_u32(app, id, comm, 3).await?)
    } else {
        None
    };
    let event = if has(5) {
        Some(read_u32(app, id, comm, 5).await?)
    } else {
        None
    };
    let count = read_u32(app, id, map, 0).await?.min(MAP_MAX as u32);
    let mut entries = Vec::new();
    for s in 1..=count as u8 {
        entries.push(mapped(table, read_u32(app, id, map, s).await?));
    }
    Ok(json!({
        "tpdo": n,
        "cob_id": format!("0x{cob:08X}"),
        "can_id": format!("0x{:03X}", cob & 0x7FF),
        "valid": cob & 0x8000_0000 == 0,
        "transmission_type": ty,
        "transmission": transmission_text(ty as u8),
        "inhibit_100us": inhibit,
        "inhibit_ms": inhibit.map(|v| v as f64 / 10.0),
        "event_ms": event,
        "mapping": entries,
    }))
}

/// What a TPDO's transmission type (0x1800+n/2) means (CiA 301 Table 72).
fn transmission_text(t: u8) -> String {
    match t {
        0 => "synchronous (acyclic)".into(),
        1 => "synchronous, every SYNC".into(),
        2..=240 => format!("synchronous, every {t}th SYNC"),
        241..=251 => "reserved".into(),
        252 => "RTR-only, synchronous".into(),
        253 => "RTR-only, event-driven".into(),
        254 => "event-driven (manufacturer-specific)".into(),
        255 => "event-driven (device profile)".into(),
    }
}

/// The objects of a table a TPDO may map, for the page's picker.
fn mappable(table: &Table) -> Vec<Value> {
    table
        .entries
        .iter()
        .filter(|e| e.pdo && e.ty.bits() > 0)
        .map(|e| {
            json!({"index": format!("0x{:04X}", e.index), "sub": e.sub, "name": e.name,
                   "bits": e.ty.bits()})
        })
        .collect()
}

/// `GET /api/nodes/N/pdo`: every TPDO of node N read over SDO.
async fn pdo_view(State(app): State<App>, Path(node): Path<String>) -> Answer {
    let id = known_node(&app, &node)?;
    let table = model_of(&app, id)?;
    let mut list = Vec::new();
    for n in tpdos(table) {
        list.push(read_tpdo(&app, id, table, n).await?);
    }
    Ok(Json(json!({
        "ok": true, "node": id, "tpdos": list, "mappable": mappable(table),
    })))
}

/// One object of a remap's `mapping`: `"0x6020/1"` (its size from the table) or a raw entry
/// `"0x60200120"`.
fn parse_mapping(table: &Table, v: &Value) -> Result<u32, String> {
    let s = v
        .as_str()
        .ok_or_else(|| format!("{v}: expected \"INDEX/SUB\" or a raw 32-bit entry"))?
        .trim();
    if let Some((ix, sb)) = s.split_once('/') {
        let ix = crate::common::parse_index(ix).map_err(|e| format!("`{s}`: {e}"))?;
        let sb = crate::common::parse_sub(sb).map_err(|e| format!("`{s}`: {e}"))?;
        let e = entry_of(table, ix, sb)
            .ok_or_else(|| format!("`{s}`: the {} has no object 0x{ix:04X}/{sb}", table.product))?;
        let bits = e.ty.bits();
        if bits == 0 {
            return Err(format!(
                "`{s}` ({}) is {}: it has no size a PDO could carry",
                e.name,
                type_name(e.ty)
            ));
        }
        return Ok(u32::from(ix) << 16 | u32::from(sb) << 8 | u32::from(bits));
    }
    let hex = s
        .strip_prefix("0x")
        .or_else(|| s.strip_prefix("0X"))
        .filter(|h| h.len() == 8)
        .ok_or_else(|| format!("`{s}`: expected \"INDEX/SUB\" or a raw entry 0xIIIISSLL"))?;
    u32::from_str_radix(hex, 16).map_err(|_| format!("`{s}`: not hex"))
}

/// `PUT /api/nodes/N/pdo/T` `{"mapping": ["0x6020/1", …], "transmission_type": 255,
/// "inhibit_100us": 0, "event_ms": 1}`: remaps TPDO T by the CiA 301 procedure — COB-ID bit 31
/// set (invalid), mapping count 0, the entries, the count, the communication parameters given,
/// COB-ID valid again. The node checks each step; if it refuses one (SDO abort), the TPDO's
/// previous mapping and parameters are written back the same way and the abort is the answer
/// (D46).
async fn remap(
    State(app): State<App>,
    Path((node, tpdo)): Path<(String, String)>,
    body: String,
) -> Answer {
    let id = known_node(&app, &node)?;
    let table = model_of(&app, id)?;
    let n: u16 = tpdo
        .parse()
        .ok()
        .filter(|n| tpdos(table).contains(n))
        .ok_or_else(|| {
            fail(
                StatusCode::NOT_FOUND,
                format!(
                    "no TPDO `{tpdo}` on the {} (it has {:?})",
                    table.product,
                    tpdos(table)
                ),
            )
        })?;
    let bad = |why: String| fail(StatusCode::BAD_REQUEST, format!("bad body: {why}"));
    let v: Value = serde_json::from_str(&body).map_err(|e| bad(e.to_string()))?;
    let list = v["mapping"]
        .as_array()
        .ok_or_else(|| bad("expected {\"mapping\": [\"0x6020/1\", …]}".into()))?;
    if list.len() > MAP_MAX {
        return Err(bad(format!(
            "{} mapping entries, at most {MAP_MAX}",
            list.len()
        )));
    }
    let mapping = list
        .iter()
        .map(|m| parse_mapping(table, m))
        .collect::<Result<Vec<u32>, _>>()
        .map_err(bad)?;
    let number = |key: &str, max: u32| -> Result<Option<u32>, ApiError> {
        match &v[key] {
            Value::Null => Ok(None),
            x => x
                .as_u64()
                .filter(|x| *x <= u64::from(max))
                .map(|x| Some(x as u32))
                .ok_or_else(|| bad(format!("`{key}`: {x} is no number of 0…{max}"))),
        }
    };
    let comm = 0x1800 + n - 1;
    let map = 0x1A00 + n - 1;
    let ty = number("transmission_type", 255)?;
    let inhibit = number("inhibit_100us", 65535)?;
    let event = number("event_ms", 65535)?;
    let has = |sub: u8| entry_of(table, comm, sub).is_some();
    if (inhibit.is_some() && !has(3)) || (event.is_some() && !has(5)) {
        return Err(bad(format!(
            "TPDO {n} of the {} has no {}",
            table.product,
            if inhibit.is_some() && !has(3) {
                "inhibit time"
            } else {
                "event timer"
            }
        )));
    }
    let _remapping = app.od.start_remap(id).ok_or_else(|| {
        fail(
            StatusCode::CONFLICT,
            format!("node {id}: another remap is running on it; try again when it has ended"),
        )
    })?;
    // What the TPDO is now, to restore it if the node refuses a step.
    let before = Tpdo {
        cob: read_u32(&app, id, comm, 1).await?,
        ty: read_u32(&app, id, comm, 2).await?,
        inhibit: if has(3) {
            Some(read_u32(&app, id, comm, 3).await?)
        } else {
            None
        },
        event: if has(5) {
            Some(read_u32(&app, id, comm, 5).await?)
        } else {
            None
        },
        mapping: {
            let count = read_u32(&app, id, map, 0).await?.min(MAP_MAX as u32);
            let mut m = Vec::new();
            for s in 1..=count as u8 {
                m.push(read_u32(&app, id, map, s).await?);
            }
            m
        },
    };
    let after = Tpdo {
        cob: before.cob & !0x8000_0000,
        ty: ty.unwrap_or(before.ty),
        inhibit: inhibit.or(before.inhibit),
        event: event.or(before.event),
        mapping,
    };
    match apply(&app, id, n, &before, &after).await {
        Ok(()) => {
            app.shared.lock().unwrap().forget_mapping(id);
            let now = read_tpdo(&app, id, table, n).await?;
            Ok(Json(json!({"ok": true, "node": id, "tpdo": now})))
        }
        Err(e) => {
            // The node refused a step: put back what was there, the same way.
            let restored = match apply(&app, id, n, &after, &before).await {
                Ok(()) => "the previous mapping and parameters were written back".to_string(),
                Err(r) => format!("writing the previous mapping back failed too ({}): the TPDO may be left invalid", r.1),
            };
            app.shared.lock().unwrap().forget_mapping(id);
            Err(fail(
                e.0,
                format!("remap of TPDO {n} refused at {}; {restored}", e.1),
            ))
        }
    }
}

/// A TPDO's parameters.
struct Tpdo {
    cob: u32,
    ty: u32,
    inhibit: Option<u32>,
    event: Option<u32>,
    mapping: Vec<u32>,
}

/// Writes `to` into TPDO `n` of node `id` (now `from`) by the CiA 301 procedure.
async fn apply(app: &App, id: u8, n: u16, from: &Tpdo, to: &Tpdo) -> Result<(), ApiError> {
    let comm = 0x1800 + n - 1;
    let map = 0x1A00 + n - 1;
    write(app, id, comm, 1, from.cob | 0x8000_0000, 4).await?;
    write(app, id, map, 0, 0, 1).await?;
    for (i, m) in to.mapping.iter().enumerate() {
        write(app, id, map, i as u8 + 1, *m, 4).await?;
    }
    write(app, id, map, 0, to.mapping.len() as u32, 1).await?;
    if to.ty != from.ty {
        write(app, id, comm, 2, to.ty, 1).await?;
    }
    if let Some(v) = to.inhibit.filter(|v| Some(*v) != from.inhibit) {
        write(app, id, comm, 3, v, 2).await?;
    }
    if let Some(v) = to.event.filter(|v| Some(*v) != from.event) {
        write(app, id, comm, 5, v, 2).await?;
    }
    if to.cob & 0x8000_0000 == 0 {
        write(app, id, comm, 1, to.cob, 4).await?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decimals_follow_the_step() {
        // Positions in mm from nm steps.
        assert_eq!(decimals(1000, 6), 3);
        assert_eq!(decimals(5000, 6), 3);
        assert_eq!(decimals(500, 6), 4);
        assert_eq!(decimals(20000, 6), 2);
        assert_eq!(decimals(1, 6), 6);
        // Velocities in mm/s from 0.01 mm/s steps.
        assert_eq!(decimals(100, 2), 0);
        assert_eq!(decimals(1, 2), 2);
        assert_eq!(decimals(10, 2), 1);
    }

    /// The served page's node table rounds a position to the node's step (D47).
    #[test]
    fn the_served_table_shows_positions_at_their_resolution() {
        let info = NodeInfo {
            position_step_nm: Some(20_000),
            velocity_step: Some(100),
            tpdos: Vec::new(),
        };
        let res = resolution(Some(&info));
        assert_eq!(
            (&res["position_decimals"], &res["velocity_decimals"]),
            (&json!(2), &json!(0))
        );
        let snap = json!({
            "t": 1.0, "seq": 1, "bus": "mem://x",
            "nodes": [{"node": 5, "positions": [250.123456, null], "positions_from": "TPDO",
                       "resolution": res}],
        });
        let page = super::super::page::render_page(&snap);
        assert!(
            page.contains(r#"<td class="pos">250.12 mm · no position</td>"#),
            "{page}"
        );
    }

    #[test]
    fn ranges_read_with_the_types_sign() {
        let th = &models::widest(models::all()[0]).table;
        let e = th.entries.iter().find(|e| e.index == 0x1017).unwrap();
        assert_eq!(range_json(e)["text"], "0 … 65535");
        let e = th
            .entries
            .iter()
            .find(|e| e.ty == DataType::Integer32 && e.range == &Range::Any)
            .unwrap();
        assert_eq!(range_json(e)["min"], -2147483648i64);
    }

    #[test]
    fn mapping_entries_take_their_size_from_the_table() {
        let th = &models::widest(models::all()[0]).table;
        assert_eq!(parse_mapping(th, &json!("0x6020/1")), Ok(0x6020_0120));
        assert_eq!(parse_mapping(th, &json!("0x60200120")), Ok(0x6020_0120));
        assert!(parse_mapping(th, &json!("0x7777/1")).is_err());
        assert!(parse_mapping(th, &json!(5)).is_err());
    }
}
