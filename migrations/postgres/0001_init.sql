-- rigcal schema v1 on PostgreSQL: the same tables, columns and meanings as
-- migrations/sqlite/0001_init.sql. Times are milliseconds since the Unix epoch (UTC),
-- integers are BIGINT and reals DOUBLE PRECISION, so both backends decode to the same
-- Rust types.

CREATE TABLE tenants (
    id          TEXT PRIMARY KEY,
    name        TEXT NOT NULL UNIQUE,
    created_at  BIGINT NOT NULL,
    max_rms_px  DOUBLE PRECISION NOT NULL DEFAULT 1.0,
    max_sigma_translation_m DOUBLE PRECISION NOT NULL DEFAULT 0.005,
    max_sigma_rotation_deg  DOUBLE PRECISION NOT NULL DEFAULT 0.1
);

CREATE TABLE api_keys (
    id          TEXT PRIMARY KEY,
    tenant_id   TEXT NOT NULL REFERENCES tenants(id),
    key_hash    TEXT NOT NULL UNIQUE,
    prefix      TEXT NOT NULL,
    created_at  BIGINT NOT NULL,
    revoked_at  BIGINT
);

CREATE TABLE sessions (
    id          TEXT PRIMARY KEY,
    tenant_id   TEXT NOT NULL REFERENCES tenants(id),
    vehicle_id  TEXT,
    method      TEXT NOT NULL,
    manifest    TEXT NOT NULL,
    capture_check TEXT,
    created_at  BIGINT NOT NULL
);
CREATE INDEX sessions_tenant ON sessions(tenant_id, created_at);

CREATE TABLE images (
    session_id  TEXT NOT NULL REFERENCES sessions(id),
    camera      TEXT NOT NULL,
    frame       BIGINT NOT NULL,
    sha256      TEXT NOT NULL,
    bytes       BIGINT NOT NULL,
    format      TEXT NOT NULL,
    width       BIGINT NOT NULL,
    height      BIGINT NOT NULL,
    created_at  BIGINT NOT NULL,
    PRIMARY KEY (session_id, camera, frame)
);

CREATE TABLE jobs (
    id            TEXT PRIMARY KEY,
    tenant_id     TEXT NOT NULL REFERENCES tenants(id),
    session_id    TEXT NOT NULL REFERENCES sessions(id),
    vehicle_id    TEXT,
    method        TEXT NOT NULL,
    options       TEXT NOT NULL,
    status        TEXT NOT NULL,
    stage         TEXT,
    progress      DOUBLE PRECISION NOT NULL DEFAULT 0,
    attempts      BIGINT NOT NULL DEFAULT 0,
    max_attempts  BIGINT NOT NULL,
    error         TEXT,
    lease_owner   TEXT,
    lease_expires_at BIGINT,
    run_after     BIGINT NOT NULL,
    cancel_requested BIGINT NOT NULL DEFAULT 0,
    residual_rms_px DOUBLE PRECISION,
    created_at    BIGINT NOT NULL,
    started_at    BIGINT,
    finished_at   BIGINT
);
CREATE INDEX jobs_claim ON jobs(status, run_after);
CREATE INDEX jobs_tenant_created ON jobs(tenant_id, created_at DESC);
CREATE INDEX jobs_vehicle ON jobs(tenant_id, vehicle_id, created_at);

CREATE TABLE job_events (
    id        BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    job_id    TEXT NOT NULL REFERENCES jobs(id),
    at        BIGINT NOT NULL,
    kind      TEXT NOT NULL,
    status    TEXT NOT NULL,
    stage     TEXT,
    progress  DOUBLE PRECISION NOT NULL,
    message   TEXT
);
CREATE INDEX job_events_job ON job_events(job_id, id);

CREATE TABLE results (
    job_id     TEXT PRIMARY KEY REFERENCES jobs(id),
    status     TEXT NOT NULL,
    document   TEXT NOT NULL,
    created_at BIGINT NOT NULL
);
