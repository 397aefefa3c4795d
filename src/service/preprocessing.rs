//! A sequence's backgrounds and masks in its frame jobs (issue 13): loaded
//! from the image store into the frame pipeline
//! ([`FramePipeline::with_preprocessing`]), and a background computed from
//! the sequence's own first frames when its parameters ask for one
//! ([`ComputedBackground`]).
//!
//! A computed background is made by the first frame job that finds enough
//! frames uploaded: it decodes the sequence's `frames` lowest-numbered
//! frames one at a time into a [`BackgroundBuilder`] per camera (memory
//! independent of the frame count) and stores the backgrounds as PNGs with
//! their rows; a cached pipeline made without them is then stale
//! ([`super::jobs::PipelineCache`]). Until then frame jobs are deferred ([`JobError::Deferred`]): put
//! back uncounted, not claimed again for [`WAIT_FOR_BACKGROUND`], so other
//! sequences' frames go on. Two workers may compute it at once; the first
//! stored wins and the other's files go.

use std::sync::Arc;
use std::time::Duration;

use super::app::AppState;
use super::jobs::{JobError, StoredRawLayout};
use super::parameters::ComputedBackground;
use super::store::{SequenceId, SequenceImage, SequenceImageKind};
use crate::formats;
use crate::photogrammetry::background::BackgroundBuilder;
use crate::photogrammetry::{FramePipeline, GreyImage, Mask, Preprocessing, Splitter};

/// How long a frame job waiting for its sequence's background stays
/// unclaimed before it looks again.
pub const WAIT_FOR_BACKGROUND: Duration = Duration::from_secs(2);

/// `pipeline` with a sequence's stored backgrounds and masks (`stored`,
/// [`super::store::Store::sequence_images`]), if it has any. A stored
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
/// enough frames have arrived, else defers the job.
pub async fn ensure_computed_background(
    state: &Arc<AppState>,
    sequence_id: SequenceId,
    computed: &ComputedBackground,
    cameras: usize,
    splitter: Option<Splitter>,
) -> Result<(), JobError> {
    let stored = state.store.sequence_images(sequence_id).await?;
    if stored
        .iter()
        .any(|i| i.kind == SequenceImageKind::Background)
    {
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
    let mut builders: Vec<Option<BackgroundBuilder>> = (0..cameras).map(|_| None).collect();
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
        for (camera, sha256) in state.store.frame_images(sequence_id, frame).await? {
            let bytes = state.images.read(&sha256).await.map_err(|e| {
                JobError::image(&format!("the image of camera {camera} of frame {frame}"), e)
            })?;
            let Some(slot) = usize::try_from(camera).ok().filter(|&c| c < cameras) else {
                continue;
            };
            // With a splitter, the one image holds every camera's view.
            let slots = if splitter.is_some() {
                0..cameras
            } else {
                slot..slot + 1
            };
            let taken: Vec<Option<BackgroundBuilder>> =
                slots.clone().map(|c| builders[c].take()).collect();
            let mode = computed.mode;
            let updated = state
                .cpu
                .run(move || {
                    let source = format!("cam{camera} of frame {frame}");
                    let image = match &layout {
                        Some(layout) => formats::image::decode_raw(&bytes, layout, &source),
                        None => formats::image::decode_image(&bytes, &source),
                    }
                    .map_err(JobError::failed)?;
                    let views = match splitter {
                        Some(splitter) => splitter.split(&image).map_err(JobError::failed)?,
                        None => vec![image],
                    };
                    views
                        .iter()
                        .zip(taken)
                        .map(|(view, builder)| {
                            let mut builder = builder.unwrap_or_else(|| {
                                BackgroundBuilder::new(
                                    mode,
                                    view.width(),
                                    view.height(),
                                    view.bit_depth(),
                                )
                            });
                            builder.add(view).map_err(|e| {
                                JobError::Failed(format!(
                                    "computing the background from {source}: {e}"
                                ))
                            })?;
                            Ok(builder)
                        })
                        .collect::<Result<Vec<_>, JobError>>()
                })
                .await
                .map_err(|e| JobError::Retry(format!("computing the background: {e}")))??;
            for (c, builder) in slots.zip(updated) {
                builders[c] = Some(builder);
            }
        }
    }
    let mut rows = Vec::new();
    for (camera, builder) in builders.into_iter().enumerate() {
        let Some(builder) = builder else { continue };
        let png = state
            .cpu
            .run(move || {
                let background: GreyImage = builder.finish().map_err(JobError::failed)?;
                let bits = i64::from(background.bit_depth().bits());
                let source = format!("the background of camera {camera}");
                let png =
                    formats::image::encode_png(&background, &source).map_err(JobError::failed)?;
                Ok::<_, JobError>((png, bits))
            })
            .await
            .map_err(|e| JobError::Retry(format!("computing the background: {e}")))??;
        rows.push((camera as i64, png));
    }
    store_backgrounds(state, sequence_id, rows).await
}

/// Writes computed backgrounds (camera, (PNG, bits)) into the image store
/// and their rows, under the store's lock; files that end up unused (a
/// background stored meanwhile by another worker) go again.
async fn store_backgrounds(
    state: &AppState,
    sequence_id: SequenceId,
    backgrounds: Vec<(i64, (Vec<u8>, i64))>,
) -> Result<(), JobError> {
    let mut files = Vec::with_capacity(backgrounds.len());
    let mut rows = Vec::with_capacity(backgrounds.len());
    for (camera, (png, bits)) in backgrounds {
        let mut upload = state.images.create_upload().await.map_err(io_error)?;
        upload.write(&png).await.map_err(io_error)?;
        let file = upload.finish().await.map_err(io_error)?;
        rows.push((camera, file.sha256.clone(), file.size as i64, bits));
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
    if super::images::is_storage_full(&error) {
        JobError::StorageFull(format!("the disk is full; waiting for space: {error}"))
    } else {
        JobError::Retry(format!("the image store: {error}"))
    }
}
