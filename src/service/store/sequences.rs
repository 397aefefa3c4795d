//! Sequences and their frames: a frame's upload (inputs and its job in one
//! transaction), what its job reads, and its results.

use sqlx::sqlite::SqliteRow;
use sqlx::{FromRow, Row, Sqlite, Transaction};

use super::jobs::{enqueue, finish, ClaimedJob, JobState};
use super::{
    decode_text, file_in_use, stored_as_text, text_column, CalibrationId, CompleteError,
    FrameNumber, InsertFrameError, JobId, OnUniqueViolation, SequenceId, Store, TextColumn,
};

/// A stored sequence.
#[derive(Clone, Debug)]
pub struct SequenceRow {
    /// Its id.
    pub id: SequenceId,
    /// Its calibration.
    pub calibration_id: CalibrationId,
    /// Its name.
    pub name: String,
    /// Detection and matching parameters (JSON).
    pub parameters: String,
    /// Whether images are kept after processing.
    pub keep_images: bool,
    /// When it was created.
    pub created_at: String,
}

/// What was uploaded for a frame (the `frames.input` column).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameInputKind {
    /// One image per camera, to detect the targets in.
    Images,
    /// One target list per camera, detected elsewhere.
    Targets,
}

stored_as_text!(FrameInputKind, "frame input", {
    Images => "images",
    Targets => "targets",
});

/// A frame upload to store with its job.
#[derive(Clone, Debug)]
pub struct NewFrame {
    /// The sequence.
    pub sequence_id: SequenceId,
    /// The frame number.
    pub frame: FrameNumber,
    /// Images or targets.
    pub input: FrameInputKind,
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
    pub sequence_id: SequenceId,
    /// The frame.
    pub frame: FrameNumber,
    /// Images or targets.
    pub input: FrameInputKind,
    /// The raw layout (JSON), if raw.
    pub raw_layout: Option<String>,
    /// The sequence's calibration.
    pub calibration_id: CalibrationId,
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

impl FromRow<'_, SqliteRow> for FrameInput {
    fn from_row(row: &SqliteRow) -> Result<Self, sqlx::Error> {
        Ok(FrameInput {
            sequence_id: row.try_get("sequence_id")?,
            frame: row.try_get("frame")?,
            input: text_column(row, "input")?,
            raw_layout: row.try_get("raw_layout")?,
            calibration_id: row.try_get("calibration_id")?,
        })
    }
}

impl Store {
    /// Stores a sequence; `None` if its calibration does not exist.
    pub async fn insert_sequence(
        &self,
        calibration_id: CalibrationId,
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
    pub async fn sequence(&self, id: SequenceId) -> Result<Option<SequenceRow>, sqlx::Error> {
        sqlx::query_as(
            "SELECT id, calibration_id, name, parameters, keep_images, created_at \
             FROM sequences WHERE id = ?",
        )
        .bind(id)
        .fetch_optional(&self.reader)
        .await
    }

    /// A sequence's frames counted by their job's state.
    pub async fn frame_counts(&self, sequence_id: SequenceId) -> Result<FrameCounts, sqlx::Error> {
        let rows: Vec<(String, i64)> = sqlx::query_as(
            "SELECT j.state, count(*) FROM frames f JOIN jobs j ON j.id = f.job_id \
             WHERE f.sequence_id = ? GROUP BY j.state",
        )
        .bind(sequence_id)
        .fetch_all(&self.reader)
        .await?;
        let mut counts = FrameCounts::default();
        for (state, count) in rows {
            match decode_text("state", &state)? {
                JobState::Queued => counts.queued = count,
                JobState::Running => counts.running = count,
                JobState::Succeeded => counts.done = count,
                JobState::Failed => counts.failed = count,
            }
        }
        Ok(counts)
    }

    /// Stores an uploaded frame, its inputs and its process_frame job in
    /// one transaction; returns the job's id.
    pub async fn insert_frame(&self, frame: &NewFrame) -> Result<JobId, InsertFrameError> {
        let mut tx = self.write_transaction().await?;
        let payload =
            serde_json::json!({"sequence_id": frame.sequence_id, "frame": frame.frame}).to_string();
        let job_id = enqueue(&mut tx, crate::service::jobs::PROCESS_FRAME, &payload).await?;
        sqlx::query(
            "INSERT INTO frames (sequence_id, frame, job_id, input, raw_layout) \
             VALUES (?, ?, ?, ?, ?)",
        )
        .bind(frame.sequence_id)
        .bind(frame.frame)
        .bind(job_id)
        .bind(frame.input.as_str())
        .bind(&frame.raw_layout)
        .execute(&mut *tx)
        .await
        .on_unique_violation(|| InsertFrameError::Exists {
            sequence_id: frame.sequence_id,
            frame: frame.frame,
        })?;
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
        sequence_id: SequenceId,
        frame: FrameNumber,
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
        sequence_id: SequenceId,
        frame: FrameNumber,
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

    /// A frame's targets per camera (count and blob), in camera order.
    pub async fn frame_targets(
        &self,
        sequence_id: SequenceId,
        frame: FrameNumber,
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
    pub async fn frame_exists(
        &self,
        sequence_id: SequenceId,
        frame: FrameNumber,
    ) -> Result<bool, sqlx::Error> {
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
        sequence_id: SequenceId,
        frame: FrameNumber,
    ) -> Result<Option<(i64, Vec<u8>)>, sqlx::Error> {
        sqlx::query_as("SELECT count, data FROM particles WHERE sequence_id = ? AND frame = ?")
            .bind(sequence_id)
            .bind(frame)
            .fetch_optional(&self.reader)
            .await
    }

    /// The processed frames of a sequence, in order.
    pub async fn processed_frames(
        &self,
        sequence_id: SequenceId,
    ) -> Result<Vec<FrameNumber>, sqlx::Error> {
        let rows: Vec<(FrameNumber,)> =
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
        finish(&mut tx, job, None, duration_s).await?;
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
}

async fn insert_targets(
    tx: &mut Transaction<'_, Sqlite>,
    sequence_id: SequenceId,
    frame: FrameNumber,
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
