//! Self-calibration from a sequence's particles and reprocessing
//! (issue 14): a refined calibration stored with its origin and report,
//! the sequence switched to a calibration with its reprocess job, and a
//! frame's particles replaced by ones another calibration made.

use super::calibrations::insert_calibration;
use super::jobs::{enqueue, finish, ClaimedJob};
use super::StoreError;
use super::{CalibrationId, CompleteError, FrameNumber, JobId, SequenceId, Store};

use crate::service::model::job_kind::JobKind;

/// A refined calibration to store when its self-calibration job completes.
#[derive(Clone, Copy, Debug)]
pub struct RefinedCalibration<'a> {
    /// The calibration JSON.
    pub model: &'a str,
    /// Its cameras.
    pub cameras: i64,
    /// The self-calibration report (JSON).
    pub report: &'a str,
    /// The calibration it was refined from.
    pub origin: CalibrationId,
}

/// The payload of a reprocess job.
pub fn reprocess_payload(sequence_id: SequenceId, calibration_id: CalibrationId) -> String {
    serde_json::json!({"sequence_id": sequence_id, "calibration_id": calibration_id}).to_string()
}

impl Store {
    /// Stores a refined calibration naming its origin and its job, and
    /// completes the job, in one transaction. With `reprocess`, the
    /// sequence is switched to the new calibration and its reprocess job
    /// enqueued in the same transaction. Returns the calibration's id and
    /// the reprocess job's.
    pub async fn complete_self_calibration(
        &self,
        job: &ClaimedJob,
        refined: RefinedCalibration<'_>,
        reprocess: Option<SequenceId>,
        duration_s: f64,
    ) -> Result<(CalibrationId, Option<JobId>), CompleteError> {
        let mut tx = self.write_transaction().await?;
        finish(&mut tx, self.dialect, job, None, duration_s).await?;
        let row = insert_calibration(
            &mut tx,
            refined.model,
            refined.cameras,
            Some(refined.report),
            Some(job.id),
        )
        .await?;
        sqlx::query("UPDATE calibrations SET origin_calibration = $1 WHERE id = $2")
            .bind(refined.origin)
            .bind(row.id)
            .execute(&mut *tx)
            .await?;
        let mut reprocess_job = None;
        if let Some(sequence_id) = reprocess {
            sqlx::query("UPDATE sequences SET calibration_id = $1 WHERE id = $2")
                .bind(row.id)
                .bind(sequence_id)
                .execute(&mut *tx)
                .await?;
            let payload = reprocess_payload(sequence_id, row.id);
            reprocess_job =
                Some(enqueue(&mut tx, JobKind::ReprocessSequence.as_str(), &payload).await?);
        }
        tx.commit().await?;
        Ok((row.id, reprocess_job))
    }

    /// Switches the sequence to `calibration_id` (frames processed from now
    /// on use it) and enqueues the job that re-matches its processed
    /// frames, in one transaction; `None` if the sequence does not exist.
    pub async fn start_reprocess(
        &self,
        sequence_id: SequenceId,
        calibration_id: CalibrationId,
    ) -> Result<Option<JobId>, StoreError> {
        let mut tx = self.write_transaction().await?;
        let changed = sqlx::query("UPDATE sequences SET calibration_id = $1 WHERE id = $2")
            .bind(calibration_id)
            .bind(sequence_id)
            .execute(&mut *tx)
            .await?
            .rows_affected();
        if changed == 0 {
            return Ok(None);
        }
        let payload = reprocess_payload(sequence_id, calibration_id);
        let job = enqueue(&mut tx, JobKind::ReprocessSequence.as_str(), &payload).await?;
        tx.commit().await?;
        Ok(Some(job))
    }

    /// The sequence's frames within `first..=last` that have targets for
    /// `cameras` cameras, in order.
    pub async fn frames_with_targets(
        &self,
        sequence_id: SequenceId,
        (first, last): (FrameNumber, FrameNumber),
        cameras: i64,
    ) -> Result<Vec<FrameNumber>, StoreError> {
        let rows: Vec<(FrameNumber,)> = sqlx::query_as(
            "SELECT frame FROM targets WHERE sequence_id = $1 AND frame BETWEEN $2 AND $3 \
             GROUP BY frame HAVING count(*) = $4 ORDER BY frame",
        )
        .bind(sequence_id)
        .bind(first)
        .bind(last)
        .bind(cameras)
        .fetch_all(&self.reader)
        .await?;
        Ok(rows.into_iter().map(|(f,)| f).collect())
    }

    /// How many targets the sequence's frames within `first..=last` have
    /// stored, every camera's (a self-calibration's memory need, known
    /// before the targets are read).
    pub async fn target_count(
        &self,
        sequence_id: SequenceId,
        (first, last): (FrameNumber, FrameNumber),
    ) -> Result<i64, StoreError> {
        let (count,): (Option<i64>,) = sqlx::query_as(
            "SELECT CAST(SUM(count) AS BIGINT) FROM targets \
             WHERE sequence_id = $1 AND frame BETWEEN $2 AND $3",
        )
        .bind(sequence_id)
        .bind(first)
        .bind(last)
        .fetch_one(&self.reader)
        .await?;
        Ok(count.unwrap_or(0))
    }

    /// The sequence's processed frames whose particles another calibration
    /// than `calibration_id` made, in order.
    pub async fn frames_made_by_others(
        &self,
        sequence_id: SequenceId,
        calibration_id: CalibrationId,
    ) -> Result<Vec<FrameNumber>, StoreError> {
        let rows: Vec<(FrameNumber,)> = sqlx::query_as(
            "SELECT frame FROM particles WHERE sequence_id = $1 \
             AND (calibration_id IS NULL OR calibration_id != $2) ORDER BY frame",
        )
        .bind(sequence_id)
        .bind(calibration_id)
        .fetch_all(&self.reader)
        .await?;
        Ok(rows.into_iter().map(|(f,)| f).collect())
    }

    /// Replaces a processed frame's particles with those `calibration_id`
    /// made, in one transaction fenced on the reprocess `job`'s lease (a
    /// worker whose lease ran out writes nothing:
    /// [`CompleteError::LostLease`]), with their health rows: the old ones stay until the new ones
    /// are written. False if the frame has no particles.
    pub async fn replace_particles(
        &self,
        job: &ClaimedJob,
        (sequence_id, frame): (SequenceId, FrameNumber),
        calibration_id: CalibrationId,
        particles: (i64, &[u8]),
        health: &[super::HealthRow],
    ) -> Result<bool, CompleteError> {
        let mut tx = self.write_transaction().await?;
        let held: Option<(i64,)> = sqlx::query_as(
            "SELECT 1 FROM jobs WHERE id = $1 AND state = 'running' AND lease_token = $2",
        )
        .bind(job.id)
        .bind(job.token)
        .fetch_optional(&mut *tx)
        .await?;
        if held.is_none() {
            return Err(CompleteError::LostLease(job.id));
        }
        let changed = sqlx::query(
            "UPDATE particles SET count = $1, data = $2, calibration_id = $3 \
             WHERE sequence_id = $4 AND frame = $5",
        )
        .bind(particles.0)
        .bind(particles.1)
        .bind(calibration_id)
        .bind(sequence_id)
        .bind(frame)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        if changed == 1 {
            super::health::replace_health(&mut tx, self.dialect, (sequence_id, frame), health)
                .await?;
        }
        tx.commit().await?;
        Ok(changed == 1)
    }
}
