-- The event log (issue 17): every change announced on a sequence's event
-- stream (`GET /sequences/{id}/events`), written by the process that made
-- the change, after that change commits, and read by every serving
-- process. So a stream shows what `ptv worker` processes on other hosts
-- do, and a client that reconnects with `Last-Event-ID` is sent what it
-- missed. `id` is the stream's event id. Rows older than a day are
-- deleted (`Store::prune_events`); a stream then starts from a snapshot.
CREATE TABLE events (
    id           INTEGER PRIMARY KEY AUTOINCREMENT,
    sequence_id  INTEGER NOT NULL,
    -- The change as JSON (src/service/events.rs, `Change`).
    change       TEXT    NOT NULL,
    created_at   TEXT    NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now'))
);
CREATE INDEX events_sequence ON events (sequence_id, id);
CREATE INDEX events_created ON events (created_at);
