//! The durable job queue's workers.
//!
//! Jobs are rows of the `jobs` table ([`Store`]): enqueued in the same
//! transaction as what they work on, claimed with a lease (`UPDATE ...
//! RETURNING` in one write transaction; see the store's `jobs` module),
//! and completed in the same transaction that stores their results,
//! fenced by the claim's token, so a job's results exist exactly once.
//! Each kind of job is a [`JobKind`]; a worker parses the claimed row's
//! kind and runs its function by `match` (a kind this release does not
//! know fails the job with a message).
//!
//! Workers are async tasks, one per `--workers`, in `ptv serve` or in any
//! number of `ptv worker` processes on the same data directory. Each
//! claims a job, renews its lease by heartbeat every third of
//! `--lease-secs` while the attempt runs, reads its inputs (all in the
//! database and the image directory: nothing of the serving process),
//! and hands the CPU work to [`CpuPool`] (a rayon pool of the same size),
//! never computing on the async runtime's threads. Before its work, a
//! frame, background or calibration job takes the memory it declares
//! from the process's budget ([`crate::service::infra::budget`]), waiting its turn with
//! its lease renewed. An idle worker polls
//! the queue (a read) with a backoff from [`IDLE_POLL_MIN`] to
//! [`IDLE_POLL_MAX`]; in `ptv serve` an upload also wakes it at once.
//! A killed, hung or cut-off worker stops renewing: once its lease has
//! run out the next claim anywhere queues the job again (or fails it
//! once it was claimed [`MAX_ATTEMPTS`] times), and the late worker's
//! completion, if it ever comes, is fenced out and dropped. At start-up
//! the reaper ([`Store::reap`]) ends at once the leases of processes of
//! this host that no longer exist.
//!
//! Kinds today: [`JobKind::ProcessFrame`] ([`process_frame`]),
//! [`JobKind::SolveCalibration`] ([`solve_calibration`]: calibration by resection
//! from the files of a `/calibrations/solve` request, kept in the image
//! store and listed in `job_files`), and in [`crate::service::ops::selfcal`]
//! `self_calibrate` (a sequence's calibration refined from its stored
//! targets) and `reprocess_sequence` (its frames matched again with
//! another calibration).

use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Deserialize;
use tokio::sync::watch;

pub mod attempt;
pub mod cache;
pub mod pipelines;
pub mod pool;

use self::attempt::{JobError, JobRun, TimeLimit, STORAGE_FULL_PAUSE, UNAVAILABLE_PAUSE};
use self::cache::Prepared;
use self::pipelines::{pipeline_of, sequence_parameters};
use self::pool::CpuError;
use crate::formats::control::{self, OptionError};
use crate::formats::{self, FormatError};
use crate::photogrammetry::calibrate::{self, CalibrationError};
use crate::photogrammetry::correspond::{MatchError, Particle};
use crate::photogrammetry::{Cancel, InvalidDetectionParameters, PipelineError, SplitterError};
use crate::service::infra::codec;
use crate::service::infra::codec::DamagedBlob;
use crate::service::model::job_kind::JobKind;
use crate::service::model::parameters::SolveOptions;
use crate::service::model::raw_layout::StoredRawLayout;
use crate::service::ops::selfcal;
use crate::service::ops::state::AppState;
use crate::service::store::{
    ClaimedJob, CompleteError, FrameInputKind, FrameNumber, JobFile, SequenceId, Store,
    MAX_ATTEMPTS,
};

/// Runs `workers` workers until `shutdown` turns true; each finishes its
/// running job first.
pub fn spawn_workers(
    state: Arc<AppState>,
    workers: usize,
    shutdown: watch::Receiver<bool>,
) -> tokio::task::JoinSet<()> {
    let mut set = tokio::task::JoinSet::new();
    for index in 0..workers {
        let worker = format!("{}/{index}", state.instance);
        set.spawn(worker_loop(state.clone(), worker, shutdown.clone()));
    }
    set
}

/// The shortest wait of an idle worker before it looks at the queue again.
pub const IDLE_POLL_MIN: Duration = Duration::from_millis(50);

/// The longest: the wait doubles while the queue stays empty.
pub const IDLE_POLL_MAX: Duration = Duration::from_secs(1);

