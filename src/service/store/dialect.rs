//! The two engines' differences, kept to the fragments of SQL that differ
//! (one text per query: the store writes every query once, with `$N`
//! parameters, which both SQLite and PostgreSQL read), and how their
//! errors are told apart.
//!
//! | | SQLite | PostgreSQL |
//! |---|---|---|
//! | now, as stored (UTC RFC 3339 text, ms) | `strftime('%Y-%m-%dT%H:%M:%fZ', 'now')` | `to_char(clock_timestamp() AT TIME ZONE 'UTC', ...)` |
//! | now + a lease (seconds bound at `$N`, either sign) | `strftime(..., printf('%+.3f seconds', $N))` | `clock_timestamp() + make_interval(secs => $N)` |
//! | a claim's row lock | the write lock (`BEGIN IMMEDIATE`) | `FOR UPDATE SKIP LOCKED` |
//! | a row held to the end of a write (a sequence's) | the write lock | `FOR UPDATE` |
//! | a write transaction | `BEGIN IMMEDIATE` on the one writer connection | `BEGIN` (read committed) on a pool |
//!
//! Timestamps stay text in both, in one format, so that they compare as
//! text and read back the same whatever the engine.

use sqlx::{Any, Transaction};

use crate::service::model::ids::SequenceId;

/// Which engine a [`super::Store`] runs on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dialect {
    /// SQLite in the data directory (the embedded default).
    Sqlite,
    /// A PostgreSQL server (`--database postgres://...`).
    Postgres,
}

/// PostgreSQL's clock as the stored timestamps are written.
const PG_FORMAT: &str = r#"'YYYY-MM-DD"T"HH24:MI:SS.MS"Z"'"#;

impl Dialect {
    /// The database's clock now, as the stored timestamps are written.
    pub(super) fn now(self) -> String {
        match self {
            Dialect::Sqlite => "strftime('%Y-%m-%dT%H:%M:%fZ', 'now')".to_owned(),
            Dialect::Postgres => {
                format!("to_char(clock_timestamp() AT TIME ZONE 'UTC', {PG_FORMAT})")
            }
        }
    }

    /// The database's clock plus the seconds bound at `$parameter` (a
    /// double), as the stored timestamps are written.
    pub(super) fn now_plus(self, parameter: usize) -> String {
        match self {
            Dialect::Sqlite => format!(
                "strftime('%Y-%m-%dT%H:%M:%fZ', 'now', printf('%+.3f seconds', ${parameter}))"
            ),
            Dialect::Postgres => format!(
                "to_char((clock_timestamp() + make_interval(secs => ${parameter})) \
                 AT TIME ZONE 'UTC', {PG_FORMAT})"
            ),
        }
    }

    /// Whether a row's lease (`lease_until`) has run out, or it has none.
    pub(super) fn lease_expired(self) -> String {
        format!("(lease_until IS NULL OR lease_until <= {})", self.now())
    }

    /// What a claim's `SELECT` of a queued row ends with: nothing on
    /// SQLite (the write transaction holds the database's write lock),
    /// `FOR UPDATE SKIP LOCKED` on PostgreSQL (claimers in other
    /// transactions pass over a row one of them has locked).
    pub(super) fn skip_locked(self) -> &'static str {
        match self {
            Dialect::Sqlite => "",
            Dialect::Postgres => " FOR UPDATE SKIP LOCKED",
        }
    }

    /// What a `SELECT` of a row that a write transaction must hold until
    /// it ends (its sequence, before checking the sequence's frames) ends
    /// with: nothing on SQLite (the write lock holds the database),
    /// `FOR UPDATE` on PostgreSQL (a frame inserted meanwhile, whose
    /// foreign key takes a share lock on the same row, waits).
    pub(super) fn for_update(self) -> &'static str {
        match self {
            Dialect::Sqlite => "",
            Dialect::Postgres => " FOR UPDATE",
        }
    }

    /// How a write transaction begins.
    pub(super) fn begin_write(self) -> &'static str {
        match self {
            Dialect::Sqlite => "BEGIN IMMEDIATE",
            Dialect::Postgres => "BEGIN",
        }
    }
}

