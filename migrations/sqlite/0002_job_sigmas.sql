-- The worst 1-sigma of a finished job's extrinsics, kept beside residual_rms_px so the
-- jobs list can mark pass/fail against the tenant's thresholds without reading every
-- result document. NULL: no result, or no observable camera.
ALTER TABLE jobs ADD COLUMN worst_sigma_translation_m REAL;
ALTER TABLE jobs ADD COLUMN worst_sigma_rotation_deg REAL;
