//! The web dashboard (`canpos dashboard`, `--web ADDR` on `run`, `scenario` and the demo; see
//! docs/DASHBOARD.md): the nodes of a bus with their NMT state, live position and velocity
//! plots, cams, work areas, alarms, the EMCY log, the sensors' control interfaces and an SDO
//! object browser.
//!
//! HTTP with axum; the live data goes out as server-sent events, five a second, each carrying
//! only the plot points the stream has not sent yet (points are decimated on the server to one
//! per [`watch::SAMPLE_PERIOD`] and channel, so a 1 kHz TPDO rate costs the browser 50 points a
//! second). The page and uPlot are compiled into the binary: nothing is fetched at run time.
//!
//! Only the page's own origin changes state ([`guard`]); the web side keeps to a share of the
//! process's descriptors and times out what clients leave unfinished ([`serve`]).

mod answer;
mod app;
pub mod guard;
mod od;
mod page;
pub mod serve;
pub mod trace;
mod trace_api;
mod values;
pub mod watch;

use std::convert::Infallible;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use answer::{fail, ApiError};
use anyhow::{Context, Result};
use app::{asset, bus_result, known_node, model_of, refused, type_name, value_type, Answer, App};
use axum::extract::{Path, State};
use axum::http::{header, Method, StatusCode, Uri};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use canpos_host::control;
use canpos_host::crossbeam_channel::Sender;
use canpos_host::Transport;
use canpos_stack::od::Access;
use canpos_stack::Table;
use page::{render_page, APP_JS, STYLE, UPLOT_CSS, UPLOT_JS, UPLOT_LICENSE};
use serde_json::{json, Value};
use watch::{BusCmd, Controller, Link, Shared};

use crate::client::decode;
use crate::client::sdo::{format_auto, hex_string};

/// Default address of `canpos dashboard`.
pub const DEFAULT_LISTEN: &str = "127.0.0.1:29080";

/// A running dashboard. Dropping it stops the server and its threads.
pub struct Dashboard {
    addr: SocketAddr,
    stop_tx: Vec<Sender<()>>,
    shutdown: Option<tokio::sync::oneshot::Sender<()>>,
    shared: Arc<Mutex<Shared>>,
    connections: Arc<AtomicUsize>,
}

impl Dashboard {
    /// The address the page is served on.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// The page's URL.
    pub fn url(&self) -> String {
        format!("http://{}/", self.addr)
    }

    /// Gives node `id` the object table of `model` (e.g. one built from an EDS file).
    pub fn pin_model(&self, id: u8, model: &'static Table) {
        self.shared.lock().unwrap().pin_model(id, model);
    }

    /// Open event streams (for tests: a browser that left holds none).
    pub fn streams(&self) -> usize {
        self.shared.lock().unwrap().streams
    }

    /// Open web connections.
    pub fn connections(&self) -> usize {
        self.connections.load(Ordering::SeqCst)
    }

    /// Names the bus in the page's header (the bus URL rather than what the connection calls
    /// itself, e.g. `in-process bus port 3`).
    pub fn set_bus_label(&self, label: &str) {
        self.shared.lock().unwrap().bus = label.to_string();
    }

    /// Figures the bus load at `kbps` kbit/s, as the user said (`canpos dashboard --bitrate`):
    /// it wins over what the bus or a sensor tells (D60).
    pub fn set_bitrate(&self, kbps: u32) {
        let hub = self.shared.lock().unwrap().trace.clone();
        hub.trace
            .lock()
            .unwrap()
            .offer_bitrate(kbps, trace::BitrateFrom::Given);
    }

    /// When the bus connection is lost, reconnect with `reopen` (and say so on the page)
    /// instead of ending: a standalone dashboard outlives a hub that restarts.
    pub fn reconnect_with(&self, reopen: trace::Reopen) {
        self.shared.lock().unwrap().trace.reopen_with(reopen);
    }
}

