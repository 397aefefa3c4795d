//! The store's unit tests: SQLite, and PostgreSQL where a server is given.

use super::*;
use sqlx::sqlite::{SqliteConnectOptions, SqlitePoolOptions};

/// Multi-row inserts: every row once, in order, in at most eight
/// (SQLite) or ten (PostgreSQL) distinct statement sizes per table,
/// none above the bound.
#[test]
fn inserts_are_cut_into_a_few_statement_sizes() {
    for (dialect, most, texts) in [(Dialect::Sqlite, 128, 8), (Dialect::Postgres, 512, 10)] {
        let mut sizes = std::collections::BTreeSet::new();
        for rows in [0, 1, 2, 3, 100, 127, 128, 129, 255, 511, 513, 2000, 15_001] {
            let items: Vec<usize> = (0..rows).collect();
            let chunks: Vec<&[usize]> = statement_chunks(dialect, &items).collect();
            assert_eq!(chunks.concat(), items, "{rows} rows");
            assert!(chunks.iter().all(|c| !c.is_empty() && c.len() <= most));
            sizes.extend(chunks.iter().map(|c| c.len()));
        }
        assert!(sizes.len() <= texts, "{sizes:?}");
    }
    assert_eq!(
        statement_rows(Dialect::Sqlite, 100).collect::<Vec<_>>(),
        [64, 32, 4]
    );
    assert_eq!(placeholders(Dialect::Sqlite, 2, 2), "(?, ?), (?, ?)");
    assert_eq!(placeholders(Dialect::Postgres, 2, 2), "($1, $2), ($3, $4)");
}

/// `--fsync` reaches every connection: SQLite's `synchronous` is FULL
/// (2) on the writer and the readers with it, NORMAL (1) without.
#[tokio::test]
async fn commits_are_flushed_as_asked() {
    for (synchronous, expected) in [(Synchronous::Normal, 1), (Synchronous::Full, 2)] {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open_sqlite(dir.path(), 1, synchronous)
            .await
            .unwrap();
        for pool in [&store.writer, &store.reader] {
            let (found,): (i64,) = sqlx::query_as("PRAGMA synchronous")
                .fetch_one(pool)
                .await
                .unwrap();
            assert_eq!(found, expected, "{synchronous:?}");
        }
        store.close().await;
    }
}

/// The database in `data_dir` (created where missing) with its first
/// `version` migrations run, on one connection.
async fn migrated_to(data_dir: &Path, version: usize) -> sqlx::SqlitePool {
    let pool = SqlitePoolOptions::new()
        .max_connections(1)
        .connect_with(
            SqliteConnectOptions::new()
                .filename(data_dir.join("ptv.sqlite"))
                .create_if_missing(true),
        )
        .await
        .unwrap();
    Migrator::new(Migrations(&MIGRATIONS[..version]))
        .await
        .unwrap()
        .run(&pool)
        .await
        .unwrap();
    pool
}

/// A database as the version before migration 3 left it: a calibration
/// stored from the API, one solved by a job, a processed frame and one
/// still queued, a job of a plug-in kind; the results as they stored
/// them, as paths.
async fn database_of_version_2(data_dir: &Path) {
    let pool = migrated_to(data_dir, 2).await;
    sqlx::raw_sql(
        "INSERT INTO calibrations (id, model, cameras) VALUES (1, '{}', 2), (2, '{}', 2);
         INSERT INTO jobs (id, kind, payload, state, result) VALUES
             (1, 'solve_calibration', '{}', 'succeeded', '/api/v1/calibrations/2'),
             (2, 'process_frame', '{}', 'succeeded', '/api/v1/sequences/1/frames/0/particles'),
             (3, 'process_frame', '{}', 'queued', NULL),
             (4, 'echo', '{}', 'succeeded', '/echo'),
             (5, 'solve_calibration', '{}', 'failed', NULL);
         INSERT INTO sequences (id, calibration_id, name, parameters, keep_images)
             VALUES (1, 1, '', '{}', 1);
         INSERT INTO frames (sequence_id, frame, job_id, input) VALUES
             (1, 0, 2, 'images'), (1, 1, 3, 'targets');",
    )
    .execute(&pool)
    .await
    .unwrap();
    pool.close().await;
}

