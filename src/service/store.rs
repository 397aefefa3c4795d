//! All of the service's SQL: calibrations, sequences, frames and their
//! inputs and results, and the job queue, in one SQLite database.
//!
//! SQLite runs in WAL mode (readers never wait for the writer) with a busy
//! timeout. Writes go through a pool of one connection, so they queue in
//! the process instead of failing on SQLite's lock; reads use their own
//! pool. Every multi-statement write is one transaction: an upload and its
//! job, a job's results and its completion. Queries are checked at run
//! time (no database at build time); their results map onto `FromRow`
//! structs (`FromRow` written out, no derive macros).

use std::path::Path;
use std::str::FromStr;
use std::time::Duration;

use std::future::Future;
use std::pin::Pin;

use serde::{Deserialize, Serialize};
use sqlx::error::BoxDynError;
use sqlx::migrate::{Migration, MigrationSource, MigrationType, Migrator};
use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteRow,
    SqliteSynchronous,
};
use sqlx::{FromRow, Row, Sqlite, Transaction};

/// How often a job may be claimed before a crash-looping one is failed.
pub const MAX_ATTEMPTS: i64 = 3;

/// The database.
#[derive(Clone, Debug)]
pub struct Store {
    /// Readers, several at once.
    reader: SqlitePool,
    /// The one writer.
    writer: SqlitePool,
}

/// A stored calibration.
#[derive(Clone, Debug)]
pub struct CalibrationRow {
    /// Its id.
    pub id: i64,
    /// The calibration JSON.
    pub model: String,
    /// How many cameras.
    pub cameras: i64,
    /// The resection report (JSON), if solved.
    pub report: Option<String>,
    /// When it was stored.
    pub created_at: String,
}

/// A stored sequence.
#[derive(Clone, Debug)]
pub struct SequenceRow {
    /// Its id.
    pub id: i64,
    /// Its calibration.
    pub calibration_id: i64,
    /// Its name.
    pub name: String,
    /// Detection and matching parameters (JSON).
    pub parameters: String,
    /// Whether images are kept after processing.
    pub keep_images: bool,
    /// When it was created.
    pub created_at: String,
}

/// A job's state.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
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

impl JobState {
    /// Every state, in the order of a job's life.
    pub const ALL: [JobState; 4] = [
        JobState::Queued,
        JobState::Running,
        JobState::Succeeded,
        JobState::Failed,
    ];

    /// The name stored in the database.
    pub fn as_str(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Succeeded => "succeeded",
            JobState::Failed => "failed",
        }
    }
}

impl FromStr for JobState {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        JobState::ALL
            .into_iter()
            .find(|state| state.as_str() == s)
            .ok_or_else(|| format!("unknown job state `{s}`"))
    }
}

/// A stored job.
#[derive(Clone, Debug)]
pub struct JobRow {
    /// Its id.
    pub id: i64,
    /// Its kind.
    pub kind: String,
    /// What it works on (JSON).
    pub payload: String,
    /// queued, running, succeeded or failed.
    pub state: String,
    /// How often a worker claimed it.
    pub attempts: i64,
    /// Why it failed (or why its last attempt did).
    pub error: Option<String>,
    /// Where its result is.
    pub result: Option<String>,
    /// Enqueued at.
    pub created_at: String,
    /// Last claimed at.
    pub started_at: Option<String>,
    /// Finished at.
    pub finished_at: Option<String>,
}

/// A job a worker has claimed.
#[derive(Clone, Debug)]
pub struct ClaimedJob {
    /// Its id.
    pub id: i64,
    /// Its kind.
    pub kind: String,
    /// What it works on (JSON).
    pub payload: String,
    /// This claim's number, from 1.
    pub attempts: i64,
    /// Who holds it; completion is refused to anyone else.
    pub locked_by: String,
}

/// A frame upload to store with its job.
#[derive(Clone, Debug)]
pub struct NewFrame {
    /// The sequence.
    pub sequence_id: i64,
    /// The frame number.
    pub frame: i64,
    /// `images` or `targets`.
    pub input: &'static str,
    /// The raw images' layout (JSON), if raw.
    pub raw_layout: Option<String>,
    /// Per camera, the image's hash and size.
    pub images: Vec<(i64, String, i64)>,
    /// Per camera, uploaded targets: count and blob.
    pub targets: Vec<(i64, i64, Vec<u8>)>,
}

