//! Calibration health (migration 0011): a processed frame's disparity rows
//! per camera and sub-volume (`frame_health`, written with its particles),
//! and a sequence's drift monitor (`calibration_health`), advanced in frame
//! order and fenced on how far it had got.

use sqlx::{Any, Transaction};

use super::StoreError;
use super::{CalibrationId, FrameNumber, JobState, SequenceId, Store};

/// One row of a frame's health: a camera over the whole frame (`cell`
/// -1) or in one sub-volume (`cell` 0..).
#[derive(Clone, Debug, PartialEq)]
pub struct HealthRow {
    /// The camera, from 0.
    pub camera: i64,
    /// The sub-volume (x fastest, then y, then z), or -1: the whole frame.
    pub cell: i64,
    /// Well-matched particles seen.
    pub count: i64,
    /// The mean disparity vector (px).
    pub mean: [f64; 2],
    /// The RMS of the vectors' lengths (px).
    pub rms: f64,
}

/// A sequence's stored drift monitor.
#[derive(Clone, Debug)]
pub struct HealthState {
    /// The calibration whose particles it follows.
    pub calibration_id: CalibrationId,
    /// The last frame it took (None: none yet).
    pub through_frame: Option<FrameNumber>,
    /// Frames taken with health rows.
    pub frames: i64,
    /// The monitor (JSON).
    pub monitor: String,
    /// When it last advanced (UTC).
    pub updated_at: String,
}

/// The next frame for a drift monitor, in frame order.
#[derive(Clone, Debug, PartialEq)]
pub enum HealthFrame {
    /// Processed with the monitor's calibration: its whole-frame rows (one
    /// per camera; none for a frame stored before health was).
    Taken(FrameNumber, Vec<HealthRow>),
    /// Failed: a gap, passed over.
    Gap(FrameNumber),
}

/// Per camera and bin of frames, the mean of the frames' whole-frame
/// disparities (frames where the camera saw a well-matched particle).
#[derive(Clone, Debug, PartialEq)]
pub struct HealthSeriesPoint {
    /// The camera.
    pub camera: i64,
    /// The first frame of the bin.
    pub frame: FrameNumber,
    /// The mean of the frames' mean vectors (px).
    pub mean: [f64; 2],
    /// The mean of the frames' RMS (px).
    pub rms: f64,
}

type RowTuple = (i64, i64, i64, f64, f64, f64);

fn row_of((camera, cell, count, x, y, rms): RowTuple) -> HealthRow {
    HealthRow {
        camera,
        cell,
        count,
        mean: [x, y],
        rms,
    }
}

/// Stores a frame's health rows, in the transaction that stores its
/// particles: at most cameras x (1 + cells) rows, in statements of at most
/// [`super::rows_per_statement`] rows ([`super::statement_chunks`]), as the
/// store's other multi-row inserts.
pub(super) async fn insert_health(
    tx: &mut Transaction<'_, Any>,
    dialect: super::Dialect,
    (sequence_id, frame): (SequenceId, FrameNumber),
    rows: &[HealthRow],
) -> Result<(), StoreError> {
    for chunk in super::statement_chunks(dialect, rows) {
        let sql = format!(
            "INSERT INTO frame_health (sequence_id, frame, camera, cell, count, mean_x, mean_y, rms) \
             VALUES {}",
            super::placeholders(dialect, chunk.len(), 8)
        );
        let mut insert = sqlx::query(&sql);
        for row in chunk {
            insert = insert
                .bind(sequence_id)
                .bind(frame)
                .bind(row.camera)
                .bind(row.cell)
                .bind(row.count)
                .bind(row.mean[0])
                .bind(row.mean[1])
                .bind(row.rms);
        }
        insert.execute(&mut **tx).await?;
    }
    Ok(())
}

/// Replaces a frame's health rows (its particles were made again with
/// another calibration).
pub(super) async fn replace_health(
    tx: &mut Transaction<'_, Any>,
    dialect: super::Dialect,
    key: (SequenceId, FrameNumber),
    rows: &[HealthRow],
) -> Result<(), StoreError> {
    sqlx::query("DELETE FROM frame_health WHERE sequence_id = $1 AND frame = $2")
        .bind(key.0)
        .bind(key.1)
        .execute(&mut **tx)
        .await?;
    insert_health(tx, dialect, key, rows).await
}

impl Store {
    /// A sequence's drift monitor, if it has taken anything yet.
    pub async fn health_state(
        &self,
        sequence_id: SequenceId,
    ) -> Result<Option<HealthState>, StoreError> {
        let row: Option<(CalibrationId, Option<FrameNumber>, i64, String, String)> =
            sqlx::query_as(
                "SELECT calibration_id, through_frame, frames, monitor, updated_at \
                 FROM calibration_health WHERE sequence_id = $1",
            )
            .bind(sequence_id)
            .fetch_optional(&self.reader)
            .await?;
        Ok(row.map(
            |(calibration_id, through_frame, frames, monitor, updated_at)| HealthState {
                calibration_id,
                through_frame,
                frames,
                monitor,
                updated_at,
            },
        ))
    }