impl Drop for Dashboard {
    fn drop(&mut self) {
        for s in &self.stop_tx {
            let _ = s.send(());
        }
        if let Some(s) = self.shutdown.take() {
            let _ = s.send(());
        }
    }
}

/// Where the sensors' control interfaces are.
pub enum Controls {
    /// The runtime of this process and its number of sensors.
    Local(canpos_host::ControlHandle, usize),
    /// Control addresses over TCP.
    Remote(Vec<String>),
}

/// Starts a dashboard on `listen` for the bus seen through `bus` (a connection of its own).
pub fn start(
    bus: Box<dyn Transport>,
    listen: &str,
    controls: Controls,
    window_s: f64,
) -> Result<Dashboard> {
    let listener = std::net::TcpListener::bind(listen)
        .with_context(|| format!("cannot serve the dashboard on {listen}"))?;
    start_on(bus, listener, controls, window_s)
}

/// [`start`] on a listener already bound.
pub fn start_on(
    bus: Box<dyn Transport>,
    listener: std::net::TcpListener,
    controls: Controls,
    window_s: f64,
) -> Result<Dashboard> {
    listener.set_nonblocking(true)?;
    let addr = listener.local_addr()?;
    canpos_host::warn_if_exposed(addr, "the dashboard");
    let controllers = match controls {
        Controls::Local(h, n) => (0..n)
            .map(|i| Controller {
                link: Link::Local(h.clone()),
                sensor: i,
                state: None,
            })
            .collect(),
        Controls::Remote(addrs) => addrs.iter().flat_map(|a| watch::probe(a)).collect(),
    };
    let shared = Arc::new(Mutex::new(Shared::new(
        bus.describe(),
        window_s,
        controllers,
    )));
    // Every frame in and out goes through the trace (issue 38).
    let hub = shared.lock().unwrap().trace.clone();
    // The bus's own bit rate where the connection knows it (an in-process bus's pacing, else
    // the rate declared to it); a socketcand hub names none (D60).
    if let Some(kbps) = bus
        .bus_stats()
        .map(|s| s.bitrate_kbps)
        .or_else(|| bus.bus_bitrate())
    {
        hub.trace
            .lock()
            .unwrap()
            .offer_bitrate(kbps, trace::BitrateFrom::Bus);
    }
    let bus: Box<dyn Transport> = Box::new(trace::Tap::new(bus, hub, watch::scan));
    let (cmd_tx, cmd_rx) = watch::bus_queue(watch::QUEUE);
    let (stop_bus, stop_bus_rx) = canpos_host::crossbeam_channel::bounded(1);
    let (stop_poll, stop_poll_rx) = canpos_host::crossbeam_channel::bounded(1);
    {
        let s = shared.clone();
        std::thread::Builder::new()
            .name("canpos-web-bus".into())
            .spawn(move || watch::run_bus(bus, s, cmd_rx, stop_bus_rx))?;
        let s = shared.clone();
        std::thread::Builder::new()
            .name("canpos-web-ctl".into())
            .spawn(move || watch::run_poller(s, stop_poll_rx))?;
    }
    let app = App {
        shared: shared.clone(),
        cmds: Arc::new(cmd_tx),
        od: Arc::default(),
    };
    let router = router(app);
    let cap = serve::connection_cap();
    let connections = Arc::new(AtomicUsize::new(0));
    let (shutdown, shutdown_rx) = tokio::sync::oneshot::channel::<()>();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("canpos-web")
        .enable_all()
        .build()?;
    std::thread::Builder::new()
        .name("canpos-web".into())
        .spawn({
            let connections = connections.clone();
            move || {
                rt.block_on(async move {
                    let l = match tokio::net::TcpListener::from_std(listener) {
                        Ok(l) => l,
                        Err(e) => return tracing::error!("dashboard: {e}"),
                    };
                    serve::run(l, router, cap, connections, shutdown_rx).await;
                });
                // Open connections (event streams) end with the runtime.
                rt.shutdown_timeout(Duration::from_millis(100));
            }
        })?;
    Ok(Dashboard {
        addr,
        stop_tx: vec![stop_bus, stop_poll],
        shutdown: Some(shutdown),
        shared,
        connections,
    })
}

