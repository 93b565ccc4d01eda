-- As migrations/sqlite/0007_image_detections.sql. Detection at upload (capture
-- feedback): every uploaded image whose slot needs
-- detection gets a row here, written in the transaction that records the image. Workers
-- claim pending rows with a lease (as they claim jobs), detect the image and keep the
-- outcome (JSON) keyed by the image's bytes (sha256) and the detector's version, so a
-- job reuses it instead of decoding the image again, and only an outcome of the same
-- bytes and the same detector.
CREATE TABLE image_detections (
    id               TEXT PRIMARY KEY,
    session_id       TEXT NOT NULL REFERENCES sessions(id),
    camera           TEXT NOT NULL,
    frame            BIGINT NOT NULL,
    sha256           TEXT NOT NULL,
    -- pending | done | failed (the detector failed on it attempts times; the job detects
    -- it again itself and reports what happens then)
    status           TEXT NOT NULL,
    attempts         BIGINT NOT NULL DEFAULT 0,
    lease_owner      TEXT,
    lease_expires_at BIGINT,
    detector         TEXT,
    outcome          TEXT,
    error            TEXT,
    created_at       BIGINT NOT NULL,
    finished_at      BIGINT,
    UNIQUE (session_id, camera, frame)
);
CREATE INDEX image_detections_pending ON image_detections (created_at) WHERE status = 'pending';

-- The capture check of a session of images, recomputed as detections land: how many of
-- the images awaiting detection it covers (NULL: a check computed from the session's
-- own detections at creation, complete).
ALTER TABLE sessions ADD COLUMN check_detected BIGINT;
ALTER TABLE sessions ADD COLUMN check_expected BIGINT;

-- The session's event stream (GET /v1/sessions/{id}/events): `image` when an image's
-- detection lands, `check` when the capture check is recomputed.
CREATE TABLE session_events (
    id          BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    session_id  TEXT NOT NULL REFERENCES sessions(id),
    at          BIGINT NOT NULL,
    kind        TEXT NOT NULL,
    data        TEXT NOT NULL
);
CREATE INDEX session_events_session ON session_events (session_id, id);
