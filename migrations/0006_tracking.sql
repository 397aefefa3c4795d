-- Tracking in time (issue 15): a sequence's particles linked into
-- trajectories as its frames complete, in frame order.
--
-- A tracking run is one pass of the tracker over a sequence with one set
-- of settings; a sequence's current run is its newest. Runs with other
-- settings are new rows: an older run's trajectories stay as they were,
-- and one still tracking stops there ('superseded').
CREATE TABLE tracking_runs (
    id               INTEGER PRIMARY KEY,
    sequence_id      INTEGER NOT NULL REFERENCES sequences (id),
    -- The settings (JSON, every default filled in).
    parameters       TEXT    NOT NULL,
    -- The last frame the tracker took (NULL: none yet). Advanced in the
    -- transaction that stores the points that frame made final.
    tracked_through  INTEGER,
    -- The client said the sequence has all its frames: once every frame
    -- is tracked, the tracker ends and its last points are stored.
    finish_requested INTEGER NOT NULL DEFAULT 0 CHECK (finish_requested IN (0, 1)),
    state            TEXT    NOT NULL DEFAULT 'tracking'
                     CHECK (state IN ('tracking', 'finished', 'failed', 'superseded')),
    error            TEXT,
    created_at       TEXT    NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now'))
);
CREATE INDEX tracking_runs_sequence ON tracking_runs (sequence_id, id);

-- The frames a run's tracker took, in order: with the particles stored
-- then (their count), or as a gap (NULL: the frame failed). A restarted
-- service rebuilds the tracker by giving it these frames again (the
-- tracker is deterministic), so what a gap was stays a gap even if the
-- frame is retried later.
CREATE TABLE tracking_frames (
    run_id     INTEGER NOT NULL REFERENCES tracking_runs (id),
    frame      INTEGER NOT NULL,
    particles  INTEGER,
    PRIMARY KEY (run_id, frame)
);

-- Every trajectory point of a run: a particle of a frame belongs to at
-- most one trajectory. Velocities and accelerations from the local
-- polynomial fit (mm per frame, mm per frame²); NULL where the fit has none
-- (an acceleration from two points, a velocity from one).
CREATE TABLE trajectory_points (
    run_id      INTEGER NOT NULL REFERENCES tracking_runs (id),
    frame       INTEGER NOT NULL,
    particle    INTEGER NOT NULL,
    trajectory  INTEGER NOT NULL,
    x REAL NOT NULL, y REAL NOT NULL, z REAL NOT NULL,
    u REAL, v REAL, w REAL,
    ax REAL, ay REAL, az REAL,
    su REAL, sv REAL, sw REAL,
    -- The particle's targets per camera, comma-separated, -1 for none (as
    -- the CSV's t0,t1,... columns).
    targets     TEXT NOT NULL,
    PRIMARY KEY (run_id, frame, particle)
);
CREATE INDEX trajectory_points_trajectory ON trajectory_points (run_id, trajectory, frame);

-- Per run and trajectory: its extent and length, kept with the points.
CREATE TABLE trajectories (
    run_id       INTEGER NOT NULL REFERENCES tracking_runs (id),
    id           INTEGER NOT NULL,
    first_frame  INTEGER NOT NULL,
    last_frame   INTEGER NOT NULL,
    length       INTEGER NOT NULL,
    PRIMARY KEY (run_id, id)
);
