//! The job queue: enqueue, claim, complete, fail, release, reap; and the
//! input files of jobs that are not frames.

use sqlx::sqlite::SqliteRow;
use sqlx::{FromRow, Row, Sqlite, Transaction};

use super::{
    decode_text, stored_as_text, text_column, CalibrationId, CompleteError, FrameNumber, JobId,
    SequenceId, Store,
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
    fn of(row: &SqliteRow) -> Result<Option<JobResult>, sqlx::Error> {
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
    /// Who holds it; completion is refused to anyone else.
    pub locked_by: String,
}

impl FromRow<'_, SqliteRow> for JobRow {
    fn from_row(row: &SqliteRow) -> Result<Self, sqlx::Error> {
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
        })
    }
}

impl FromRow<'_, SqliteRow> for ClaimedJob {
    fn from_row(row: &SqliteRow) -> Result<Self, sqlx::Error> {
        Ok(ClaimedJob {
            id: row.try_get("id")?,
            kind: row.try_get("kind")?,
            payload: row.try_get("payload")?,
            attempts: row.try_get("attempts")?,
            locked_by: row.try_get("locked_by")?,
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
    /// Claims the oldest queued job for `worker` that is not deferred
    /// ([`Store::defer`]), in one statement.
    pub async fn claim(&self, worker: &str) -> Result<Option<ClaimedJob>, sqlx::Error> {
        sqlx::query_as(
            "UPDATE jobs SET state = 'running', attempts = attempts + 1, locked_by = ?1, \
             started_at = strftime('%Y-%m-%dT%H:%M:%fZ', 'now') \
             WHERE id = (SELECT id FROM jobs WHERE state = 'queued' \
                         AND (not_before IS NULL \
                              OR not_before <= strftime('%Y-%m-%dT%H:%M:%fZ', 'now')) \
                         ORDER BY id LIMIT 1) \
             RETURNING id, kind, payload, attempts, locked_by",
        )
        .bind(worker)
        .fetch_optional(&self.writer)
        .await
    }

    /// Fails a job the worker holds.
    pub async fn fail(
        &self,
        job: &ClaimedJob,
        error: &str,
        duration_s: f64,
    ) -> Result<(), CompleteError> {
        let done = sqlx::query(
            "UPDATE jobs SET state = 'failed', error = ?, locked_by = NULL, duration_s = ?, \
             finished_at = strftime('%Y-%m-%dT%H:%M:%fZ', 'now') \
             WHERE id = ? AND state = 'running' AND locked_by = ?",
        )
        .bind(error)
        .bind(duration_s)
        .bind(job.id)
        .bind(&job.locked_by)
        .execute(&self.writer)
        .await?;
        if done.rows_affected() == 0 {
            return Err(CompleteError::LostLease(job.id));
        }
        Ok(())
    }

    /// Returns a job the worker holds to the queue (its attempt failed for
    /// a passing reason, or the service is stopping).
    pub async fn release(&self, job: &ClaimedJob, error: Option<&str>) -> Result<(), sqlx::Error> {
        sqlx::query(
            "UPDATE jobs SET state = 'queued', error = coalesce(?, error), locked_by = NULL \
             WHERE id = ? AND state = 'running' AND locked_by = ?",
        )
        .bind(error)
        .bind(job.id)
        .bind(&job.locked_by)
        .execute(&self.writer)
        .await?;
        Ok(())
    }

    /// Returns a job the worker holds to the queue without counting the
    /// claim (its attempt failed for want of disk space, which is not the
    /// job's fault): `attempts` goes back by one, `error` says why.
    pub async fn give_back(&self, job: &ClaimedJob, error: &str) -> Result<(), sqlx::Error> {
        sqlx::query(
            "UPDATE jobs SET state = 'queued', attempts = max(attempts - 1, 0), error = ?, \
             locked_by = NULL WHERE id = ? AND state = 'running' AND locked_by = ?",
        )
        .bind(error)
        .bind(job.id)
        .bind(&job.locked_by)
        .execute(&self.writer)
        .await?;
        Ok(())
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
    ) -> Result<(), sqlx::Error> {
        sqlx::query(
            "UPDATE jobs SET state = 'queued', attempts = max(attempts - 1, 0), error = ?, \
             locked_by = NULL, \
             not_before = strftime('%Y-%m-%dT%H:%M:%fZ', 'now', printf('+%.3f seconds', ?)) \
             WHERE id = ? AND state = 'running' AND locked_by = ?",
        )
        .bind(note)
        .bind(delay_s)
        .bind(job.id)
        .bind(&job.locked_by)
        .execute(&self.writer)
        .await?;
        Ok(())
    }

    /// Queues a failed job again with its attempts reset (`POST
    /// /jobs/{id}/retry`); its error stays until it runs. What it works on
    /// is still there: a frame's images and targets and a solve's files
    /// go only when their job succeeds.
    pub async fn retry(&self, id: JobId) -> Result<RetryOutcome, sqlx::Error> {
        let mut tx = self.write_transaction().await?;
        let state: Option<(String,)> = sqlx::query_as("SELECT state FROM jobs WHERE id = ?")
            .bind(id)
            .fetch_optional(&mut *tx)
            .await?;
        let outcome = match state {
            None => RetryOutcome::Unknown,
            Some((state,)) => match decode_text("state", &state)? {
                JobState::Failed => {
                    sqlx::query(
                        "UPDATE jobs SET state = 'queued', attempts = 0, locked_by = NULL, \
                         finished_at = NULL, duration_s = NULL WHERE id = ?",
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

    /// The reaper, run at start-up before any worker: a job left running
    /// by a process that died goes back to the queue, or fails once it has
    /// been claimed [`MAX_ATTEMPTS`] times (a job that kills its worker
    /// must not kill every restart). Returns (requeued, failed).
    pub async fn reap(&self) -> Result<(u64, u64), sqlx::Error> {
        let mut tx = self.write_transaction().await?;
        let failed = sqlx::query(
            "UPDATE jobs SET state = 'failed', locked_by = NULL, \
             error = 'the service stopped while running this job ' || attempts || \
                     ' times; it is not retried again', \
             finished_at = strftime('%Y-%m-%dT%H:%M:%fZ', 'now') \
             WHERE state = 'running' AND attempts >= ?",
        )
        .bind(MAX_ATTEMPTS)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        let requeued = sqlx::query(
            "UPDATE jobs SET state = 'queued', locked_by = NULL WHERE state = 'running'",
        )
        .execute(&mut *tx)
        .await?
        .rows_affected();
        tx.commit().await?;
        Ok((requeued, failed))
    }

    /// A job by id, with what its result is: the calibration that names
    /// it, or, once it succeeded, the frame that does.
    pub async fn job(&self, id: JobId) -> Result<Option<JobRow>, sqlx::Error> {
        sqlx::query_as(
            "SELECT j.id, j.kind, j.payload, j.state, j.attempts, j.error, j.result, \
             j.created_at, j.started_at, j.finished_at, c.id AS result_calibration, \
             f.sequence_id AS result_sequence, f.frame AS result_frame \
             FROM jobs j \
             LEFT JOIN calibrations c ON c.job_id = j.id \
             LEFT JOIN frames f ON f.job_id = j.id AND j.state = 'succeeded' \
             WHERE j.id = ?",
        )
        .bind(id)
        .fetch_optional(&self.reader)
        .await
    }

    /// Jobs counted by kind and state.
    pub async fn job_counts(&self) -> Result<Vec<(String, String, i64)>, sqlx::Error> {
        sqlx::query_as("SELECT kind, state, count(*) FROM jobs GROUP BY kind, state")
            .fetch_all(&self.reader)
            .await
    }

    /// Enqueues a job and records its input files in one transaction;
    /// returns the job's id.
    pub async fn enqueue_with_files(
        &self,
        kind: &str,
        payload: &str,
        files: &[JobFile],
    ) -> Result<JobId, sqlx::Error> {
        let mut tx = self.write_transaction().await?;
        let id = enqueue(&mut tx, kind, payload).await?;
        for file in files {
            sqlx::query(
                "INSERT INTO job_files (job_id, part, camera, sha256, size) VALUES (?, ?, ?, ?, ?)",
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
    pub async fn job_files(&self, job_id: JobId) -> Result<Vec<JobFile>, sqlx::Error> {
        let rows: Vec<(String, Option<i64>, String, i64)> = sqlx::query_as(
            "SELECT part, camera, sha256, size FROM job_files WHERE job_id = ? ORDER BY rowid",
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
        finish(&mut tx, job, Some(result), duration_s).await?;
        tx.commit().await?;
        Ok(())
    }

    /// Enqueues a job on its own (e.g. solve_calibration, whose inputs are
    /// files already in the image store, named in the payload).
    pub async fn enqueue(&self, kind: &str, payload: &str) -> Result<JobId, sqlx::Error> {
        let mut tx = self.write_transaction().await?;
        let id = enqueue(&mut tx, kind, payload).await?;
        tx.commit().await?;
        Ok(id)
    }

    /// Returns the jobs this process's workers hold to the queue (at a
    /// shutdown whose grace period ran out).
    pub async fn release_held(&self, instance: &str) -> Result<u64, sqlx::Error> {
        Ok(sqlx::query(
            "UPDATE jobs SET state = 'queued', locked_by = NULL \
             WHERE state = 'running' AND substr(locked_by, 1, length(?1) + 1) = ?1 || '/'",
        )
        .bind(instance)
        .execute(&self.writer)
        .await?
        .rows_affected())
    }
}

/// Enqueues a job inside the caller's transaction, so that the job exists
/// exactly when what it works on does.
pub async fn enqueue(
    tx: &mut Transaction<'_, Sqlite>,
    kind: &str,
    payload: &str,
) -> Result<JobId, sqlx::Error> {
    let (id,): (JobId,) =
        sqlx::query_as("INSERT INTO jobs (kind, payload) VALUES (?, ?) RETURNING id")
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
    tx: &mut Transaction<'_, Sqlite>,
    job: &ClaimedJob,
    link: Option<&str>,
    duration_s: f64,
) -> Result<(), CompleteError> {
    let done = sqlx::query(
        "UPDATE jobs SET state = 'succeeded', result = ?, error = NULL, locked_by = NULL, \
         duration_s = ?, finished_at = strftime('%Y-%m-%dT%H:%M:%fZ', 'now') \
         WHERE id = ? AND state = 'running' AND locked_by = ?",
    )
    .bind(link)
    .bind(duration_s)
    .bind(job.id)
    .bind(&job.locked_by)
    .execute(&mut **tx)
    .await?;
    if done.rows_affected() == 0 {
        return Err(CompleteError::LostLease(job.id));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A row of the `jobs` table as `Store::job` reads it, with `state`.
    async fn job_row_with_state(state: &str) -> Result<JobRow, sqlx::Error> {
        let pool = sqlx::sqlite::SqlitePoolOptions::new()
            .connect("sqlite::memory:")
            .await?;
        sqlx::query_as(
            "SELECT 7 AS id, 'process_frame' AS kind, '{}' AS payload, ? AS state, \
             1 AS attempts, NULL AS error, NULL AS result, '2024-01-01T00:00:00Z' AS created_at, \
             NULL AS started_at, NULL AS finished_at, NULL AS result_calibration, \
             NULL AS result_sequence, NULL AS result_frame",
        )
        .bind(state)
        .fetch_one(&pool)
        .await
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
