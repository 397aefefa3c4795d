//! `/sequences`: a recording processed with one calibration and one set of
//! parameters. Create one, read it, list them; and the sequence with its
//! calibration's cameras (`sequence_cameras_and_row`) the frame and
//! image uploads start from. Its frames are in [`super::frames`], their
//! particles and targets in [`super::results`].

use std::sync::Arc;

use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::calibrations::stored_rig;
use super::extract::Shared;
use super::lookups::sequence;
use super::problem::{ApiError, ApiJson, ApiPath, ApiQuery};
use super::tracking::{run_view, TrackingRunView};
use crate::photogrammetry::{Camera, Cancel, Splitter, StopOnDrop};
use crate::service::model::parameters::{
    ComputedBackground, DetectionSettings, HealthSettings, MatchingSettings, SequenceParameters,
};
use crate::service::model::tracking_settings::TrackingSettings;
use crate::service::ops::jobs::pipelines::prepare_pipeline;
use crate::service::ops::links;
use crate::service::ops::state::AppState;
use crate::service::store::{
    CalibrationId, FrameCounts, SequenceId, SequenceImageKind, SequenceRow,
};

/// Longest sequence name.
const MAX_NAME: usize = 200;

pub(super) fn router() -> Router<Arc<AppState>> {
    Router::new()
        .route("/sequences", post(create).get(list))
        .route("/sequences/{id}", get(read))
}

/// A new sequence.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CreateSequence {
    /// The calibration its frames are processed with.
    #[schema(value_type = i64)]
    pub calibration_id: CalibrationId,
    /// A label (no path separators or control characters).
    #[serde(default)]
    pub name: Option<String>,
    /// Detection parameters.
    #[serde(default)]
    pub detection: DetectionSettings,
    /// Matching parameters.
    #[serde(default)]
    pub matching: MatchingSettings,
    /// Whether to keep the images after processing [default: true].
    #[serde(default)]
    pub keep_images: Option<bool>,
    /// A background computed from the sequence's own frames [default:
    /// none; a background can also be uploaded before the first frame,
    /// `POST /sequences/{id}/background`].
    #[serde(default)]
    pub background: Option<ComputedBackground>,
    /// Track the frames' particles into trajectories as the frames
    /// complete, with these settings [default: off; `POST
    /// /sequences/{id}/tracking` starts tracking later].
    #[serde(default)]
    pub tracking: Option<TrackingSettings>,
    /// How its calibration health is watched [default: an alarm when a
    /// camera's mean disparity drifts 0.3 px over 50 frames].
    #[serde(default)]
    pub health: Option<HealthSettings>,
}

/// Frames of a sequence by state.
#[derive(Debug, Serialize, ToSchema)]
pub struct FrameCountsView {
    /// Waiting for a worker.
    pub queued: i64,
    /// Being processed.
    pub running: i64,
    /// Processed.
    pub done: i64,
    /// Failed (see their jobs).
    pub failed: i64,
}

/// Where a sequence's background stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum BackgroundStatus {
    /// No background: frames are detected as they are.
    None,
    /// Uploaded (`POST /sequences/{id}/background`).
    Uploaded,
    /// To be computed from the frames, which wait until enough have arrived.
    Waiting,
    /// Computed from the sequence's first frames.
    Computed,
}

/// A sequence.
#[derive(Debug, Serialize, ToSchema)]
pub struct SequenceView {
    /// Its id.
    #[schema(value_type = i64)]
    pub id: SequenceId,
    /// Its calibration.
    #[schema(value_type = i64)]
    pub calibration_id: CalibrationId,
    /// Its name.
    pub name: String,
    /// The parameters, defaults filled in.
    pub parameters: SequenceParameters,
    /// Whether images are kept after processing.
    pub keep_images: bool,
    /// Its background.
    pub background: BackgroundStatus,
    /// The cameras that have a background.
    pub background_cameras: Vec<i64>,
    /// The cameras that have a mask.
    pub mask_cameras: Vec<i64>,
    /// When it was created (UTC).
    pub created_at: String,
    /// Its frames by state.
    pub frames: FrameCountsView,
    /// Its current tracking run (null: not tracked), with how far it has
    /// got (`tracked_through`).
    pub tracking: Option<TrackingRunView>,
}

