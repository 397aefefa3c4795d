-- Backward tracking: SQLite's ../0012_backward_tracking.sql, where the
-- columns are explained, in PostgreSQL's types.
ALTER TABLE tracking_runs ADD COLUMN backward_points BIGINT;
ALTER TABLE tracking_runs ADD COLUMN backward_lengthened BIGINT;
ALTER TABLE tracking_runs ADD COLUMN backward_joined BIGINT;
