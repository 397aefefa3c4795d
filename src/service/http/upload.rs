//! The one multipart upload path, shared by frame uploads
//! (`POST /sequences/{id}/frames`) and calibration solving
//! (`POST /calibrations/solve`):
//!
//! 1. read the parts ([`text_part`] for small text parts read whole,
//!    [`stream_part`] for files streamed into the image store, never whole
//!    in memory), draining the body when reading fails ([`or_drain`]);
//! 2. check the images' headers against their cameras' sensors, then
//!    check that each image decodes, one at a time, so that a truncated or
//!    corrupt file is refused now rather than failing its job later
//!    ([`check_images`], on the blocking pool: it reads the files; a
//!    1280x1024 8-bit PNG decodes in under 20 ms, a TIFF of LZW strips is
//!    checked without being decoded, and an upload of four 8192x8192 PNGs
//!    of a dark field was answered in 175 ms);
//! 3. stage the files (S3: put them), then persist them and commit the
//!    rows that refer to them under the image store's lock, removing the files again if the commit fails
//!    ([`persist_and_commit`]), so that a failed request leaves no file
//!    and a crash at any instant at most files no row refers to, which the
//!    start-up sweep removes;
//! 4. wake a worker and answer 202 with the job ([`accepted`]).

use std::future::Future;
use std::path::{Path, PathBuf};

use axum::extract::multipart::Field;
use axum::extract::Multipart;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use futures_util::future::try_join_all;
use serde::Serialize;

use super::problem::ApiError;
use crate::formats::image::{check_image, read_header, ImageHeader, RawLayout};
use crate::photogrammetry::{Sensor, SensorMismatch};
use crate::service::ops::images::{ImageStore, UploadedFile};
use crate::service::ops::links;
use crate::service::ops::state::AppState;
use crate::service::store::JobId;

/// Reads a small text part whole, up to `limit` bytes.
pub async fn text_part(
    field: &mut Field<'_>,
    name: &str,
    limit: usize,
) -> Result<String, ApiError> {
    let mut bytes = Vec::new();
    while let Some(chunk) = field.chunk().await? {
        if bytes.len() + chunk.len() > limit {
            return Err(ApiError::too_large(format!(
                "part `{name}` is larger than {limit} bytes"
            )));
        }
        bytes.extend_from_slice(&chunk);
    }
    String::from_utf8(bytes)
        .map_err(|_| ApiError::unprocessable(format!("part `{name}` is not UTF-8 text")))
}

/// Streams a part into a temporary file of the image store, hashed as it
/// is written; the body limit bounds it.
pub async fn stream_part(
    images: &ImageStore,
    field: &mut Field<'_>,
) -> Result<UploadedFile, ApiError> {
    let mut upload = images.create_upload().await?;
    while let Some(chunk) = field.chunk().await? {
        upload.write(&chunk).await?;
    }
    Ok(upload.finish().await?)
}

/// `read` (the parts as read, or anything decided before the body is
/// read); when it failed, the rest of the body is read and dropped first
/// (bounded by the body limit), so that the client, still sending, gets
/// the answer rather than a broken pipe.
pub async fn or_drain<T>(
    read: Result<T, ApiError>,
    multipart: &mut Multipart,
) -> Result<T, ApiError> {
    if read.is_err() {
        while let Ok(Some(mut field)) = multipart.next_field().await {
            while let Ok(Some(_)) = field.chunk().await {}
        }
    }
    read
}

