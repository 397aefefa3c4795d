-- A job's result is found from the rows it wrote, and the HTTP layer
-- writes its link: a process_frame job's is its frame (frames.job_id), a
-- solve_calibration job's the calibration it stored (calibrations.job_id,
-- added here). jobs.result keeps only links other job kinds give when they
-- succeed (Store::succeed).
ALTER TABLE calibrations ADD COLUMN job_id INTEGER REFERENCES jobs (id);
-- A job stores at most one calibration.
CREATE UNIQUE INDEX calibrations_job ON calibrations (job_id) WHERE job_id IS NOT NULL;

-- Before, a solve_calibration job's result was its calibration's path.
UPDATE calibrations SET job_id = (
    SELECT j.id FROM jobs j
    WHERE j.kind = 'solve_calibration'
      AND j.result = '/api/v1/calibrations/' || calibrations.id
);

-- The paths the rows now give are dropped; any other text stays, served
-- as it is.
UPDATE jobs SET result = NULL
WHERE (kind = 'solve_calibration'
       AND EXISTS (SELECT 1 FROM calibrations c WHERE c.job_id = jobs.id))
   OR (kind = 'process_frame'
       AND EXISTS (SELECT 1 FROM frames f
                   WHERE f.job_id = jobs.id
                     AND jobs.result = '/api/v1/sequences/' || f.sequence_id
                                       || '/frames/' || f.frame || '/particles'));
