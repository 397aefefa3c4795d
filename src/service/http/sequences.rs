//! `/sequences`: a recording processed with one calibration and one set of
//! parameters. Create one, upload its frames (images, or targets detected
//! on the camera side), and fetch each frame's particles and targets, or
//! all particles as one streamed CSV.
//!
//! Size: about 1,270 lines, 8 routes with their views and the frame
//! upload's checks; splitting frames (upload, particles, targets) from the
//! sequence itself is an open item of issue 31.

use std::sync::Arc;

use axum::body::Body;
use axum::extract::multipart::Field;
use axum::extract::Multipart;
use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::calibrations::stored_rig;
use super::decimal;
use super::extract::Shared;
use super::lookups::sequence;
use super::problem::{ApiError, ApiJson, ApiMultipart, ApiPath, ApiQuery};
use super::tracking::{frame_trajectories, run_view, TrackingRunView};
use super::upload::{accepted, check_images, or_drain, persist_and_commit, stream_part, text_part};
use crate::formats;
use crate::formats::image::ImageHeader;
use crate::formats::targets::TargetsReader;
use crate::photogrammetry::correspond::{max_targets, Particle, MAX_TARGETS_PER_CAMERA};
use crate::photogrammetry::{Camera, Cancel, Sensor, Splitter, StopOnDrop, Target};
use crate::service::infra::codec;
use crate::service::model::parameters::{
    ComputedBackground, DetectionSettings, HealthSettings, MatchingSettings, SequenceParameters,
};
use crate::service::model::raw_layout::StoredRawLayout;
use crate::service::model::tracking_settings::TrackingSettings;
use crate::service::ops::events::Change;
use crate::service::ops::events::JobStateView;
use crate::service::ops::images::UploadedFile;
use crate::service::ops::jobs::pipelines::prepare_pipeline;
use crate::service::ops::links;
use crate::service::ops::state::AppState;
use crate::service::store::{
    CalibrationId, FrameCounts, FrameInputKind, FrameNumber, InsertFrameError, JobId, NewFrame,
    SequenceId, SequenceImageKind, SequenceRow, TrackingRunId,
};

/// The response header that names the calibration that made a frame's
/// particles (CSV and rt_is; JSON has `calibration_id`).
pub const CALIBRATION_HEADER: &str = "ptv-calibration-id";

/// Longest sequence name.
const MAX_NAME: usize = 200;
/// Largest targets part (bytes). The part is parsed as it arrives
/// ([`TargetsReader`]), so this bounds the work, not the memory: a part
/// holds at most one batch of its text ([`TARGETS_BATCH`], 1 MiB, plus
/// one chunk), the reader's pending text (a slice of 64 KiB, or one
/// record of at most 1 MiB) and its targets, at most `max_targets` of its camera's sensor
/// (40 bytes each, twice that while their vector grows: 80 MiB at the
/// largest sensors' 2^20).
const MAX_TARGETS_PART: usize = 64 << 20;

