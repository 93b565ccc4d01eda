//! Operations endpoints: health, readiness, metrics, the OpenAPI contract and its
//! rendered reference (generated here from `openapi.yaml`; no external assets).

use super::error::ApiError;
use super::AppState;
use crate::store::db::sql;
use axum::extract::{Path, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use axum::Json;
use serde_json::{json, Value};
use std::fmt::Write;
use std::sync::OnceLock;

pub const OPENAPI_YAML: &str = include_str!("../../../../openapi.yaml");

pub async fn healthz() -> Json<Value> {
    Json(json!({"status": "ok", "version": env!("CARGO_PKG_VERSION")}))
}

/// Ready when the database answers and the blob store is reachable and writable.
pub async fn readyz(State(state): State<AppState>) -> Result<Json<Value>, ApiError> {
    let unavailable = |d: String| ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "not-ready", d);
    state
        .store
        .db
        .execute(sql("SELECT 1"))
        .await
        .map_err(|e| unavailable(format!("database: {e}")))?;
    state
        .store
        .blobs
        .probe()
        .await
        .map_err(|e| unavailable(format!("blob store {}: {e}", state.store.blobs.describe())))?;
    Ok(Json(json!({"status": "ready"})))
}

pub async fn metrics(State(state): State<AppState>) -> Result<Response, ApiError> {
    let counts = state.queue.counts().await?;
    Ok((
        [(
            header::CONTENT_TYPE,
            "text/plain; version=0.0.4; charset=utf-8",
        )],
        state.metrics.render(&counts),
    )
        .into_response())
}

pub async fn openapi() -> Response {
    ([(header::CONTENT_TYPE, "application/yaml")], OPENAPI_YAML).into_response()
}

pub async fn not_found() -> ApiError {
    ApiError::new(StatusCode::NOT_FOUND, "not-found", "no such resource")
}

use crate::dashboard::svg::esc;

