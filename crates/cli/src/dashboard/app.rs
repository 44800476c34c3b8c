//! The dashboard's web state and the helpers every group of endpoints shares (the node and
//! object of a path, waiting for a bus command). Below the endpoint modules, so that they and
//! the router (`dashboard.rs`) depend on it and not on each other.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use canpos_stack::od::DataType;
use canpos_stack::Table;
use serde_json::Value;

use super::answer::{fail, ApiError};
use super::values::Values;
use super::watch::{self, BusQueue, Outcome, Pending, Refused, Shared};
use crate::client::sdo::ValueType;

/// The web server's state, shared by every handler.
#[derive(Clone)]
pub(super) struct App {
    pub(super) shared: Arc<Mutex<Shared>>,
    pub(super) cmds: Arc<BusQueue>,
    /// The values the object browser's reads brought in ([`super::od`]).
    pub(super) od: Arc<Values>,
}

pub(super) async fn asset(ty: &'static str, body: &'static str) -> Response {
    ([(header::CONTENT_TYPE, ty)], body).into_response()
}

pub(super) type Answer = Result<Json<Value>, ApiError>;

/// A node-id from the path; it must be one the dashboard knows.
pub(super) fn known_node(app: &App, s: &str) -> Result<u8, ApiError> {
    let id = crate::common::parse_node(s, 1)
        .map_err(|e| fail(StatusCode::BAD_REQUEST, e.to_string()))?;
    if !app.shared.lock().unwrap().nodes.contains_key(&id) {
        return Err(fail(
            StatusCode::NOT_FOUND,
            format!("unknown node {id}: no such node on the bus"),
        ));
    }
    Ok(id)
}

pub(super) fn type_name(t: DataType) -> &'static str {
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

pub(super) fn value_type(t: DataType) -> ValueType {
    match t {
        DataType::Boolean | DataType::Unsigned8 => ValueType::U8,
        DataType::Integer8 => ValueType::I8,
        DataType::Integer16 => ValueType::I16,
        DataType::Integer32 => ValueType::I32,
        DataType::Unsigned16 => ValueType::U16,
        DataType::Unsigned32 => ValueType::U32,
        DataType::VisibleString => ValueType::Str,
        DataType::Domain => ValueType::Bytes,
    }
}

/// The object table of node `id`'s model: that of the model's widest unit (the two-channel
/// TMI's), as the dashboard does not know the unit's configuration; an object a unit does not
/// have is answered by the unit itself (SDO abort 0x06020000 / 0x06090011).
pub(super) fn model_of(app: &App, id: u8) -> Result<&'static Table, ApiError> {
    let model = app.shared.lock().unwrap().nodes[&id].model;
    model.ok_or_else(|| {
        fail(
            StatusCode::CONFLICT,
            format!("node {id}: its model is not known (not a TH, E-Series or TMI; name its EDS with --eds {id}=FILE), so there is no object table"),
        )
    })
}

/// How long a request waits for its command to start on the bus: with [`watch::QUEUE`]
/// commands ahead, each ended by its [`watch::SDO_TIMEOUT`] at worst (8 × 1 s), it starts
/// within.
const BUS_PATIENCE: Duration = Duration::from_secs(12);
/// How long a request waits for a command that has started to end. An expedited transfer
/// ends within its SDO timeout; only a long segmented one with a node that answers each
/// segment late takes longer, and it is then reported as unfinished, its effect unknown.
const BUS_RUN_LIMIT: Duration = Duration::from_secs(30);

/// The answer to a command the queue did not take.
pub(super) fn refused(app: &App, r: Refused) -> ApiError {
    match r {
        Refused::Busy => fail(
            StatusCode::SERVICE_UNAVAILABLE,
            format!(
                "the bus is busy: {} requests already wait for it; nothing was sent, try again",
                watch::QUEUE
            ),
        ),
        Refused::Gone => gone(app),
    }
}

pub(super) fn gone(app: &App) -> ApiError {
    let why = app.shared.lock().unwrap().bus_error.clone();
    fail(
        StatusCode::SERVICE_UNAVAILABLE,
        match why {
            Some(why) => format!("the bus connection is gone: {why}"),
            None => "the bus connection is gone".into(),
        },
    )
}

/// Waits for a queued command of node `id`: its result, or an error that says what happened.
pub(super) async fn bus_result<T>(
    app: &App,
    id: u8,
    p: Pending<Result<T, String>>,
) -> Result<T, ApiError> {
    match p.outcome(BUS_PATIENCE, BUS_RUN_LIMIT).await {
        Outcome::Done(Ok(v)) => Ok(v),
        Outcome::Done(Err(why)) => Err(fail(StatusCode::BAD_GATEWAY, format!("node {id}: {why}"))),
        Outcome::TimedOut { ahead } => Err(fail(
            StatusCode::SERVICE_UNAVAILABLE,
            format!(
                "timed out waiting for the bus: {ahead} requests ahead after {} s; nothing was sent",
                BUS_PATIENCE.as_secs()
            ),
        )),
        Outcome::Unfinished => Err(fail(
            StatusCode::GATEWAY_TIMEOUT,
            format!(
                "node {id}: the transfer started but has not ended after {} s; whether it took effect is unknown",
                BUS_RUN_LIMIT.as_secs()
            ),
        )),
        Outcome::Gone => Err(gone(app)),
    }
}
