//! A sequence's backgrounds and masks in its frame jobs (issue 13): loaded
//! from the image store into the frame pipeline
//! ([`FramePipeline::with_preprocessing`]), and a background computed from
//! the sequence's own first frames when its parameters ask for one
//! ([`ComputedBackground`]).
//!
//! A computed background is made by the first frame job that finds enough
//! frames uploaded: one camera at a time, it decodes the sequence's
//! `frames` lowest-numbered frames one at a time into that camera's
//! [`BackgroundBuilder`] (memory independent of the frame count and of
//! the number of cameras, taken from the memory budget first: see
//! [`ensure_computed_background`]) and stores the backgrounds as PNGs
//! with their rows; a cached pipeline made without them is then stale
//! ([`crate::service::ops::jobs::cache::PipelineCache`]). Until then frame jobs are deferred ([`JobError::Deferred`]): put
//! back uncounted, not claimed again for [`WAIT_FOR_BACKGROUND`], so other
//! sequences' frames go on. One worker of a process computes it, the
//! process's others defer; workers of two processes may compute it at
//! once: the first stored wins and the other's files go.

use std::sync::Arc;
use std::time::Duration;

use crate::formats;
use crate::formats::image::RawLayout;
use crate::photogrammetry::background::{BackgroundBuilder, BackgroundMode, DEFAULT_MEDIAN_SAMPLE};
use crate::photogrammetry::{FramePipeline, GreyImage, Mask, Preprocessing, Splitter};
use crate::service::infra::budget::{self, MemoryNeed};
use crate::service::model::parameters::ComputedBackground;
use crate::service::model::raw_layout::StoredRawLayout;
use crate::service::ops::jobs::attempt::JobError;
use crate::service::ops::state::AppState;
use crate::service::store::{
    CameraImage, FrameNumber, NewSequenceImage, SequenceId, SequenceImage, SequenceImageKind,
};

/// How long a frame job waiting for its sequence's background stays
/// unclaimed before it looks again.
pub const WAIT_FOR_BACKGROUND: Duration = Duration::from_secs(2);

/// `pipeline` with a sequence's stored backgrounds and masks (`stored`,
/// [`crate::service::store::Store::sequence_images`]), if it has any. A stored
/// image that no longer decodes, or does not fit its camera, fails the job
/// with the reason.
pub async fn with_stored_images(
    state: &AppState,
    stored: Vec<SequenceImage>,
    pipeline: FramePipeline,
) -> Result<FramePipeline, JobError> {
    if stored.is_empty() {
        return Ok(pipeline);
    }
    let cameras = pipeline.cameras().len();
    let mut files = Vec::with_capacity(stored.len());
    for image in stored {
        let bytes = state.images.read(&image.sha256).await.map_err(|e| {
            JobError::image(
                &format!("the sequence's {} of camera {}", image.kind, image.camera),
                e,
            )
        })?;
        files.push((image.kind, image.camera, bytes));
    }
    state
        .cpu
        .run(move || {
            let mut per_camera = vec![Preprocessing::default(); cameras];
            for (kind, camera, bytes) in files {
                let source = format!("the sequence's {kind} of camera {camera}");
                let slot = usize::try_from(camera)
                    .ok()
                    .and_then(|c| per_camera.get_mut(c))
                    .ok_or_else(|| {
                        JobError::Failed(format!("{source}: the calibration has {cameras} cameras"))
                    })?;
                let image =
                    formats::image::decode_image(&bytes, &source).map_err(JobError::failed)?;
                match kind {
                    SequenceImageKind::Background => slot.background = Some(image),
                    SequenceImageKind::Mask => slot.mask = Some(Mask::from_image(&image)),
                }
            }
            pipeline
                .with_preprocessing(per_camera)
                .map_err(JobError::failed)
        })
        .await
        .map_err(|e| JobError::Retry(format!("loading the sequence's backgrounds: {e}")))?
}

