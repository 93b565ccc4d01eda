//! Webhooks: `POST /v1/webhooks {url, events, secret}`, list, show, delete, and the
//! record of deliveries (`GET /v1/webhooks/{id}/deliveries`). Delivery, signing and the
//! SSRF policy are in [`crate::webhooks`].

use super::auth::AuthTenant;
use super::error::ApiError;
use super::jobs::json_body;
use super::AppState;
use crate::store::rfc3339;
use crate::store::webhooks::WebhookRow;
use crate::webhooks::{parse_url, resolve, EVENTS};
use axum::body::Bytes;
use axum::extract::{Path, RawQuery, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use rigcal_core::session::InputError;
use serde::Deserialize;
use serde_json::{json, Value};

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CreateWebhook {
    url: String,
    events: Vec<String>,
    secret: String,
}

fn view(w: &WebhookRow) -> Value {
    json!({
        "id": w.id,
        "url": w.url,
        "events": w.events,
        "created_at": rfc3339(w.created_at),
        "links": {
            "self": format!("/v1/webhooks/{}", w.id),
            "deliveries": format!("/v1/webhooks/{}/deliveries", w.id),
        },
    })
}

/// `POST /v1/webhooks`: 201 with the webhook (never its secret).
pub async fn create(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    body: Bytes,
) -> Result<Response, ApiError> {
    let req: CreateWebhook = json_body(&body)?;
    let url = parse_url(&req.url).map_err(|e| ApiError::invalid(InputError::new("url", e)))?;
    resolve(&url, state.config.worker.webhooks.allow_private)
        .await
        .map_err(|e| ApiError::invalid(InputError::new("url", e)))?;
    if req.events.is_empty() || req.events.len() > EVENTS.len() {
        return Err(ApiError::invalid(InputError::new(
            "events",
            format!("1 to {} of {}", EVENTS.len(), EVENTS.join(", ")),
        )));
    }
    let mut events: Vec<String> = Vec::new();
    for (i, e) in req.events.iter().enumerate() {
        if !EVENTS.contains(&e.as_str()) {
            return Err(ApiError::invalid(InputError::new(
                format!("events[{i}]"),
                format!(
                    "one of {}, got {}",
                    EVENTS.join(", "),
                    rigcal_core::session::quoted_prefix(e)
                ),
            )));
        }
        if !events.contains(e) {
            events.push(e.clone());
        }
    }
    let n = req.secret.chars().count();
    if !(16..=256).contains(&n) || req.secret.chars().any(char::is_control) {
        return Err(ApiError::invalid(InputError::new(
            "secret",
            format!("16 to 256 characters without control characters (the HMAC-SHA256 key of the signatures), got {n}"),
        )));
    }
    let w = state
        .store
        .create_webhook(&tenant.id, url.as_str(), &events, &req.secret)
        .await?;
    Ok((
        StatusCode::CREATED,
        [(header::LOCATION, format!("/v1/webhooks/{}", w.id))],
        Json(view(&w)),
    )
        .into_response())
}

pub async fn list(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
) -> Result<Json<Value>, ApiError> {
    let rows = state.store.webhooks(&tenant.id).await?;
    Ok(Json(
        json!({"webhooks": rows.iter().map(view).collect::<Vec<_>>()}),
    ))
}

async fn webhook_or_404(state: &AppState, tenant: &str, id: &str) -> Result<WebhookRow, ApiError> {
    state
        .store
        .webhook(tenant, id)
        .await?
        .ok_or_else(|| ApiError::not_found("webhook").field("id"))
}

pub async fn show(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(id): Path<String>,
) -> Result<Json<Value>, ApiError> {
    Ok(Json(view(&webhook_or_404(&state, &tenant.id, &id).await?)))
}

/// `DELETE /v1/webhooks/{id}`: 204; its pending deliveries end `failed`.
pub async fn delete(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(id): Path<String>,
) -> Result<StatusCode, ApiError> {
    if state.store.delete_webhook(&tenant.id, &id).await? {
        Ok(StatusCode::NO_CONTENT)
    } else {
        Err(ApiError::not_found("webhook").field("id"))
    }
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct DeliveriesQuery {
    limit: Option<String>,
}

/// `GET /v1/webhooks/{id}/deliveries[?limit=N]`: newest first, each with its attempts
/// and their status codes.
pub async fn deliveries(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(id): Path<String>,
    RawQuery(raw): RawQuery,
) -> Result<Json<Value>, ApiError> {
    let q: DeliveriesQuery = ApiError::parse_query(raw.as_deref(), "limit")?;
    let limit = match q.limit.as_deref() {
        None => 50,
        Some(s) => match s.parse::<i64>() {
            Ok(n) if (1..=500).contains(&n) => n,
            _ => {
                return Err(ApiError::invalid(InputError::new(
                    "limit",
                    format!(
                        "an integer from 1 to 500, got {}",
                        rigcal_core::session::quoted_prefix(s)
                    ),
                )))
            }
        },
    };
    let w = webhook_or_404(&state, &tenant.id, &id).await?;
    let d = state.store.deliveries(&w.id, limit).await?;
    Ok(Json(json!({"webhook_id": w.id, "deliveries": d})))
}
