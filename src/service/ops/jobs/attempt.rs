//! A job attempt: the claimed job it runs ([`JobRun`]), its time limit
//! from its size ([`TimeLimit`]), and why it did not succeed
//! ([`JobError`]), which decides what happens to the job.

use std::time::{Duration, Instant};

use crate::service::infra::budget::BudgetError;
use crate::service::infra::config::JobLimits;
use crate::service::infra::errors::error_chain;
use crate::service::store::{ClaimedJob, CompleteError, StoreError};

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
    /// ([`crate::service::ops::preprocessing::WAIT_FOR_BACKGROUND`]); the message says
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
    pub fn image(what: &str, error: crate::service::ops::images::ImageStoreError) -> JobError {
        use crate::service::ops::images::ImageStoreError;
        match error {
            ImageStoreError::Unavailable(message) => {
                JobError::Unavailable(format!("{what}: {message}"))
            }
            ImageStoreError::Io(error)
                if crate::service::infra::errors::is_storage_full(&error) =>
            {
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

impl From<StoreError> for JobError {
    /// A full disk, or a database that cannot be reached for now, is not
    /// the job's fault: its attempt is given back uncounted
    /// (the worker pausing before its next claim); any other database error a passing failure.
    fn from(error: StoreError) -> Self {
        use crate::service::store::ErrorKind;
        match error.kind() {
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

impl From<BudgetError> for JobError {
    fn from(error: BudgetError) -> Self {
        match error {
            BudgetError::TooLarge(message) => JobError::Failed(message),
            BudgetError::Closed => JobError::Retry(error.to_string()),
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
    pub fn describe(&self, pixels: u64, targets: u64) -> String {
        format!(
            "{:.1} s = --job-timeout-secs {} + --job-timeout-factor {} x the expected {:.2} s              for {pixels} pixels and {targets} targets",
            self.for_work(pixels, targets).as_secs_f64(),
            self.floor_secs,
            self.factor,
            (pixels as f64 * NS_PER_PIXEL + targets as f64 * NS_PER_TARGET) * 1e-9,
        )
    }
}
