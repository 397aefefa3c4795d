-- Backward tracking (issue 34): what a run's pass back, after its last
-- frame, added to its trajectories (src/service/ops/tracking/backward.rs):
-- points before the trajectories' first points, trajectories lengthened,
-- trajectories joined onto the one ending before them. NULL where the
-- pass did not run (the run's settings have it off, or the run has not
-- finished); written in the transaction that finishes the run and
-- rewrites its points.
ALTER TABLE tracking_runs ADD COLUMN backward_points INTEGER;
ALTER TABLE tracking_runs ADD COLUMN backward_lengthened INTEGER;
ALTER TABLE tracking_runs ADD COLUMN backward_joined INTEGER;
