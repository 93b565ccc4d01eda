//! Capture sessions: create from a manifest (or a whole archive), upload images one by
//! one (idempotent) or as an archive, read back with the capture check.
//!
//! Writes follow one order so that a failed request changes nothing: validate
//! everything first, then write blobs (atomic, content-addressed), then the rows.

use super::auth::AuthTenant;
use super::error::ApiError;
use super::AppState;
use crate::calib::check::capture_check;
use crate::imageio::{self, ImageError, ImageMeta};
use crate::pipeline::undetected_images;
use crate::session::{image_slots, parse_session, ImageSlot, InputError, Session};
use crate::store::{rfc3339, ImageRow, SessionRow, Store, Tenant};
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde_json::{json, Value};
use std::collections::{BTreeMap, HashMap};
use std::io::Read;

/// Parse a stored or uploaded manifest. Syntax errors are 400 `malformed-json`;
/// content errors 422 with the field path (`limit-exceeded` for the size limits).
pub fn parse_manifest(bytes: &[u8], max_bytes: usize) -> Result<Session, ApiError> {
    if bytes.len() > max_bytes {
        return Err(ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "payload-too-large",
            format!(
                "a manifest of at most {max_bytes} bytes, got {}",
                bytes.len()
            ),
        ));
    }
    if let Err(e) = serde_json::from_slice::<serde::de::IgnoredAny>(bytes) {
        return Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            "malformed-json",
            format!("the manifest is not valid JSON: {e}"),
        ));
    }
    parse_session(bytes).map_err(|e| {
        let limit =
            (e.field == "cameras" || e.field == "frames") && e.expected.starts_with("at most");
        let mut err = ApiError::invalid(e);
        if limit {
            err.slug = "limit-exceeded";
        }
        err
    })
}

pub fn image_error(e: ImageError, field: &str) -> ApiError {
    let (status, slug) = match &e {
        ImageError::UnsupportedFormat(_) => (
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported-image-format",
        ),
        ImageError::TooLarge { .. } => (StatusCode::UNPROCESSABLE_ENTITY, "image-too-large"),
        ImageError::SizeMismatch { .. } => {
            (StatusCode::UNPROCESSABLE_ENTITY, "image-size-mismatch")
        }
        ImageError::Undecodable(_) => (StatusCode::UNPROCESSABLE_ENTITY, "undecodable-image"),
    };
    ApiError::new(status, slug, format!("{field}: expected {e}")).field(field)
}

async fn session_or_404(store: &Store, tenant: &Tenant, id: &str) -> Result<SessionRow, ApiError> {
    store
        .session(tenant, id)
        .await?
        .ok_or_else(|| ApiError::not_found("session").field("id"))
}

fn stored_session(row: &SessionRow) -> Result<Session, ApiError> {
    parse_session(row.manifest.as_bytes()).map_err(ApiError::internal)
}

async fn view(store: &Store, row: &SessionRow, session: &Session) -> Result<Value, ApiError> {
    let images = store.images(&row.id).await?;
    let have: HashMap<(String, i64), &ImageRow> = images
        .iter()
        .map(|i| ((i.camera.clone(), i.frame), i))
        .collect();
    let all = image_slots(session);
    // Received once but whose bytes are gone from the blob store (a lost disk, a removed
    // directory): missing again, and said so, rather than "received".
    let lost: Vec<&ImageSlot> = all
        .iter()
        .filter(|s| {
            have.get(&(s.camera.clone(), s.frame))
                .is_some_and(|i| !store.blobs.contains(&i.sha256))
        })
        .collect();
    let missing: Vec<&ImageSlot> = all
        .iter()
        .filter(|s| !have.contains_key(&(s.camera.clone(), s.frame)))
        .chain(lost.iter().copied())
        .collect();
    let check: Value = row
        .capture_check
        .as_deref()
        .and_then(|c| serde_json::from_str(c).ok())
        .unwrap_or(Value::Null);
    Ok(json!({
        "id": row.id,
        "vehicle_id": row.vehicle_id,
        "method": row.method,
        "created_at": rfc3339(row.created_at),
        "reference_camera": session.cameras[session.reference].id,
        "cameras": session.cameras.iter().map(|c| json!({"id": c.id, "width": c.camera.width, "height": c.camera.height})).collect::<Vec<_>>(),
        "frames": session.frames.len(),
        "images_expected": all.len(),
        "images_received": images.len() - lost.len(),
        "images_missing": missing,
        "images_lost": lost.iter().map(|s| s.field.as_str()).collect::<Vec<_>>(),
        "capture_check": check,
    }))
}

