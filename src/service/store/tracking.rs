//! Tracking runs and their trajectories (issue 15): a run's settings and
//! how far it has got, the frames its tracker took, and the trajectory
//! points, stored frame by frame in one transaction with the run's
//! progress, so that a crash leaves either the frame tracked (its points
//! and `tracked_through`) or not at all, and a repeated frame writes
//! nothing twice (the progress is the fence).
//!
//! **One tracker per run, across processes.** The process that advances a
//! run holds the run's lease (`lease_owner`, `lease_until`, `lease_token`:
//! [`Store::take_tracking_lease`]), renewed while it keeps the run's
//! tracker; another process takes the run over only once the lease has
//! run out (and rebuilds the tracker by replay). The stored frames are
//! fenced on the lease's token as well as on the progress.

use sqlx::any::AnyRow;
use sqlx::{Any, FromRow, Row, Transaction};

use std::time::Duration;

use super::StoreError;
use crate::service::model::tracking_settings::TrackingSettings;

use super::{
    json_column, json_text, stored_as_text, text_column, CalibrationId, FrameNumber, LeaseToken,
    SequenceId, Store, TrackingRunId,
};

/// Where a tracking run stands (`tracking_runs.state`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TrackingState {
    /// Following the frames as they complete.
    Tracking,
    /// Ended after the last frame (finish requested); every point stored.
    Finished,
    /// The tracker refused a frame's particles; `error` says why.
    Failed,
    /// A newer run of the sequence took over before this one finished; its
    /// points so far stay.
    Superseded,
}

stored_as_text!(TrackingState, "tracking state", {
    Tracking => "tracking",
    Finished => "finished",
    Failed => "failed",
    Superseded => "superseded",
});

/// A stored tracking run.
#[derive(Clone, Debug)]
pub struct TrackingRunRow {
    /// Its id.
    pub id: TrackingRunId,
    /// Its sequence.
    pub sequence_id: SequenceId,
    /// Its settings.
    pub parameters: TrackingSettings,
    /// The last frame its tracker took.
    pub tracked_through: Option<FrameNumber>,
    /// Whether the client said the sequence has all its frames.
    pub finish_requested: bool,
    /// Where it stands.
    pub state: TrackingState,
    /// Why it failed.
    pub error: Option<String>,
    /// When it was created.
    pub created_at: String,
    /// The calibration its image-space recovery projects with: the
    /// sequence's when the run was created (`None` for runs stored before
    /// migration 0007, which track without recovery).
    pub calibration_id: Option<CalibrationId>,
    /// What its backward pass added, where it ran (migration 0012).
    pub backward: Option<BackwardRow>,
}

/// What a run's backward pass added ([`crate::photogrammetry::track::BackwardSummary`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BackwardRow {
    /// Points added before the trajectories' first points.
    pub points: i64,
    /// Trajectories that gained points at their start.
    pub lengthened: i64,
    /// Trajectories joined onto the one ending before them.
    pub joined: i64,
}

const RUN_COLUMNS: &str = "id, sequence_id, parameters, tracked_through, finish_requested, state, \
     error, created_at, calibration_id, backward_points, backward_lengthened, backward_joined";

impl FromRow<'_, AnyRow> for TrackingRunRow {
    fn from_row(row: &AnyRow) -> Result<Self, sqlx::Error> {
        Ok(TrackingRunRow {
            id: row.try_get("id")?,
            sequence_id: row.try_get("sequence_id")?,
            parameters: json_column(row, "parameters")?,
            tracked_through: row.try_get("tracked_through")?,
            finish_requested: row.try_get::<i64, _>("finish_requested")? != 0,
            state: text_column(row, "state")?,
            error: row.try_get("error")?,
            created_at: row.try_get("created_at")?,
            calibration_id: row.try_get("calibration_id")?,
            backward: match (
                row.try_get::<Option<i64>, _>("backward_points")?,
                row.try_get::<Option<i64>, _>("backward_lengthened")?,
                row.try_get::<Option<i64>, _>("backward_joined")?,
            ) {
                (Some(points), Some(lengthened), Some(joined)) => Some(BackwardRow {
                    points,
                    lengthened,
                    joined,
                }),
                _ => None,
            },
        })
    }
}

