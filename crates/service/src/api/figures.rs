//! The dashboard's figures as `image/svg+xml`, behind the same API key as the data they
//! draw (drawn by [`crate::dashboard::svg`]).

use super::auth::AuthTenant;
use super::error::ApiError;
use super::jobs::document;
use super::vehicles::history;
use super::AppState;
use crate::dashboard::svg;
use axum::extract::{Path, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use rigcal_core::result::ResultDocument;

/// Figures of a job, by file name.
pub const JOB_FIGURES: [&str; 4] = [
    "rig.svg",
    "residual-histogram.svg",
    "residuals-per-camera.svg",
    "residuals-per-frame.svg",
];

fn svg_response(body: String) -> Response {
    (
        [
            (header::CONTENT_TYPE, "image/svg+xml"),
            (header::CACHE_CONTROL, "private, no-cache"),
        ],
        body,
    )
        .into_response()
}

/// `GET /v1/jobs/{id}/figures/{name}` for a finished job with a result document.
pub async fn job(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path((id, name)): Path<(String, String)>,
) -> Result<Response, ApiError> {
    if !JOB_FIGURES.contains(&name.as_str()) {
        return Err(ApiError::new(
            StatusCode::NOT_FOUND,
            "not-found",
            format!(
                "no such figure: expected one of {}, got {name:?}",
                JOB_FIGURES.join(", ")
            ),
        )
        .field("name"));
    }
    let (_, text) = document(&state, &tenant.id, &id).await?;
    let doc: ResultDocument = serde_json::from_str(&text).map_err(ApiError::internal)?;
    let no_residuals = || {
        ApiError::new(
            StatusCode::CONFLICT,
            "no-residuals",
            "the job ended before residuals were computed",
        )
    };
    let body = match name.as_str() {
        "rig.svg" => svg::rig_top_view(&doc),
        "residual-histogram.svg" => {
            svg::residual_histogram(&doc.residuals.as_ref().ok_or_else(no_residuals)?.histogram)
        }
        "residuals-per-camera.svg" => {
            let r = doc.residuals.as_ref().ok_or_else(no_residuals)?;
            let items: Vec<_> = r
                .per_camera
                .iter()
                .map(|c| (c.camera.clone(), c.stats.rms, c.stats.p95))
                .collect();
            svg::residual_bars("Residuals per camera", "cameras", &items)
        }
        _ => {
            let r = doc.residuals.as_ref().ok_or_else(no_residuals)?;
            let items: Vec<_> = r
                .per_frame
                .iter()
                .map(|f| (f.frame.to_string(), f.stats.rms, f.stats.p95))
                .collect();
            svg::residual_bars("Residuals per frame", "frames", &items)
        }
    };
    Ok(svg_response(body))
}

/// `GET /v1/vehicles/{vehicle_id}/drift.svg`: each camera's change between accepted
/// calibrations.
pub async fn drift(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(vehicle): Path<String>,
) -> Result<Response, ApiError> {
    let h = history(&state, &tenant.id, &vehicle).await?;
    let mut series: Vec<svg::DriftSeries> = Vec::new();
    for (k, entry) in h.iter().enumerate() {
        for c in entry.changes.iter().flatten() {
            match series.iter_mut().find(|s| s.camera == c.camera) {
                Some(s) => s.points.push((k, c.translation_mm, c.rotation_deg)),
                None => series.push(svg::DriftSeries {
                    camera: c.camera.clone(),
                    points: vec![(k, c.translation_mm, c.rotation_deg)],
                }),
            }
        }
    }
    Ok(svg_response(svg::drift_chart(&series, h.len())))
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FleetFigureQuery {
    camera: String,
}

/// `GET /v1/vehicle-models/{model}/fleet.svg?camera=ID`: one camera of the fleet.
pub async fn fleet(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(model): Path<String>,
    axum::extract::RawQuery(raw): axum::extract::RawQuery,
) -> Result<Response, ApiError> {
    let q: FleetFigureQuery = ApiError::parse_query(raw.as_deref(), "camera")?;
    let (row, s) = super::vehicle_models::fleet_of(&state, &tenant.id, &model, None, None).await?;
    let Some(c) = s.cameras.iter().position(|c| c.camera == q.camera) else {
        let ids: Vec<&str> = s.cameras.iter().map(|c| c.camera.as_str()).collect();
        return Err(ApiError::invalid(rigcal_core::session::InputError::new(
            "camera",
            format!(
                "a camera of vehicle model {} other than its reference: one of {}",
                row.model,
                ids.join(", ")
            ),
        )));
    };
    let drift: Vec<&crate::fleet::DriftSeries> =
        s.drift.iter().filter(|d| d.camera == q.camera).collect();
    Ok(svg_response(svg::fleet_chart(
        &q.camera,
        &s.cameras[c].axes,
        &s.latest[c],
        s.outlier_z,
        &drift,
    )))
}