/// The capture check, on a blocking thread (it reconstructs trajectories).
async fn run_check(session: Session) -> Option<String> {
    if !undetected_images(&session).is_empty() {
        return None;
    }
    // The check is advice before a solve: if it fails (a bug), the session is still
    // stored and the failure is logged as the internal error it is, not hidden.
    let outcome = tokio::task::spawn_blocking(move || {
        std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| capture_check(&session)))
    })
    .await;
    match outcome {
        Ok(Ok(check)) => match serde_json::to_string(&check) {
            Ok(text) => Some(text),
            Err(e) => {
                tracing::error!("internal error: the capture check did not serialise: {e}");
                None
            }
        },
        Ok(Err(_)) => {
            tracing::error!("internal error: the capture check panicked");
            None
        }
        Err(e) => {
            tracing::error!("internal error: the capture check task failed: {e}");
            None
        }
    }
}

fn content_type(headers: &HeaderMap) -> String {
    headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .map(|v| {
            v.split(';')
                .next()
                .unwrap_or("")
                .trim()
                .to_ascii_lowercase()
        })
        .unwrap_or_default()
}

enum ArchiveKind {
    Tar,
    Zip,
}

fn archive_kind(headers: &HeaderMap, body: &[u8]) -> Option<ArchiveKind> {
    match content_type(headers).as_str() {
        "application/zip" | "application/x-zip-compressed" => Some(ArchiveKind::Zip),
        "application/x-tar" | "application/tar" => Some(ArchiveKind::Tar),
        "application/octet-stream" if body.starts_with(b"PK\x03\x04") => Some(ArchiveKind::Zip),
        "application/octet-stream" if body.len() > 262 && &body[257..262] == b"ustar" => {
            Some(ArchiveKind::Tar)
        }
        _ => None,
    }
}