/// The API reference as HTML, rendered once from `openapi.yaml`.
pub fn render_docs(spec: &Value) -> String {
    let mut h = String::new();
    let title = spec["info"]["title"].as_str().unwrap_or("API");
    let _ = write!(
        h,
        "<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{} reference</title>\
<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\"><style>\
body{{font:15px/1.5 system-ui,sans-serif;max-width:60rem;margin:2rem auto;padding:0 1rem;color:#1b1f24}}\
code,pre{{font:13px ui-monospace,monospace;background:#f3f4f6;border-radius:4px}}pre{{padding:.6rem;overflow:auto}}\
.op{{border:1px solid #d0d7de;border-radius:6px;margin:1rem 0;padding:.5rem 1rem}}\
.m{{display:inline-block;min-width:4.5rem;font-weight:700}}.get{{color:#0a5d1a}}.post{{color:#0b4f8a}}.put{{color:#7a4a00}}.delete{{color:#9b1c1c}}\
table{{border-collapse:collapse}}td,th{{border:1px solid #d0d7de;padding:.2rem .5rem;text-align:left}}</style></head><body><main>",
        esc(title)
    );
    let _ = write!(
        h,
        "<h1>{} {}</h1><p>{}</p><p><a href=\"/openapi.yaml\">openapi.yaml</a> is the contract.</p>",
        esc(title),
        esc(spec["info"]["version"].as_str().unwrap_or("")),
        esc(spec["info"]["description"].as_str().unwrap_or(""))
    );
    if let Some(paths) = spec["paths"].as_object() {
        let _ = write!(h, "<nav aria-label=\"Endpoints\"><ul>");
        for (path, ops) in paths {
            for (m, op) in ops.as_object().into_iter().flatten() {
                if !["get", "post", "put", "delete", "patch"].contains(&m.as_str()) {
                    continue;
                }
                let id = op["operationId"].as_str().unwrap_or("");
                let _ = write!(
                    h,
                    "<li><a href=\"#{}\"><span class=\"m {m}\">{}</span> <code>{}</code></a> {}</li>",
                    esc(id),
                    m.to_uppercase(),
                    esc(path),
                    esc(op["summary"].as_str().unwrap_or(""))
                );
            }
        }
        let _ = write!(h, "</ul></nav>");
        for (path, ops) in paths {
            for (m, op) in ops.as_object().into_iter().flatten() {
                if !["get", "post", "put", "delete", "patch"].contains(&m.as_str()) {
                    continue;
                }
                let _ = write!(
                    h,
                    "<section class=\"op\" id=\"{}\"><h2><span class=\"m {m}\">{}</span> <code>{}</code></h2><p>{}</p>",
                    esc(op["operationId"].as_str().unwrap_or("")),
                    m.to_uppercase(),
                    esc(path),
                    esc(op["description"].as_str().or(op["summary"].as_str()).unwrap_or(""))
                );
                let params: Vec<&Value> = ops["parameters"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .chain(op["parameters"].as_array().into_iter().flatten())
                    .collect();
                if !params.is_empty() {
                    let _ = write!(
                        h,
                        "<table><tr><th>Parameter</th><th>In</th><th>Description</th></tr>"
                    );
                    for p in params {
                        let p = resolve(spec, p);
                        let _ = write!(
                            h,
                            "<tr><td><code>{}</code></td><td>{}</td><td>{}</td></tr>",
                            esc(p["name"].as_str().unwrap_or("")),
                            esc(p["in"].as_str().unwrap_or("")),
                            esc(p["description"].as_str().unwrap_or(""))
                        );
                    }
                    let _ = write!(h, "</table>");
                }
                if let Some(resps) = op["responses"].as_object() {
                    let _ = write!(h, "<table><tr><th>Status</th><th>Meaning</th></tr>");
                    for (code, r) in resps {
                        let r = resolve(spec, r);
                        let _ = write!(
                            h,
                            "<tr><td>{}</td><td>{}</td></tr>",
                            esc(code),
                            esc(r["description"].as_str().unwrap_or(""))
                        );
                    }
                    let _ = write!(h, "</table>");
                }
                let _ = write!(h, "</section>");
            }
        }
    }
    h.push_str("</main></body></html>");
    h
}

/// Follow a local `$ref` (`#/components/...`).
fn resolve<'a>(spec: &'a Value, v: &'a Value) -> &'a Value {
    match v["$ref"].as_str().and_then(|r| r.strip_prefix('#')) {
        Some(ptr) => spec.pointer(ptr).unwrap_or(v),
        None => v,
    }
}

pub async fn docs() -> Html<String> {
    static PAGE: OnceLock<String> = OnceLock::new();
    Html(
        PAGE.get_or_init(|| match serde_norway::from_str::<Value>(OPENAPI_YAML) {
            Ok(spec) => render_docs(&spec),
            Err(e) => format!(
                "<!doctype html><p>openapi.yaml does not parse: {}</p>",
                esc(&e.to_string())
            ),
        })
        .clone(),
    )
}

/// `GET /assets/{name}`: the dashboard's scripts, styles and icon.
pub async fn asset(headers: HeaderMap, Path(name): Path<String>) -> Response {
    crate::dashboard::asset(&headers, &name).unwrap_or_else(|| {
        ApiError::new(
            StatusCode::NOT_FOUND,
            "not-found",
            format!(
                "no such asset: expected one of {}",
                crate::dashboard::asset_names().join(", ")
            ),
        )
        .field("name")
        .into_response()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every route the router serves is in the contract, and the contract parses.
    #[test]
    fn openapi_documents_every_route() {
        let spec: Value = serde_norway::from_str(OPENAPI_YAML).expect("openapi.yaml parses");
        let router = include_str!("mod.rs");
        let mut routes = Vec::new();
        for (i, _) in router.match_indices(".route(") {
            let rest = &router[i + 7..];
            let Some(start) = rest.find('"') else {
                continue;
            };
            let path = rest[start + 1..].split('"').next().unwrap_or("");
            let full = if path.starts_with("/sessions")
                || path.starts_with("/jobs")
                || path.starts_with("/vehicles")
                || path.starts_with("/vehicle-models")
                || path.starts_with("/webhooks")
                || path == "/events"
                || path.starts_with("/tenant")
            {
                format!("/v1{path}")
            } else {
                path.to_string()
            };
            routes.push(full);
        }
        assert!(routes.len() >= 15, "{routes:?}");
        for r in &routes {
            assert!(
                spec["paths"].get(r).is_some(),
                "{r} missing from openapi.yaml"
            );
        }
        let html = render_docs(&spec);
        assert!(html.contains("createSession"));
    }
}
