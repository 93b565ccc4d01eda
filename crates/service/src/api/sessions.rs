//! Capture sessions: create from a manifest (or a whole archive), upload images one by
//! one (idempotent) or as an archive, read back with the capture check.
//!
//! Writes follow one order so that a failed request changes nothing: validate
//! everything first, then write blobs (atomic, content-addressed), then the rows.

use super::archive::{self, ArchiveKind, Limits, Unpacked};
use super::auth::AuthTenant;
use super::error::ApiError;
use super::AppState;
use crate::store::blob::{StageError, Staged};
use crate::store::{rfc3339, ImageRow, SessionRow, Store, Tenant};
use axum::body::Body;
use axum::extract::{Path, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::Json;
use futures::Stream;
use rigcal_calib::check::capture_check;
use rigcal_core::session::undetected_images;
use rigcal_core::session::{image_slots, parse_session, ImageSlot, InputError, Session};
use rigcal_detect::imageio::{self, ImageError, ImageMeta};
use rigcal_engine::pipeline::detection::awaiting_detection;
use serde_json::{json, Value};
use std::collections::HashMap;
use std::collections::HashSet;
use std::convert::Infallible;
use std::time::Duration;

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
    let gone = futures::future::try_join_all(all.iter().map(|s| async {
        match have.get(&(s.camera.clone(), s.frame)) {
            Some(i) => Ok(!store.blobs.contains(&i.sha256).await?),
            None => Ok::<bool, std::io::Error>(false),
        }
    }))
    .await
    .map_err(ApiError::storage)?;
    let lost: Vec<&ImageSlot> = all
        .iter()
        .zip(gone)
        .filter(|(_, g)| *g)
        .map(|(s, _)| s)
        .collect();
    let missing: Vec<&ImageSlot> = all
        .iter()
        .filter(|s| !have.contains_key(&(s.camera.clone(), s.frame)))
        .chain(lost.iter().copied())
        .collect();
    let check: Value = match row.capture_check.as_deref() {
        Some(c) => serde_json::from_str(c).map_err(ApiError::internal)?,
        None => Value::Null,
    };
    let counts = store.detection_counts(&row.id).await?;
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
        "images_to_detect": awaiting_detection(session).len(),
        "images_detected": counts.done + counts.failed,
        "capture_check": check,
        "capture_check_complete": check_complete(row),
    }))
}

/// Whether the stored capture check covers every image: one computed at creation from
/// the session's detections, or one recomputed at upload over all its images.
fn check_complete(row: &SessionRow) -> bool {
    row.capture_check.is_some()
        && match (row.check_detected, row.check_expected) {
            (Some(d), Some(e)) => d >= e,
            _ => true,
        }
}

/// The (camera, frame) slots of `session` whose images are detected at upload.
fn to_detect(session: &Session) -> HashSet<(String, i64)> {
    awaiting_detection(session)
        .into_iter()
        .map(|s| (s.camera, s.frame))
        .collect()
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

/// Inspect every staged image the manifest names (one image in memory at a time).
/// Nothing is stored here.
fn inspect_archive_images(
    session: &Session,
    mut unpacked: Unpacked,
    prefix: &str,
    max_pixels: u64,
) -> Result<Vec<(ImageSlot, ImageMeta, Staged)>, ApiError> {
    let mut out = Vec::new();
    for slot in image_slots(session) {
        let Some(staged) = unpacked.files.remove(&format!("{prefix}{}", slot.path)) else {
            continue;
        };
        let bytes = staged.read().map_err(ApiError::storage)?;
        let meta = imageio::inspect(&bytes, Some(slot.size), max_pixels)
            .map_err(|e| image_error(e, &slot.field))?;
        out.push((slot, meta, staged));
    }
    Ok(out)
}

/// Move staged images to their content addresses (blocking) and return their rows.
async fn commit_images(
    store: &Store,
    images: Vec<(ImageSlot, ImageMeta, Staged)>,
) -> Result<Vec<ImageRow>, ApiError> {
    let blobs = store.blobs.clone();
    tokio::task::spawn_blocking(move || -> std::io::Result<Vec<ImageRow>> {
        images
            .into_iter()
            .map(|(slot, meta, staged)| {
                let bytes = staged.len as i64;
                let sha = blobs.commit(staged)?;
                Ok(ImageRow {
                    camera: slot.camera,
                    frame: slot.frame,
                    sha256: sha,
                    bytes,
                    format: meta.format.to_string(),
                    width: meta.width as i64,
                    height: meta.height as i64,
                })
            })
            .collect()
    })
    .await
    .map_err(ApiError::internal)?
    .map_err(ApiError::storage)
}

/// Blobs first (durable), then the rows. Conflicting existing images were ruled out by
/// the caller.
async fn store_images(
    store: &Store,
    session_id: &str,
    session: &Session,
    images: Vec<(ImageSlot, ImageMeta, Staged)>,
) -> Result<(), ApiError> {
    let detect = to_detect(session);
    for r in &commit_images(store, images).await? {
        let d = detect.contains(&(r.camera.clone(), r.frame));
        store.insert_image(session_id, r, d).await?;
    }
    Ok(())
}

/// An archive upload's slot: at most `max_concurrent_archives` are read at once, the
/// next is 503 `busy` with `Retry-After` (each holds a spool file and a blocking thread).
fn archive_slot(state: &AppState) -> Result<tokio::sync::OwnedSemaphorePermit, ApiError> {
    state
        .archive_slots
        .clone()
        .try_acquire_owned()
        .map_err(|_| {
            ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                "busy",
                format!(
                    "at most {} archive uploads are read at once; retry later",
                    state.config.max_concurrent_archives
                ),
            )
        })
}