/// Files of an archive (path → bytes), total size capped (zip bombs).
fn unpack(
    kind: ArchiveKind,
    body: &[u8],
    max_total: usize,
) -> Result<BTreeMap<String, Vec<u8>>, ApiError> {
    let bad = |d: String| {
        ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, "invalid-archive", d).field("archive")
    };
    let mut files = BTreeMap::new();
    let mut total = 0usize;
    let mut add = |name: String,
                   r: &mut dyn Read,
                   files: &mut BTreeMap<String, Vec<u8>>|
     -> Result<(), ApiError> {
        let mut buf = Vec::new();
        let left = max_total.saturating_sub(total);
        r.take(left as u64 + 1)
            .read_to_end(&mut buf)
            .map_err(|e| bad(format!("archive entry {name} is unreadable: {e}")))?;
        if buf.len() > left {
            return Err(ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                "payload-too-large",
                format!("the archive unpacks to more than {max_total} bytes"),
            )
            .field("archive"));
        }
        total += buf.len();
        if files.len() >= 200_000 {
            return Err(bad("an archive of at most 200000 files".into()));
        }
        // Two entries of one name (two session.json, an image twice): which one the
        // client meant is unknowable, so neither is taken.
        let key = name.trim_start_matches("./").to_string();
        if files.contains_key(&key) {
            return Err(bad(format!(
                "archive entry names unique, got {} twice",
                crate::session::quoted_prefix(&key)
            )));
        }
        files.insert(key, buf);
        Ok(())
    };
    match kind {
        ArchiveKind::Tar => {
            let mut ar = tar::Archive::new(body);
            let entries = ar
                .entries()
                .map_err(|e| bad(format!("not a readable tar archive: {e}")))?;
            for entry in entries {
                let mut entry =
                    entry.map_err(|e| bad(format!("a tar entry is unreadable: {e}")))?;
                if !entry.header().entry_type().is_file() {
                    continue;
                }
                let name = entry
                    .path()
                    .map_err(|e| bad(format!("a tar entry has an invalid path: {e}")))?
                    .to_string_lossy()
                    .to_string();
                add(name, &mut entry, &mut files)?;
            }
        }
        ArchiveKind::Zip => {
            // The zip reader keeps one entry per name; a name twice is found in the
            // central directory itself.
            if let Some(name) = zip_duplicate_name(body) {
                return Err(bad(format!(
                    "archive entry names unique, got {} twice",
                    crate::session::quoted_prefix(&name)
                )));
            }
            let mut ar = zip::ZipArchive::new(std::io::Cursor::new(body))
                .map_err(|e| bad(format!("not a readable zip archive: {e}")))?;
            for i in 0..ar.len() {
                let mut f = ar
                    .by_index(i)
                    .map_err(|e| bad(format!("zip entry {i} is unreadable: {e}")))?;
                if !f.is_file() {
                    continue;
                }
                let name = f
                    .name()
                    .map_err(|e| bad(format!("zip entry {i} has an invalid name: {e}")))?
                    .to_string();
                add(name, &mut f, &mut files)?;
            }
        }
    }
    Ok(files)
}

/// A name that the zip's central directory lists twice. Walks the directory from the
/// end-of-central-directory record (the last one in the file; a zip64 directory, whose
/// offset does not fit there, is left to the reader).
fn zip_duplicate_name(body: &[u8]) -> Option<String> {
    let le16 = |b: &[u8], i: usize| Some(u16::from_le_bytes([*b.get(i)?, *b.get(i + 1)?]) as usize);
    let le32 = |b: &[u8], i: usize| {
        Some(
            u32::from_le_bytes([*b.get(i)?, *b.get(i + 1)?, *b.get(i + 2)?, *b.get(i + 3)?])
                as usize,
        )
    };
    let eocd = (0..=body.len().checked_sub(22)?)
        .rev()
        .take(22 + 65_535)
        .find(|&i| body[i..].starts_with(b"PK\x05\x06"))?;
    let (count, offset) = (le16(body, eocd + 10)?, le32(body, eocd + 16)?);
    let mut at = offset;
    let mut names = std::collections::HashSet::new();
    for _ in 0..count {
        if !body.get(at..)?.starts_with(b"PK\x01\x02") {
            return None;
        }
        let (n, m, k) = (
            le16(body, at + 28)?,
            le16(body, at + 30)?,
            le16(body, at + 32)?,
        );
        let name = String::from_utf8_lossy(body.get(at + 46..at + 46 + n)?).to_string();
        if !names.insert(name.clone()) {
            return Some(name);
        }
        at += 46 + n + m + k;
    }
    None
}

/// The manifest of an unpacked archive: `session.json` at the top or in one folder.
/// Returns its bytes and the folder prefix image paths are relative to.
fn find_manifest(files: &BTreeMap<String, Vec<u8>>) -> Option<(Vec<u8>, String)> {
    let mut found: Vec<&String> = files
        .keys()
        .filter(|k| {
            *k == "session.json" || (k.ends_with("/session.json") && k.matches('/').count() == 1)
        })
        .collect();
    found.sort_by_key(|k| k.len());
    let k = found.first()?;
    let prefix = k.strip_suffix("session.json").unwrap_or("").to_string();
    Some((files[*k].clone(), prefix))
}

