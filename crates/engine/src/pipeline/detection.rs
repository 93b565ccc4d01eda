//! The detection stage: every image a session names and that has no detections yet is
//! read, checked (header, size, complete decode), and searched for the session's
//! AprilTag targets; the measured corners become that frame's observations. Images run
//! in parallel over the cores. A bad image is skipped with its reason — the rest of the
//! session still calibrates — and the report lists what each image gave.

use super::{enter, Cancelled, Progress};
use rigcal_core::result::{DetectionQuality, DetectionReport, ImageReport};
use rigcal_core::session::{
    from_manifest, image_slots, ImageSlot, LineSpec, Method, ObservationSpec, Session, TargetSpec,
};
use rigcal_core::target::line_layout::{LineLayout, Print as LinePrint};
use rigcal_detect::imageio;
use rigcal_detect::linegrid::detect_line_grids;
use rigcal_detect::linetarget::detect_line_targets;
use rigcal_detect::refine::Lens;
use rigcal_detect::{detect_tags, gray::Gray, DetectOptions};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

/// The detector a stored [`ImageDetection`] came from: outcomes of another build are
/// never reused, since its corners may differ.
pub const DETECTOR_VERSION: &str = concat!("rigcal-detect-", env!("CARGO_PKG_VERSION"));

/// The detector name an outcome detected at `quality` is kept under:
/// [`DETECTOR_VERSION`] for `accurate` (the name every outcome had before there was a
/// choice), `+fast` after it for `fast`.
pub fn detector_name(quality: DetectionQuality) -> String {
    match quality {
        DetectionQuality::Accurate => DETECTOR_VERSION.to_string(),
        DetectionQuality::Fast => format!("{DETECTOR_VERSION}+fast"),
    }
}

/// Whether an outcome kept under `detector` may stand in for detecting at `quality`: it
/// is this build's, at that quality or a better one (an `accurate` outcome serves a
/// `fast` job, never the other way round).
pub fn reusable_for(detector: &str, quality: DetectionQuality) -> bool {
    detector == detector_name(DetectionQuality::Accurate)
        || (quality == DetectionQuality::Fast && detector == detector_name(DetectionQuality::Fast))
}

/// Default pixel budget of one image (the service's `--max-image-pixels`).
pub const DEFAULT_MAX_IMAGE_PIXELS: u64 = 50_000_000;

/// Where the stage reads a slot's bytes: files next to the manifest (CLI) or the
/// service's blob store. An error here means the input is not available (a missing
/// file, a lost blob, a storage failure): the job fails with `input_missing` naming the
/// images, never with a verdict on a capture it could not read. (Bytes that are there
/// but do not decode are the capture's fault: that image is skipped with its reason.)
pub trait ImageSource: Sync {
    fn read(&self, slot: &ImageSlot) -> Result<Vec<u8>, String>;