pub(super) async fn view(state: &AppState, row: SequenceRow) -> Result<SequenceView, ApiError> {
    let counts = state.store.frame_counts(row.id).await?;
    let images = state.store.sequence_images(row.id).await?;
    let cameras_of = |kind| {
        images
            .iter()
            .filter(|i| i.kind == kind)
            .map(|i| i.camera)
            .collect::<Vec<_>>()
    };
    let background_cameras = cameras_of(SequenceImageKind::Background);
    let tracking = match state.store.current_tracking_run(row.id).await? {
        Some(run) => Some(run_view(state, run).await?),
        None => None,
    };
    let background = match (&row.parameters.background, background_cameras.is_empty()) {
        (None, true) => BackgroundStatus::None,
        (None, false) => BackgroundStatus::Uploaded,
        (Some(_), true) => BackgroundStatus::Waiting,
        (Some(_), false) => BackgroundStatus::Computed,
    };
    Ok(SequenceView {
        id: row.id,
        calibration_id: row.calibration_id,
        name: row.name,
        parameters: row.parameters,
        keep_images: row.keep_images,
        background,
        background_cameras,
        mask_cameras: cameras_of(SequenceImageKind::Mask),
        created_at: row.created_at,
        frames: counts.into(),
        tracking,
    })
}

/// Checks a sequence name: a label, never a path.
pub(super) fn check_name(name: &str) -> Result<(), ApiError> {
    if name.len() > MAX_NAME {
        return Err(ApiError::unprocessable(format!(
            "name: at most {MAX_NAME} bytes, got {}",
            name.len()
        )));
    }
    if name.contains(['/', '\\']) || name.contains("..") || name.chars().any(char::is_control) {
        return Err(ApiError::unprocessable(format!(
            "name: `{}` looks like a path; use a label without `/`, `\\`, `..` or control \
             characters",
            name.escape_debug()
        )));
    }
    Ok(())
}

