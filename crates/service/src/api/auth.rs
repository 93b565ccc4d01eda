//! API keys: `Authorization: Bearer <key>`, hashed at rest, one tenant per key. Every
//! tenant-scoped query filters on the tenant, so another tenant's objects are simply
//! not found (404), never forbidden (which would reveal that they exist).

use super::error::ApiError;
use super::AppState;
use crate::store::Tenant;
use axum::extract::FromRequestParts;
use axum::http::{header, request::Parts, StatusCode};

/// The tenant on whose behalf a request acts.
pub struct AuthTenant(pub Tenant);

/// Tenant used by `--insecure-no-auth` (local use, the demo).
pub const LOCAL_TENANT: &str = "local";

impl FromRequestParts<AppState> for AuthTenant {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &AppState) -> Result<Self, ApiError> {
        if state.config.insecure_no_auth {
            return Ok(AuthTenant(state.store.ensure_tenant(LOCAL_TENANT).await?));
        }
        let unauthorized = |detail: &str| {
            ApiError::new(StatusCode::UNAUTHORIZED, "unauthorized", detail).field("Authorization")
        };
        let value = parts
            .headers
            .get(header::AUTHORIZATION)
            .ok_or_else(|| unauthorized("an Authorization: Bearer <api key> header is required"))?;
        let text = value
            .to_str()
            .map_err(|_| unauthorized("the Authorization header is not valid text"))?;
        // The scheme is case-insensitive (RFC 9110 §11.1): `Bearer`, `bearer`, `BEARER`.
        let key = text
            .split_once(' ')
            .filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer"))
            .map(|(_, k)| k.trim())
            .filter(|k| !k.is_empty() && k.len() <= 256)
            .ok_or_else(|| unauthorized("expected Authorization: Bearer <api key>"))?;
        match state.store.tenant_for_key(key).await? {
            Some(t) => Ok(AuthTenant(t)),
            None => Err(unauthorized("unknown or revoked API key")),
        }
    }
}
