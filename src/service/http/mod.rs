//! The HTTP API: axum routers per resource under `/api/v1`, plus
//! `/healthz`, `/metrics`, `/openapi.json`, `/docs` and the web page at
//! `/` ([`web`]).
//!
//! - [`calibrations`]: create (JSON or OpenPTV files), read, export as
//!   OpenPTV files, project and intersect.
//! - [`sequences`]: create, read, upload frames, fetch particles and
//!   targets.
//! - [`events`]: a sequence's live progress as server-sent events.
//! - [`selfcal`]: a sequence's calibration self-calibrated from its
//!   targets, its frames reprocessed with another calibration, a
//!   calibration's report.
//! - [`tracking`]: a sequence's tracking runs, a new run, the finish
//!   request, its trajectories (CSV or JSON, streamed) and one trajectory.
//! - [`plots`]: pictures (PNG or SVG) of a calibration's residuals and
//!   disparity maps, a frame's image with targets and reprojections, a
//!   frame's particles and a sequence's trajectories.
//! - [`jobs`]: a job's state.
//! - [`problem`]: the one error type, its statuses by the errors' types,
//!   and the extractors that use it.
//! - [`upload`]: the multipart upload path frames and solving share.
//! - [`links`]: the API's URLs.
//! - [`web`]: the lab web page and its assets, compiled in.
//! - [`docs`]: the OpenAPI document and the vendored Swagger UI.
//! - [`layers`]: the tower and tower-http layers every request passes
//!   through (request ids, tracing, compression, timeouts, body limits,
//!   the panic guard, load shedding, the bearer token) and the request
//!   counts for `/metrics`.

pub mod calibrations;
pub mod decimal;
pub mod docs;
pub mod events;
pub mod experiments;
pub mod jobs;
pub mod layers;
pub mod links;
pub mod plots;
pub mod problem;
pub mod selfcal;
pub mod sequence_images;
pub mod sequences;
pub mod tracking;
pub mod upload;
pub mod web;

use std::sync::Arc;

use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use serde::Deserialize;
use utoipa::IntoParams;

use self::problem::ApiError;
use super::app::AppState;

/// The shared state handlers get.
pub type Shared = State<Arc<AppState>>;

/// The longest page of a list.
pub const MAX_PAGE: u32 = 100;
/// A list's page when the query does not say.
pub const DEFAULT_PAGE: u32 = 20;

/// The query of the lists that go newest first (`GET /calibrations`,
/// `GET /sequences`): a page of `limit` below the id `before`.
#[derive(Debug, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct PageQuery {
    /// Items per page, 1 to 100 [default: 20].
    #[serde(default)]
    pub limit: Option<u32>,
    /// Only items with a lower id (the `next` link sets it).
    #[serde(default)]
    pub before: Option<i64>,
}

impl PageQuery {
    /// The page's length, checked.
    pub fn limit(&self) -> Result<u32, ApiError> {
        match self.limit {
            None => Ok(DEFAULT_PAGE),
            Some(n @ 1..=MAX_PAGE) => Ok(n),
            Some(n) => Err(ApiError::bad_request(format!(
                "limit: {n} is not within 1 to {MAX_PAGE}"
            ))),
        }
    }

    /// The link to the page after one whose last item has id `last`.
    pub fn next(&self, path: &str, last: i64) -> String {
        format!(
            "/api/v1{path}?limit={}&before={last}",
            self.limit.unwrap_or(DEFAULT_PAGE)
        )
    }
}

/// The whole application's routes, in the service's layers.
pub fn router(state: Arc<AppState>) -> Router {
    // The bearer token is checked in `layers::apply`, on every path under
    // `/api` whether it names a route or not.
    let api = Router::new()
        .merge(calibrations::router())
        .merge(sequences::router())
        .merge(events::router())
        .merge(sequence_images::router())
        .merge(selfcal::router())
        .merge(experiments::router())
        .merge(tracking::router())
        .merge(plots::router())
        .merge(jobs::router());
    let routes = Router::new()
        .nest("/api/v1", api)
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics))
        .merge(docs::router())
        .merge(web::router())
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed);
    layers::apply(routes, &state.config, state.metrics.clone()).with_state(state)
}

/// Liveness: the process answers `ok`.
#[utoipa::path(get, path = "/healthz", tag = "operations", security(()),
    responses((status = 200, content_type = "text/plain", body = String)))]
pub async fn healthz() -> &'static str {
    "ok\n"
}

/// Readiness: 200 `ready` when the database takes a write lock within
/// 5 s and the object store (if images go to one) answers a listing
/// within 5 s, else 503 (problem+json): the service cannot store anything
/// now.
/// `/healthz` stays liveness.
#[utoipa::path(get, path = "/readyz", tag = "operations", security(()),
    responses(
        (status = 200, content_type = "text/plain", body = String),
        (status = 503, body = problem::Problem, content_type = "application/problem+json"),
    ))]
pub async fn readyz(State(state): Shared) -> Result<&'static str, ApiError> {
    match state.store.ready(std::time::Duration::from_secs(5)).await {
        Ok(()) => {}
        Err(error) => {
            tracing::warn!(%error, "not ready");
            return Err(ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                "the database cannot take writes now; the error is in the service's log",
            ));
        }
    }
    match state.images.ready(std::time::Duration::from_secs(5)).await {
        Ok(()) => Ok("ready\n"),
        Err(error) => {
            tracing::warn!(%error, "not ready");
            Err(ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                "the object store cannot be reached now; the error is in the service's log",
            ))
        }
    }
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
