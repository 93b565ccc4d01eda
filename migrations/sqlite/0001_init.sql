-- rigcal schema v1. Times are milliseconds since the Unix epoch (UTC).

CREATE TABLE tenants (
    id          TEXT PRIMARY KEY,
    name        TEXT NOT NULL UNIQUE,
    created_at  INTEGER NOT NULL,
    -- Acceptance thresholds shown on the dashboard (pass/fail mark).
    max_rms_px  REAL NOT NULL DEFAULT 1.0,
    max_sigma_translation_m REAL NOT NULL DEFAULT 0.005,
    max_sigma_rotation_deg  REAL NOT NULL DEFAULT 0.1
);

CREATE TABLE api_keys (
    id          TEXT PRIMARY KEY,
    tenant_id   TEXT NOT NULL REFERENCES tenants(id),
    -- SHA-256 of the key, hex. The key itself is printed once and never stored.
    key_hash    TEXT NOT NULL UNIQUE,
    prefix      TEXT NOT NULL,
    created_at  INTEGER NOT NULL,
    revoked_at  INTEGER
);

CREATE TABLE sessions (
    id          TEXT PRIMARY KEY,
    tenant_id   TEXT NOT NULL REFERENCES tenants(id),
    vehicle_id  TEXT,
    method      TEXT NOT NULL,
    manifest    TEXT NOT NULL,
    -- Capture check (JSON), computed when the detections exist.
    capture_check TEXT,
    created_at  INTEGER NOT NULL
);
CREATE INDEX sessions_tenant ON sessions(tenant_id, created_at);

CREATE TABLE images (
    session_id  TEXT NOT NULL REFERENCES sessions(id),
    camera      TEXT NOT NULL,
    frame       INTEGER NOT NULL,
    sha256      TEXT NOT NULL,
    bytes       INTEGER NOT NULL,
    format      TEXT NOT NULL,
    width       INTEGER NOT NULL,
    height      INTEGER NOT NULL,
    created_at  INTEGER NOT NULL,
    PRIMARY KEY (session_id, camera, frame)
);

CREATE TABLE jobs (
    id            TEXT PRIMARY KEY,
    tenant_id     TEXT NOT NULL REFERENCES tenants(id),
    session_id    TEXT NOT NULL REFERENCES sessions(id),
    vehicle_id    TEXT,
    method        TEXT NOT NULL,
    options       TEXT NOT NULL,
    -- queued | running | succeeded | degraded | failed | cancelled
    status        TEXT NOT NULL,
    stage         TEXT,
    progress      REAL NOT NULL DEFAULT 0,
    attempts      INTEGER NOT NULL DEFAULT 0,
    max_attempts  INTEGER NOT NULL,
    -- Problem (JSON) of the last failure: {code, detail, field}.
    error         TEXT,
    lease_owner   TEXT,
    lease_expires_at INTEGER,
    run_after     INTEGER NOT NULL,
    cancel_requested INTEGER NOT NULL DEFAULT 0,
    residual_rms_px REAL,
    created_at    INTEGER NOT NULL,
    started_at    INTEGER,
    finished_at   INTEGER
);
CREATE INDEX jobs_claim ON jobs(status, run_after);
CREATE INDEX jobs_tenant_created ON jobs(tenant_id, created_at DESC);
CREATE INDEX jobs_vehicle ON jobs(tenant_id, vehicle_id, created_at);

CREATE TABLE job_events (
    id        INTEGER PRIMARY KEY AUTOINCREMENT,
    job_id    TEXT NOT NULL REFERENCES jobs(id),
    at        INTEGER NOT NULL,
    -- status | stage | retry | error
    kind      TEXT NOT NULL,
    status    TEXT NOT NULL,
    stage     TEXT,
    progress  REAL NOT NULL,
    message   TEXT
);
CREATE INDEX job_events_job ON job_events(job_id, id);

CREATE TABLE results (
    job_id     TEXT PRIMARY KEY REFERENCES jobs(id),
    status     TEXT NOT NULL,
    document   TEXT NOT NULL,
    created_at INTEGER NOT NULL
);
