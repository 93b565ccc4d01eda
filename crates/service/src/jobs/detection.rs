//! Detection at upload: workers detect each uploaded image as it arrives (before they
//! take jobs: an image is short work and feeds the operator's capture check), keep the
//! outcome for the job, and recompute the session's capture check as outcomes land, so
//! the check is complete moments after the last image of a capture instead of after a
//! whole solve.

use super::worker::WorkerConfig;
use crate::store::blob::BlobStore;
use crate::store::detections::{DetectionTask, StoredDetection};
use crate::store::Store;
use futures::stream::{FuturesUnordered, StreamExt};
use rigcal_calib::check::{capture_check, CaptureCheck};
use rigcal_core::result::DetectionQuality;
use rigcal_core::session::{parse_session, ImageSlot, Session};
use rigcal_engine::pipeline::detection::{
    awaiting_detection, detect_image, detector_name, merge_detections, reusable_for,
    DetectionFailure, ImageDetection,
};
use rigcal_engine::pipeline::ImageSource;
use serde_json::json;
use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// A session's uploaded images, read from the blob store by (camera, frame), with the
/// detections made at upload that the job may reuse (same bytes, this build's detector).
pub struct BlobSource {
    pub blobs: BlobStore,
    pub max_pixels: u64,
    pub by_slot: HashMap<(String, i64), String>,
    pub detected: HashMap<(String, i64), ImageDetection>,
}

impl BlobSource {
    /// The source of `session_id`'s images, with its reusable detections: those of an
    /// image whose bytes are still stored (a lost image fails the job `input_missing`
    /// as it would without a kept detection: the job's bundle must be able to replay it).
    /// Only outcomes that serve a job of `quality` are offered.
    pub async fn of(
        store: &Store,
        session_id: &str,
        max_pixels: u64,
        quality: DetectionQuality,
    ) -> Result<Self, String> {
        let by_slot: HashMap<(String, i64), String> = store
            .images(session_id)
            .await
            .map_err(|e| e.to_string())?
            .into_iter()
            .map(|r| ((r.camera, r.frame), r.sha256))
            .collect();
        let mut detected = HashMap::new();
        for d in store
            .detections(session_id)
            .await
            .map_err(|e| e.to_string())?
        {
            let key = (d.camera.clone(), d.frame);
            let Some(sha) = by_slot.get(&key) else {
                continue;
            };
            let Some(outcome) = reusable(&d, sha, quality) else {
                continue;
            };
            if store.blobs.contains(sha).await.map_err(|e| e.to_string())? {
                detected.insert(key, outcome);
            }
        }
        Ok(BlobSource {
            blobs: store.blobs.clone(),
            max_pixels,
            by_slot,
            detected,
        })
    }
}

/// A stored outcome a job of `quality` may use in place of detecting: of these bytes,
/// of this build's detector at a quality that serves the job's, and one that parses (one that does not is detected again, and the
/// disagreement logged: it is ours, not the client's).
fn reusable(
    d: &StoredDetection,
    sha256: &str,
    quality: DetectionQuality,
) -> Option<ImageDetection> {
    if d.sha256 != sha256 || !reusable_for(&d.detector, quality) {
        return None;
    }
    let doc = d.outcome.as_ref().ok()?;
    match serde_json::from_str::<ImageDetection>(doc) {
        Ok(o) => Some(o),
        Err(e) => {
            tracing::error!(
                "internal error: a stored detection of {} frame {} does not parse ({e}); detecting it again",
                d.camera,
                d.frame
            );
            None
        }
    }
}

impl ImageSource for BlobSource {
    fn read(&self, slot: &ImageSlot) -> Result<Vec<u8>, String> {
        let sha = self
            .by_slot
            .get(&(slot.camera.clone(), slot.frame))
            .ok_or_else(|| format!("{} was never uploaded", slot.field))?;
        self.blobs
            .get(sha)
            .map_err(|e| format!("stored image {sha} unreadable: {e}"))
    }

