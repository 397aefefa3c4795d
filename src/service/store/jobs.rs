//! The job queue: enqueue, claim, renew, complete, fail, release, reap;
//! and the input files of jobs that are not frames.
//!
//! **Leases.** A claim holds its job for a lease (`lease_until`, from the
//! database's clock) that the worker renews by heartbeat ([`Store::renew`])
//! while the attempt runs. A running job whose lease has run out (its
//! worker died, hung or lost the database) is queued again by the next
//! claim, from any process ([`expire_leases`]), or failed once it has been
//! claimed [`MAX_ATTEMPTS`] times. Every claim increments the job's
//! fencing token (`lease_token`), and every end of an attempt (success
//! with its results, failure, release, give-back, deferral) is an `UPDATE
//! ... WHERE id = ? AND lease_token = ?` that checks the rows it changed,
//! in the transaction of the attempt's results: a worker whose lease ran
//! out and whose job another worker took writes nothing. Each claim and
//! how it ended is a row of `job_claims`, the job's attempt history.
//!
//! On SQLite a claim is one `BEGIN IMMEDIATE` transaction (the write lock
//! makes it atomic across processes): expire (when a read saw a lease run
//! out), take the oldest queued job (`UPDATE ... WHERE id = (SELECT ...)
//! RETURNING`), record the claim. On PostgreSQL the same
//! statements run in one read-committed transaction, the oldest queued job
//! (and the expired leases) taken with `FOR UPDATE SKIP LOCKED`: claimers
//! at once lock different rows, never wait for each other and never get
//! the same job (`tests/service/leases.rs` and `reliability.rs` check these
//! rules on both engines).

use sqlx::any::AnyRow;
use sqlx::{Any, FromRow, Row, Transaction};

use std::time::Duration;

use super::StoreError;
use super::{
    decode_text, stored_as_text, text_column, CalibrationId, CompleteError, Dialect, FrameNumber,
    JobId, LeaseToken, SequenceId, Store, TextColumn,
};

/// How often a job may be claimed before a crash-looping one is failed.
pub const MAX_ATTEMPTS: i64 = 3;

/// A job's state (the `jobs.state` column).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JobState {
    /// Waiting for a worker.
    Queued,
    /// A worker has it.
    Running,
    /// Done; its result is stored.
    Succeeded,
    /// Given up; `error` says why.
    Failed,
}

stored_as_text!(JobState, "job state", {
    Queued => "queued",
    Running => "running",
    Succeeded => "succeeded",
    Failed => "failed",
});

/// What [`Store::retry`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RetryOutcome {
    /// The failed job is queued again.
    Queued,
    /// The job is not failed, but in this state; nothing changed.
    NotFailed(JobState),
    /// No job has this id.
    Unknown,
}

/// A stored job.
#[derive(Clone, Debug)]
pub struct JobRow {
    /// Its id.
    pub id: JobId,
    /// Its kind.
    pub kind: String,
    /// What it works on (JSON).
    pub payload: String,
    /// Its state.
    pub state: JobState,
    /// How often a worker claimed it.
    pub attempts: i64,
    /// Why it failed (or why its last attempt did).
    pub error: Option<String>,
    /// Where its result is, once it succeeded.
    pub result: Option<JobResult>,
    /// Enqueued at.
    pub created_at: String,
    /// Last claimed at.
    pub started_at: Option<String>,
    /// Finished at.
    pub finished_at: Option<String>,
    /// The worker holding it while it runs.
    pub worker: Option<String>,
    /// Until when its worker holds it (renewed while it runs).
    pub lease_until: Option<String>,
}

/// Where a succeeded job's result is: what the HTTP layer links to.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum JobResult {
    /// The calibration a solve_calibration job stored.
    Calibration(CalibrationId),
    /// The frame a process_frame job processed: its particles.
    Frame {
        /// The sequence.
        sequence_id: SequenceId,
        /// The frame.
        frame: FrameNumber,
    },
    /// The link another kind of job gave when it succeeded
    /// ([`Store::succeed`]).
    Link(String),
}