/// One stored trajectory point.
#[derive(Clone, Debug, PartialEq)]
pub struct PointRow {
    /// The trajectory.
    pub trajectory: i64,
    /// The frame.
    pub frame: FrameNumber,
    /// The particle's index in the frame's particles; at or above their
    /// count, a particle the tracker recovered from the frame's targets.
    pub particle: i64,
    /// Position (mm).
    pub position: [f64; 3],
    /// Velocity (mm per frame), where the fit gives one.
    pub velocity: Option<[f64; 3]>,
    /// Acceleration (mm per frame²), where the fit gives one.
    pub acceleration: Option<[f64; 3]>,
    /// The velocity's standard deviations.
    pub velocity_sigma: Option<[f64; 3]>,
    /// The particle's target per camera, comma-separated, -1 for none.
    pub targets: String,
}

impl FromRow<'_, AnyRow> for PointRow {
    fn from_row(row: &AnyRow) -> Result<Self, sqlx::Error> {
        let triple = |names: [&str; 3]| -> Result<Option<[f64; 3]>, sqlx::Error> {
            let values = [
                row.try_get::<Option<f64>, _>(names[0])?,
                row.try_get::<Option<f64>, _>(names[1])?,
                row.try_get::<Option<f64>, _>(names[2])?,
            ];
            Ok(match values {
                [Some(a), Some(b), Some(c)] => Some([a, b, c]),
                _ => None,
            })
        };
        Ok(PointRow {
            trajectory: row.try_get("trajectory")?,
            frame: row.try_get("frame")?,
            particle: row.try_get("particle")?,
            position: [row.try_get("x")?, row.try_get("y")?, row.try_get("z")?],
            velocity: triple(["u", "v", "w"])?,
            acceleration: triple(["ax", "ay", "az"])?,
            velocity_sigma: triple(["su", "sv", "sw"])?,
            targets: row.try_get("targets")?,
        })
    }
}

/// The frames of a block of the trajectory points' index
/// (`trajectory_points_block`, migration 0010: `frame / 16`).
const FRAMES_PER_BLOCK: i64 = 16;

const POINT_COLUMNS: &str =
    "trajectory, frame, particle, x, y, z, u, v, w, ax, ay, az, su, sv, sw, targets";

/// A trajectory's extent.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TrajectoryRow {
    /// Its number within the run.
    pub id: i64,
    /// Its first frame.
    pub first_frame: FrameNumber,
    /// Its last frame.
    pub last_frame: FrameNumber,
    /// Its points.
    pub length: i64,
}

impl FromRow<'_, AnyRow> for TrajectoryRow {
    fn from_row(row: &AnyRow) -> Result<Self, sqlx::Error> {
        Ok(TrajectoryRow {
            id: row.try_get("id")?,
            first_frame: row.try_get("first_frame")?,
            last_frame: row.try_get("last_frame")?,
            length: row.try_get("length")?,
        })
    }
}

/// A frame of the sequence, as tracking sees it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameReadiness {
    /// Processed: its particles are stored.
    Processed,
    /// Its job failed: a gap.
    Failed,
    /// Queued or running.
    Pending,
}

