//! The durable job queue's workers.
//!
//! Jobs are rows of the `jobs` table ([`Store`]): enqueued in the same
//! transaction as what they work on, claimed with a lease (`UPDATE ...
//! RETURNING` in one write transaction; see the store's `jobs` module),
//! and completed in the same transaction that stores their results,
//! fenced by the claim's token, so a job's results exist exactly once.
//! Each kind of job is a [`JobHandler`] registered in [`JobKinds`] under
//! its name; the workers do not know the kinds.
//!
//! Workers are async tasks, one per `--workers`, in `ptv serve` or in any
//! number of `ptv worker` processes on the same data directory. Each
//! claims a job, renews its lease by heartbeat every third of
//! `--lease-secs` while the attempt runs, reads its inputs (all in the
//! database and the image directory: nothing of the serving process),
//! and hands the CPU work to [`CpuPool`] (a rayon pool of the same size),
//! never computing on the async runtime's threads. Before its work, a
//! frame, background or calibration job takes the memory it declares
//! from the process's budget ([`super::budget`]), waiting its turn with
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
//! Kinds today: [`PROCESS_FRAME`] ([`process_frame`]),
//! [`SOLVE_CALIBRATION`] ([`solve_calibration`]: calibration by resection
//! from the files of a `/calibrations/solve` request, kept in the image
//! store and listed in `job_files`), and in [`super::selfcal`]
//! `self_calibrate` (a sequence's calibration refined from its stored
//! targets) and `reprocess_sequence` (its frames matched again with
//! another calibration).

use std::collections::HashMap;
use std::future::Future;
use std::panic::AssertUnwindSafe;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::Deserialize;
use tokio::sync::{oneshot, watch};

use super::app::AppState;
use super::codec;
use super::codec::DamagedBlob;
use super::parameters::SequenceParameters;
use super::parameters::SolveOptions;
use super::store::{
    CalibrationId, ClaimedJob, CompleteError, FrameInputKind, FrameNumber, JobFile, SequenceId,
    Store, MAX_ATTEMPTS,
};
use crate::formats::control::{self, OptionError};
use crate::formats::image::RawLayout;
use crate::formats::{self, FormatError};
use crate::photogrammetry::calibrate::{self, CalibrationError};
use crate::photogrammetry::correspond::{MatchError, Particle};
use crate::photogrammetry::{
    BitDepth, Cancel, FramePipeline, InvalidDetectionParameters, PipelineError, Splitter,
    SplitterError,
};
use crate::service::config::JobLimits;

/// The kind of the job that processes one uploaded frame.
pub const PROCESS_FRAME: &str = "process_frame";

/// The kind of the job that solves a calibration by resection.
pub const SOLVE_CALIBRATION: &str = "solve_calibration";

/// Why a job attempt did not succeed.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    /// The job cannot succeed (bad input): it fails, with this message.
    #[error("{0}")]
    Failed(String),
    /// A passing failure (I/O, database): the job is queued again, up to
    /// [`MAX_ATTEMPTS`] claims.
    #[error("{0}")]
    Retry(String),
    /// The disk is full (the database's or the image store's): not the
    /// job's fault, so the attempt is given back uncounted and the job
    /// queued again, however often, the worker pausing
    /// [`STORAGE_FULL_PAUSE`] before its next claim.
    #[error("{0}")]
    StorageFull(String),
    /// The database or the object store cannot be reached for now
    /// (PostgreSQL or the S3 server restarting, the network): not the
    /// job's fault, so the attempt is given back uncounted however often,
    /// and the job is not claimed again for [`UNAVAILABLE_PAUSE`].
    #[error("{0}")]
    Unavailable(String),
    /// The job waits for other work (its sequence's computed background):
    /// given back uncounted, not claimed again for a while
    /// ([`super::preprocessing::WAIT_FOR_BACKGROUND`]); the message says
    /// what it waits for and shows as the job's `error` meanwhile.
    #[error("{0}")]
    Deferred(String),
    /// The worker no longer holds the job (its lease ran out and another
    /// worker took it): its result is dropped.
    #[error("lost the job's lease")]
    LostLease,
}

