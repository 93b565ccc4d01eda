//! `rigcal detect`: targets and camera from JSON files, detections as JSON on stdout.

use anyhow::{anyhow, Context, Result};
use clap::builder::RangedU64ValueParser;
use rigcal_core::session::{camera_from_spec, CameraSpec, TargetSpec};
use rigcal_core::target::line_layout::Print as LinePrint;
use rigcal_detect::{detect_tags, DetectOptions, Quality};
use rigcal_engine::pipeline::detection::{decode_gray, DEFAULT_MAX_IMAGE_PIXELS};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

/// Detect AprilTags / AprilGrid corners in images; prints detections as JSON (one
/// object per image, an array when several are given).
#[derive(clap::Args)]
pub struct Args {
    #[arg(required = true)]
    images: Vec<PathBuf>,
    /// A target definition as in a session's `targets[]` (aprilgrid or apriltags),
    /// or an array of them: a JSON file, or the JSON itself.
    #[arg(long)]
    target: String,
    /// A camera as in a session's `cameras[]`: sides are then fitted in the
    /// undistorted plane (better corners under distortion). A JSON file, or the JSON
    /// itself.
    #[arg(long)]
    camera: Option<String>,
    /// Threads for the tags of one image (default: the machine's cores; 1 to time a
    /// single core).
    #[arg(long, value_parser = RangedU64ValueParser::<usize>::new().range(1..=256))]
    threads: Option<usize>,
    /// accurate | fast (docs/performance.md, "Detection quality").
    #[arg(long, default_value = "accurate")]
    detect_quality: Quality,
}

fn read(p: &Path) -> Result<Vec<u8>> {
    std::fs::read(p).with_context(|| format!("reading {}", p.display()))
}

/// The JSON of option `flag`: `arg` itself when it is JSON (an object or an array), else
/// the file it names. A path never starts with `{` or `[` in practice; one that does is
/// given as `./{…`.
fn json_arg(flag: &str, arg: &str) -> Result<Vec<u8>> {
    if arg.trim_start().starts_with(['{', '[']) {
        Ok(arg.as_bytes().to_vec())
    } else {
        read(Path::new(arg)).with_context(|| format!("{flag}: neither JSON nor a readable file"))
    }
}

pub fn run(a: Args) -> Result<i32> {
    let threads = a
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let text = json_arg("--target", &a.target)?;
    let targets: Vec<TargetSpec> = match serde_json::from_slice::<Vec<TargetSpec>>(&text) {
        Ok(t) => t,
        Err(_) => vec![serde_json::from_slice::<TargetSpec>(&text).map_err(|e| {
            anyhow!("--target: a target object (aprilgrid | apriltags | line_target | line_grid | line_segments) or an array of them: {e}")
        })?],
    };
    let camera = match &a.camera {
        Some(p) => {
            let spec: CameraSpec = serde_json::from_slice(&json_arg("--camera", p)?)
                .map_err(|e| anyhow!("--camera: a camera as in a session's cameras[]: {e}"))?;
            Some(camera_from_spec(&spec, "camera").map_err(|e| anyhow!("--camera: {e}"))?)
        }
        None => None,
    };
    // Line targets (Wu's L, thin-line grids) are found by shape, whatever their size;
    // their lines are reported per print found, left to right, per target.
    let lines_only = targets.iter().all(TargetSpec::is_line_target);
    let layouts = if lines_only {
        targets
            .iter()
            .enumerate()
            .map(|(i, t)| {
                rigcal_core::session::line_layout(t, &format!("targets[{i}]"))
                    .map(|l| (t.id().to_string(), l))
                    .map_err(|e| anyhow!("--target: {e}"))
            })
            .collect::<Result<Vec<_>>>()?
    } else {
        Vec::new()
    };
    // The detector's decoder table is built once per thread (as a worker keeps it), not
    // inside the first image's `elapsed_ms`.
    rigcal_detect::quads::warm_up(&DetectOptions::default().quads).map_err(|e| anyhow!(e))?;
    let mut out = Vec::new();
    let mut failures = 0;
    for path in &a.images {
        let bytes = read(path)?;
        let size = camera.as_ref().map(|c| (c.width, c.height));
        let result = decode_gray(&bytes, size, DEFAULT_MAX_IMAGE_PIXELS).and_then(|gray| {
            let start = std::time::Instant::now();
            let v = if lines_only {
                let lens = rigcal_detect::refine::Lens(camera.as_ref());
                let mut per_target = Vec::new();
                for (id, layout) in &layouts {
                    let found = match layout.print {
                        LinePrint::Outline => {
                            json!(rigcal_detect::linetarget::detect_line_targets(&gray, lens))
                        }
                        LinePrint::Strokes { .. } => json!(
                            rigcal_detect::linegrid::detect_line_grids(&gray, lens, layout)
                        ),
                    };
                    per_target.push(json!({"target": id, "found": found}));
                }
                json!({ "line_targets": per_target })
            } else {
                let opts = DetectOptions {
                    threads,
                    ..DetectOptions::of_quality(a.detect_quality)
                };
                let d = detect_tags(&gray, &targets, camera.as_ref(), &opts)?;
                serde_json::to_value(&d).map_err(|e| e.to_string())?
            };
            Ok((v, start.elapsed().as_secs_f64() * 1e3))
        });
        out.push(match result {
            Ok((mut v, ms)) => {
                v["image"] = json!(path.display().to_string());
                v["elapsed_ms"] = json!(ms);
                v
            }
            Err(e) => {
                failures += 1;
                json!({"image": path.display().to_string(), "error": e})
            }
        });
    }
    let doc = if out.len() == 1 {
        out.remove(0)
    } else {
        Value::Array(out)
    };
    println!("{}", serde_json::to_string_pretty(&doc)?);
    Ok(if failures > 0 { 1 } else { 0 })
}