/// Starts the dashboard of `--web ADDR` for a runtime of this process (a second connection to
/// its bus) and prints its URL.
pub fn start_for_runtime(
    web: &str,
    bus: Box<dyn Transport>,
    handle: &canpos_host::RuntimeHandle,
    sensors: usize,
) -> Result<Dashboard> {
    let d = start(bus, web, Controls::Local(handle.control(), sensors), 30.0)?;
    eprintln!("canpos: dashboard on {}", d.url());
    Ok(d)
}

fn router(app: App) -> Router {
    Router::new()
        .route("/", get(page))
        .route("/app.js", get(|| asset("text/javascript", APP_JS)))
        .route("/style.css", get(|| asset("text/css", STYLE)))
        .route(
            "/uplot/uPlot.iife.min.js",
            get(|| asset("text/javascript", UPLOT_JS)),
        )
        .route("/uplot/uPlot.min.css", get(|| asset("text/css", UPLOT_CSS)))
        .route(
            "/uplot/LICENSE",
            get(|| asset("text/plain; charset=utf-8", UPLOT_LICENSE)),
        )
        .route("/api/status", get(status))
        .route("/api/snapshot", get(snapshot_get))
        .route("/api/events", get(events))
        .route("/api/scan", post(scan))
        .route("/api/nodes/{node}/od", get(od))
        .route(
            "/api/nodes/{node}/sdo/{index}/{sub}",
            get(sdo_read).put(sdo_write),
        )
        .route("/api/nodes/{node}/control", post(node_control))
        .merge(od::routes())
        .merge(trace_api::routes())
        // axum answers a known path's other methods 405 with an empty body; the API's errors
        // are JSON (axum still adds `Allow`).
        .method_not_allowed_fallback(|method: Method, uri: Uri| async move {
            fail(
                StatusCode::METHOD_NOT_ALLOWED,
                format!(
                    "{method} is not allowed on {} (the Allow header lists what is)",
                    uri.path()
                ),
            )
        })
        .fallback(|| async { fail(StatusCode::NOT_FOUND, "no such page or API".into()) })
        .layer(axum::middleware::from_fn(guard::guard))
        .with_state(app)
}

/// The page with the bus as it is now: the node table filled in and the whole snapshot
/// embedded for the script. A client that runs no script (curl, a text browser) or takes its
/// screenshot at the load event (headless Chromium's `--screenshot`) sees the nodes without a
/// second request; the script then polls [`snapshot_get`] for what is new.
async fn page(State(app): State<App>) -> Response {
    let snap = snapshot(&app.shared.lock().unwrap(), 0);
    (
        [
            (header::CONTENT_TYPE, "text/html; charset=utf-8"),
            // The page is a snapshot: a reload must fetch a new one.
            (header::CACHE_CONTROL, "no-store"),
        ],
        render_page(&snap),
    )
        .into_response()
}

async fn status(State(app): State<App>) -> Json<Value> {
    let s = app.shared.lock().unwrap();
    Json(json!({
        "ok": true,
        "bus": s.bus,
        "frames": s.frames,
        "frames_per_s": s.frames_per_s,
        "nodes": s.nodes.keys().collect::<Vec<_>>(),
        "streams": s.streams,
        "bus_error": s.bus_error,
    }))
}

/// `GET /api/snapshot?since=SEQ`: the page's view of the bus as one plain JSON answer, with the
/// plot points newer than `SEQ` (all of them without it) and `seq` to ask from next time. The
/// page polls it; a client that cannot hold a stream open gets everything from it.
/// A query that is no sequence number is refused in JSON, as every API error is.
async fn snapshot_get(
    State(app): State<App>,
    q: Result<axum::extract::Query<SnapshotQuery>, axum::extract::rejection::QueryRejection>,
) -> Answer {
    let axum::extract::Query(q) = q.map_err(|e| {
        fail(
            StatusCode::BAD_REQUEST,
            format!(
                "{}; expected ?since=N, N the `seq` of the last answer (0…18446744073709551615)",
                e.body_text()
            ),
        )
    })?;
    Ok(Json(snapshot(
        &app.shared.lock().unwrap(),
        q.since.unwrap_or(0),
    )))
}