/// How long a worker waits after an attempt that found the disk full
/// before it claims again (or tries again to give the job back).
pub const STORAGE_FULL_PAUSE: Duration = Duration::from_secs(2);

/// How long a job whose attempt found the database or the object store
/// out of reach waits before it is claimed again.
pub const UNAVAILABLE_PAUSE: Duration = Duration::from_secs(5);

impl JobError {
    /// An image store error while reading `what` (`the image of camera
    /// 2`): out of reach, the attempt is given back; a full disk waits for
    /// space; a missing file that a committed row names fails the job
    /// (the store lost it: nothing a retry mends); other I/O is retried.
    pub fn image(what: &str, error: super::images::ImageStoreError) -> JobError {
        use super::images::ImageStoreError;
        match error {
            ImageStoreError::Unavailable(message) => {
                JobError::Unavailable(format!("{what}: {message}"))
            }
            ImageStoreError::Io(error) if super::images::is_storage_full(&error) => {
                JobError::StorageFull(format!("the disk is full; waiting for space: {error}"))
            }
            ImageStoreError::Missing { sha256 } => JobError::Failed(format!(
                "{what} is missing from the image store (image {sha256}), although a \
                 committed row refers to it: the store lost it"
            )),
            error => JobError::Retry(format!("{what}: {error}")),
        }
    }

    /// The job cannot succeed: it fails with `error` and its causes as
    /// its message.
    pub fn failed(error: impl std::error::Error + 'static) -> JobError {
        JobError::Failed(error_chain(&error))
    }
}

impl From<sqlx::Error> for JobError {
    /// A full disk, or a database that cannot be reached for now, is not
    /// the job's fault: its attempt is given back uncounted
    /// (the worker pausing before its next claim); any other database error a passing failure.
    fn from(error: sqlx::Error) -> Self {
        use super::store::ErrorKind;
        match super::store::error_kind(&error) {
            ErrorKind::StorageFull => {
                JobError::StorageFull(format!("the disk is full; waiting for space: {error}"))
            }
            ErrorKind::Unavailable => JobError::Unavailable(format!(
                "the database cannot be reached; waiting for it: {error}"
            )),
            ErrorKind::Other => JobError::Retry(format!("database: {error}")),
        }
    }
}

impl From<CompleteError> for JobError {
    fn from(error: CompleteError) -> Self {
        match error {
            CompleteError::LostLease(_) => JobError::LostLease,
            CompleteError::Database(e) => e.into(),
        }
    }
}

/// A claimed job and when its attempt started.
#[derive(Clone, Debug)]
pub struct JobRun {
    /// The claim.
    pub job: ClaimedJob,
    /// When the attempt started.
    pub started: Instant,
}

impl JobRun {
    /// Seconds since the attempt started.
    pub fn elapsed_s(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }
}

/// The future a handler returns.
pub type JobFuture = Pin<Box<dyn Future<Output = Result<(), JobError>> + Send>>;

/// Runs one kind of job: reads the payload, does the work, and completes
/// the job with its results in one transaction ([`super::store::finish`]).
pub type JobHandler = Arc<dyn Fn(Arc<AppState>, JobRun) -> JobFuture + Send + Sync>;

/// The job kinds the workers run, by name.
#[derive(Clone, Default)]
pub struct JobKinds {
    handlers: HashMap<&'static str, JobHandler>,
}

impl JobKinds {
    /// The kinds the service has today.
    pub fn standard() -> JobKinds {
        let mut kinds = JobKinds::default();
        kinds.register(PROCESS_FRAME, process_frame);
        kinds.register(SOLVE_CALIBRATION, solve_calibration);
        kinds.register(
            super::selfcal::SELF_CALIBRATE,
            super::selfcal::self_calibrate_job,
        );
        kinds.register(
            super::selfcal::REPROCESS_SEQUENCE,
            super::selfcal::reprocess_sequence,
        );
        kinds
    }

