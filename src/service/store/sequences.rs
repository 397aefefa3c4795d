//! Sequences and their frames: a frame's upload (inputs and its job in one
//! transaction), what its job reads, and its results.

use sqlx::any::AnyRow;
use sqlx::{Any, FromRow, Row, Transaction};

use super::calibrations::{insert_calibration, CalibrationRow};
use super::jobs::{enqueue, finish, ClaimedJob, JobState};
use super::StoreError;
use crate::service::infra::codec::CameraTargets;
use crate::service::model::parameters::SequenceParameters;
use crate::service::model::tracking_settings::TrackingSettings;

use super::{
    decode_text, file_in_use, json_column, json_text, stored_as_text, text_column, CalibrationId,
    CompleteError, FrameNumber, InsertFrameError, JobId, OnUniqueViolation, SequenceId, Store,
    TextColumn,
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
    /// Detection and matching parameters.
    pub parameters: SequenceParameters,
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
    /// Per camera, the image file.
    pub images: Vec<CameraImage>,
    /// Per camera, uploaded targets.
    pub targets: Vec<CameraTargets>,
}

/// One camera's image file of a frame: the file's hash in the image store
/// and its size (bytes).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CameraImage {
    /// The camera, from 0 (0 for a splitter's one image of all cameras).
    pub camera: i64,
    /// The file's hash in the image store.
    pub sha256: String,
    /// Its size (bytes).
    pub size: i64,
}

/// A background or mask image of a camera, to store: the file's hash in
/// the image store, its size (bytes) and its bits per sample (8 or 16).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NewSequenceImage {
    /// The camera, from 0.
    pub camera: i64,
    /// The file's hash in the image store.
    pub sha256: String,
    /// Its size (bytes).
    pub size: i64,
    /// Bits per sample, 8 or 16.
    pub bits: i64,
}

impl FromRow<'_, AnyRow> for CameraImage {
    fn from_row(row: &AnyRow) -> Result<Self, sqlx::Error> {
        Ok(CameraImage {
            camera: row.try_get("camera")?,
            sha256: row.try_get("sha256")?,
            size: row.try_get("size")?,
        })
    }
}

impl FromRow<'_, AnyRow> for CameraTargets {
    fn from_row(row: &AnyRow) -> Result<Self, sqlx::Error> {
        Ok(CameraTargets {
            camera: row.try_get("camera")?,
            count: row.try_get("count")?,
            data: row.try_get("data")?,
        })
    }
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

/// A frame in a list: its job's state and its particle count.
#[derive(Clone, Debug)]
pub struct FrameSummary {
    /// The frame.
    pub frame: FrameNumber,
    /// Its process_frame job.
    pub job_id: JobId,
    /// The job's state.
    pub state: JobState,
    /// Its particles, once processed.
    pub particles: Option<i64>,
}

impl FromRow<'_, AnyRow> for FrameSummary {
    fn from_row(row: &AnyRow) -> Result<Self, sqlx::Error> {
        Ok(FrameSummary {
            frame: row.try_get("frame")?,
            job_id: row.try_get("job_id")?,
            state: text_column(row, "state")?,
            particles: row.try_get("particles")?,
        })
    }
}

/// What a sequence's per-camera image is for (`sequence_images.kind`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SequenceImageKind {
    /// Subtracted from every frame before the high-pass filter.
    Background,
    /// Non-zero pixels are used, zero ones never.
    Mask,
}

stored_as_text!(SequenceImageKind, "sequence image kind", {
    Background => "background",
    Mask => "mask",
});

impl std::fmt::Display for SequenceImageKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A sequence's background or mask of one camera.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SequenceImage {
    /// Background or mask.
    pub kind: SequenceImageKind,
    /// The camera, from 0.
    pub camera: i64,
    /// The file's hash in the image store.
    pub sha256: String,
    /// Its size (bytes).
    pub size: i64,
    /// Bits per sample, 8 or 16.
    pub bits: i64,
}

impl FromRow<'_, AnyRow> for SequenceImage {
    fn from_row(row: &AnyRow) -> Result<Self, sqlx::Error> {
        Ok(SequenceImage {
            kind: text_column(row, "kind")?,
            camera: row.try_get("camera")?,
            sha256: row.try_get("sha256")?,
            size: row.try_get("size")?,
            bits: row.try_get("bits")?,
        })
    }
}

