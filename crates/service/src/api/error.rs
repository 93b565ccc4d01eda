//! Every 4xx/5xx answer is `application/problem+json` (RFC 9457) with a stable `type`
//! per kind of error, a human `detail`, and the offending `field` when there is one.
//!
//! Handlers return [`ApiError`]; [`problem_fallback`] converts the few answers produced
//! outside handlers (unknown routes, wrong methods, body limits, extractor rejections)
//! so that no error escapes in another format.

use axum::body::{Body, Bytes};
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use rigcal_core::session::InputError;
use serde::Serialize;

pub const PROBLEM_JSON: &str = "application/problem+json";

#[derive(Debug, Clone, Serialize)]
pub struct Problem {
    #[serde(rename = "type")]
    pub kind: String,
    pub title: String,
    pub status: u16,
    pub detail: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub field: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub instance: Option<String>,
}

#[derive(Debug, Clone)]
pub struct ApiError {
    pub status: StatusCode,
    /// Stable slug: the `type` is `urn:rigcal:problem:<slug>`.
    pub slug: &'static str,
    pub detail: String,
    pub field: Option<String>,
}

impl ApiError {
    /// A route's query string parsed into `T` (`deny_unknown_fields`), or 400
    /// `invalid-query` saying what was wrong and which parameters the route knows.
    pub fn parse_query<T: serde::de::DeserializeOwned>(
        raw: Option<&str>,
        known: &str,
    ) -> Result<T, ApiError> {
        serde_urlencoded::from_str(raw.unwrap_or("")).map_err(|e| {
            ApiError::new(
                StatusCode::BAD_REQUEST,
                "invalid-query",
                format!("query: {e}; known parameters: {known}"),
            )
            .field("query")
        })
    }

    pub fn new(status: StatusCode, slug: &'static str, detail: impl Into<String>) -> Self {
        Self {
            status,
            slug,
            detail: rigcal_core::session::bounded(
                detail.into(),
                rigcal_core::session::MAX_DETAIL_LEN,
            ),
            field: None,
        }
    }

    pub fn field(mut self, field: impl Into<String>) -> Self {
        self.field = Some(rigcal_core::session::bounded(
            field.into(),
            rigcal_core::session::MAX_FIELD_LEN,
        ));
        self
    }

    pub fn not_found(what: &str) -> Self {
        Self::new(
            StatusCode::NOT_FOUND,
            "not-found",
            format!("no such {what}"),
        )
    }

    /// A request whose content is invalid at `field`.
    pub fn invalid(e: InputError) -> Self {
        Self::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid-field",
            format!("{}: expected {}", e.field, e.expected),
        )
        .field(e.field)
    }

    /// Storage (the blob directory, the database file) failed: 503 with `Retry-After`,
    /// the operation and path in the log only, nothing stored by the request.
    pub fn storage(e: impl std::fmt::Display) -> Self {
        tracing::error!("storage unavailable: {e}");
        Self::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "storage-unavailable",
            "the server's storage is unavailable; nothing was stored by this request, retry later",
        )
    }

    /// A request body that could not be read: beyond the route's limit (413), paused
    /// longer than the body timeout (408), or cut off (400).
    pub fn body(e: &(dyn std::error::Error + 'static), limit: usize) -> Self {
        let mut cur: Option<&(dyn std::error::Error + 'static)> = Some(e);
        while let Some(err) = cur {
            if err.is::<http_body_util::LengthLimitError>() {
                return Self::new(
                    StatusCode::PAYLOAD_TOO_LARGE,
                    "payload-too-large",
                    format!("a request body of at most {limit} bytes"),
                );
            }
            if err.is::<tower_http::timeout::TimeoutError>() {
                return Self::new(
                    StatusCode::REQUEST_TIMEOUT,
                    "request-timeout",
                    "the request body paused longer than the server's body timeout",
                );
            }
            cur = err.source();
        }
        Self::new(
            StatusCode::BAD_REQUEST,
            "bad-request",
            "the request body could not be read to its end",
        )
    }

    /// Read a whole (small) request body, at most `limit` bytes.
    pub async fn read_body(body: axum::body::Body, limit: usize) -> Result<Bytes, Self> {
        let limited = http_body_util::Limited::new(body, limit);
        match http_body_util::BodyExt::collect(limited).await {
            Ok(c) => Ok(c.to_bytes()),
            Err(e) => Err(Self::body(&*e, limit)),
        }
    }

    pub fn internal(e: impl std::fmt::Display) -> Self {
        tracing::error!("internal error: {e}");
        Self::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "internal",
            "an internal error occurred; nothing was changed by this request",
        )
    }
}