    /// Registers a kind: `handler(state, run)`.
    pub fn register<F, Fut>(&mut self, kind: &'static str, handler: F)
    where
        F: Fn(Arc<AppState>, JobRun) -> Fut + Send + Sync + 'static,
        Fut: Future<Output = Result<(), JobError>> + Send + 'static,
    {
        self.handlers.insert(
            kind,
            Arc::new(move |state, run| Box::pin(handler(state, run))),
        );
    }

    fn get(&self, kind: &str) -> Option<&JobHandler> {
        self.handlers.get(kind)
    }
}

/// Why work handed to the [`CpuPool`] gave no result.
#[derive(Debug, thiserror::Error)]
pub enum CpuError {
    /// The work panicked, with this message.
    #[error("panicked: {0}")]
    Panicked(String),
    /// The pool dropped the work without running it to its end.
    #[error("the CPU pool dropped the work")]
    Dropped,
    /// The work ran past its deadline and did not stop when told to.
    #[error("ran past its time limit of {:.1} s and did not stop", .0.as_secs_f64())]
    Overran(Duration),
}

/// How long work past its deadline gets to notice its [`Cancel`] token
/// before the waiter sets it itself, and then to return, before the waiter
/// gives up on it.
const STOP_GRACE: Duration = Duration::from_secs(5);

/// A bounded pool of CPU threads for detection and matching.
#[derive(Debug)]
pub struct CpuPool {
    pool: rayon::ThreadPool,
}

impl CpuPool {
    /// A pool of `threads` threads.
    pub fn new(threads: usize) -> Result<CpuPool, rayon::ThreadPoolBuildError> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads.max(1))
            .thread_name(|i| format!("ptv-cpu-{i}"))
            .build()?;
        Ok(CpuPool { pool })
    }

    /// Runs `work` on the pool and waits for it without blocking the async
    /// runtime; a panic in `work` comes back as [`CpuError::Panicked`].
    pub async fn run<T, F>(&self, work: F) -> Result<T, CpuError>
    where
        T: Send + 'static,
        F: FnOnce() -> T + Send + 'static,
    {
        let (sender, receiver) = oneshot::channel();
        self.pool.spawn(move || {
            let result = std::panic::catch_unwind(AssertUnwindSafe(work));
            let _ = sender.send(result);
        });
        match receiver.await {
            Ok(Ok(value)) => Ok(value),
            Ok(Err(panic)) => Err(CpuError::Panicked(
                panic
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| panic.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "a panic".to_owned()),
            )),
            Err(_) => Err(CpuError::Dropped),
        }
    }

    /// [`CpuPool::run`] for work that checks `cancel` (a deadline, or a
    /// waiter that may go away): the token's deadline is its own to notice;
    /// `STOP_GRACE` after it the token is stopped from here, and if the
    /// work has still not returned after another grace, the wait ends with
    /// [`CpuError::Overran`] (the thread stays busy until the work's next
    /// check; every loop of the core checks within milliseconds).
    pub async fn run_until<T, F>(&self, cancel: &Cancel, work: F) -> Result<T, CpuError>
    where
        T: Send + 'static,
        F: FnOnce() -> T + Send + 'static,
    {
        let run = self.run(work);
        tokio::pin!(run);
        let limit = loop {
            let Some(deadline) = cancel.deadline() else {
                return run.await;
            };
            let at = tokio::time::Instant::from_std(deadline + STOP_GRACE);
            match tokio::time::timeout_at(at, &mut run).await {
                Ok(result) => return result,
                // The limit grew meanwhile: wait on.
                Err(_) if cancel.deadline() > Some(deadline) => continue,
                Err(_) => break cancel.limit().unwrap_or_default(),
            }
        };
        cancel.stop();
        tokio::time::timeout(STOP_GRACE, &mut run)
            .await
            .unwrap_or(Err(CpuError::Overran(limit)))
    }

    /// [`CpuPool::run`] for work that can fail: its error, or the pool's
    /// turned into it.
    pub async fn try_run<T, E, F>(&self, work: F) -> Result<T, E>
    where
        T: Send + 'static,
        E: From<CpuError> + Send + 'static,
        F: FnOnce() -> Result<T, E> + Send + 'static,
    {
        self.run(work).await?
    }
}