impl JobResult {
    /// The result of a row of [`Store::job`]'s query: the calibration or
    /// frame it wrote, else the link it gave.
    fn of(row: &AnyRow) -> Result<Option<JobResult>, sqlx::Error> {
        let calibration: Option<CalibrationId> = row.try_get("result_calibration")?;
        let sequence: Option<SequenceId> = row.try_get("result_sequence")?;
        let frame: Option<FrameNumber> = row.try_get("result_frame")?;
        Ok(match (calibration, sequence, frame) {
            (Some(id), _, _) => Some(JobResult::Calibration(id)),
            (None, Some(sequence_id), Some(frame)) => Some(JobResult::Frame { sequence_id, frame }),
            _ => row
                .try_get::<Option<String>, _>("result")?
                .map(JobResult::Link),
        })
    }
}

/// A job a worker has claimed.
#[derive(Clone, Debug)]
pub struct ClaimedJob {
    /// Its id.
    pub id: JobId,
    /// Its kind.
    pub kind: String,
    /// What it works on (JSON).
    pub payload: String,
    /// This claim's number, from 1.
    pub attempts: i64,
    /// Who holds it (host, process, worker).
    pub locked_by: String,
    /// The claim's fencing token: completion is refused once another claim
    /// has taken the job.
    pub token: LeaseToken,
}

impl FromRow<'_, AnyRow> for JobRow {
    fn from_row(row: &AnyRow) -> Result<Self, sqlx::Error> {
        Ok(JobRow {
            id: row.try_get("id")?,
            kind: row.try_get("kind")?,
            payload: row.try_get("payload")?,
            state: text_column(row, "state")?,
            attempts: row.try_get("attempts")?,
            error: row.try_get("error")?,
            result: JobResult::of(row)?,
            created_at: row.try_get("created_at")?,
            started_at: row.try_get("started_at")?,
            finished_at: row.try_get("finished_at")?,
            worker: row.try_get("locked_by")?,
            lease_until: row.try_get("lease_until")?,
        })
    }
}

impl FromRow<'_, AnyRow> for ClaimedJob {
    fn from_row(row: &AnyRow) -> Result<Self, sqlx::Error> {
        Ok(ClaimedJob {
            id: row.try_get("id")?,
            kind: row.try_get("kind")?,
            payload: row.try_get("payload")?,
            attempts: row.try_get("attempts")?,
            locked_by: row.try_get("locked_by")?,
            token: row.try_get("lease_token")?,
        })
    }
}

/// A stored input file of a job: its part, camera, hash and size.
#[derive(Clone, Debug, PartialEq)]
pub struct JobFile {
    /// The request's part name.
    pub part: String,
    /// The camera of a per-camera part.
    pub camera: Option<i64>,
    /// The file's hash in the image store.
    pub sha256: String,
    /// Bytes.
    pub size: i64,
}

impl Store {
    /// Whether a claim would find a job now (a read, so that idle workers
    /// polling the queue do not take the write lock).
    pub async fn claimable(&self) -> Result<bool, StoreError> {
        let (ready, expired) = self.queue_state().await?;
        Ok(ready || expired)
    }

    /// Whether a queued job is ready to be claimed, and whether a running
    /// job's lease has run out (one read).
    async fn queue_state(&self) -> Result<(bool, bool), StoreError> {
        let d = self.dialect;
        let (ready, expired): (i64, i64) = sqlx::query_as(&format!(
            "SELECT CASE WHEN EXISTS (SELECT 1 FROM jobs WHERE state = 'queued' \
             AND (not_before IS NULL OR not_before <= {now})) THEN 1 ELSE 0 END, \
             CASE WHEN EXISTS (SELECT 1 FROM jobs WHERE state = 'running' AND {expired}) \
             THEN 1 ELSE 0 END",
            now = d.now(),
            expired = d.lease_expired(),
        ))
        .fetch_one(&self.reader)
        .await?;
        Ok((ready == 1, expired == 1))
    }