/// The query of [`snapshot_get`].
#[derive(serde::Deserialize)]
struct SnapshotQuery {
    since: Option<u64>,
}

async fn scan(State(app): State<App>) -> Answer {
    app.cmds.scan().map_err(|r| refused(&app, r))?;
    Ok(Json(json!({"ok": true})))
}

/// Counts an open event stream for as long as it lives.
struct StreamGuard(Arc<Mutex<Shared>>);

impl Drop for StreamGuard {
    fn drop(&mut self) {
        self.0.lock().unwrap().streams -= 1;
    }
}

async fn events(State(app): State<App>) -> impl IntoResponse {
    app.shared.lock().unwrap().streams += 1;
    let guard = StreamGuard(app.shared.clone());
    let mut tick = tokio::time::interval(Duration::from_millis(200));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let stream =
        futures_util::stream::unfold((guard, tick, 0u64), |(g, mut tick, sent)| async move {
            tick.tick().await;
            let (text, sent) = {
                let s = g.0.lock().unwrap();
                let snap = snapshot(&s, sent);
                (snap.to_string(), s.seq - 1)
            };
            Some((
                Ok::<_, Infallible>(Event::default().data(text)),
                (g, tick, sent),
            ))
        });
    Sse::new(stream).keep_alive(KeepAlive::default())
}

/// Labels of a cam-state byte (0x6300/n): bit k = cam k+1 (OD.md G28), active = the position
/// is between the cam's low and high limit.
fn cam_labels(v: u8) -> Vec<String> {
    (0..8)
        .filter(|b| v & (1 << b) != 0)
        .map(|b| format!("cam {} active", b + 1))
        .collect()
}

/// Labels of a work-area state byte (0x6400/n), as the TMI manual (002 §1.11.2) names the
/// bits; TH / E-Series use the same register (CiA 406).
fn area_labels(v: u8) -> Vec<&'static str> {
    let mut out = Vec::new();
    if v & 1 != 0 {
        out.push("out of range (position ≤ preset or ≥ sensor length)");
    }
    if v & 2 != 0 {
        out.push("above work area high limit");
    }
    if v & 4 != 0 {
        out.push("below work area low limit");
    }
    out
}

/// Labels of the alarm register (0x6503): bit 0 is "Missing magnet" (000 Table 17).
fn alarm_labels(v: u16) -> Vec<String> {
    (0..16)
        .filter(|b| v & (1 << b) != 0)
        .map(|b| match b {
            0 => "missing magnet (position error)".to_string(),
            b => format!("alarm bit {b}"),
        })
        .collect()
}

/// What an EMCY code means on this model: the manuals' tables, and for the TMI's transducer
/// errors the sub-codes of its system-data errors (002 §1.14).
fn emcy_text(model: Option<&Table>, e: &watch::Emcy) -> String {
    let tmi = model.is_some_and(|m| m.name == "tmi");
    let base = match (e.code, tmi) {
        (0x9080 | 0x9090, false) => "external error",
        (c, _) => decode::emcy_meaning(c),
    };
    if tmi && e.code == 0x5000 {
        let sub = match (e.msef[0], e.msef[1], e.msef[2]) {
            (1, 2, 0) => Some("wrong mapping"),
            (1, 3, 1) => Some("wrong vendor-id"),
            (1, 3, 2) => Some("wrong scale"),
            (1, 4, 0) => Some("wrong resolution"),
            (1, 5, 0) => Some("system data instead of process data"),
            (1, 6, 0) => Some("no system data"),
            (2, 1, 0) => Some("invalid serial number"),
            _ => None,
        };
        if let Some(s) = sub {
            return format!("{base}: {s}");
        }
    }
    base.to_string()
}