/// Makes sure the sequence's computed background exists: computes it if
/// enough frames have arrived, else defers the job. `sensors` are the
/// cameras' (width, height); with a `splitter`, each frame is one image of
/// every camera's view.
///
/// Streamed one camera at a time: for each camera, each frame's image is
/// read, decoded, cut to the camera's view, added to the camera's
/// [`BackgroundBuilder`] and dropped, and the camera's background is
/// written to the image store before the next camera starts. The most
/// held at once ([`computed_background_need`]) is the builder's kept
/// frames of one camera at their own sample width (at most
/// [`DEFAULT_MEDIAN_SAMPLE`] frames for a median, one for a minimum), one
/// decoded image and its view, the median and its PNG: for one
/// 8192x8192 16-bit camera, 32 x 128 MiB + 4 x 128 MiB = 4.5 GiB however
/// many cameras the sequence has (all cameras at once took 8.3 GiB for
/// two). The job takes that from the memory budget first
/// ([`crate::service::infra::budget`]). Where the budget is smaller, the
/// median keeps fewer frames, as many as fit
/// ([`budget::median_sample_within`]; 12 of 128 MiB in 2 GiB), and only a
/// budget below the least sample fails the job. With a splitter every
/// frame's image is decoded
/// once per camera, the price of holding one camera's frames only.
pub async fn ensure_computed_background(
    state: &Arc<AppState>,
    sequence_id: SequenceId,
    computed: &ComputedBackground,
    sensors: &[(u32, u32)],
    splitter: Option<Splitter>,
) -> Result<(), JobError> {
    let cameras = sensors.len();
    if has_background(state, sequence_id).await? {
        return Ok(());
    }
    let (frames, arrived) = state
        .store
        .image_frames(sequence_id, computed.frames)
        .await?;
    if arrived < i64::from(computed.frames) {
        return Err(JobError::Deferred(format!(
            "waiting for the sequence's background: it is computed from its first {} frames \
             and {arrived} have arrived",
            computed.frames
        )));
    }
    // One worker of this process computes it; the others wait (in
    // another process, another worker may compute it too: the first
    // stored wins).
    let Some(_computing) = state.computing.start(sequence_id) else {
        return Err(JobError::Deferred(
            "waiting for the sequence's background: another worker computes it".to_owned(),
        ));
    };
    let inputs = frame_files(state, sequence_id, frames).await?;
    let (need, sample) =
        computed_background_need(state, computed, sensors, splitter, &inputs).await?;
    let _grant = state.budget.acquire(&need).await?;
    // Another worker of this process may have computed it while this one
    // waited for the memory.
    if has_background(state, sequence_id).await? {
        return Ok(());
    }
    let mut files = Vec::new();
    for camera in 0..cameras {
        let from = (&inputs[..], splitter, sample);
        let Some((png, bits)) = camera_background(state, computed, camera, cameras, from).await?
        else {
            continue;
        };
        // Written out at once, so that only one camera's PNG is held.
        let mut upload = state.images.create_upload().await.map_err(io_error)?;
        upload.write(&png).await.map_err(io_error)?;
        drop(png);
        let file = upload.finish().await.map_err(io_error)?;
        files.push((camera as i64, file, bits));
    }
    store_backgrounds(state, sequence_id, files).await
}

/// Whether the sequence has a background (uploaded, or computed by any
/// worker).
async fn has_background(state: &AppState, sequence_id: SequenceId) -> Result<bool, JobError> {
    Ok(state
        .store
        .sequence_images(sequence_id)
        .await?
        .iter()
        .any(|i| i.kind == SequenceImageKind::Background))
}

/// Each frame's raw layout (if raw) and image files (names only).
async fn frame_files(
    state: &AppState,
    sequence_id: SequenceId,
    frames: Vec<FrameNumber>,
) -> Result<Vec<FrameFiles>, JobError> {
    let mut inputs = Vec::with_capacity(frames.len());
    for frame in frames {
        let input = state
            .store
            .frame_input(sequence_id, frame)
            .await?
            .ok_or_else(|| JobError::Retry(format!("frame {frame} went away")))?;
        let layout = match &input.raw_layout {
            None => None,
            Some(text) => Some(
                serde_json::from_str::<StoredRawLayout>(text)
                    .ok()
                    .and_then(|l| l.layout())
                    .ok_or_else(|| JobError::Failed(format!("malformed raw layout {text}")))?,
            ),
        };
        let images = state.store.frame_images(sequence_id, frame).await?;
        inputs.push((frame, layout, images));
    }
    Ok(inputs)
}