    fn detected(&self, slot: &ImageSlot) -> Option<ImageDetection> {
        self.detected
            .get(&(slot.camera.clone(), slot.frame))
            .cloned()
    }

    fn max_pixels(&self) -> u64 {
        self.max_pixels
    }
}

/// How often a session's partial capture check is recomputed while its images are
/// being detected (the check reconstructs trajectories: once per image would cost more
/// than the detections). The check that covers the last uploaded image is computed at
/// once.
const REFRESH_EVERY: Duration = Duration::from_secs(1);

/// A worker's sessions whose stored check is behind their detections.
#[derive(Default)]
pub struct Refreshes {
    last: HashMap<String, Instant>,
    behind: HashSet<String>,
}

impl Refreshes {
    /// Recompute the checks that are behind: all of them when `all` (the worker is
    /// idle), else those last computed over [`REFRESH_EVERY`] ago or with no image
    /// left to detect.
    async fn run(&mut self, store: &Store, all: bool) -> sqlx::Result<()> {
        let behind: Vec<String> = self.behind.iter().cloned().collect();
        for id in behind {
            let due = all
                || self
                    .last
                    .get(&id)
                    .is_none_or(|t| t.elapsed() >= REFRESH_EVERY)
                || {
                    let c = store.detection_counts(&id).await?;
                    c.done + c.failed == c.queued
                };
            if !due {
                continue;
            }
            self.behind.remove(&id);
            self.last.insert(id.clone(), Instant::now());
            if let Some(row) = store.session_by_id(&id).await? {
                match parse_session(row.manifest.as_bytes()) {
                    Ok(session) => refresh_check(store, &id, session).await?,
                    Err(e) => {
                        tracing::error!(session = %id, "internal error: the stored session no longer validates ({}: {})", e.field, e.expected)
                    }
                }
            }
        }
        // Forget sessions not touched for a while.
        self.last.retain(|_, t| t.elapsed() < REFRESH_EVERY * 60);
        Ok(())
    }
}

/// Uploaded images a worker detects in one turn before it looks at the job queue: a job
/// submitted while a fleet's uploads keep arriving waits for at most this many images
/// (a few seconds at 1080p), not for every image uploaded meanwhile. A job's own
/// detection reuses what was detected already, so the images left wait little longer.
pub const IMAGES_PER_TURN: usize = 16;

