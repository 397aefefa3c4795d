-- Calibration health during a run: SQLite's ../0011_calibration_health.sql,
-- where the tables are explained, in PostgreSQL's types (BIGINT, DOUBLE
-- PRECISION; timestamps as RFC 3339 text, as everywhere).
CREATE TABLE frame_health (
    sequence_id  BIGINT           NOT NULL,
    frame        BIGINT           NOT NULL,
    camera       BIGINT           NOT NULL CHECK (camera >= 0),
    cell         BIGINT           NOT NULL CHECK (cell >= -1),
    count        BIGINT           NOT NULL CHECK (count >= 0),
    mean_x       DOUBLE PRECISION NOT NULL,
    mean_y       DOUBLE PRECISION NOT NULL,
    rms          DOUBLE PRECISION NOT NULL,
    PRIMARY KEY (sequence_id, frame, camera, cell),
    FOREIGN KEY (sequence_id, frame) REFERENCES frames (sequence_id, frame)
);

CREATE TABLE calibration_health (
    sequence_id     BIGINT  PRIMARY KEY REFERENCES sequences (id),
    calibration_id  BIGINT  NOT NULL REFERENCES calibrations (id),
    through_frame   BIGINT,
    frames          BIGINT  NOT NULL DEFAULT 0,
    monitor         TEXT    NOT NULL,
    updated_at      TEXT    NOT NULL
                    DEFAULT to_char(clock_timestamp() AT TIME ZONE 'UTC', 'YYYY-MM-DD"T"HH24:MI:SS.MS"Z"')
);
CREATE INDEX calibration_health_updated ON calibration_health (updated_at);
