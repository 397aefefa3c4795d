//! `/sequences/{id}/frames`: a sequence's frames. Upload one (images, or
//! targets detected on the camera side: the multipart parts, the targets
//! part parsed as it arrives, the background depth checks), or list them
//! a page at a time.

use std::sync::Arc;

use axum::extract::multipart::Field;
use axum::extract::Multipart;
use axum::extract::State;
use axum::response::Response;
use axum::routing::post;
use axum::{Json, Router};
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::decimal;
use super::extract::Shared;
use super::lookups::sequence;
use super::problem::{ApiError, ApiMultipart, ApiPath, ApiQuery};
use super::sequences::{sequence_cameras_and_row, SequenceRig};
use super::upload::{accepted, check_images, or_drain, persist_and_commit, stream_part, text_part};
use crate::formats::image::ImageHeader;
use crate::formats::targets::TargetsReader;
use crate::photogrammetry::correspond::{max_targets, MAX_TARGETS_PER_CAMERA};
use crate::photogrammetry::{Camera, Sensor, Splitter, Target};
use crate::service::infra::codec;
use crate::service::model::raw_layout::StoredRawLayout;
use crate::service::ops::events::Change;
use crate::service::ops::events::JobStateView;
use crate::service::ops::images::UploadedFile;
use crate::service::ops::links;
use crate::service::ops::state::AppState;
use crate::service::store::{
    CameraImage, FrameInputKind, FrameNumber, InsertFrameError, JobId, NewFrame, SequenceId,
    SequenceImageKind,
};

/// Largest targets part (bytes). The part is parsed as it arrives
/// ([`TargetsReader`]), so this bounds the work, not the memory: a part
/// holds at most one batch of its text ([`TARGETS_BATCH`], 1 MiB, plus
/// one chunk), the reader's pending text (a slice of 64 KiB, or one
/// record of at most 1 MiB) and its targets, at most `max_targets` of its camera's sensor
/// (40 bytes each, twice that while their vector grows: 80 MiB at the
/// largest sensors' 2^20).
const MAX_TARGETS_PART: usize = 64 << 20;

pub(super) fn router() -> Router<Arc<AppState>> {
    Router::new().route("/sequences/{id}/frames", post(upload_frame).get(frames))
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
        new_frame.images = vec![CameraImage {
            camera: 0,
            sha256: whole.sha256.clone(),
            size: whole.size as i64,
        }];
    } else if !images.is_empty() {
        let sensors: Vec<Sensor> = cameras.iter().map(|c| c.sensor().clone()).collect();
        let layout = raw.as_ref().and_then(StoredRawLayout::layout);
        let headers =
            check_images(&images, &sensors, layout, |camera| format!("cam{camera}")).await?;
        check_background_depths(&state, id, &headers).await?;
        new_frame.images = images
            .iter()
            .enumerate()
            .map(|(camera, f)| CameraImage {
                camera: camera as i64,
                sha256: f.sha256.clone(),
                size: f.size as i64,
            })
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