/// A calibration row of `size` bytes.
async fn write(store: &Store, size: usize) -> Result<CalibrationRow, StoreError> {
    store.insert_calibration(&"x".repeat(size), 2, None).await
}

/// SQLite ended the transaction behind sqlx's back (as it may on a
/// full disk): sqlx's queued ROLLBACK then fails and its depth stays
/// at 1, which made every later write fail with "attempted to call
/// begin_with at non-zero transaction depth".
#[tokio::test]
async fn a_transaction_sqlite_ended_itself_does_not_block_later_writes() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path(), 1).await.unwrap();
    let mut tx = store.write_transaction().await.unwrap();
    sqlx::query("ROLLBACK").execute(&mut *tx).await.unwrap();
    drop(tx);
    for _ in 0..3 {
        write(&store, 10).await.unwrap();
    }
    store.close().await;
}

/// The other way round: SQLite inside a transaction that sqlx does not
/// know of.
#[tokio::test]
async fn a_transaction_left_open_does_not_block_later_writes() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path(), 1).await.unwrap();
    sqlx::query("BEGIN").execute(&store.writer).await.unwrap();
    for _ in 0..3 {
        write(&store, 10).await.unwrap();
    }
    store.close().await;
}

/// Ready while the writer can take the write lock; not while another
/// process holds it.
#[tokio::test]
async fn ready_means_the_write_lock_can_be_taken() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path(), 1).await.unwrap();
    store.ready(Duration::from_secs(5)).await.unwrap();
    let other = SqlitePoolOptions::new()
        .max_connections(1)
        .connect_with(SqliteConnectOptions::new().filename(dir.path().join("ptv.sqlite")))
        .await
        .unwrap();
    let lock = other.begin_with("BEGIN IMMEDIATE").await.unwrap();
    assert!(store.ready(Duration::from_millis(300)).await.is_err());
    lock.rollback().await.unwrap();
    store.ready(Duration::from_secs(5)).await.unwrap();
    other.close().await;
    store.close().await;
}

/// The page limit fails writes with SQLITE_FULL as a full disk does;
/// once lifted, writes succeed again on the same store.
#[tokio::test]
async fn writes_fail_as_storage_full_at_the_page_limit_and_recover_when_lifted() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path(), 1).await.unwrap();
    let limit = store.set_max_page_count(Some(0)).await.unwrap();
    assert!(limit > 0);
    let mut failure = None;
    for _ in 0..1000 {
        if let Err(error) = write(&store, 3000).await {
            failure = Some(error);
            break;
        }
    }
    let failure = failure.expect("the page limit was reached");
    assert!(failure.is_storage_full(), "{failure:?}");
    // Still full, and still failing as full (not as a stuck
    // transaction), on every write.
    for _ in 0..3 {
        let error = write(&store, 3000).await.unwrap_err();
        assert!(error.is_storage_full(), "{error:?}");
    }
    store.set_max_page_count(None).await.unwrap();
    for _ in 0..3 {
        write(&store, 3000).await.unwrap();
    }
    store.close().await;
}

#[tokio::test]
async fn results_stored_as_paths_are_read_as_the_rows_they_name() {
    let dir = tempfile::tempdir().unwrap();
    database_of_version_2(dir.path()).await;
    let store = Store::open(dir.path(), 1).await.unwrap();
    let result = |id| {
        let store = store.clone();
        async move { store.job(JobId(id)).await.unwrap().unwrap().result }
    };
    assert_eq!(
        result(1).await,
        Some(JobResult::Calibration(CalibrationId(2)))
    );
    assert_eq!(
        result(2).await,
        Some(JobResult::Frame {
            sequence_id: SequenceId(1),
            frame: FrameNumber(0)
        })
    );
    assert_eq!(result(3).await, None);
    assert_eq!(result(4).await, Some(JobResult::Link("/echo".to_owned())));
    assert_eq!(result(5).await, None);
    // The paths are gone from the jobs the rows now name; a plug-in
    // kind's link stays.
    let links: Vec<(i64, Option<String>)> =
        sqlx::query_as("SELECT id, result FROM jobs ORDER BY id")
            .fetch_all(&store.reader)
            .await
            .unwrap();
    assert_eq!(
        links,
        vec![
            (1, None),
            (2, None),
            (3, None),
            (4, Some("/echo".to_owned())),
            (5, None)
        ]
    );
    store.close().await;
}

