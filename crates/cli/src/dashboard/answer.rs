//! The API's error answer: a status and a reason, as JSON (`{"ok": false, "error": …}`), which
//! the page shows. Below the routes and the request guard that both answer with it.

use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde_json::json;

/// An error answer: the status says what kind, the body why (the page shows `error`).
pub(super) struct ApiError(pub(super) StatusCode, pub(super) String);

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        (self.0, Json(json!({"ok": false, "error": self.1}))).into_response()
    }
}

/// An [`ApiError`] of `code` saying `why`.
pub(super) fn fail(code: StatusCode, why: String) -> ApiError {
    ApiError(code, why)
}