/// Inspect every image of `files` named by the manifest. Nothing is written here.
fn inspect_archive_images(
    session: &Session,
    files: &BTreeMap<String, Vec<u8>>,
    prefix: &str,
    max_pixels: u64,
) -> Result<Vec<(ImageSlot, ImageMeta, Vec<u8>)>, ApiError> {
    let mut out = Vec::new();
    for slot in image_slots(session) {
        let Some(bytes) = files.get(&format!("{prefix}{}", slot.path)) else {
            continue;
        };
        let meta = imageio::inspect(bytes, Some(slot.size), max_pixels)
            .map_err(|e| image_error(e, &slot.field))?;
        out.push((slot, meta, bytes.clone()));
    }
    Ok(out)
}

/// Write blobs (blocking) and then rows. Conflicting existing images were ruled out by the caller.
async fn store_images(
    store: &Store,
    session_id: &str,
    images: Vec<(ImageSlot, ImageMeta, Vec<u8>)>,
) -> Result<(), ApiError> {
    let blobs = store.blobs.clone();
    let rows = tokio::task::spawn_blocking(move || -> std::io::Result<Vec<ImageRow>> {
        images
            .into_iter()
            .map(|(slot, meta, bytes)| {
                let sha = blobs.put(&bytes)?;
                Ok(ImageRow {
                    camera: slot.camera,
                    frame: slot.frame,
                    sha256: sha,
                    bytes: bytes.len() as i64,
                    format: meta.format.to_string(),
                    width: meta.width as i64,
                    height: meta.height as i64,
                })
            })
            .collect()
    })
    .await
    .map_err(ApiError::internal)?
    .map_err(ApiError::storage)?;
    for r in &rows {
        store.insert_image(session_id, r).await?;
    }
    Ok(())
}

/// `POST /v1/sessions`: a JSON manifest, or a tar/zip archive with `session.json` and images.
pub async fn create(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    headers: HeaderMap,
    body: Bytes,
) -> Result<Response, ApiError> {
    let cfg = &state.config;
    let (manifest_bytes, images) = if let Some(kind) = archive_kind(&headers, &body) {
        let body2 = body.clone();
        let max = cfg.max_archive_bytes;
        let files = tokio::task::spawn_blocking(move || unpack(kind, &body2, max))
            .await
            .map_err(ApiError::internal)??;
        let (manifest, prefix) = find_manifest(&files).ok_or_else(|| {
            ApiError::new(
                StatusCode::UNPROCESSABLE_ENTITY,
                "invalid-archive",
                "the archive has no session.json (at its top or in one top-level folder)",
            )
            .field("session.json")
        })?;
        let session = parse_manifest(&manifest, cfg.max_manifest_bytes)?;
        let max_px = cfg.max_image_pixels;
        let images = tokio::task::spawn_blocking(move || {
            inspect_archive_images(&session, &files, &prefix, max_px)
        })
        .await
        .map_err(ApiError::internal)??;
        (manifest, images)
    } else {
        let ct = content_type(&headers);
        if !(ct == "application/json" || ct.ends_with("+json") || ct.is_empty()) {
            return Err(ApiError::new(
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "unsupported-media-type",
                format!("Content-Type application/json (a manifest), application/x-tar or application/zip (an archive), got {ct}"),
            )
            .field("Content-Type"));
        }
        (body.to_vec(), vec![])
    };
    let session = parse_manifest(&manifest_bytes, cfg.max_manifest_bytes)?;
    let text = String::from_utf8(manifest_bytes).map_err(|_| {
        ApiError::new(
            StatusCode::BAD_REQUEST,
            "malformed-json",
            "the manifest is not UTF-8",
        )
    })?;
    let check = run_check(session.clone()).await;
    let method = match session.manifest.method {
        crate::session::Method::Motion => "motion",
        crate::session::Method::Vanishing => "vanishing",
    };
    // Blobs first (durable), then the session and image rows.
    let blobs = state.store.blobs.clone();
    let pre: Vec<(ImageSlot, ImageMeta, Vec<u8>)> = images;
    let pre = tokio::task::spawn_blocking(
        move || -> std::io::Result<Vec<(ImageSlot, ImageMeta, Vec<u8>)>> {
            for (_, _, b) in &pre {
                blobs.put(b)?;
            }
            Ok(pre)
        },
    )
    .await
    .map_err(ApiError::internal)?
    .map_err(ApiError::storage)?;
    let row = state
        .store
        .insert_session(
            &tenant,
            session.manifest.vehicle_id.as_deref(),
            method,
            &text,
            check.as_deref(),
        )
        .await?;
    store_images(&state.store, &row.id, pre).await?;
    let v = view(&state.store, &row, &session).await?;
    Ok((
        StatusCode::CREATED,
        [(header::LOCATION, format!("/v1/sessions/{}", row.id))],
        Json(v),
    )
        .into_response())
}