pub(super) fn router() -> Router<Arc<AppState>> {
    Router::new()
        .route("/sequences", post(create).get(list))
        .route("/sequences/{id}", get(read))
        .route("/sequences/{id}/frames", post(upload_frame).get(frames))
        .route(
            "/sequences/{id}/frames/{frame}/particles",
            get(frame_particles),
        )
        .route("/sequences/{id}/frames/{frame}/targets", get(frame_targets))
        .route("/sequences/{id}/particles", get(all_particles))
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
    let parameters: SequenceParameters = serde_json::from_str(&row.parameters)?;
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
    let background = match (&parameters.background, background_cameras.is_empty()) {
        (None, true) => BackgroundStatus::None,
        (None, false) => BackgroundStatus::Uploaded,
        (Some(_), true) => BackgroundStatus::Waiting,
        (Some(_), false) => BackgroundStatus::Computed,
    };
    Ok(SequenceView {
        id: row.id,
        calibration_id: row.calibration_id,
        name: row.name,
        parameters,
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
            Some(serde_json::to_string(&settings)?)
        }
        None => None,
    };
    let stored = serde_json::to_string(&parameters)?;
    let row = state
        .store
        .insert_sequence(
            calibration.id,
            &name,
            &stored,
            request.keep_images.unwrap_or(true),
            tracking.as_deref(),
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

/// Query of the frame list.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct FramePageQuery {
    /// Frames per page, 1 to 1000 [default: 100].
    #[serde(default)]
    pub limit: Option<u32>,
    /// Only frames with a higher number (the `next` link sets it).
    #[serde(default)]
    #[param(value_type = Option<i64>, minimum = 0, maximum = 4_294_967_295_u64)]
    pub after: Option<u32>,
}

/// Longest page of the frame list.
const MAX_FRAME_PAGE: u32 = 1000;

/// A frame in the list.
#[derive(Debug, Serialize, ToSchema)]
pub struct FrameSummaryView {
    /// The frame.
    #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
    pub frame: FrameNumber,
    /// Its job.
    #[schema(value_type = i64)]
    pub job_id: JobId,
    /// The job's state.
    pub state: JobStateView,
    /// How many particles, once processed.
    pub particles: Option<i64>,
}

/// A page of a sequence's frames, in frame order.
#[derive(Debug, Serialize, ToSchema)]
pub struct FrameList {
    /// The frames.
    pub items: Vec<FrameSummaryView>,
    /// The next page, if there may be more.
    pub next: Option<String>,
}

/// A sequence's frames in frame order, a page at a time: each frame's job,
/// its state, and its particle count once processed.
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/frames", tag = "sequences",
    params(("id" = i64, Path, description = "Sequence id"), FramePageQuery),
    responses(
        (status = 200, body = FrameList),
        (status = 400, description = "A bad query", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn frames(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
    ApiQuery(query): ApiQuery<FramePageQuery>,
) -> Result<Json<FrameList>, ApiError> {
    let limit = match query.limit {
        None => 100,
        Some(n @ 1..=MAX_FRAME_PAGE) => n,
        Some(n) => {
            return Err(ApiError::bad_request(format!(
                "limit: {n} is not within 1 to {MAX_FRAME_PAGE}"
            )))
        }
    };
    sequence(&state, id).await?;
    let after = query.after.map(|frame| FrameNumber(frame.into()));
    let rows = state.store.frames_page(id, after, limit).await?;
    let next = (rows.len() == limit as usize)
        .then(|| {
            rows.last().map(|r| {
                format!(
                    "{}/frames?limit={limit}&after={}",
                    links::sequence(id),
                    r.frame
                )
            })
        })
        .flatten();
    Ok(Json(FrameList {
        items: rows
            .into_iter()
            .map(|r| FrameSummaryView {
                frame: r.frame,
                job_id: r.job_id,
                state: r.state.into(),
                particles: r.particles,
            })
            .collect(),
        next,
    }))
}

/// An accepted frame.
#[derive(Debug, Serialize, ToSchema)]
pub struct FrameAccepted {
    /// The frame number.
    #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
    pub frame: FrameNumber,
    /// The job that processes it.
    #[schema(value_type = i64)]
    pub job_id: JobId,
    /// Where to poll the job.
    pub job: String,
    /// Where the particles will be.
    pub particles: String,
}

/// A numeric part: `frame`, `width`, `height`, `bits`, each 0 to
/// 4,294,967,295 in the one accepted form ([`decimal`]): text in another
/// form is a 400 naming the part and the form, a number above the range
/// a 422.
async fn number_part(field: &mut Field<'_>, name: &str) -> Result<u32, ApiError> {
    let text = text_part(field, name, 64).await?;
    decimal::parse::<u32>(&text).map_err(|refused| match refused {
        decimal::Refused::Form => ApiError::bad_request(format!(
            "part `{name}` is `{}`, not a non-negative integer in the accepted form: {}",
            text.escape_debug(),
            decimal::FORM
        )),
        decimal::Refused::Range => ApiError::unprocessable(format!(
            "part `{name}` is {text}, above the largest accepted, {}",
            u32::MAX
        )),
    })
}

/// The camera index of a part named `{prefix}{index}`, below `cameras`.
pub(super) fn camera_of(
    name: &str,
    prefix: &str,
    cameras: usize,
) -> Option<Result<usize, ApiError>> {
    let digits = name.strip_prefix(prefix)?;
    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let beyond = || {
        ApiError::unprocessable(format!(
            "part `{name}`: the calibration has {cameras} cameras, {prefix}0 to {prefix}{}",
            cameras - 1
        ))
    };
    Some(match decimal::parse::<usize>(digits) {
        Ok(c) if c < cameras => Ok(c),
        Ok(_) | Err(decimal::Refused::Range) => Err(beyond()),
        // `cam00` is not `cam0`: one name per camera.
        Err(decimal::Refused::Form) => Err(ApiError::bad_request(format!(
            "part `{name}`: the camera index is written as {}: {prefix}0 to {prefix}{}",
            decimal::FORM,
            cameras - 1
        ))),
    })
}

/// The parts of a frame upload, as read.
struct UploadParts {
    frame: Option<FrameNumber>,
    images: Vec<Option<UploadedFile>>,
    /// The whole sensor's image, for a calibration with a splitter.
    whole: Option<UploadedFile>,
    targets: Vec<Option<Vec<Target>>>,
    width: Option<u32>,
    height: Option<u32>,
    bits: Option<u32>,
}

/// Reads a frame upload's parts for a calibration of `cameras`: images
/// streamed to temporary files, targets parsed as they arrive (each
/// camera's at most `max_targets` of its sensor), numbers checked.
async fn read_parts(
    state: &AppState,
    id: SequenceId,
    cameras: &[Camera],
    splitter: Option<Splitter>,
    multipart: &mut Multipart,
) -> Result<UploadParts, ApiError> {
    let n = cameras.len();
    let mut parts = UploadParts {
        frame: None,
        images: (0..n).map(|_| None).collect(),
        whole: None,
        targets: vec![None; n],
        width: None,
        height: None,
        bits: None,
    };
    while let Some(mut field) = multipart.next_field().await? {
        let name = field.name().unwrap_or("").to_owned();
        let repeated = || ApiError::bad_request(format!("part `{name}` is given twice"));
        if name == "frame" {
            if parts.frame.is_some() {
                return Err(repeated());
            }
            let number = FrameNumber(number_part(&mut field, &name).await?.into());
            if state.store.frame_exists(id, number).await? {
                return Err(InsertFrameError::Exists {
                    sequence_id: id,
                    frame: number,
                }
                .into());
            }
            parts.frame = Some(number);
        } else if name == "width" {
            parts.width = Some(number_part(&mut field, &name).await?);
        } else if name == "height" {
            parts.height = Some(number_part(&mut field, &name).await?);
        } else if name == "bits" {
            parts.bits = Some(number_part(&mut field, &name).await?);
        } else if name == "image" && splitter.is_some() {
            if parts.whole.is_some() {
                return Err(repeated());
            }
            parts.whole = Some(stream_part(&state.images, &mut field).await?);
        } else if let Some(camera) = camera_of(&name, "cam", n) {
            let camera = camera?;
            if let Some(splitter) = splitter {
                return Err(ApiError::unprocessable(format!(
                    "part `{name}`: the calibration's cameras are the {} views of one sensor \
                     (its `splitter`); send the whole sensor's image as one part `image`",
                    splitter.name()
                )));
            }
            if parts.images[camera].is_some() {
                return Err(repeated());
            }
            parts.images[camera] = Some(stream_part(&state.images, &mut field).await?);
        } else if let Some(camera) = camera_of(&name, "targets", n) {
            let camera = camera?;
            if parts.targets[camera].is_some() {
                return Err(repeated());
            }
            parts.targets[camera] =
                Some(targets_part(state, &mut field, &name, camera, cameras).await?);
        } else {
            return Err(ApiError::bad_request(format!(
                "unknown part `{}`; expected `frame`, `cam0`..`cam{m}` or `targets0`..`targets{m}`, \
                 and `width`, `height`, `bits` for raw images",
                name.escape_debug(),
                m = n - 1
            )));
        }
    }
    Ok(parts)
}

/// The bytes of a targets part gathered before they are parsed on the
/// CPU pool: a batch of 1 MiB parses in milliseconds (16,000 rows), off
/// the runtime, and the part holds at most this much besides its targets.
const TARGETS_BATCH: usize = 1 << 20;

/// Reads camera `camera`'s targets part `name`, parsing its rows as they
/// arrive and refusing it once it has more targets than the camera's
/// sensor can hold ([`max_targets`], which matching would refuse anyway)
/// or is larger than [`MAX_TARGETS_PART`]. The chunks are gathered into
/// batches of [`TARGETS_BATCH`] bytes, each parsed on the CPU pool, not
/// on the runtime that serves the connections.
async fn targets_part(
    state: &AppState,
    field: &mut Field<'_>,
    name: &str,
    camera: usize,
    cameras: &[Camera],
) -> Result<Vec<Target>, ApiError> {
    let sensor = cameras[camera].sensor();
    let reason = format!(
        "camera {camera}'s {}x{} px sensor (one target per 2x2 pixels, at most \
         {MAX_TARGETS_PER_CAMERA} a camera)",
        sensor.width, sensor.height
    );
    let mut reader = TargetsReader::new(name, max_targets(sensor), &reason);
    let mut size = 0;
    let mut batch = Vec::new();
    while let Some(chunk) = field.chunk().await? {
        size += chunk.len();
        if size > MAX_TARGETS_PART {
            return Err(ApiError::too_large(format!(
                "part `{name}` is larger than {MAX_TARGETS_PART} bytes"
            )));
        }
        batch.extend_from_slice(&chunk);
        if batch.len() >= TARGETS_BATCH {
            let bytes = std::mem::take(&mut batch);
            reader = state
                .cpu
                .run(move || reader.push(&bytes).map(|()| reader))
                .await??;
        }
    }
    let targets = state
        .cpu
        .run(move || {
            reader.push(&batch)?;
            reader.finish()
        })
        .await??;
    Ok(targets)
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

/// Uploads one frame: multipart with a `frame` number and, per camera,
/// `cam0`, `cam1`, ... images (PNG or TIFF, or raw with `width`, `height`,
/// `bits` parts) or `targets0`, `targets1`, ... (CSV or OpenPTV
/// `_targets`). Answers 202 with the job that processes it.
#[utoipa::path(
    post, path = "/api/v1/sequences/{id}/frames", tag = "sequences",
    params(("id" = i64, Path, description = "Sequence id")),
    request_body(content_type = "multipart/form-data", description = "Parts: `frame` (an integer 0 to 4294967295 in decimal digits, without sign, spaces or leading zeros); `cam0`..`camN-1` (images) or `targets0`..`targetsN-1` (CSV x,y,... or OpenPTV _targets); for raw images `width`, `height`, `bits` (8 or 16)."),
    responses(
        (status = 202, body = FrameAccepted),
        (status = 400, description = "Malformed or truncated multipart, unknown or repeated part", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such sequence", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, description = "The frame exists", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 413, description = "Larger than --max-upload-mb", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 415, description = "Not multipart, or an image that does not decode as greyscale PNG/TIFF (unknown, BigTIFF, colour, truncated, corrupt)", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 422, description = "Wrong camera count, image size, or targets (malformed, or more than the camera's sensor may have)", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn upload_frame(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
    ApiMultipart(mut multipart): ApiMultipart,
) -> Result<Response, ApiError> {
    let rig = or_drain(sequence_cameras_and_row(&state, id).await, &mut multipart).await?;
    let SequenceRig {
        cameras, splitter, ..
    } = rig;
    let n = cameras.len();

    let parts = read_parts(&state, id, &cameras, splitter, &mut multipart).await;
    let UploadParts {
        frame,
        images,
        whole,
        targets,
        width,
        height,
        bits,
    } = or_drain(parts, &mut multipart).await?;
    let frame = frame.ok_or_else(|| ApiError::bad_request("the `frame` part is missing"))?;
    // A splitter's one image stands for every camera's.
    let image_count = if whole.is_some() {
        n
    } else {
        images.iter().flatten().count()
    };
    let target_count = targets.iter().flatten().count();
    if image_count > 0 && target_count > 0 {
        return Err(ApiError::bad_request(
            "give either images (`camC`, or `image` with a splitter) or targets (`targetsC`) \
             for a frame, not both",
        ));
    }
    let given = image_count.max(target_count);
    if given != n {
        let missing: Vec<String> = (0..n)
            .filter(|&c| images[c].is_none() && targets[c].is_none())
            .map(|c| format!("cam{c}"))
            .collect();
        return Err(ApiError::unprocessable(format!(
            "the calibration has {n} cameras but {given} were given (missing: {}); give one \
             image or targets part per camera",
            missing.join(", ")
        )));
    }

    let raw = match (width, height, bits) {
        (None, None, None) => None,
        (Some(width), Some(height), Some(bits)) if bits == 8 || bits == 16 => {
            Some(StoredRawLayout {
                width,
                height,
                bits,
            })
        }
        (Some(_), Some(_), Some(bits)) => {
            return Err(ApiError::unprocessable(format!(
                "part `bits` is {bits}; raw images have 8 or 16 bits"
            )))
        }
        _ => {
            return Err(ApiError::bad_request(
                "raw images need all of `width`, `height` and `bits`",
            ))
        }
    };

    let mut new_frame = NewFrame {
        sequence_id: id,
        frame,
        input: if image_count > 0 {
            FrameInputKind::Images
        } else {
            FrameInputKind::Targets
        },
        raw_layout: raw.as_ref().map(serde_json::to_string).transpose()?,
        images: Vec::new(),
        targets: Vec::new(),
    };
    let images: Vec<UploadedFile> = images.into_iter().flatten().collect();
    if let (Some(whole), Some(splitter)) = (&whole, splitter) {
        // The whole sensor: the views' size times the layout's grid.
        let view = cameras[0].sensor();
        let (width, height) = splitter
            .image_size(view.width, view.height)
            .ok_or_else(|| ApiError::internal("a splitter's sensor overflows"))?;
        let sensor = Sensor {
            width,
            height,
            ..view.clone()
        };
        let layout = raw.as_ref().and_then(StoredRawLayout::layout);
        let headers = check_images(std::slice::from_ref(whole), &[sensor], layout, |_| {
            "part `image`".to_owned()
        })
        .await?;
        check_background_depths(&state, id, &vec![headers[0]; n]).await?;
        new_frame.images = vec![(0, whole.sha256.clone(), whole.size as i64)];
    } else if !images.is_empty() {
        let sensors: Vec<Sensor> = cameras.iter().map(|c| c.sensor().clone()).collect();
        let layout = raw.as_ref().and_then(StoredRawLayout::layout);
        let headers =
            check_images(&images, &sensors, layout, |camera| format!("cam{camera}")).await?;
        check_background_depths(&state, id, &headers).await?;
        new_frame.images = images
            .iter()
            .enumerate()
            .map(|(camera, f)| (camera as i64, f.sha256.clone(), f.size as i64))
            .collect();
    } else {
        new_frame.targets = codec::encode_frame_targets(targets.iter().flatten());
    }

    let files = whole.into_iter().chain(images).collect();
    let job_id = persist_and_commit(&state, files, || state.store.insert_frame(&new_frame)).await?;
    state
        .events
        .send(id, Change::FrameAccepted { frame, job_id });
    let body = FrameAccepted {
        frame,
        job_id,
        job: links::job(job_id),
        particles: links::frame_particles(id, frame),
    };
    Ok(accepted(&state, job_id, body))
}

/// Checks that a frame's images have the bit depth of the sequence's
/// backgrounds, camera by camera (a 16-bit frame less an 8-bit background
/// would be meaningless).
async fn check_background_depths(
    state: &AppState,
    id: SequenceId,
    headers: &[ImageHeader],
) -> Result<(), ApiError> {
    for background in state.store.sequence_images(id).await? {
        if background.kind != SequenceImageKind::Background {
            continue;
        }
        let Some(header) = usize::try_from(background.camera)
            .ok()
            .and_then(|c| headers.get(c))
        else {
            continue;
        };
        if i64::from(header.bit_depth.bits()) != background.bits {
            return Err(ApiError::unprocessable(format!(
                "cam{}: the image has {} bits per sample but the sequence's background of this \
                 camera has {}; send images of the background's depth",
                background.camera,
                header.bit_depth.bits(),
                background.bits
            )));
        }
    }
    Ok(())
}

/// How to write particles.
#[derive(Clone, Copy, Debug, Default, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum ParticleFormat {
    /// JSON.
    #[default]
    Json,
    /// CSV `x,y,z,sx,sy,sz,rms_px,cameras,t0,...` as `ptv match` writes.
    Csv,
    /// OpenPTV's `rt_is`.
    RtIs,
    /// ParaView's VTK XML `.vtp` of the frame (vertices with their sigmas,
    /// cameras and trajectory), as `ptv export --export vtk` writes it.
    Vtk,
}

/// Query of the particle routes.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct ParticleQuery {
    /// json (default), csv, rt_is or vtk (`particles.<frame>.vtp`,
    /// application/xml).
    #[serde(default)]
    pub format: ParticleFormat,
}

/// One particle.
#[derive(Debug, Serialize, ToSchema)]
pub struct ParticleView {
    /// X (mm).
    pub x: f64,
    /// Y (mm).
    pub y: f64,
    /// Z (mm).
    pub z: f64,
    /// Standard deviations of X, Y, Z (mm).
    pub sigma: [f64; 3],
    /// Root mean square reprojection residual (px).
    pub rms_px: f64,
    /// Per camera, the index of its target in the frame's targets of that
    /// camera, or null.
    pub targets: Vec<Option<usize>>,
    /// Its trajectory in the sequence's current tracking run (null: none
    /// yet, or the sequence is not tracked).
    pub trajectory: Option<i64>,
}

/// A frame's particles.
#[derive(Debug, Serialize, ToSchema)]
pub struct FrameParticles {
    /// The sequence.
    #[schema(value_type = i64)]
    pub sequence_id: SequenceId,
    /// The frame.
    #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
    pub frame: FrameNumber,
    /// The calibration that made these particles (the sequence's, or the
    /// one it had when the frame was processed, until reprocessed).
    #[schema(value_type = i64)]
    pub calibration_id: CalibrationId,
    /// The tracking run that `trajectory` refers to (null: the sequence is
    /// not tracked).
    #[schema(value_type = Option<i64>)]
    pub tracking_run: Option<TrackingRunId>,
    /// The particles the frame's correspondences gave. Particles a tracking
    /// run recovered from the frame's targets (image-space recovery) are
    /// not among them: they exist only as points of their trajectories
    /// (`GET /sequences/{id}/trajectories`), whose `particle` index is at or
    /// above this list's length.
    pub particles: Vec<ParticleView>,
}

/// The frame's stored particles and the calibration that made them, or
/// why there are none.
pub(super) async fn load_particles(
    state: &AppState,
    id: SequenceId,
    frame: FrameNumber,
) -> Result<(usize, Vec<Particle>, CalibrationId), ApiError> {
    let row = sequence(state, id).await?;
    let cameras = state
        .store
        .calibration(row.calibration_id)
        .await?
        .map_or(0, |c| c.cameras as usize);
    match state.store.frame_particles(id, frame).await? {
        Some((_, blob, made_by)) => {
            Ok((cameras, codec::decode_particles(&blob, cameras)?, made_by))
        }
        None => Err(no_results(state, id, frame).await),
    }
}

/// Why a frame has no results: it is not processed yet (409), or it does
/// not exist (404).
pub(super) async fn no_results(state: &AppState, id: SequenceId, frame: FrameNumber) -> ApiError {
    match state.store.frame_exists(id, frame).await {
        Ok(true) => {
            ApiError::conflict(format!("frame {frame} is not processed (yet); see its job"))
        }
        Ok(false) => ApiError::not_found(format!("sequence {id} has no frame {frame}")),
        Err(error) => error.into(),
    }
}

/// A processed frame's 3D particles.
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/frames/{frame}/particles", tag = "sequences",
    params(
        ("id" = i64, Path, description = "Sequence id"),
        ("frame" = i64, Path, description = "Frame number", minimum = 0, maximum = 4_294_967_295_u64),
        ParticleQuery,
    ),
    responses(
        (status = 200, body = FrameParticles, description = "JSON; text/csv, text/plain (rt_is) or application/xml (vtk: ParaView's `.vtp`, an attachment) by `format`, the calibration that made them in the `Ptv-Calibration-Id` header",
            headers(("Ptv-Calibration-Id" = i64, description = "The calibration that made the particles"))),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not processed yet", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn frame_particles(
    State(state): Shared,
    ApiPath((id, frame)): ApiPath<(SequenceId, u32)>,
    ApiQuery(query): ApiQuery<ParticleQuery>,
) -> Result<Response, ApiError> {
    let frame = FrameNumber(frame.into());
    let (cameras, particles, made_by) = load_particles(&state, id, frame).await?;
    let provenance = [(CALIBRATION_HEADER, made_by.to_string())];
    Ok(match query.format {
        ParticleFormat::Json => {
            let (tracking_run, trajectories) =
                frame_trajectories(&state, id, frame, particles.len()).await?;
            Json(FrameParticles {
                sequence_id: id,
                frame,
                calibration_id: made_by,
                tracking_run,
                particles: particles
                    .iter()
                    .zip(trajectories)
                    .map(|(p, trajectory)| ParticleView {
                        x: p.position.x,
                        y: p.position.y,
                        z: p.position.z,
                        sigma: [p.sigma.x, p.sigma.y, p.sigma.z],
                        rms_px: p.rms_px,
                        targets: p.targets.clone(),
                        trajectory,
                    })
                    .collect(),
            })
            .into_response()
        }
        ParticleFormat::Csv => (
            [(header::CONTENT_TYPE, "text/csv")],
            provenance,
            formats::csv::format_particles(&particles, cameras),
        )
            .into_response(),
        ParticleFormat::RtIs => (
            [(header::CONTENT_TYPE, "text/plain; charset=utf-8")],
            provenance,
            formats::openptv::format_rt_is(&particles, cameras),
        )
            .into_response(),
        ParticleFormat::Vtk => {
            let (_, trajectories) = frame_trajectories(&state, id, frame, particles.len()).await?;
            let records = super::exports::particle_records(&particles, &trajectories);
            (
                provenance,
                super::exports::attachment(
                    super::exports::VTK_CONTENT_TYPE,
                    &format!("particles.{frame}.vtp"),
                    formats::vtk::particles_vtp(&records).into_bytes(),
                ),
            )
                .into_response()
        }
    })
}

/// How to write targets.
#[derive(Clone, Copy, Debug, Default, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum TargetFormat {
    /// JSON.
    #[default]
    Json,
    /// CSV `x,y,n,nx,ny,sumg` as `ptv detect` writes.
    Csv,
    /// OpenPTV's `_targets`.
    Openptv,
}

/// Query of the targets route.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct TargetQuery {
    /// The camera, from 0.
    pub camera: usize,
    /// json (default), csv or openptv.
    #[serde(default)]
    pub format: TargetFormat,
}

/// One target.
#[derive(Debug, Serialize, ToSchema)]
pub struct TargetView {
    /// Centroid x (px).
    pub x: f64,
    /// Centroid y (px).
    pub y: f64,
    /// Pixels.
    pub n: u32,
    /// Extent in x (px).
    pub nx: u32,
    /// Extent in y (px).
    pub ny: u32,
    /// Sum of grey values.
    pub sumg: u64,
}

/// A frame's targets in one camera.
#[derive(Debug, Serialize, ToSchema)]
pub struct FrameTargets {
    /// The frame.
    #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
    pub frame: FrameNumber,
    /// The camera.
    pub camera: usize,
    /// The targets, indexed as the particles' `targets` refer to them.
    pub targets: Vec<TargetView>,
}

/// A frame's targets in one camera (detected, or as uploaded).
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/frames/{frame}/targets", tag = "sequences",
    params(
        ("id" = i64, Path, description = "Sequence id"),
        ("frame" = i64, Path, description = "Frame number", minimum = 0, maximum = 4_294_967_295_u64),
        TargetQuery,
    ),
    responses(
        (status = 200, body = FrameTargets, description = "JSON; text/csv or text/plain (openptv) by `format`"),
        (status = 400, description = "No or bad camera", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not processed yet", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn frame_targets(
    State(state): Shared,
    ApiPath((id, frame)): ApiPath<(SequenceId, u32)>,
    ApiQuery(query): ApiQuery<TargetQuery>,
) -> Result<Response, ApiError> {
    let frame = FrameNumber(frame.into());
    sequence(&state, id).await?;
    let stored = state.store.frame_targets(id, frame).await?;
    if stored.is_empty() {
        return Err(no_results(&state, id, frame).await);
    }
    let (_, _, blob) = stored
        .iter()
        .find(|(camera, _, _)| *camera == query.camera as i64)
        .ok_or_else(|| {
            ApiError::not_found(format!(
                "camera {} does not exist; cameras are 0 to {}",
                query.camera,
                stored.len() - 1
            ))
        })?;
    let targets = codec::decode_targets(blob)?;
    Ok(match query.format {
        TargetFormat::Json => Json(FrameTargets {
            frame,
            camera: query.camera,
            targets: targets
                .iter()
                .map(|t| TargetView {
                    x: t.x,
                    y: t.y,
                    n: t.n,
                    nx: t.nx,
                    ny: t.ny,
                    sumg: t.sumg,
                })
                .collect(),
        })
        .into_response(),
        TargetFormat::Csv => (
            [(header::CONTENT_TYPE, "text/csv")],
            formats::csv::format_targets(&targets),
        )
            .into_response(),
        TargetFormat::Openptv => (
            [(header::CONTENT_TYPE, "text/plain; charset=utf-8")],
            formats::openptv::format_targets(&targets),
        )
            .into_response(),
    })
}

/// Query of the all-particles route.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct AllParticlesQuery {
    /// Only csv.
    #[serde(default)]
    pub format: Option<String>,
}

/// All processed frames' particles as one CSV with a `frame` column and
/// the calibration that made each frame's particles, streamed frame by
/// frame.
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/particles", tag = "sequences",
    params(("id" = i64, Path, description = "Sequence id"), AllParticlesQuery),
    responses(
        (status = 200, content_type = "text/csv", body = String, description = "frame,calibration_id,x,y,z,sx,sy,sz,rms_px,cameras,t0,...: calibration_id is the calibration that made the frame's particles"),
        (status = 400, body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn all_particles(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
    ApiQuery(query): ApiQuery<AllParticlesQuery>,
) -> Result<Response, ApiError> {
    if let Some(format) = query.format.as_deref().filter(|f| *f != "csv") {
        return Err(ApiError::bad_request(format!(
            "format `{format}`: all frames come only as csv"
        )));
    }
    let row = sequence(&state, id).await?;
    let cameras = state
        .store
        .calibration(row.calibration_id)
        .await?
        .map_or(0, |c| c.cameras as usize);
    let frames = state.store.processed_frames(id).await?;
    let header_line = {
        let mut line = String::from("frame,calibration_id,");
        line.push_str(formats::csv::format_particles(&[], cameras).trim_end());
        line.push('\n');
        line
    };
    let first = futures_util::stream::once(async move { Ok::<_, std::io::Error>(header_line) });
    let rest = futures_util::stream::unfold(
        (state, frames.into_iter()),
        move |(state, mut frames)| async move {
            let frame = frames.next()?;
            let chunk = match state.store.frame_particles(id, frame).await {
                Ok(Some((_, blob, made_by))) => match codec::decode_particles(&blob, cameras) {
                    Ok(particles) => Ok(frame_rows(frame, made_by, &particles, cameras)),
                    Err(e) => Err(std::io::Error::other(e)),
                },
                Ok(None) => Ok(String::new()),
                Err(e) => Err(std::io::Error::other(e)),
            };
            Some((chunk, (state, frames)))
        },
    );
    use futures_util::StreamExt as _;
    Ok((
        [(header::CONTENT_TYPE, "text/csv")],
        Body::from_stream(first.chain(rest)),
    )
        .into_response())
}

/// A frame's particle rows with the frame number and the calibration that
/// made them in front.
fn frame_rows(
    frame: FrameNumber,
    made_by: CalibrationId,
    particles: &[Particle],
    cameras: usize,
) -> String {
    let table = formats::csv::format_particles(particles, cameras);
    let mut out = String::with_capacity(table.len() + particles.len() * 12);
    for line in table.lines().skip(1) {
        out.push_str(&frame.to_string());
        out.push(',');
        out.push_str(&made_by.to_string());
        out.push(',');
        out.push_str(line);
        out.push('\n');
    }
    out
}