/// One camera's background from the frames' images (`from`: the frames'
/// files, the splitter, the most frames a median keeps), as a PNG and its
/// bits per sample; `None` where no frame has an image of the camera.
/// Each image is read, decoded, cut to the camera's view, added and
/// dropped before the next.
async fn camera_background(
    state: &AppState,
    computed: &ComputedBackground,
    camera: usize,
    cameras: usize,
    (inputs, splitter, sample): (&[FrameFiles], Option<Splitter>, usize),
) -> Result<Option<(Vec<u8>, i64)>, JobError> {
    let mut builder: Option<BackgroundBuilder> = None;
    for (frame, layout, images) in inputs {
        let (frame, layout) = (*frame, *layout);
        // With a splitter, the one image holds every camera's view.
        let image = images
            .iter()
            .find(|i| splitter.is_some() || usize::try_from(i.camera).ok() == Some(camera));
        let Some(CameraImage {
            camera: stored_camera,
            sha256,
            ..
        }) = image
        else {
            continue;
        };
        let stored_camera = *stored_camera;
        let bytes = state.images.read(sha256).await.map_err(|e| {
            JobError::image(
                &format!("the image of camera {stored_camera} of frame {frame}"),
                e,
            )
        })?;
        let taken = builder.take();
        let mode = computed.mode;
        let updated = state
            .cpu
            .run(move || {
                let source = format!("cam{stored_camera} of frame {frame}");
                let image = match &layout {
                    Some(layout) => formats::image::decode_raw(&bytes, layout, &source),
                    None => formats::image::decode_image(&bytes, &source),
                }
                .map_err(JobError::failed)?;
                drop(bytes);
                let view = match splitter {
                    Some(splitter) => splitter
                        .view(&image, camera)
                        .map_err(JobError::failed)?
                        .ok_or_else(|| {
                            JobError::Failed(format!(
                                "the calibration has {cameras} cameras but its splitter \
                                     `{}` cuts {} views",
                                splitter.name(),
                                splitter.views()
                            ))
                        })?,
                    None => image,
                };
                let mut builder = match taken {
                    Some(builder) => builder,
                    None => {
                        BackgroundBuilder::new(mode, view.width(), view.height(), view.bit_depth())
                            .with_sample_limit(sample)
                            .map_err(JobError::failed)?
                    }
                };
                builder.add(&view).map_err(|e| {
                    JobError::Failed(format!("computing the background from {source}: {e}"))
                })?;
                Ok::<_, JobError>(builder)
            })
            .await
            .map_err(|e| JobError::Retry(format!("computing the background: {e}")))??;
        builder = Some(updated);
    }
    let Some(builder) = builder else {
        return Ok(None);
    };
    let png_and_bits = state
        .cpu
        .run(move || {
            let background: GreyImage = builder.finish().map_err(JobError::failed)?;
            let bits = i64::from(background.bit_depth().bits());
            let source = format!("the background of camera {camera}");
            let png = formats::image::encode_png(&background, &source).map_err(JobError::failed)?;
            Ok::<_, JobError>((png, bits))
        })
        .await
        .map_err(|e| JobError::Retry(format!("computing the background: {e}")))??;
    Ok(Some(png_and_bits))
}

/// A frame's number, raw layout (if raw) and (camera, SHA-256) of its
/// image files.
type FrameFiles = (FrameNumber, Option<RawLayout>, Vec<CameraImage>);

