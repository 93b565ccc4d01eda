-- Webhooks (POST /v1/webhooks): a tenant's subscriptions to job events. Deliveries are
-- an outbox written in the transaction that ends a job, so no event is lost to a crash
-- between the two; dispatchers in every serve and worker process claim due deliveries
-- with a lease, as workers claim jobs. Each attempt is recorded.
CREATE TABLE webhooks (
    id          TEXT PRIMARY KEY,
    tenant_id   TEXT NOT NULL REFERENCES tenants(id),
    url         TEXT NOT NULL,
    -- The subscribed event types, comma-delimited with a comma at each end
    -- (",job.finished,job.failed,") so that one LIKE matches on both backends.
    events      TEXT NOT NULL,
    -- The HMAC key of the signatures (needed in clear to sign; never returned).
    secret      TEXT NOT NULL,
    created_at  INTEGER NOT NULL,
    deleted_at  INTEGER
);
CREATE INDEX webhooks_tenant ON webhooks (tenant_id, created_at);

CREATE TABLE webhook_deliveries (
    id               TEXT PRIMARY KEY,
    webhook_id       TEXT NOT NULL REFERENCES webhooks(id),
    tenant_id        TEXT NOT NULL,
    event            TEXT NOT NULL,
    job_id           TEXT NOT NULL,
    -- The JSON body, built at the first attempt and sent unchanged on every retry.
    body             TEXT,
    -- pending | delivered | failed
    status           TEXT NOT NULL,
    attempts         INTEGER NOT NULL DEFAULT 0,
    next_attempt_at  INTEGER NOT NULL,
    lease_owner      TEXT,
    lease_expires_at INTEGER,
    last_status_code INTEGER,
    last_error       TEXT,
    created_at       INTEGER NOT NULL,
    finished_at      INTEGER
);
CREATE INDEX webhook_deliveries_due ON webhook_deliveries (next_attempt_at) WHERE status = 'pending';
CREATE INDEX webhook_deliveries_hook ON webhook_deliveries (webhook_id, created_at);

CREATE TABLE webhook_attempts (
    delivery_id  TEXT NOT NULL REFERENCES webhook_deliveries(id),
    attempt      INTEGER NOT NULL,
    at           INTEGER NOT NULL,
    status_code  INTEGER,
    error        TEXT,
    duration_ms  INTEGER NOT NULL,
    PRIMARY KEY (delivery_id, attempt)
);
