//! Self-calibration of a sequence's calibration from its stored targets,
//! and reprocessing of its frames with another calibration (issue 14).
//!
//! - [`JobKind::SelfCalibrate`](crate::service::model::job_kind::JobKind::SelfCalibrate) ([`self_calibrate_job`]): the targets of the
//!   sequence's frames in the asked range, stored by their frame jobs
//!   (detected or uploaded), go through
//!   [`crate::photogrammetry::selfcal::self_calibrate`] (Wieneke 2008: match
//!   in a wide band, keep confident particles, bundle-adjust the cameras
//!   with the particles as unknowns, narrow the band) under a [`Cancel`]
//!   whose deadline is the job's time limit. A refined rig is stored as a
//!   new calibration naming its origin (`origin_calibration`) and carrying
//!   the self-calibration report, in the transaction that completes the
//!   job; with `reprocess`, the same transaction switches the sequence to
//!   it and enqueues its reprocess job. A diverged adjustment stores
//!   nothing: the job fails saying why, and the input calibration stays.
//! - [`JobKind::ReprocessSequence`](crate::service::model::job_kind::JobKind::ReprocessSequence) ([`reprocess_sequence`]): every processed frame
//!   whose particles another calibration made is matched again from its
//!   stored targets (no detection) with the sequence's pipeline for the new
//!   calibration, its particles replaced in one statement per frame (the
//!   old ones stay until then, and a job stopped midway resumes where it
//!   stopped: it picks frames by the calibration their particles name).
//!
//! Both take their memory from the process's budget
//! ([`crate::service::infra::budget::selfcal_need`] for all the frames' targets at once,
//! [`crate::service::infra::budget::reprocess_need`] for each frame in turn).

use std::sync::Arc;

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::formats;
use crate::service::infra::codec::{self, CameraTargets};
use crate::service::ops::jobs::attempt::{JobError, JobRun, TimeLimit};
use crate::service::ops::jobs::pipelines::{pipeline_of, sequence_parameters};
use crate::service::ops::state::AppState;
use crate::service::store::{
    CalibrationId, FrameNumber, RefinedCalibration, SequenceId, MAX_FRAME_NUMBER,
};

use crate::photogrammetry::selfcal::{self, Outcome, SelfCalibrationError, SelfCalibrationOptions};
use crate::photogrammetry::{Camera, CameraParameters, Cancel, Target, Volume};

/// Most frames one self-calibration reads (their targets are held in
/// memory together: 1,000 frames of 4 cameras x 10,000 targets is 1.6 GB).
pub const MAX_SELF_CALIBRATION_FRAMES: i64 = 1000;

/// A range of a sequence's frames, both ends included.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FrameSpan {
    /// The first frame.
    #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
    pub first: FrameNumber,
    /// The last frame.
    #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
    pub last: FrameNumber,
}

/// How to self-calibrate a sequence's calibration (all optional; the
/// defaults are `ptv selfcalibrate`'s).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct SelfCalibrationRequest {
    /// The frames whose targets are used [default: every frame with
    /// targets, at most 1,000].
    #[serde(default)]
    pub frames: Option<FrameSpan>,
    /// The first round's band (px): wide enough for the calibration's
    /// disparities [default: 4].
    #[serde(default)]
    pub tolerance: Option<f64>,
    /// The narrowest band (px), about 3-5 times the image noise [default:
    /// 0.5].
    #[serde(default)]
    pub final_tolerance: Option<f64>,
    /// The fewest cameras a confident particle is seen by [default: 3].
    #[serde(default)]
    pub min_cameras: Option<usize>,
    /// Parameters adjusted besides the exterior orientation, OpenPTV's
    /// names: xh,yh,c,k1,k2,k3,p1,p2,scx,she [default: none].
    #[serde(default)]
    pub free: Vec<String>,
    /// Most rounds (match, select, adjust) [default: 10].
    #[serde(default)]
    pub max_rounds: Option<usize>,
    /// Whether to switch the sequence to the refined calibration and
    /// reprocess its frames with it once it is stored [default: false].
    #[serde(default)]
    pub reprocess: bool,
}

