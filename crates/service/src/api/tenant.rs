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
use rigcal_core::session::InputError;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

/// Acceptance thresholds: a finished job passes when it succeeded and its residual RMS
/// and worst 1-σ are within them.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Thresholds {
    pub max_rms_px: f64,
    pub max_sigma_translation_m: f64,
    pub max_sigma_rotation_deg: f64,
}

impl Thresholds {
    fn of(t: &Tenant) -> Self {
        Thresholds {
            max_rms_px: t.max_rms_px,
            max_sigma_translation_m: t.max_sigma_translation_m,
            max_sigma_rotation_deg: t.max_sigma_rotation_deg,
        }
    }

    /// Each a positive finite number within what a calibration can mean.
    fn check(&self) -> Result<(), InputError> {
        for (field, v, max, unit) in [
            ("max_rms_px", self.max_rms_px, 100.0, "pixels"),
            (
                "max_sigma_translation_m",
                self.max_sigma_translation_m,
                10.0,
                "metres",
            ),
            (
                "max_sigma_rotation_deg",
                self.max_sigma_rotation_deg,
                180.0,
                "degrees",
            ),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= max) {
                return Err(InputError::new(
                    field,
                    format!("a positive number of {unit} up to {max}, got {v}"),
                ));
            }
        }
        Ok(())
    }
}

pub async fn show(AuthTenant(tenant): AuthTenant) -> Json<Value> {
    Json(json!({
        "name": tenant.name,
        "acceptance_thresholds": Thresholds::of(&tenant),
    }))
}

/// `GET /v1/tenant/thresholds`.
pub async fn thresholds(AuthTenant(tenant): AuthTenant) -> Json<Thresholds> {
    Json(Thresholds::of(&tenant))
}

/// `PUT /v1/tenant/thresholds`: all three, replaced together.
pub async fn set_thresholds(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    body: Bytes,
) -> Result<Json<Thresholds>, ApiError> {
    let t: Thresholds = json_body(&body)?;
    t.check().map_err(ApiError::invalid)?;
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
