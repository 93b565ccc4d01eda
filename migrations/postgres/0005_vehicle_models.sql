-- As migrations/sqlite/0005_vehicle_models.sql: vehicle models, and a job's model and
-- extrinsics for judging it against the nominal rig and for fleet statistics.
CREATE TABLE vehicle_models (
    tenant_id  TEXT NOT NULL REFERENCES tenants(id),
    model      TEXT NOT NULL,
    document   TEXT NOT NULL,
    created_at BIGINT NOT NULL,
    updated_at BIGINT NOT NULL,
    PRIMARY KEY (tenant_id, model)
);
ALTER TABLE jobs ADD COLUMN vehicle_model TEXT;
ALTER TABLE jobs ADD COLUMN extrinsics TEXT;
CREATE INDEX jobs_vehicle_model ON jobs (tenant_id, vehicle_model, finished_at);
