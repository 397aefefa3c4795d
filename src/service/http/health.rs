//! The operations routes: liveness, readiness and the counters.

use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};

use super::extract::Shared;
use super::problem::{self, ApiError};
use crate::photogrammetry::health::DriftMonitor;
use crate::service::infra::metrics::{render_health, CameraDrift};

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
/// queue depth, jobs by kind and state, job durations, particles per frame,
/// and per sequence whose calibration health advanced in the last hour (at
/// most 100) and camera its drift (px) and alarm.
#[utoipa::path(get, path = "/metrics", tag = "operations", security(()),
    responses((status = 200, content_type = "text/plain", body = String)))]
pub async fn metrics(State(state): Shared) -> Result<Response, ApiError> {
    let jobs = state.store.job_counts().await?;
    let mut text = state.metrics.render(&jobs);
    let mut drifts = Vec::new();
    for (sequence, stored) in state.store.recent_health_states(3600.0, 100).await? {
        // A monitor that does not read (written by a newer version) is
        // left out, as an unknown event is.
        let Ok(monitor) = serde_json::from_str::<DriftMonitor>(&stored.monitor) else {
            continue;
        };
        for (camera, c) in monitor.cameras.iter().enumerate() {
            drifts.push(CameraDrift {
                sequence: sequence.0,
                camera,
                drift_px: c.drift_px,
                alarm: c.alarm.is_some(),
            });
        }
    }
    text.push_str(&render_health(&drifts));
    Ok(([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], text).into_response())
}