async fn worker_loop(state: Arc<AppState>, worker: String, mut shutdown: watch::Receiver<bool>) {
    let mut idle = IDLE_POLL_MIN;
    loop {
        if *shutdown.borrow() {
            return;
        }
        match state
            .store
            .claim(&worker, state.config.lease.duration())
            .await
        {
            Ok(Some(job)) => {
                idle = IDLE_POLL_MIN;
                execute(&state, job).await;
            }
            Ok(None) => {
                tokio::select! {
                    _ = state.wake.notified() => idle = IDLE_POLL_MIN,
                    _ = tokio::time::sleep(idle) => idle = (idle * 2).min(IDLE_POLL_MAX),
                    _ = shutdown.changed() => {}
                }
            }
            Err(error) => {
                tracing::error!(%error, "cannot claim a job");
                tokio::time::sleep(IDLE_POLL_MAX).await;
            }
        }
    }
}

/// Renews a held job's lease every [`crate::service::infra::config::Lease::heartbeat`]
/// until dropped; stops (and says so) once the job is no longer held.
struct Heartbeat(tokio::task::JoinHandle<()>);

impl Heartbeat {
    fn start(state: &Arc<AppState>, job: &ClaimedJob) -> Heartbeat {
        let (state, job) = (state.clone(), job.clone());
        Heartbeat(tokio::spawn(async move {
            let lease = state.config.lease.duration();
            loop {
                tokio::time::sleep(state.config.lease.heartbeat()).await;
                match state.store.renew(&job, lease).await {
                    Ok(true) => {}
                    Ok(false) => {
                        tracing::warn!(
                            job = %job.id,
                            token = %job.token,
                            "lost the job's lease (it ran out and another worker took the job); \
                             this attempt's result will be dropped"
                        );
                        return;
                    }
                    Err(error) => {
                        tracing::warn!(job = %job.id, %error, "cannot renew a job's lease")
                    }
                }
            }
        }))
    }
}

