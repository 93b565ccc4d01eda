//! `GET /v1/jobs/{id}/bundle`: one tar with everything a job ran on — the manifest as
//! stored (`session.json`), the images at the paths it names, the job's options and the
//! rigcal version (`job.json`) and the result (`result.json`, once there is one) — so
//! `rigcal calibrate bundle.tar` replays it offline. The tar is written to a temporary
//! file and streamed, so a session of a gigabyte of images is never held in memory.

use super::auth::AuthTenant;
use super::error::ApiError;
use super::AppState;
use axum::body::{Body, Bytes};
use axum::extract::{Path, State};
use axum::http::header;
use axum::response::{IntoResponse, Response};
use rigcal_core::session::{image_slots, parse_session};
use serde_json::json;
use std::io::Seek;
use tokio::io::AsyncReadExt;

pub async fn bundle(
    State(state): State<AppState>,
    AuthTenant(tenant): AuthTenant,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let job = state
        .queue
        .get_for(&tenant.id, &id)
        .await?
        .ok_or_else(|| ApiError::not_found("job").field("id"))?;
    let session = state
        .store
        .session_by_id(&job.session_id)
        .await?
        .ok_or_else(|| ApiError::internal("the session of a job is missing"))?;
    let parsed = parse_session(session.manifest.as_bytes()).map_err(ApiError::internal)?;
    let rows = state.store.images(&job.session_id).await?;
    let result = state.queue.result(&tenant.id, &id).await?;
    let options: serde_json::Value =
        serde_json::from_str(&job.options).map_err(ApiError::internal)?;
    let job_json = json!({
        "job_id": job.id,
        "status": job.status,
        "options": options,
        "rigcal_version": env!("CARGO_PKG_VERSION"),
    });
    // Every stored image at the path its slot names.
    let images: Vec<(String, String)> = image_slots(&parsed)
        .into_iter()
        .filter_map(|slot| {
            rows.iter()
                .find(|r| r.camera == slot.camera && r.frame == slot.frame)
                .map(|r| (slot.path, r.sha256.clone()))
        })
        .collect();
    let blobs = state.store.blobs.clone();
    let manifest = session.manifest.clone();
    let file = tokio::task::spawn_blocking(move || -> std::io::Result<std::fs::File> {
        let tmp = tempfile::NamedTempFile::new_in(blobs.tmp_dir()?)?;
        {
            let mut tar = tar::Builder::new(tmp.as_file());
            let mut add = |name: &str, bytes: &[u8]| {
                let mut h = tar::Header::new_gnu();
                h.set_size(bytes.len() as u64);
                h.set_mode(0o644);
                h.set_cksum();
                tar.append_data(&mut h, name, bytes)
            };
            add("session.json", manifest.as_bytes())?;
            add(
                "job.json",
                serde_json::to_string_pretty(&job_json)?.as_bytes(),
            )?;
            if let Some(r) = &result {
                add("result.json", r.as_bytes())?;
            }
            for (path, sha) in &images {
                add(path, &blobs.get(sha)?)?;
            }
            tar.finish()?;
        }
        // The open file outlives its name: nothing is left behind in blobs/tmp.
        let (mut file, path) = tmp.keep().map_err(|e| e.error)?;
        std::fs::remove_file(path)?;
        file.rewind()?;
        Ok(file)
    })
    .await
    .map_err(ApiError::internal)?
    .map_err(ApiError::internal)?;
    let stream = async_stream::stream! {
        let mut file = tokio::fs::File::from_std(file);
        let mut buf = vec![0u8; 1 << 16];
        loop {
            match file.read(&mut buf).await {
                Ok(0) => break,
                Ok(n) => yield Ok::<Bytes, std::io::Error>(Bytes::copy_from_slice(&buf[..n])),
                Err(e) => { yield Err(e); break; }
            }
        }
    };
    Ok((
        [
            (header::CONTENT_TYPE, "application/x-tar".to_string()),
            (
                header::CONTENT_DISPOSITION,
                format!("attachment; filename=\"rigcal-{}-bundle.tar\"", job.id),
            ),
        ],
        Body::from_stream(stream),
    )
        .into_response())
}