/// Checks uploaded images, one per camera in camera order: first every
/// header (PNG or TIFF greyscale of its camera's sensor size; raw: the
/// length `raw` needs, which is all a raw buffer can be checked for), then
/// every PNG or TIFF checked to decode ([`check_image`]: plain TIFF strips
/// without decoding them, the rest decoded one at a time and dropped at
/// once, at most one decoded image per request in memory), so that a
/// truncated file or a TIFF whose strips point outside it is refused here. `source(camera)`
/// names an image in messages. Files that are not a greyscale PNG or TIFF
/// this program can decode (unknown, BigTIFF, colour, truncated, corrupt)
/// are 415 whichever step finds it, wrong sizes 422. Returns the headers,
/// in the files' order.
pub async fn check_images(
    files: &[UploadedFile],
    sensors: &[Sensor],
    raw: Option<RawLayout>,
    source: impl Fn(usize) -> String + Send + 'static,
) -> Result<Vec<ImageHeader>, ApiError> {
    let checks: Vec<(PathBuf, Sensor)> = files
        .iter()
        .zip(sensors)
        .map(|(file, sensor)| {
            let path = file.temp_path().map(Path::to_owned).unwrap_or_default();
            (path, sensor.clone())
        })
        .collect();
    // At most one check per core decodes at a time, whatever the uploads
    // in flight: each holds one decoded image (128 MiB at the largest
    // sensor).
    let _permit = decode_permits()
        .acquire()
        .await
        .map_err(ApiError::internal)?;
    tokio::task::spawn_blocking(move || {
        let mut headers = Vec::with_capacity(checks.len());
        for (camera, (path, sensor)) in checks.iter().enumerate() {
            let source = source(camera);
            let header = read_header(path, raw.as_ref(), &source)?;
            SensorMismatch::check(header.width, header.height, sensor)
                .map_err(|e| ApiError::from(e).at(&source))?;
            headers.push(header);
        }
        if raw.is_none() {
            for (camera, (path, _)) in checks.iter().enumerate() {
                let source = source(camera);
                let bytes = std::fs::read(path).map_err(ApiError::internal)?;
                check_image(&bytes, &source)?;
            }
        }
        Ok::<_, ApiError>(headers)
    })
    .await?
}

/// The permits of [`check_images`]' decoding: one per core.
fn decode_permits() -> &'static tokio::sync::Semaphore {
    static PERMITS: std::sync::OnceLock<tokio::sync::Semaphore> = std::sync::OnceLock::new();
    PERMITS.get_or_init(|| {
        let cores = std::thread::available_parallelism().map_or(1, usize::from);
        tokio::sync::Semaphore::new(cores)
    })
}

/// Moves the request's files into the image store and runs `commit`, which
/// stores the rows that refer to them, under the store's lock. If either
/// fails, the files that no row refers to go again.
pub async fn persist_and_commit<T, E, F, Fut>(
    state: &AppState,
    files: Vec<UploadedFile>,
    commit: F,
) -> Result<T, ApiError>
where
    F: FnOnce() -> Fut,
    Fut: Future<Output = Result<T, E>>,
    ApiError: From<E>,
{
    // Staged (put to S3) before the lock, so that uploads' transfers run in
    // parallel; see `service::images` for why this is safe. A request's
    // files go at once, as do their checks under the lock: an object
    // store's latency is paid once per request, not once per file.
    try_join_all(files.iter().map(|file| state.images.stage(file))).await?;
    let _guard = state.images.lock(&state.store).await?;
    let hashes: Vec<String> = files.iter().map(|f| f.sha256.clone()).collect();
    let committed = async {
        try_join_all(files.into_iter().map(|file| state.images.persist(file))).await?;
        Ok::<T, ApiError>(commit().await?)
    }
    .await;
    if committed.is_err() {
        for hash in &hashes {
            if !state.store.image_in_use(hash).await? {
                state.images.remove(hash).await?;
            }
        }
    }
    committed
}

/// Wakes a worker for the job just enqueued and answers 202 with `body`,
/// its `Location` the job.
pub fn accepted(state: &AppState, job_id: JobId, body: impl Serialize) -> Response {
    state.wake.notify_one();
    (
        StatusCode::ACCEPTED,
        [(header::LOCATION, links::job(job_id))],
        Json(body),
    )
        .into_response()
}