/// The page's view of the bus; plot points newer than sequence number `sent` only.
fn snapshot(s: &Shared, sent: u64) -> Value {
    let nodes: Vec<Value> = s
        .nodes
        .iter()
        .map(|(id, n)| {
            let ctl = s.controller_of(*id);
            let st = ctl.and_then(|c| c.state.as_ref());
            let alarms = n
                .alarms
                .or_else(|| st.and_then(|st| st["alarms"].as_u64()).map(|a| a as u16));
            let error_register = st
                .and_then(|st| st["error_register"].as_u64())
                .map(|r| r as u8)
                .or(n.error_register);
            let nmt = st
                .and_then(|st| st["nmt"].as_str().map(str::to_string))
                .or_else(|| watch::nmt_of(s, *id, n))
                .unwrap_or_else(|| watch::nmt_name(n.nmt).to_string());
            let channels: Vec<Value> = n
                .channels
                .iter()
                .enumerate()
                .map(|(i, c)| {
                    let new: Vec<_> = c.samples.iter().filter(|p| p.seq > sent).collect();
                    // The control state fills in what the TPDO does not carry (TH maps
                    // cams, E-Series the work area).
                    let cam = c.cam.or_else(|| {
                        st.and_then(|st| st["cam_state"][i].as_u64())
                            .map(|v| v as u8)
                    });
                    let area = c.area.or_else(|| {
                        st.and_then(|st| st["work_area"][i].as_u64())
                            .map(|v| v as u8)
                    });
                    json!({
                        "pos": c.pos, "vel": c.vel,
                        "t": new.iter().map(|p| p.t).collect::<Vec<_>>(),
                        "p": new.iter().map(|p| nan_null(p.pos)).collect::<Vec<_>>(),
                        "v": new.iter().map(|p| nan_null(p.vel)).collect::<Vec<_>>(),
                        "cam": cam, "cam_labels": cam.map(cam_labels).unwrap_or_default(),
                        "area": area, "area_labels": area.map(area_labels).unwrap_or_default(),
                    })
                })
                .collect();
            let emcy: Vec<Value> = n
                .emcy
                .iter()
                .rev()
                .take(30)
                .map(|e| {
                    json!({
                        "t": e.t,
                        "code": format!("0x{:04X}", e.code),
                        "register": format!("0x{:02X}", e.register),
                        "register_text": decode::error_register(e.register),
                        "msef": hex_string(&e.msef),
                        "meaning": emcy_text(n.model, e),
                    })
                })
                .collect();
            // The table's positions: the TPDO's, else what the control interface reports (a
            // pre-operational sensor sends no TPDO).
            let tpdo: Vec<Option<f64>> = n.channels.iter().map(|c| c.pos).collect();
            let (positions, from) = if tpdo.iter().any(Option::is_some) {
                (tpdo, Some("TPDO"))
            } else {
                match st.and_then(|st| st["reported_mm"].as_array()) {
                    Some(r) if !r.is_empty() => {
                        (r.iter().map(Value::as_f64).collect(), Some("control"))
                    }
                    _ => (Vec::new(), None),
                }
            };
            json!({
                "node": id,
                "positions": positions,
                "positions_from": from,
                "model": n.model.map(|m| m.name),
                "product": n.model.map(|m| m.product),
                "name": n.name,
                "vendor": n.identity[0],
                "serial": n.identity[3],
                "nmt": nmt,
                "error_register": error_register,
                "error_register_text": error_register.map(decode::error_register),
                "alarms": alarms,
                "alarm_labels": alarms.map(alarm_labels).unwrap_or_default(),
                "emcy": emcy,
                "channels": channels,
                // The figures' resolution, from the node's measuring steps (0x6005).
                "resolution": od::resolution(n.info.as_ref()),
                "control": st.map(|st| json!({
                    "sensor": ctl.map(|c| c.sensor),
                    "name": st["name"],
                    "powered": st["powered"],
                    "faults": st["faults"],
                    "true_mm": st["true_mm"],
                    "bus_load": bus_load(st),
                    "bus_off": st["bus_off"],
                    // The controller's error state, where the state reports one.
                    "bus_state": st.get("bus_state").or_else(|| st.get("error_state")),
                    // The simulation clock: how late the host made it (docs/CLOCK.md).
                    "clock": st.get("clock"),
                    // A device served from an EDS: no magnets or faults, its process objects
                    // (inputs the page may set, outputs as the master wrote them).
                    "device": st.get("device"),
                    "process": st.get("process"),
                })),
            })
        })
        .collect();
    // The bus's own load, where a sensor's state reports it (the physical-bus model).
    let load = s
        .controllers
        .iter()
        .filter_map(|c| c.state.as_ref())
        .find_map(bus_load);
    json!({
        // Ask for points after this one next time.
        "seq": s.seq - 1,
        "t": s.start.elapsed().as_secs_f64(),
        "window_s": s.window_s,
        "bus": s.bus,
        "frames_per_s": s.frames_per_s,
        "bus_load": load,
        "bus_error": s.bus_error,
        "nodes": nodes,
    })
}

