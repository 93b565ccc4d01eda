//! A vehicle's calibration history with the drift between accepted calibrations.

use super::auth::AuthTenant;
use super::error::ApiError;
use super::AppState;
use crate::result::{ExtrinsicValue, ResultDocument, Status};
use crate::store::rfc3339;
use axum::extract::{Path, State};
use axum::Json;
use serde_json::{json, Value};

/// Change of one camera between two calibrations: translation (mm) and rotation (deg).
pub fn change(prev: &ExtrinsicValue, now: &ExtrinsicValue) -> (f64, f64) {
    let dt = (0..3)
        .map(|i| (now.translation[i] - prev.translation[i]).powi(2))
        .sum::<f64>()
        .sqrt();
    let dot: f64 = (0..4)
        .map(|i| now.quaternion_wxyz[i] * prev.quaternion_wxyz[i])
        .sum();
    let angle = 2.0 * dot.abs().min(1.0).acos();
    (dt * 1000.0, angle.to_degrees())
}

/// `GET /v1/vehicles/{vehicle_id}/calibrations`: oldest first. A calibration is
/// *accepted* when it succeeded; each entry carries its change from the previous
/// accepted one, per camera.
pub async fn calibrations(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(vehicle): Path<String>,
) -> Result<Json<Value>, ApiError> {
    let rows = state.queue.vehicle_results(&tenant.id, &vehicle).await?;
    if rows.is_empty() {
        return Err(ApiError::not_found("vehicle with calibrations").field("vehicle_id"));
    }
    let mut prev_accepted: Option<(String, ResultDocument)> = None;
    let mut out = Vec::new();
    for (job, text) in rows {
        let Ok(doc) = serde_json::from_str::<ResultDocument>(&text) else {
            continue;
        };
        let accepted = doc.status == Status::Succeeded;
        let changes: Option<Vec<Value>> = prev_accepted.as_ref().map(|(_, p)| {
            doc.extrinsics
                .iter()
                .filter_map(|e| {
                    let before = p.extrinsics.iter().find(|x| x.value.camera == e.value.camera)?;
                    let (mm, deg) = change(&before.value, &e.value);
                    Some(json!({"camera": e.value.camera, "translation_mm": mm, "rotation_deg": deg}))
                })
                .collect()
        });
        out.push(json!({
            "job_id": job.id,
            "session_id": job.session_id,
            "status": doc.status.as_str(),
            "accepted": accepted,
            "finished_at": job.finished_at.map(rfc3339),
            "residual_rms_px": job.residual_rms_px,
            "extrinsics": doc.extrinsics.iter().map(|e| json!({
                "camera": e.value.camera,
                "translation": e.value.translation,
                "rpy_deg": e.value.rpy_deg,
                "sigma_translation_m": e.sigma_translation_m,
                "sigma_rotation_deg": e.sigma_rotation_deg,
            })).collect::<Vec<_>>(),
            "previous_accepted_job_id": prev_accepted.as_ref().map(|(id, _)| id.clone()),
            "change_from_previous_accepted": changes,
        }));
        if accepted {
            prev_accepted = Some((job.id.clone(), doc));
        }
    }
    Ok(Json(json!({"vehicle_id": vehicle, "calibrations": out})))
}
