//! The detection stage: every image a session names and that has no detections yet is
//! read, checked (header, size, complete decode), and searched for the session's
//! AprilTag targets; the measured corners become that frame's observations. Images run
//! in parallel over the cores. A bad image is skipped with its reason — the rest of the
//! session still calibrates — and the report lists what each image gave.

use super::{enter, Cancelled, Progress};
use crate::detect::{detect_tags, gray::Gray, DetectOptions};
use crate::imageio;
use crate::result::{DetectionReport, ImageReport};
use crate::session::{from_manifest, image_slots, ImageSlot, ObservationSpec, Session, TargetSpec};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

/// Default pixel budget of one image (the service's `--max-image-pixels`).
pub const DEFAULT_MAX_IMAGE_PIXELS: u64 = 50_000_000;

/// Where the stage reads a slot's bytes: files next to the manifest (CLI) or the
/// service's blob store.
pub trait ImageSource: Sync {
    fn read(&self, slot: &ImageSlot) -> Result<Vec<u8>, String>;

    fn max_pixels(&self) -> u64 {
        DEFAULT_MAX_IMAGE_PIXELS
    }
}

/// Images as files, paths relative to a directory (the manifest's).
pub struct DirSource(pub PathBuf);

impl ImageSource for DirSource {
    fn read(&self, slot: &ImageSlot) -> Result<Vec<u8>, String> {
        let path = self.0.join(&slot.path);
        std::fs::read(&path).map_err(|e| format!("cannot read {}: {e}", path.display()))
    }
}

/// No images available (a session of detections only).
pub struct NoImages;

impl ImageSource for NoImages {
    fn read(&self, slot: &ImageSlot) -> Result<Vec<u8>, String> {
        Err(format!("no image source for {}", slot.path))
    }
}

/// Does the session have AprilTag targets to look for?
fn has_tag_targets(session: &Session) -> bool {
    session.manifest.targets.iter().any(|t| {
        matches!(
            t,
            TargetSpec::Aprilgrid { .. } | TargetSpec::Apriltags { .. }
        )
    })
}

/// Detect what can be detected. Returns the session with observations filled in (or
/// the original, when there was nothing to do) and the report (`None` when the session
/// named no image needing detection).
pub fn detect_session(
    session: &Session,
    source: &dyn ImageSource,
    progress: &dyn Progress,
) -> Result<(Session, Option<DetectionReport>), Cancelled> {
    let pending: Vec<(usize, ImageSlot)> = image_slots(session)
        .into_iter()
        .filter_map(|s| {
            let fi = s.frame_pos?;
            let f = &session.manifest.frames[fi];
            let done = f.observations.get(&s.camera).is_some_and(|o| !o.is_empty());
            (!done).then_some((fi, s))
        })
        .collect();
    if pending.is_empty() || !has_tag_targets(session) {
        return Ok((session.clone(), None));
    }
    enter(progress, "detection")?;
    let start = Instant::now();
    let next = AtomicUsize::new(0);
    let stop = AtomicBool::new(false);
    let results: Mutex<Vec<Option<SlotOutcome>>> = Mutex::new(vec![None; pending.len()]);
    let threads = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(pending.len());
    // Workers report each finished image; this thread forwards to `progress` (which
    // is not shared across threads) and relays a cancel back.
    let (tx, rx) = std::sync::mpsc::channel::<()>();
    std::thread::scope(|s| {
        for _ in 0..threads {
            let tx = tx.clone();
            let (next, stop, results, pending) = (&next, &stop, &results, &pending);
            s.spawn(move || loop {
                if stop.load(Ordering::SeqCst) {
                    break;
                }
                let i = next.fetch_add(1, Ordering::SeqCst);
                let Some((_, slot)) = pending.get(i) else {
                    break;
                };
                let out = detect_slot(session, slot, source);
                if let Ok(mut r) = results.lock() {
                    r[i] = Some(out);
                }
                let _ = tx.send(());
            });
        }
        drop(tx);
        let mut n = 0;
        while rx.recv().is_ok() {
            n += 1;
            // The stage's share of a job is its first 5 %.
            let fraction = 0.05 * n as f64 / pending.len() as f64;
            if !progress.stage("detection", fraction) {
                stop.store(true, Ordering::SeqCst);
            }
        }
    });
    if stop.load(Ordering::SeqCst) {
        return Err(Cancelled("detection".into()));
    }
    let results = results.into_inner().unwrap_or_default();
    let mut manifest = session.manifest.clone();
    let mut images = Vec::new();
    for ((fi, slot), r) in pending.iter().zip(results) {
        let Some((report, obs)) = r else { continue };
        // Detected (or skipped with a reason): no longer an image awaiting detection.
        manifest.frames[*fi].images.remove(&slot.camera);
        if !obs.is_empty() {
            manifest.frames[*fi]
                .observations
                .insert(slot.camera.clone(), obs);
        }
        images.push(report);
    }
    let report = DetectionReport {
        images_total: images.len(),
        images_skipped: images.iter().filter(|r| r.error.is_some()).count(),
        points_total: images.iter().map(|r| r.points).sum(),
        seconds: start.elapsed().as_secs_f64(),
        images,
    };
    // The detections are ours, so the manifest still validates; if it somehow does not,
    // calibrate the original and let the report say what was found.
    let detected = from_manifest(manifest).unwrap_or_else(|_| session.clone());
    Ok((detected, Some(report)))
}

/// Decode an image for detection, with the header-first checks of uploads (format,
/// `expected` size, pixel budget, complete file). Errors read as "expected …".
pub fn decode_gray(
    bytes: &[u8],
    expected: Option<(u32, u32)>,
    max_pixels: u64,
) -> Result<Gray, String> {
    let (_, img) =
        imageio::decode(bytes, expected, max_pixels).map_err(|e| format!("expected {e}"))?;
    Ok(Gray::from_dynamic(&img))
}

/// What one image gave: its report line and its observations.
type SlotOutcome = (ImageReport, Vec<ObservationSpec>);

fn detect_slot(
    session: &Session,
    slot: &ImageSlot,
    source: &dyn ImageSource,
) -> (ImageReport, Vec<ObservationSpec>) {
    let mut report = ImageReport {
        field: slot.field.clone(),
        camera: slot.camera.clone(),
        frame: slot.frame,
        path: slot.path.clone(),
        tags: 0,
        points: 0,
        tags_from_layout: 0,
        rejected: vec![],
        error: None,
    };
    let camera = session
        .camera_index(&slot.camera)
        .map(|i| &session.cameras[i].camera);
    let outcome = source.read(slot).and_then(|bytes| {
        let gray = decode_gray(&bytes, Some(slot.size), source.max_pixels())?;
        detect_tags(
            &gray,
            &session.manifest.targets,
            camera,
            &DetectOptions::default(),
        )
    });
    match outcome {
        Ok(d) => {
            report.tags = d.tags.len();
            report.tags_from_layout = d.tags.iter().filter(|t| t.source == "layout").count();
            report.points = d.points.len();
            report.rejected = d.rejected.iter().map(|r| r.reason.clone()).collect();
            let obs = d
                .points
                .into_iter()
                .map(|p| ObservationSpec {
                    point: p.point,
                    u: p.u,
                    v: p.v,
                })
                .collect();
            (report, obs)
        }
        Err(e) => {
            report.error = Some(e);
            (report, vec![])
        }
    }
}
