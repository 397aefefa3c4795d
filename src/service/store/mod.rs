//! All of the service's SQL: calibrations, sequences, frames and their
//! inputs and results, and the job queue, in one database: SQLite in the
//! data directory (the default), or PostgreSQL (`--database
//! postgres://...`). The HTTP layer, the jobs and the tracker call
//! [`Store`]'s methods and do not know which engine runs.
//!
//! **One query text for both engines.** The queries go through sqlx's
//! `Any` driver and are written once, with `$N` parameters (SQLite reads
//! `$N` as parameter N); where the dialects differ (the database's clock
//! as stored text, the clock plus a lease, the claim's row lock, how a
//! write transaction begins) a [`Dialect`] supplies the fragment. `Any`
//! decodes `bool` only from a real boolean, so flags are 0/1 integers and
//! `EXISTS` is read through `CASE`; every integer is 64-bit.
//!
//! SQLite runs in WAL mode (readers never wait for the writer) with a busy
//! timeout. Writes go through a pool of one connection, so they queue in
//! the process instead of failing on SQLite's lock; reads use their own
//! pool. PostgreSQL has one pool for both; the server orders concurrent
//! writes (read committed), the claim locks its row with `FOR UPDATE SKIP
//! LOCKED`. Every multi-statement write is one transaction: an upload and
//! its job, a job's results and its completion. Queries are checked at run
//! time (no database at build time); their results map onto `FromRow`
//! structs (`FromRow` written out, no derive macros).
//!
//! What differs by engine: SQLite takes one write lock for every write
//! transaction (`BEGIN IMMEDIATE`), so transactions that read then write
//! are serial; on PostgreSQL they run concurrently and rely on their
//! `WHERE` fences (state, token, progress) and row locks. SQLite's page
//! limit ([`Store::set_max_page_count`]) and `left_clean`'s `BEGIN
//! DEFERRED` probe exist on SQLite only. Migrations are per engine
//! (`migrations/`, `migrations/postgres/`); PostgreSQL's run under its
//! advisory lock, SQLite's under the flock on `ptv.sqlite.lock`.
//!
//! **No connection is left inside a transaction.** A failed statement or
//! `COMMIT` leaves sqlx's `Transaction` to be dropped, which only queues a
//! `ROLLBACK` for the connection's next use. If SQLite already ended the
//! transaction itself (it may, on SQLITE_FULL, SQLITE_IOERR or
//! SQLITE_NOMEM), that `ROLLBACK` fails ("no transaction is active") and
//! sqlx's transaction depth stays at 1, so that every later `BEGIN
//! IMMEDIATE` on the one writer fails ("attempted to call begin_with at
//! non-zero transaction depth") until the process restarts. The writer
//! pool therefore checks every connection it gets back
//! (`after_release`, `left_clean`): the queued rollback has run by then
//! (the connection's worker runs its commands in order), and a connection
//! that sqlx or SQLite still thinks inside a transaction is closed, not
//! returned (closing rolls back whatever SQLite still holds). The next
//! write opens a fresh connection. One check at the pool covers every
//! write path, transactions and single statements alike, and also a
//! transaction whose future was cancelled; an explicit rollback in each
//! path would add nothing the queued one does not do.
//!
//! **Errors by kind**: the store's methods fail with [`StoreError`], never
//! sqlx's error, and its [`ErrorKind`] says what it means. A full disk
//! (SQLITE_FULL, PostgreSQL's 53100, [`StoreError::is_storage_full`]) is
//! an error of its own kind to the callers: a 507 with `Retry-After` to a
//! client, a job attempt given back to the queue ([`Store::give_back`])
//! rather than counted; so is a database that cannot be reached
//! (PostgreSQL stopped or restarting, the network): a 503 with
//! `Retry-After`, the attempt given back. [`Store::set_max_page_count`]
//! makes the writer fail exactly so (SQLite's page limit), for tests.
//!
//! One file per table group, each with its own `impl Store`:
//! `calibrations`, `sequences`
//! (sequences and their frames' inputs and results) and `jobs`
//! (the queue and the jobs' input files), `selfcal`
//! (refined calibrations, reprocessing), `tracking`
//! (tracking runs, the frames they took, trajectory points), `health`
//! (frames' calibration health, the sequences' drift monitors); here the pools, the migrations
//! and what they share.

