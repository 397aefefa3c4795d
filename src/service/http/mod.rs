//! The HTTP API: axum routers per resource under `/api/v1`, plus
//! `/healthz`, `/metrics`, `/openapi.json`, `/docs` and the web page at
//! `/` ([`web`]).
//!
//! - [`calibrations`]: create (JSON or OpenPTV files), read, export as
//!   OpenPTV files, project and intersect.
//! - [`sequences`]: create, read, list.
//! - [`frames`]: a sequence's frames: upload one, list them.
//! - [`results`]: a frame's particles and targets, all particles of a
//!   sequence.
//! - [`calibration_health`]: a sequence's calibration health during the
//!   run (the drift of each camera's disparities, its alarm).
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
//! - [`extract`]: the shared state handlers get, the list pages' query.
//! - [`health`]: `/healthz`, `/readyz`, `/metrics`.
//! - [`lookups`]: the stored things handlers read by id, or a 404.
//! - [`problem`]: the one error type, its statuses by the errors' types,
//!   and the extractors that use it.
//! - [`upload`]: the multipart upload path frames and solving share.
//! - [`web`]: the lab web page and its assets, compiled in.
//! - [`docs`]: the OpenAPI document and the vendored Swagger UI.
//! - [`layers`]: the tower and tower-http layers every request passes
//!   through (request ids, tracing, compression, timeouts, body limits,
//!   the panic guard, load shedding, the bearer token) and the request
//!   counts for `/metrics`.

pub mod calibration_health;
pub mod calibrations;
pub mod decimal;
pub mod docs;
pub mod events;
pub mod experiments;
pub mod exports;
pub mod extract;
pub mod frames;
pub mod health;
pub mod jobs;
pub mod layers;
pub mod lookups;
pub mod plots;
pub mod problem;
pub mod results;
pub mod selfcal;
pub mod sequence_images;
pub mod sequences;
pub mod tracking;
pub mod upload;
pub mod web;

use std::sync::Arc;

use axum::http::StatusCode;
use axum::routing::get;
use axum::Router;

use self::health::{healthz, metrics, readyz};
use self::problem::ApiError;
use crate::service::ops::state::AppState;

/// The whole application's routes, in the service's layers.
pub fn router(state: Arc<AppState>) -> Router {
    // The bearer token is checked in `layers::apply`, on every path under
    // `/api` whether it names a route or not.
    let api = Router::new()
        .merge(calibrations::router())
        .merge(sequences::router())
        .merge(frames::router())
        .merge(results::router())
        .merge(calibration_health::router())
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

async fn not_found() -> ApiError {
    ApiError::not_found("no such route; the API is under /api/v1, its description at /docs")
}

async fn method_not_allowed() -> ApiError {
    ApiError::new(
        StatusCode::METHOD_NOT_ALLOWED,
        "this route does not take this method; see /docs",
    )
}
