//! Self-calibration of a sequence's calibration from its stored targets,
//! reprocessing a sequence with another calibration, and a calibration's
//! report ([`crate::service::ops::selfcal`] has the jobs).

use std::sync::Arc;

use axum::extract::State;
use axum::response::Response;
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::extract::Shared;
use super::lookups::sequence;
use super::problem::{ApiError, ApiJson, ApiPath};
use super::upload::accepted;
use crate::formats;
use crate::service::model::job_kind::JobKind;
use crate::service::ops::links;
use crate::service::ops::selfcal::{
    SelfCalibrationPayload, SelfCalibrationRequest, SelfCalibrationRequestError,
};
use crate::service::ops::state::AppState;
use crate::service::store::{CalibrationId, JobId, SequenceId};

pub(super) fn router() -> Router<Arc<AppState>> {
    Router::new()
        .route("/sequences/{id}/self-calibration", post(self_calibrate))
        .route("/sequences/{id}/reprocess", post(reprocess))
        .route("/calibrations/{id}/report", get(report))
}

/// An accepted self-calibration or reprocessing.
#[derive(Debug, Serialize, ToSchema)]
pub struct SequenceJobAccepted {
    /// The job.
    #[schema(value_type = i64)]
    pub job_id: JobId,
    /// Where to poll the job; once succeeded, its `result` is the refined
    /// calibration (self-calibration) or the sequence (reprocessing).
    pub job: String,
    /// The sequence.
    #[schema(value_type = i64)]
    pub sequence_id: SequenceId,
    /// The calibration refined (self-calibration) or the one the frames
    /// are reprocessed with.
    #[schema(value_type = i64)]
    pub calibration_id: CalibrationId,
}

/// Queues the self-calibration of a sequence's calibration from the
/// targets its frames' jobs stored: the job stores a new calibration that
/// names its origin (`origin_calibration`) and carries the report (also at
/// `/calibrations/{id}/report`); with `reprocess`, the sequence is then
/// switched to it and its frames matched again. A diverged adjustment
/// stores nothing and the job's `error` says why.
#[utoipa::path(
    post, path = "/api/v1/sequences/{id}/self-calibration", tag = "sequences",
    params(("id" = i64, Path, description = "Sequence id")),
    request_body = SelfCalibrationRequest,
    responses(
        (status = 202, body = SequenceJobAccepted, description = "Queued; poll the job"),
        (status = 400, description = "Not JSON, or unknown fields", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such sequence", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 422, description = "Invalid options, or no frames with targets", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn self_calibrate(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
    ApiJson(request): ApiJson<SelfCalibrationRequest>,
) -> Result<Response, ApiError> {
    let row = sequence(&state, id).await?;
    let calibration = state
        .store
        .calibration(row.calibration_id)
        .await?
        .ok_or_else(|| ApiError::internal("a sequence's calibration is gone"))?;
    let (cameras, _) = formats::calibration::stored_from_json_with_splitter(
        &calibration.model,
        "the stored calibration",
    )
    .map_err(ApiError::internal)?;
    let parameters: Vec<_> = cameras.iter().map(|c| c.parameters().clone()).collect();
    request.options(&parameters, row.parameters.matching().volume)?;
    let frames = state
        .store
        .frames_with_targets(id, request.span(), calibration.cameras)
        .await?;
    if frames.is_empty() {
        return Err(SelfCalibrationRequestError::NoTargets {
            sequence: id,
            range: request
                .frames
                .map(|s| format!(" in {}..{}", s.first, s.last))
                .unwrap_or_default(),
            cameras: calibration.cameras,
        }
        .into());
    }
    let payload = serde_json::to_string(&SelfCalibrationPayload {
        sequence_id: id,
        calibration_id: calibration.id,
        options: request,
    })?;
    let job_id = state
        .store
        .enqueue(JobKind::SelfCalibrate.as_str(), &payload)
        .await?;
    Ok(accepted(
        &state,
        job_id,
        SequenceJobAccepted {
            job_id,
            job: links::job(job_id),
            sequence_id: id,
            calibration_id: calibration.id,
        },
    ))
}

/// Which calibration to reprocess a sequence with.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ReprocessRequest {
    /// The calibration (of the same rig: as many cameras).
    #[schema(value_type = i64)]
    pub calibration: CalibrationId,
}

/// Switches a sequence to another calibration (frames processed from now
/// on use it) and queues the job that matches its processed frames again
/// from their stored targets (no detection). Each frame's particles are
/// replaced in one transaction: until then the old ones stay, naming the
/// calibration that made them.
#[utoipa::path(
    post, path = "/api/v1/sequences/{id}/reprocess", tag = "sequences",
    params(("id" = i64, Path, description = "Sequence id")),
    request_body = ReprocessRequest,
    responses(
        (status = 202, body = SequenceJobAccepted, description = "Queued; poll the job"),
        (status = 400, description = "Not JSON, or unknown fields", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such sequence", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 422, description = "Unknown calibration, or one of another rig", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn reprocess(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
    ApiJson(request): ApiJson<ReprocessRequest>,
) -> Result<Response, ApiError> {
    let row = sequence(&state, id).await?;
    let current = state
        .store
        .calibration(row.calibration_id)
        .await?
        .ok_or_else(|| ApiError::internal("a sequence's calibration is gone"))?;
    let calibration = state.store.calibration(request.calibration).await?.ok_or(
        SelfCalibrationRequestError::UnknownCalibration(request.calibration),
    )?;
    if calibration.cameras != current.cameras {
        return Err(SelfCalibrationRequestError::CameraCount {
            calibration: calibration.id,
            given: calibration.cameras,
            sequence: id,
            cameras: current.cameras,
        }
        .into());
    }
    let job_id = state
        .store
        .start_reprocess(id, calibration.id)
        .await?
        .ok_or_else(|| ApiError::not_found(format!("sequence {id} does not exist")))?;
    Ok(accepted(
        &state,
        job_id,
        SequenceJobAccepted {
            job_id,
            job: links::job(job_id),
            sequence_id: id,
            calibration_id: calibration.id,
        },
    ))
}

/// A calibration's report: the resection's (solved from control points)
/// or the self-calibration's (refined from particles: disparities before
/// and after per camera, with maps over sub-volumes, each parameter's
/// change with its sigma, the rounds' bands and particles, the gauge).
#[utoipa::path(
    get, path = "/api/v1/calibrations/{id}/report", tag = "calibrations",
    params(("id" = i64, Path, description = "Calibration id")),
    responses(
        (status = 200, body = Object, description = "The report (JSON)"),
        (status = 404, description = "No such calibration, or it has no report (uploaded as it is)", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn report(
    State(state): Shared,
    ApiPath(id): ApiPath<CalibrationId>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let row = state
        .store
        .calibration(id)
        .await?
        .ok_or_else(|| ApiError::not_found(format!("calibration {id} does not exist")))?;
    let report = row.report.ok_or_else(|| {
        ApiError::not_found(format!(
            "calibration {id} has no report: it was stored as given, not solved or \
             self-calibrated"
        ))
    })?;
    Ok(Json(serde_json::from_str(&report)?))
}
