//! Vehicle models: `PUT/GET /v1/vehicle-models/{model}` (the nominal rig, tolerances,
//! `vehicle_from_ref` and optional thresholds), `GET /v1/vehicle-models`, and the fleet
//! statistics `GET /v1/vehicle-models/{model}/fleet`. Sessions name a model
//! (`vehicle_model`); their jobs are judged against it when read (`acceptance.nominal`).

use super::auth::AuthTenant;
use super::error::ApiError;
use super::AppState;
use crate::fleet;
use crate::store::rfc3339;
use crate::store::vehicle_models::ModelRow;
use axum::body::Bytes;
use axum::extract::{Path, RawQuery, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use rigcal_core::session::{check_identifier, InputError};
use rigcal_core::vehicle::VehicleModel;
use serde::Deserialize;
use serde_json::{json, Value};

fn model_name(model: &str) -> Result<(), ApiError> {
    check_identifier("model", model).map_err(ApiError::invalid)
}

fn show_row(r: &ModelRow) -> Value {
    let mut v = serde_json::to_value(&r.document).unwrap_or(Value::Null);
    if let Value::Object(o) = &mut v {
        o.insert("model".into(), json!(r.model));
        o.insert("created_at".into(), json!(rfc3339(r.created_at)));
        o.insert("updated_at".into(), json!(rfc3339(r.updated_at)));
        o.insert(
            "links".into(),
            json!({
                "self": format!("/v1/vehicle-models/{}", r.model),
                "fleet": format!("/v1/vehicle-models/{}/fleet", r.model),
            }),
        );
    }
    v
}

async fn model_or_404(state: &AppState, tenant: &str, model: &str) -> Result<ModelRow, ApiError> {
    model_name(model)?;
    state
        .store
        .vehicle_model(tenant, model)
        .await?
        .ok_or_else(|| ApiError::not_found("vehicle model").field("model"))
}

/// `PUT /v1/vehicle-models/{model}`: 201 when created, 200 when replaced. Jobs are
/// judged when read, so a new nominal rig or tolerance applies to old jobs at once.
pub async fn put(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(model): Path<String>,
    body: Bytes,
) -> Result<Response, ApiError> {
    model_name(&model)?;
    let doc: VehicleModel = super::jobs::json_body(&body)?;
    doc.check().map_err(ApiError::invalid)?;
    let created = state
        .store
        .put_vehicle_model(&tenant.id, &model, &doc)
        .await?;
    let row = state
        .store
        .vehicle_model(&tenant.id, &model)
        .await?
        .ok_or_else(|| ApiError::internal("a vehicle model just stored is missing"))?;
    let status = if created {
        StatusCode::CREATED
    } else {
        StatusCode::OK
    };
    Ok((
        status,
        [(header::LOCATION, format!("/v1/vehicle-models/{model}"))],
        Json(show_row(&row)),
    )
        .into_response())
}

/// `GET /v1/vehicle-models/{model}`.
pub async fn show(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(model): Path<String>,
) -> Result<Json<Value>, ApiError> {
    Ok(Json(show_row(
        &model_or_404(&state, &tenant.id, &model).await?,
    )))
}

/// `GET /v1/vehicle-models`: the tenant's models by name.
pub async fn list(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
) -> Result<Json<Value>, ApiError> {
    let rows = state.store.vehicle_models(&tenant.id).await?;
    Ok(Json(
        json!({"vehicle_models": rows.iter().map(show_row).collect::<Vec<_>>()}),
    ))
}

/// The fleet statistics of `model` with the query's threshold and period (checked here,
/// named by their parameters), and the model.
pub async fn fleet_of(
    state: &AppState,
    tenant_id: &str,
    model: &str,
    z: Option<&str>,
    bucket: Option<&str>,
) -> Result<(ModelRow, fleet::FleetStats), ApiError> {
    let row = model_or_404(state, tenant_id, model).await?;
    let z = match z {
        None => row.document.fleet_outlier_z,
        Some(s) => match s.parse::<f64>() {
            Ok(z) if z.is_finite() && (1.0..=100.0).contains(&z) => z,
            _ => {
                return Err(ApiError::invalid(InputError::new(
                    "z",
                    format!("a robust z-score between 1 and 100, got {s:?}"),
                )))
            }
        },
    };
    const DAY: i64 = 86_400_000;
    let bucket_ms = match bucket.unwrap_or("week") {
        "day" => DAY,
        "week" => 7 * DAY,
        "month" => 30 * DAY,
        other => {
            return Err(ApiError::invalid(InputError::new(
                "bucket",
                format!("one of day, week, month, got {other:?}"),
            )))
        }
    };
    let jobs = state.store.fleet_jobs(tenant_id, model).await?;
    let s = fleet::stats(&row.document, &jobs, z, bucket_ms).map_err(ApiError::internal)?;
    Ok((row, s))
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct FleetQuery {
    z: Option<String>,
    bucket: Option<String>,
}

/// `GET /v1/vehicle-models/{model}/fleet[?z=Z][&bucket=day|week|month]`.
pub async fn fleet(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(model): Path<String>,
    RawQuery(raw): RawQuery,
) -> Result<Json<Value>, ApiError> {
    let q: FleetQuery = ApiError::parse_query(raw.as_deref(), "z, bucket")?;
    let (_, s) = fleet_of(
        &state,
        &tenant.id,
        &model,
        q.z.as_deref(),
        q.bucket.as_deref(),
    )
    .await?;
    let bucket = match s.bucket_ms / 86_400_000 {
        1 => "day",
        7 => "week",
        _ => "month",
    };
    let outliers: Vec<Value> = s
        .outliers
        .iter()
        .map(|o| {
            json!({
                "vehicle_id": o.vehicle_id,
                "job_id": o.job_id,
                "finished_at": rfc3339(o.finished_at),
                "max_abs_z": o.max_abs_z,
                "axes": o.axes,
            })
        })
        .collect();
    let drift: Vec<Value> = s
        .drift
        .iter()
        .map(|d| {
            json!({
                "camera": d.camera,
                "axis": d.axis,
                "unit": d.unit,
                "points": d.points.iter().map(|p| json!({
                    "from": rfc3339(p.from),
                    "median": p.median,
                    "count": p.count,
                })).collect::<Vec<_>>(),
            })
        })
        .collect();
    Ok(Json(json!({
        "vehicle_model": model,
        "vehicles": s.vehicles,
        "calibrations": s.calibrations,
        "outlier_z": s.outlier_z,
        "cameras": s.cameras,
        "outliers": outliers,
        "drift": {"bucket": bucket, "series": drift},
    })))
}
