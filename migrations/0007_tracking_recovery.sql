-- Tracking with the image-space recovery (issue 15): a run's tracker looks
-- in the frames' stored targets for the particles the correspondences
-- missed, projecting with the calibration the run was started with. That
-- calibration is recorded here, so that a tracker rebuilt by replay after
-- a restart recovers exactly what it did before, even if the sequence was
-- switched to another calibration since (self-calibration).
--
-- NULL for runs stored before this migration: their settings have no
-- `recovery` and they were tracked without it, which they keep doing.
ALTER TABLE tracking_runs ADD COLUMN calibration_id INTEGER REFERENCES calibrations (id);