/// Why a sequence's backgrounds or masks were not stored.
#[derive(Debug, thiserror::Error)]
pub enum SequenceImagesError {
    /// Frames were uploaded already: they would be processed differently.
    #[error(
        "sequence {0} has frames already; its {1} must come before its first frame, so that \
         every frame is processed alike (create a new sequence)"
    )]
    HasFrames(SequenceId, SequenceImageKind),
    /// The sequence has this kind of image already.
    #[error("sequence {0} has its {1} already; create a new sequence to use another")]
    Exists(SequenceId, SequenceImageKind),
    /// The database failed.
    #[error(transparent)]
    Database(#[from] StoreError),
}

impl From<sqlx::Error> for SequenceImagesError {
    fn from(error: sqlx::Error) -> Self {
        SequenceImagesError::Database(error.into())
    }
}

impl FromRow<'_, AnyRow> for SequenceRow {
    fn from_row(row: &AnyRow) -> Result<Self, sqlx::Error> {
        Ok(SequenceRow {
            id: row.try_get("id")?,
            calibration_id: row.try_get("calibration_id")?,
            name: row.try_get("name")?,
            parameters: json_column(row, "parameters")?,
            keep_images: row.try_get::<i64, _>("keep_images")? != 0,
            created_at: row.try_get("created_at")?,
        })
    }
}