/// Why a self-calibration or reprocess request cannot be queued.
#[derive(Debug, thiserror::Error)]
pub enum SelfCalibrationRequestError {
    /// An end of the range that is no frame number.
    #[error("frames.{field}: {frame} is not a frame number, 0 to {MAX_FRAME_NUMBER}")]
    FrameNumber {
        /// `first` or `last`.
        field: &'static str,
        /// The value given.
        frame: FrameNumber,
    },
    /// The range runs backwards.
    #[error("frames: the first frame ({first}) is after the last ({last}); give first <= last")]
    FrameOrder {
        /// The first frame.
        first: FrameNumber,
        /// The last frame.
        last: FrameNumber,
    },
    /// A name in `free` is not a parameter or media term the particles can
    /// adjust (the message names the choices).
    #[error("free: {0}")]
    UnknownParameter(String),
    /// The options do not pass the core's checks.
    #[error("options: {0}")]
    Options(#[from] SelfCalibrationError),
    /// No frame has targets to self-calibrate from.
    #[error(
        "sequence {sequence} has no frames{range} with targets of all {cameras} cameras; upload \
         frames and wait until their jobs have run (their targets are stored then), or widen \
         `frames`"
    )]
    NoTargets {
        /// The sequence.
        sequence: SequenceId,
        /// The range asked, as text.
        range: String,
        /// Its calibration's cameras.
        cameras: i64,
    },
    /// A reprocess calibration for another rig.
    #[error(
        "calibration: calibration {calibration} has {given} cameras, but sequence {sequence}'s \
         frames have {cameras}; give a calibration of the same rig (e.g. one self-calibrated \
         from it)"
    )]
    CameraCount {
        /// The calibration given.
        calibration: CalibrationId,
        /// Its cameras.
        given: i64,
        /// The sequence.
        sequence: SequenceId,
        /// The sequence's calibration's cameras.
        cameras: i64,
    },
    /// A reprocess calibration that does not exist.
    #[error("calibration: calibration {0} does not exist")]
    UnknownCalibration(CalibrationId),
}

impl SelfCalibrationRequest {
    /// The core's options for a rig of `cameras`, the band's volume the
    /// sequence's; checked as the core checks them.
    pub fn options(
        &self,
        cameras: &[CameraParameters],
        volume: Option<Volume>,
    ) -> Result<SelfCalibrationOptions, SelfCalibrationRequestError> {
        if let Some(span) = self.frames {
            for (field, frame) in [("first", span.first), ("last", span.last)] {
                if !(0..=MAX_FRAME_NUMBER).contains(&frame.0) {
                    return Err(SelfCalibrationRequestError::FrameNumber { field, frame });
                }
            }
            if span.first > span.last {
                return Err(SelfCalibrationRequestError::FrameOrder {
                    first: span.first,
                    last: span.last,
                });
            }
        }
        let mut defaults = SelfCalibrationOptions::default();
        for name in self.free.iter().filter(|n| !n.trim().is_empty()) {
            defaults
                .free(name)
                .map_err(SelfCalibrationRequestError::UnknownParameter)?;
        }
        let options = SelfCalibrationOptions {
            start_tolerance_px: self.tolerance.unwrap_or(defaults.start_tolerance_px),
            final_tolerance_px: self.final_tolerance.unwrap_or(defaults.final_tolerance_px),
            min_cameras: self.min_cameras.unwrap_or(defaults.min_cameras),
            max_rounds: self.max_rounds.unwrap_or(defaults.max_rounds),
            volume,
            ..defaults
        };
        // The core's checks, with one empty frame standing for the
        // sequence's (their count is checked when they are read).
        selfcal::check_inputs(cameras, &[vec![Vec::new(); cameras.len()]], &options)?;
        Ok(options)
    }

    /// The frames to read: the range asked, or every frame.
    pub fn span(&self) -> (FrameNumber, FrameNumber) {
        match self.frames {
            Some(span) => (span.first, span.last),
            None => (FrameNumber(0), FrameNumber(i64::MAX)),
        }
    }
}

/// A self_calibrate job's payload: checked when the request was taken.
#[derive(Debug, Serialize, Deserialize)]
pub struct SelfCalibrationPayload {
    /// The sequence whose targets are used.
    pub sequence_id: SequenceId,
    /// The calibration refined (the sequence's when the request came).
    pub calibration_id: CalibrationId,
    /// The request's options.
    pub options: SelfCalibrationRequest,
}

/// A reprocess job's payload.
#[derive(Debug, Deserialize)]
struct ReprocessPayload {
    sequence_id: SequenceId,
    calibration_id: CalibrationId,
}

/// Expected single-core time of one target in one self-calibration round
/// (ns): 10 frames x 2,000 particles in 4 cameras (80,000 targets) take
/// about 10 rounds in 10 s on 2 cores (issue 14's figure), 12.5 us a
/// target and round.
const NS_PER_TARGET_ROUND: f64 = 12_500.0;