mod calibrations;
mod dialect;
mod error;
mod events;
mod health;
mod jobs;
mod selfcal;
mod sequences;
mod tracking;

use std::path::Path;
use std::str::FromStr;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::Arc;
use std::time::Duration;

use std::future::Future;
use std::pin::Pin;

use sqlx::any::{AnyConnectOptions, AnyPoolOptions, AnyRow};
use sqlx::error::BoxDynError;
use sqlx::migrate::{Migration, MigrationSource, MigrationType, Migrator};
use sqlx::{Any, Database, Executor, Row, TransactionManager};
use sqlx::{AnyConnection, AnyPool};

use crate::service::infra::urls::PostgresUrl;

pub use self::calibrations::{insert_calibration, CalibrationRow, CalibrationSummary};
pub use self::dialect::Dialect;
pub use self::error::{ErrorKind, StoreError};
pub use self::events::EventRow;
pub use self::health::{HealthFrame, HealthRow, HealthSeriesPoint, HealthState};
pub use self::jobs::{
    enqueue, expire_leases, finish, ClaimOutcome, ClaimedJob, JobClaim, JobFile, JobResult, JobRow,
    JobState, RetryOutcome, WorkerId, MAX_ATTEMPTS,
};
pub use self::selfcal::{reprocess_payload, RefinedCalibration};
pub use self::sequences::{
    CameraImage, FrameCounts, FrameInput, FrameInputKind, FrameSummary, NewFrame, NewSequenceImage,
    SequenceImage, SequenceImageKind, SequenceImagesError, SequenceRow,
};
pub use self::tracking::{
    BackwardRow, FrameReadiness, PointRow, TrackingRunRow, TrackingState, TrajectoryRow,
};
pub use crate::service::model::ids::{
    CalibrationId, EventId, FrameNumber, JobId, LeaseToken, SequenceId, TrackingRunId,
    MAX_FRAME_NUMBER,
};

/// The database.
#[derive(Clone, Debug)]
pub struct Store {
    /// Readers, several at once (on PostgreSQL the same pool as `writer`).
    reader: AnyPool,
    /// The one writer on SQLite; on PostgreSQL a pool (the server orders
    /// the writes, with row locks).
    writer: AnyPool,
    /// Which engine runs, for the few fragments of SQL that differ.
    dialect: Dialect,
    /// The page limit put on the writer by [`Store::set_max_page_count`]
    /// (0: none), applied again to every writer connection opened.
    page_limit: Arc<AtomicU32>,
}