/// A bus-load figure of a control state (`bus_load…` keys), if it has one.
fn bus_load(st: &Value) -> Option<Value> {
    st.as_object()?
        .iter()
        .find(|(k, v)| k.starts_with("bus_load") && !v.is_null())
        .map(|(k, v)| json!({"key": k, "value": v}))
}

fn nan_null(v: f64) -> Value {
    if v.is_finite() {
        json!(v)
    } else {
        Value::Null
    }
}

fn access_name(a: Access) -> &'static str {
    match a {
        Access::Ro => "ro",
        Access::Wo => "wo",
        Access::Rw => "rw",
        Access::Const => "const",
    }
}

async fn od(State(app): State<App>, Path(node): Path<String>) -> Answer {
    let id = known_node(&app, &node)?;
    let model = model_of(&app, id)?;
    let entries: Vec<Value> = model
        .entries
        .iter()
        .map(|e| {
            json!({
                "index": format!("0x{:04X}", e.index), "sub": e.sub, "name": e.name,
                "type": type_name(e.ty), "access": access_name(e.access), "pdo": e.pdo,
                "range": od::range_json(e),
            })
        })
        .collect();
    Ok(Json(
        json!({"ok": true, "node": id, "model": model.name, "product": model.product, "entries": entries}),
    ))
}

/// The node, its model's entry for `index`/`sub` (an unknown object is refused before
/// anything goes on the bus).
fn object(
    app: &App,
    node: &str,
    index: &str,
    sub: &str,
) -> Result<(u8, &'static canpos_stack::od::Entry), ApiError> {
    let id = known_node(app, node)?;
    let model = model_of(app, id)?;
    let ix = crate::common::parse_index(index)
        .map_err(|e| fail(StatusCode::BAD_REQUEST, e.to_string()))?;
    let sb =
        crate::common::parse_sub(sub).map_err(|e| fail(StatusCode::BAD_REQUEST, e.to_string()))?;
    let entry = model
        .entries
        .iter()
        .find(|e| e.index == ix && e.sub == sb)
        .ok_or_else(|| {
            fail(
                StatusCode::NOT_FOUND,
                format!(
                    "unknown object 0x{ix:04X}/{sb}: the {} has no such entry",
                    model.product
                ),
            )
        })?;
    Ok((id, entry))
}

