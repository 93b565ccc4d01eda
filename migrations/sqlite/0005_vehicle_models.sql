-- Vehicle models (PUT /v1/vehicle-models/{model}): the nominal rig, tolerances and
-- thresholds of a tenant's vehicle model, as the checked JSON document. A job carries its
-- session's model and, once finished, its extrinsics, so the jobs list judges a job
-- against the nominal rig and the fleet statistics read one column, never the result
-- documents.
CREATE TABLE vehicle_models (
    tenant_id  TEXT NOT NULL REFERENCES tenants(id),
    model      TEXT NOT NULL,
    document   TEXT NOT NULL,
    created_at INTEGER NOT NULL,
    updated_at INTEGER NOT NULL,
    PRIMARY KEY (tenant_id, model)
);
ALTER TABLE jobs ADD COLUMN vehicle_model TEXT;
-- JSON array of the result's extrinsic values (camera, ref_from_cam, translation,
-- quaternion_wxyz, rpy_deg); NULL until the job has a result.
ALTER TABLE jobs ADD COLUMN extrinsics TEXT;
CREATE INDEX jobs_vehicle_model ON jobs (tenant_id, vehicle_model, finished_at);
