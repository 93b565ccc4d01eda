-- As migrations/sqlite/0002_job_sigmas.sql: the worst 1-sigma of a finished job's
-- extrinsics beside residual_rms_px, for the jobs list's pass/fail mark.
ALTER TABLE jobs ADD COLUMN worst_sigma_translation_m DOUBLE PRECISION;
ALTER TABLE jobs ADD COLUMN worst_sigma_rotation_deg DOUBLE PRECISION;