/// Spool and unpack an archive body (the caller holds an archive slot).
async fn read_archive(
    state: &AppState,
    content_type: &str,
    body: Body,
) -> Result<Unpacked, ApiError> {
    let cfg = &state.config;
    let spooled = archive::spool(body, &state.store.blobs, cfg.max_archive_bytes as u64).await?;
    let kind = ArchiveKind::of(content_type, &spooled.head).ok_or_else(|| {
        ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported-media-type",
            format!("Content-Type application/x-tar or application/zip (or application/octet-stream with a tar or zip body), got {content_type}"),
        )
        .field("Content-Type")
    })?;
    let limits = Limits {
        total: cfg.max_archive_bytes as u64,
        entry: cfg.max_image_bytes as u64,
        manifest: cfg.max_manifest_bytes as u64,
    };
    let blobs = state.store.blobs.clone();
    tokio::task::spawn_blocking(move || archive::unpack(kind, &spooled, &blobs, limits))
        .await
        .map_err(ApiError::internal)?
}

/// `POST /v1/sessions`: a JSON manifest, or a tar/zip archive with `session.json` and images.
pub async fn create(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    let cfg = &state.config;
    let ct = content_type(&headers);
    let (manifest_bytes, session, images) = if ct == "application/json"
        || ct.ends_with("+json")
        || ct.is_empty()
    {
        let bytes = ApiError::read_body(body, cfg.max_manifest_bytes).await?;
        let session = parse_manifest(&bytes, cfg.max_manifest_bytes)?;
        (bytes.to_vec(), session, vec![])
    } else if ArchiveKind::may_be(&ct) {
        let _slot = archive_slot(&state)?;
        let mut unpacked = read_archive(&state, &ct, body).await?;
        let (manifest, prefix) = unpacked.take_manifest().ok_or_else(|| {
            ApiError::new(
                StatusCode::UNPROCESSABLE_ENTITY,
                "invalid-archive",
                "the archive has no session.json (at its top or in one top-level folder)",
            )
            .field("session.json")
        })?;
        let session = parse_manifest(&manifest, cfg.max_manifest_bytes)?;
        let max_px = cfg.worker.max_image_pixels;
        let s2 = session.clone();
        let images = tokio::task::spawn_blocking(move || {
            inspect_archive_images(&s2, unpacked, &prefix, max_px)
        })
        .await
        .map_err(ApiError::internal)??;
        (manifest, session, images)
    } else {
        return Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported-media-type",
            format!("Content-Type application/json (a manifest), application/x-tar or application/zip (an archive), got {ct}"),
        )
        .field("Content-Type"));
    };
    if let Some(name) = &session.manifest.vehicle_model {
        let model = state
            .store
            .vehicle_model(&tenant.id, name)
            .await?
            .ok_or_else(|| {
                ApiError::invalid(InputError::new(
                    "vehicle_model",
                    format!("a vehicle model of this tenant (PUT /v1/vehicle-models/{name} first), got {name}"),
                ))
            })?;
        let ids: Vec<&str> = session.cameras.iter().map(|c| c.id.as_str()).collect();
        model
            .document
            .fits(&session.manifest.reference_camera, &ids)
            .map_err(ApiError::invalid)?;
    }
    let text = String::from_utf8(manifest_bytes).map_err(|_| {
        ApiError::new(
            StatusCode::BAD_REQUEST,
            "malformed-json",
            "the manifest is not UTF-8",
        )
    })?;
    let check = run_check(session.clone()).await;
    let method = match session.manifest.method {
        rigcal_core::session::Method::Motion => "motion",
        rigcal_core::session::Method::Vanishing => "vanishing",
    };
    // Blobs first (durable), then the session and image rows.
    let rows = commit_images(&state.store, images).await?;
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
    let detect = to_detect(&session);
    for r in &rows {
        let d = detect.contains(&(r.camera.clone(), r.frame));
        state.store.insert_image(&row.id, r, d).await?;
    }
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

