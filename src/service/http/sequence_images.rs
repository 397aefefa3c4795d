//! `/sequences/{id}/background` and `/sequences/{id}/mask`: the per-camera
//! images a sequence's detection uses (issue 13). A background is
//! subtracted from every frame of its camera before the high-pass filter
//! and the threshold (the remedy for static structure brighter than the
//! particles: windows, models, reflections); a mask's zero pixels are never
//! part of a target. Both come before the sequence's first frame, so every
//! frame is processed alike, and once: a sequence's images never change.
//! A background can also be computed by the service from the sequence's
//! own frames (`background` in `POST /sequences`, see
//! [`crate::service::model::parameters::ComputedBackground`]).

use std::sync::Arc;

use axum::extract::{Multipart, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::post;
use axum::{Json, Router};

use super::extract::Shared;
use super::frames::camera_of;
use super::problem::{ApiError, ApiMultipart, ApiPath};
use super::sequences::{sequence_cameras_and_row, view, SequenceView};
use super::upload::{check_images, or_drain, persist_and_commit, stream_part};
use crate::photogrammetry::Sensor;
use crate::service::ops::images::UploadedFile;
use crate::service::ops::links;
use crate::service::ops::state::AppState;
use crate::service::store::{NewSequenceImage, SequenceId, SequenceImageKind, SequenceImagesError};

pub(super) fn router() -> Router<Arc<AppState>> {
    Router::new()
        .route("/sequences/{id}/background", post(upload_background))
        .route("/sequences/{id}/mask", post(upload_mask))
}

impl From<SequenceImagesError> for ApiError {
    /// A sequence that has frames, or has this kind of image, is a 409.
    fn from(error: SequenceImagesError) -> Self {
        match error {
            SequenceImagesError::HasFrames(..) | SequenceImagesError::Exists(..) => {
                ApiError::conflict(error.to_string())
            }
            SequenceImagesError::Database(error) => error.into(),
        }
    }
}

/// Uploads the sequence's background: multipart `cam0`, `cam1`, ... (PNG
/// or TIFF of each camera's sensor size, of the bit depth its frames will
/// have), for any of the cameras. Before the first frame only.
#[utoipa::path(
    post, path = "/api/v1/sequences/{id}/background", tag = "sequences",
    params(("id" = i64, Path, description = "Sequence id")),
    request_body(content_type = "multipart/form-data", description = "Parts `cam0`..`camN-1`: the background of each camera given (PNG or TIFF, 8 or 16 bits, the camera's sensor size); cameras without one are detected without."),
    responses(
        (status = 201, body = SequenceView),
        (status = 400, description = "Malformed multipart, unknown or repeated part, no part", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such sequence", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, description = "The sequence has frames, a background already, or computes its background", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 415, description = "Not a greyscale PNG or TIFF that decodes (unknown, BigTIFF, colour, truncated, corrupt)", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 422, description = "Wrong size, or an image that does not decode", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn upload_background(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
    ApiMultipart(multipart): ApiMultipart,
) -> Result<Response, ApiError> {
    upload(state, id, SequenceImageKind::Background, multipart).await
}

/// Uploads the sequence's masks: multipart `cam0`, `cam1`, ... (PNG or
/// TIFF of each camera's sensor size, any bit depth; non-zero pixels are
/// used), for any of the cameras. Before the first frame only.
#[utoipa::path(
    post, path = "/api/v1/sequences/{id}/mask", tag = "sequences",
    params(("id" = i64, Path, description = "Sequence id")),
    request_body(content_type = "multipart/form-data", description = "Parts `cam0`..`camN-1`: the mask of each camera given (PNG or TIFF of the camera's sensor size; non-zero = use the pixel)."),
    responses(
        (status = 201, body = SequenceView),
        (status = 400, description = "Malformed multipart, unknown or repeated part, no part", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such sequence", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, description = "The sequence has frames or masks already", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 415, description = "Not a greyscale PNG or TIFF that decodes (unknown, BigTIFF, colour, truncated, corrupt)", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 422, description = "Wrong size, or an image that does not decode", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn upload_mask(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
    ApiMultipart(multipart): ApiMultipart,
) -> Result<Response, ApiError> {
    upload(state, id, SequenceImageKind::Mask, multipart).await
}

/// The one path of both uploads: read the `camC` parts into the image
/// store, check them against their cameras' sensors, then store them and
/// their rows, refused if the sequence has frames by then.
async fn upload(
    state: Arc<AppState>,
    id: SequenceId,
    kind: SequenceImageKind,
    mut multipart: Multipart,
) -> Result<Response, ApiError> {
    let checked = async {
        let rig = sequence_cameras_and_row(&state, id).await?;
        if kind == SequenceImageKind::Background && rig.row.parameters.background.is_some() {
            return Err(ApiError::conflict(format!(
                "sequence {id} computes its background from its frames (`background` when it \
                 was created); create a sequence without it to upload one"
            )));
        }
        Ok(rig.cameras)
    }
    .await;
    let cameras = or_drain(checked, &mut multipart).await?;
    let read = read_camera_parts(&state, kind, cameras.len(), &mut multipart).await;
    let files = or_drain(read, &mut multipart).await?;
    let (given, files): (Vec<usize>, Vec<UploadedFile>) = files
        .into_iter()
        .enumerate()
        .filter_map(|(camera, file)| file.map(|f| (camera, f)))
        .unzip();
    if files.is_empty() {
        return Err(ApiError::bad_request(format!(
            "no {kind} was given; send parts `cam0`..`cam{}`",
            cameras.len() - 1
        )));
    }
    let sensors: Vec<Sensor> = given.iter().map(|&c| cameras[c].sensor().clone()).collect();
    let names = given.clone();
    let headers = check_images(&files, &sensors, None, move |i| {
        format!("{kind} of cam{}", names[i])
    })
    .await?;
    let rows: Vec<NewSequenceImage> = given
        .iter()
        .zip(&files)
        .zip(&headers)
        .map(|((&camera, file), header)| NewSequenceImage {
            camera: camera as i64,
            sha256: file.sha256.clone(),
            size: file.size as i64,
            bits: i64::from(header.bit_depth.bits()),
        })
        .collect();
    persist_and_commit(&state, files, || {
        state.store.insert_sequence_images(id, kind, &rows)
    })
    .await?;
    let row = super::lookups::sequence(&state, id).await?;
    Ok((
        StatusCode::CREATED,
        [(header::LOCATION, links::sequence(id))],
        Json(view(&state, row).await?),
    )
        .into_response())
}

/// The `camC` parts of a background or mask upload, streamed into the
/// image store; per camera, the file if given.
async fn read_camera_parts(
    state: &AppState,
    kind: SequenceImageKind,
    n: usize,
    multipart: &mut Multipart,
) -> Result<Vec<Option<UploadedFile>>, ApiError> {
    let mut files: Vec<Option<UploadedFile>> = (0..n).map(|_| None).collect();
    while let Some(mut field) = multipart.next_field().await? {
        let name = field.name().unwrap_or("").to_owned();
        let Some(camera) = camera_of(&name, "cam", n) else {
            return Err(ApiError::bad_request(format!(
                "unknown part `{}`; a {kind} upload has parts `cam0`..`cam{}`",
                name.escape_debug(),
                n - 1
            )));
        };
        let camera = camera?;
        if files[camera].is_some() {
            return Err(ApiError::bad_request(format!(
                "part `{name}` is given twice"
            )));
        }
        files[camera] = Some(stream_part(&state.images, &mut field).await?);
    }
    Ok(files)
}
