//! Calibrations: stored from the API, or solved by a job and stored with
//! its report when the job completes.

use sqlx::any::AnyRow;
use sqlx::{Any, FromRow, Row, Transaction};

use super::jobs::{finish, ClaimedJob};
use super::StoreError;
use super::{CalibrationId, CompleteError, JobId, Store};

/// A stored calibration.
#[derive(Clone, Debug)]
pub struct CalibrationRow {
    /// Its id.
    pub id: CalibrationId,
    /// The calibration JSON.
    pub model: String,
    /// How many cameras.
    pub cameras: i64,
    /// The report (JSON): the resection's if solved, the
    /// self-calibration's if refined from particles.
    pub report: Option<String>,
    /// The calibration it was refined from by self-calibration, if any.
    pub origin: Option<CalibrationId>,
    /// When it was stored.
    pub created_at: String,
}

/// A calibration in a list: what it is without its model and report.
#[derive(Clone, Debug)]
pub struct CalibrationSummary {
    /// Its id.
    pub id: CalibrationId,
    /// How many cameras.
    pub cameras: i64,
    /// Whether it has a report (solved or self-calibrated).
    pub has_report: bool,
    /// The calibration it was refined from, if any.
    pub origin: Option<CalibrationId>,
    /// When it was stored.
    pub created_at: String,
}

impl FromRow<'_, AnyRow> for CalibrationSummary {
    fn from_row(row: &AnyRow) -> Result<Self, sqlx::Error> {
        Ok(CalibrationSummary {
            id: row.try_get("id")?,
            cameras: row.try_get("cameras")?,
            has_report: row.try_get::<i64, _>("has_report")? != 0,
            origin: row.try_get("origin_calibration")?,
            created_at: row.try_get("created_at")?,
        })
    }
}

impl FromRow<'_, AnyRow> for CalibrationRow {
    fn from_row(row: &AnyRow) -> Result<Self, sqlx::Error> {
        Ok(CalibrationRow {
            id: row.try_get("id")?,
            model: row.try_get("model")?,
            cameras: row.try_get("cameras")?,
            report: row.try_get("report")?,
            origin: row.try_get("origin_calibration")?,
            created_at: row.try_get("created_at")?,
        })
    }
}

impl Store {
    /// Stores a calibration.
    pub async fn insert_calibration(
        &self,
        model: &str,
        cameras: i64,
        report: Option<&str>,
    ) -> Result<CalibrationRow, StoreError> {
        let mut tx = self.write_transaction().await?;
        let row = insert_calibration(&mut tx, model, cameras, report, None).await?;
        tx.commit().await?;
        Ok(row)
    }

    /// A calibration by id.
    pub async fn calibration(
        &self,
        id: CalibrationId,
    ) -> Result<Option<CalibrationRow>, StoreError> {
        sqlx::query_as(
            "SELECT id, model, cameras, report, origin_calibration, created_at FROM calibrations \
             WHERE id = $1",
        )
        .bind(id)
        .fetch_optional(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// Calibrations newest first (highest id first), below `before` if
    /// given, at most `limit`, without their model and report: id,
    /// cameras, whether it has a report, origin, created_at.
    pub async fn calibrations_page(
        &self,
        before: Option<CalibrationId>,
        limit: u32,
    ) -> Result<Vec<CalibrationSummary>, StoreError> {
        sqlx::query_as(
            "SELECT id, cameras, CASE WHEN report IS NULL THEN 0 ELSE 1 END AS has_report, origin_calibration, created_at \
             FROM calibrations WHERE id < $1 ORDER BY id DESC LIMIT $2",
        )
        .bind(before.map_or(i64::MAX, |b| b.0))
        .bind(i64::from(limit))
        .fetch_all(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// Stores a solved calibration with its report and completes its job,
    /// in one transaction (the calibration names the job: its result);
    /// unless `keep_files`, the job's file rows go too.
    /// Returns the calibration's id and the hashes of the removed file
    /// rows, whose files go where nothing else refers to them (checked by
    /// the caller after the commit, as for `complete_frame`).
    pub async fn complete_calibration(
        &self,
        job: &ClaimedJob,
        model: &str,
        cameras: i64,
        report: &str,
        keep_files: bool,
        duration_s: f64,
    ) -> Result<(CalibrationId, Vec<String>), CompleteError> {
        let mut tx = self.write_transaction().await?;
        finish(&mut tx, self.dialect, job, None, duration_s).await?;
        let row = insert_calibration(&mut tx, model, cameras, Some(report), Some(job.id)).await?;
        let mut released = Vec::new();
        if !keep_files {
            let hashes: Vec<(String,)> =
                sqlx::query_as("DELETE FROM job_files WHERE job_id = $1 RETURNING sha256")
                    .bind(job.id)
                    .fetch_all(&mut *tx)
                    .await?;
            released.extend(hashes.into_iter().map(|(hash,)| hash));
            released.sort_unstable();
            released.dedup();
        }
        tx.commit().await?;
        Ok((row.id, released))
    }
}

/// Stores a calibration inside the caller's transaction (a solve job's
/// completion stores its calibration, naming the job, and finishes the job
/// together).
pub async fn insert_calibration(
    tx: &mut Transaction<'_, Any>,
    model: &str,
    cameras: i64,
    report: Option<&str>,
    solved_by: Option<JobId>,
) -> Result<CalibrationRow, StoreError> {
    sqlx::query_as(
        "INSERT INTO calibrations (model, cameras, report, job_id) VALUES ($1, $2, $3, $4) \
         RETURNING id, model, cameras, report, origin_calibration, created_at",
    )
    .bind(model)
    .bind(cameras)
    .bind(report)
    .bind(solved_by)
    .fetch_one(&mut **tx)
    .await
    .map_err(StoreError::from)
}
