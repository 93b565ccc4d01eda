-- Idempotency-Key records (IETF draft-ietf-httpapi-idempotency-key-header): the first
-- successful answer to a POST, replayed for the same key and body within 24 h. A row
-- with a NULL fingerprint is a request still in flight under that key.
CREATE TABLE idempotency_keys (
    tenant_id TEXT NOT NULL,
    key TEXT NOT NULL,
    route TEXT NOT NULL,
    fingerprint TEXT,
    status INTEGER,
    content_type TEXT,
    location TEXT,
    body BLOB,
    created_at INTEGER NOT NULL,
    PRIMARY KEY (tenant_id, key)
);
CREATE INDEX idempotency_keys_created ON idempotency_keys (created_at);