impl Drop for Heartbeat {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// Fault injection for tests: `PTV_FAULT_JOB_DELAY_MS` makes every attempt
/// wait that long (its lease renewed) before its handler runs, so that a
/// test can kill a worker in the middle of a job. Unset in production.
fn fault_job_delay() -> Option<Duration> {
    static DELAY: std::sync::OnceLock<Option<Duration>> = std::sync::OnceLock::new();
    *DELAY.get_or_init(|| {
        std::env::var("PTV_FAULT_JOB_DELAY_MS")
            .ok()
            .and_then(|ms| ms.parse().ok())
            .map(Duration::from_millis)
    })
}

/// Runs one claimed job, its lease renewed meanwhile, and records its
/// outcome (fenced on the claim's token).
async fn execute(state: &Arc<AppState>, job: ClaimedJob) {
    let run = JobRun {
        job: job.clone(),
        started: Instant::now(),
    };
    let kind = job.kind.clone();
    crate::service::ops::events::job_running(&state.events, &job);
    let heartbeat = Heartbeat::start(state, &job);
    if let Some(delay) = fault_job_delay() {
        tokio::time::sleep(delay).await;
    }
    let outcome = match kind.parse::<JobKind>() {
        Ok(JobKind::ProcessFrame) => process_frame(state.clone(), run.clone()).await,
        Ok(JobKind::SolveCalibration) => solve_calibration(state.clone(), run.clone()).await,
        Ok(JobKind::SelfCalibrate) => selfcal::self_calibrate_job(state.clone(), run.clone()).await,
        Ok(JobKind::ReprocessSequence) => {
            selfcal::reprocess_sequence(state.clone(), run.clone()).await
        }
        Err(unknown) => Err(JobError::Failed(unknown.to_string())),
    };
    drop(heartbeat);
    let seconds = run.elapsed_s();
    let announced = crate::service::ops::events::JobOutcome::of(&outcome, job.attempts);
    let fenced = |error: CompleteError| match error {
        CompleteError::LostLease(_) => tracing::warn!(
            job = %job.id,
            token = %job.token,
            "the job's lease was lost (another worker took it); this attempt's outcome is dropped"
        ),
        CompleteError::Database(error) => {
            tracing::error!(job = %job.id, %error, "cannot record a job's outcome")
        }
    };
    let label = match outcome {
        Ok(()) => "succeeded",
        Err(JobError::LostLease) => {
            tracing::warn!(
                job = %job.id,
                token = %job.token,
                "the job's lease was lost (another worker took it); result dropped"
            );
            "lost"
        }
        Err(JobError::Failed(message)) => {
            if let Err(error) = state.store.fail(&job, &message, seconds).await {
                fenced(error);
            }
            "failed"
        }
        Err(JobError::Retry(message)) if job.attempts < MAX_ATTEMPTS => {
            tracing::warn!(job = %job.id, %message, "job attempt failed; queued again");
            if let Err(error) = state.store.release(&job, Some(&message)).await {
                fenced(error);
            }
            state.wake.notify_one();
            "retried"
        }
        Err(JobError::Retry(message)) => {
            let message = format!("gave up after {} attempts: {message}", job.attempts);
            if let Err(error) = state.store.fail(&job, &message, seconds).await {
                fenced(error);
            }
            "failed"
        }
        Err(error @ (JobError::StorageFull(_) | JobError::Unavailable(_))) => {
            let unavailable = matches!(error, JobError::Unavailable(_));
            let message = error.to_string();
            tracing::warn!(job = %job.id, %message, "job given back uncounted; queued again");
            // Giving the job back is a write too: on a full disk, or with
            // the database out of reach, it may fail, so keep trying (a
            // shutdown's grace period ends this, and the job then goes back
            // with the others held); a lost lease ends it. A job that found
            // a backend out of reach is not claimed again for a while.
            loop {
                let given_back = if unavailable {
                    let pause = UNAVAILABLE_PAUSE.as_secs_f64();
                    state.store.defer(&job, &message, pause).await
                } else {
                    state.store.give_back(&job, &message).await
                };
                match given_back {
                    Ok(()) => break,
                    Err(error @ CompleteError::LostLease(_)) => {
                        fenced(error);
                        break;
                    }
                    Err(error) => {
                        tracing::error!(job = %job.id, %error, "cannot queue a job again");
                        tokio::time::sleep(STORAGE_FULL_PAUSE).await;
                    }
                }
            }
            tokio::time::sleep(STORAGE_FULL_PAUSE).await;
            if unavailable {
                "unavailable"
            } else {
                "storage_full"
            }
        }
        Err(JobError::Deferred(note)) => {
            let delay = crate::service::ops::preprocessing::WAIT_FOR_BACKGROUND.as_secs_f64();
            if let Err(error) = state.store.defer(&job, &note, delay).await {
                fenced(error);
            }
            "deferred"
        }
    };
    state.metrics.job(&kind, label, seconds);
    crate::service::ops::events::job_ended(&state.events, &job, announced);
    if kind == JobKind::ProcessFrame.as_str() {
        // A frame done (or failed: a gap) may let its sequence's tracking
        // advance.
        if let Ok(payload) = serde_json::from_str::<FramePayload>(&job.payload) {
            crate::service::ops::tracking::kick(state, payload.sequence_id);
        }
    }
}

/// A process_frame job's payload.
#[derive(Debug, Deserialize)]
struct FramePayload {
    sequence_id: SequenceId,
    frame: FrameNumber,
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

/// A frame's targets (encoded per camera, for images) and particles. Images
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
) -> Result<(Vec<(i64, i64, Vec<u8>)>, Vec<Particle>), JobError> {
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
        let files = futures_util::future::try_join_all(images.iter().map(|(camera, sha256)| {
            let camera = *camera;
            async move {
                state
                    .images
                    .read(sha256)
                    .await
                    .map_err(|e| JobError::image(&format!("the image of camera {camera}"), e))
            }
        }))
        .await?;
        let mut targets = Vec::with_capacity(cameras);
        for (index, ((camera, _), bytes)) in images.into_iter().zip(files).enumerate() {
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
                let targets = codec::encode_frame_targets(&frame.targets);
                Ok::<_, FrameError>((targets, frame.particles))
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
            .map(|(_, count, _)| u64::try_from(*count).unwrap_or(0))
            .sum();
        cancel.set_limit(limit.for_work(0, size.1));
        let (pipeline, work_cancel) = (pipeline.clone(), cancel.clone());
        let particles = state
            .cpu
            .run_until(cancel, move || {
                let targets = stored
                    .iter()
                    .map(|(_, _, blob)| codec::decode_targets(blob))
                    .collect::<Result<Vec<_>, _>>()?;
                Ok::<_, FrameError>(
                    pipeline
                        .matcher()
                        .match_frame_until(&targets, &work_cancel)?,
                )
            })
            .await
            .map_err(FrameError::from)
            .and_then(|r| r)
            .map_err(JobError::failed)?;
        Ok((Vec::new(), particles))
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
    let (targets, particles) = match computed {
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
            (particles.len() as i64, &blob),
            !keep_images,
            run.elapsed_s(),
        )
        .await?;
    state.metrics.particles(particles.len());
    remove_unused_images(&state.store, &state.images, &released).await;
    Ok(())
}

/// A solve_calibration job's payload: its options, checked when the
/// request was taken; its inputs are its `job_files`.
#[derive(Debug, Deserialize, serde::Serialize)]
pub struct SolvePayload {
    /// `options`, as given.
    pub options: SolveOptions,
}

/// How a part of a `/calibrations/solve` request is named in messages.
pub fn part_source(part: &str, camera: Option<usize>) -> String {
    match camera {
        Some(camera) => format!("part `{part}` of camera {camera}"),
        None => format!("part `{part}`"),
    }
}

/// Why a solve request's files do not give a calibration.
#[derive(Debug, thiserror::Error)]
pub enum SolveError {
    /// A file does not parse.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// A text part is not text (its source named).
    #[error("{0} is not UTF-8 text")]
    NotText(String),
    /// A part this job does not know.
    #[error("unknown input part `{0}`")]
    UnknownPart(String),
    /// A part that must be there is not.
    #[error("the `{0}` part is missing")]
    Missing(&'static str),
    /// An option is invalid.
    #[error("options.{0}")]
    Options(#[from] OptionError),
    /// The marks' detection parameters are invalid.
    #[error("options.detection")]
    Detection(#[from] InvalidDetectionParameters),
    /// A camera's image gave more marks than its limit.
    #[error("the image of camera {camera}: {error}")]
    Marks {
        /// The camera, from 0.
        camera: usize,
        /// Why.
        error: crate::photogrammetry::DetectError,
    },
    /// The calibration itself failed.
    #[error(transparent)]
    Calibration(#[from] CalibrationError),
    /// The work did not finish.
    #[error("the calibration {0}")]
    Cpu(#[from] CpuError),
}

/// Text of a part, or what is wrong with it.
pub fn part_text(bytes: Vec<u8>, source: &str) -> Result<String, SolveError> {
    String::from_utf8(bytes).map_err(|_| SolveError::NotText(source.to_owned()))
}

/// Calibrates from a solve request's files (part, camera, bytes; per-camera
/// parts in camera order): the calibration JSON, its camera count and the
/// report JSON. CPU work: run it on the pool.
pub fn solve(
    files: Vec<(JobFile, Vec<u8>)>,
    options: &SolveOptions,
) -> Result<(String, i64, String), SolveError> {
    let (mut setup, mut control_points) = (None, None);
    let (mut observations, mut references, mut images) = (Vec::new(), Vec::new(), Vec::new());
    for (file, bytes) in files {
        let source = part_source(&file.part, file.camera.map(|c| c as usize));
        match file.part.as_str() {
            "setup" => {
                let text = part_text(bytes, &source)?;
                setup = Some(formats::calibration::setup_from_json(&text, &source)?);
            }
            "control" => {
                let text = part_text(bytes, &source)?;
                control_points = Some(control::parse_control_points(&text, &source)?);
            }
            "observations" | "reference" => {
                let text = part_text(bytes, &source)?;
                let marks = control::parse_mark_observations(&text, &source)?;
                if file.part == "observations" {
                    observations.push(marks);
                } else {
                    references.push(marks);
                }
            }
            "image" => images.push(formats::image::decode_image(&bytes, &source)?),
            other => return Err(SolveError::UnknownPart(other.to_owned())),
        }
    }
    let formats::calibration::Setup {
        cameras: setup,
        unknown,
    } = setup.ok_or(SolveError::Missing("setup"))?;
    let control_points = control_points.ok_or(SolveError::Missing("control"))?;
    let calibration_options = calibrate::CalibrationOptions {
        unknown,
        ..options.calibration_options()?
    };
    let result = if images.is_empty() {
        calibrate::calibrate(&setup, &control_points, &observations, &calibration_options)
    } else {
        let parameters = options.mark_detection()?;
        let marks = images
            .iter()
            .enumerate()
            .map(|(camera, image)| {
                calibrate::detect_marks(image, &parameters)
                    .map_err(|error| SolveError::Marks { camera, error })
            })
            .collect::<Result<Vec<_>, _>>()?;
        if references.is_empty() {
            references = vec![Vec::new(); setup.len()];
        }
        calibrate::calibrate_from_marks(
            &setup,
            &control_points,
            &marks,
            &references,
            &calibration_options,
        )
    }?;
    let cameras = result.camera_models()?;
    let model = formats::calibration::to_json(&cameras);
    // Stored only if it reads back: a solve that ran out of the ranges
    // real cameras have (a diverged adjustment) fails, naming the value.
    formats::calibration::from_json(&model, "the solved calibration")?;
    Ok((
        model,
        cameras.len() as i64,
        control::report_to_json(&result.report),
    ))
}

/// What a solve_calibration job needs of the memory budget: its images
/// decoded all at once (2 bytes a sample at most) and the largest one's
/// marks detected ([`crate::service::infra::budget::DETECT_BYTES_PER_PIXEL`]), from the
/// images' headers; an image whose header does not read fails later in
/// [`solve`] with the reason.
fn solve_need(files: &[(JobFile, Vec<u8>)]) -> crate::service::infra::budget::MemoryNeed {
    let pixels: Vec<u64> = files
        .iter()
        .filter(|(file, _)| file.part == "image")
        .filter_map(|(_, bytes)| {
            formats::image::probe_image(std::io::Cursor::new(bytes), "an image").ok()
        })
        .map(|header| u64::from(header.width) * u64::from(header.height))
        .collect();
    let largest = pixels.iter().copied().max().unwrap_or(0);
    let bytes = pixels.iter().sum::<u64>().saturating_mul(2).saturating_add(
        largest.saturating_mul(crate::service::infra::budget::DETECT_BYTES_PER_PIXEL),
    );
    crate::service::infra::budget::MemoryNeed::new(
        bytes,
        format!(
            "solving a calibration from {} image(s) of {} pixels in all",
            pixels.len(),
            pixels.iter().sum::<u64>()
        ),
    )
}

/// The solve_calibration job: calibrates from the request's files and
/// stores the calibration with its report, completing the job in the same
/// transaction; with `keep_images: false` its files go afterwards.
pub async fn solve_calibration(state: Arc<AppState>, run: JobRun) -> Result<(), JobError> {
    let payload: SolvePayload = serde_json::from_str(&run.job.payload)
        .map_err(|e| JobError::Failed(format!("malformed payload: {e}")))?;
    let mut files = Vec::new();
    for file in state.store.job_files(run.job.id).await? {
        let bytes = state.images.read(&file.sha256).await.map_err(|e| {
            let part = part_source(&file.part, file.camera.map(|c| c as usize));
            JobError::image(&format!("the file of {part}"), e)
        })?;
        files.push((file, bytes));
    }
    let grant = state.budget.acquire(&solve_need(&files)).await?;
    let options = payload.options.clone();
    let (model, cameras, report) = state
        .cpu
        .try_run(move || solve(files, &options))
        .await
        .map_err(JobError::failed)?;
    drop(grant);
    let (_, released) = state
        .store
        .complete_calibration(
            &run.job,
            &model,
            cameras,
            &report,
            payload.options.keep_images.unwrap_or(true),
            run.elapsed_s(),
        )
        .await?;
    remove_unused_images(&state.store, &state.images, &released).await;
    Ok(())
}

/// Deletes the files of `hashes` that nothing refers to any more, each
/// checked under the image store's lock against what is committed.
pub(super) async fn remove_unused_images(
    store: &Store,
    images: &crate::service::ops::images::ImageStore,
    hashes: &[String],
) {
    if hashes.is_empty() {
        return;
    }
    let _guard = match images.lock(store).await {
        Ok(guard) => guard,
        Err(error) => {
            // The files stay; the next sweep removes them.
            tracing::warn!(%error, "cannot lock the image store to delete unused files");
            return;
        }
    };
    for hash in hashes {
        match store.image_in_use(hash).await {
            Ok(false) => {
                if let Err(error) = images.remove(hash).await {
                    tracing::warn!(%error, hash, "cannot delete an image file");
                }
            }
            Ok(true) => {}
            Err(error) => tracing::warn!(%error, "cannot check an image's use"),
        }
    }
}