/// The frames' targets, per frame and camera, in frame order.
async fn read_frames(
    state: &AppState,
    sequence_id: SequenceId,
    frames: &[FrameNumber],
) -> Result<Vec<Vec<Vec<Target>>>, JobError> {
    let mut out = Vec::with_capacity(frames.len());
    for &frame in frames {
        let stored = state.store.frame_targets(sequence_id, frame).await?;
        let cameras = stored
            .iter()
            .map(CameraTargets::decode)
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| JobError::Failed(format!("frame {frame}'s stored targets: {e}")))?;
        out.push(cameras);
    }
    Ok(out)
}

/// The self_calibrate job: the sequence's stored targets to a refined
/// calibration, stored with its origin and report (and, if asked, the
/// sequence switched to it and its reprocess job queued).
pub async fn self_calibrate_job(state: Arc<AppState>, run: JobRun) -> Result<(), JobError> {
    let payload: SelfCalibrationPayload = serde_json::from_str(&run.job.payload)
        .map_err(|e| JobError::Failed(format!("malformed payload: {e}")))?;
    let calibration = state
        .store
        .calibration(payload.calibration_id)
        .await?
        .ok_or_else(|| {
            JobError::Failed(format!(
                "calibration {} does not exist",
                payload.calibration_id
            ))
        })?;
    let (cameras, splitter) = formats::calibration::stored_from_json_with_splitter(
        &calibration.model,
        "the stored calibration",
    )
    .map_err(JobError::failed)?;
    let parameters: Vec<CameraParameters> =
        cameras.iter().map(|c| c.parameters().clone()).collect();
    let sequence_parameters = sequence_parameters(&state, payload.sequence_id).await?;
    let options = payload
        .options
        .options(&parameters, sequence_parameters.matching().volume)
        .map_err(JobError::failed)?;
    let mut frames = state
        .store
        .frames_with_targets(
            payload.sequence_id,
            payload.options.span(),
            calibration.cameras,
        )
        .await?;
    frames.truncate(MAX_SELF_CALIBRATION_FRAMES as usize);
    if frames.is_empty() {
        return Err(JobError::failed(SelfCalibrationRequestError::NoTargets {
            sequence: payload.sequence_id,
            range: range_text(payload.options.frames),
            cameras: calibration.cameras,
        }));
    }
    // The memory of every frame's targets and their adjustment, from the
    // stored counts, taken before the targets are read.
    let span = (frames[0], frames[frames.len() - 1]);
    let stored = state.store.target_count(payload.sequence_id, span).await?;
    let need = crate::service::infra::budget::selfcal_need(
        u64::try_from(stored).unwrap_or(0),
        parameters.len(),
        frames.len(),
    );
    let _grant = state.budget.acquire(&need).await?;
    let targets = read_frames(&state, payload.sequence_id, &frames).await?;
    let count: u64 = targets.iter().flatten().map(|t| t.len() as u64).sum();
    let limit = TimeLimit::of(&state.config.job_limits);
    let expected_ns = count as f64 * options.max_rounds as f64 * NS_PER_TARGET_ROUND;
    let cancel = Cancel::with_limit(limit.for_expected(expected_ns * 1e-9));
    let (work_cancel, sequence_id, job_id) = (cancel.clone(), payload.sequence_id, run.job.id);
    let result = state
        .cpu
        .run_until(&cancel, move || {
            selfcal::self_calibrate(&parameters, &targets, &options, &work_cancel, &mut |p| {
                if p.frames_matched == p.frames {
                    tracing::info!(
                        job = %job_id, sequence = %sequence_id, round = p.round + 1,
                        band_px = p.band_px, "self-calibration round matched"
                    );
                }
            })
        })
        .await
        .map_err(|e| JobError::Failed(format!("the self-calibration {e}")))?
        .map_err(JobError::failed)?;
    if result.report.outcome == Outcome::Diverged {
        return Err(JobError::Failed(format!(
            "the self-calibration diverged ({}); calibration {}, its input, is kept and no \
             calibration was stored",
            result
                .report
                .message
                .as_deref()
                .unwrap_or("no reason given"),
            payload.calibration_id
        )));
    }
    let refined = result
        .cameras
        .iter()
        .map(|p| Camera::new(p.clone()))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| JobError::Failed(format!("the refined calibration is not a rig: {e}")))?;
    let model = formats::calibration::to_json_with_splitter(&refined, splitter);
    // Stored only if it reads back (within the ranges real cameras have).
    formats::calibration::from_json_with_splitter(&model, "the refined calibration")
        .map_err(|e| JobError::Failed(format!("the refined calibration is not a rig: {e}")))?;
    let report = serde_json::to_string(&result.report)
        .map_err(|e| JobError::Failed(format!("the report did not serialise: {e}")))?;
    let (_, reprocess) = state
        .store
        .complete_self_calibration(
            &run.job,
            RefinedCalibration {
                model: &model,
                cameras: refined.len() as i64,
                report: &report,
                origin: payload.calibration_id,
            },
            payload.options.reprocess.then_some(payload.sequence_id),
            run.elapsed_s(),
        )
        .await?;
    if reprocess.is_some() {
        state.wake.notify_one();
    }
    Ok(())
}

