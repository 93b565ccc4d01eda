//! `rigcal calibrate`: a session file in, the result document (or an export) out.

use anyhow::{anyhow, Context, Result};
use rigcal_core::result::DetectionQuality;
use rigcal_core::session::parse_session;
use rigcal_core::vehicle::VehicleModel;
use rigcal_engine::export::{render_in, ExportError, Format, Frame};
use rigcal_engine::pipeline::{run as run_pipeline, CalibOptions, DirSource, LossKind, Silent};
use std::path::PathBuf;

/// Calibrate a capture session (JSON, or a job bundle `.tar` from
/// `GET /v1/jobs/{id}/bundle`, replayed with the job's options); prints the result
/// document. Exit code 0 succeeded, 3 degraded, 1 failed or bad input.
#[derive(clap::Args)]
pub struct Args {
    session: PathBuf,
    /// json | kalibr | opencv | urdf | colmap | ros2 | camera_info
    #[arg(long, default_value = "json")]
    format: Format,
    /// The camera of `--format camera_info`.
    #[arg(long)]
    camera: Option<String>,
    /// The frame of the export: `reference` (the reference camera's) or `vehicle` (the
    /// vehicle model's, placed by its `vehicle_from_ref`; needs `--vehicle-model`).
    #[arg(long, default_value = "reference", value_parser = ["reference", "vehicle"])]
    frame: String,
    /// A vehicle model document (as `PUT /v1/vehicle-models/{model}` takes): every
    /// camera's deviation from the nominal rig is printed on stderr, and `--frame
    /// vehicle` uses its `vehicle_from_ref`.
    #[arg(long)]
    vehicle_model: Option<PathBuf>,
    /// Robust loss of the outlier pass: huber | cauchy | squared
    #[arg(long, default_value = "huber")]
    loss: LossKind,
    /// Scale of the robust loss, pixels.
    #[arg(long, default_value_t = 2.0)]
    loss_scale: f64,
    /// Detection of a session of images: accurate | fast (docs/performance.md,
    /// "Detection quality").
    #[arg(long, default_value = "accurate")]
    detect_quality: DetectionQuality,
}

/// A job bundle unpacked: its directory (kept while it lives) and the job's options.
struct Bundle {
    dir: tempfile::TempDir,
    loss: LossKind,
    loss_scale: f64,
    quality: DetectionQuality,
}

/// Unpack `path` if it is a tar (a job bundle); `None` for anything else.
fn unpack_bundle(path: &std::path::Path) -> Result<Option<Bundle>> {
    let mut head = [0u8; 262];
    let n = std::io::Read::read(&mut std::fs::File::open(path)?, &mut head)?;
    if n < 262 || &head[257..262] != b"ustar" {
        return Ok(None);
    }
    let dir = tempfile::tempdir().context("a temporary directory for the bundle")?;
    // `unpack` refuses entries that would land outside the directory (`..`, absolute).
    tar::Archive::new(std::fs::File::open(path)?)
        .unpack(dir.path())
        .with_context(|| format!("unpacking the bundle {}", path.display()))?;
    let job: serde_json::Value = serde_json::from_slice(
        &std::fs::read(dir.path().join("job.json")).context("the bundle has no job.json")?,
    )
    .context("the bundle's job.json")?;
    let loss = job["options"]["loss"]
        .as_str()
        .ok_or_else(|| anyhow!("the bundle's job.json: options.loss, a string, is missing"))?
        .parse::<LossKind>()
        .map_err(|e| anyhow!("the bundle's job.json options.loss: {e}"))?;
    let loss_scale = job["options"]["loss_scale"].as_f64().ok_or_else(|| {
        anyhow!("the bundle's job.json: options.loss_scale, a number, is missing")
    })?;
    // Bundles of jobs from before the option have none: those ran at `accurate`.
    let quality = match &job["options"]["detection"]["quality"] {
        serde_json::Value::Null => DetectionQuality::Accurate,
        v => v
            .as_str()
            .ok_or_else(|| {
                anyhow!("the bundle's job.json: options.detection.quality is not a string")
            })?
            .parse::<DetectionQuality>()
            .map_err(|e| anyhow!("the bundle's job.json options.detection.quality: {e}"))?,
    };
    Ok(Some(Bundle {
        dir,
        loss,
        loss_scale,
        quality,
    }))
}