async fn sdo_read(
    State(app): State<App>,
    Path((node, index, sub)): Path<(String, String, String)>,
) -> Answer {
    let (id, e) = object(&app, &node, &index, &sub)?;
    let p = app
        .cmds
        .submit(|job| BusCmd::Read(id, e.index, e.sub, job))
        .map_err(|r| refused(&app, r))?;
    // A refused read leaves no value to export; a timeout says nothing about the value.
    let d = bus_result(&app, id, p).await.inspect_err(|err| {
        if err.1.contains("SDO abort") {
            app.od.forget(id, e)
        }
    })?;
    app.od.remember(id, e, &d);
    let value = value_type(e.ty)
        .decode(&d)
        .unwrap_or_else(|_| format_auto(&d));
    Ok(Json(json!({
        "ok": true, "node": id, "index": format!("0x{:04X}", e.index), "sub": e.sub,
        "name": e.name, "type": type_name(e.ty), "value": value, "hex": hex_string(&d),
    })))
}

async fn sdo_write(
    State(app): State<App>,
    Path((node, index, sub)): Path<(String, String, String)>,
    body: String,
) -> Answer {
    let (id, e) = object(&app, &node, &index, &sub)?;
    let v: Value = serde_json::from_str(&body).map_err(|err| {
        fail(
            StatusCode::BAD_REQUEST,
            format!("bad body: {err}; expected {{\"value\": \"…\"}}"),
        )
    })?;
    let text = match &v["value"] {
        Value::String(s) => s.clone(),
        Value::Number(n) => n.to_string(),
        _ => {
            return Err(fail(
                StatusCode::BAD_REQUEST,
                "bad body: expected {\"value\": \"…\"}".into(),
            ))
        }
    };
    if !e.access.writable() {
        return Err(fail(
            StatusCode::CONFLICT,
            format!(
                "object 0x{:04X}/{} ({}) is {}: not writable",
                e.index,
                e.sub,
                e.name,
                access_name(e.access)
            ),
        ));
    }
    let data = value_type(e.ty).encode(&text).map_err(|why| {
        fail(
            StatusCode::BAD_REQUEST,
            format!("value for {} ({}): {why}", e.name, type_name(e.ty)),
        )
    })?;
    let p = app
        .cmds
        .submit(|job| BusCmd::Write(id, e.index, e.sub, data.clone(), job))
        .map_err(|r| refused(&app, r))?;
    bus_result(&app, id, p).await?;
    Ok(Json(
        json!({"ok": true, "node": id, "hex": hex_string(&data)}),
    ))
}

/// The commands the page may send (`state` and `reset-lateness` are the poller's;
/// `set-input` is an EDS device's).
const PAGE_COMMANDS: [&str; 7] = [
    "magnet",
    "motion",
    "fault",
    "power-cycle",
    "nmt",
    "ambient",
    "set-input",
];