/// Detect pending uploaded images (with `cfg`'s lease, image budget, quality and
/// backoff), up to `limit` at once on blocking threads, claiming
/// the next as soon as one ends (so no core waits for the slowest image of a batch),
/// until none is pending or [`IMAGES_PER_TURN`] were claimed; record each outcome and
/// recompute the capture checks that are due (see [`Refreshes`]). Returns how many were
/// detected (0: nothing to do; the checks still behind are brought up to date then).
pub async fn run_batch(
    name: &str,
    store: &Store,
    cfg: &WorkerConfig,
    limit: usize,
    refreshes: &mut Refreshes,
) -> sqlx::Result<usize> {
    let lease_ms = cfg.lease.as_millis() as i64;
    let backoff_ms = cfg.backoff.as_millis() as i64;
    let (max_pixels, quality) = (cfg.max_image_pixels, cfg.upload_detect_quality);
    // Each session parsed once while its images are being detected.
    let mut sessions: HashMap<String, Result<Arc<Session>, String>> = HashMap::new();
    let mut running = FuturesUnordered::new();
    let mut done = 0;
    let mut claimed = 0;
    let mut drained = false;
    loop {
        while !drained && running.len() < limit && claimed < IMAGES_PER_TURN {
            let tasks = store.claim_detections(name, lease_ms, 1).await?;
            if tasks.is_empty() {
                drained = true;
                break;
            }
            // Every task the claim returned is run: a leased row left aside would wait
            // out its lease.
            for task in tasks {
                claimed += 1;
                if !sessions.contains_key(&task.session_id) {
                    let parsed = load_session(store, &task.session_id).await?;
                    sessions.insert(task.session_id.clone(), parsed);
                }
                let session = sessions[&task.session_id].clone();
                let blobs = store.blobs.clone();
                running.push(async move {
                    let t = task.clone();
                    let outcome = tokio::task::spawn_blocking(move || {
                        detect_one(&t, session, &blobs, max_pixels, quality)
                    })
                    .await
                    .unwrap_or_else(|e| {
                        Err(format!("internal error: the detection task failed: {e}"))
                    });
                    (task, outcome)
                });
            }
        }
        let Some((task, outcome)) = running.next().await else {
            break;
        };
        done += 1;
        let (doc, event) = match &outcome {
            Ok(d) => match serde_json::to_string(d) {
                Ok(doc) => (Ok(doc), image_event(&task, Some(d), None)),
                Err(e) => {
                    let why = format!("internal error: the outcome did not serialise: {e}");
                    let ev = image_event(&task, None, Some(&why));
                    (Err(why), ev)
                }
            },
            Err(why) => (Err(why.clone()), image_event(&task, None, Some(why))),
        };
        if let Err(why) = &doc {
            tracing::warn!(session = %task.session_id, camera = %task.camera, frame = task.frame, attempt = task.attempts, "detection at upload gave no outcome: {why}");
        }
        let doc = doc.as_deref().map_err(String::as_str);
        if store
            .finish_detection(
                &task,
                name,
                &detector_name(quality),
                doc,
                &event,
                backoff_ms,
            )
            .await?
            && sessions[&task.session_id].is_ok()
        {
            refreshes.behind.insert(task.session_id.clone());
        }
        // The images still running go on on their threads while a check is computed.
        refreshes.run(store, false).await?;
    }
    if done == 0 {
        refreshes.run(store, true).await?;
    }
    Ok(done)
}

async fn load_session(store: &Store, id: &str) -> sqlx::Result<Result<Arc<Session>, String>> {
    Ok(match store.session_by_id(id).await? {
        Some(row) => parse_session(row.manifest.as_bytes())
            .map(Arc::new)
            .map_err(|e| {
                format!(
                    "internal error: the stored session no longer validates ({}: {})",
                    e.field, e.expected
                )
            }),
        None => Err("internal error: the image's session no longer exists".into()),
    })
}

/// Detect one task's image. `Err` when the image gave no outcome to keep: its bytes
/// could not be read, its session is unusable, or the detector panicked (each retried
/// by another claim, up to the attempt limit).
fn detect_one(
    task: &DetectionTask,
    session: Result<Arc<Session>, String>,
    blobs: &BlobStore,
    max_pixels: u64,
    quality: DetectionQuality,
) -> Result<ImageDetection, String> {
    let session = session?;
    let slot = awaiting_detection(&session)
        .into_iter()
        .find(|s| s.camera == task.camera && s.frame == task.frame)
        .ok_or_else(|| {
            format!(
                "internal error: camera {} frame {} is not an image awaiting detection in its session",
                task.camera, task.frame
            )
        })?;
    let source = BlobSource {
        blobs: blobs.clone(),
        max_pixels,
        by_slot: HashMap::from([((task.camera.clone(), task.frame), task.sha256.clone())]),
        detected: HashMap::new(),
    };
    let out = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        detect_image(&session, &slot, &source, quality)
    }))
    .map_err(|_| "internal error: the detector panicked on this image".to_string())?;
    if out.unreadable() {
        return Err(out.report.error.clone().unwrap_or_default());
    }
    Ok(out)
}

