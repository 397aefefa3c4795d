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

use std::fmt;
use std::str::FromStr;

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

/// A PostgreSQL connection URL (`postgres://` or `postgresql://`), as
/// `--database` / `PTV_DATABASE_URL` give it. Shown without its password.
#[derive(Clone, PartialEq, Eq)]
pub struct PostgresUrl(String);

impl PostgresUrl {
    /// The URL, password included, for connecting.
    pub fn as_str(&self) -> &str {
        &self.0
    }

    /// The server it names, `HOST:PORT` (as libpq reads the URL: a host
    /// or port left out is the environment's or the default), for
    /// messages; `None` if the URL does not parse.
    pub fn server(&self) -> Option<String> {
        let options = sqlx::postgres::PgConnectOptions::from_str(&self.0).ok()?;
        Some(format!("{}:{}", options.get_host(), options.get_port()))
    }
}

impl FromStr for PostgresUrl {
    type Err = String;

    fn from_str(url: &str) -> Result<Self, Self::Err> {
        if url.starts_with("postgres://") || url.starts_with("postgresql://") {
            Ok(PostgresUrl(url.to_owned()))
        } else {
            Err(format!(
                "`{}` is not a PostgreSQL URL (postgres://USER@HOST:PORT/DATABASE); \
                 leave --database out for SQLite in the data directory",
                redacted(url)
            ))
        }
    }
}

impl fmt::Debug for PostgresUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "PostgresUrl({})", redacted(&self.0))
    }
}

impl fmt::Display for PostgresUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&redacted(&self.0))
    }
}

/// A URL with the password of its user part replaced by `***`.
fn redacted(url: &str) -> String {
    let Some((scheme, rest)) = url.split_once("://") else {
        return url.to_owned();
    };
    let (authority, path) = rest.split_at(rest.find('/').unwrap_or(rest.len()));
    match authority.rsplit_once('@') {
        Some((user, host)) => match user.split_once(':') {
            Some((name, _)) => format!("{scheme}://{name}:***@{host}{path}"),
            None => url.to_owned(),
        },
        None => url.to_owned(),
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
        sqlx::Error::Io(io) if crate::service::images::is_storage_full(io) => {
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
    fn a_postgres_url_is_taken_and_shown_without_its_password() {
        let url: PostgresUrl = "postgres://ptv:secret@db.lab:5432/ptv".parse().unwrap();
        assert_eq!(url.as_str(), "postgres://ptv:secret@db.lab:5432/ptv");
        assert_eq!(url.to_string(), "postgres://ptv:***@db.lab:5432/ptv");
        assert!(!format!("{url:?}").contains("secret"));
        let error = "mysql://ptv:secret@db/ptv"
            .parse::<PostgresUrl>()
            .unwrap_err();
        assert!(error.contains("not a PostgreSQL URL"), "{error}");
        assert!(!error.contains("secret"), "{error}");
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