    /// The frames after `after` (from the sequence's lowest-numbered, if
    /// None) a drift monitor of `calibration_id` takes next, in order and
    /// numbered one after the other, at most `limit`: each processed with
    /// that calibration (with its whole-frame rows) or failed (a gap), up
    /// to the first that is neither (queued, running, or processed with
    /// another calibration, which reprocessing will replace) or a number
    /// not uploaded yet.
    pub async fn health_frames(
        &self,
        sequence_id: SequenceId,
        calibration_id: CalibrationId,
        after: Option<FrameNumber>,
        limit: u32,
    ) -> Result<Vec<HealthFrame>, StoreError> {
        let frames: Vec<(FrameNumber, String, Option<CalibrationId>)> = sqlx::query_as(
            "SELECT f.frame, j.state, p.calibration_id FROM frames f \
             JOIN jobs j ON j.id = f.job_id \
             LEFT JOIN particles p ON p.sequence_id = f.sequence_id AND p.frame = f.frame \
             WHERE f.sequence_id = $1 AND f.frame > $2 ORDER BY f.frame LIMIT $3",
        )
        .bind(sequence_id)
        .bind(after.map_or(-1, |a| a.0))
        .bind(i64::from(limit))
        .fetch_all(&self.reader)
        .await?;
        let mut ready: Vec<(FrameNumber, bool)> = Vec::new();
        let mut next = after.map(|a| a.0 + 1);
        for (frame, state, made_by) in frames {
            if next.is_some_and(|n| n != frame.0) {
                // A number not uploaded (yet): the monitor waits there.
                break;
            }
            next = Some(frame.0 + 1);
            if made_by == Some(calibration_id) {
                ready.push((frame, true));
            } else if made_by.is_none()
                && super::decode_text::<JobState>("state", &state)? == JobState::Failed
            {
                ready.push((frame, false));
            } else {
                break;
            }
        }
        let (Some(first), Some(last)) = (ready.first(), ready.last()) else {
            return Ok(Vec::new());
        };
        let rows: Vec<(FrameNumber, i64, i64, i64, f64, f64, f64)> = sqlx::query_as(
            "SELECT frame, camera, cell, count, mean_x, mean_y, rms FROM frame_health \
             WHERE sequence_id = $1 AND frame BETWEEN $2 AND $3 AND cell = -1 \
             ORDER BY frame, camera",
        )
        .bind(sequence_id)
        .bind(first.0)
        .bind(last.0)
        .fetch_all(&self.reader)
        .await?;
        let mut rows = rows.into_iter().peekable();
        Ok(ready
            .into_iter()
            .map(|(frame, processed)| {
                let mut of_frame = Vec::new();
                while let Some(r) = rows.next_if(|r| r.0 <= frame) {
                    if r.0 == frame {
                        of_frame.push(row_of((r.1, r.2, r.3, r.4, r.5, r.6)));
                    }
                }
                if processed {
                    HealthFrame::Taken(frame, of_frame)
                } else {
                    HealthFrame::Gap(frame)
                }
            })
            .collect())
    }

    /// Stores a sequence's drift monitor, advanced to `through` with
    /// `frames` taken, if it is still where it was read (`previous`: its
    /// calibration and last frame, or None when it had no row); false
    /// (nothing written) if another process advanced it meanwhile.
    pub async fn store_health(
        &self,
        sequence_id: SequenceId,
        previous: Option<(CalibrationId, Option<FrameNumber>)>,
        (calibration_id, through, frames): (CalibrationId, FrameNumber, i64),
        monitor: &str,
    ) -> Result<bool, StoreError> {
        let written = match previous {
            None => sqlx::query(
                "INSERT INTO calibration_health \
                 (sequence_id, calibration_id, through_frame, frames, monitor) \
                 VALUES ($1, $2, $3, $4, $5) ON CONFLICT (sequence_id) DO NOTHING",
            )
            .bind(sequence_id)
            .bind(calibration_id)
            .bind(through)
            .bind(frames)
            .bind(monitor)
            .execute(&self.writer)
            .await?
            .rows_affected(),
            Some((old_calibration, old_through)) => sqlx::query(&format!(
                "UPDATE calibration_health SET calibration_id = $1, through_frame = $2, \
                 frames = $3, monitor = $4, updated_at = {} \
                 WHERE sequence_id = $5 AND calibration_id = $6 \
                 AND through_frame IS NOT DISTINCT FROM $7",
                self.dialect.now()
            ))
            .bind(calibration_id)
            .bind(through)
            .bind(frames)
            .bind(monitor)
            .bind(sequence_id)
            .bind(old_calibration)
            .bind(old_through)
            .execute(&self.writer)
            .await?
            .rows_affected(),
        };
        Ok(written == 1)
    }

