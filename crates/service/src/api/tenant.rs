//! `GET /v1/tenant`: who the API key acts for, and the acceptance thresholds its jobs
//! are judged by (the dashboard checks a key with it and shows the thresholds).

use super::auth::AuthTenant;
use axum::Json;
use serde_json::{json, Value};

pub async fn show(AuthTenant(tenant): AuthTenant) -> Json<Value> {
    Json(json!({
        "name": tenant.name,
        "acceptance_thresholds": {
            "max_rms_px": tenant.max_rms_px,
            "max_sigma_translation_m": tenant.max_sigma_translation_m,
            "max_sigma_rotation_deg": tenant.max_sigma_rotation_deg,
        },
    }))
}