pub async fn show(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(id): Path<String>,
) -> Result<Json<Value>, ApiError> {
    let row = session_or_404(&state.store, &tenant, &id).await?;
    let session = stored_session(&row)?;
    Ok(Json(view(&state.store, &row, &session).await?))
}

/// `GET /v1/sessions/{id}/check`: the capture check (409 while detections are pending).
pub async fn check(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(id): Path<String>,
) -> Result<Json<Value>, ApiError> {
    let row = session_or_404(&state.store, &tenant, &id).await?;
    match row
        .capture_check
        .as_deref()
        .map(serde_json::from_str::<Value>)
    {
        Some(Ok(v)) => Ok(Json(v)),
        Some(Err(e)) => Err(ApiError::internal(e)),
        None => Err(ApiError::new(
            StatusCode::CONFLICT,
            "check-not-ready",
            "the capture check runs on detections; this session's images have no detections yet",
        )),
    }
}

/// `PUT /v1/sessions/{id}/images/{camera}/{frame}`: one image, idempotent.
pub async fn put_image(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path((id, camera, frame)): Path<(String, String, String)>,
    body: Bytes,
) -> Result<Json<Value>, ApiError> {
    let row = session_or_404(&state.store, &tenant, &id).await?;
    let session = stored_session(&row)?;
    let all = image_slots(&session);
    let mut ids: Vec<&str> = session.cameras.iter().map(|c| c.id.as_str()).collect();
    if let Some(v) = &session.vanishing {
        ids.push(v.auxiliary.id.as_str());
    }
    if !ids.contains(&camera.as_str()) {
        return Err(ApiError::new(
            StatusCode::NOT_FOUND,
            "unknown-camera",
            format!(
                "camera: one of the session's cameras ({}), got {camera:?}",
                ids.join(", ")
            ),
        )
        .field("camera"));
    }
    let frame_index: i64 = frame.parse().map_err(|_| {
        ApiError::new(
            StatusCode::NOT_FOUND,
            "unknown-frame",
            format!("frame: an integer frame index of the session, got {frame:?}"),
        )
        .field("frame")
    })?;
    let Some(slot) = all
        .into_iter()
        .find(|s| s.camera == camera && s.frame == frame_index)
    else {
        return Err(ApiError::new(
            StatusCode::NOT_FOUND,
            "unknown-frame",
            format!("frame: a frame whose manifest entry names an image for camera {camera}, got {frame_index}"),
        )
        .field("frame"));
    };
    let ((w, h), max_px) = (slot.size, state.config.max_image_pixels);
    let body2 = body.clone();
    let meta = tokio::task::spawn_blocking(move || imageio::inspect(&body2, Some((w, h)), max_px))
        .await
        .map_err(ApiError::internal)?
        .map_err(|e| image_error(e, "image"))?;
    let sha = crate::store::blob::sha256_hex(&body);
    // Same slot with other bytes: refuse before writing anything.
    if let Some(existing) = state
        .store
        .images(&row.id)
        .await?
        .into_iter()
        .find(|i| i.camera == camera && i.frame == frame_index)
    {
        if existing.sha256 != sha {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                "image-conflict",
                format!("camera {camera} frame {frame_index} already has a different image (sha256 {}); images are immutable", existing.sha256),
            )
            .field("image"));
        }
    }
    store_images(&state.store, &row.id, vec![(slot, meta, body.to_vec())]).await?;
    let images = state.store.images(&row.id).await?;
    let stored = images
        .iter()
        .find(|i| i.camera == camera && i.frame == frame_index)
        .ok_or_else(|| ApiError::internal("image row missing after insert"))?;
    if stored.sha256 != sha {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            "image-conflict",
            format!("camera {camera} frame {frame_index} already has a different image"),
        )
        .field("image"));
    }
    Ok(Json(json!({
        "session_id": row.id,
        "camera": stored.camera,
        "frame": stored.frame,
        "sha256": stored.sha256,
        "bytes": stored.bytes,
        "format": stored.format,
        "width": stored.width,
        "height": stored.height,
    })))
}

