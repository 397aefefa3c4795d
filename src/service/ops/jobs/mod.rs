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

use tokio::sync::watch;

pub mod attempt;
pub mod cache;
pub mod frame;
pub mod pipelines;
pub mod pool;
pub mod solve;

use self::attempt::{JobError, JobRun, STORAGE_FULL_PAUSE, UNAVAILABLE_PAUSE};
use self::frame::{process_frame, FramePayload};
use self::solve::solve_calibration;
use crate::service::model::job_kind::JobKind;
use crate::service::ops::selfcal;
use crate::service::ops::state::AppState;
use crate::service::store::{ClaimedJob, CompleteError, MAX_ATTEMPTS};

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
        // and calibration health advance.
        if let Ok(payload) = serde_json::from_str::<FramePayload>(&job.payload) {
            crate::service::ops::tracking::kick(state, payload.sequence_id);
            crate::service::ops::health::advance_later(state, payload.sequence_id);
        }
    } else if kind == JobKind::ReprocessSequence.as_str() {
        // Frames reprocessed with the sequence's new calibration feed its
        // new health monitor.
        if let Ok(payload) = serde_json::from_str::<OfSequence>(&job.payload) {
            crate::service::ops::health::advance_later(state, payload.sequence_id);
        }
    }
}

/// The sequence a job's payload names (other fields ignored).
#[derive(serde::Deserialize)]
struct OfSequence {
    sequence_id: crate::service::store::SequenceId,
}
