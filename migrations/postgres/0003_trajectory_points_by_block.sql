-- Trajectory points found by trajectory within blocks of 16 frames
-- (issue 30), in place of an index led by the trajectory: SQLite's 0010,
-- which says why.
DROP INDEX trajectory_points_trajectory;
CREATE INDEX trajectory_points_block ON trajectory_points (run_id, (frame / 16), trajectory, frame);

-- No foreign key from a run's points and trajectories to the run. On
-- PostgreSQL a foreign key is checked by a trigger that looks the run up
-- for every row inserted: about half of the time of storing a frame's
-- points (20,000 rows: 212-220 ms with it, 104-128 ms without, on this
-- project's 2-core test machine). It checks nothing the writes do not: a
-- frame's points and extents are written only in the transaction that
-- has just advanced their run's row (`Store::store_tracked_frame`,
-- `finish_tracking_run`: the UPDATE is fenced and holds the row until
-- the commit), and runs are never deleted. `tracking_frames` (one row a
-- frame) keeps its key.
ALTER TABLE trajectory_points DROP CONSTRAINT trajectory_points_run_id_fkey;
ALTER TABLE trajectories DROP CONSTRAINT trajectories_run_id_fkey;
