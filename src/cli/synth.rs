//! `rigcal synth`: a synthetic session and its ground truth, optionally rendered.

use super::{non_negative, parse_size};
use anyhow::{anyhow, Result};
use rigcal_synth::hall;
use std::path::PathBuf;

/// Write a synthetic session and its ground truth (session.json, truth.json; the
/// realistic hall presets also corners.json, every image's visible tag corners).
#[derive(clap::Args)]
pub struct Args {
    #[arg(long)]
    preset: String,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Pixel noise σ of the observations (sessions of detections).
    #[arg(long, default_value_t = 0.0, value_parser = non_negative)]
    noise: f64,
    /// Render the capture's images (hall presets: car-hall, car-hall-planar,
    /// car-hall-isolated, fisheye-handheld) with blur, vignetting, gain, noise, JPEG.
    #[arg(long)]
    images: bool,
    /// Image size of the hall presets, e.g. 1024x768 (intrinsics scale with it).
    #[arg(long, value_parser = parse_size)]
    size: Option<(u32, u32)>,
    /// Sensor noise σ of rendered images, grey levels.
    #[arg(long, default_value_t = 1.0, value_parser = non_negative)]
    grey_noise: f64,
    /// Write PNG instead of JPEG (q 92).
    #[arg(long)]
    png: bool,
    /// Write colour images, as a colour camera delivers them (its white balance a little
    /// off neutral), instead of grey ones.
    #[arg(long)]
    colour: bool,
    /// Hall presets: AprilGrids only, no tags scattered on the walls.
    #[arg(long)]
    boards_only: bool,
    /// Output directory.
    #[arg(long, default_value = ".")]
    out: PathBuf,
}

pub fn run(a: Args) -> Result<i32> {
    let out = &a.out;
    if hall::PRESETS.contains(&a.preset.as_str()) {
        let mut scene = hall::hall(&a.preset, a.seed, a.size).map_err(|e| anyhow!(e))?;
        if a.boards_only {
            scene = scene.boards_only();
        }
        let nuisance = hall::Nuisance {
            noise: a.grey_noise,
            jpeg_quality: (!a.png).then_some(92),
            colour: a.colour.then_some(hall::HALL_WHITE_BALANCE),
            ..Default::default()
        };
        let w = hall::write_capture(&scene, out, a.images.then_some(&nuisance), a.noise, a.seed)?;
        eprintln!(
            "wrote {} ({} images, {} fully visible tags)",
            out.join("session.json").display(),
            w.images,
            w.visible_tags
        );
        return Ok(0);
    }
    if a.images || a.size.is_some() || a.boards_only || a.colour {
        return Err(anyhow!(
            "--images/--size/--boards-only/--colour: only for the hall presets ({})",
            hall::PRESETS.join(", ")
        ));
    }
    let (session, truth) = rigcal_synth::generate(&a.preset, a.seed, a.noise).ok_or_else(|| {
        anyhow!(
            "--preset: one of {}, got {:?}",
            rigcal_synth::PRESETS.join(", "),
            a.preset
        )
    })?;
    std::fs::create_dir_all(out)?;
    std::fs::write(
        out.join("session.json"),
        serde_json::to_string_pretty(&session)?,
    )?;
    std::fs::write(
        out.join("truth.json"),
        serde_json::to_string_pretty(&truth)?,
    )?;
    eprintln!(
        "wrote {} and {}",
        out.join("session.json").display(),
        out.join("truth.json").display()
    );
    Ok(0)
}
