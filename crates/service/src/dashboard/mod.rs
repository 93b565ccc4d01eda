//! The job-status dashboard served at `/`: a small page (HTML, CSS, plain JavaScript —
//! no build step, no framework, nothing fetched from elsewhere) embedded in the binary,
//! and the SVG figures it shows ([`svg`]).
//!
//! Why a page that talks to the JSON API rather than server-rendered HTML: the API key
//! lives in the browser's session storage (the issue's "asks once, keeps it in the
//! browser session"), so every request must carry `Authorization`, which a plain
//! navigation cannot. The page is therefore one more API client and shows exactly what
//! the API returns; all numbers come from the result document, all figures from [`svg`].

pub mod svg;

use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};

struct Asset {
    name: &'static str,
    content_type: &'static str,
    body: &'static str,
    /// FNV-1a of the body, computed at compile time (the body never changes at run time).
    checksum: u64,
}

impl Asset {
    const fn new(name: &'static str, content_type: &'static str, body: &'static str) -> Self {
        Asset {
            name,
            content_type,
            body,
            checksum: fnv1a(body.as_bytes()),
        }
    }
}

const fn fnv1a(bytes: &[u8]) -> u64 {
    let mut h = 0xcbf29ce484222325u64;
    let mut i = 0;
    while i < bytes.len() {
        h = (h ^ bytes[i] as u64).wrapping_mul(0x100000001b3);
        i += 1;
    }
    h
}

const INDEX: Asset = Asset::new(
    "index.html",
    "text/html; charset=utf-8",
    include_str!("assets/index.html"),
);

const ASSETS: [Asset; 3] = [
    Asset::new(
        "app.js",
        "text/javascript; charset=utf-8",
        include_str!("assets/app.js"),
    ),
    Asset::new(
        "app.css",
        "text/css; charset=utf-8",
        include_str!("assets/app.css"),
    ),
    Asset::new(
        "favicon.svg",
        "image/svg+xml",
        include_str!("assets/favicon.svg"),
    ),
];

/// Same-origin only: scripts, styles, images and connections to this server; no inline
/// script, no framing. The figures are inserted as markup from our own API.
const CSP: &str = "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; connect-src 'self'; form-action 'self'; base-uri 'none'; frame-ancestors 'none'";

fn serve(headers: &HeaderMap, asset: &Asset) -> Response {
    // Weak validator: the build's version and the asset's checksum.
    let tag = format!("W/\"{}-{:x}\"", env!("CARGO_PKG_VERSION"), asset.checksum);
    let fresh = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == tag));
    let mut resp = if fresh {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        ([(header::CONTENT_TYPE, asset.content_type)], asset.body).into_response()
    };
    let h = resp.headers_mut();
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(CSP),
    );
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    if let Ok(v) = HeaderValue::from_str(&tag) {
        h.insert(header::ETAG, v);
    }
    resp
}

/// `GET /`: the dashboard page.
pub async fn index(headers: HeaderMap) -> Response {
    serve(&headers, &INDEX)
}

/// The asset `name` (conditional on `If-None-Match`), `None` if there is none; the API
/// turns `None` into its 404 (the dashboard has no error type of its own).
pub fn asset(headers: &HeaderMap, name: &str) -> Option<Response> {
    ASSETS
        .iter()
        .find(|a| a.name == name)
        .map(|a| serve(headers, a))
}

/// The names `asset` knows, for the 404's "expected".
pub fn asset_names() -> Vec<&'static str> {
    ASSETS.iter().map(|a| a.name).collect()
}