    /// What [`detect_image`] already gave for this slot's bytes, when the source kept it
    /// (the service detects images as they are uploaded). The stage then uses it instead
    /// of decoding the image again. A source must only offer an outcome of these exact
    /// bytes, of this build's detector ([`DETECTOR_VERSION`]) and of a quality that
    /// serves the job's ([`reusable_for`]); anything else is detected afresh.
    fn detected(&self, _slot: &ImageSlot) -> Option<ImageDetection> {
        None
    }

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

/// Images held in memory by the path the manifest names them with (benches, tests).
pub struct MemorySource(pub std::collections::HashMap<String, Vec<u8>>);

impl ImageSource for MemorySource {
    fn read(&self, slot: &ImageSlot) -> Result<Vec<u8>, String> {
        self.0
            .get(&slot.path)
            .cloned()
            .ok_or_else(|| format!("no image {}", slot.path))
    }
}

/// No images available (a session of detections only).
pub struct NoImages;

impl ImageSource for NoImages {
    fn read(&self, slot: &ImageSlot) -> Result<Vec<u8>, String> {
        Err(format!("no image source for {}", slot.path))
    }
}

/// Whether this build can detect the session's targets: AprilTag boards, or the line
/// targets of a vanishing session.
fn detectable(session: &Session) -> bool {
    session.manifest.method == Method::Vanishing
        || session.manifest.targets.iter().any(|t| {
            matches!(
                t,
                TargetSpec::Aprilgrid { .. } | TargetSpec::Apriltags { .. }
            )
        })
}

/// Why the stage produced no session to calibrate.
#[derive(Debug)]
pub enum DetectionFailure {
    Cancelled(Cancelled),
    /// The detections did not make a valid session: a bug of this stage (it must only
    /// emit what the session validation accepts), reported as such with the field the
    /// validation refused, never replaced by the undetected session.
    Inconsistent {
        field: String,
        expected: String,
        report: DetectionReport,
    },
    /// Images whose bytes could not be read (field paths, with why).
    InputMissing {
        images: Vec<(String, String)>,
        report: DetectionReport,
    },
}

impl From<Cancelled> for DetectionFailure {
    fn from(c: Cancelled) -> Self {
        DetectionFailure::Cancelled(c)
    }
}

/// The image slots of a session that detection would fill: those whose frame (or ring
/// entry) has no detections yet, for targets this build can detect (none otherwise).
/// One definition for the detection stage and for detection at upload.
pub fn awaiting_detection(session: &Session) -> Vec<ImageSlot> {
    if !detectable(session) {
        return vec![];
    }
    image_slots(session)
        .into_iter()
        .filter(|s| match s.frame_pos {
            Some(fi) => {
                let f = &session.manifest.frames[fi];
                !(f.observations.get(&s.camera).is_some_and(|o| !o.is_empty())
                    || f.lines.get(&s.camera).is_some_and(|l| !l.is_empty()))
            }
            // A ring image (vanishing method): its slot's frame is the ring index.
            None => session
                .manifest
                .ring
                .iter()
                .find(|r| r.index == s.frame)
                .is_some_and(|r| r.lines.is_empty()),
        })
        .collect()
}

/// Detect what can be detected. Returns the session with observations filled in (or
/// the original, when there was nothing to do) and the report (`None` when the session
/// named no image needing detection).
pub fn detect_session(
    session: &Session,
    source: &dyn ImageSource,
    quality: DetectionQuality,
    progress: &dyn Progress,
) -> Result<(Session, Option<DetectionReport>), DetectionFailure> {
    let pending = awaiting_detection(session);
    if pending.is_empty() {
        return Ok((session.clone(), None));
    }
    enter(progress, "detection")?;
    let start = Instant::now();
    let next = AtomicUsize::new(0);
    let stop = AtomicBool::new(false);
    let reused = AtomicUsize::new(0);
    let results: Mutex<Vec<Option<ImageDetection>>> = Mutex::new(vec![None; pending.len()]);
    let threads = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(pending.len());
    // Workers report each finished image; this thread forwards to `progress` (which
    // is not shared across threads) and relays a cancel back.
    let (tx, rx) = std::sync::mpsc::channel::<()>();
    std::thread::scope(|s| {
        for _ in 0..threads {
            let tx = tx.clone();
            let (next, stop, results, pending, reused) =
                (&next, &stop, &results, &pending, &reused);
            s.spawn(move || loop {
                if stop.load(Ordering::SeqCst) {
                    break;
                }
                let i = next.fetch_add(1, Ordering::SeqCst);
                let Some(slot) = pending.get(i) else {
                    break;
                };
                let out = match source.detected(slot) {
                    Some(kept) => {
                        reused.fetch_add(1, Ordering::SeqCst);
                        kept
                    }
                    None => detect_image(session, slot, source, quality),
                };
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
        return Err(Cancelled("detection".into()).into());
    }
    // A worker that panicked poisons the lock: its image has no outcome and is reported
    // as not detected below (the panic itself reaches the job's error through the
    // worker's catch).
    let results = results.into_inner().unwrap_or_else(|p| p.into_inner());
    let outcomes: Vec<(ImageSlot, ImageDetection)> = pending
        .into_iter()
        .zip(results)
        .filter_map(|(slot, r)| Some((slot, r?)))
        .collect();
    let (detected, mut report) = merge_detections(session, outcomes)?;
    report.seconds = start.elapsed().as_secs_f64();
    report.images_reused = reused.into_inner();
    report.quality = quality;
    Ok((detected, Some(report)))
}

/// Put what images gave into their session: each slot's points or lines become its
/// frame's (or ring entry's) detections and the slot no longer awaits detection; slots
/// without an outcome stay as they were. Returns the session, validated again, and the
/// report of the outcomes (its `seconds` 0: the caller times the detection). An image
/// that could not be read fails the merge with `InputMissing`; detections the session
/// validation refuses fail it with `Inconsistent` (a bug of the detector).
pub fn merge_detections(
    session: &Session,
    outcomes: Vec<(ImageSlot, ImageDetection)>,
) -> Result<(Session, DetectionReport), DetectionFailure> {
    let mut manifest = session.manifest.clone();
    let mut images = Vec::new();
    for (slot, ImageDetection { report, found }) in outcomes {
        // Detected (or skipped with a reason): no longer an image awaiting detection.
        match slot.frame_pos {
            Some(fi) => {
                let Some(frame) = manifest.frames.get_mut(fi) else {
                    return Err(DetectionFailure::Inconsistent {
                        field: slot.field,
                        expected: "a frame of the session".into(),
                        report: DetectionReport::of(images),
                    });
                };
                frame.images.remove(&slot.camera);
                match found {
                    Found::Points(obs) if !obs.is_empty() => {
                        frame.observations.insert(slot.camera.clone(), obs);
                    }
                    Found::Lines(lines) if !lines.is_empty() => {
                        frame.lines.insert(slot.camera.clone(), lines);
                    }
                    _ => {}
                }
            }
            None => {
                if let Some(r) = manifest.ring.iter_mut().find(|r| r.index == slot.frame) {
                    r.image = None;
                    if let Found::Lines(lines) = found {
                        r.lines = lines;
                    }
                }
            }
        }
        images.push(report);
    }
    let unreadable: Vec<(String, String)> = images
        .iter()
        .filter(|r| r.unreadable)
        .map(|r| (r.field.clone(), r.error.clone().unwrap_or_default()))
        .collect();
    let report = DetectionReport::of(images);
    if !unreadable.is_empty() {
        return Err(DetectionFailure::InputMissing {
            images: unreadable,
            report,
        });
    }
    match from_manifest(manifest) {
        Ok(detected) => Ok((detected, report)),
        Err(e) => Err(DetectionFailure::Inconsistent {
            field: e.field,
            expected: e.expected,
            report,
        }),
    }
}

/// Decode an image for detection, with the header-first checks of uploads (format,
/// `expected` size, pixel budget, complete file). Errors read as "expected …".
pub fn decode_gray(
    bytes: &[u8],
    expected: Option<(u32, u32)>,
    max_pixels: u64,
) -> Result<Gray, String> {
    imageio::decode_gray(bytes, expected, max_pixels)
        .map(|(_, gray)| gray)
        .map_err(|e| format!("expected {e}"))
}

/// What one image gave: tag corners (motion method) or feature-line points (vanishing).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Found {
    Points(Vec<ObservationSpec>),
    Lines(Vec<LineSpec>),
}

/// What one image gave: its report line and its detections. Serialisable, so a store
/// can keep it beside the image and a later job reuse it (see [`ImageSource::detected`]).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ImageDetection {
    pub report: ImageReport,
    pub found: Found,
}

impl ImageDetection {
    fn of(report: ImageReport, found: Found) -> Self {
        ImageDetection { report, found }
    }

    /// An image that gave nothing, for `why` (it is reported as skipped).
    pub fn skipped(session: &Session, slot: &ImageSlot, why: String) -> Self {
        let mut report = blank_report(slot);
        report.error = Some(why);
        ImageDetection::of(report, Found::none(session))
    }

    /// Whether the image's bytes could not be read (a storage failure, not an outcome).
    pub fn unreadable(&self) -> bool {
        self.report.unreadable
    }
}

/// The report line of an image before detection.
fn blank_report(slot: &ImageSlot) -> ImageReport {
    ImageReport {
        field: slot.field.clone(),
        camera: slot.camera.clone(),
        frame: slot.frame,
        path: slot.path.clone(),
        tags: 0,
        points: 0,
        tags_from_layout: 0,
        rejected: vec![],
        error: None,
        unreadable: false,
    }
}

impl Found {
    /// Nothing found, of the kind the session's method detects.
    fn none(session: &Session) -> Found {
        if session.manifest.method == Method::Vanishing {
            Found::Lines(vec![])
        } else {
            Found::Points(vec![])
        }
    }
}

/// Detect one image of the session (read through `source`): the unit of work of the
/// detection stage, and of detection at upload.
pub fn detect_image(
    session: &Session,
    slot: &ImageSlot,
    source: &dyn ImageSource,
    quality: DetectionQuality,
) -> ImageDetection {
    let camera = session
        .camera_index(&slot.camera)
        .map(|i| &session.cameras[i].camera);
    let bytes = match source.read(slot) {
        Ok(b) => b,
        Err(e) => {
            let mut none = ImageDetection::skipped(session, slot, e);
            none.report.unreadable = true;
            return none;
        }
    };
    let mut report = blank_report(slot);
    if session.manifest.method == Method::Vanishing {
        let outcome = Ok(bytes).and_then(|bytes: Vec<u8>| {
            let gray = decode_gray(&bytes, Some(slot.size), source.max_pixels())?;
            line_slot(session, slot, &gray)
        });
        return match outcome {
            Ok((lines, targets)) => {
                report.tags = targets;
                report.points = lines.iter().map(|l| l.points.len()).sum();
                ImageDetection::of(report, Found::Lines(lines))
            }
            Err(e) => {
                report.error = Some(e);
                ImageDetection::of(report, Found::Lines(vec![]))
            }
        };
    }
    let outcome = Ok(bytes).and_then(|bytes: Vec<u8>| {
        let gray = decode_gray(&bytes, Some(slot.size), source.max_pixels())?;
        detect_tags(
            &gray,
            &session.manifest.targets,
            camera,
            &DetectOptions::of_quality(quality),
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
            ImageDetection::of(report, Found::Points(obs))
        }
        Err(e) => {
            report.error = Some(e);
            ImageDetection::of(report, Found::Points(vec![]))
        }
    }
}

/// Size of a detected L in the image (its corners' spread), to prefer the nearest.
/// One print of a line target found in an image, whatever its layout.
struct Print {
    lines: Vec<(usize, Vec<[f64; 2]>)>,
    /// Raw-pixel `u` of its centre (prints are named left to right).
    centre_u: f64,
    /// Its extent (px): the largest of several complete prints is the nearest.
    size: f64,
    /// Cut by the image border (a grid whose lines end at the border).
    cut: bool,
    /// Its layout's orientation mark could not be read: why (its labels are unknown).
    unread_mark: Option<String>,
}

/// Every print of `layout` in the image: the filled L by its outline, thin lines as
/// ridges.
fn find_prints(gray: &Gray, lens: Lens, layout: &LineLayout) -> Vec<Print> {
    match layout.print {
        LinePrint::Outline => detect_line_targets(gray, lens)
            .into_iter()
            .map(|d| {
                let c = &d.corners;
                Print {
                    centre_u: c.iter().map(|p| p[0]).sum::<f64>() / c.len() as f64,
                    size: (c[0][0] - c[3][0]).hypot(c[0][1] - c[3][1]),
                    cut: false, // the outline detector refuses prints touching the border
                    unread_mark: None,
                    lines: d.lines.into_iter().map(|l| (l.line, l.points)).collect(),
                }
            })
            .collect(),
        LinePrint::Strokes { .. } => detect_line_grids(gray, lens, layout)
            .into_iter()
            .map(|d| {
                let pts = d.lines.iter().flat_map(|l| l.points.iter());
                let (lo, hi) = pts.fold(([f64::MAX; 2], [f64::MIN; 2]), |(lo, hi), p| {
                    (
                        [lo[0].min(p[0]), lo[1].min(p[1])],
                        [hi[0].max(p[0]), hi[1].max(p[1])],
                    )
                });
                Print {
                    centre_u: d.centre[0],
                    size: (hi[0] - lo[0]).hypot(hi[1] - lo[1]),
                    cut: d.touches_border,
                    unread_mark: d.mark_error,
                    lines: d.lines.into_iter().map(|l| (l.line, l.points)).collect(),
                }
            })
            .collect(),
    }
}

fn what(layout: &LineLayout) -> &'static str {
    match layout.print {
        LinePrint::Outline => "a line target (a dark L on a light ground)",
        LinePrint::Strokes { .. } => "a target of thin lines in two orthogonal groups",
    }
}

/// The print's lines as observations of `target`, or why its labels are unknown.
fn line_specs(p: &Print, target: &str) -> Result<Vec<LineSpec>, String> {
    if let Some(why) = &p.unread_mark {
        return Err(format!(
            "target {target}: its lines were found but not which way round: {why}"
        ));
    }
    Ok(p.lines
        .iter()
        .map(|(line, points)| LineSpec {
            target: target.to_string(),
            line: *line as u8,
            points: points.clone(),
        })
        .collect())
}

/// Line targets in a rig image (the one `frames[0].line_targets` names: the largest
/// complete print of its layout if several show) or in a ring image (its two targets:
/// the complete prints of their layouts, named left to right; a print cut by the
/// border, such as a third target at the edge, is ignored).
fn line_slot(
    session: &Session,
    slot: &ImageSlot,
    gray: &Gray,
) -> Result<(Vec<LineSpec>, usize), String> {
    let v = session
        .vanishing
        .as_ref()
        .ok_or("a vanishing session (internal: no vanishing input)")?;
    let layout_of = |id: &str| {
        v.targets
            .iter()
            .find(|t| t.id == id)
            .map(|t| &t.layout)
            .ok_or_else(|| format!("a line target named {id} (internal: validated ids)"))
    };
    let frame = session.manifest.frames.first();
    match slot.frame_pos {
        Some(_) => {
            let camera = session
                .camera_index(&slot.camera)
                .map(|i| &session.cameras[i].camera)
                .ok_or("a rig camera")?;
            let target = frame
                .and_then(|f| f.line_targets.get(&slot.camera))
                .ok_or_else(|| {
                    format!(
                        "expected frames[0].line_targets.{} to name the line target this camera sees",
                        slot.camera
                    )
                })?;
            let layout = layout_of(target)?;
            let found = find_prints(gray, Lens(Some(camera)), layout);
            let n = found.len();
            let best = found
                .iter()
                .filter(|p| !p.cut)
                .max_by(|a, b| a.size.total_cmp(&b.size));
            match best {
                Some(p) => Ok((line_specs(p, target)?, n)),
                None if n > 0 => Err(format!(
                    "expected {} (target {target}) fully in view, found {n} cut by the image border",
                    what(layout)
                )),
                None => Err(format!("expected {}, found none", what(layout))),
            }
        }
        None => {
            let r = session
                .manifest
                .ring
                .iter()
                .find(|r| r.index == slot.frame)
                .ok_or("a ring view")?;
            let (a, b) = (&r.targets[0], &r.targets[1]);
            let (la, lb) = (layout_of(a)?, layout_of(b)?);
            let lens = Lens(Some(&v.auxiliary.camera));
            let mut found = find_prints(gray, lens, la);
            if lb != la {
                found.extend(find_prints(gray, lens, lb));
            }
            let n = found.len();
            let mut complete: Vec<Print> = found.into_iter().filter(|p| !p.cut).collect();
            if complete.len() < 2 {
                return Err(format!(
                    "expected the two line targets {a} and {b} fully in view, found {} complete print(s) ({} cut by the image border)",
                    complete.len(),
                    n - complete.len()
                ));
            }
            // More than two complete prints: the adjacent pair nearest the image centre
            // (the pair the view was taken of), then left to right.
            complete.sort_by(|p, q| p.centre_u.total_cmp(&q.centre_u));
            let mid = gray.width as f64 / 2.0;
            let k = (0..complete.len() - 1)
                .min_by(|&i, &j| {
                    let off = |i: usize| {
                        ((complete[i].centre_u + complete[i + 1].centre_u) / 2.0 - mid).abs()
                    };
                    off(i).total_cmp(&off(j))
                })
                .unwrap_or(0);
            let mut lines = line_specs(&complete[k], a)?;
            lines.extend(line_specs(&complete[k + 1], b)?);
            Ok((lines, n))
        }
    }
}