    /// Claims the oldest queued job that is not deferred ([`Store::defer`])
    /// for `worker`, holding it for `lease`; first queues again the running
    /// jobs whose lease has run out ([`expire_leases`]), when a read before
    /// saw one. One write
    /// transaction; the claim is recorded in `job_claims`.
    pub async fn claim(
        &self,
        worker: &str,
        lease: Duration,
    ) -> Result<Option<ClaimedJob>, StoreError> {
        let (ready, expired) = self.queue_state().await?;
        if !(ready || expired) {
            return Ok(None);
        }
        let d = self.dialect;
        let mut tx = self.write_transaction().await?;
        // Only when the read saw a lease run out (two statements fewer per
        // claim otherwise: a round trip each on PostgreSQL); one that runs
        // out meanwhile is expired by the next claim.
        if expired {
            expire_leases(&mut tx, d).await?;
        }
        // The oldest ready job, taken in the same statement (on PostgreSQL
        // its row locked by the subquery, rows other claimers hold skipped).
        let job: Option<ClaimedJob> = sqlx::query_as(&format!(
            "UPDATE jobs SET state = 'running', attempts = attempts + 1, locked_by = $1, \
             lease_token = lease_token + 1, lease_until = {until}, started_at = {now} \
             WHERE id = (SELECT id FROM jobs WHERE state = 'queued' \
                         AND (not_before IS NULL OR not_before <= {now}) \
                         ORDER BY id LIMIT 1{skip_locked}) \
             AND state = 'queued' \
             RETURNING id, kind, payload, attempts, locked_by, lease_token",
            until = d.now_plus(2),
            now = d.now(),
            skip_locked = d.skip_locked(),
        ))
        .bind(worker)
        .bind(lease.as_secs_f64())
        .fetch_optional(&mut *tx)
        .await?;
        let Some(job) = job else {
            tx.commit().await?;
            return Ok(None);
        };
        sqlx::query("INSERT INTO job_claims (job_id, token, worker) VALUES ($1, $2, $3)")
            .bind(job.id)
            .bind(job.token)
            .bind(worker)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(Some(job))
    }

    /// Renews the lease of a job the worker holds for another `lease`
    /// (the heartbeat). False if the worker no longer holds it: another
    /// claim took it (its lease ran out), or the attempt ended.
    pub async fn renew(&self, job: &ClaimedJob, lease: Duration) -> Result<bool, StoreError> {
        let done = sqlx::query(&format!(
            "UPDATE jobs SET lease_until = {until} \
             WHERE id = $2 AND state = 'running' AND lease_token = $3",
            until = self.dialect.now_plus(1)
        ))
        .bind(lease.as_secs_f64())
        .bind(job.id)
        .bind(job.token)
        .execute(&self.writer)
        .await?;
        Ok(done.rows_affected() > 0)
    }

    /// Ends the worker's attempt at a job that it still holds: `set` (the
    /// job's new state and columns, binding `$1` and `$2` from `binds`),
    /// fenced on the claim's token, and the claim's outcome recorded, in
    /// one transaction. [`CompleteError::LostLease`] if the worker no
    /// longer holds the job (nothing written).
    async fn end_attempt(
        &self,
        job: &ClaimedJob,
        set: &str,
        binds: (Option<&str>, Option<f64>),
        outcome: ClaimOutcome,
    ) -> Result<(), CompleteError> {
        let mut tx = self.write_transaction().await?;
        let done = sqlx::query(&format!(
            "UPDATE jobs SET {set}, locked_by = NULL, lease_until = NULL \
             WHERE id = $3 AND state = 'running' AND lease_token = $4"
        ))
        .bind(binds.0)
        .bind(binds.1)
        .bind(job.id)
        .bind(job.token)
        .execute(&mut *tx)
        .await?;
        if done.rows_affected() == 0 {
            return Err(CompleteError::LostLease(job.id));
        }
        end_claim(&mut tx, self.dialect, job.id, job.token, outcome).await?;
        tx.commit().await?;
        Ok(())
    }

