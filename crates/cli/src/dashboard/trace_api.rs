//! The trace's and the transmitter's endpoints (issue 38 items 1, 2, 9): the HTTP side of
//! [`super::trace`].

use std::sync::Arc;
use std::time::{Duration, Instant};

use canpos_stack::Frame;
use serde_json::{json, Value};

use super::app::{asset, App};
use super::trace::*;
use crate::capture::Format;
use crate::client::sdo::hex_string;
use crate::client::Monitor;
use axum::extract::{Query, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};

use super::answer::{fail, ApiError};

/// The trace's and transmitter's routes (docs/DASHBOARD.md, "Trace" and "Transmit").
pub(super) fn routes() -> Router<App> {
    Router::new()
        .route("/trace.js", get(|| asset("text/javascript", TRACE_JS)))
        .route("/api/trace", get(trace_get))
        .route("/api/trace/export", get(trace_export))
        .route("/api/trace/clear", post(trace_clear))
        .route("/api/send", get(send_list).post(send))
        .route("/api/send/stop", post(send_stop))
        .route("/api/send/renew", post(send_renew))
        .route("/lease.js", get(|| asset("text/javascript", LEASE_JS)))
        .route("/api/nmt", post(nmt))
}

const TRACE_JS: &str = include_str!("../../assets/dashboard/trace.js");
/// The page's worker that renews its lease (D61).
const LEASE_JS: &str = include_str!("../../assets/dashboard/lease.js");

type Answer = Result<Json<Value>, ApiError>;

/// The query of the trace's reads: `since` (log), `from` / `to` (hex identifiers), `node`.
#[derive(serde::Deserialize, Default)]
struct TraceQuery {
    since: Option<u64>,
    from: Option<String>,
    to: Option<String>,
    node: Option<String>,
    format: Option<String>,
    limit: Option<usize>,
}

fn bad(why: String) -> ApiError {
    fail(StatusCode::BAD_REQUEST, why)
}

/// An identifier: hex with or without `0x`, at most 29 bits.
fn parse_id(s: &str) -> Result<u32, ApiError> {
    let t = s.trim();
    let h = t
        .strip_prefix("0x")
        .or_else(|| t.strip_prefix("0X"))
        .unwrap_or(t);
    if h.is_empty() || h.len() > 8 {
        return Err(bad(format!("identifier `{s}`: expected hex, e.g. 0x185")));
    }
    let v = u32::from_str_radix(h, 16)
        .map_err(|_| bad(format!("identifier `{s}`: expected hex, e.g. 0x185")))?;
    if v > 0x1FFF_FFFF {
        return Err(bad(format!(
            "identifier `{s}` is above 0x1FFFFFFF (29 bits)"
        )));
    }
    Ok(v)
}

fn filter_of(q: &TraceQuery) -> Result<Filter, ApiError> {
    fn opt(v: &Option<String>) -> Option<&str> {
        v.as_deref().filter(|s| !s.trim().is_empty())
    }
    let node = match opt(&q.node) {
        Some(n) => {
            Some(crate::common::parse_node(n.trim(), 1).map_err(|e| bad(format!("node: {e}")))?)
        }
        None => None,
    };
    let f = Filter {
        from: opt(&q.from).map(parse_id).transpose()?,
        to: opt(&q.to).map(parse_id).transpose()?,
        node,
    };
    if let (Some(a), Some(b)) = (f.from, f.to) {
        if a > b {
            return Err(bad(format!("from 0x{a:X} is above to 0x{b:X}")));
        }
    }
    Ok(f)
}