fn image_event(
    task: &DetectionTask,
    outcome: Option<&ImageDetection>,
    error: Option<&str>,
) -> serde_json::Value {
    match outcome {
        Some(d) => json!({
            "camera": task.camera,
            "frame": task.frame,
            "field": d.report.field,
            "tags": d.report.tags,
            "points": d.report.points,
            "error": d.report.error,
        }),
        None => json!({
            "camera": task.camera,
            "frame": task.frame,
            "tags": 0,
            "points": 0,
            "error": error,
        }),
    }
}

/// Recompute `session`'s capture check over the detections stored so far and store it
/// (with its `check` event) unless a fuller one is there already. A check that cannot be
/// computed (a bug of ours) is stored as such: `insufficient` with an `internal_error`
/// reason naming the stage, never left silently behind its detections.
pub async fn refresh_check(store: &Store, session_id: &str, session: Session) -> sqlx::Result<()> {
    let images: HashMap<(String, i64), String> = store
        .images(session_id)
        .await?
        .into_iter()
        .map(|r| ((r.camera, r.frame), r.sha256))
        .collect();
    let stored = store.detections(session_id).await?;
    let outcome = tokio::task::spawn_blocking(move || {
        let awaiting = awaiting_detection(&session);
        let expected = awaiting.len() as i64;
        let outcomes: Vec<(ImageSlot, ImageDetection)> = awaiting
            .into_iter()
            .filter_map(|slot| {
                let key = (slot.camera.clone(), slot.frame);
                let d = stored.iter().find(|d| (d.camera.clone(), d.frame) == key)?;
                let o = match &d.outcome {
                    // The check takes an outcome of either quality (`Fast` accepts both).
                    Ok(_) => reusable(d, images.get(&key)?, DetectionQuality::Fast)?,
                    Err(why) => ImageDetection::skipped(
                        &session,
                        &slot,
                        format!("the detector gave no outcome at upload: {why}"),
                    ),
                };
                Some((slot, o))
            })
            .collect();
        let detected = outcomes.len() as i64;
        (check_of(&session, outcomes), expected, detected)
    })
    .await;
    let (check, expected, detected) = match outcome {
        Ok(x) => x,
        Err(e) => {
            tracing::error!(session = %session_id, "internal error: the capture check task failed: {e}");
            return Ok(());
        }
    };
    let check = check.unwrap_or_else(|why| {
        tracing::error!(session = %session_id, "{why}");
        CaptureCheck::internal_error(why)
    });
    let check = match serde_json::to_value(&check) {
        Ok(v) => v,
        Err(e) => {
            tracing::error!(session = %session_id, "internal error: the capture check did not serialise: {e}");
            return Ok(());
        }
    };
    let text = check.to_string();
    let event = json!({
        "complete": detected == expected,
        "images_detected": detected,
        "images_expected": expected,
        "check": check,
    });
    store
        .store_check(session_id, &text, detected, expected, &event)
        .await?;
    Ok(())
}

/// The capture check of `session` with `outcomes` merged in; `Err` (an internal error,
/// with the stage that failed) when they do not make a valid session or the check fails.
fn check_of(
    session: &Session,
    outcomes: Vec<(ImageSlot, ImageDetection)>,
) -> Result<CaptureCheck, String> {
    let merged = match merge_detections(session, outcomes) {
        Ok((merged, _)) => merged,
        Err(DetectionFailure::Inconsistent { field, expected, .. }) => {
            return Err(format!(
                "internal error in the detection at upload: its detections do not make a valid session ({field}: expected {expected})"
            ))
        }
        Err(DetectionFailure::InputMissing { images, .. }) => {
            return Err(format!(
                "internal error in the detection at upload: a kept detection is of an unreadable image ({})",
                images.first().map_or("", |i| i.0.as_str())
            ))
        }
        Err(DetectionFailure::Cancelled(_)) => {
            return Err("internal error in the detection at upload: the merge was cancelled".into())
        }
    };
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| capture_check(&merged)))
        .map_err(|_| "internal error in the capture check: it panicked".to_string())
}