    /// Fails a job the worker holds.
    pub async fn fail(
        &self,
        job: &ClaimedJob,
        error: &str,
        duration_s: f64,
    ) -> Result<(), CompleteError> {
        self.end_attempt(
            job,
            &format!(
                "state = 'failed', error = $1, duration_s = $2, finished_at = {}",
                self.dialect.now()
            ),
            (Some(error), Some(duration_s)),
            ClaimOutcome::Failed,
        )
        .await
    }

    /// Returns a job the worker holds to the queue (its attempt failed for
    /// a passing reason).
    pub async fn release(
        &self,
        job: &ClaimedJob,
        error: Option<&str>,
    ) -> Result<(), CompleteError> {
        self.end_attempt(
            job,
            "state = 'queued', error = coalesce($1, error)",
            (error, None),
            ClaimOutcome::Released,
        )
        .await
    }

    /// Returns a job the worker holds to the queue without counting the
    /// claim (its attempt failed for want of disk space, which is not the
    /// job's fault): `attempts` goes back by one, `error` says why.
    pub async fn give_back(&self, job: &ClaimedJob, error: &str) -> Result<(), CompleteError> {
        self.end_attempt(
            job,
            "state = 'queued', attempts = CASE WHEN attempts > 0 THEN attempts - 1 ELSE 0 END, \
             error = $1",
            (Some(error), None),
            ClaimOutcome::GivenBack,
        )
        .await
    }

    /// Returns a job the worker holds to the queue without counting the
    /// claim, not to be claimed again for `delay_s` seconds: it waits for
    /// something other work provides (a sequence's computed background),
    /// and `note` says what. Other jobs are claimed meanwhile.
    pub async fn defer(
        &self,
        job: &ClaimedJob,
        note: &str,
        delay_s: f64,
    ) -> Result<(), CompleteError> {
        self.end_attempt(
            job,
            &format!(
                "state = 'queued', attempts = CASE WHEN attempts > 0 THEN attempts - 1 ELSE 0 END, \
                 error = $1, not_before = {}",
                self.dialect.now_plus(2)
            ),
            (Some(note), Some(delay_s)),
            ClaimOutcome::GivenBack,
        )
        .await
    }

    /// A job's claims in order (its attempt history): token, worker, when,
    /// and how each ended (`None` while it runs); at most the last `last`.
    pub async fn job_claims(&self, id: JobId, last: u32) -> Result<Vec<JobClaim>, StoreError> {
        let rows: Vec<(LeaseToken, String, String, Option<String>)> = sqlx::query_as(
            "SELECT * FROM (SELECT token, worker, claimed_at, outcome FROM job_claims \
             WHERE job_id = $1 ORDER BY token DESC LIMIT $2) AS last ORDER BY token",
        )
        .bind(id)
        .bind(i64::from(last))
        .fetch_all(&self.reader)
        .await?;
        rows.into_iter()
            .map(|(token, worker, claimed_at, outcome)| {
                Ok(JobClaim {
                    token,
                    worker,
                    claimed_at,
                    outcome: outcome.map(|o| decode_text("outcome", &o)).transpose()?,
                })
            })
            .collect()
    }