fn query(
    q: Result<Query<TraceQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<TraceQuery, ApiError> {
    q.map(|Query(q)| q).map_err(|e| {
        bad(format!(
            "{}; expected ?since=N&from=0xID&to=0xID&node=N (each optional)",
            e.body_text()
        ))
    })
}

/// The monitor of the mappings the dashboard read, and its trace hub.
fn monitor(app: &App) -> (Monitor, Arc<TraceHub>) {
    let s = app.shared.lock().unwrap();
    let m = monitor_of(
        s.nodes
            .iter()
            .filter_map(|(id, n)| n.info.as_ref().map(|i| (*id, i))),
    );
    (m, s.trace.clone())
}

fn periodic_json(hub: &TraceHub) -> Vec<Value> {
    let now = Instant::now();
    hub.periodic()
        .iter()
        .map(|j| {
            json!({
                "id": id_text(&j.frame), "ext": j.frame.is_extended(), "rtr": j.frame.is_remote(),
                "dlc": j.frame.dlc(), "data": hex_string(j.frame.data()),
                "period_ms": j.period.as_secs_f64() * 1e3, "sent": j.sent,
                "lease": j.lease,
                "ends_in_s": j.ends.saturating_duration_since(now).as_secs_f64(),
            })
        })
        .collect()
}

/// `GET /api/trace`: the rows, the log since `since`, load, rate, the hub link and the
/// periodic transmissions.
async fn trace_get(
    State(app): State<App>,
    q: Result<Query<TraceQuery>, axum::extract::rejection::QueryRejection>,
) -> Answer {
    let q = query(q)?;
    let filter = filter_of(&q)?;
    let (mon, hub) = monitor(&app);
    let mut v = answer(
        &hub.trace.lock().unwrap(),
        &mon,
        &filter,
        q.since.unwrap_or(0),
        q.limit.unwrap_or(LOG_ANSWER),
        Instant::now(),
    );
    let o = v.as_object_mut().expect("an object");
    o.insert("link".into(), link_json(&hub.link.lock().unwrap()));
    o.insert("periodic".into(), json!(periodic_json(&hub)));
    Ok(Json(v))
}

/// `GET /api/trace/export?format=pcapng|candump`: the logged frames as a capture file.
async fn trace_export(
    State(app): State<App>,
    q: Result<Query<TraceQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Response, ApiError> {
    let q = query(q)?;
    let filter = filter_of(&q)?;
    let (format, ext, ty) = match q.format.as_deref().unwrap_or("pcapng") {
        "pcapng" => (Format::Pcapng, "pcapng", "application/x-pcapng"),
        "candump" => (Format::Candump, "log", "text/plain; charset=utf-8"),
        other => return Err(bad(format!("format `{other}`: expected pcapng or candump"))),
    };
    let (mon, hub) = monitor(&app);
    let body = export(&hub.trace.lock().unwrap(), &mon, &filter, format)
        .map_err(|e| fail(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
    Ok((
        [
            (header::CONTENT_TYPE, ty.to_string()),
            (
                header::CONTENT_DISPOSITION,
                format!("attachment; filename=\"canpos-trace.{ext}\""),
            ),
        ],
        body,
    )
        .into_response())
}

async fn trace_clear(State(app): State<App>) -> Answer {
    let hub = app.shared.lock().unwrap().trace.clone();
    hub.trace.lock().unwrap().clear();
    Ok(Json(json!({"ok": true})))
}

fn body_json(body: &str) -> Result<serde_json::Map<String, Value>, ApiError> {
    match serde_json::from_str::<Value>(body) {
        Ok(Value::Object(o)) => Ok(o),
        Ok(_) => Err(bad("bad body: expected a JSON object".into())),
        Err(e) => Err(bad(format!("bad body: {e}"))),
    }
}

/// The frame a send request describes, with the hub's checks (`< send >`): identifier within
/// 11 bits (29 when extended), DLC 0…8, as many data bytes as the DLC says, none for a remote
/// frame.
fn frame_of(o: &serde_json::Map<String, Value>) -> Result<Frame, ApiError> {
    let id = match o.get("id") {
        Some(Value::String(s)) => parse_id(s)?,
        Some(Value::Number(n)) => n
            .as_u64()
            .filter(|v| *v <= 0x1FFF_FFFF)
            .ok_or_else(|| bad(format!("identifier {n} is not 0…0x1FFFFFFF")))?
            as u32,
        _ => return Err(bad("`id` is missing: e.g. \"0x605\"".into())),
    };
    let flag = |k: &str| match o.get(k) {
        None | Some(Value::Null) => Ok(None),
        Some(Value::Bool(b)) => Ok(Some(*b)),
        Some(_) => Err(bad(format!("`{k}` must be true or false"))),
    };
    // As the hub reads an identifier: above 0x7FF it is an extended one.
    let ext = flag("ext")?.unwrap_or(id > 0x7FF);
    if !ext && id > 0x7FF {
        return Err(bad(format!(
            "identifier 0x{id:X} is above 0x7FF: a standard frame has 11 bits (set ext)"
        )));
    }
    let rtr = flag("rtr")?.unwrap_or(false);
    let data: Vec<u8> = match o.get("data") {
        None | Some(Value::Null) => Vec::new(),
        Some(Value::String(s)) => {
            let hex: String = s.chars().filter(|c| !c.is_whitespace()).collect();
            if !hex.len().is_multiple_of(2) || !hex.bytes().all(|b| b.is_ascii_hexdigit()) {
                return Err(bad(format!(
                    "data `{s}`: expected hex bytes, e.g. \"40 00 10 00\""
                )));
            }
            (0..hex.len() / 2)
                .map(|i| u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).expect("hex"))
                .collect()
        }
        Some(Value::Array(a)) => a
            .iter()
            .map(|v| v.as_u64().filter(|b| *b <= 0xFF).map(|b| b as u8))
            .collect::<Option<Vec<u8>>>()
            .ok_or_else(|| bad("data: expected bytes 0…255".into()))?,
        Some(_) => {
            return Err(bad(
                "data: expected a hex string or an array of bytes".into()
            ))
        }
    };
    let dlc = match o.get("dlc") {
        None | Some(Value::Null) => data.len(),
        Some(v) => v
            .as_u64()
            .filter(|d| *d <= 8)
            .ok_or_else(|| bad(format!("DLC {v} is not 0…8")))? as usize,
    };
    if data.len() > 8 {
        return Err(bad(format!(
            "{} data bytes: a CAN frame has 8 at most",
            data.len()
        )));
    }
    if rtr {
        if !data.is_empty() {
            return Err(bad(
                "a remote frame carries no data (give its DLC only)".into()
            ));
        }
        return Frame::remote(id, ext, dlc as u8).map_err(|e| bad(format!("{e:?}")));
    }
    if dlc != data.len() {
        return Err(bad(format!(
            "DLC {dlc} but {} data bytes: they must agree",
            data.len()
        )));
    }
    Frame::with_id(id, ext, &data).map_err(|e| bad(format!("{e:?}")))
}

/// `POST /api/send`: a frame once, or every `period_ms` for as long as its lease is renewed
/// (`lease`, one made up when the request names none) or for `duration_s` (D61).
async fn send(State(app): State<App>, body: String) -> Answer {
    let o = body_json(&body)?;
    let f = frame_of(&o)?;
    let hub = app.shared.lock().unwrap().trace.clone();
    match o.get("period_ms") {
        None | Some(Value::Null) => {
            if o.get("lease").is_some_and(|v| !v.is_null())
                || o.get("duration_s").is_some_and(|v| !v.is_null())
            {
                return Err(bad(
                    "`lease` and `duration_s` are a periodic transmission's: give period_ms".into(),
                ));
            }
            hub.send_once(f).map_err(refused_send)?;
            Ok(Json(json!({"ok": true, "id": id_text(&f), "once": true})))
        }
        Some(v) => {
            let period = period_of(v)?;
            let term = term_of(&o, &hub)?;
            let lease = match &term {
                Term::Lease(name) => Some(name.clone()),
                Term::For(_) => None,
            };
            hub.send_periodic(f, period, term, Instant::now())
                .map_err(refused_send)?;
            Ok(Json(json!({
                "ok": true, "id": id_text(&f), "lease": lease, "lease_s": LEASE.as_secs(),
                "periodic": periodic_json(&hub),
            })))
        }
    }
}

/// A lease's name: 1…[`LEASE_NAME`] letters, digits, `-`, `_`, `.`.
fn lease_name(v: &Value) -> Result<String, ApiError> {
    let s = v
        .as_str()
        .ok_or_else(|| bad(format!("lease {v}: expected a name, e.g. \"my-script\"")))?;
    if s.is_empty()
        || s.len() > LEASE_NAME
        || !s
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'-' | b'_' | b'.'))
    {
        return Err(bad(format!(
            "lease `{s}`: expected 1…{LEASE_NAME} letters, digits, `-`, `_` or `.`"
        )));
    }
    Ok(s.to_string())
}

/// How long a periodic transmission runs: `duration_s` (0 < s ≤ [`MAX_DURATION`]), else the
/// lease `lease`, else a new lease.
fn term_of(o: &serde_json::Map<String, Value>, hub: &TraceHub) -> Result<Term, ApiError> {
    let lease = o.get("lease").filter(|v| !v.is_null());
    match o.get("duration_s").filter(|v| !v.is_null()) {
        Some(_) if lease.is_some() => Err(bad(
            "give `lease` or `duration_s`, not both: a leased transmission ends when its lease is not renewed".into(),
        )),
        Some(v) => {
            let s = v
                .as_f64()
                .filter(|s| s.is_finite())
                .ok_or_else(|| bad(format!("duration_s {v}: expected a number of seconds")))?;
            // Checked as a number first: `Duration::from_secs_f64` panics beyond u64 seconds.
            if !(s > 0.0 && s <= MAX_DURATION.as_secs_f64()) {
                return Err(bad(format!(
                    "duration {s} s: expected more than 0 and at most {} s (24 h)",
                    MAX_DURATION.as_secs()
                )));
            }
            Ok(Term::For(Duration::from_secs_f64(s)))
        }
        None => Ok(Term::Lease(match lease {
            Some(v) => lease_name(v)?,
            None => hub.new_lease(),
        })),
    }
}

/// `POST /api/send/renew {"lease": "…"}`: keeps the lease's periodic transmissions going for
/// [`LEASE`] more; `renewed` says how many it holds (0: they ended).
async fn send_renew(State(app): State<App>, body: String) -> Answer {
    let o = body_json(&body)?;
    let name = lease_name(o.get("lease").unwrap_or(&Value::Null))?;
    let hub = app.shared.lock().unwrap().trace.clone();
    let n = hub.renew(&name, Instant::now());
    Ok(Json(
        json!({"ok": true, "lease": name, "renewed": n, "lease_s": LEASE.as_secs()}),
    ))
}

/// The answer to a frame the transmitter did not take.
fn refused_send(r: SendRefused) -> ApiError {
    match r {
        SendRefused::Busy => fail(
            StatusCode::SERVICE_UNAVAILABLE,
            format!("{ONCE_QUEUE} frames wait to be sent already; nothing was queued, try again"),
        ),
        SendRefused::TooMany => fail(
            StatusCode::CONFLICT,
            format!("{PERIODIC} periodic transmissions run already: stop one first"),
        ),
        SendRefused::Down => fail(
            StatusCode::SERVICE_UNAVAILABLE,
            "the bus connection is lost; the dashboard is reconnecting: nothing was queued".into(),
        ),
    }
}

/// A periodic transmission's `period_ms`, within [`MIN_PERIOD`] … [`MAX_PERIOD`].
fn period_of(v: &Value) -> Result<Duration, ApiError> {
    let ms = v
        .as_f64()
        .filter(|m| m.is_finite())
        .ok_or_else(|| bad(format!("period_ms {v}: expected a number of milliseconds")))?;
    // Checked as a number first: `Duration::from_secs_f64` panics beyond u64 seconds (1e300).
    let (lo, hi) = (
        MIN_PERIOD.as_secs_f64() * 1e3,
        MAX_PERIOD.as_secs_f64() * 1e3,
    );
    if !(lo..=hi).contains(&ms) {
        return Err(bad(format!(
            "period {ms} ms: expected {} ms … {} s",
            MIN_PERIOD.as_millis(),
            MAX_PERIOD.as_secs()
        )));
    }
    Ok(Duration::from_secs_f64(ms / 1e3))
}

async fn send_list(State(app): State<App>) -> Answer {
    let hub = app.shared.lock().unwrap().trace.clone();
    Ok(Json(json!({"ok": true, "periodic": periodic_json(&hub)})))
}

/// `POST /api/send/stop {"id": …, "ext": …}`: ends a periodic transmission;
/// `{"lease": …}` ends all of a lease's (a page that closes).
async fn send_stop(State(app): State<App>, body: String) -> Answer {
    let o = body_json(&body)?;
    if let Some(v) = o.get("lease").filter(|v| !v.is_null()) {
        let name = lease_name(v)?;
        let hub = app.shared.lock().unwrap().trace.clone();
        let n = hub.stop_lease(&name);
        return Ok(Json(
            json!({"ok": true, "stopped": n, "periodic": periodic_json(&hub)}),
        ));
    }
    let id = match o.get("id") {
        Some(Value::String(s)) => parse_id(s)?,
        _ => return Err(bad("`id` is missing: e.g. \"0x605\"".into())),
    };
    let ext = o.get("ext").and_then(Value::as_bool).unwrap_or(id > 0x7FF);
    let hub = app.shared.lock().unwrap().trace.clone();
    if !hub.stop_periodic(ext, id) {
        return Err(fail(
            StatusCode::NOT_FOUND,
            format!("no periodic transmission of 0x{id:X}"),
        ));
    }
    Ok(Json(json!({"ok": true, "periodic": periodic_json(&hub)})))
}

/// NMT command specifiers by the names `canpos nmt` takes.
fn nmt_cs(name: &str) -> Option<u8> {
    Some(match name {
        "start" => 0x01,
        "stop" => 0x02,
        "preop" | "pre-operational" => 0x80,
        "reset" | "reset-node" => 0x81,
        "reset-comm" | "reset-communication" => 0x82,
        _ => return None,
    })
}

/// `POST /api/nmt {"command": "start", "node": 0}`: an NMT command to one node or (0) all.
async fn nmt(State(app): State<App>, body: String) -> Answer {
    let o = body_json(&body)?;
    let name = o.get("command").and_then(Value::as_str).unwrap_or("");
    let cs = nmt_cs(name).ok_or_else(|| {
        bad(format!(
            "NMT command `{name}`: expected start, stop, preop, reset or reset-comm"
        ))
    })?;
    let node = match o.get("node") {
        None | Some(Value::Null) => 0,
        Some(v) => v
            .as_u64()
            .filter(|n| *n <= 127)
            .ok_or_else(|| bad(format!("node {v}: expected 0 (all) or 1…127")))?
            as u8,
    };
    let hub = app.shared.lock().unwrap().trace.clone();
    let f = Frame::new(0x000, &[cs, node]).expect("two bytes");
    hub.send_once(f).map_err(refused_send)?;
    Ok(Json(json!({"ok": true, "command": name, "node": node})))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_period_out_of_range_is_refused_whatever_its_size() {
        assert_eq!(period_of(&json!(1)).ok(), Some(MIN_PERIOD));
        assert_eq!(period_of(&json!(3_600_000)).ok(), Some(MAX_PERIOD));
        // Beyond what a Duration holds: refused as out of range, not a panic of the handler.
        for v in [
            json!(0.5),
            json!(-1),
            json!(3_600_001),
            json!(1e20),
            json!(1e300),
            json!(f64::MAX),
        ] {
            let e = period_of(&v).unwrap_err();
            assert_eq!(e.0, StatusCode::BAD_REQUEST, "{v}");
            assert!(e.1.contains("expected 1 ms"), "{v}: {}", e.1);
        }
        assert!(period_of(&json!("5")).is_err());
    }

    fn obj(v: Value) -> serde_json::Map<String, Value> {
        v.as_object().unwrap().clone()
    }

    #[test]
    fn a_periodic_transmission_has_a_lease_or_a_duration_within_bounds() {
        let hub = TraceHub::new(1000);
        // Named, made up, or a duration.
        assert_eq!(
            term_of(&obj(json!({"lease": "my-script.1"})), &hub).ok(),
            Some(Term::Lease("my-script.1".into()))
        );
        assert!(
            matches!(term_of(&obj(json!({})), &hub), Ok(Term::Lease(n)) if n.starts_with("lease-"))
        );
        assert_eq!(
            term_of(&obj(json!({"duration_s": 2.5})), &hub).ok(),
            Some(Term::For(Duration::from_millis(2500)))
        );
        assert_eq!(
            term_of(&obj(json!({"duration_s": 86_400})), &hub).ok(),
            Some(Term::For(MAX_DURATION))
        );
        // Refused: both, a name that is no name, a duration out of range (no panic beyond
        // what a Duration holds).
        for bad in [
            json!({"lease": "a", "duration_s": 1}),
            json!({"lease": ""}),
            json!({"lease": "a b"}),
            json!({"lease": "x".repeat(65)}),
            json!({"lease": 7}),
            json!({"duration_s": 0}),
            json!({"duration_s": -1}),
            json!({"duration_s": 86_400.5}),
            json!({"duration_s": 1e300}),
            json!({"duration_s": "5"}),
        ] {
            let e = term_of(&obj(bad.clone()), &hub).unwrap_err();
            assert_eq!(e.0, StatusCode::BAD_REQUEST, "{bad}");
        }
    }
}