impl FromRow<'_, AnyRow> for FrameInput {
    fn from_row(row: &AnyRow) -> Result<Self, sqlx::Error> {
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
    /// Stores a sequence and, with `tracking` settings, its first
    /// tracking run, in one transaction; `None` if its calibration does not
    /// exist.
    pub async fn insert_sequence(
        &self,
        calibration_id: CalibrationId,
        name: &str,
        parameters: &SequenceParameters,
        keep_images: bool,
        tracking: Option<&TrackingSettings>,
    ) -> Result<Option<SequenceRow>, StoreError> {
        let parameters = json_text(parameters)?;
        let mut tx = self.write_transaction().await?;
        let result: Option<SequenceRow> = sqlx::query_as(
            "INSERT INTO sequences (calibration_id, name, parameters, keep_images) \
             SELECT id, $1, $2, $3 FROM calibrations WHERE id = $4 \
             RETURNING id, calibration_id, name, parameters, keep_images, created_at",
        )
        .bind(name)
        .bind(parameters)
        .bind(i64::from(keep_images))
        .bind(calibration_id)
        .fetch_optional(&mut *tx)
        .await?;
        if let (Some(row), Some(tracking)) = (&result, tracking) {
            super::tracking::insert_run(&mut tx, row.id, tracking, false).await?;
        }
        tx.commit().await?;
        Ok(result)
    }

    /// Stores a calibration, a sequence on it and the sequence's
    /// backgrounds (camera, hash, size, bits), in one transaction: an
    /// imported experiment (`POST /experiments/openptv`).
    pub async fn insert_experiment(
        &self,
        model: &str,
        cameras: i64,
        name: &str,
        parameters: &SequenceParameters,
        keep_images: bool,
        backgrounds: &[NewSequenceImage],
    ) -> Result<(CalibrationRow, SequenceRow), StoreError> {
        let parameters = json_text(parameters)?;
        let mut tx = self.write_transaction().await?;
        let calibration = insert_calibration(&mut tx, model, cameras, None, None).await?;
        let sequence: SequenceRow = sqlx::query_as(
            "INSERT INTO sequences (calibration_id, name, parameters, keep_images) \
             VALUES ($1, $2, $3, $4) \
             RETURNING id, calibration_id, name, parameters, keep_images, created_at",
        )
        .bind(calibration.id)
        .bind(name)
        .bind(parameters)
        .bind(i64::from(keep_images))
        .fetch_one(&mut *tx)
        .await?;
        for image in backgrounds {
            insert_sequence_image(&mut tx, sequence.id, SequenceImageKind::Background, image)
                .await?;
        }
        tx.commit().await?;
        Ok((calibration, sequence))
    }

    /// A sequence by id.
    pub async fn sequence(&self, id: SequenceId) -> Result<Option<SequenceRow>, StoreError> {
        sqlx::query_as(
            "SELECT id, calibration_id, name, parameters, keep_images, created_at \
             FROM sequences WHERE id = $1",
        )
        .bind(id)
        .fetch_optional(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// Sequences newest first (highest id first), below `before` if given,
    /// at most `limit`.
    pub async fn sequences_page(
        &self,
        before: Option<SequenceId>,
        limit: u32,
    ) -> Result<Vec<SequenceRow>, StoreError> {
        sqlx::query_as(
            "SELECT id, calibration_id, name, parameters, keep_images, created_at \
             FROM sequences WHERE id < $1 ORDER BY id DESC LIMIT $2",
        )
        .bind(before.map_or(i64::MAX, |b| b.0))
        .bind(i64::from(limit))
        .fetch_all(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// A sequence's frames in order, after `after` if given, at most
    /// `limit`: each with its job, the job's state and the particle count
    /// once processed.
    pub async fn frames_page(
        &self,
        sequence_id: SequenceId,
        after: Option<FrameNumber>,
        limit: u32,
    ) -> Result<Vec<FrameSummary>, StoreError> {
        sqlx::query_as(
            "SELECT f.frame, f.job_id, j.state, p.count AS particles \
             FROM frames f JOIN jobs j ON j.id = f.job_id \
             LEFT JOIN particles p ON p.sequence_id = f.sequence_id AND p.frame = f.frame \
             WHERE f.sequence_id = $1 AND f.frame > $2 ORDER BY f.frame LIMIT $3",
        )
        .bind(sequence_id)
        .bind(after.map_or(-1, |a| a.0))
        .bind(i64::from(limit))
        .fetch_all(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// A sequence's frames counted by their job's state.
    pub async fn frame_counts(&self, sequence_id: SequenceId) -> Result<FrameCounts, StoreError> {
        let rows: Vec<(String, i64)> = sqlx::query_as(
            "SELECT j.state, count(*) FROM frames f JOIN jobs j ON j.id = f.job_id \
             WHERE f.sequence_id = $1 GROUP BY j.state",
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
        let job_id = enqueue(
            &mut tx,
            crate::service::model::job_kind::JobKind::ProcessFrame.as_str(),
            &payload,
        )
        .await?;
        sqlx::query(
            "INSERT INTO frames (sequence_id, frame, job_id, input, raw_layout) \
             VALUES ($1, $2, $3, $4, $5)",
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
        for CameraImage {
            camera,
            sha256,
            size,
        } in &frame.images
        {
            sqlx::query(
                "INSERT INTO images (sequence_id, frame, camera, sha256, size) \
                 VALUES ($1, $2, $3, $4, $5)",
            )
            .bind(frame.sequence_id)
            .bind(frame.frame)
            .bind(camera)
            .bind(sha256)
            .bind(size)
            .execute(&mut *tx)
            .await?;
        }
        for targets in &frame.targets {
            insert_targets(&mut tx, frame.sequence_id, frame.frame, targets).await?;
        }
        tx.commit().await?;
        Ok(job_id)
    }

    /// What a process_frame job needs to know about its frame.
    pub async fn frame_input(
        &self,
        sequence_id: SequenceId,
        frame: FrameNumber,
    ) -> Result<Option<FrameInput>, StoreError> {
        sqlx::query_as(
            "SELECT f.sequence_id, f.frame, f.input, f.raw_layout, s.calibration_id \
             FROM frames f JOIN sequences s ON s.id = f.sequence_id \
             WHERE f.sequence_id = $1 AND f.frame = $2",
        )
        .bind(sequence_id)
        .bind(frame)
        .fetch_optional(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// A frame's image files, in camera order.
    pub async fn frame_images(
        &self,
        sequence_id: SequenceId,
        frame: FrameNumber,
    ) -> Result<Vec<CameraImage>, StoreError> {
        sqlx::query_as(
            "SELECT camera, sha256, size FROM images WHERE sequence_id = $1 AND frame = $2 \
             ORDER BY camera",
        )
        .bind(sequence_id)
        .bind(frame)
        .fetch_all(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// A frame's targets per camera, in camera order.
    pub async fn frame_targets(
        &self,
        sequence_id: SequenceId,
        frame: FrameNumber,
    ) -> Result<Vec<CameraTargets>, StoreError> {
        sqlx::query_as(
            "SELECT camera, count, data FROM targets WHERE sequence_id = $1 AND frame = $2 \
             ORDER BY camera",
        )
        .bind(sequence_id)
        .bind(frame)
        .fetch_all(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// Whether the frame exists.
    pub async fn frame_exists(
        &self,
        sequence_id: SequenceId,
        frame: FrameNumber,
    ) -> Result<bool, StoreError> {
        let row: Option<(i64,)> =
            sqlx::query_as("SELECT job_id FROM frames WHERE sequence_id = $1 AND frame = $2")
                .bind(sequence_id)
                .bind(frame)
                .fetch_optional(&self.reader)
                .await?;
        Ok(row.is_some())
    }

    /// A frame's particles (count, blob and the calibration that made
    /// them), if processed.
    pub async fn frame_particles(
        &self,
        sequence_id: SequenceId,
        frame: FrameNumber,
    ) -> Result<Option<(i64, Vec<u8>, CalibrationId)>, StoreError> {
        sqlx::query_as(
            "SELECT count, data, calibration_id FROM particles WHERE sequence_id = $1 AND frame = $2",
        )
        .bind(sequence_id)
        .bind(frame)
        .fetch_optional(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// The processed frames of a sequence, in order.
    pub async fn processed_frames(
        &self,
        sequence_id: SequenceId,
    ) -> Result<Vec<FrameNumber>, StoreError> {
        let rows: Vec<(FrameNumber,)> =
            sqlx::query_as("SELECT frame FROM particles WHERE sequence_id = $1 ORDER BY frame")
                .bind(sequence_id)
                .fetch_all(&self.reader)
                .await?;
        Ok(rows.into_iter().map(|(f,)| f).collect())
    }

    /// Stores a processed frame's results and completes its job, in one
    /// transaction: `targets` (detected; empty when they were uploaded),
    /// the particles (naming `input.calibration_id`, which made them), their
    /// calibration health rows (`health`), and, when the sequence does not keep images, the
    /// removal of the frame's image rows. Returns the hashes of the removed
    /// rows: their files go where nothing else refers to them, which the
    /// caller checks after the commit under the image store's lock
    /// (`images::remove_unused_images`). A check here, inside the
    /// transaction, would miss on PostgreSQL (read committed) when two
    /// frames of the same images complete at once: each would still see
    /// the other's rows, and neither delete the file.
    pub async fn complete_frame(
        &self,
        job: &ClaimedJob,
        input: &FrameInput,
        targets: &[CameraTargets],
        (particles, health): ((i64, &[u8]), &[super::HealthRow]),
        drop_images: bool,
        duration_s: f64,
    ) -> Result<Vec<String>, CompleteError> {
        let (sequence_id, frame) = (input.sequence_id, input.frame);
        let mut tx = self.write_transaction().await?;
        finish(&mut tx, self.dialect, job, None, duration_s).await?;
        for targets in targets {
            insert_targets(&mut tx, sequence_id, frame, targets).await?;
        }
        sqlx::query(
            "INSERT INTO particles (sequence_id, frame, count, data, calibration_id) \
             VALUES ($1, $2, $3, $4, $5)",
        )
        .bind(sequence_id)
        .bind(frame)
        .bind(particles.0)
        .bind(particles.1)
        .bind(input.calibration_id)
        .execute(&mut *tx)
        .await?;
        // Replaced, not only inserted: rows a frame's earlier results left
        // (only a hand-edited database has them without particles) never
        // stop its completion.
        super::health::replace_health(&mut tx, self.dialect, (sequence_id, frame), health).await?;
        let mut released = Vec::new();
        if drop_images {
            let hashes: Vec<(String,)> = sqlx::query_as(
                "DELETE FROM images WHERE sequence_id = $1 AND frame = $2 RETURNING sha256",
            )
            .bind(sequence_id)
            .bind(frame)
            .fetch_all(&mut *tx)
            .await?;
            released.extend(hashes.into_iter().map(|(hash,)| hash));
            released.sort_unstable();
            released.dedup();
        }
        tx.commit().await?;
        Ok(released)
    }

    /// A sequence's backgrounds and masks, by kind and camera.
    pub async fn sequence_images(
        &self,
        sequence_id: SequenceId,
    ) -> Result<Vec<SequenceImage>, StoreError> {
        sqlx::query_as(
            "SELECT kind, camera, sha256, size, bits FROM sequence_images \
             WHERE sequence_id = $1 ORDER BY kind, camera",
        )
        .bind(sequence_id)
        .fetch_all(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// Stores uploaded backgrounds or masks of a
    /// sequence that has no frames and none of this kind yet, in one
    /// transaction.
    pub async fn insert_sequence_images(
        &self,
        sequence_id: SequenceId,
        kind: SequenceImageKind,
        images: &[NewSequenceImage],
    ) -> Result<(), SequenceImagesError> {
        let mut tx = self.write_transaction().await?;
        super::dialect::lock_sequence(&mut tx, self.dialect, sequence_id).await?;
        let (frames,): (i64,) =
            sqlx::query_as("SELECT count(*) FROM frames WHERE sequence_id = $1")
                .bind(sequence_id)
                .fetch_one(&mut *tx)
                .await?;
        if frames > 0 {
            return Err(SequenceImagesError::HasFrames(sequence_id, kind));
        }
        let (existing,): (i64,) = sqlx::query_as(
            "SELECT count(*) FROM sequence_images WHERE sequence_id = $1 AND kind = $2",
        )
        .bind(sequence_id)
        .bind(kind.as_str())
        .fetch_one(&mut *tx)
        .await?;
        if existing > 0 {
            return Err(SequenceImagesError::Exists(sequence_id, kind));
        }
        for image in images {
            insert_sequence_image(&mut tx, sequence_id, kind, image).await?;
        }
        tx.commit().await?;
        Ok(())
    }

    /// Stores a background the service computed;
    /// a background stored meanwhile (by another worker, from the same
    /// frames) is kept. Returns the hashes of the files no row refers to
    /// afterwards, whose files may go.
    pub async fn insert_computed_background(
        &self,
        sequence_id: SequenceId,
        images: &[NewSequenceImage],
    ) -> Result<Vec<String>, StoreError> {
        let mut tx = self.write_transaction().await?;
        super::dialect::lock_sequence(&mut tx, self.dialect, sequence_id).await?;
        let (existing,): (i64,) = sqlx::query_as(
            "SELECT count(*) FROM sequence_images WHERE sequence_id = $1 AND kind = 'background'",
        )
        .bind(sequence_id)
        .fetch_one(&mut *tx)
        .await?;
        if existing == 0 {
            for image in images {
                insert_sequence_image(&mut tx, sequence_id, SequenceImageKind::Background, image)
                    .await?;
            }
        }
        let mut orphans = Vec::new();
        for image in images {
            if !file_in_use(&mut tx, &image.sha256).await? {
                orphans.push(image.sha256.clone());
            }
        }
        tx.commit().await?;
        Ok(orphans)
    }

    /// The lowest-numbered frames of a sequence that have images (at most
    /// `limit`), and how many such frames it has in all.
    pub async fn image_frames(
        &self,
        sequence_id: SequenceId,
        limit: u32,
    ) -> Result<(Vec<FrameNumber>, i64), StoreError> {
        let frames: Vec<(FrameNumber,)> = sqlx::query_as(
            "SELECT frame FROM frames WHERE sequence_id = $1 AND input = 'images' \
             ORDER BY frame LIMIT $2",
        )
        .bind(sequence_id)
        .bind(i64::from(limit))
        .fetch_all(&self.reader)
        .await?;
        let (count,): (i64,) = sqlx::query_as(
            "SELECT count(*) FROM frames WHERE sequence_id = $1 AND input = 'images'",
        )
        .bind(sequence_id)
        .fetch_one(&self.reader)
        .await?;
        Ok((frames.into_iter().map(|(f,)| f).collect(), count))
    }
}

async fn insert_targets(
    tx: &mut Transaction<'_, Any>,
    sequence_id: SequenceId,
    frame: FrameNumber,
    targets: &CameraTargets,
) -> Result<(), StoreError> {
    sqlx::query(
        "INSERT INTO targets (sequence_id, frame, camera, count, data) VALUES ($1, $2, $3, $4, $5)",
    )
    .bind(sequence_id)
    .bind(frame)
    .bind(targets.camera)
    .bind(targets.count)
    .bind(&targets.data)
    .execute(&mut **tx)
    .await?;
    Ok(())
}

async fn insert_sequence_image(
    tx: &mut Transaction<'_, Any>,
    sequence_id: SequenceId,
    kind: SequenceImageKind,
    image: &NewSequenceImage,
) -> Result<(), StoreError> {
    sqlx::query(
        "INSERT INTO sequence_images (sequence_id, kind, camera, sha256, size, bits) \
         VALUES ($1, $2, $3, $4, $5, $6)",
    )
    .bind(sequence_id)
    .bind(kind.as_str())
    .bind(image.camera)
    .bind(&image.sha256)
    .bind(image.size)
    .bind(image.bits)
    .execute(&mut **tx)
    .await?;
    Ok(())
}