    /// Queues a failed job again with its attempts reset (`POST
    /// /jobs/{id}/retry`); its error stays until it runs. What it works on
    /// is still there: a frame's images and targets and a solve's files
    /// go only when their job succeeds.
    pub async fn retry(&self, id: JobId) -> Result<RetryOutcome, StoreError> {
        let mut tx = self.write_transaction().await?;
        let state: Option<(String,)> = sqlx::query_as("SELECT state FROM jobs WHERE id = $1")
            .bind(id)
            .fetch_optional(&mut *tx)
            .await?;
        let outcome = match state {
            None => RetryOutcome::Unknown,
            Some((state,)) => match decode_text("state", &state)? {
                JobState::Failed => {
                    sqlx::query(
                        "UPDATE jobs SET state = 'queued', attempts = 0, locked_by = NULL, \
                         finished_at = NULL, duration_s = NULL WHERE id = $1 AND state = 'failed'",
                    )
                    .bind(id)
                    .execute(&mut *tx)
                    .await?;
                    RetryOutcome::Queued
                }
                other => RetryOutcome::NotFailed(other),
            },
        };
        tx.commit().await?;
        Ok(outcome)
    }

    /// The reaper, run at start-up: the leases of jobs (and tracking runs)
    /// held by processes of this host that no longer exist (a kill, a crash: `alive` says
    /// whether a process id runs) end at once, instead of when they run
    /// out; then every running job whose lease has run out goes back to
    /// the queue, or fails once it has been claimed [`MAX_ATTEMPTS`]
    /// times (a job that kills its worker must not kill every restart).
    /// Jobs that live processes hold, here or on other hosts, are left to
    /// their leases. Returns (requeued, failed).
    pub async fn reap(
        &self,
        host: &str,
        alive: impl Fn(u32) -> bool,
    ) -> Result<(u64, u64), StoreError> {
        let mut tx = self.write_transaction().await?;
        let held: Vec<(JobId, LeaseToken, String)> = sqlx::query_as(
            "SELECT id, lease_token, locked_by FROM jobs \
             WHERE state = 'running' AND locked_by IS NOT NULL",
        )
        .fetch_all(&mut *tx)
        .await?;
        for (id, token, owner) in held {
            let dead = WorkerId::parse(&owner)
                .is_some_and(|(owner_host, pid)| owner_host == host && !alive(pid));
            if dead {
                sqlx::query(
                    "UPDATE jobs SET lease_until = NULL WHERE id = $1 AND lease_token = $2",
                )
                .bind(id)
                .bind(token)
                .execute(&mut *tx)
                .await?;
            }
        }
        let holders: Vec<(i64, String)> = sqlx::query_as(
            "SELECT id, lease_owner FROM tracking_runs WHERE lease_owner IS NOT NULL",
        )
        .fetch_all(&mut *tx)
        .await?;
        for (id, owner) in holders {
            let dead = WorkerId::parse(&owner)
                .is_some_and(|(owner_host, pid)| owner_host == host && !alive(pid));
            if dead {
                sqlx::query(
                    "UPDATE tracking_runs SET lease_owner = NULL, lease_until = NULL \
                     WHERE id = $1 AND lease_owner = $2",
                )
                .bind(id)
                .bind(&owner)
                .execute(&mut *tx)
                .await?;
            }
        }
        let outcome = expire_leases(&mut tx, self.dialect).await?;
        tx.commit().await?;
        Ok(outcome)
    }