pub fn run(a: Args) -> Result<i32> {
    let bundle =
        unpack_bundle(&a.session).with_context(|| format!("reading {}", a.session.display()))?;
    let (manifest, loss, loss_scale, quality) = match &bundle {
        Some(b) => (
            b.dir.path().join("session.json"),
            b.loss,
            b.loss_scale,
            b.quality,
        ),
        None => (a.session.clone(), a.loss, a.loss_scale, a.detect_quality),
    };
    if bundle.is_some() {
        eprintln!(
            "replaying the job bundle with its options (loss {loss:?}, scale {loss_scale} px, detection {quality})"
        );
    }
    let model = match &a.vehicle_model {
        None => None,
        Some(p) => {
            let bytes = std::fs::read(p).with_context(|| format!("reading {}", p.display()))?;
            Some(
                VehicleModel::parse(&bytes)
                    .map_err(|e| anyhow!("--vehicle-model {}: {e}", p.display()))?,
            )
        }
    };
    let frame = match (a.frame.as_str(), &model) {
        ("vehicle", None) => return Err(anyhow!("--frame vehicle: needs --vehicle-model FILE with vehicle_from_ref")),
        ("vehicle", Some(m)) => Frame::Vehicle(m.vehicle_from_ref().ok_or_else(|| {
            anyhow!("--frame vehicle: the vehicle model defines no vehicle_from_ref (where the reference camera sits in the vehicle frame)")
        })?),
        _ => Frame::Reference,
    };
    let bytes =
        std::fs::read(&manifest).with_context(|| format!("reading {}", manifest.display()))?;
    let session = parse_session(&bytes).map_err(|e| anyhow!("session: {e}"))?;
    let opts = CalibOptions {
        detection: quality,
        ..CalibOptions::from_loss(loss, loss_scale)
            .map_err(|e| anyhow!("--{}: {}", e.field.replace('_', "-"), e.expected))?
    };
    // Images are named relative to the session file.
    let dir = manifest
        .parent()
        .map(|p| p.to_path_buf())
        .unwrap_or_default();
    let doc = run_pipeline(&session, &DirSource(dir), &opts, &Silent)
        .map_err(|c| anyhow!("cancelled at {}", c.0))?;
    if let Some(m) = &model {
        let ids: Vec<&str> = session.cameras.iter().map(|c| c.id.as_str()).collect();
        m.fits(&session.manifest.reference_camera, &ids)
            .map_err(|e| anyhow!("session against --vehicle-model: {e}"))?;
        let values: Vec<_> = doc.extrinsics.iter().map(|e| e.value.clone()).collect();
        for d in m
            .deviations(&values)
            .map_err(|e| anyhow!("--vehicle-model: {e}"))?
        {
            match (d.translation_norm_mm, d.rotation_angle_deg) {
                (Some(t), Some(r)) => eprintln!(
                    "{}: {t:.2} mm, {r:.3}° from nominal: {}",
                    d.camera,
                    if d.within_tolerance {
                        "within tolerance".to_string()
                    } else {
                        d.exceeded.join("; ")
                    }
                ),
                _ => eprintln!("{}: {}", d.camera, d.exceeded.join("; ")),
            }
        }
    }
    match render_in(&doc, &session, a.format, a.camera.as_deref(), frame) {
        Ok(text) => println!("{text}"),
        Err(ExportError::NothingToExport) => {
            println!("{}", serde_json::to_string_pretty(&doc)?);
            eprintln!("error: nothing to export: the calibration {:?}", doc.status);
        }
        Err(ExportError::Unrepresentable(why)) => return Err(anyhow!("--format: {why}")),
        Err(ExportError::Camera(why)) => return Err(anyhow!("--camera: {why}")),
    }
    Ok(doc.exit_code())
}