/// Migration 5 names the calibration that made each stored particle
/// set: before it, the sequence's one calibration did.
#[tokio::test]
async fn particles_stored_before_migration_5_name_their_sequences_calibration() {
    let dir = tempfile::tempdir().unwrap();
    database_of_version_2(dir.path()).await;
    let pool = migrated_to(dir.path(), 4).await;
    sqlx::raw_sql(
        "INSERT INTO sequences (id, calibration_id, name, parameters, keep_images)
             VALUES (2, 2, '', '{}', 1);
         INSERT INTO jobs (id, kind, payload, state) VALUES (6, 'process_frame', '{}', 'succeeded');
         INSERT INTO frames (sequence_id, frame, job_id, input) VALUES (2, 0, 6, 'targets');
         INSERT INTO particles (sequence_id, frame, count, data) VALUES
             (1, 0, 0, x''), (2, 0, 0, x'');",
    )
    .execute(&pool)
    .await
    .unwrap();
    pool.close().await;
    let store = Store::open(dir.path(), 1).await.unwrap();
    let made_by = |sequence| {
        let store = store.clone();
        async move {
            store
                .frame_particles(SequenceId(sequence), FrameNumber(0))
                .await
                .unwrap()
                .map(|(_, _, calibration)| calibration)
        }
    };
    assert_eq!(made_by(1).await, Some(CalibrationId(1)));
    assert_eq!(made_by(2).await, Some(CalibrationId(2)));
    let origin = store.calibration(CalibrationId(2)).await.unwrap().unwrap();
    assert_eq!(origin.origin, None);
    store.close().await;
}

/// Migration 7 records the calibration a tracking run's recovery
/// projects with: a run stored before has none (and its settings no
/// `recovery`: it goes on without), a new run gets its sequence's.
#[tokio::test]
async fn tracking_runs_before_migration_7_have_no_calibration_and_new_ones_their_sequences() {
    let dir = tempfile::tempdir().unwrap();
    database_of_version_2(dir.path()).await;
    let pool = migrated_to(dir.path(), 6).await;
    let old_settings = r#"{"max_velocity":2.0,"max_acceleration":1.0,"max_gap":1,"min_length":3,"fit_half_window":2,"fit_order":2,"first_frame":0}"#;
    sqlx::query("INSERT INTO tracking_runs (id, sequence_id, parameters) VALUES (1, 1, $1)")
        .bind(old_settings)
        .execute(&pool)
        .await
        .unwrap();
    pool.close().await;
    let store = Store::open(dir.path(), 1).await.unwrap();
    let old = store.tracking_run(TrackingRunId(1)).await.unwrap().unwrap();
    assert_eq!(old.calibration_id, None);
    assert!(!old.parameters.recovers());
    let new = store
        .insert_tracking_run(SequenceId(1), &old.parameters)
        .await
        .unwrap()
        .unwrap();
    assert_eq!(new.calibration_id, Some(CalibrationId(1)));
    store.close().await;
}

