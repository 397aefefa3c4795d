//! The HTTP API: axum routers per resource under `/api/v1`, plus
//! `/healthz`, `/metrics`, `/openapi.json` and `/docs`.
//!
//! - [`calibrations`]: create (JSON or OpenPTV files), read, export as
//!   OpenPTV files, project and intersect.
//! - [`sequences`]: create, read, upload frames, fetch particles and
//!   targets.
//! - [`jobs`]: a job's state.
//! - [`problem`]: the one error type, its statuses by the errors' types,
//!   and the extractors that use it.
//! - [`upload`]: the multipart upload path frames and solving share.
//! - [`links`]: the API's URLs.
//! - [`docs`]: the OpenAPI document and the vendored Swagger UI.
//!
//! Every request is counted for `/metrics`; a declared body larger than
//! `--max-upload-mb` is refused before it is read, and a streamed one as
//! soon as it passes the limit. With `--api-token`, `/api` needs the bearer.

pub mod calibrations;
pub mod docs;
pub mod jobs;
pub mod links;
pub mod problem;
pub mod sequences;
pub mod upload;

use std::sync::Arc;

use axum::extract::{DefaultBodyLimit, MatchedPath, Request, State};
use axum::http::{header, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;

use self::problem::ApiError;
use super::app::AppState;

/// The shared state handlers get.
pub type Shared = State<Arc<AppState>>;

/// The whole application's routes.
pub fn router(state: Arc<AppState>) -> Router {
    let api = Router::new()
        .merge(calibrations::router())
        .merge(sequences::router())
        .merge(jobs::router())
        .layer(middleware::from_fn_with_state(state.clone(), require_token));
    Router::new()
        .nest("/api/v1", api)
        .route("/healthz", get(healthz))
        .route("/metrics", get(metrics))
        .merge(docs::router())
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .layer(DefaultBodyLimit::max(state.config.max_upload_bytes()))
        .layer(middleware::from_fn_with_state(state.clone(), observe))
        .with_state(state)
}

/// Refuses a declared body over the limit before reading it, and counts
/// the request by route and status.
async fn observe(State(state): Shared, request: Request, next: Next) -> Response {
    let method = request.method().to_string();
    let route = request
        .extensions()
        .get::<MatchedPath>()
        .map_or("unmatched", |p| p.as_str())
        .to_owned();
    let declared = request
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    let limit = state.config.max_upload_bytes() as u64;
    let has_body = declared.is_some_and(|n| n > 0)
        || request.headers().contains_key(header::TRANSFER_ENCODING);
    let mut response = match declared {
        Some(length) if length > limit => ApiError::too_large(format!(
            "the body is {length} bytes, more than the service's limit of {limit} bytes \
             (--max-upload-mb); send fewer or smaller images per request"
        ))
        .into_response(),
        _ => next.run(request).await,
    };
    // A refused request's body may be partly unread: the connection cannot
    // carry another request, so say so rather than let the client reuse it.
    if has_body && (response.status().is_client_error() || response.status().is_server_error()) {
        response.headers_mut().insert(
            header::CONNECTION,
            header::HeaderValue::from_static("close"),
        );
    }
    state
        .metrics
        .request(&method, &route, response.status().as_u16());
    response
}

/// With `--api-token`, the request needs `Authorization: Bearer <token>`.
async fn require_token(State(state): Shared, request: Request, next: Next) -> Response {
    let Some(token) = state.config.api_token.as_deref() else {
        return next.run(request).await;
    };
    let given = request
        .headers()
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer "));
    if given.is_some_and(|given| constant_time_eq(given.as_bytes(), token.as_bytes())) {
        next.run(request).await
    } else {
        let mut response = ApiError::new(
            StatusCode::UNAUTHORIZED,
            "this service needs `Authorization: Bearer <token>` with its API token",
        )
        .into_response();
        response.headers_mut().insert(
            header::WWW_AUTHENTICATE,
            header::HeaderValue::from_static("Bearer"),
        );
        response
    }
}

/// Compares without stopping at the first difference.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// Liveness: the process answers `ok`.
#[utoipa::path(get, path = "/healthz", tag = "operations", security(()),
    responses((status = 200, content_type = "text/plain", body = String)))]
pub async fn healthz() -> &'static str {
    "ok\n"
}

/// Counters in Prometheus' text format: requests by route and status,
/// queue depth, jobs by kind and state, job durations, particles per frame.
#[utoipa::path(get, path = "/metrics", tag = "operations", security(()),
    responses((status = 200, content_type = "text/plain", body = String)))]
pub async fn metrics(State(state): Shared) -> Result<Response, ApiError> {
    let jobs = state.store.job_counts().await?;
    Ok((
        [(header::CONTENT_TYPE, "text/plain; version=0.0.4")],
        state.metrics.render(&jobs),
    )
        .into_response())
}

async fn not_found() -> ApiError {
    ApiError::not_found("no such route; the API is under /api/v1, its description at /docs")
}

async fn method_not_allowed() -> ApiError {
    ApiError::new(
        StatusCode::METHOD_NOT_ALLOWED,
        "this route does not take this method; see /docs",
    )
}