/// `frames` as words for a message.
fn range_text(frames: Option<FrameSpan>) -> String {
    match frames {
        Some(span) => format!(" in {}..{}", span.first, span.last),
        None => String::new(),
    }
}

/// The reprocess_sequence job: each processed frame whose particles
/// another calibration made, matched again from its stored targets with
/// the job's calibration, its particles replaced frame by frame.
pub async fn reprocess_sequence(state: Arc<AppState>, run: JobRun) -> Result<(), JobError> {
    let payload: ReprocessPayload = serde_json::from_str(&run.job.payload)
        .map_err(|e| JobError::Failed(format!("malformed payload: {e}")))?;
    let (sequence_id, calibration_id) = (payload.sequence_id, payload.calibration_id);
    let limit = TimeLimit::of(&state.config.job_limits);
    let mut done = 0usize;
    // A second pass takes the frames whose jobs were running with the old
    // calibration when the sequence was switched, and completed since.
    for _ in 0..2 {
        let frames = state
            .store
            .frames_made_by_others(sequence_id, calibration_id)
            .await?;
        for frame in frames {
            let sequence = state.store.sequence(sequence_id).await?.ok_or_else(|| {
                JobError::Failed(format!("sequence {sequence_id} does not exist"))
            })?;
            if sequence.calibration_id != calibration_id {
                return Err(JobError::Failed(format!(
                    "sequence {sequence_id} was switched to calibration {} after {done} frames \
                     were reprocessed with calibration {calibration_id}; that calibration's \
                     reprocess job takes over",
                    sequence.calibration_id
                )));
            }
            let (pipeline, _) = pipeline_of(&state, sequence_id, calibration_id).await?;
            let cameras = pipeline.cameras().len();
            let stored = state.store.frame_targets(sequence_id, frame).await?;
            let count: u64 = stored
                .iter()
                .map(|t| u64::try_from(t.count).unwrap_or(0))
                .sum();
            // One frame's memory at a time, released before the next.
            let stored_bytes = stored.iter().map(|t| t.data.len() as u64).sum();
            let _grant = state
                .budget
                .acquire(&crate::service::infra::budget::reprocess_need(
                    frame.0,
                    count,
                    stored_bytes,
                ))
                .await?;
            let cancel = Cancel::with_limit(limit.for_work(0, count));
            let work_cancel = cancel.clone();
            let (particles, health) = state
                .cpu
                .run_until(&cancel, move || {
                    let targets = stored
                        .iter()
                        .map(CameraTargets::decode)
                        .collect::<Result<Vec<_>, _>>()
                        .map_err(|e| format!("its stored targets: {e}"))?;
                    let matcher = pipeline.matcher();
                    let particles = matcher
                        .match_frame_until(&targets, &work_cancel)
                        .map_err(|e| e.to_string())?;
                    let health = crate::service::ops::health::frame_health(
                        matcher.cameras(),
                        &targets,
                        &particles,
                        matcher.volume(),
                        matcher.tolerance(),
                    );
                    Ok::<_, String>((particles, health))
                })
                .await
                .map_err(|e| JobError::Failed(format!("reprocessing frame {frame}: {e}")))?
                .map_err(|e| JobError::Failed(format!("reprocessing frame {frame}: {e}")))?;
            let blob = codec::encode_particles(&particles, cameras);
            state
                .store
                .replace_particles(
                    &run.job,
                    (sequence_id, frame),
                    calibration_id,
                    (particles.len() as i64, &blob),
                    &crate::service::ops::health::rows_of(&health),
                )
                .await?;
            done += 1;
        }
    }
    let link = crate::service::ops::links::sequence(sequence_id);
    state
        .store
        .succeed(&run.job, &link, run.elapsed_s())
        .await?;
    Ok(())
}
