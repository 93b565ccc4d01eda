//! Jobs: submit, list, show, cancel, stream progress (SSE), and read results/exports.

use super::auth::AuthTenant;
use super::error::ApiError;
use super::AppState;
use crate::jobs::acceptance::{judge, Acceptance};
use crate::jobs::queue::{JobFilter, JobRow, JobStatus};
use crate::jobs::JobOptions;
use crate::store::Tenant;
use crate::store::{now_ms, parse_rfc3339, rfc3339};
use axum::body::Bytes;
use axum::extract::{Path, RawQuery, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::Json;
use futures::Stream;
use rigcal_core::result::ResultDocument;
use rigcal_core::session::undetected_images;
use rigcal_core::session::{parse_session, InputError};
use rigcal_core::vehicle::VehicleModel;
use rigcal_engine::export::{render_in, ExportError, Format, Frame};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::convert::Infallible;
use std::time::Duration;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CreateJob {
    session_id: String,
    #[serde(default)]
    options: Option<JobOptions>,
}

/// A job as the API shows it.
#[derive(Serialize)]
pub struct JobView {
    id: String,
    session_id: String,
    vehicle_id: Option<String>,
    vehicle_model: Option<String>,
    method: String,
    status: JobStatus,
    stage: Option<String>,
    progress: f64,
    attempts: i64,
    max_attempts: i64,
    options: serde_json::Value,
    error: Option<serde_json::Value>,
    residual_rms_px: Option<f64>,
    /// Largest 1-σ over the cameras' observable extrinsic components (m, deg).
    worst_sigma_translation_m: Option<f64>,
    worst_sigma_rotation_deg: Option<f64>,
    created_at: String,
    started_at: Option<String>,
    finished_at: Option<String>,
    /// Seconds spent queued and running (so far, for unfinished jobs).
    queued_seconds: f64,
    running_seconds: Option<f64>,
    acceptance: Acceptance,
    links: JobLinks,
}

impl JobView {
    fn of(j: &JobRow, tenant: &Tenant, models: &Models) -> Self {
        let now = now_ms();
        let queued_until = j.started_at.unwrap_or(if j.is_terminal() {
            j.finished_at.unwrap_or(now)
        } else {
            now
        });
        JobView {
            id: j.id.clone(),
            session_id: j.session_id.clone(),
            vehicle_id: j.vehicle_id.clone(),
            vehicle_model: j.vehicle_model.clone(),
            method: j.method.clone(),
            status: j.status,
            stage: j.stage.clone(),
            progress: j.progress,
            attempts: j.attempts,
            max_attempts: j.max_attempts,
            options: serde_json::from_str(&j.options).unwrap_or(serde_json::Value::Null),
            error: j
                .error
                .as_deref()
                .and_then(|e| serde_json::from_str(e).ok()),
            residual_rms_px: j.residual_rms_px,
            worst_sigma_translation_m: j.worst_sigma_translation_m,
            worst_sigma_rotation_deg: j.worst_sigma_rotation_deg,
            created_at: rfc3339(j.created_at),
            started_at: j.started_at.map(rfc3339),
            finished_at: j.finished_at.map(rfc3339),
            queued_seconds: (queued_until - j.created_at).max(0) as f64 / 1000.0,
            running_seconds: j
                .started_at
                .map(|s| (j.finished_at.unwrap_or(now) - s).max(0) as f64 / 1000.0),
            acceptance: judge(
                j,
                tenant,
                j.vehicle_model.as_ref().and_then(|m| models.get(m)),
            ),
            links: JobLinks {
                self_: format!("/v1/jobs/{}", j.id),
                events: format!("/v1/jobs/{}/events", j.id),
                result: format!("/v1/jobs/{}/result", j.id),
                diagnostics: format!("/v1/jobs/{}/diagnostics", j.id),
                session: format!("/v1/sessions/{}", j.session_id),
            },
        }
    }
}

#[derive(Serialize)]
pub struct JobLinks {
    #[serde(rename = "self")]
    self_: String,
    events: String,
    result: String,
    diagnostics: String,
    session: String,
}

/// Parse a JSON body into `T`, with the field path of the first error.
pub fn json_body<T: serde::de::DeserializeOwned>(body: &[u8]) -> Result<T, ApiError> {
    if let Err(e) = serde_json::from_slice::<serde::de::IgnoredAny>(body) {
        return Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            "malformed-json",
            format!("the body is not valid JSON: {e}"),
        ));
    }
    let de = &mut serde_json::Deserializer::from_slice(body);
    serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.inner().to_string();
        // serde reports a missing field at its parent's path; the field is the missing one.
        let missing = inner
            .strip_prefix("missing field `")
            .and_then(|r| r.split_once('`'))
            .map(|(name, _)| name.to_string());
        let path = match (path.as_str(), missing) {
            (".", Some(m)) => m,
            (".", None) => "(document)".into(),
            (p, Some(m)) => format!("{p}.{m}"),
            (p, None) => p.to_string(),
        };
        ApiError::invalid(InputError::new(path, inner))
    })
}