    /// A sequence's whole-frame disparities made with `calibration_id`, per
    /// camera, averaged over bins of frames so that at most about
    /// `max_bins` bins come back: at most cameras x `max_bins` points,
    /// whatever the sequence's length.
    pub async fn health_series(
        &self,
        sequence_id: SequenceId,
        calibration_id: CalibrationId,
        max_bins: i64,
    ) -> Result<Vec<HealthSeriesPoint>, StoreError> {
        let (first, last): (Option<i64>, Option<i64>) = sqlx::query_as(
            "SELECT min(frame), max(frame) FROM frame_health WHERE sequence_id = $1 AND cell = -1",
        )
        .bind(sequence_id)
        .fetch_one(&self.reader)
        .await?;
        let (Some(first), Some(last)) = (first, last) else {
            return Ok(Vec::new());
        };
        let bin = ((last - first) / max_bins.max(1) + 1).max(1);
        let rows: Vec<(i64, i64, f64, f64, f64)> = sqlx::query_as(
            "SELECT h.camera, min(h.frame), avg(h.mean_x), avg(h.mean_y), avg(h.rms) \
             FROM frame_health h JOIN particles p \
             ON p.sequence_id = h.sequence_id AND p.frame = h.frame \
             WHERE h.sequence_id = $1 AND h.cell = -1 AND h.count > 0 AND p.calibration_id = $2 \
             GROUP BY h.camera, (h.frame - $3) / $4 ORDER BY 2, 1",
        )
        .bind(sequence_id)
        .bind(calibration_id)
        .bind(first)
        .bind(bin)
        .fetch_all(&self.reader)
        .await?;
        Ok(rows
            .into_iter()
            .map(|(camera, frame, x, y, rms)| HealthSeriesPoint {
                camera,
                frame: FrameNumber(frame),
                mean: [x, y],
                rms,
            })
            .collect())
    }

    /// A frame's health rows, every camera and sub-volume.
    pub async fn frame_health(
        &self,
        sequence_id: SequenceId,
        frame: FrameNumber,
    ) -> Result<Vec<HealthRow>, StoreError> {
        let rows: Vec<RowTuple> = sqlx::query_as(
            "SELECT camera, cell, count, mean_x, mean_y, rms FROM frame_health \
             WHERE sequence_id = $1 AND frame = $2 ORDER BY camera, cell",
        )
        .bind(sequence_id)
        .bind(frame)
        .fetch_all(&self.reader)
        .await?;
        Ok(rows.into_iter().map(row_of).collect())
    }

    /// The latest frame up to `through` that has health rows, with its
    /// rows (every camera and sub-volume).
    pub async fn latest_frame_health(
        &self,
        sequence_id: SequenceId,
        through: FrameNumber,
    ) -> Result<Option<(FrameNumber, Vec<HealthRow>)>, StoreError> {
        let (latest,): (Option<FrameNumber>,) = sqlx::query_as(
            "SELECT max(frame) FROM frame_health WHERE sequence_id = $1 AND frame <= $2",
        )
        .bind(sequence_id)
        .bind(through)
        .fetch_one(&self.reader)
        .await?;
        let Some(frame) = latest else {
            return Ok(None);
        };
        Ok(Some((frame, self.frame_health(sequence_id, frame).await?)))
    }

    /// The drift monitors that advanced within the last `age_s` seconds,
    /// newest first, at most `limit`: the runs going on, for `/metrics`.
    pub async fn recent_health_states(
        &self,
        age_s: f64,
        limit: u32,
    ) -> Result<Vec<(SequenceId, HealthState)>, StoreError> {
        let rows: Vec<(
            SequenceId,
            CalibrationId,
            Option<FrameNumber>,
            i64,
            String,
            String,
        )> = sqlx::query_as(&format!(
            "SELECT sequence_id, calibration_id, through_frame, frames, monitor, updated_at \
                 FROM calibration_health WHERE updated_at >= {} \
                 ORDER BY updated_at DESC LIMIT $2",
            self.dialect.now_plus(1)
        ))
        .bind(-age_s)
        .bind(i64::from(limit))
        .fetch_all(&self.reader)
        .await?;
        Ok(rows
            .into_iter()
            .map(
                |(sequence_id, calibration_id, through_frame, frames, monitor, updated_at)| {
                    (
                        sequence_id,
                        HealthState {
                            calibration_id,
                            through_frame,
                            frames,
                            monitor,
                            updated_at,
                        },
                    )
                },
            )
            .collect())
    }
}
