//! The `process_frame` job: one uploaded frame's images decoded, its
//! targets detected and matched into particles with the sequence's
//! pipeline, within the job's time limit and memory need, its calibration
//! health measured; its results stored with the job's completion.

use super::attempt::{JobError, JobRun, TimeLimit};
use super::cache::Prepared;
use super::pipelines::{pipeline_of, sequence_parameters};
use super::pool::CpuError;
use crate::formats::{self, FormatError};
use crate::photogrammetry::correspond::{MatchError, Particle};
use crate::photogrammetry::health::FrameHealth;
use crate::photogrammetry::{Cancel, FramePipeline, PipelineError, SplitterError, Target};
use crate::service::infra::codec::{self, CameraTargets, DamagedBlob};
use crate::service::model::raw_layout::StoredRawLayout;
use crate::service::ops::health::{frame_health, rows_of};
use crate::service::ops::images::remove_unused_images;
use crate::service::ops::state::AppState;
use crate::service::store::{CameraImage, FrameInputKind, FrameNumber, SequenceId};
use serde::Deserialize;
use std::sync::Arc;

/// A process_frame job's payload.
#[derive(Debug, Deserialize)]
pub struct FramePayload {
    pub sequence_id: SequenceId,
    pub frame: FrameNumber,
}

/// Why a frame could not be processed.
#[derive(Debug, thiserror::Error)]
pub enum FrameError {
    /// An image does not decode.
    #[error(transparent)]
    Image(#[from] FormatError),
    /// Detection or matching refused the frame.
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    /// Matching refused the uploaded targets.
    #[error(transparent)]
    Matching(#[from] MatchError),
    /// The splitter's layout does not fit the frame's image.
    #[error(transparent)]
    Splitter(#[from] SplitterError),
    /// The uploaded targets' blob does not read.
    #[error(transparent)]
    StoredTargets(#[from] DamagedBlob),
    /// The work did not finish.
    #[error("processing {0}")]
    Cpu(#[from] CpuError),
}

/// A frame's results: its targets (encoded per camera, for images; none
/// for uploaded targets), particles and calibration health.
type FrameResults = (Vec<CameraTargets>, Vec<Particle>, FrameHealth);

/// The calibration health of a frame matched by `pipeline`
/// ([`crate::service::ops::health`]).
fn health_of(
    pipeline: &FramePipeline,
    targets: &[Vec<Target>],
    particles: &[Particle],
) -> FrameHealth {
    let matcher = pipeline.matcher();
    frame_health(
        matcher.cameras(),
        targets,
        particles,
        matcher.volume(),
        matcher.tolerance(),
    )
}

/// A frame's targets (encoded per camera, for images), particles and
/// calibration health (measured on the CPU pool with the matching). Images
/// are read, decoded and detected one camera at a time, keeping only their
/// targets, so a worker holds at most one compressed and one decoded image
/// at a time (with a splitter, the one image and its views); `size` keeps
/// the pixels and targets seen so far, for the time limit that `cancel`
/// carries.
async fn frame_work(
    state: &AppState,
    input: &crate::service::store::FrameInput,
    (pipeline, splitter): &Prepared,
    limit: &TimeLimit,
    cancel: &Cancel,
    size: &mut (u64, u64),
) -> Result<FrameResults, JobError> {
    let cameras = pipeline.cameras().len();
    let splitter = *splitter;
    if input.input == FrameInputKind::Images {
        let layout = match &input.raw_layout {
            None => None,
            Some(text) => serde_json::from_str::<StoredRawLayout>(text)
                .ok()
                .and_then(|l| l.layout())
                .map(Some)
                .ok_or_else(|| JobError::Failed(format!("malformed raw layout {text}")))?,
        };
        size.0 = pipeline
            .cameras()
            .iter()
            .map(|c| u64::from(c.sensor().width) * u64::from(c.sensor().height))
            .sum();
        cancel.set_limit(limit.for_work(size.0, 0));
        let images = state
            .store
            .frame_images(input.sequence_id, input.frame)
            .await?;
        let expected = if splitter.is_some() { 1 } else { cameras };
        if images.len() != expected {
            return Err(JobError::failed(PipelineError::ImageCount {
                images: images.len(),
                cameras: expected,
            }));
        }
        // The files are read all at once, concurrently, so that an object
        // store's latency per request (tens of ms) is paid once per frame
        // rather than once per camera; they are still decoded one at a
        // time, each dropped once detected.
        cancel.check().map_err(JobError::failed)?;
        let files = futures_util::future::try_join_all(images.iter().map(|image| {
            let camera = image.camera;
            async move {
                state
                    .images
                    .read(&image.sha256)
                    .await
                    .map_err(|e| JobError::image(&format!("the image of camera {camera}"), e))
            }
        }))
        .await?;
        let mut targets = Vec::with_capacity(cameras);
        for (index, (CameraImage { camera, .. }, bytes)) in
            images.into_iter().zip(files).enumerate()
        {
            cancel.check().map_err(JobError::failed)?;
            let (pipeline, work_cancel) = (pipeline.clone(), cancel.clone());
            let found = state
                .cpu
                .run_until(cancel, move || {
                    work_cancel.check().map_err(PipelineError::from)?;
                    let source = format!("cam{camera}");
                    let image = match &layout {
                        Some(layout) => formats::image::decode_raw(&bytes, layout, &source),
                        None => formats::image::decode_image(&bytes, &source),
                    }?;
                    drop(bytes);
                    let Some(splitter) = splitter else {
                        return Ok::<_, FrameError>(vec![pipeline.detect_camera(index, &image)?]);
                    };
                    let views = splitter.split(&image)?;
                    drop(image);
                    let mut found = Vec::with_capacity(views.len());
                    for (view, image) in views.iter().enumerate() {
                        work_cancel.check().map_err(PipelineError::from)?;
                        found.push(pipeline.detect_camera(view, image)?);
                    }
                    Ok(found)
                })
                .await
                .map_err(FrameError::from)
                .and_then(|r| r)
                .map_err(JobError::failed)?;
            size.1 += found.iter().map(|t| t.len() as u64).sum::<u64>();
            targets.extend(found);
        }
        cancel.set_limit(limit.for_work(size.0, size.1));
        let (pipeline, work_cancel) = (pipeline.clone(), cancel.clone());
        state
            .cpu
            .run_until(cancel, move || {
                let frame = pipeline.match_targets(targets, &work_cancel)?;
                let health = health_of(&pipeline, &frame.targets, &frame.particles);
                let targets = codec::encode_frame_targets(&frame.targets);
                Ok::<_, FrameError>((targets, frame.particles, health))
            })
            .await
            .map_err(FrameError::from)
            .and_then(|r| r)
            .map_err(JobError::failed)
    } else {
        let stored = state
            .store
            .frame_targets(input.sequence_id, input.frame)
            .await?;
        size.1 = stored
            .iter()
            .map(|t| u64::try_from(t.count).unwrap_or(0))
            .sum();
        cancel.set_limit(limit.for_work(0, size.1));
        let (pipeline, work_cancel) = (pipeline.clone(), cancel.clone());
        let (particles, health) = state
            .cpu
            .run_until(cancel, move || {
                let targets = stored
                    .iter()
                    .map(CameraTargets::decode)
                    .collect::<Result<Vec<_>, _>>()?;
                let particles = pipeline
                    .matcher()
                    .match_frame_until(&targets, &work_cancel)?;
                let health = health_of(&pipeline, &targets, &particles);
                Ok::<_, FrameError>((particles, health))
            })
            .await
            .map_err(FrameError::from)
            .and_then(|r| r)
            .map_err(JobError::failed)?;
        Ok((Vec::new(), particles, health))
    }
}

/// What a frame job needs of the memory budget
/// ([`crate::service::infra::budget::frame_need`]): its cameras' views detected one at a
/// time (none for uploaded targets) and their targets matched.
fn frame_need(
    input: &crate::service::store::FrameInput,
    (pipeline, splitter): &Prepared,
) -> crate::service::infra::budget::MemoryNeed {
    let views: Vec<(u32, u32)> = pipeline
        .cameras()
        .iter()
        .map(|c| (c.sensor().width, c.sensor().height))
        .collect();
    if input.input != FrameInputKind::Images {
        return crate::service::infra::budget::frame_need(&views, None, false);
    }
    let image = splitter.and_then(|s| views.first().and_then(|&(w, h)| s.image_size(w, h)));
    crate::service::infra::budget::frame_need(&views, image, true)
}

/// The process_frame job: the frame's images (or uploaded targets) to
/// particles, stored with the detected targets.
pub async fn process_frame(state: Arc<AppState>, run: JobRun) -> Result<(), JobError> {
    let payload: FramePayload = serde_json::from_str(&run.job.payload)
        .map_err(|e| JobError::Failed(format!("malformed payload: {e}")))?;
    let input = state
        .store
        .frame_input(payload.sequence_id, payload.frame)
        .await?
        .ok_or_else(|| JobError::Failed("the frame does not exist".to_owned()))?;
    if input.input == FrameInputKind::Images {
        let parameters = sequence_parameters(&state, input.sequence_id).await?;
        if let Some(computed) = &parameters.background {
            let calibration = state
                .store
                .calibration(input.calibration_id)
                .await?
                .ok_or_else(|| JobError::Failed("the sequence's calibration is gone".into()))?;
            let (cameras, splitter) = formats::calibration::stored_from_json_with_splitter(
                &calibration.model,
                "the stored calibration",
            )
            .map_err(JobError::failed)?;
            let sensors: Vec<(u32, u32)> = cameras
                .iter()
                .map(|c| (c.sensor().width, c.sensor().height))
                .collect();
            crate::service::ops::preprocessing::ensure_computed_background(
                &state,
                input.sequence_id,
                computed,
                &sensors,
                splitter,
            )
            .await?;
        }
    }
    let prepared = pipeline_of(&state, input.sequence_id, input.calibration_id).await?;
    let cameras = prepared.0.cameras().len();

    // The time limit follows the frame's size: its pixels from the start,
    // its targets once they are known.
    let limit = TimeLimit::of(&state.config.job_limits);
    let cancel = Cancel::new();
    let mut size = (0u64, 0u64);
    // The frame's memory, held from the budget while it is worked on (a
    // wait here does not count against its time limit).
    let grant = state.budget.acquire(&frame_need(&input, &prepared)).await?;
    let computed = frame_work(&state, &input, &prepared, &limit, &cancel, &mut size).await;
    drop(grant);
    let (targets, particles, health) = match computed {
        Ok(result) => result,
        Err(_) if cancel.is_stopped() || cancel.check().is_err() => {
            let (pixels, targets) = size;
            return Err(JobError::Failed(format!(
                "stopped after {:.1} s, past the frame's time limit of {}; not retried, as it \
                 would stop again",
                run.elapsed_s(),
                limit.describe(pixels, targets)
            )));
        }
        Err(error) => return Err(error),
    };

    let blob = codec::encode_particles(&particles, cameras);
    let keep_images = state
        .store
        .sequence(input.sequence_id)
        .await?
        .map_or(true, |s| s.keep_images);
    let released = state
        .store
        .complete_frame(
            &run.job,
            &input,
            &targets,
            ((particles.len() as i64, &blob), &rows_of(&health)),
            !keep_images,
            run.elapsed_s(),
        )
        .await?;
    state.metrics.particles(particles.len());
    remove_unused_images(&state.store, &state.images, &released).await;
    Ok(())
}
