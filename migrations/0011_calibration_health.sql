-- Calibration health during a run (issue 33): per processed frame and
-- camera, the disparity of its well-matched particles (the observed
-- target minus the projection of the particle's intersected position, in
-- px; photogrammetry::health), and per sequence the running drift monitor
-- fed those frames in frame order.
--
-- One row per camera for the whole frame (cell -1, written even when the
-- camera had no well-matched particle: count 0), and one per camera and
-- sub-volume that had any (cell 0.., x fastest, then y, then z, of the
-- sequence's 2 x 2 x 2 grid): at most cameras x (1 + 8) rows a frame,
-- 144 at 16 cameras. Written in the transaction that stores the frame's
-- particles, and replaced with them (reprocessing).
CREATE TABLE frame_health (
    sequence_id  INTEGER NOT NULL,
    frame        INTEGER NOT NULL,
    camera       INTEGER NOT NULL CHECK (camera >= 0),
    cell         INTEGER NOT NULL CHECK (cell >= -1),
    count        INTEGER NOT NULL CHECK (count >= 0),
    -- The mean disparity vector (px) and the RMS of the vectors' lengths.
    mean_x       REAL    NOT NULL,
    mean_y       REAL    NOT NULL,
    rms          REAL    NOT NULL,
    PRIMARY KEY (sequence_id, frame, camera, cell),
    FOREIGN KEY (sequence_id, frame) REFERENCES frames (sequence_id, frame)
);

-- A sequence's drift monitor (photogrammetry::health::DriftMonitor, as
-- JSON: per camera the baseline, the last window's frame means, the
-- alarm once fired), for the calibration its particles are made with.
-- Advanced in frame order over the frames done (processed with that
-- calibration, or failed: a gap), fenced on `through_frame` so that two
-- processes never both take a frame. Another calibration (the sequence
-- switched after a self-calibration) starts a new monitor.
CREATE TABLE calibration_health (
    sequence_id     INTEGER PRIMARY KEY REFERENCES sequences (id),
    calibration_id  INTEGER NOT NULL REFERENCES calibrations (id),
    -- The last frame taken (NULL: none yet).
    through_frame   INTEGER,
    -- Frames taken with health rows (gaps not counted).
    frames          INTEGER NOT NULL DEFAULT 0,
    monitor         TEXT    NOT NULL,
    updated_at      TEXT    NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now'))
);
CREATE INDEX calibration_health_updated ON calibration_health (updated_at);