async fn node_control(State(app): State<App>, Path(node): Path<String>, body: String) -> Answer {
    let id = known_node(&app, &node)?;
    let mut v: Value = serde_json::from_str(&body)
        .map_err(|e| fail(StatusCode::BAD_REQUEST, format!("bad body: {e}")))?;
    let Some(obj) = v.as_object_mut() else {
        return Err(fail(
            StatusCode::BAD_REQUEST,
            "bad body: expected a JSON object".into(),
        ));
    };
    let cmd = obj.get("cmd").and_then(Value::as_str).unwrap_or("");
    if !PAGE_COMMANDS.contains(&cmd) {
        return Err(fail(
            StatusCode::BAD_REQUEST,
            format!(
                "unknown command `{cmd}` (known: {})",
                PAGE_COMMANDS.join(", ")
            ),
        ));
    }
    if let Some(Value::String(name)) = obj.get("name") {
        if cmd == "fault" && name.parse::<control::Fault>().is_err() {
            return Err(fail(
                StatusCode::NOT_FOUND,
                format!("unknown fault `{name}` (docs/CONTROL.md lists them)"),
            ));
        }
    }
    let (link, sensor) = {
        let s = app.shared.lock().unwrap();
        let c = s.controller_of(id).ok_or_else(|| {
            fail(
                StatusCode::CONFLICT,
                format!("node {id} has no control interface known to the dashboard (start it with --control and pass that to --control here)"),
            )
        })?;
        (c.link.clone(), c.sensor)
    };
    obj.insert("sensor".into(), json!(sensor));
    let req = control::parse_request(&v.to_string()).map_err(|e| {
        fail(
            StatusCode::BAD_REQUEST,
            e["error"].as_str().unwrap_or("bad request").to_string(),
        )
    })?;
    let answer = tokio::task::spawn_blocking(move || link.request(req))
        .await
        .map_err(|e| fail(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
    if answer["ok"] == true {
        Ok(Json(answer))
    } else {
        Err(fail(
            StatusCode::BAD_REQUEST,
            format!(
                "node {id}: {}",
                answer["error"].as_str().unwrap_or("refused")
            ),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A node's name (0x1008) is the device's text: on the served page it stays text, in the
    /// table and in the embedded snapshot (a `</script>` in it does not end the script).
    #[test]
    fn the_served_page_keeps_a_devices_text_as_text() {
        let evil = "</script><script>alert(1)</script><b>&'\"";
        let snap = json!({
            "t": 1.25, "seq": 7, "bus": "mem://<x>",
            "nodes": [{
                "node": 5, "name": evil, "product": "P", "model": "th", "serial": 1,
                "nmt": "operational", "positions": [250.0, null], "positions_from": "TPDO",
                "error_register": 0, "error_register_text": "none",
            }],
        });
        let page = render_page(&snap);
        assert!(!page.contains("<script>alert"), "{page}");
        assert!(!page.contains("<b>"), "{page}");
        assert!(page.contains(r#"<td class="name">&lt;/script&gt;&lt;script&gt;alert(1)&lt;/script&gt;&lt;b&gt;&amp;&#39;&quot;</td>"#), "{page}");
        assert!(
            page.contains(r#"<td class="pos">250.000 mm · no position</td>"#),
            "{page}"
        );
        assert!(page.contains("bus mem://&lt;x&gt;"), "{page}");
        // The embedded JSON reads back as the snapshot.
        let start = page
            .find(r#"<script id="initial" type="application/json">"#)
            .unwrap();
        let body = &page[start..];
        let body = &body[body.find('>').unwrap() + 1..body.find("</script>").unwrap()];
        assert_eq!(serde_json::from_str::<Value>(body).unwrap(), snap);
        for p in [
            "<!--BUS-->",
            "<!--LINK-->",
            "<!--ROWS-->",
            "<!--SNAPSHOT-->",
        ] {
            assert!(!page.contains(p), "{p} left: {page}");
        }
    }

    #[test]
    fn labels_name_the_bits() {
        assert_eq!(cam_labels(0b101), ["cam 1 active", "cam 3 active"]);
        assert_eq!(area_labels(0), Vec::<&str>::new());
        assert_eq!(area_labels(6).len(), 2);
        assert_eq!(alarm_labels(1), ["missing magnet (position error)"]);
    }

    #[test]
    fn models_are_recognised_from_their_tables() {
        assert_eq!(
            watch::recognise(Some(0x40), Some("C304")).map(|m| m.name),
            Some("th")
        );
        assert_eq!(
            watch::recognise(Some(0x40), Some("MTS")).map(|m| m.name),
            Some("e-series")
        );
        assert_eq!(
            watch::recognise(Some(0x182), None).map(|m| m.name),
            Some("tmi")
        );
        assert!(watch::recognise(Some(0x1234), Some("C304")).is_none());
    }

    #[test]
    fn pdo_fields_sign_extend_positions() {
        // TH TPDO1: position i32, velocity i16, cam u8.
        let map = [0x6020_0120, 0x6030_0110, 0x6300_0108];
        let d = [0xFE, 0xFF, 0xFF, 0xFF, 0x10, 0x00, 0x05];
        assert_eq!(
            watch::pdo_fields(&map, &d),
            [(0x6020, 1, -2), (0x6030, 1, 16), (0x6300, 1, 5)]
        );
        // Short data stops at the uncovered mapping.
        assert_eq!(watch::pdo_fields(&map, &d[..5]).len(), 1);
    }
}