impl From<sqlx::Error> for ApiError {
    /// A database that cannot be read or written (I/O, a read-only or full disk, a file
    /// that cannot be opened) is storage unavailable; anything else is internal. SQLite
    /// says which by its result code (the primary code is the low byte of an extended
    /// one): SQLITE_READONLY 8, SQLITE_IOERR 10, SQLITE_FULL 13, SQLITE_CANTOPEN 14.
    fn from(e: sqlx::Error) -> Self {
        let storage = match &e {
            sqlx::Error::Io(_) | sqlx::Error::PoolTimedOut => true,
            sqlx::Error::Database(d) => d
                .code()
                .and_then(|c| c.parse::<i32>().ok())
                .is_some_and(|c| matches!(c & 0xff, 8 | 10 | 13 | 14)),
            _ => false,
        };
        if storage {
            Self::storage(e)
        } else {
            Self::internal(e)
        }
    }
}

fn title(slug: &str) -> String {
    let mut t = slug.replace('-', " ");
    if let Some(c) = t.get(0..1) {
        let up = c.to_uppercase();
        t.replace_range(0..1, &up);
    }
    t
}

/// The problem document (RFC 9457) of an error.
pub fn problem_json(
    status: StatusCode,
    slug: &str,
    detail: &str,
    field: Option<String>,
) -> serde_json::Value {
    let p = Problem {
        kind: format!("urn:rigcal:problem:{slug}"),
        title: title(slug),
        status: status.as_u16(),
        detail: detail.to_string(),
        field,
        instance: None,
    };
    serde_json::to_value(&p).unwrap_or_default()
}

pub fn problem_response(
    status: StatusCode,
    slug: &str,
    detail: String,
    field: Option<String>,
) -> Response {
    let body = problem_json(status, slug, &detail, field).to_string();
    let mut r = Response::new(Body::from(body));
    *r.status_mut() = status;
    r.headers_mut()
        .insert(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON));
    r
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut r = problem_response(self.status, self.slug, self.detail, self.field);
        if self.status == StatusCode::SERVICE_UNAVAILABLE {
            r.headers_mut()
                .insert(header::RETRY_AFTER, HeaderValue::from_static("5"));
        }
        if self.status == StatusCode::UNAUTHORIZED {
            r.headers_mut().insert(
                header::WWW_AUTHENTICATE,
                HeaderValue::from_static("Bearer realm=\"rigcal\""),
            );
        }
        r
    }
}

/// Slug for an error status produced outside the handlers.
fn slug_for(status: StatusCode) -> &'static str {
    match status {
        StatusCode::NOT_FOUND => "not-found",
        StatusCode::METHOD_NOT_ALLOWED => "method-not-allowed",
        StatusCode::PAYLOAD_TOO_LARGE => "payload-too-large",
        StatusCode::UNSUPPORTED_MEDIA_TYPE => "unsupported-media-type",
        StatusCode::UNPROCESSABLE_ENTITY => "invalid-field",
        StatusCode::BAD_REQUEST => "bad-request",
        StatusCode::UNAUTHORIZED => "unauthorized",
        // Bare 503s come from the whole-request timeout (storage errors are problems
        // already).
        StatusCode::SERVICE_UNAVAILABLE => "request-timeout",
        s if s.is_server_error() => "internal",
        _ => "bad-request",
    }
}

/// Rewrite any error answer that is not already problem+json.
pub async fn problem_fallback(resp: Response) -> Response {
    let status = resp.status();
    if !(status.is_client_error() || status.is_server_error()) {
        return resp;
    }
    let is_problem = resp
        .headers()
        .get(header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().starts_with(PROBLEM_JSON.as_bytes()));
    if is_problem {
        return resp;
    }
    let allow = resp.headers().get(header::ALLOW).cloned();
    let body = axum::body::to_bytes(resp.into_body(), 64 * 1024)
        .await
        .unwrap_or_default();
    let text = String::from_utf8_lossy(&body).trim().to_string();
    let detail = match (status, text.is_empty()) {
        (StatusCode::NOT_FOUND, true) => "no such resource".to_string(),
        (StatusCode::METHOD_NOT_ALLOWED, true) => "method not allowed on this resource".into(),
        (StatusCode::PAYLOAD_TOO_LARGE, _) => {
            "the request body exceeds the configured limit for this endpoint".into()
        }
        (StatusCode::SERVICE_UNAVAILABLE, true) => {
            "the request took longer than the server's request timeout; retry later".into()
        }
        (_, true) => status.canonical_reason().unwrap_or("error").to_string(),
        (_, false) => text,
    };
    let mut r = problem_response(status, slug_for(status), detail, None);
    if status == StatusCode::SERVICE_UNAVAILABLE {
        r.headers_mut()
            .insert(header::RETRY_AFTER, HeaderValue::from_static("5"));
    }
    if let Some(a) = allow {
        r.headers_mut().insert(header::ALLOW, a);
    }
    r
}