/// The vehicle models jobs are judged against, by name.
pub type Models = std::collections::HashMap<String, VehicleModel>;

/// The models the `jobs` name (each read once).
pub async fn models_of<'a>(
    state: &AppState,
    tenant_id: &str,
    jobs: impl IntoIterator<Item = &'a JobRow>,
) -> Result<Models, ApiError> {
    let mut out = Models::new();
    for name in jobs.into_iter().filter_map(|j| j.vehicle_model.as_ref()) {
        if out.contains_key(name) {
            continue;
        }
        if let Some(row) = state.store.vehicle_model(tenant_id, name).await? {
            out.insert(name.clone(), row.document);
        }
    }
    Ok(out)
}

/// The job as the API shows it, judged against its vehicle model as stored now.
pub async fn view(state: &AppState, tenant: &Tenant, job: &JobRow) -> Result<JobView, ApiError> {
    let models = models_of(state, &tenant.id, [job]).await?;
    Ok(JobView::of(job, tenant, &models))
}

async fn job_or_404(state: &AppState, tenant: &str, id: &str) -> Result<JobRow, ApiError> {
    state
        .queue
        .get_for(tenant, id)
        .await?
        .ok_or_else(|| ApiError::not_found("job").field("id"))
}

/// `POST /v1/jobs {session_id, options}` → 202 with the queued job.
pub async fn create(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    body: Bytes,
) -> Result<Response, ApiError> {
    let req: CreateJob = json_body(&body)?;
    let options = req.options.unwrap_or_default();
    options.calib()?;
    let session = state
        .store
        .session(&tenant, &req.session_id)
        .await?
        .ok_or_else(|| {
            ApiError::new(
                StatusCode::NOT_FOUND,
                "unknown-session",
                format!(
                    "session_id: an existing session of this tenant, got {:?}",
                    req.session_id
                ),
            )
            .field("session_id")
        })?;
    let parsed = parse_session(session.manifest.as_bytes()).map_err(ApiError::internal)?;
    let have = state.store.images(&session.id).await?;
    // Images the manifest names, without detections and not uploaded yet.
    let undetected: std::collections::HashSet<String> =
        undetected_images(&parsed).into_iter().collect();
    let missing: Vec<String> = rigcal_core::session::image_slots(&parsed)
        .into_iter()
        .filter(|slot| {
            undetected.contains(&slot.field)
                && !have
                    .iter()
                    .any(|h| h.frame == slot.frame && h.camera == slot.camera)
        })
        .map(|slot| slot.field)
        .collect();
    if !missing.is_empty() {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            "session-incomplete",
            format!(
                "{} image(s) of the session are not uploaded yet, first {}",
                missing.len(),
                missing[0]
            ),
        )
        .field(missing[0].clone()));
    }
    let job = state
        .queue
        .enqueue(
            &tenant.id,
            &session.id,
            (
                session.vehicle_id.as_deref(),
                parsed.manifest.vehicle_model.as_deref(),
            ),
            &session.method,
            &serde_json::to_string(&options).map_err(ApiError::internal)?,
            state.config.max_attempts,
        )
        .await?;
    Ok((
        StatusCode::ACCEPTED,
        [(header::LOCATION, format!("/v1/jobs/{}", job.id))],
        Json(view(&state, &tenant, &job).await?),
    )
        .into_response())
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct ListQuery {
    status: Option<String>,
    vehicle_id: Option<String>,
    method: Option<String>,
    created_after: Option<String>,
    created_before: Option<String>,
    limit: Option<String>,
    offset: Option<String>,
}

