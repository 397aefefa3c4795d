//! The event log (`events`, migration 0009): the changes announced on the
//! sequences' event streams, appended by the process that made each
//! change once it committed, and read back by every serving process
//! (`service::events`). Rows are appended in batches, one transaction per
//! batch, and deleted after a day.

use sqlx::any::AnyRow;
use sqlx::{FromRow, Row};

use super::StoreError;
use super::{EventId, SequenceId, Store};

/// Rows of one `INSERT` into the log (two parameters each, far below
/// either engine's limit).
const INSERT_ROWS: usize = 200;

/// One logged change: its id, its sequence and the change as JSON.
#[derive(Clone, Debug, PartialEq)]
pub struct EventRow {
    /// The event's id (the SSE `id:`).
    pub id: EventId,
    /// The sequence it changed.
    pub sequence_id: SequenceId,
    /// The change (`service::events::Change`) as JSON.
    pub change: String,
}

impl FromRow<'_, AnyRow> for EventRow {
    fn from_row(row: &AnyRow) -> Result<Self, sqlx::Error> {
        Ok(EventRow {
            id: row.try_get("id")?,
            sequence_id: row.try_get("sequence_id")?,
            change: row.try_get("change")?,
        })
    }
}

impl Store {
    /// Appends `events` (sequence, change as JSON) in one transaction, in
    /// order, [`INSERT_ROWS`] rows a statement; returns the last id given.
    pub async fn append_events(
        &self,
        events: &[(SequenceId, String)],
    ) -> Result<Option<EventId>, StoreError> {
        if events.is_empty() {
            return Ok(None);
        }
        let mut tx = self.write_transaction().await?;
        let mut last = None;
        for chunk in events.chunks(INSERT_ROWS) {
            let sql = format!(
                "INSERT INTO events (sequence_id, change) VALUES {} RETURNING id",
                super::placeholders(self.dialect, chunk.len(), 2)
            );
            let mut insert = sqlx::query_as::<_, (EventId,)>(&sql);
            for (sequence_id, change) in chunk {
                insert = insert.bind(*sequence_id).bind(change.as_str());
            }
            let ids = insert.fetch_all(&mut *tx).await?;
            last = ids.into_iter().map(|(id,)| id).max().or(last);
        }
        tx.commit().await?;
        Ok(last)
    }

    /// The logged events of every sequence with an id above `after`, in
    /// id order, at most `limit`.
    pub async fn events_after(
        &self,
        after: EventId,
        limit: u32,
    ) -> Result<Vec<EventRow>, StoreError> {
        sqlx::query_as(
            "SELECT id, sequence_id, change FROM events WHERE id > $1 ORDER BY id LIMIT $2",
        )
        .bind(after)
        .bind(i64::from(limit))
        .fetch_all(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// The logged events of `sequence_id` with an id above `after`, in id
    /// order, at most `limit`: what a client reconnecting with
    /// `Last-Event-ID` missed.
    pub async fn sequence_events_after(
        &self,
        sequence_id: SequenceId,
        after: EventId,
        limit: u32,
    ) -> Result<Vec<EventRow>, StoreError> {
        sqlx::query_as(
            "SELECT id, sequence_id, change FROM events \
             WHERE sequence_id = $1 AND id > $2 ORDER BY id LIMIT $3",
        )
        .bind(sequence_id)
        .bind(after)
        .bind(i64::from(limit))
        .fetch_all(&self.reader)
        .await
        .map_err(StoreError::from)
    }

    /// The highest event id logged (0 when none): where a process that
    /// starts following the log begins.
    pub async fn last_event_id(&self) -> Result<EventId, StoreError> {
        let (id,): (i64,) = sqlx::query_as("SELECT COALESCE(MAX(id), 0) FROM events")
            .fetch_one(&self.reader)
            .await?;
        Ok(EventId(id))
    }

    /// The lowest event id still logged (none: the log is empty): a
    /// client that last saw an event below it missed some that are gone.
    pub async fn oldest_event_id(&self) -> Result<Option<EventId>, StoreError> {
        let (id,): (Option<i64>,) = sqlx::query_as("SELECT MIN(id) FROM events")
            .fetch_one(&self.reader)
            .await?;
        Ok(id.map(EventId))
    }

    /// Deletes the events logged more than `age_s` seconds ago; returns
    /// how many.
    pub async fn prune_events(&self, age_s: u32) -> Result<u64, StoreError> {
        Ok(sqlx::query(&format!(
            "DELETE FROM events WHERE created_at < {}",
            self.dialect.now_plus(1)
        ))
        .bind(-f64::from(age_s))
        .execute(&self.writer)
        .await?
        .rows_affected())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn events_are_appended_in_order_and_read_by_sequence() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path(), 2).await.unwrap();
        assert_eq!(store.last_event_id().await.unwrap(), EventId(0));
        let (one, two) = (SequenceId(1), SequenceId(2));
        let last = store
            .append_events(&[(one, "a".into()), (two, "b".into()), (one, "c".into())])
            .await
            .unwrap();
        assert_eq!(last, Some(EventId(3)));
        assert_eq!(store.append_events(&[]).await.unwrap(), None);
        let all = store.events_after(EventId(0), 10).await.unwrap();
        let changes: Vec<_> = all.iter().map(|e| e.change.as_str()).collect();
        assert_eq!(changes, ["a", "b", "c"]);
        assert_eq!(
            store.events_after(EventId(1), 1).await.unwrap()[0].change,
            "b"
        );
        let ones = store
            .sequence_events_after(one, EventId(1), 10)
            .await
            .unwrap();
        assert_eq!(ones.len(), 1);
        assert_eq!((ones[0].id, ones[0].sequence_id), (EventId(3), one));
        assert_eq!(store.last_event_id().await.unwrap(), EventId(3));
        assert_eq!(store.oldest_event_id().await.unwrap(), Some(EventId(1)));
        // Nothing is a day old yet.
        assert_eq!(store.prune_events(86_400).await.unwrap(), 0);
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        assert_eq!(store.prune_events(0).await.unwrap(), 3);
        assert!(store.events_after(EventId(0), 10).await.unwrap().is_empty());
        assert_eq!(store.oldest_event_id().await.unwrap(), None);
        // Ids are never given twice, also after a prune.
        let next = store.append_events(&[(one, "d".into())]).await.unwrap();
        assert_eq!(next, Some(EventId(4)));
        // More than one statement's rows: in order, ids rising.
        let dir = tempfile::tempdir().unwrap();
        let other = Store::open(dir.path(), 1).await.unwrap();
        let many: Vec<_> = (0..INSERT_ROWS + 7)
            .map(|i| (two, format!("m{i}")))
            .collect();
        let last = other.append_events(&many).await.unwrap().unwrap();
        assert_eq!(last, EventId(many.len() as i64));
        let read = other.events_after(EventId(0), 1000).await.unwrap();
        assert!(read
            .iter()
            .zip(&many)
            .all(|(row, (_, change))| &row.change == change));
        assert_eq!(read.len(), many.len());
    }
}