/// What a process_frame job needs.
#[derive(Clone, Debug)]
pub struct FrameInput {
    /// The sequence.
    pub sequence_id: i64,
    /// The frame.
    pub frame: i64,
    /// `images` or `targets`.
    pub input: String,
    /// The raw layout (JSON), if raw.
    pub raw_layout: Option<String>,
    /// The sequence's calibration.
    pub calibration_id: i64,
}

/// Counts of a sequence's frames by their job's state.
#[derive(Clone, Copy, Debug, Default)]
pub struct FrameCounts {
    /// Waiting.
    pub queued: i64,
    /// Being processed.
    pub running: i64,
    /// Processed.
    pub done: i64,
    /// Failed.
    pub failed: i64,
}

/// The schema's migrations, `migrations/*.sql`, compiled into the binary
/// (what `sqlx::migrate!` does, without its proc-macro, which would build
/// SQLite a second time for the compiler).
#[derive(Debug)]
struct Migrations;

/// Version, description and SQL of each migration, in order.
const MIGRATIONS: &[(i64, &str, &str)] = &[
    (
        1,
        "service",
        include_str!("../../migrations/0001_service.sql"),
    ),
    (
        2,
        "job_files",
        include_str!("../../migrations/0002_job_files.sql"),
    ),
];

impl<'s> MigrationSource<'s> for Migrations {
    fn resolve(
        self,
    ) -> Pin<Box<dyn Future<Output = Result<Vec<Migration>, BoxDynError>> + Send + 's>> {
        Box::pin(async {
            Ok(MIGRATIONS
                .iter()
                .map(|(version, description, sql)| {
                    Migration::new(
                        *version,
                        (*description).into(),
                        MigrationType::Simple,
                        (*sql).into(),
                        false,
                    )
                })
                .collect())
        })
    }
}

impl FromRow<'_, SqliteRow> for CalibrationRow {
    fn from_row(row: &SqliteRow) -> Result<Self, sqlx::Error> {
        Ok(CalibrationRow {
            id: row.try_get("id")?,
            model: row.try_get("model")?,
            cameras: row.try_get("cameras")?,
            report: row.try_get("report")?,
            created_at: row.try_get("created_at")?,
        })
    }
}

impl FromRow<'_, SqliteRow> for SequenceRow {
    fn from_row(row: &SqliteRow) -> Result<Self, sqlx::Error> {
        Ok(SequenceRow {
            id: row.try_get("id")?,
            calibration_id: row.try_get("calibration_id")?,
            name: row.try_get("name")?,
            parameters: row.try_get("parameters")?,
            keep_images: row.try_get("keep_images")?,
            created_at: row.try_get("created_at")?,
        })
    }
}

