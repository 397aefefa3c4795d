-- Trajectory points found by trajectory within blocks of 16 frames
-- (issue 30), in place of an index led by the trajectory.
--
-- Every frame adds one point to each live trajectory. Under an index led
-- by (run_id, trajectory, frame) those points land on as many leaf pages
-- as there are live trajectories, all over an index that grows with the
-- run, so a frame's commit rewrote a large part of it: the time to store
-- a frame grew with the run's length (2,000 particles a frame: 16 ms at
-- frame 10, 34 ms at frame 200, and growing). Led by the frame's block,
-- a frame's points land in its block's pages only, at most 16 frames of
-- entries, whatever the run's length. A trajectory's points are read a
-- block at a time (`Store::trajectory_points`: one seek per block of the
-- frames asked for). `frame / 16` is the same expression in the queries.
DROP INDEX trajectory_points_trajectory;
CREATE INDEX trajectory_points_block ON trajectory_points (run_id, (frame / 16), trajectory, frame);