    /// A job by id, with what its result is: the calibration that names
    /// it, or, once it succeeded, the frame that does.
    pub async fn job(&self, id: JobId) -> Result<Option<JobRow>, StoreError> {
        sqlx::query_as(
            "SELECT j.id, j.kind, j.payload, j.state, j.attempts, j.error, j.result, \
             j.created_at, j.started_at, j.finished_at, j.locked_by, j.lease_until, \
             c.id AS result_calibration, \
             f.sequence_id AS result_sequence, f.frame AS result_frame \
             FROM jobs j \
             LEFT JOIN calibrations c ON c.job_id = j.id \
             LEFT JOIN frames f ON f.job_id = j.id AND j.state = 'succeeded' \
             WHERE j.id = $1",
        )
        .bind(id)
        .fetch_optional(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// Jobs counted by kind and state.
    pub async fn job_counts(&self) -> Result<Vec<(String, String, i64)>, StoreError> {
        sqlx::query_as("SELECT kind, state, count(*) FROM jobs GROUP BY kind, state")
            .fetch_all(&self.reader)
            .await
            .map_err(StoreError::from)
    }

    /// Enqueues a job and records its input files in one transaction;
    /// returns the job's id.
    pub async fn enqueue_with_files(
        &self,
        kind: &str,
        payload: &str,
        files: &[JobFile],
    ) -> Result<JobId, StoreError> {
        let mut tx = self.write_transaction().await?;
        let id = enqueue(&mut tx, kind, payload).await?;
        for file in files {
            sqlx::query(
                "INSERT INTO job_files (job_id, part, camera, sha256, size) VALUES ($1, $2, $3, $4, $5)",
            )
            .bind(id)
            .bind(&file.part)
            .bind(file.camera)
            .bind(&file.sha256)
            .bind(file.size)
            .execute(&mut *tx)
            .await?;
        }
        tx.commit().await?;
        Ok(id)
    }

    /// A job's input files, in the order they were recorded.
    pub async fn job_files(&self, job_id: JobId) -> Result<Vec<JobFile>, StoreError> {
        let rows: Vec<(String, Option<i64>, String, i64)> = sqlx::query_as(
            "SELECT part, camera, sha256, size FROM job_files WHERE job_id = $1 ORDER BY rowid",
        )
        .bind(job_id)
        .fetch_all(&self.reader)
        .await?;
        Ok(rows
            .into_iter()
            .map(|(part, camera, sha256, size)| JobFile {
                part,
                camera,
                sha256,
                size,
            })
            .collect())
    }

    /// Completes a held job whose results are stored elsewhere (or that
    /// has none) with a link to its result ([`JobResult::Link`]).
    pub async fn succeed(
        &self,
        job: &ClaimedJob,
        result: &str,
        duration_s: f64,
    ) -> Result<(), CompleteError> {
        let mut tx = self.write_transaction().await?;
        finish(&mut tx, self.dialect, job, Some(result), duration_s).await?;
        tx.commit().await?;
        Ok(())
    }

    /// Enqueues a job on its own (e.g. solve_calibration, whose inputs are
    /// files already in the image store, named in the payload).
    pub async fn enqueue(&self, kind: &str, payload: &str) -> Result<JobId, StoreError> {
        let mut tx = self.write_transaction().await?;
        let id = enqueue(&mut tx, kind, payload).await?;
        tx.commit().await?;
        Ok(id)
    }

    /// Returns the jobs this process's workers hold to the queue (at a
    /// shutdown whose grace period ran out).
    pub async fn release_held(&self, instance: &str) -> Result<u64, StoreError> {
        let mut tx = self.write_transaction().await?;
        let held: Vec<(JobId, LeaseToken)> = sqlx::query_as(
            "UPDATE jobs SET state = 'queued', locked_by = NULL, lease_until = NULL \
             WHERE state = 'running' AND substr(locked_by, 1, length($1) + 1) = $1 || '/' \
             RETURNING id, lease_token",
        )
        .bind(instance)
        .fetch_all(&mut *tx)
        .await?;
        for (id, token) in &held {
            end_claim(&mut tx, self.dialect, *id, *token, ClaimOutcome::Released).await?;
        }
        tx.commit().await?;
        Ok(held.len() as u64)
    }
}

/// Enqueues a job inside the caller's transaction, so that the job exists
/// exactly when what it works on does.
pub async fn enqueue(
    tx: &mut Transaction<'_, Any>,
    kind: &str,
    payload: &str,
) -> Result<JobId, StoreError> {
    let (id,): (JobId,) =
        sqlx::query_as("INSERT INTO jobs (kind, payload) VALUES ($1, $2) RETURNING id")
            .bind(kind)
            .bind(payload)
            .fetch_one(&mut **tx)
            .await?;
    Ok(id)
}

/// Marks the held job succeeded inside the transaction that stores its
/// results; fails (and the caller rolls back) if the worker no longer holds
/// it. `link` is for kinds whose results no row names (the frame and
/// calibration rows name their jobs).
pub async fn finish(
    tx: &mut Transaction<'_, Any>,
    dialect: Dialect,
    job: &ClaimedJob,
    link: Option<&str>,
    duration_s: f64,
) -> Result<(), CompleteError> {
    let done = sqlx::query(&format!(
        "UPDATE jobs SET state = 'succeeded', result = $1, error = NULL, locked_by = NULL, \
         lease_until = NULL, duration_s = $2, finished_at = {} \
         WHERE id = $3 AND state = 'running' AND lease_token = $4",
        dialect.now()
    ))
    .bind(link)
    .bind(duration_s)
    .bind(job.id)
    .bind(job.token)
    .execute(&mut **tx)
    .await?;
    if done.rows_affected() == 0 {
        return Err(CompleteError::LostLease(job.id));
    }
    end_claim(tx, dialect, job.id, job.token, ClaimOutcome::Succeeded).await?;
    Ok(())
}

/// Records how a claim ended.
async fn end_claim(
    tx: &mut Transaction<'_, Any>,
    dialect: Dialect,
    id: JobId,
    token: LeaseToken,
    outcome: ClaimOutcome,
) -> Result<(), StoreError> {
    sqlx::query(&format!(
        "UPDATE job_claims SET outcome = $1, ended_at = {} \
         WHERE job_id = $2 AND token = $3 AND outcome IS NULL",
        dialect.now()
    ))
    .bind(outcome.as_str())
    .bind(id)
    .bind(token)
    .execute(&mut **tx)
    .await?;
    Ok(())
}

/// Queues again the running jobs whose lease has run out, or fails those
/// claimed [`MAX_ATTEMPTS`] times, recording their claims as expired;
/// inside the caller's write transaction (a claim, the reaper). Returns
/// (requeued, failed).
pub async fn expire_leases(
    tx: &mut Transaction<'_, Any>,
    dialect: Dialect,
) -> Result<(u64, u64), StoreError> {
    // On PostgreSQL, claimers expiring at once pass over each other's rows
    // (SKIP LOCKED) rather than wait for them, and cannot deadlock.
    let (now, expired, skip_locked) = (
        dialect.now(),
        dialect.lease_expired(),
        dialect.skip_locked(),
    );
    let failed: Vec<(JobId, LeaseToken)> = sqlx::query_as(&format!(
        "UPDATE jobs SET state = 'failed', locked_by = NULL, lease_until = NULL, \
         error = 'its worker stopped or lost its lease while running this job ' || attempts || \
                 ' times; it is not retried again', \
         finished_at = {now} \
         WHERE id IN (SELECT id FROM jobs \
                      WHERE state = 'running' AND {expired} AND attempts >= $1{skip_locked}) \
         RETURNING id, lease_token"
    ))
    .bind(MAX_ATTEMPTS)
    .fetch_all(&mut **tx)
    .await?;
    let requeued: Vec<(JobId, LeaseToken)> = sqlx::query_as(&format!(
        "UPDATE jobs SET state = 'queued', \
         error = 'the lease of ' || coalesce(locked_by, 'a stopped process') || \
                 ' ran out; queued again', \
         locked_by = NULL, lease_until = NULL \
         WHERE id IN (SELECT id FROM jobs WHERE state = 'running' AND {expired}{skip_locked}) \
         RETURNING id, lease_token"
    ))
    .fetch_all(&mut **tx)
    .await?;
    for (id, token) in failed.iter().chain(&requeued) {
        end_claim(tx, dialect, *id, *token, ClaimOutcome::Expired).await?;
    }
    Ok((requeued.len() as u64, failed.len() as u64))
}

/// How a claim of a job ended (`job_claims.outcome`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ClaimOutcome {
    /// The job succeeded with this claim's results.
    Succeeded,
    /// The job failed in this attempt.
    Failed,
    /// Queued again after a passing failure, or at a shutdown.
    Released,
    /// Queued again uncounted (a full disk; deferred).
    GivenBack,
    /// Its lease ran out (the worker died, hung or lost the database);
    /// queued again for another worker, or failed at the attempt limit.
    Expired,
}

stored_as_text!(ClaimOutcome, "claim outcome", {
    Succeeded => "succeeded",
    Failed => "failed",
    Released => "released",
    GivenBack => "given_back",
    Expired => "expired",
});

/// One claim of a job: its attempt history's line.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct JobClaim {
    /// The claim's fencing token.
    pub token: LeaseToken,
    /// The worker that claimed it.
    pub worker: String,
    /// When.
    pub claimed_at: String,
    /// How the attempt ended; `None` while it runs.
    pub outcome: Option<ClaimOutcome>,
}

