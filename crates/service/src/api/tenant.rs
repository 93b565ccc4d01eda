//! `GET /v1/tenant`: who the API key acts for, and the acceptance thresholds its jobs
//! are judged by (the dashboard checks a key with it and shows the thresholds);
//! `GET/PUT /v1/tenant/thresholds`: the thresholds alone, readable and settable. Jobs are
//! judged when read, so new thresholds apply to old jobs at once.

use super::auth::AuthTenant;
use super::error::ApiError;
use super::jobs::json_body;
use super::AppState;
use crate::store::Tenant;
use axum::body::Bytes;
use axum::extract::State;
use axum::Json;
use rigcal_core::vehicle::AcceptanceThresholds;
use serde_json::{json, Value};

/// The tenant's acceptance thresholds (a vehicle model may carry its own).
pub type Thresholds = AcceptanceThresholds;

fn thresholds_of(t: &Tenant) -> Thresholds {
    Thresholds {
        max_rms_px: t.max_rms_px,
        max_sigma_translation_m: t.max_sigma_translation_m,
        max_sigma_rotation_deg: t.max_sigma_rotation_deg,
    }
}

pub async fn show(AuthTenant(tenant): AuthTenant) -> Json<Value> {
    Json(json!({
        "name": tenant.name,
        "acceptance_thresholds": thresholds_of(&tenant),
    }))
}

/// `GET /v1/tenant/thresholds`.
pub async fn thresholds(AuthTenant(tenant): AuthTenant) -> Json<Thresholds> {
    Json(thresholds_of(&tenant))
}

/// `PUT /v1/tenant/thresholds`: all three, replaced together.
pub async fn set_thresholds(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    body: Bytes,
) -> Result<Json<Thresholds>, ApiError> {
    let t: Thresholds = json_body(&body)?;
    t.check("").map_err(ApiError::invalid)?;
    state
        .store
        .set_thresholds(
            &tenant.id,
            t.max_rms_px,
            t.max_sigma_translation_m,
            t.max_sigma_rotation_deg,
        )
        .await?;
    Ok(Json(t))
}
