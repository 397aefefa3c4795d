-- The per-camera images a sequence's detection uses (issue 13): a
-- background, subtracted from every frame before the high-pass filter and
-- the threshold, and a mask (non-zero pixels are used, zero ones never).
-- The files are in the image store, content-addressed as frames' images;
-- the start-up sweep keeps them while a row here refers to them. A
-- background is uploaded, or computed by the service from the sequence's
-- first frames (its parameters say which).
CREATE TABLE sequence_images (
    sequence_id  INTEGER NOT NULL REFERENCES sequences (id),
    kind         TEXT    NOT NULL CHECK (kind IN ('background', 'mask')),
    camera       INTEGER NOT NULL CHECK (camera >= 0),
    sha256       TEXT    NOT NULL,
    size         INTEGER NOT NULL,
    -- Bits per sample (8 or 16): a background must match its frames'.
    bits         INTEGER NOT NULL CHECK (bits IN (8, 16)),
    PRIMARY KEY (sequence_id, kind, camera)
);
CREATE INDEX sequence_images_sha256 ON sequence_images (sha256);

-- A queued job is not claimed before this time (UTC RFC 3339; NULL: at
-- once): a frame that waits for its sequence's computed background is
-- put back with a delay instead of being claimed again at once.
ALTER TABLE jobs ADD COLUMN not_before TEXT;