/// `POST /v1/sessions/{id}/archive`: the images of an existing session as one tar or
/// zip (with its `session.json`, which must equal the stored manifest, if present).
pub async fn archive(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<Json<Value>, ApiError> {
    let row = session_or_404(&state.store, &tenant, &id).await?;
    let session = stored_session(&row)?;
    let kind = archive_kind(&headers, &body).ok_or_else(|| {
        ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported-media-type",
            "Content-Type application/x-tar or application/zip",
        )
        .field("Content-Type")
    })?;
    let max = state.config.max_archive_bytes;
    let body2 = body.clone();
    let files = tokio::task::spawn_blocking(move || unpack(kind, &body2, max))
        .await
        .map_err(ApiError::internal)??;
    let prefix = match find_manifest(&files) {
        Some((m, prefix)) => {
            let theirs: Value = serde_json::from_slice(&m).map_err(|e| {
                ApiError::new(
                    StatusCode::BAD_REQUEST,
                    "malformed-json",
                    format!("session.json: {e}"),
                )
                .field("session.json")
            })?;
            let ours: Value = serde_json::from_str(&row.manifest).map_err(ApiError::internal)?;
            if theirs != ours {
                return Err(ApiError::new(
                    StatusCode::CONFLICT,
                    "manifest-mismatch",
                    "the archive's session.json differs from the session's manifest; create a new session for a new manifest",
                )
                .field("session.json"));
            }
            prefix
        }
        None => String::new(),
    };
    let max_px = state.config.max_image_pixels;
    let s2 = session.clone();
    let images =
        tokio::task::spawn_blocking(move || inspect_archive_images(&s2, &files, &prefix, max_px))
            .await
            .map_err(ApiError::internal)??;
    if images.is_empty() {
        return Err(ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid-archive",
            "the archive contains none of the image paths the manifest names",
        )
        .field("archive"));
    }
    let existing: HashMap<(String, i64), String> = state
        .store
        .images(&row.id)
        .await?
        .into_iter()
        .map(|i| ((i.camera, i.frame), i.sha256))
        .collect();
    for (slot, _, bytes) in &images {
        if let Some(sha) = existing.get(&(slot.camera.clone(), slot.frame)) {
            if *sha != crate::store::blob::sha256_hex(bytes) {
                return Err(ApiError::new(
                    StatusCode::CONFLICT,
                    "image-conflict",
                    format!(
                        "{}: camera {} frame {} already has a different image",
                        slot.path, slot.camera, slot.frame
                    ),
                )
                .field(slot.path.clone()));
            }
        }
    }
    store_images(&state.store, &row.id, images).await?;
    Ok(Json(view(&state.store, &row, &session).await?))
}

impl From<InputError> for ApiError {
    fn from(e: InputError) -> Self {
        ApiError::invalid(e)
    }
}
