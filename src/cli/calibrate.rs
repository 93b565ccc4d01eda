//! `rigcal calibrate`: a session file in, the result document (or an export) out.

use anyhow::{anyhow, Context, Result};
use rigcal_core::session::parse_session;
use rigcal_engine::export::{render_for, ExportError, Format};
use rigcal_engine::pipeline::{run as run_pipeline, CalibOptions, DirSource, LossKind, Silent};
use std::path::PathBuf;

/// Calibrate a capture session (JSON); prints the result document. Exit code 0
/// succeeded, 3 degraded, 1 failed or bad input.
#[derive(clap::Args)]
pub struct Args {
    session: PathBuf,
    /// json | kalibr | opencv | urdf | colmap | ros2 | camera_info
    #[arg(long, default_value = "json")]
    format: Format,
    /// The camera of `--format camera_info`.
    #[arg(long)]
    camera: Option<String>,
    /// Robust loss of the outlier pass: huber | cauchy | squared
    #[arg(long, default_value = "huber")]
    loss: LossKind,
    /// Scale of the robust loss, pixels.
    #[arg(long, default_value_t = 2.0)]
    loss_scale: f64,
}

pub fn run(a: Args) -> Result<i32> {
    let bytes =
        std::fs::read(&a.session).with_context(|| format!("reading {}", a.session.display()))?;
    let session = parse_session(&bytes).map_err(|e| anyhow!("session: {e}"))?;
    let opts = CalibOptions::from_loss(a.loss, a.loss_scale)
        .map_err(|e| anyhow!("--{}: {}", e.field.replace('_', "-"), e.expected))?;
    // Images are named relative to the session file.
    let dir = a
        .session
        .parent()
        .map(|p| p.to_path_buf())
        .unwrap_or_default();
    let doc = run_pipeline(&session, &DirSource(dir), &opts, &Silent)
        .map_err(|c| anyhow!("cancelled at {}", c.0))?;
    match render_for(&doc, &session, a.format, a.camera.as_deref()) {
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