/// A worker's name in claims and leases: `HOST:PID:RANDOM/INDEX`, the host
/// and process id so that a restarted process on the same host can tell
/// that the holder is gone, the random part so that a reused process id
/// is another owner.
pub struct WorkerId;

impl WorkerId {
    /// The name of this process's workers' prefix (`HOST:PID:RANDOM`).
    pub fn instance(host: &str) -> String {
        format!(
            "{host}:{}:{:08x}",
            std::process::id(),
            rand::random::<u32>()
        )
    }

    /// The host and process id of a worker's name; `None` for a name of
    /// another form (an older version's).
    pub fn parse(owner: &str) -> Option<(&str, u32)> {
        let instance = owner.split('/').next()?;
        let mut parts = instance.rsplitn(3, ':');
        let _random = parts.next()?;
        let pid = parts.next()?.parse().ok()?;
        let host = parts.next()?;
        Some((host, pid))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A row of the `jobs` table as `Store::job` reads it, with `state`.
    async fn job_row_with_state(state: &str) -> Result<JobRow, sqlx::Error> {
        sqlx::any::install_default_drivers();
        let pool = sqlx::any::AnyPoolOptions::new()
            .connect("sqlite::memory:")
            .await?;
        sqlx::query_as(
            "SELECT 7 AS id, 'process_frame' AS kind, '{}' AS payload, $1 AS state, \
             1 AS attempts, NULL AS error, NULL AS result, '2024-01-01T00:00:00Z' AS created_at, \
             NULL AS started_at, NULL AS finished_at, NULL AS locked_by, NULL AS lease_until, \
             NULL AS result_calibration, \
             NULL AS result_sequence, NULL AS result_frame",
        )
        .bind(state)
        .fetch_one(&pool)
        .await
    }

    #[test]
    fn worker_names_give_their_host_and_process() {
        let instance = WorkerId::instance("lab-pc.local");
        let worker = format!("{instance}/3");
        let (host, pid) = WorkerId::parse(&worker).unwrap();
        assert_eq!((host, pid), ("lab-pc.local", std::process::id()));
        // A host name with colons (an address) keeps them.
        assert_eq!(WorkerId::parse("fe80::1:42:ab/0"), Some(("fe80::1", 42)));
        // An older version's names, and names of no process.
        assert_eq!(WorkerId::parse("4242-1700000000/0"), None);
        assert_eq!(WorkerId::parse("killed/0"), None);
    }

    #[tokio::test]
    async fn a_stored_state_is_read_as_its_enum_and_an_unknown_one_is_named() {
        let row = job_row_with_state("succeeded").await.unwrap();
        assert_eq!(row.state, JobState::Succeeded);
        let error = job_row_with_state("paused").await.unwrap_err();
        assert!(
            matches!(&error, sqlx::Error::ColumnDecode { index, .. } if index == "state"),
            "{error:?}"
        );
        let message = error.to_string();
        assert!(
            message.contains(
                "unknown job state `paused`; this version knows queued, running, succeeded, failed"
            ),
            "{message}"
        );
    }
}