impl FromRow<'_, SqliteRow> for JobRow {
    fn from_row(row: &SqliteRow) -> Result<Self, sqlx::Error> {
        Ok(JobRow {
            id: row.try_get("id")?,
            kind: row.try_get("kind")?,
            payload: row.try_get("payload")?,
            state: row.try_get("state")?,
            attempts: row.try_get("attempts")?,
            error: row.try_get("error")?,
            result: row.try_get("result")?,
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

impl FromRow<'_, SqliteRow> for FrameInput {
    fn from_row(row: &SqliteRow) -> Result<Self, sqlx::Error> {
        Ok(FrameInput {
            sequence_id: row.try_get("sequence_id")?,
            frame: row.try_get("frame")?,
            input: row.try_get("input")?,
            raw_layout: row.try_get("raw_layout")?,
            calibration_id: row.try_get("calibration_id")?,
        })
    }
}

/// Why a frame could not be stored.
#[derive(Debug, thiserror::Error)]
pub enum InsertFrameError {
    /// The frame number is taken.
    #[error("frame {0} exists")]
    Exists(i64),
    /// The database failed.
    #[error(transparent)]
    Database(#[from] sqlx::Error),
}

/// A completion that the job's holder may no longer make.
#[derive(Debug, thiserror::Error)]
pub enum CompleteError {
    /// The job is no longer running under this worker.
    #[error("job {0} is no longer held by this worker")]
    LostLease(i64),
    /// The database failed.
    #[error(transparent)]
    Database(#[from] sqlx::Error),
}

/// Whether an error is SQLite's unique or primary-key violation.
fn is_unique_violation(error: &sqlx::Error) -> bool {
    matches!(error, sqlx::Error::Database(e) if e.is_unique_violation())
}

impl Store {
    /// Opens (creating if missing) the database `ptv.sqlite` in
    /// `data_dir` and brings its schema up to date.
    pub async fn open(data_dir: &Path, readers: u32) -> Result<Store, sqlx::Error> {
        let options = SqliteConnectOptions::new()
            .filename(data_dir.join("ptv.sqlite"))
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            // In WAL mode NORMAL survives a crash of the process (a kill);
            // only a power loss may lose the last transactions.
            .synchronous(SqliteSynchronous::Normal)
            .busy_timeout(Duration::from_secs(10))
            .foreign_keys(true);
        let writer = SqlitePoolOptions::new()
            .max_connections(1)
            .connect_with(options.clone())
            .await?;
        Migrator::new(Migrations)
            .await
            .map_err(sqlx::Error::from)?
            .run(&writer)
            .await?;
        let reader = SqlitePoolOptions::new()
            .max_connections(readers.max(1))
            .connect_with(options.read_only(true))
            .await?;
        Ok(Store { reader, writer })
    }

    /// Starts a write transaction with `BEGIN IMMEDIATE`: it takes SQLite's
    /// write lock at once, so a transaction that reads before it writes never
    /// finds its snapshot stale when it comes to write (a deferred `BEGIN`
    /// would then fail with SQLITE_BUSY whatever the busy timeout), also
    /// with several processes on one database.
    async fn write_transaction(
        &self,
    ) -> Result<sqlx::Transaction<'static, sqlx::Sqlite>, sqlx::Error> {
        self.writer.begin_with("BEGIN IMMEDIATE").await
    }

    /// Closes both pools.
    pub async fn close(&self) {
        self.writer.close().await;
        self.reader.close().await;
    }

    // ---- calibrations ----

    /// Stores a calibration.
    pub async fn insert_calibration(
        &self,
        model: &str,
        cameras: i64,
        report: Option<&str>,
    ) -> Result<CalibrationRow, sqlx::Error> {
        let mut tx = self.write_transaction().await?;
        let row = insert_calibration(&mut tx, model, cameras, report).await?;
        tx.commit().await?;
        Ok(row)
    }

    /// A calibration by id.
    pub async fn calibration(&self, id: i64) -> Result<Option<CalibrationRow>, sqlx::Error> {
        sqlx::query_as(
            "SELECT id, model, cameras, report, created_at FROM calibrations WHERE id = ?",
        )
        .bind(id)
        .fetch_optional(&self.reader)
        .await
    }

    // ---- sequences ----

    /// Stores a sequence; `None` if its calibration does not exist.
    pub async fn insert_sequence(
        &self,
        calibration_id: i64,
        name: &str,
        parameters: &str,
        keep_images: bool,
    ) -> Result<Option<SequenceRow>, sqlx::Error> {
        let result = sqlx::query_as(
            "INSERT INTO sequences (calibration_id, name, parameters, keep_images) \
             SELECT id, ?, ?, ? FROM calibrations WHERE id = ? \
             RETURNING id, calibration_id, name, parameters, keep_images, created_at",
        )
        .bind(name)
        .bind(parameters)
        .bind(keep_images)
        .bind(calibration_id)
        .fetch_optional(&self.writer)
        .await?;
        Ok(result)
    }

    /// A sequence by id.
    pub async fn sequence(&self, id: i64) -> Result<Option<SequenceRow>, sqlx::Error> {
        sqlx::query_as(
            "SELECT id, calibration_id, name, parameters, keep_images, created_at \
             FROM sequences WHERE id = ?",
        )
        .bind(id)
        .fetch_optional(&self.reader)
        .await
    }

    /// A sequence's frames counted by their job's state.
    pub async fn frame_counts(&self, sequence_id: i64) -> Result<FrameCounts, sqlx::Error> {
        let rows: Vec<(String, i64)> = sqlx::query_as(
            "SELECT j.state, count(*) FROM frames f JOIN jobs j ON j.id = f.job_id \
             WHERE f.sequence_id = ? GROUP BY j.state",
        )
        .bind(sequence_id)
        .fetch_all(&self.reader)
        .await?;
        let mut counts = FrameCounts::default();
        for (state, count) in rows {
            match state.parse() {
                Ok(JobState::Queued) => counts.queued = count,
                Ok(JobState::Running) => counts.running = count,
                Ok(JobState::Succeeded) => counts.done = count,
                Ok(JobState::Failed) => counts.failed = count,
                Err(_) => {}
            }
        }
        Ok(counts)
    }

    // ---- frames ----

    /// Stores an uploaded frame, its inputs and its process_frame job in
    /// one transaction; returns the job's id.
    pub async fn insert_frame(&self, frame: &NewFrame) -> Result<i64, InsertFrameError> {
        let mut tx = self.write_transaction().await?;
        let payload =
            serde_json::json!({"sequence_id": frame.sequence_id, "frame": frame.frame}).to_string();
        let job_id = enqueue(&mut tx, super::jobs::PROCESS_FRAME, &payload).await?;
        let inserted = sqlx::query(
            "INSERT INTO frames (sequence_id, frame, job_id, input, raw_layout) \
             VALUES (?, ?, ?, ?, ?)",
        )
        .bind(frame.sequence_id)
        .bind(frame.frame)
        .bind(job_id)
        .bind(frame.input)
        .bind(&frame.raw_layout)
        .execute(&mut *tx)
        .await;
        match inserted {
            Err(e) if is_unique_violation(&e) => return Err(InsertFrameError::Exists(frame.frame)),
            other => other?,
        };
        for (camera, sha256, size) in &frame.images {
            sqlx::query(
                "INSERT INTO images (sequence_id, frame, camera, sha256, size) \
                 VALUES (?, ?, ?, ?, ?)",
            )
            .bind(frame.sequence_id)
            .bind(frame.frame)
            .bind(camera)
            .bind(sha256)
            .bind(size)
            .execute(&mut *tx)
            .await?;
        }
        for (camera, count, data) in &frame.targets {
            insert_targets(
                &mut tx,
                frame.sequence_id,
                frame.frame,
                *camera,
                *count,
                data,
            )
            .await?;
        }
        tx.commit().await?;
        Ok(job_id)
    }

    /// What a process_frame job needs to know about its frame.
    pub async fn frame_input(
        &self,
        sequence_id: i64,
        frame: i64,
    ) -> Result<Option<FrameInput>, sqlx::Error> {
        sqlx::query_as(
            "SELECT f.sequence_id, f.frame, f.input, f.raw_layout, s.calibration_id \
             FROM frames f JOIN sequences s ON s.id = f.sequence_id \
             WHERE f.sequence_id = ? AND f.frame = ?",
        )
        .bind(sequence_id)
        .bind(frame)
        .fetch_optional(&self.reader)
        .await
    }

    /// A frame's images: camera and hash, in camera order.
    pub async fn frame_images(
        &self,
        sequence_id: i64,
        frame: i64,
    ) -> Result<Vec<(i64, String)>, sqlx::Error> {
        sqlx::query_as(
            "SELECT camera, sha256 FROM images WHERE sequence_id = ? AND frame = ? \
             ORDER BY camera",
        )
        .bind(sequence_id)
        .bind(frame)
        .fetch_all(&self.reader)
        .await
    }

    /// Whether any frame or job refers to the file with this hash.
    pub async fn image_in_use(&self, sha256: &str) -> Result<bool, sqlx::Error> {
        let mut conn = self.writer.acquire().await?;
        file_in_use(&mut conn, sha256).await
    }

    /// A frame's targets per camera (count and blob), in camera order.
    pub async fn frame_targets(
        &self,
        sequence_id: i64,
        frame: i64,
    ) -> Result<Vec<(i64, i64, Vec<u8>)>, sqlx::Error> {
        sqlx::query_as(
            "SELECT camera, count, data FROM targets WHERE sequence_id = ? AND frame = ? \
             ORDER BY camera",
        )
        .bind(sequence_id)
        .bind(frame)
        .fetch_all(&self.reader)
        .await
    }

    /// Whether the frame exists.
    pub async fn frame_exists(&self, sequence_id: i64, frame: i64) -> Result<bool, sqlx::Error> {
        let row: Option<(i64,)> =
            sqlx::query_as("SELECT job_id FROM frames WHERE sequence_id = ? AND frame = ?")
                .bind(sequence_id)
                .bind(frame)
                .fetch_optional(&self.reader)
                .await?;
        Ok(row.is_some())
    }

    /// A frame's particles (count and blob), if processed.
    pub async fn frame_particles(
        &self,
        sequence_id: i64,
        frame: i64,
    ) -> Result<Option<(i64, Vec<u8>)>, sqlx::Error> {
        sqlx::query_as("SELECT count, data FROM particles WHERE sequence_id = ? AND frame = ?")
            .bind(sequence_id)
            .bind(frame)
            .fetch_optional(&self.reader)
            .await
    }

    /// The processed frames of a sequence, in order.
    pub async fn processed_frames(&self, sequence_id: i64) -> Result<Vec<i64>, sqlx::Error> {
        let rows: Vec<(i64,)> =
            sqlx::query_as("SELECT frame FROM particles WHERE sequence_id = ? ORDER BY frame")
                .bind(sequence_id)
                .fetch_all(&self.reader)
                .await?;
        Ok(rows.into_iter().map(|(f,)| f).collect())
    }

    /// Stores a processed frame's results and completes its job, in one
    /// transaction: `targets` (detected; empty when they were uploaded),
    /// the particles, and, when the sequence does not keep images, the
    /// removal of the frame's image rows. Returns the hashes of the images
    /// no frame refers to any more, whose files may go.
    pub async fn complete_frame(
        &self,
        job: &ClaimedJob,
        input: &FrameInput,
        targets: &[(i64, i64, Vec<u8>)],
        particles: (i64, &[u8]),
        drop_images: bool,
        duration_s: f64,
    ) -> Result<Vec<String>, CompleteError> {
        let (sequence_id, frame) = (input.sequence_id, input.frame);
        let mut tx = self.write_transaction().await?;
        let result = format!("/api/v1/sequences/{sequence_id}/frames/{frame}/particles");
        finish(&mut tx, job, &result, duration_s).await?;
        for (camera, count, data) in targets {
            insert_targets(&mut tx, sequence_id, frame, *camera, *count, data).await?;
        }
        sqlx::query("INSERT INTO particles (sequence_id, frame, count, data) VALUES (?, ?, ?, ?)")
            .bind(sequence_id)
            .bind(frame)
            .bind(particles.0)
            .bind(particles.1)
            .execute(&mut *tx)
            .await?;
        let mut orphans = Vec::new();
        if drop_images {
            let hashes: Vec<(String,)> = sqlx::query_as(
                "DELETE FROM images WHERE sequence_id = ? AND frame = ? RETURNING sha256",
            )
            .bind(sequence_id)
            .bind(frame)
            .fetch_all(&mut *tx)
            .await?;
            for (hash,) in hashes {
                if !file_in_use(&mut tx, &hash).await? {
                    orphans.push(hash);
                }
            }
        }
        tx.commit().await?;
        Ok(orphans)
    }

    // ---- jobs ----

    /// Claims the oldest queued job for `worker`, in one statement.
    pub async fn claim(&self, worker: &str) -> Result<Option<ClaimedJob>, sqlx::Error> {
        sqlx::query_as(
            "UPDATE jobs SET state = 'running', attempts = attempts + 1, locked_by = ?1, \
             started_at = strftime('%Y-%m-%dT%H:%M:%fZ', 'now') \
             WHERE id = (SELECT id FROM jobs WHERE state = 'queued' ORDER BY id LIMIT 1) \
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

    /// A job by id.
    pub async fn job(&self, id: i64) -> Result<Option<JobRow>, sqlx::Error> {
        sqlx::query_as(
            "SELECT id, kind, payload, state, attempts, error, result, created_at, started_at, \
             finished_at FROM jobs WHERE id = ?",
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
}

/// Whether any frame's image or job's file is the file with this hash.
async fn file_in_use(conn: &mut sqlx::SqliteConnection, sha256: &str) -> Result<bool, sqlx::Error> {
    let (n,): (i64,) = sqlx::query_as(
        "SELECT (SELECT count(*) FROM images WHERE sha256 = ?1) + \
                (SELECT count(*) FROM job_files WHERE sha256 = ?1)",
    )
    .bind(sha256)
    .fetch_one(&mut *conn)
    .await?;
    Ok(n > 0)
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
    /// Enqueues a job and records its input files in one transaction;
    /// returns the job's id.
    pub async fn enqueue_with_files(
        &self,
        kind: &str,
        payload: &str,
        files: &[JobFile],
    ) -> Result<i64, sqlx::Error> {
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
    pub async fn job_files(&self, job_id: i64) -> Result<Vec<JobFile>, sqlx::Error> {
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

    /// Stores a solved calibration with its report and completes its job,
    /// in one transaction; unless `keep_files`, the job's file rows go too.
    /// Returns the calibration's id and the hashes of the files nothing
    /// refers to any more, whose files may go.
    pub async fn complete_calibration(
        &self,
        job: &ClaimedJob,
        model: &str,
        cameras: i64,
        report: &str,
        keep_files: bool,
        duration_s: f64,
    ) -> Result<(i64, Vec<String>), CompleteError> {
        let mut tx = self.write_transaction().await?;
        let row = insert_calibration(&mut tx, model, cameras, Some(report)).await?;
        let result = format!("/api/v1/calibrations/{}", row.id);
        finish(&mut tx, job, &result, duration_s).await?;
        let mut orphans = Vec::new();
        if !keep_files {
            let hashes: Vec<(String,)> =
                sqlx::query_as("DELETE FROM job_files WHERE job_id = ? RETURNING sha256")
                    .bind(job.id)
                    .fetch_all(&mut *tx)
                    .await?;
            for (hash,) in hashes {
                if !orphans.contains(&hash) && !file_in_use(&mut tx, &hash).await? {
                    orphans.push(hash);
                }
            }
        }
        tx.commit().await?;
        Ok((row.id, orphans))
    }
}

/// Enqueues a job inside the caller's transaction, so that the job exists
/// exactly when what it works on does.
pub async fn enqueue(
    tx: &mut Transaction<'_, Sqlite>,
    kind: &str,
    payload: &str,
) -> Result<i64, sqlx::Error> {
    let (id,): (i64,) =
        sqlx::query_as("INSERT INTO jobs (kind, payload) VALUES (?, ?) RETURNING id")
            .bind(kind)
            .bind(payload)
            .fetch_one(&mut **tx)
            .await?;
    Ok(id)
}

/// Marks the held job succeeded inside the transaction that stores its
/// results; fails (and the caller rolls back) if the worker no longer holds
/// it.
pub async fn finish(
    tx: &mut Transaction<'_, Sqlite>,
    job: &ClaimedJob,
    result: &str,
    duration_s: f64,
) -> Result<(), CompleteError> {
    let done = sqlx::query(
        "UPDATE jobs SET state = 'succeeded', result = ?, error = NULL, locked_by = NULL, \
         duration_s = ?, finished_at = strftime('%Y-%m-%dT%H:%M:%fZ', 'now') \
         WHERE id = ? AND state = 'running' AND locked_by = ?",
    )
    .bind(result)
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

/// Stores a calibration inside the caller's transaction (a solve job's
/// completion stores its calibration and finishes the job together).
pub async fn insert_calibration(
    tx: &mut Transaction<'_, Sqlite>,
    model: &str,
    cameras: i64,
    report: Option<&str>,
) -> Result<CalibrationRow, sqlx::Error> {
    sqlx::query_as(
        "INSERT INTO calibrations (model, cameras, report) VALUES (?, ?, ?) \
         RETURNING id, model, cameras, report, created_at",
    )
    .bind(model)
    .bind(cameras)
    .bind(report)
    .fetch_one(&mut **tx)
    .await
}

async fn insert_targets(
    tx: &mut Transaction<'_, Sqlite>,
    sequence_id: i64,
    frame: i64,
    camera: i64,
    count: i64,
    data: &[u8],
) -> Result<(), sqlx::Error> {
    sqlx::query(
        "INSERT INTO targets (sequence_id, frame, camera, count, data) VALUES (?, ?, ?, ?, ?)",
    )
    .bind(sequence_id)
    .bind(frame)
    .bind(camera)
    .bind(count)
    .bind(data)
    .execute(&mut **tx)
    .await?;
    Ok(())
}

impl Store {
    /// Completes a held job whose results are stored elsewhere (or that
    /// has none) with a link to its result.
    pub async fn succeed(
        &self,
        job: &ClaimedJob,
        result: &str,
        duration_s: f64,
    ) -> Result<(), CompleteError> {
        let mut tx = self.write_transaction().await?;
        finish(&mut tx, job, result, duration_s).await?;
        tx.commit().await?;
        Ok(())
    }

    /// Enqueues a job on its own (e.g. solve_calibration, whose inputs are
    /// files already in the image store, named in the payload).
    pub async fn enqueue(&self, kind: &str, payload: &str) -> Result<i64, sqlx::Error> {
        let mut tx = self.write_transaction().await?;
        let id = enqueue(&mut tx, kind, payload).await?;
        tx.commit().await?;
        Ok(id)
    }
}

impl Store {
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
