//! `Idempotency-Key` on the POSTs that create something (sessions, archives, jobs), as in
//! the IETF draft (draft-ietf-httpapi-idempotency-key-header): the same key and the same
//! body within 24 h get the first answer again (`Idempotent-Replayed: true`) and create
//! nothing; the same key with another body or route is 422; a key whose first request
//! is still running is 409. Only successful answers are kept: a request that failed
//! created nothing, so its key is free for the retry.
//!
//! The body is hashed as it streams (archives can be a gigabyte): into the handler for a
//! fresh key, into the hash only for a replay. This layer sits inside the route's body
//! limit and the body timeout, so a replayed body is held to the same rules.

use super::auth::AuthTenant;
use super::error::ApiError;
use super::AppState;
use crate::store::idempotency::{Claim, StoredAnswer};
use crate::store::now_ms;
use axum::body::Body;
use axum::extract::{FromRequestParts, Request, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use futures::StreamExt;
use http_body_util::BodyExt;
use sha2::{Digest, Sha256};
use std::sync::{Arc, Mutex};

const HEADER: &str = "idempotency-key";
/// Answers of these routes are small JSON documents.
const MAX_ANSWER_BYTES: usize = 16 << 20;

/// A key: 1-255 visible ASCII characters (a UUID, a ULID, a factory's order number).
fn parse_key(v: &HeaderValue) -> Result<String, ApiError> {
    match v.to_str() {
        Ok(k) if !k.is_empty() && k.len() <= 255 && k.bytes().all(|b| b.is_ascii_graphic()) => {
            Ok(k.to_string())
        }
        _ => Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            "invalid-header",
            "Idempotency-Key: 1 to 255 visible ASCII characters (a UUID, for example)",
        )
        .field("Idempotency-Key")),
    }
}

fn seeded(route: &str) -> Sha256 {
    let mut h = Sha256::new();
    h.update(route.as_bytes());
    h.update([0]);
    h
}

pub async fn idempotent(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let Some(raw) = req.headers().get(HEADER) else {
        return next.run(req).await;
    };
    let key = match parse_key(raw) {
        Ok(k) => k,
        Err(e) => return e.into_response(),
    };
    let (mut parts, body) = req.into_parts();
    let tenant = match AuthTenant::from_request_parts(&mut parts, &state).await {
        Ok(AuthTenant(t)) => t,
        Err(e) => return e.into_response(),
    };
    let route = format!("{} {}", parts.method, parts.uri.path());
    let claim = match state
        .store
        .idempotency_claim(&tenant.id, &key, &route, now_ms())
        .await
    {
        Ok(c) => c,
        Err(e) => return ApiError::from(e).into_response(),
    };
    match claim {
        Claim::InFlight => {
            let mut r = ApiError::new(
                StatusCode::CONFLICT,
                "request-in-progress",
                "a request with this Idempotency-Key is still being processed; retry when it has answered",
            )
            .field("Idempotency-Key")
            .into_response();
            r.headers_mut()
                .insert(header::RETRY_AFTER, HeaderValue::from_static("1"));
            r
        }
        Claim::Answered(answer) => {
            // The route's own body limit, for the message of a body beyond it.
            let limit = if route.starts_with("POST /v1/jobs") {
                state.config.max_manifest_bytes
            } else {
                state.config.max_archive_bytes
            };
            replay(answer, &route, body, limit).await
        }
        Claim::Fresh => {
            let hasher = Arc::new(Mutex::new(seeded(&route)));
            let h = hasher.clone();
            let body = Body::new(body.map_frame(move |f| {
                if let (Some(d), Ok(mut h)) = (f.data_ref(), h.lock()) {
                    h.update(d);
                }
                f
            }));
            let resp = next.run(Request::from_parts(parts, body)).await;
            let fingerprint: Result<String, ()> = match hasher.lock() {
                Ok(h) => Ok(hex::encode(h.clone().finalize())),
                Err(_) => Err(()),
            };
            match (resp.status().is_success(), fingerprint) {
                (true, Ok(fingerprint)) => {
                    keep(&state, &tenant.id, &key, route, fingerprint, resp).await
                }
                _ => {
                    // Nothing was created (or the hash is lost): free the key. A failure
                    // to free it only delays the retry until the in-flight timeout.
                    let _ = state.store.idempotency_release(&tenant.id, &key).await;
                    resp
                }
            }
        }
    }
}

/// Store a successful answer and return it.
async fn keep(
    state: &AppState,
    tenant_id: &str,
    key: &str,
    route: String,
    fingerprint: String,
    resp: Response,
) -> Response {
    let (parts, body) = resp.into_parts();
    let body = match axum::body::to_bytes(body, MAX_ANSWER_BYTES).await {
        Ok(b) => b,
        Err(e) => return ApiError::internal(format!("reading the answer: {e}")).into_response(),
    };
    let text = |h: header::HeaderName| {
        parts
            .headers
            .get(h)
            .and_then(|v| v.to_str().ok())
            .map(str::to_string)
    };
    let answer = StoredAnswer {
        route,
        fingerprint,
        status: parts.status.as_u16(),
        content_type: text(header::CONTENT_TYPE),
        location: text(header::LOCATION),
        body: body.to_vec(),
    };
    if let Err(e) = state
        .store
        .idempotency_finish(tenant_id, key, &answer)
        .await
    {
        // The work is done and stored; only the replay record is missing. Say so rather
        // than answer as if a retry were safe.
        tracing::warn!("idempotency record for key {key:?} not stored: {e}");
        return ApiError::from(e).into_response();
    }
    Response::from_parts(parts, Body::from(body))
}

/// The stored answer again, if `body` is the body it answered.
async fn replay(answer: StoredAnswer, route: &str, body: Body, limit: usize) -> Response {
    let mismatch = |what: &str| {
        ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "idempotency-key-reused",
            format!("this Idempotency-Key was used for {what}; use a new key for a new request"),
        )
        .field("Idempotency-Key")
        .into_response()
    };
    if answer.route != route {
        return mismatch(&format!("another request ({})", answer.route));
    }
    let mut h = seeded(route);
    let mut stream = body.into_data_stream();
    while let Some(chunk) = stream.next().await {
        match chunk {
            Ok(d) => h.update(&d),
            Err(e) => return ApiError::body(&e, limit).into_response(),
        }
    }
    if hex::encode(h.finalize()) != answer.fingerprint {
        return mismatch("a request with another body");
    }
    let mut r = Response::new(Body::from(answer.body));
    // Only successful answers are stored (`keep`), so the status is a 2xx we wrote; a
    // stored value that is no status is a corrupt record, said as such.
    match StatusCode::from_u16(answer.status) {
        Ok(s) => *r.status_mut() = s,
        Err(_) => {
            return ApiError::internal(format!(
                "stored idempotency answer has status {}",
                answer.status
            ))
            .into_response()
        }
    }
    let headers = r.headers_mut();
    for (name, value) in [
        (header::CONTENT_TYPE, answer.content_type),
        (header::LOCATION, answer.location),
    ] {
        if let Some(v) = value.and_then(|v| HeaderValue::from_str(&v).ok()) {
            headers.insert(name, v);
        }
    }
    headers.insert("idempotent-replayed", HeaderValue::from_static("true"));
    r
}
