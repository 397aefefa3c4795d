//! The two engines' differences, kept to the fragments of SQL that differ
//! (one text per query: the store writes every query once, with `$N`
//! parameters, which both SQLite and PostgreSQL read). How their errors
//! are told apart is [`super::error`].
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