/// What computing a sequence's background needs at most (see
/// [`ensure_computed_background`], [`budget::background_bytes`]):
/// its largest camera's kept frames at the depth of the first frame's
/// images (read to see their headers; frames of another depth are
/// refused by the builder), one decoded image and its view, the median,
/// its PNG, and the first frame's largest file.
async fn computed_background_need(
    state: &AppState,
    computed: &ComputedBackground,
    sensors: &[(u32, u32)],
    splitter: Option<Splitter>,
    inputs: &[FrameFiles],
) -> Result<(MemoryNeed, usize), JobError> {
    let mut sample_bytes = 1;
    let mut compressed = 0u64;
    if let Some((frame, layout, images)) = inputs.first() {
        for CameraImage { camera, sha256, .. } in images {
            let bytes = state.images.read(sha256).await.map_err(|e| {
                JobError::image(&format!("the image of camera {camera} of frame {frame}"), e)
            })?;
            compressed = compressed.max(bytes.len() as u64);
            let source = format!("cam{camera} of frame {frame}");
            let header = match layout {
                Some(layout) => formats::image::probe_raw(bytes.len() as u64, layout, &source),
                None => formats::image::probe_image(std::io::Cursor::new(&bytes), &source),
            }
            .map_err(JobError::failed)?;
            sample_bytes = sample_bytes.max(if header.bit_depth.bits() > 8 { 2 } else { 1 });
        }
    }
    let view = sensors
        .iter()
        .map(|&(w, h)| u64::from(w) * u64::from(h))
        .max()
        .unwrap_or(0);
    let image = match splitter {
        Some(splitter) => sensors
            .iter()
            .filter_map(|&(w, h)| splitter.image_size(w, h))
            .map(|(w, h)| u64::from(w) * u64::from(h))
            .max()
            .unwrap_or(0),
        None => view,
    };
    let frames = inputs.len() as u64;
    let (kept, sample) = match computed.mode {
        BackgroundMode::Median => {
            // As many frames as the budget holds, up to the default.
            let budget = state.budget.total_mib().saturating_mul(budget::MIB);
            let sample = budget::median_sample_within(
                budget,
                DEFAULT_MEDIAN_SAMPLE as u64,
                frames,
                view,
                image,
                sample_bytes,
                compressed,
            )
            // Not even the least sample fits: the need of that sample,
            // which the budget refuses with the reason.
            .unwrap_or(budget::LEAST_MEDIAN_SAMPLE);
            (frames.min(sample), sample)
        }
        BackgroundMode::Min => (frames.min(1), DEFAULT_MEDIAN_SAMPLE as u64),
    };
    let bytes = budget::background_bytes(kept, view, image, sample_bytes, compressed);
    let need = MemoryNeed::new(
        bytes,
        format!(
            "the {} background of {} camera(s) of up to {view} pixels at {} bits, one camera \
             at a time, {kept} frames kept",
            match computed.mode {
                BackgroundMode::Median => "median",
                BackgroundMode::Min => "minimum",
            },
            sensors.len(),
            sample_bytes * 8,
        ),
    );
    Ok((need, sample as usize))
}

/// Stores computed backgrounds (camera, written file, bits) in the image
/// store and their rows, under the store's lock; files that end up unused
/// (a background stored meanwhile by another worker) go again.
async fn store_backgrounds(
    state: &AppState,
    sequence_id: SequenceId,
    backgrounds: Vec<(i64, crate::service::ops::images::UploadedFile, i64)>,
) -> Result<(), JobError> {
    let mut files = Vec::with_capacity(backgrounds.len());
    let mut rows = Vec::with_capacity(backgrounds.len());
    for (camera, file, bits) in backgrounds {
        rows.push(NewSequenceImage {
            camera,
            sha256: file.sha256.clone(),
            size: file.size as i64,
            bits,
        });
        files.push(file);
    }
    for file in &files {
        state
            .images
            .stage(file)
            .await
            .map_err(|e| JobError::image("a background", e))?;
    }
    let _guard = state.images.lock(&state.store).await?;
    for file in files {
        state
            .images
            .persist(file)
            .await
            .map_err(|e| JobError::image("a background", e))?;
    }
    let orphans = state
        .store
        .insert_computed_background(sequence_id, &rows)
        .await?;
    for hash in orphans {
        if let Err(error) = state.images.remove(&hash).await {
            tracing::warn!(%error, hash, "cannot delete an unused background file");
        }
    }
    Ok(())
}

/// An image store error as a job error: a full disk waits for space,
/// anything else is tried again.
fn io_error(error: std::io::Error) -> JobError {
    if crate::service::infra::errors::is_storage_full(&error) {
        JobError::StorageFull(format!("the disk is full; waiting for space: {error}"))
    } else {
        JobError::Retry(format!("the image store: {error}"))
    }
}