/// A lock that every process on the database holds one at a time
/// ([`Store::lock_across_hosts`]), held until dropped: on PostgreSQL a
/// transaction holding a transaction-level advisory lock (dropping it
/// rolls back, which releases the lock); nothing on SQLite, whose
/// processes share one host and lock a file instead.
#[derive(Debug)]
pub struct HostsLock(#[allow(dead_code)] Option<sqlx::Transaction<'static, Any>>);

/// Whether a writer connection came back outside any transaction, by
/// sqlx's count and, on SQLite, by SQLite's own state (`BEGIN` fails
/// inside a transaction; a deferred one takes no lock and writes nothing).
/// A connection for which this is false is closed rather than reused.
async fn left_clean(conn: &mut AnyConnection, dialect: Dialect) -> bool {
    let depth = <<Any as Database>::TransactionManager>::get_transaction_depth(conn);
    if depth > 0 {
        tracing::warn!(
            depth,
            "a database connection was left inside a transaction; it is closed"
        );
        return false;
    }
    if dialect == Dialect::Postgres {
        // The server ends a failed transaction's connection state itself
        // (sqlx's queued ROLLBACK runs before the next use).
        return true;
    }
    match conn.execute("BEGIN DEFERRED; ROLLBACK").await {
        Ok(_) => true,
        Err(error) => {
            tracing::warn!(%error, "a database connection is in an unknown state; it is closed");
            false
        }
    }
}

/// The schema's migrations, `migrations/*.sql`, compiled into the binary
/// (what `sqlx::migrate!` does, without its proc-macro, which would build
/// SQLite a second time for the compiler): [`MIGRATIONS`], or its first
/// ones (the tests build older databases).
#[derive(Debug)]
struct Migrations(&'static [(i64, &'static str, &'static str)]);

/// Version, description and SQL of each SQLite migration, in order.
const MIGRATIONS: &[(i64, &str, &str)] = &[
    (
        1,
        "service",
        include_str!("../../../migrations/0001_service.sql"),
    ),
    (
        2,
        "job_files",
        include_str!("../../../migrations/0002_job_files.sql"),
    ),
    (
        3,
        "job_results",
        include_str!("../../../migrations/0003_job_results.sql"),
    ),
    (
        4,
        "sequence_images",
        include_str!("../../../migrations/0004_sequence_images.sql"),
    ),
    (
        5,
        "self_calibration",
        include_str!("../../../migrations/0005_self_calibration.sql"),
    ),
    (
        6,
        "tracking",
        include_str!("../../../migrations/0006_tracking.sql"),
    ),
    (
        7,
        "tracking_recovery",
        include_str!("../../../migrations/0007_tracking_recovery.sql"),
    ),
    (
        8,
        "leases",
        include_str!("../../../migrations/0008_leases.sql"),
    ),
    (
        9,
        "events",
        include_str!("../../../migrations/0009_events.sql"),
    ),
    (
        10,
        "trajectory_points_by_block",
        include_str!("../../../migrations/0010_trajectory_points_by_block.sql"),
    ),
    (
        11,
        "calibration_health",
        include_str!("../../../migrations/0011_calibration_health.sql"),
    ),
    (
        12,
        "backward_tracking",
        include_str!("../../../migrations/0012_backward_tracking.sql"),
    ),
];

/// Version, description and SQL of each PostgreSQL migration, in order
/// (`migrations/postgres/`): 0001 is the schema SQLite's 0001-0008
/// reach, 0002 SQLite's 0009, 0003 SQLite's 0010, 0004 SQLite's 0011, 0005 SQLite's 0012; each
/// engine numbers its own migrations.
const POSTGRES_MIGRATIONS: &[(i64, &str, &str)] = &[
    (
        1,
        "schema",
        include_str!("../../../migrations/postgres/0001_schema.sql"),
    ),
    (
        2,
        "events",
        include_str!("../../../migrations/postgres/0002_events.sql"),
    ),
    (
        3,
        "trajectory_points_by_block",
        include_str!("../../../migrations/postgres/0003_trajectory_points_by_block.sql"),
    ),
    (
        4,
        "calibration_health",
        include_str!("../../../migrations/postgres/0004_calibration_health.sql"),
    ),
    (
        5,
        "backward_tracking",
        include_str!("../../../migrations/postgres/0005_backward_tracking.sql"),
    ),
];

impl<'s> MigrationSource<'s> for Migrations {
    fn resolve(
        self,
    ) -> Pin<Box<dyn Future<Output = Result<Vec<Migration>, BoxDynError>> + Send + 's>> {
        Box::pin(async move {
            Ok(self
                .0
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

/// Why a frame could not be stored.
#[derive(Debug, thiserror::Error)]
pub enum InsertFrameError {
    /// The frame number is taken.
    #[error("frame {frame} of sequence {sequence_id} exists")]
    Exists {
        /// The sequence.
        sequence_id: SequenceId,
        /// The frame.
        frame: FrameNumber,
    },
    /// The database failed.
    #[error(transparent)]
    Database(#[from] StoreError),
}

/// A completion that the job's holder may no longer make.
#[derive(Debug, thiserror::Error)]
pub enum CompleteError {
    /// The job is no longer running under this worker.
    #[error("job {0} is no longer held by this worker")]
    LostLease(JobId),
    /// The database failed.
    #[error(transparent)]
    Database(#[from] StoreError),
}

/// The store's error enums that wrap a database failure take sqlx's error
/// as [`StoreError`] (so that `?` works on a statement inside the store);
/// `sequences.rs`'s `SequenceImagesError` does so itself.
macro_rules! database_failure_from_sqlx {
    ($($type:ty),+) => {
        $(impl From<sqlx::Error> for $type {
            fn from(error: sqlx::Error) -> Self {
                Self::Database(error.into())
            }
        })+
    };
}
database_failure_from_sqlx!(InsertFrameError, CompleteError);

/// A stored text that names none of a column's values (a database written
/// by a newer version, or edited by hand).
#[derive(Debug, thiserror::Error)]
#[error("unknown {what} `{value}`; this version knows {known}")]
pub struct UnknownValue {
    /// What the column holds: `job state`, ...
    what: &'static str,
    /// The text found.
    value: String,
    /// The values this version knows, comma-separated.
    known: String,
}

/// An enum stored as text: its values and their names in the database.
trait TextColumn: Copy + 'static {
    /// What the column holds, for messages.
    const WHAT: &'static str;
    /// Every value.
    const ALL: &'static [Self];
    /// The name stored in the database.
    fn as_str(self) -> &'static str;

    /// The value of a stored name.
    fn parse_text(text: &str) -> Result<Self, UnknownValue> {
        Self::ALL
            .iter()
            .copied()
            .find(|value| value.as_str() == text)
            .ok_or_else(|| UnknownValue {
                what: Self::WHAT,
                value: text.to_owned(),
                known: Self::ALL
                    .iter()
                    .map(|v| v.as_str())
                    .collect::<Vec<_>>()
                    .join(", "),
            })
    }
}

/// Makes an enum a [`TextColumn`] with these names, parsed by `FromStr`.
macro_rules! stored_as_text {
    ($type:ident, $what:literal, { $($variant:ident => $name:literal),+ $(,)? }) => {
        impl $crate::service::store::TextColumn for $type {
            const WHAT: &'static str = $what;
            const ALL: &'static [$type] = &[$($type::$variant),+];

            fn as_str(self) -> &'static str {
                match self {
                    $($type::$variant => $name),+
                }
            }
        }

        impl std::str::FromStr for $type {
            type Err = $crate::service::store::UnknownValue;
            fn from_str(text: &str) -> Result<Self, Self::Err> {
                <$type as $crate::service::store::TextColumn>::parse_text(text)
            }
        }
    };
}
use stored_as_text;

/// A text column read as its enum; an unknown text is a decode error that
/// names the column and the text.
fn decode_text<T: FromStr<Err = UnknownValue>>(column: &str, text: &str) -> Result<T, sqlx::Error> {
    text.parse().map_err(|error| sqlx::Error::ColumnDecode {
        index: column.to_owned(),
        source: Box::new(error),
    })
}

/// The JSON text column `column` of `row`, parsed: settings are parsed
/// once, where they are read, and a stored text this version cannot read
/// is a decode error that names the column.
fn json_column<T: serde::de::DeserializeOwned>(
    row: &AnyRow,
    column: &str,
) -> Result<T, sqlx::Error> {
    serde_json::from_str(row.try_get::<&str, _>(column)?).map_err(|error| {
        sqlx::Error::ColumnDecode {
            index: column.to_owned(),
            source: Box::new(error),
        }
    })
}

/// `value` as the JSON text a column stores.
fn json_text<T: serde::Serialize>(value: &T) -> Result<String, StoreError> {
    serde_json::to_string(value).map_err(|error| sqlx::Error::Encode(Box::new(error)).into())
}

/// The text column `column` of `row`, as its enum (see [`decode_text`]).
fn text_column<T: FromStr<Err = UnknownValue>>(
    row: &AnyRow,
    column: &str,
) -> Result<T, sqlx::Error> {
    decode_text(column, row.try_get::<&str, _>(column)?)
}

/// realworld-axum-sqlx's `on_constraint`, for SQLite's unique and
/// primary-key violations: the statement's error, or the one that says
/// what the violation means.
trait OnUniqueViolation<T> {
    /// `error()` where the statement violated a unique constraint.
    fn on_unique_violation<E: From<sqlx::Error>>(self, error: impl FnOnce() -> E) -> Result<T, E>;
}

impl<T> OnUniqueViolation<T> for Result<T, sqlx::Error> {
    fn on_unique_violation<E: From<sqlx::Error>>(self, error: impl FnOnce() -> E) -> Result<T, E> {
        self.map_err(|e| match e {
            sqlx::Error::Database(ref db) if db.is_unique_violation() => error(),
            other => other.into(),
        })
    }
}

/// The SQLite database `ptv.sqlite` in `data_dir`, as a URL for the Any
/// driver (which takes its options from the URL only; the pragmas are set
/// on each connection by [`sqlite_pragmas`]).
fn sqlite_url(data_dir: &Path, read_only: bool) -> Result<AnyConnectOptions, sqlx::Error> {
    let path = data_dir.join("ptv.sqlite");
    let path = std::path::absolute(&path).map_err(sqlx::Error::Io)?;
    let mut url = String::from("sqlite://");
    for byte in path.as_os_str().as_encoded_bytes() {
        match byte {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'/' | b'-' | b'_' | b'.' | b'~' => {
                url.push(char::from(*byte))
            }
            other => url.push_str(&format!("%{other:02X}")),
        }
    }
    url.push_str(if read_only { "?mode=ro" } else { "?mode=rwc" });
    AnyConnectOptions::from_str(&url)
}

/// The pragmas of every SQLite connection: WAL (readers never wait for
/// the writer; set once, kept in the file), `synchronous = NORMAL` (in
/// WAL mode it survives a killed process; only a power loss may lose the
/// last transactions), a busy timeout, foreign keys.
async fn sqlite_pragmas(
    conn: &mut AnyConnection,
    writer: bool,
    synchronous: Synchronous,
) -> Result<(), sqlx::Error> {
    if writer {
        conn.execute("PRAGMA journal_mode = WAL").await?;
    }
    let synchronous = match synchronous {
        Synchronous::Normal => "NORMAL",
        Synchronous::Full => "FULL",
    };
    conn.execute(
        format!(
            "PRAGMA synchronous = {synchronous}; PRAGMA busy_timeout = 10000; \
             PRAGMA foreign_keys = ON"
        )
        .as_str(),
    )
    .await?;
    Ok(())
}

/// When SQLite's commits reach the disk (its `synchronous` setting, in
/// WAL mode).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Synchronous {
    /// `NORMAL`: a commit survives a killed process; a power loss may
    /// undo the last ones (the WAL is flushed at checkpoints). The
    /// default.
    #[default]
    Normal,
    /// `FULL`: every commit is flushed to the disk before it returns, so
    /// it survives a power loss too (`ptv serve --fsync`).
    Full,
}

impl Store {
    /// Opens (creating if missing) the database `ptv.sqlite` in
    /// `data_dir` and brings its schema up to date. Processes that start
    /// on one data directory at once (`ptv serve` and `ptv worker`s) open
    /// it one at a time, under a lock on `ptv.sqlite.lock`: two migrating
    /// a new database together would both apply its first migration, and
    /// switching a new database to WAL does not wait for a busy one.
    pub async fn open(data_dir: &Path, readers: u32) -> Result<Store, StoreError> {
        Store::open_sqlite(data_dir, readers, Synchronous::Normal).await
    }

    /// [`Store::open`] with SQLite's commits flushed as `synchronous` says.
    pub async fn open_sqlite(
        data_dir: &Path,
        readers: u32,
        synchronous: Synchronous,
    ) -> Result<Store, StoreError> {
        sqlx::any::install_default_drivers();
        let _opening =
            crate::service::infra::file_lock::exclusive(data_dir.join("ptv.sqlite.lock"))
                .await
                .map_err(sqlx::Error::Io)?;
        let page_limit = Arc::new(AtomicU32::new(0));
        let limit = page_limit.clone();
        let writer = AnyPoolOptions::new()
            .max_connections(1)
            .after_connect(move |conn, _| {
                let limit = limit.load(Ordering::Acquire);
                Box::pin(async move {
                    sqlite_pragmas(conn, true, synchronous).await?;
                    if limit > 0 {
                        apply_page_limit(conn, limit).await?;
                    }
                    Ok(())
                })
            })
            .after_release(|conn, _| {
                Box::pin(async move { Ok(left_clean(conn, Dialect::Sqlite).await) })
            })
            .connect_with(sqlite_url(data_dir, false)?)
            .await?;
        Migrator::new(Migrations(MIGRATIONS))
            .await
            .map_err(sqlx::Error::from)?
            .run(&writer)
            .await?;
        let reader = AnyPoolOptions::new()
            .max_connections(readers.max(1))
            .after_connect(move |conn, _| {
                Box::pin(async move { sqlite_pragmas(conn, false, synchronous).await })
            })
            .connect_with(sqlite_url(data_dir, true)?)
            .await?;
        Ok(Store {
            reader,
            writer,
            dialect: Dialect::Sqlite,
            page_limit,
        })
    }

    /// Opens one connection to the PostgreSQL server at `url` and closes it,
    /// giving up after `within`: the error names the cause (connection
    /// refused, no such host, a password refused), where the pool's only
    /// says that it timed out. An attempt without an answer in time is an
    /// I/O error of kind `TimedOut`.
    pub async fn reach_postgres(url: &PostgresUrl, within: Duration) -> Result<(), StoreError> {
        use sqlx::Connection as _;
        let options = sqlx::postgres::PgConnectOptions::from_str(url.as_str())?;
        match tokio::time::timeout(within, sqlx::PgConnection::connect_with(&options)).await {
            Ok(Ok(connection)) => {
                let _ = connection.close().await;
                Ok(())
            }
            Ok(Err(error)) => Err(error.into()),
            Err(_) => Err(std::io::Error::new(
                std::io::ErrorKind::TimedOut,
                format!("no answer within {:.0} s", within.as_secs_f64()),
            )
            .into()),
        }
    }

    /// Connects to the PostgreSQL database at `url` and brings its schema
    /// up to date. sqlx's migrator takes PostgreSQL's advisory lock for
    /// the run, so processes started together migrate one at a time. One
    /// pool serves reads and writes: `readers` connections and a few for
    /// the writes (claims, heartbeats, results).
    pub async fn open_postgres(url: &PostgresUrl, readers: u32) -> Result<Store, StoreError> {
        sqlx::any::install_default_drivers();
        let pool = AnyPoolOptions::new()
            .max_connections(readers.max(1) + 8)
            .acquire_timeout(Duration::from_secs(10))
            .after_release(|conn, _| {
                Box::pin(async move { Ok(left_clean(conn, Dialect::Postgres).await) })
            })
            .connect_with(AnyConnectOptions::from_str(url.as_str())?)
            .await?;
        Migrator::new(Migrations(POSTGRES_MIGRATIONS))
            .await
            .map_err(sqlx::Error::from)?
            .run(&pool)
            .await?;
        Ok(Store {
            reader: pool.clone(),
            writer: pool,
            dialect: Dialect::Postgres,
            page_limit: Arc::new(AtomicU32::new(0)),
        })
    }

    /// Which engine runs.
    pub fn dialect(&self) -> Dialect {
        self.dialect
    }

    /// Fault injection for tests: limits the database to `pages` pages
    /// (SQLite's `max_page_count`; never below its current size, so
    /// `Some(0)` means "not one page more"), so that writes that need
    /// more fail with SQLITE_FULL exactly as on a full disk; `None` lifts
    /// the limit. Returns the limit in force. SQLite only (PostgreSQL has
    /// no such limit): an error on PostgreSQL.
    #[doc(hidden)]
    pub async fn set_max_page_count(&self, pages: Option<u32>) -> Result<u32, StoreError> {
        if self.dialect != Dialect::Sqlite {
            return Err(sqlx::Error::Configuration(
                "the page limit is SQLite's; PostgreSQL has none".into(),
            )
            .into());
        }
        self.page_limit
            .store(pages.map_or(0, |p| p.max(1)), Ordering::Release);
        let mut conn = self.writer.acquire().await?;
        match pages {
            Some(pages) => Ok(apply_page_limit(&mut conn, pages.max(1)).await?),
            None => {
                // A fresh connection has SQLite's default limit.
                conn.close().await?;
                let mut conn = self.writer.acquire().await?;
                let (limit,): (i64,) = sqlx::query_as("PRAGMA max_page_count")
                    .fetch_one(&mut *conn)
                    .await?;
                Ok(u32::try_from(limit).unwrap_or(u32::MAX))
            }
        }
    }

    /// Starts a write transaction. On SQLite with `BEGIN IMMEDIATE`: it
    /// takes SQLite's write lock at once, so a transaction that reads
    /// before it writes never finds its snapshot stale when it comes to
    /// write (a deferred `BEGIN` would then fail with SQLITE_BUSY whatever
    /// the busy timeout), also with several processes on one database. On
    /// PostgreSQL a plain `BEGIN` (read committed): the writes that must
    /// not race are fenced by their `WHERE` (tokens, states) or lock their
    /// rows (`FOR UPDATE`).
    async fn write_transaction(&self) -> Result<sqlx::Transaction<'static, Any>, StoreError> {
        Ok(self.writer.begin_with(self.dialect.begin_write()).await?)
    }

    /// Readiness: on SQLite the writer takes SQLite's write lock (`BEGIN
    /// IMMEDIATE`, then `ROLLBACK`: nothing written) within `within`; on
    /// PostgreSQL a connection answers. A full disk does not show here
    /// (only a write that needs space finds it); a writer that cannot be
    /// opened or locked does.
    pub async fn ready(&self, within: Duration) -> Result<(), StoreError> {
        let probe = match self.dialect {
            Dialect::Sqlite => "BEGIN IMMEDIATE; ROLLBACK",
            Dialect::Postgres => "SELECT 1",
        };
        tokio::time::timeout(within, async {
            let mut conn = self.writer.acquire().await?;
            conn.execute(probe).await?;
            Ok(())
        })
        .await
        .unwrap_or_else(|_| Err(StoreError::timed_out()))
    }

    /// Closes both pools.
    pub async fn close(&self) {
        self.writer.close().await;
        self.reader.close().await;
    }

    /// Takes the lock named `key` that the processes on this database
    /// share with every other host's (see [`HostsLock`]); waits while
    /// another holds it. One connection stays with the lock: take it once
    /// per process at a time (behind a process mutex), so that waiters do
    /// not use up the pool.
    pub async fn lock_across_hosts(&self, key: i64) -> Result<HostsLock, StoreError> {
        match self.dialect {
            Dialect::Sqlite => Ok(HostsLock(None)),
            Dialect::Postgres => {
                let mut tx = self.writer.begin().await?;
                sqlx::query("SELECT pg_advisory_xact_lock($1)")
                    .bind(key)
                    .execute(&mut *tx)
                    .await?;
                Ok(HostsLock(Some(tx)))
            }
        }
    }

    /// Whether any frame, job or sequence refers to the file with this hash.
    pub async fn image_in_use(&self, sha256: &str) -> Result<bool, StoreError> {
        let mut conn = self.writer.acquire().await?;
        Ok(file_in_use(&mut conn, sha256).await?)
    }
}

/// Sets the connection's `max_page_count`; returns the limit in force.
async fn apply_page_limit(conn: &mut AnyConnection, pages: u32) -> Result<u32, sqlx::Error> {
    let (limit,): (i64,) = sqlx::query_as(&format!("PRAGMA max_page_count = {pages}"))
        .fetch_one(&mut *conn)
        .await?;
    Ok(u32::try_from(limit).unwrap_or(u32::MAX))
}

/// The `VALUES` list of a multi-row insert, `rows` rows of `columns`
/// parameters each, bound in order: `$1`.. on PostgreSQL; on SQLite
/// anonymous `?`. SQLite keeps every named or numbered parameter (`$N`,
/// `?N`) in a list it searches linearly, once per parameter when the
/// statement is prepared and again when each value is bound, so a
/// statement of N such parameters costs O(N²): 0.4 s for the 17,000 of a
/// frame's trajectory points (issue 30). Anonymous ones are bound by
/// position at no search. (sqlx's `QueryBuilder` writes `?` under the
/// `Any` driver, which PostgreSQL does not read.)
fn placeholders(dialect: Dialect, rows: usize, columns: usize) -> String {
    let mut sql = String::with_capacity(rows * columns * 7);
    let mut numbers = itoa::Buffer::new();
    for row in 0..rows {
        if row > 0 {
            sql.push_str(", ");
        }
        sql.push('(');
        for column in 0..columns {
            if column > 0 {
                sql.push_str(", ");
            }
            match dialect {
                Dialect::Sqlite => sql.push('?'),
                Dialect::Postgres => {
                    sql.push('$');
                    sql.push_str(numbers.format(row * columns + column + 1));
                }
            }
        }
        sql.push(')');
    }
    sql
}

/// The most rows one multi-row insert writes: on SQLite (in this
/// process, no round trip) 128; on PostgreSQL, where each statement is a
/// round trip to the server, 512 (8,704 values of a trajectory point's
/// 17, within its 65,535).
fn rows_per_statement(dialect: Dialect) -> usize {
    match dialect {
        Dialect::Sqlite => 128,
        Dialect::Postgres => 512,
    }
}

/// The row counts of the statements that insert `rows` rows: full ones of
/// [`rows_per_statement`], the rest in powers of two (100 rows as 64, 32
/// and 4). A table's inserts then have at most ten statement texts,
/// each prepared once per connection and kept in sqlx's statement cache,
/// where a text per row count would prepare each insert anew; and no
/// statement is so long that a slow-statement log of it (sqlx logs the
/// whole text) floods the log.
fn statement_rows(dialect: Dialect, rows: usize) -> impl Iterator<Item = usize> {
    let most = rows_per_statement(dialect);
    let rest = rows % most;
    std::iter::repeat(most).take(rows / most).chain(
        (0..usize::BITS)
            .rev()
            .map(|bit| 1usize << bit)
            .filter(move |size| rest & size != 0),
    )
}

/// `items` in the slices [`statement_rows`] gives.
fn statement_chunks<T>(dialect: Dialect, mut items: &[T]) -> impl Iterator<Item = &[T]> {
    statement_rows(dialect, items.len()).map(move |n| {
        let (chunk, rest) = items.split_at(n);
        items = rest;
        chunk
    })
}

/// Whether any frame's image, job's file or sequence's background or
/// mask is the file with this hash.
async fn file_in_use(conn: &mut AnyConnection, sha256: &str) -> Result<bool, sqlx::Error> {
    let (n,): (i64,) = sqlx::query_as(
        "SELECT (SELECT count(*) FROM images WHERE sha256 = $1) + \
                (SELECT count(*) FROM job_files WHERE sha256 = $1) + \
                (SELECT count(*) FROM sequence_images WHERE sha256 = $1)",
    )
    .bind(sha256)
    .fetch_one(&mut *conn)
    .await?;
    Ok(n > 0)
}

#[cfg(test)]
mod tests;