fn parse_filter(raw: Option<&str>) -> Result<JobFilter, ApiError> {
    let q: ListQuery = ApiError::parse_query(
        raw,
        "status, vehicle_id, method, created_after, created_before, limit, offset",
    )?;
    let bad = |field: &str, expected: String| ApiError::invalid(InputError::new(field, expected));
    let status = match &q.status {
        None => None,
        Some(s) => Some(JobStatus::parse(s).ok_or_else(|| {
            let known: Vec<&str> = JobStatus::ALL.iter().map(|s| s.as_str()).collect();
            bad("status", format!("one of {}, got {s:?}", known.join(", ")))
        })?),
    };
    if let Some(m) = &q.method {
        if m != "motion" && m != "vanishing" {
            return Err(bad("method", format!("motion or vanishing, got {m:?}")));
        }
    }
    let time = |field: &str, v: &Option<String>| -> Result<Option<i64>, ApiError> {
        v.as_deref()
            .map(|s| {
                parse_rfc3339(s).ok_or_else(|| {
                    bad(
                        field,
                        format!("an RFC 3339 time such as 2026-11-23T08:00:00Z, got {s:?}"),
                    )
                })
            })
            .transpose()
    };
    let int = |field: &str,
               v: &Option<String>,
               default: i64,
               lo: i64,
               hi: i64|
     -> Result<i64, ApiError> {
        match v.as_deref() {
            None => Ok(default),
            Some(s) => match s.parse::<i64>() {
                Ok(n) if (lo..=hi).contains(&n) => Ok(n),
                _ => Err(bad(
                    field,
                    format!("an integer from {lo} to {hi}, got {s:?}"),
                )),
            },
        }
    };
    Ok(JobFilter {
        status,
        vehicle_id: q.vehicle_id,
        method: q.method,
        created_after: time("created_after", &q.created_after)?,
        created_before: time("created_before", &q.created_before)?,
        limit: int("limit", &q.limit, 50, 1, 500)?,
        offset: int("offset", &q.offset, 0, 0, i64::MAX / 2)?,
    })
}

/// `GET /v1/jobs`: newest first, filtered, paginated (`limit`, `offset`, `total`).
pub async fn list(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    RawQuery(raw): RawQuery,
) -> Result<Json<Value>, ApiError> {
    let f = parse_filter(raw.as_deref())?;
    let (rows, total) = state.queue.list(&tenant.id, &f).await?;
    let models = models_of(&state, &tenant.id, &rows).await?;
    Ok(Json(json!({
        "jobs": rows.iter().map(|j| JobView::of(j, &tenant, &models)).collect::<Vec<_>>(),
        "total": total,
        "limit": f.limit,
        "offset": f.offset,
    })))
}

pub async fn show(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(id): Path<String>,
) -> Result<Json<JobView>, ApiError> {
    let job = job_or_404(&state, &tenant.id, &id).await?;
    Ok(Json(view(&state, &tenant, &job).await?))
}

/// `DELETE /v1/jobs/{id}`: cancel (at once when queued; between stages when running).
pub async fn cancel(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let job = job_or_404(&state, &tenant.id, &id).await?;
    if job.is_terminal() {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            "job-finished",
            format!("the job already ended ({}); nothing to cancel", job.status),
        ));
    }
    let job = state
        .queue
        .cancel(&tenant.id, &id)
        .await?
        .ok_or_else(|| ApiError::not_found("job"))?;
    Ok((
        StatusCode::ACCEPTED,
        Json(view(&state, &tenant, &job).await?),
    )
        .into_response())
}

/// The event a stream resumes after: `Last-Event-ID` as a non-negative integer no
/// later than the newest event stored (anything else would start the stream somewhere
/// the client did not ask for: from now, from the beginning, or never), `None` without
/// the header.
pub(super) fn last_event_id(headers: &HeaderMap, latest: i64) -> Result<Option<i64>, ApiError> {
    let Some(value) = headers.get("last-event-id") else {
        return Ok(None);
    };
    let bad = |detail: String| {
        ApiError::new(StatusCode::BAD_REQUEST, "invalid-field", detail).field("Last-Event-ID")
    };
    let n: i64 = value
        .to_str()
        .ok()
        .map(str::trim)
        .filter(|s| !s.is_empty() && s.len() <= 19 && s.bytes().all(|b| b.is_ascii_digit()))
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| bad("a non-negative integer, the id of an event this server sent".into()))?;
    if n > latest {
        return Err(bad(format!(
            "an event id this server sent (the latest is {latest}), got {n}"
        )));
    }
    Ok(Some(n))
}