/// Creates a sequence: validates the parameters against the calibration
/// (preparing the frame pipeline) and stores it.
#[utoipa::path(
    post, path = "/api/v1/sequences", tag = "sequences",
    request_body = CreateSequence,
    responses(
        (status = 201, body = SequenceView),
        (status = 400, description = "Not JSON", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 422, description = "Unknown calibration or invalid parameters", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn create(
    State(state): Shared,
    ApiJson(request): ApiJson<CreateSequence>,
) -> Result<Response, ApiError> {
    let name = request.name.unwrap_or_default();
    check_name(&name)?;
    let calibration = state
        .store
        .calibration(request.calibration_id)
        .await?
        .ok_or_else(|| {
            ApiError::unprocessable(format!(
                "calibration_id: calibration {} does not exist",
                request.calibration_id
            ))
        })?;
    let mut parameters = SequenceParameters::with_defaults(request.detection, request.matching);
    if let Some(background) = &request.background {
        background.validate().map_err(ApiError::unprocessable)?;
    }
    parameters.background = request.background;
    if let Some(health) = request.health {
        health.validate().map_err(ApiError::unprocessable)?;
        parameters.health = Some(health);
    }
    let tracking = match &request.tracking {
        Some(settings) => Some(settings.with_defaults()?),
        None => None,
    };
    // Dropped with this handler (client gone, request timeout): the
    // preparation does not start if it still waits for a CPU thread.
    let cancel = Cancel::new();
    let _stop = StopOnDrop(cancel.clone());
    let (pipeline, splitter) =
        prepare_pipeline(&state, &calibration.model, &parameters, &cancel).await?;
    // The tracking limits against the volume the particles are found in.
    let tracking = match tracking {
        Some(settings) => {
            settings.check_volume(pipeline.volume())?;
            Some(settings)
        }
        None => None,
    };
    let row = state
        .store
        .insert_sequence(
            calibration.id,
            &name,
            &parameters,
            request.keep_images.unwrap_or(true),
            tracking.as_ref(),
        )
        .await?
        .ok_or_else(|| ApiError::unprocessable("calibration_id: the calibration does not exist"))?;
    state
        .pipelines
        .insert(row.id, calibration.id, 0, (Arc::new(pipeline), splitter));
    let location = links::sequence(row.id);
    Ok((
        StatusCode::CREATED,
        [(header::LOCATION, location)],
        Json(view(&state, row).await?),
    )
        .into_response())
}

/// A sequence, with its frames counted by state.
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}", tag = "sequences",
    params(("id" = i64, Path, description = "Sequence id")),
    responses(
        (status = 200, body = SequenceView),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn read(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
) -> Result<Json<SequenceView>, ApiError> {
    let row = sequence(&state, id).await?;
    Ok(Json(view(&state, row).await?))
}

/// A sequence in the list.
#[derive(Debug, Serialize, ToSchema)]
pub struct SequenceSummaryView {
    /// Its id.
    #[schema(value_type = i64)]
    pub id: SequenceId,
    /// Its calibration.
    #[schema(value_type = i64)]
    pub calibration_id: CalibrationId,
    /// Its name.
    pub name: String,
    /// When it was created (UTC).
    pub created_at: String,
    /// Its frames by state.
    pub frames: FrameCountsView,
    /// Where it is.
    pub link: String,
}

/// A page of sequences, newest first.
#[derive(Debug, Serialize, ToSchema)]
pub struct SequenceList {
    /// The sequences.
    pub items: Vec<SequenceSummaryView>,
    /// The next page (older ones), if there may be more.
    pub next: Option<String>,
}

/// The sequences, newest first, a page at a time, with their frames
/// counted by state.
#[utoipa::path(
    get, path = "/api/v1/sequences", tag = "sequences",
    params(super::extract::PageQuery),
    responses(
        (status = 200, body = SequenceList),
        (status = 400, description = "A bad query", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn list(
    State(state): Shared,
    ApiQuery(query): ApiQuery<super::extract::PageQuery>,
) -> Result<Json<SequenceList>, ApiError> {
    let limit = query.limit()?;
    let rows = state
        .store
        .sequences_page(query.before.map(SequenceId), limit)
        .await?;
    let next = (rows.len() == limit as usize)
        .then(|| rows.last().map(|r| query.next("/sequences", r.id.0)))
        .flatten();
    let mut items = Vec::with_capacity(rows.len());
    for row in rows {
        let counts = state.store.frame_counts(row.id).await?;
        items.push(SequenceSummaryView {
            id: row.id,
            calibration_id: row.calibration_id,
            name: row.name,
            created_at: row.created_at,
            frames: counts.into(),
            link: links::sequence(row.id),
        });
    }
    Ok(Json(SequenceList { items, next }))
}

impl From<FrameCounts> for FrameCountsView {
    fn from(counts: FrameCounts) -> Self {
        FrameCountsView {
            queued: counts.queued,
            running: counts.running,
            done: counts.done,
            failed: counts.failed,
        }
    }
}

/// A sequence and its calibration's cameras and splitter.
pub(super) struct SequenceRig {
    /// The sequence.
    pub row: SequenceRow,
    /// Its calibration's cameras.
    pub cameras: Vec<Camera>,
    /// Whether they are views of one sensor.
    pub splitter: Option<Splitter>,
}

/// A sequence and its calibration's cameras and splitter, or a 404.
pub(super) async fn sequence_cameras_and_row(
    state: &AppState,
    id: SequenceId,
) -> Result<SequenceRig, ApiError> {
    let row = sequence(state, id).await?;
    let calibration = state
        .store
        .calibration(row.calibration_id)
        .await?
        .ok_or_else(|| ApiError::internal("a sequence's calibration is missing"))?;
    let (cameras, splitter) = stored_rig(&calibration)?;
    Ok(SequenceRig {
        row,
        cameras,
        splitter,
    })
}
