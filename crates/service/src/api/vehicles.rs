//! A vehicle's calibration history with the drift between accepted calibrations.

use super::auth::AuthTenant;
use super::error::ApiError;
use super::AppState;
use crate::jobs::queue::JobRow;
use crate::store::rfc3339;
use axum::extract::{Path, State};
use axum::Json;
use rigcal_core::result::{ExtrinsicValue, ResultDocument, Status};
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

pub struct CameraChange {
    pub camera: String,
    pub translation_mm: f64,
    pub rotation_deg: f64,
}

/// One calibration of the vehicle and its change from the previous accepted one.
pub struct HistoryEntry {
    pub job: JobRow,
    pub doc: ResultDocument,
    /// Accepted: it succeeded (only accepted calibrations are drifted from).
    pub accepted: bool,
    pub previous_accepted_job_id: Option<String>,
    /// `None` for the first accepted calibration and those before it.
    pub changes: Option<Vec<CameraChange>>,
}

/// The vehicle's calibrations, oldest first; 404 when it has none.
pub async fn history(
    state: &AppState,
    tenant_id: &str,
    vehicle: &str,
) -> Result<Vec<HistoryEntry>, ApiError> {
    let rows = state.queue.vehicle_results(tenant_id, vehicle).await?;
    if rows.is_empty() {
        return Err(ApiError::not_found("vehicle with calibrations").field("vehicle_id"));
    }
    let mut prev: Option<(String, ResultDocument)> = None;
    let mut out = Vec::new();
    for (job, text) in rows {
        let Ok(doc) = serde_json::from_str::<ResultDocument>(&text) else {
            continue;
        };
        let accepted = doc.status == Status::Succeeded;
        let changes = prev.as_ref().map(|(_, p)| {
            doc.extrinsics
                .iter()
                .filter_map(|e| {
                    let before = p
                        .extrinsics
                        .iter()
                        .find(|x| x.value.camera == e.value.camera)?;
                    let (mm, deg) = change(&before.value, &e.value);
                    Some(CameraChange {
                        camera: e.value.camera.clone(),
                        translation_mm: mm,
                        rotation_deg: deg,
                    })
                })
                .collect()
        });
        let previous_accepted_job_id = prev.as_ref().map(|(id, _)| id.clone());
        if accepted {
            prev = Some((job.id.clone(), doc.clone()));
        }
        out.push(HistoryEntry {
            job,
            doc,
            accepted,
            previous_accepted_job_id,
            changes,
        });
    }
    Ok(out)
}

/// `GET /v1/vehicles/{vehicle_id}/calibrations`: oldest first. A calibration is
/// *accepted* when it succeeded; each entry carries its change from the previous
/// accepted one, per camera.
pub async fn calibrations(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(vehicle): Path<String>,
) -> Result<Json<Value>, ApiError> {
    let out: Vec<Value> = history(&state, &tenant.id, &vehicle)
        .await?
        .iter()
        .map(|h| {
            json!({
                "job_id": h.job.id,
                "session_id": h.job.session_id,
                "status": h.doc.status.as_str(),
                "accepted": h.accepted,
                "finished_at": h.job.finished_at.map(rfc3339),
                "residual_rms_px": h.job.residual_rms_px,
                "extrinsics": h.doc.extrinsics.iter().map(|e| json!({
                    "camera": e.value.camera,
                    "translation": e.value.translation,
                    "rpy_deg": e.value.rpy_deg,
                    "sigma_translation_m": e.sigma_translation_m,
                    "sigma_rotation_deg": e.sigma_rotation_deg,
                })).collect::<Vec<_>>(),
                "previous_accepted_job_id": h.previous_accepted_job_id,
                "change_from_previous_accepted": h.changes.as_ref().map(|cs| cs.iter().map(|c| json!({
                    "camera": c.camera,
                    "translation_mm": c.translation_mm,
                    "rotation_deg": c.rotation_deg,
                })).collect::<Vec<_>>()),
            })
        })
        .collect();
    Ok(Json(json!({"vehicle_id": vehicle, "calibrations": out})))
}