/// [`last_event_id`] of the job events.
async fn resume_after(state: &AppState, headers: &HeaderMap) -> Result<Option<i64>, ApiError> {
    if headers.get("last-event-id").is_none() {
        return Ok(None);
    }
    last_event_id(headers, state.queue.last_event_id().await?)
}

/// `GET /v1/jobs/{id}/events`: server-sent events, one per stored job event, resumable
/// with `Last-Event-ID`; the stream ends after the job's terminal event.
pub async fn events(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, ApiError> {
    job_or_404(&state, &tenant.id, &id).await?;
    let last: i64 = resume_after(&state, &headers).await?.unwrap_or(0);
    let slot = state.events.open(&tenant.id)?;
    let source = JobEvents {
        queue: state.queue.clone(),
        id,
    };
    let stream = super::events::follow(slot, state.shutdown.clone(), last, source);
    Ok(Sse::new(stream).keep_alive(KeepAlive::new().interval(Duration::from_secs(15))))
}

/// A job's events; it has ended once its status is terminal.
struct JobEvents {
    queue: crate::jobs::queue::Queue,
    id: String,
}

impl super::events::EventSource for JobEvents {
    type Event = crate::jobs::queue::EventRow;
    async fn after(&self, last: i64) -> sqlx::Result<Vec<Self::Event>> {
        self.queue.events_after(&self.id, last).await
    }
    async fn ended(&self) -> bool {
        matches!(self.queue.get(&self.id).await, Ok(Some(j)) if j.is_terminal())
    }
}

/// `GET /v1/events`: server-sent events of every job of the tenant (`job` events: the
/// job id, status, stage, progress), from now on, or after `Last-Event-ID`. One stream
/// keeps a whole jobs table live; it never ends by itself, only with the client or the
/// server's shutdown.
pub async fn tenant_events(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    headers: HeaderMap,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, ApiError> {
    let resume = resume_after(&state, &headers).await?;
    let mut last = match resume {
        Some(n) => n,
        None => state.queue.last_event_id().await?,
    };
    let mut slot = state.events.open(&tenant.id)?;
    let queue = state.queue.clone();
    let mut shutdown = state.shutdown.clone();
    let stream = async_stream::stream! {
        // First a `ready` event carrying the cursor, so a client that loads the table
        // after it knows it missed nothing.
        yield Ok(Event::default().id(last.to_string()).event("ready").data(json!({"last_event_id": last}).to_string()));
        loop {
            if *shutdown.borrow() {
                break;
            }
            let events = match queue.tenant_events_after(&tenant.id, last, 500).await {
                Ok(e) => e,
                Err(_) => break,
            };
            for e in events {
                last = e.id;
                let data = serde_json::to_string(&e).unwrap_or_default();
                yield Ok(Event::default().id(e.id.to_string()).event("job").data(data));
            }
            tokio::select! {
                _ = slot.changed() => {},
                _ = shutdown.changed() => {},
            }
        }
    };
    Ok(Sse::new(stream).keep_alive(KeepAlive::new().interval(Duration::from_secs(15))))
}

pub(super) async fn document(
    state: &AppState,
    tenant: &str,
    id: &str,
) -> Result<(JobRow, String), ApiError> {
    let job = job_or_404(state, tenant, id).await?;
    match state.queue.result(tenant, id).await? {
        Some(doc) => Ok((job, doc)),
        None if !job.is_terminal() => Err(ApiError::new(
            StatusCode::CONFLICT,
            "result-not-ready",
            format!(
                "the job is {} (stage {}); the result exists once it ends",
                job.status,
                job.stage.as_deref().unwrap_or("-")
            ),
        )),
        None => Err(ApiError::new(
            StatusCode::CONFLICT,
            "no-result",
            format!(
                "the job ended {} without a result document{}",
                job.status,
                job.error
                    .as_deref()
                    .and_then(|e| serde_json::from_str::<Value>(e).ok())
                    .and_then(|e| e["detail"].as_str().map(|d| format!(": {d}")))
                    .unwrap_or_default()
            ),
        )),
    }
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct ResultQuery {
    format: Option<String>,
    camera: Option<String>,
    frame: Option<String>,
}

/// `GET /v1/jobs/{id}/result[?format=json|kalibr|opencv|urdf|colmap|ros2|camera_info[&camera=ID]]`.
pub async fn result(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(id): Path<String>,
    RawQuery(raw): RawQuery,
) -> Result<Response, ApiError> {
    let q: ResultQuery = ApiError::parse_query(raw.as_deref(), "format, camera, frame")?;
    let format: Format = match q.format.as_deref() {
        None => Format::Json,
        Some(f) => f.parse().map_err(|_| {
            ApiError::invalid(InputError::new(
                "format",
                format!("{}, got {f:?}", Format::expected()),
            ))
        })?,
    };
    let vehicle_frame = match q.frame.as_deref() {
        None | Some("reference") => false,
        Some("vehicle") => true,
        Some(other) => {
            return Err(ApiError::invalid(InputError::new(
                "frame",
                format!(
                    "reference or vehicle, got {}",
                    rigcal_core::session::quoted_prefix(other)
                ),
            )))
        }
    };
    let (job, text) = document(&state, &tenant.id, &id).await?;
    let models = models_of(&state, &tenant.id, [&job]).await?;
    let model = job.vehicle_model.as_ref().and_then(|m| models.get(m));
    if format == Format::Json && q.camera.is_none() && !vehicle_frame {
        let Some(nominal) = judge(&job, &tenant, model).nominal else {
            return Ok(([(header::CONTENT_TYPE, "application/json")], text).into_response());
        };
        // The stored document with the verdict against the vehicle model as it is now.
        let mut doc: Value = serde_json::from_str(&text).map_err(ApiError::internal)?;
        doc["nominal"] = serde_json::to_value(nominal).map_err(ApiError::internal)?;
        return Ok(Json(doc).into_response());
    }
    let frame = if vehicle_frame {
        let v = model.and_then(VehicleModel::vehicle_from_ref).ok_or_else(|| {
            ApiError::invalid(InputError::new(
                "frame",
                match &job.vehicle_model {
                    None => "reference: the job's session names no vehicle_model, so there is no vehicle frame".to_string(),
                    Some(m) => format!("reference: vehicle model {m} defines no vehicle_from_ref"),
                },
            ))
        })?;
        Frame::Vehicle(v)
    } else {
        Frame::Reference
    };
    let doc: ResultDocument = serde_json::from_str(&text).map_err(ApiError::internal)?;
    let session = state
        .store
        .session_by_id(&job.session_id)
        .await?
        .ok_or_else(|| ApiError::internal("session of a job missing"))?;
    let session = parse_session(session.manifest.as_bytes()).map_err(ApiError::internal)?;
    let (ct, ext) = format.media();
    let name = format.as_str();
    match render_in(&doc, &session, format, q.camera.as_deref(), frame) {
        Ok(out) => Ok((
            [
                (header::CONTENT_TYPE, ct.to_string()),
                (
                    header::CONTENT_DISPOSITION,
                    format!(
                        "attachment; filename=\"rigcal-{}-{name}{}{}.{ext}\"",
                        &job.id,
                        q.camera.as_deref().map_or(String::new(), |c| format!("-{c}")),
                        if vehicle_frame { "-vehicle" } else { "" }
                    ),
                ),
            ],
            out,
        )
            .into_response()),
        Err(ExportError::NothingToExport) => Err(ApiError::new(
            StatusCode::CONFLICT,
            "nothing-to-export",
            format!("the calibration {}: nothing to export (a failed calibration is exported as its JSON result only, which says why)", doc.status.as_str()),
        )),
        Err(ExportError::Unrepresentable(why)) => Err(ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "unexportable",
            format!("format {name}: {why}"),
        )
        .field("format")),
        Err(ExportError::Camera(why)) => Err(ApiError::invalid(InputError::new("camera", why))),
    }
}

/// `GET /v1/jobs/{id}/diagnostics`: residuals per camera and frame, histogram, outliers,
/// stages, solver and singularity report.
pub async fn diagnostics(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(id): Path<String>,
) -> Result<Json<Value>, ApiError> {
    let (job, text) = document(&state, &tenant.id, &id).await?;
    let doc: Value = serde_json::from_str(&text).map_err(ApiError::internal)?;
    Ok(Json(json!({
        "job_id": job.id,
        "status": doc["status"],
        "reasons": doc["reasons"],
        "residuals": doc.get("residuals").cloned().unwrap_or(Value::Null),
        "singularity": doc.get("singularity").cloned().unwrap_or(Value::Null),
        "solver": doc.get("solver").cloned().unwrap_or(Value::Null),
        "stages": doc["stages"],
    })))
}
