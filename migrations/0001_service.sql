-- The service's schema: calibrations, sequences of frames, their inputs and
-- results, and the durable job queue. Timestamps are UTC RFC 3339 text.

CREATE TABLE calibrations (
    id          INTEGER PRIMARY KEY,
    -- The calibration JSON (src/formats/calibration.rs), as written by
    -- formats::calibration::to_json.
    model       TEXT    NOT NULL,
    cameras     INTEGER NOT NULL CHECK (cameras >= 2),
    -- The resection report (JSON) when the calibration was solved.
    report      TEXT,
    created_at  TEXT    NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now'))
);

CREATE TABLE jobs (
    id           INTEGER PRIMARY KEY,
    -- process_frame, solve_calibration, ...
    kind         TEXT    NOT NULL,
    -- What the job works on (JSON), e.g. {"sequence_id": 1, "frame": 7}.
    payload      TEXT    NOT NULL,
    state        TEXT    NOT NULL DEFAULT 'queued'
                 CHECK (state IN ('queued', 'running', 'succeeded', 'failed')),
    attempts     INTEGER NOT NULL DEFAULT 0,
    -- The worker (process instance and thread) holding a running job.
    locked_by    TEXT,
    error        TEXT,
    -- Where the result is (an API path), once succeeded.
    result       TEXT,
    created_at   TEXT    NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')),
    started_at   TEXT,
    finished_at  TEXT,
    -- Seconds the last attempt ran, for the metrics.
    duration_s   REAL
);
CREATE INDEX jobs_queued ON jobs (id) WHERE state = 'queued';
CREATE INDEX jobs_state ON jobs (state);

CREATE TABLE sequences (
    id              INTEGER PRIMARY KEY,
    calibration_id  INTEGER NOT NULL REFERENCES calibrations (id),
    name            TEXT    NOT NULL,
    -- Detection and matching parameters (JSON, every default filled in).
    parameters      TEXT    NOT NULL,
    keep_images     INTEGER NOT NULL CHECK (keep_images IN (0, 1)),
    created_at      TEXT    NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now'))
);

-- One row per uploaded frame; its state is its job's.
CREATE TABLE frames (
    sequence_id  INTEGER NOT NULL REFERENCES sequences (id),
    frame        INTEGER NOT NULL CHECK (frame >= 0),
    job_id       INTEGER NOT NULL UNIQUE REFERENCES jobs (id),
    -- 'images' or 'targets': what was uploaded.
    input        TEXT    NOT NULL CHECK (input IN ('images', 'targets')),
    -- The layout of raw images (JSON {"width","height","bits"}), NULL for
    -- PNG/TIFF or targets.
    raw_layout   TEXT,
    created_at   TEXT    NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')),
    PRIMARY KEY (sequence_id, frame)
);

-- The uploaded images of a frame: content-addressed files under the data
-- directory's images/ (sha256 of the bytes). Deleted after processing when
-- the sequence does not keep images.
CREATE TABLE images (
    sequence_id  INTEGER NOT NULL,
    frame        INTEGER NOT NULL,
    camera       INTEGER NOT NULL CHECK (camera >= 0),
    sha256       TEXT    NOT NULL,
    size         INTEGER NOT NULL,
    PRIMARY KEY (sequence_id, frame, camera),
    FOREIGN KEY (sequence_id, frame) REFERENCES frames (sequence_id, frame)
);
CREATE INDEX images_sha256 ON images (sha256);

-- A frame's targets per camera, uploaded or detected: one compact blob per
-- camera (src/service/codec.rs), thousands of targets each.
CREATE TABLE targets (
    sequence_id  INTEGER NOT NULL,
    frame        INTEGER NOT NULL,
    camera       INTEGER NOT NULL CHECK (camera >= 0),
    count        INTEGER NOT NULL,
    data         BLOB    NOT NULL,
    PRIMARY KEY (sequence_id, frame, camera),
    FOREIGN KEY (sequence_id, frame) REFERENCES frames (sequence_id, frame)
);

-- A processed frame's particles: one compact blob per frame.
CREATE TABLE particles (
    sequence_id  INTEGER NOT NULL,
    frame        INTEGER NOT NULL,
    count        INTEGER NOT NULL,
    data         BLOB    NOT NULL,
    PRIMARY KEY (sequence_id, frame),
    FOREIGN KEY (sequence_id, frame) REFERENCES frames (sequence_id, frame)
);