/// Prepared frame pipelines by sequence (preparing one builds the
/// matcher's refraction tables, far more work than a frame), each with the
/// number of the sequence's stored backgrounds and masks it was made with:
/// a sequence's images are only ever added, so a pipeline made with fewer
/// than there are now is stale, whoever added them and when; and with the
/// calibration it was made with (reprocessing switches a sequence's).
#[derive(Debug, Default)]
pub struct PipelineCache {
    pipelines: Mutex<HashMap<SequenceId, (CalibrationId, usize, Prepared)>>,
}

/// A sequence's prepared frame pipeline and its calibration's splitter
/// (whether a frame is one image of several views).
pub type Prepared = (Arc<FramePipeline>, Option<Splitter>);

/// Pipelines kept at most; beyond, the cache starts afresh.
const CACHED_PIPELINES: usize = 32;

impl PipelineCache {
    /// The sequence's pipeline, if prepared with `calibration_id` and
    /// `images` stored backgrounds and masks.
    pub fn get(
        &self,
        sequence_id: SequenceId,
        calibration_id: CalibrationId,
        images: usize,
    ) -> Option<Prepared> {
        let map = self.pipelines.lock().unwrap_or_else(|e| e.into_inner());
        map.get(&sequence_id)
            .filter(|(calibration, made_with, _)| {
                *calibration == calibration_id && *made_with == images
            })
            .map(|(_, _, prepared)| prepared.clone())
    }

    /// Keeps a pipeline prepared with `calibration_id` and `images` stored
    /// backgrounds and masks.
    pub fn insert(
        &self,
        sequence_id: SequenceId,
        calibration_id: CalibrationId,
        images: usize,
        prepared: Prepared,
    ) {
        let mut map = self.pipelines.lock().unwrap_or_else(|e| e.into_inner());
        if map.len() >= CACHED_PIPELINES {
            map.clear();
        }
        map.insert(sequence_id, (calibration_id, images, prepared));
    }
}

