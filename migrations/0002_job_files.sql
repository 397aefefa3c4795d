-- The input files of jobs that are not frames (solve_calibration): parts
-- of the request kept in the image store (content-addressed, as images),
-- so that the start-up sweep keeps them while a row refers to them.
CREATE TABLE job_files (
    job_id  INTEGER NOT NULL REFERENCES jobs (id),
    -- The request's part: setup, control, observations, image, reference.
    part    TEXT    NOT NULL,
    -- The camera of a per-camera part, from 0; NULL otherwise.
    camera  INTEGER CHECK (camera >= 0),
    sha256  TEXT    NOT NULL,
    size    INTEGER NOT NULL
);
CREATE INDEX job_files_job ON job_files (job_id);
CREATE INDEX job_files_sha256 ON job_files (sha256);