/// What a database error means for its caller, whatever the engine: the
/// HTTP layer maps it to a status, the workers to what happens to the job
/// attempt (the one place that looks at engine codes).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ErrorKind {
    /// The disk (or SQLite's page limit) is full: SQLITE_FULL, an I/O
    /// error that says so, PostgreSQL's SQLSTATE 53100 (disk full). A 507
    /// with `Retry-After`; a job attempt given back uncounted.
    StorageFull,
    /// The database cannot be reached for now: connection refused or
    /// broken, the pool timed out, PostgreSQL restarting or shutting down
    /// (SQLSTATE 57P01, 57P02, 57P03, class 08), SQLite still busy or
    /// locked by another process's writer after its busy timeout
    /// (SQLITE_BUSY, SQLITE_LOCKED and their extended codes: `ptv worker`
    /// processes on one data directory, on a loaded machine). A 503 with
    /// `Retry-After`; a job attempt given back uncounted; workers and the
    /// tracker wait and try again.
    Unavailable,
    /// Anything else (a bug, a constraint, a corrupt file): a 500.
    Other,
}

/// SQLite's result code for "database or disk is full" (it has no
/// extended codes).
const SQLITE_FULL: &str = "13";

/// Whether `code` is SQLite's SQLITE_BUSY (5) or SQLITE_LOCKED (6), or
/// one of their extended codes (the primary code in the low byte).
/// SQLite's codes are decimal numbers of at most four digits;
/// PostgreSQL's SQLSTATEs have five characters, so none is taken for one.
fn sqlite_busy(code: &str) -> bool {
    code.len() < 5 && code.parse::<u32>().is_ok_and(|n| matches!(n & 0xff, 5 | 6))
}

/// What `error` means (see [`ErrorKind`]).
pub fn error_kind(error: &sqlx::Error) -> ErrorKind {
    match error {
        sqlx::Error::Database(db) => match db.code().as_deref() {
            Some(SQLITE_FULL | "53100") => ErrorKind::StorageFull,
            Some("57P01" | "57P02" | "57P03") => ErrorKind::Unavailable,
            Some(code) if code.len() == 5 && code.starts_with("08") => ErrorKind::Unavailable,
            Some(code) if sqlite_busy(code) => ErrorKind::Unavailable,
            _ => ErrorKind::Other,
        },
        sqlx::Error::Io(io) if crate::service::infra::errors::is_storage_full(io) => {
            ErrorKind::StorageFull
        }
        sqlx::Error::Io(io) => {
            use std::io::ErrorKind as Io;
            match io.kind() {
                Io::ConnectionRefused
                | Io::ConnectionReset
                | Io::ConnectionAborted
                | Io::NotConnected
                | Io::BrokenPipe
                | Io::UnexpectedEof
                | Io::TimedOut
                | Io::AddrNotAvailable => ErrorKind::Unavailable,
                _ => ErrorKind::Other,
            }
        }
        sqlx::Error::PoolTimedOut | sqlx::Error::WorkerCrashed => ErrorKind::Unavailable,
        _ => ErrorKind::Other,
    }
}

/// Holds the sequence's row until the transaction ends, so that its
/// checks (no frames yet, no background yet) stay true until it commits:
/// on PostgreSQL `FOR UPDATE` (a frame's insert, whose foreign key takes a
/// share lock on the row, waits; so does another such transaction); on
/// SQLite the write lock already holds everything.
pub async fn lock_sequence(
    tx: &mut Transaction<'_, Any>,
    dialect: Dialect,
    sequence_id: SequenceId,
) -> Result<(), sqlx::Error> {
    sqlx::query(&format!(
        "SELECT id FROM sequences WHERE id = $1{}",
        dialect.for_update()
    ))
    .bind(sequence_id)
    .execute(&mut **tx)
    .await?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sqlite_busy_and_locked_are_told_from_other_codes() {
        // SQLITE_BUSY, SQLITE_BUSY_RECOVERY, SQLITE_BUSY_SNAPSHOT,
        // SQLITE_LOCKED, SQLITE_LOCKED_SHAREDCACHE.
        for code in ["5", "261", "517", "6", "262"] {
            assert!(sqlite_busy(code), "{code}");
        }
        // SQLITE_FULL, SQLITE_CONSTRAINT_UNIQUE, SQLITE_IOERR_READ, and
        // PostgreSQL's serialization failure and disk full.
        for code in ["13", "2067", "266", "40001", "53100", "00005"] {
            assert!(!sqlite_busy(code), "{code}");
        }
    }

    #[test]
    fn errors_are_told_apart_by_kind() {
        let io = |kind| sqlx::Error::Io(std::io::Error::from(kind));
        assert_eq!(
            error_kind(&io(std::io::ErrorKind::ConnectionRefused)),
            ErrorKind::Unavailable
        );
        assert_eq!(
            error_kind(&sqlx::Error::PoolTimedOut),
            ErrorKind::Unavailable
        );
        assert_eq!(
            error_kind(&sqlx::Error::Io(std::io::Error::from_raw_os_error(28))),
            ErrorKind::StorageFull
        );
        assert_eq!(error_kind(&sqlx::Error::RowNotFound), ErrorKind::Other);
    }
}