/// Why a frame pipeline could not be prepared.
#[derive(Debug, thiserror::Error)]
pub enum PrepareError {
    /// The stored calibration does not read.
    #[error(transparent)]
    Calibration(#[from] FormatError),
    /// The parameters do not work with the calibration.
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    /// The preparation did not finish.
    #[error("preparing the frame pipeline {0}")]
    Cpu(#[from] CpuError),
}

/// Prepares the frame pipeline of a calibration and parameters, on the CPU
/// pool; not started if `cancel` fired while it waited for a thread (a
/// request whose client has gone). The preparation itself is bounded by
/// the cameras a calibration may have. Also the calibration's splitter.
pub async fn prepare_pipeline(
    state: &AppState,
    calibration_model: &str,
    parameters: &SequenceParameters,
    cancel: &Cancel,
) -> Result<(FramePipeline, Option<Splitter>), PrepareError> {
    let (cameras, splitter) = formats::calibration::stored_from_json_with_splitter(
        calibration_model,
        "the stored calibration",
    )?;
    let detection = parameters.detection();
    let matching = parameters.matching();
    let cancel = cancel.clone();
    state
        .cpu
        .try_run(move || {
            cancel.check().map_err(PipelineError::from)?;
            Ok((
                FramePipeline::new(&cameras, &detection, &matching)?,
                splitter,
            ))
        })
        .await
}

/// An error and its sources as one line, `: `-separated, a cause the text
/// already ends with written once.
pub fn error_chain(error: &(dyn std::error::Error + 'static)) -> String {
    let mut text = error.to_string();
    let mut source = error.source();
    while let Some(cause) = source {
        let cause_text = cause.to_string();
        if !text.ends_with(&cause_text) {
            text.push_str(": ");
            text.push_str(&cause_text);
        }
        source = cause.source();
    }
    text
}

/// Runs `workers` workers until `shutdown` turns true; each finishes its
/// running job first.
pub fn spawn_workers(
    state: Arc<AppState>,
    kinds: JobKinds,
    workers: usize,
    shutdown: watch::Receiver<bool>,
) -> tokio::task::JoinSet<()> {
    let mut set = tokio::task::JoinSet::new();
    for index in 0..workers {
        let worker = format!("{}/{index}", state.instance);
        set.spawn(worker_loop(
            state.clone(),
            kinds.clone(),
            worker,
            shutdown.clone(),
        ));
    }
    set
}

/// The shortest wait of an idle worker before it looks at the queue again.
pub const IDLE_POLL_MIN: Duration = Duration::from_millis(50);

/// The longest: the wait doubles while the queue stays empty.
pub const IDLE_POLL_MAX: Duration = Duration::from_secs(1);

async fn worker_loop(
    state: Arc<AppState>,
    kinds: JobKinds,
    worker: String,
    mut shutdown: watch::Receiver<bool>,
) {
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
                execute(&state, &kinds, job).await;
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

/// Renews a held job's lease every [`crate::service::config::Lease::heartbeat`]
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
async fn execute(state: &Arc<AppState>, kinds: &JobKinds, job: ClaimedJob) {
    let run = JobRun {
        job: job.clone(),
        started: Instant::now(),
    };
    let kind = job.kind.clone();
    super::events::job_running(state, &job);
    let heartbeat = Heartbeat::start(state, &job);
    if let Some(delay) = fault_job_delay() {
        tokio::time::sleep(delay).await;
    }
    let outcome = match kinds.get(&kind) {
        Some(handler) => handler(state.clone(), run.clone()).await,
        None => Err(JobError::Failed(format!(
            "this service does not know jobs of kind `{kind}`"
        ))),
    };
    drop(heartbeat);
    let seconds = run.elapsed_s();
    let announced = super::events::JobOutcome::of(&outcome, job.attempts);
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
            let delay = super::preprocessing::WAIT_FOR_BACKGROUND.as_secs_f64();
            if let Err(error) = state.store.defer(&job, &note, delay).await {
                fenced(error);
            }
            "deferred"
        }
    };
    state.metrics.job(&kind, label, seconds);
    super::events::job_ended(state, &job, announced);
    if kind == PROCESS_FRAME {
        // A frame done (or failed: a gap) may let its sequence's tracking
        // advance.
        if let Ok(payload) = serde_json::from_str::<FramePayload>(&job.payload) {
            super::tracking::kick(state, payload.sequence_id);
        }
    }
}

/// A process_frame job's payload.
#[derive(Debug, Deserialize)]
struct FramePayload {
    sequence_id: SequenceId,
    frame: FrameNumber,
}

/// The raw layout as stored with a frame.
#[derive(Debug, Deserialize, serde::Serialize)]
pub struct StoredRawLayout {
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// 8 or 16.
    pub bits: u32,
}

impl StoredRawLayout {
    /// The layout for the decoder.
    pub fn layout(&self) -> Option<RawLayout> {
        Some(RawLayout {
            width: self.width,
            height: self.height,
            bit_depth: BitDepth::from_bits(self.bits)?,
        })
    }
}

/// A sequence's stored parameters.
pub(super) async fn sequence_parameters(
    state: &AppState,
    sequence_id: SequenceId,
) -> Result<SequenceParameters, JobError> {
    let sequence = state
        .store
        .sequence(sequence_id)
        .await?
        .ok_or_else(|| JobError::Failed(format!("sequence {sequence_id} does not exist")))?;
    serde_json::from_str(&sequence.parameters)
        .map_err(|e| JobError::Failed(format!("the sequence's stored parameters: {e}")))
}

/// The sequence's pipeline, from the cache or prepared now, with its
/// backgrounds and masks.
pub(super) async fn pipeline_of(
    state: &AppState,
    sequence_id: SequenceId,
    calibration_id: CalibrationId,
) -> Result<Prepared, JobError> {
    let images = state.store.sequence_images(sequence_id).await?;
    if let Some(prepared) = state
        .pipelines
        .get(sequence_id, calibration_id, images.len())
    {
        return Ok(prepared);
    }
    let count = images.len();
    let parameters = sequence_parameters(state, sequence_id).await?;
    let calibration = state
        .store
        .calibration(calibration_id)
        .await?
        .ok_or_else(|| JobError::Failed(format!("calibration {calibration_id} does not exist")))?;
    let (pipeline, splitter) =
        prepare_pipeline(state, &calibration.model, &parameters, &Cancel::new())
            .await
            .map_err(JobError::failed)?;
    let pipeline =
        Arc::new(super::preprocessing::with_stored_images(state, images, pipeline).await?);
    let prepared = (pipeline, splitter);
    state
        .pipelines
        .insert(sequence_id, calibration_id, count, prepared.clone());
    Ok(prepared)
}

/// Expected single-core time to decode and detect one pixel (ns): `ptv
/// detect` on a 1280x1024 8-bit PNG takes 30-50 ms with process start-up
/// in the dev profile (at most 25 ns a pixel), a release build less.
const NS_PER_PIXEL: f64 = 25.0;

/// Expected single-core time to match one target (ns): 4 cameras of 10,000
/// targets match in about 40 ms (`benches/correspond.rs`), 1 us per target,
/// doubled for denser frames.
const NS_PER_TARGET: f64 = 2_000.0;

/// A job's time limit from its size (`--job-timeout-secs`,
/// `--job-timeout-factor`): the floor plus the factor times the expected
/// single-core time of its pixels and targets.
#[derive(Clone, Copy, Debug)]
pub struct TimeLimit {
    floor_secs: f64,
    factor: f64,
}

impl TimeLimit {
    /// The service's settings.
    pub fn of(limits: &JobLimits) -> TimeLimit {
        TimeLimit {
            floor_secs: limits.floor_secs.max(0.0),
            factor: limits.factor.max(0.0),
        }
    }

    /// The limit for work on `pixels` pixels and `targets` targets.
    pub fn for_work(&self, pixels: u64, targets: u64) -> Duration {
        let expected = (pixels as f64 * NS_PER_PIXEL + targets as f64 * NS_PER_TARGET) * 1e-9;
        Duration::try_from_secs_f64(self.floor_secs + self.factor * expected)
            .unwrap_or(Duration::MAX)
    }

    /// The limit for work expected to take `seconds` on one core.
    pub fn for_expected(&self, seconds: f64) -> Duration {
        Duration::try_from_secs_f64(self.floor_secs + self.factor * seconds.max(0.0))
            .unwrap_or(Duration::MAX)
    }

    /// The rule, for messages.
    fn describe(&self, pixels: u64, targets: u64) -> String {
        format!(
            "{:.1} s = --job-timeout-secs {} + --job-timeout-factor {} x the expected {:.2} s              for {pixels} pixels and {targets} targets",
            self.for_work(pixels, targets).as_secs_f64(),
            self.floor_secs,
            self.factor,
            (pixels as f64 * NS_PER_PIXEL + targets as f64 * NS_PER_TARGET) * 1e-9,
        )
    }
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
    input: &super::store::FrameInput,
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
/// ([`super::budget::frame_need`]): its cameras' views detected one at a
/// time (none for uploaded targets) and their targets matched.
fn frame_need(
    input: &super::store::FrameInput,
    (pipeline, splitter): &Prepared,
) -> super::budget::MemoryNeed {
    let views: Vec<(u32, u32)> = pipeline
        .cameras()
        .iter()
        .map(|c| (c.sensor().width, c.sensor().height))
        .collect();
    if input.input != FrameInputKind::Images {
        return super::budget::frame_need(&views, None, false);
    }
    let image = splitter.and_then(|s| views.first().and_then(|&(w, h)| s.image_size(w, h)));
    super::budget::frame_need(&views, image, true)
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
            super::preprocessing::ensure_computed_background(
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
/// marks detected ([`super::budget::DETECT_BYTES_PER_PIXEL`]), from the
/// images' headers; an image whose header does not read fails later in
/// [`solve`] with the reason.
fn solve_need(files: &[(JobFile, Vec<u8>)]) -> super::budget::MemoryNeed {
    let pixels: Vec<u64> = files
        .iter()
        .filter(|(file, _)| file.part == "image")
        .filter_map(|(_, bytes)| {
            formats::image::probe_image(std::io::Cursor::new(bytes), "an image").ok()
        })
        .map(|header| u64::from(header.width) * u64::from(header.height))
        .collect();
    let largest = pixels.iter().copied().max().unwrap_or(0);
    let bytes = pixels
        .iter()
        .sum::<u64>()
        .saturating_mul(2)
        .saturating_add(largest.saturating_mul(super::budget::DETECT_BYTES_PER_PIXEL));
    super::budget::MemoryNeed::new(
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
    images: &super::images::ImageStore,
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