/// Trajectory points are found by block of frames, then trajectory
/// (migration 10): every window of trajectories and frames gives exactly
/// the points a filter of all of them gives, in trajectory and frame
/// order, for points stored before the migration and after it alike, for
/// windows within a block, across blocks, past the points' frames, and
/// for every frame (the whole range of frame numbers, which must not
/// count its blocks one by one).
#[tokio::test]
async fn trajectory_points_are_read_by_block_as_a_filter_of_all_reads_them() {
    let dir = tempfile::tempdir().unwrap();
    database_of_version_2(dir.path()).await;
    // Trajectory t lives in frames t..t+20 as particle t of each frame.
    let point = |t: i64, f: i64| tracking::PointRow {
        trajectory: t,
        frame: FrameNumber(f),
        particle: t,
        position: [t as f64, f as f64, 0.5],
        velocity: (f > t).then_some([1.0, 2.0, 3.0]),
        acceleration: None,
        velocity_sigma: (f > t).then_some([0.1, 0.2, 0.3]),
        targets: format!("{t},-1"),
    };
    let frame_points = |f: i64| -> Vec<tracking::PointRow> {
        (0..40)
            .filter(|t| (*t..t + 20).contains(&f))
            .map(|t| point(t, f))
            .collect()
    };
    // Frames 0..10 stored under the schema before migration 10.
    let pool = migrated_to(dir.path(), 9).await;
    sqlx::raw_sql("INSERT INTO tracking_runs (id, sequence_id, parameters) VALUES (1, 1, '{}')")
        .execute(&pool)
        .await
        .unwrap();
    for f in 0..10 {
        for p in frame_points(f) {
            sqlx::query(
                "INSERT INTO trajectory_points (run_id, trajectory, frame, particle, x, y, z, \
                 u, v, w, su, sv, sw, targets) VALUES (1, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            )
            .bind(p.trajectory)
            .bind(p.frame.0)
            .bind(p.particle)
            .bind(p.position[0])
            .bind(p.position[1])
            .bind(p.position[2])
            .bind(p.velocity.map(|v| v[0]))
            .bind(p.velocity.map(|v| v[1]))
            .bind(p.velocity.map(|v| v[2]))
            .bind(p.velocity_sigma.map(|v| v[0]))
            .bind(p.velocity_sigma.map(|v| v[1]))
            .bind(p.velocity_sigma.map(|v| v[2]))
            .bind(&p.targets)
            .execute(&pool)
            .await
            .unwrap();
        }
        sqlx::query(
            "INSERT INTO trajectories (run_id, id, first_frame, last_frame, length) \
             SELECT 1, trajectory, min(frame), max(frame), count(*) FROM trajectory_points \
             WHERE run_id = 1 GROUP BY trajectory \
             ON CONFLICT (run_id, id) DO UPDATE SET first_frame = excluded.first_frame, \
             last_frame = excluded.last_frame, length = excluded.length",
        )
        .execute(&pool)
        .await
        .unwrap();
    }
    sqlx::query(
        "UPDATE tracking_runs SET tracked_through = 9, lease_owner = 'test', lease_token = 1",
    )
    .execute(&pool)
    .await
    .unwrap();
    pool.close().await;
    // Frames 10..60 stored by the store, after the migration.
    let store = Store::open(dir.path(), 1).await.unwrap();
    let run = TrackingRunId(1);
    let token = store
        .take_tracking_lease(run, "test", Duration::from_secs(60))
        .await
        .unwrap()
        .unwrap();
    for f in 10..60 {
        let stored = store
            .store_tracked_frame(
                (run, token),
                Some(FrameNumber(f - 1)),
                FrameNumber(f),
                Some(40),
                &frame_points(f),
            )
            .await
            .unwrap();
        assert!(stored, "frame {f}");
    }
    let all: Vec<tracking::PointRow> = (0..40)
        .flat_map(|t| (t..t + 20).map(move |f| point(t, f)))
        .collect();
    let full = (FrameNumber(i64::MIN), FrameNumber(i64::MAX));
    for (ids, frames) in [
        ((0, 39), full),
        ((0, 39), (FrameNumber(0), FrameNumber(59))),
        ((5, 7), (FrameNumber(15), FrameNumber(17))),
        ((10, 10), (FrameNumber(16), FrameNumber(16))),
        ((3, 30), (FrameNumber(9), FrameNumber(33))),
        ((20, 39), (FrameNumber(31), FrameNumber(200))),
        ((0, 4), (FrameNumber(-50), FrameNumber(2))),
        ((0, 4), (FrameNumber(30), FrameNumber(40))),
        ((40, 60), full),
        ((7, 3), full),
        ((0, 39), (FrameNumber(20), FrameNumber(10))),
    ] {
        let expected: Vec<&tracking::PointRow> = all
            .iter()
            .filter(|p| (ids.0..=ids.1).contains(&p.trajectory))
            .filter(|p| (frames.0..=frames.1).contains(&p.frame))
            .collect();
        let found = store.trajectory_points(run, ids, frames).await.unwrap();
        assert_eq!(
            found.iter().collect::<Vec<_>>(),
            expected,
            "trajectories {ids:?}, frames {frames:?}"
        );
    }
    store.close().await;
}