impl Store {
    /// A tracking run by id.
    pub async fn tracking_run(
        &self,
        id: TrackingRunId,
    ) -> Result<Option<TrackingRunRow>, StoreError> {
        sqlx::query_as(&format!(
            "SELECT {RUN_COLUMNS} FROM tracking_runs WHERE id = $1"
        ))
        .bind(id)
        .fetch_optional(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// A sequence's tracking runs, oldest first (the last is its current
    /// one).
    pub async fn tracking_runs(
        &self,
        sequence_id: SequenceId,
    ) -> Result<Vec<TrackingRunRow>, StoreError> {
        sqlx::query_as(&format!(
            "SELECT {RUN_COLUMNS} FROM tracking_runs WHERE sequence_id = $1 ORDER BY id"
        ))
        .bind(sequence_id)
        .fetch_all(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// A sequence's current (newest) tracking run.
    pub async fn current_tracking_run(
        &self,
        sequence_id: SequenceId,
    ) -> Result<Option<TrackingRunRow>, StoreError> {
        sqlx::query_as(&format!(
            "SELECT {RUN_COLUMNS} FROM tracking_runs WHERE sequence_id = $1 \
             ORDER BY id DESC LIMIT 1"
        ))
        .bind(sequence_id)
        .fetch_optional(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// Runs still tracking that `owner` holds or may take (their lease
    /// is free or has run out): those its process advances.
    pub async fn tracking_runs_to_advance(
        &self,
        owner: &str,
    ) -> Result<Vec<TrackingRunId>, StoreError> {
        let rows: Vec<(TrackingRunId,)> = sqlx::query_as(&format!(
            "SELECT id FROM tracking_runs WHERE state = 'tracking' \
             AND (lease_owner IS NULL OR lease_owner = $1 OR {expired}) ORDER BY id",
            expired = self.dialect.lease_expired()
        ))
        .bind(owner)
        .fetch_all(&self.reader)
        .await?;
        Ok(rows.into_iter().map(|(id,)| id).collect())
    }

    /// Takes or renews the lease of a run still tracking for `owner` (a
    /// process), for `lease`: its token if `owner` holds it now, `None` if
    /// another owner's lease still runs (or the run is not tracking). A
    /// change of owner increments the token.
    pub async fn take_tracking_lease(
        &self,
        id: TrackingRunId,
        owner: &str,
        lease: Duration,
    ) -> Result<Option<LeaseToken>, StoreError> {
        let row: Option<(LeaseToken,)> = sqlx::query_as(&format!(
            "UPDATE tracking_runs SET \
             lease_token = CASE WHEN lease_owner IS NOT DISTINCT FROM $1 THEN lease_token \
                           ELSE lease_token + 1 END, \
             lease_owner = $1, lease_until = {until} \
             WHERE id = $3 AND state = 'tracking' \
             AND (lease_owner IS NULL OR lease_owner = $1 OR {expired}) \
             RETURNING lease_token",
            until = self.dialect.now_plus(2),
            expired = self.dialect.lease_expired(),
        ))
        .bind(owner)
        .bind(lease.as_secs_f64())
        .bind(id)
        .fetch_optional(&self.writer)
        .await?;
        Ok(row.map(|(token,)| token))
    }

    /// Gives up the tracking leases `owner` holds (a process stopping), so
    /// that another process takes its runs over at once.
    pub async fn release_tracking_leases(&self, owner: &str) -> Result<u64, StoreError> {
        Ok(sqlx::query(
            "UPDATE tracking_runs SET lease_owner = NULL, lease_until = NULL \
             WHERE lease_owner = $1",
        )
        .bind(owner)
        .execute(&self.writer)
        .await?
        .rows_affected())
    }

    /// A new tracking run of the sequence with `parameters`, in one
    /// transaction with the end of its current run if that one is still
    /// tracking (superseded); it keeps the current run's finish request
    /// (the sequence's frames are all there or not, whatever the
    /// settings). `None` if the sequence does not exist.
    pub async fn insert_tracking_run(
        &self,
        sequence_id: SequenceId,
        parameters: &TrackingSettings,
    ) -> Result<Option<TrackingRunRow>, StoreError> {
        let mut tx = self.write_transaction().await?;
        // Held to the end: two new runs at once supersede one another in
        // turn, never both stay tracking.
        super::dialect::lock_sequence(&mut tx, self.dialect, sequence_id).await?;
        let exists: Option<(i64,)> = sqlx::query_as("SELECT 1 FROM sequences WHERE id = $1")
            .bind(sequence_id)
            .fetch_optional(&mut *tx)
            .await?;
        if exists.is_none() {
            return Ok(None);
        }
        let (finish,): (i64,) = sqlx::query_as(
            "SELECT coalesce((SELECT finish_requested FROM tracking_runs WHERE sequence_id = $1 \
             ORDER BY id DESC LIMIT 1), 0)",
        )
        .bind(sequence_id)
        .fetch_one(&mut *tx)
        .await?;
        sqlx::query(
            "UPDATE tracking_runs SET state = 'superseded' \
             WHERE sequence_id = $1 AND state = 'tracking'",
        )
        .bind(sequence_id)
        .execute(&mut *tx)
        .await?;
        let row = insert_run(&mut tx, sequence_id, parameters, finish != 0).await?;
        tx.commit().await?;
        Ok(Some(row))
    }

    /// Records that the run's sequence has all its frames; the run's row
    /// after, `None` if there is no such run.
    pub async fn request_tracking_finish(
        &self,
        id: TrackingRunId,
    ) -> Result<Option<TrackingRunRow>, StoreError> {
        sqlx::query_as(&format!(
            "UPDATE tracking_runs SET finish_requested = 1 WHERE id = $1 RETURNING {RUN_COLUMNS}"
        ))
        .bind(id)
        .fetch_optional(&self.writer)
        .await
        .map_err(StoreError::from)
    }

    /// The sequence's frames from `from` on (at most `limit`), in order,
    /// with whether each is processed, failed or pending.
    pub async fn frames_to_track(
        &self,
        sequence_id: SequenceId,
        from: FrameNumber,
        limit: u32,
    ) -> Result<Vec<(FrameNumber, FrameReadiness)>, StoreError> {
        let rows: Vec<(FrameNumber, String, i64)> = sqlx::query_as(
            "SELECT f.frame, j.state, CASE WHEN p.frame IS NULL THEN 0 ELSE 1 END FROM frames f \
             JOIN jobs j ON j.id = f.job_id \
             LEFT JOIN particles p ON p.sequence_id = f.sequence_id AND p.frame = f.frame \
             WHERE f.sequence_id = $1 AND f.frame >= $2 ORDER BY f.frame LIMIT $3",
        )
        .bind(sequence_id)
        .bind(from)
        .bind(i64::from(limit))
        .fetch_all(&self.reader)
        .await?;
        rows.into_iter()
            .map(|(frame, state, processed)| {
                let readiness = if processed != 0 {
                    FrameReadiness::Processed
                } else if super::decode_text::<super::JobState>("state", &state)?
                    == super::JobState::Failed
                {
                    FrameReadiness::Failed
                } else {
                    FrameReadiness::Pending
                };
                Ok((frame, readiness))
            })
            .collect()
    }

    /// The frames the run's tracker took, in order: each with the count of
    /// particles it was given, or `None` for a gap.
    pub async fn tracked_frames(
        &self,
        id: TrackingRunId,
    ) -> Result<Vec<(FrameNumber, Option<i64>)>, StoreError> {
        sqlx::query_as(
            "SELECT frame, particles FROM tracking_frames WHERE run_id = $1 ORDER BY frame",
        )
        .bind(id)
        .fetch_all(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// Stores what tracking `frame` gave (`particles`: how many the tracker
    /// was given, `None` for a gap) and advances the run to it, in one
    /// transaction, if the run is still tracking, still at `previous` and
    /// still held with `token`. False (nothing written) otherwise: someone
    /// else advanced it, or took the run's lease.
    pub async fn store_tracked_frame(
        &self,
        (id, token): (TrackingRunId, LeaseToken),
        previous: Option<FrameNumber>,
        frame: FrameNumber,
        particles: Option<i64>,
        points: &[PointRow],
    ) -> Result<bool, StoreError> {
        let mut tx = self.write_transaction().await?;
        let advanced = sqlx::query(
            "UPDATE tracking_runs SET tracked_through = $1 \
             WHERE id = $2 AND state = 'tracking' AND tracked_through IS NOT DISTINCT FROM $3 AND lease_token = $4",
        )
        .bind(frame)
        .bind(id)
        .bind(previous)
        .bind(token)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        if advanced == 0 {
            return Ok(false);
        }
        sqlx::query("INSERT INTO tracking_frames (run_id, frame, particles) VALUES ($1, $2, $3)")
            .bind(id)
            .bind(frame)
            .bind(particles)
            .execute(&mut *tx)
            .await?;
        insert_points(&mut tx, self.dialect, id, points).await?;
        tx.commit().await?;
        Ok(true)
    }

    /// Ends a run tracked through `through` with its last points, in one
    /// transaction; false (nothing written) if it moved meanwhile or
    /// another holder took its lease.
    pub async fn finish_tracking_run(
        &self,
        run: (TrackingRunId, LeaseToken),
        through: Option<FrameNumber>,
        points: &[PointRow],
    ) -> Result<bool, StoreError> {
        self.finish_tracking_run_with(run, through, points, None)
            .await
    }

    /// Ends a run tracked through `through` as
    /// [`Store::finish_tracking_run`] does, after its backward pass: with
    /// `backward`, `points` are all of the run's points (the pass's
    /// result: trajectories lengthened, joined ones gone), which replace
    /// those stored, and the summary is recorded; all in one transaction,
    /// so a failure leaves the run tracking, its forward points whole, and
    /// the next advance does the pass again.
    pub async fn finish_tracking_run_with(
        &self,
        (id, token): (TrackingRunId, LeaseToken),
        through: Option<FrameNumber>,
        points: &[PointRow],
        backward: Option<BackwardRow>,
    ) -> Result<bool, StoreError> {
        let mut tx = self.write_transaction().await?;
        let done = sqlx::query(
            "UPDATE tracking_runs SET state = 'finished', lease_owner = NULL, lease_until = NULL \
             WHERE id = $1 AND state = 'tracking' AND tracked_through IS NOT DISTINCT FROM $2 AND lease_token = $3",
        )
        .bind(id)
        .bind(through)
        .bind(token)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        if done == 0 {
            return Ok(false);
        }
        if let Some(added) = backward {
            for table in ["trajectory_points", "trajectories"] {
                sqlx::query(&format!("DELETE FROM {table} WHERE run_id = $1"))
                    .bind(id)
                    .execute(&mut *tx)
                    .await?;
            }
            sqlx::query(
                "UPDATE tracking_runs SET backward_points = $1, backward_lengthened = $2, \
                 backward_joined = $3 WHERE id = $4",
            )
            .bind(added.points)
            .bind(added.lengthened)
            .bind(added.joined)
            .bind(id)
            .execute(&mut *tx)
            .await?;
        }
        insert_points(&mut tx, self.dialect, id, points).await?;
        tx.commit().await?;
        Ok(true)
    }

    /// How many particles the run's tracker was given over its frames, and
    /// how many points it stored: what its backward pass holds.
    pub async fn tracking_run_size(&self, id: TrackingRunId) -> Result<(i64, i64), StoreError> {
        let (particles, points): (Option<i64>, Option<i64>) = sqlx::query_as(
            // PostgreSQL's sum of BIGINT is NUMERIC: cast back.
            "SELECT (SELECT CAST(sum(particles) AS BIGINT) FROM tracking_frames WHERE run_id = $1), \
             (SELECT CAST(sum(length) AS BIGINT) FROM trajectories WHERE run_id = $2)",
        )
        .bind(id)
        .bind(id)
        .fetch_one(&self.reader)
        .await?;
        Ok((particles.unwrap_or(0), points.unwrap_or(0)))
    }

    /// Fails a run that is still tracking, with the reason.
    pub async fn fail_tracking_run(
        &self,
        id: TrackingRunId,
        error: &str,
    ) -> Result<(), StoreError> {
        sqlx::query(
            "UPDATE tracking_runs SET state = 'failed', error = $1 \
             WHERE id = $2 AND state = 'tracking'",
        )
        .bind(error)
        .bind(id)
        .execute(&self.writer)
        .await?;
        Ok(())
    }

    /// How many trajectories the run has stored.
    pub async fn trajectory_count(&self, id: TrackingRunId) -> Result<i64, StoreError> {
        let (n,): (i64,) = sqlx::query_as("SELECT count(*) FROM trajectories WHERE run_id = $1")
            .bind(id)
            .fetch_one(&self.reader)
            .await?;
        Ok(n)
    }

    /// The run's trajectories of at least `min_length` points that have a
    /// point within `frames`, numbered above `after`, in order (at most
    /// `limit`).
    pub async fn trajectories(
        &self,
        id: TrackingRunId,
        min_length: i64,
        frames: (FrameNumber, FrameNumber),
        after: i64,
        limit: u32,
    ) -> Result<Vec<TrajectoryRow>, StoreError> {
        sqlx::query_as(
            "SELECT id, first_frame, last_frame, length FROM trajectories \
             WHERE run_id = $1 AND length >= $2 AND last_frame >= $3 AND first_frame <= $4 AND id > $5 \
             ORDER BY id LIMIT $6",
        )
        .bind(id)
        .bind(min_length)
        .bind(frames.0)
        .bind(frames.1)
        .bind(after)
        .bind(i64::from(limit))
        .fetch_all(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// One trajectory's extent.
    pub async fn trajectory(
        &self,
        id: TrackingRunId,
        trajectory: i64,
    ) -> Result<Option<TrajectoryRow>, StoreError> {
        sqlx::query_as(
            "SELECT id, first_frame, last_frame, length FROM trajectories \
             WHERE run_id = $1 AND id = $2",
        )
        .bind(id)
        .bind(trajectory)
        .fetch_optional(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// The points of the run's trajectories numbered `ids.0..=ids.1` within
    /// `frames`, by trajectory and frame.
    ///
    /// The points are indexed by block of [`FRAMES_PER_BLOCK`] frames, then
    /// trajectory (migration 0010 says why): the frames asked for are cut
    /// to those of the trajectories' extents, and each of their blocks is
    /// one seek of the index for the trajectories' range. The blocks are
    /// the outer loop (`CROSS JOIN` keeps SQLite's planner to it, `+frame`
    /// keeps it off the frame-led primary key), so a page of trajectories
    /// reads its own points and the index entries of no other trajectory.
    pub async fn trajectory_points(
        &self,
        id: TrackingRunId,
        ids: (i64, i64),
        frames: (FrameNumber, FrameNumber),
    ) -> Result<Vec<PointRow>, StoreError> {
        let extent: (Option<FrameNumber>, Option<FrameNumber>) = sqlx::query_as(
            "SELECT min(first_frame), max(last_frame) FROM trajectories \
             WHERE run_id = $1 AND id BETWEEN $2 AND $3",
        )
        .bind(id)
        .bind(ids.0)
        .bind(ids.1)
        .fetch_one(&self.reader)
        .await?;
        let (Some(first), Some(last)) = extent else {
            return Ok(Vec::new());
        };
        let frames = (frames.0.max(first), frames.1.min(last));
        if frames.0 > frames.1 {
            return Ok(Vec::new());
        }
        let columns = POINT_COLUMNS
            .split(", ")
            .map(|c| format!("p.{c}"))
            .collect::<Vec<_>>()
            .join(", ");
        sqlx::query_as(&format!(
            "WITH RECURSIVE blocks (block) AS (\
               SELECT $4 / {FRAMES_PER_BLOCK} \
               UNION ALL SELECT block + 1 FROM blocks WHERE block < $5 / {FRAMES_PER_BLOCK}) \
             SELECT {columns} FROM blocks CROSS JOIN trajectory_points p \
             WHERE p.run_id = $1 AND p.frame / {FRAMES_PER_BLOCK} = blocks.block \
             AND p.trajectory BETWEEN $2 AND $3 AND +p.frame BETWEEN $4 AND $5 \
             ORDER BY p.trajectory, p.frame"
        ))
        .bind(id)
        .bind(ids.0)
        .bind(ids.1)
        .bind(frames.0)
        .bind(frames.1)
        .fetch_all(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// The trajectory of each particle of a frame that has one: (particle,
    /// trajectory).
    pub async fn frame_trajectories(
        &self,
        id: TrackingRunId,
        frame: FrameNumber,
    ) -> Result<Vec<(i64, i64)>, StoreError> {
        sqlx::query_as(
            "SELECT particle, trajectory FROM trajectory_points WHERE run_id = $1 AND frame = $2 \
             ORDER BY particle",
        )
        .bind(id)
        .bind(frame)
        .fetch_all(&self.reader)
        .await
        .map_err(StoreError::from)
    }
}

/// Inserts a tracking run inside the caller's transaction, with the
/// sequence's calibration as the one its recovery projects with.
pub(super) async fn insert_run(
    tx: &mut Transaction<'_, Any>,
    sequence_id: SequenceId,
    parameters: &TrackingSettings,
    finish_requested: bool,
) -> Result<TrackingRunRow, StoreError> {
    let parameters = json_text(parameters)?;
    sqlx::query_as(&format!(
        "INSERT INTO tracking_runs (sequence_id, parameters, finish_requested, calibration_id) \
         VALUES ($1, $2, $3, (SELECT calibration_id FROM sequences WHERE id = $4)) \
         RETURNING {RUN_COLUMNS}"
    ))
    .bind(sequence_id)
    .bind(parameters)
    .bind(i64::from(finish_requested))
    .bind(sequence_id)
    .fetch_one(&mut **tx)
    .await
    .map_err(StoreError::from)
}

/// Inserts trajectory points and brings their trajectories' extents up to
/// date, inside the caller's transaction.
/// A frame's points are those that frame made final (the tracker hands
/// each point out once), so a frame adds rows and rewrites none; its
/// trajectories' extents are upserted. Both in statements of at most
/// [`super::rows_per_statement`] rows ([`super::statement_chunks`]).
async fn insert_points(
    tx: &mut Transaction<'_, Any>,
    dialect: super::Dialect,
    id: TrackingRunId,
    points: &[PointRow],
) -> Result<(), StoreError> {
    for chunk in super::statement_chunks(dialect, points) {
        let sql = format!(
            "INSERT INTO trajectory_points (run_id, {POINT_COLUMNS}) VALUES {}",
            super::placeholders(dialect, chunk.len(), 17)
        );
        let mut insert = sqlx::query(&sql);
        for p in chunk {
            let [u, v, w] = p.velocity.map_or([None; 3], |v| v.map(Some));
            let [ax, ay, az] = p.acceleration.map_or([None; 3], |a| a.map(Some));
            let [su, sv, sw] = p.velocity_sigma.map_or([None; 3], |s| s.map(Some));
            insert = insert
                .bind(id)
                .bind(p.trajectory)
                .bind(p.frame)
                .bind(p.particle)
                .bind(p.position[0])
                .bind(p.position[1])
                .bind(p.position[2])
                .bind(u)
                .bind(v)
                .bind(w)
                .bind(ax)
                .bind(ay)
                .bind(az)
                .bind(su)
                .bind(sv)
                .bind(sw)
                .bind(p.targets.as_str());
        }
        insert.execute(&mut **tx).await?;
    }
    // Per trajectory: its frames and points among these.
    let mut extents: std::collections::BTreeMap<i64, (FrameNumber, FrameNumber, i64)> =
        std::collections::BTreeMap::new();
    for p in points {
        let e = extents.entry(p.trajectory).or_insert((p.frame, p.frame, 0));
        e.0 = e.0.min(p.frame);
        e.1 = e.1.max(p.frame);
        e.2 += 1;
    }
    let extents: Vec<_> = extents.into_iter().collect();
    for chunk in super::statement_chunks(dialect, &extents) {
        let sql = format!(
            "INSERT INTO trajectories (run_id, id, first_frame, last_frame, length) VALUES {} \
             ON CONFLICT (run_id, id) DO UPDATE SET \
             first_frame = CASE WHEN excluded.first_frame < trajectories.first_frame \
                           THEN excluded.first_frame ELSE trajectories.first_frame END, \
             last_frame = CASE WHEN excluded.last_frame > trajectories.last_frame \
                          THEN excluded.last_frame ELSE trajectories.last_frame END, \
             length = trajectories.length + excluded.length",
            super::placeholders(dialect, chunk.len(), 5)
        );
        let mut upsert = sqlx::query(&sql);
        for (trajectory, (first, last, length)) in chunk {
            upsert = upsert
                .bind(id)
                .bind(*trajectory)
                .bind(*first)
                .bind(*last)
                .bind(*length);
        }
        upsert.execute(&mut **tx).await?;
    }
    Ok(())
}