/// `GET /v1/sessions/{id}/check`: the capture check (409 until every image awaiting
/// detection is detected; the session view shows the partial check meanwhile).
pub async fn check(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(id): Path<String>,
) -> Result<Json<Value>, ApiError> {
    let row = session_or_404(&state.store, &tenant, &id).await?;
    if check_complete(&row) {
        let text = row.capture_check.as_deref().unwrap_or("null");
        return Ok(Json(
            serde_json::from_str(text).map_err(ApiError::internal)?,
        ));
    }
    let session = stored_session(&row)?;
    let awaiting = to_detect(&session);
    let expected = awaiting.len();
    let counts = state.store.detection_counts(&row.id).await?;
    let received = state
        .store
        .images(&row.id)
        .await?
        .into_iter()
        .filter(|i| awaiting.contains(&(i.camera.clone(), i.frame)))
        .count();
    let detail = if received > counts.queued as usize {
        // Stored before this service detected images at upload (migration 0007).
        format!(
            "{} of the {expected} images awaiting detection were uploaded before images were detected at upload; the session's job detects them, and the check is not computed for this session",
            received - counts.queued as usize
        )
    } else if expected == 0 && !image_slots(&session).is_empty() {
        "the capture check runs on detections; this session's images show targets this build does not detect (it detects AprilTag, AprilGrid and line targets)".to_string()
    } else if expected == 0 {
        "the capture check runs on detections; this session has none and no image to detect"
            .to_string()
    } else {
        format!(
            "{} of {expected} images detected ({received} of {expected} received); the check is complete when every image is detected (GET /v1/sessions/{}/events follows it)",
            counts.done + counts.failed,
            row.id
        )
    };
    Err(ApiError::new(
        StatusCode::CONFLICT,
        "check-not-ready",
        detail,
    ))
}

/// `GET /v1/sessions/{id}/events`: server-sent events as the session's images are
/// detected (`image`) and its capture check recomputed (`check`, with `complete`);
/// resumable with `Last-Event-ID`. The stream ends once the check is complete (at once
/// for a session with nothing to detect).
pub async fn events(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, ApiError> {
    let row = session_or_404(&state.store, &tenant, &id).await?;
    let session = stored_session(&row)?;
    let nothing_to_detect = awaiting_detection(&session).is_empty();
    let latest = state.store.last_session_event_id().await?;
    let last = super::jobs::last_event_id(&headers, latest)?.unwrap_or(0);
    let slot = state.events.open(&tenant.id)?;
    let source = SessionEvents {
        store: state.store.clone(),
        id,
        nothing_to_detect,
    };
    let stream = super::events::follow(slot, state.shutdown.clone(), last, source);
    Ok(Sse::new(stream).keep_alive(KeepAlive::new().interval(Duration::from_secs(15))))
}

/// A session's detection events; it has ended once its check is complete (at once
/// when it has nothing to detect).
struct SessionEvents {
    store: Store,
    id: String,
    nothing_to_detect: bool,
}

impl super::events::EventSource for SessionEvents {
    type Event = crate::store::detections::SessionEvent;
    async fn after(&self, last: i64) -> sqlx::Result<Vec<Self::Event>> {
        self.store.session_events_after(&self.id, last).await
    }
    async fn ended(&self) -> bool {
        self.nothing_to_detect
            || matches!(self.store.session_by_id(&self.id).await, Ok(Some(r)) if check_complete(&r))
    }
}

/// `PUT /v1/sessions/{id}/images/{camera}/{frame}`: one image, idempotent.
pub async fn put_image(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path((id, camera, frame)): Path<(String, String, String)>,
    body: Body,
) -> Result<Json<Value>, ApiError> {
    let body = ApiError::read_body(body, state.config.max_image_bytes).await?;
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
    let ((w, h), max_px) = (slot.size, state.config.worker.max_image_pixels);
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
    let blobs = state.store.blobs.clone();
    let staged = tokio::task::spawn_blocking(move || blobs.stage(&mut &body[..], u64::MAX))
        .await
        .map_err(ApiError::internal)?
        .map_err(|e| match e {
            StageError::Read(e) => ApiError::internal(e),
            StageError::Store(e) => ApiError::storage(e),
        })?;
    store_images(&state.store, &row.id, &session, vec![(slot, meta, staged)]).await?;
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
    body: Body,
) -> Result<Json<Value>, ApiError> {
    let row = session_or_404(&state.store, &tenant, &id).await?;
    let session = stored_session(&row)?;
    let ct = content_type(&headers);
    if !ArchiveKind::may_be(&ct) {
        return Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported-media-type",
            format!("Content-Type application/x-tar or application/zip, got {ct}"),
        )
        .field("Content-Type"));
    }
    let _slot = archive_slot(&state)?;
    let mut unpacked = read_archive(&state, &ct, body).await?;
    let prefix = match unpacked.take_manifest() {
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
    let max_px = state.config.worker.max_image_pixels;
    let s2 = session.clone();
    let images =
        tokio::task::spawn_blocking(move || inspect_archive_images(&s2, unpacked, &prefix, max_px))
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
    for (slot, _, staged) in &images {
        if let Some(sha) = existing.get(&(slot.camera.clone(), slot.frame)) {
            if *sha != staged.sha256 {
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
    store_images(&state.store, &row.id, &session, images).await?;
    Ok(Json(view(&state.store, &row, &session).await?))
}

impl From<InputError> for ApiError {
    fn from(e: InputError) -> Self {
        ApiError::invalid(e)
    }
}
