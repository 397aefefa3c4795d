//! The store's errors: what a failed operation means to its caller
//! ([`ErrorKind`]), whatever the engine, with the engine's own error kept
//! for the log. Everything outside the store sees [`StoreError`], never
//! sqlx's type; this is the one place that reads engine error codes.

use std::fmt;

/// A failed database operation: its [`ErrorKind`] and the engine's error.
#[derive(Debug)]
pub struct StoreError {
    kind: ErrorKind,
    engine: sqlx::Error,
}

impl StoreError {
    /// What the error means to the caller.
    pub fn kind(&self) -> ErrorKind {
        self.kind
    }

    /// Whether the disk (or SQLite's page limit) is full.
    pub fn is_storage_full(&self) -> bool {
        self.kind == ErrorKind::StorageFull
    }

    /// Whether the operation failed on an I/O error on the way to the
    /// database (a name lookup, the network, a file), whatever its kind:
    /// at start-up, with a server to reach, one not reachable yet.
    pub fn is_io(&self) -> bool {
        matches!(self.engine, sqlx::Error::Io(_))
    }

    /// The store's error for a database that did not answer in time.
    pub(super) fn timed_out() -> StoreError {
        sqlx::Error::PoolTimedOut.into()
    }
}

impl From<sqlx::Error> for StoreError {
    fn from(engine: sqlx::Error) -> Self {
        StoreError {
            kind: kind_of(&engine),
            engine,
        }
    }
}

impl From<sqlx::migrate::MigrateError> for StoreError {
    fn from(error: sqlx::migrate::MigrateError) -> Self {
        sqlx::Error::from(error).into()
    }
}

impl From<std::io::Error> for StoreError {
    fn from(error: std::io::Error) -> Self {
        sqlx::Error::Io(error).into()
    }
}

/// The engine's message (its sources follow, as for sqlx's own error).
impl fmt::Display for StoreError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.engine.fmt(f)
    }
}

impl std::error::Error for StoreError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        std::error::Error::source(&self.engine)
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
fn kind_of(error: &sqlx::Error) -> ErrorKind {
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
            kind_of(&io(std::io::ErrorKind::ConnectionRefused)),
            ErrorKind::Unavailable
        );
        assert_eq!(kind_of(&sqlx::Error::PoolTimedOut), ErrorKind::Unavailable);
        assert_eq!(
            kind_of(&sqlx::Error::Io(std::io::Error::from_raw_os_error(28))),
            ErrorKind::StorageFull
        );
        assert_eq!(kind_of(&sqlx::Error::RowNotFound), ErrorKind::Other);
    }
}
