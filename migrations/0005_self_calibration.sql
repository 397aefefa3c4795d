-- Self-calibration from a sequence's particles (issue 14).
--
-- A calibration refined from another names it (its origin); NULL for one
-- uploaded or solved from control points. Its report (calibrations.report)
-- is then the self-calibration's.
ALTER TABLE calibrations ADD COLUMN origin_calibration INTEGER REFERENCES calibrations (id);

-- Every particle set names the calibration that made it. Before, a
-- sequence's frames were all processed with its one calibration.
ALTER TABLE particles ADD COLUMN calibration_id INTEGER REFERENCES calibrations (id);
UPDATE particles SET calibration_id = (
    SELECT s.calibration_id FROM sequences s WHERE s.id = particles.sequence_id
);
