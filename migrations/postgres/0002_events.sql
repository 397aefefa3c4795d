-- The event log (SQLite's ../0009_events.sql, where it is explained).
-- Identity values are drawn before their transactions commit, so rows may
-- become visible out of id order; the follower re-reads the last ids
-- (src/service/events.rs).
CREATE TABLE events (
    id           BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    sequence_id  BIGINT  NOT NULL,
    change       TEXT    NOT NULL,
    created_at   TEXT    NOT NULL
                 DEFAULT to_char(clock_timestamp() AT TIME ZONE 'UTC', 'YYYY-MM-DD"T"HH24:MI:SS.MS"Z"')
);
CREATE INDEX events_sequence ON events (sequence_id, id);
CREATE INDEX events_created ON events (created_at);
