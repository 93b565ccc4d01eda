//! Realistic captures end to end (`rigcal bench capture`): a hall preset rendered as
//! images, every trial with other noise, detected and calibrated as a user's session is;
//! the detection against each image's true corners and the result against the truth,
//! with the error of every translation axis in units of its reported σ, and of every
//! camera's whole pose in its reported covariance (NEES).

use crate::accuracy::error6;
use nalgebra::Matrix6;
use rigcal_core::result::{DetectionQuality, ExtrinsicValue, Status};
use rigcal_core::session::parse_session;
use rigcal_engine::pipeline::detection::{detect_session, MemorySource};
use rigcal_engine::pipeline::{calibrate_detected, CalibOptions, Silent};
use rigcal_synth::hall::{hall, Hall, Nuisance};
use std::collections::HashMap;
use std::time::Instant;

/// One trial's outcome.
#[derive(Clone, Debug, serde::Serialize)]
pub struct CaptureTrial {
    pub seed: u64,
    pub status: String,
    pub reasons: Vec<String>,
    pub legible_tags: usize,
    pub found_tags: usize,
    /// Reported corners more than 1 px from the truth.
    pub wrong_corners: usize,
    pub corner_rms_px: f64,
    /// The residual pixel noise σ the calibration estimated (before its corner-noise
    /// floor), so the error / σ at another floor can be read off this run.
    pub sigma_px: f64,
    /// Worst camera: translation (mm) and rotation (deg) error.
    pub worst_t_mm: f64,
    pub worst_r_deg: f64,
    /// Per camera and translation axis: error / reported σ (axes without σ left out).
    pub z: Vec<f64>,
    /// Per camera: the normalised estimation error squared of `[dt; dφ]` in the
    /// reported 6×6 covariance (6 is honest), for results with every direction
    /// determined. The per-axis `z` cannot see a covariance whose correlations are off.
    pub nees: Vec<f64>,
    pub detection_s: f64,
    pub total_s: f64,
}

/// `trials` captures of `preset` (hall seeds `seed..`), images of `size`, detected at
/// `quality`.
pub fn capture_trials(
    preset: &str,
    trials: usize,
    seed: u64,
    size: Option<(u32, u32)>,
    quality: DetectionQuality,
) -> Result<Vec<CaptureTrial>, String> {
    let nuisance = Nuisance::default();
    let mut out = Vec::new();
    for k in 0..trials as u64 {
        let s = seed + k;
        let h = hall(preset, s, size)?;
        let capture = h.image_capture(true);
        let mut files = HashMap::new();
        for (frame, spec) in capture.manifest.frames.iter().enumerate() {
            for (cam, path) in &spec.images {
                let ci = h.cameras.iter().position(|c| &c.0 == cam).ok_or("camera")?;
                let img = h.render(
                    frame,
                    ci,
                    &nuisance,
                    s.wrapping_mul(7919) + (frame * 64 + ci) as u64,
                );
                files.insert(
                    path.clone(),
                    Hall::encode(&img, &nuisance).map_err(|e| e.to_string())?,
                );
            }
        }
        let text = serde_json::to_string(&capture.manifest).map_err(|e| e.to_string())?;
        let session = parse_session(text.as_bytes()).map_err(|e| e.to_string())?;
        let t0 = Instant::now();
        let (detected, report) = detect_session(&session, &MemorySource(files), quality, &Silent)
            .map_err(|e| format!("detection: {e:?}"))?;
        let opts = CalibOptions {
            detection: quality,
            ..CalibOptions::default()
        };
        let doc = calibrate_detected(&detected, report, &opts, &Silent)
            .map_err(|c| format!("cancelled at {}", c.0))?;
        let total_s = t0.elapsed().as_secs_f64();
        // Detection against the truth: every legible tag's four corners reported, and
        // how far each reported corner is from its true position.
        let (mut legible, mut found, mut wrong, mut sq, mut n) = (0, 0, 0, 0.0, 0usize);
        for it in &capture.images {
            let spec = &detected.manifest.frames[it.frame];
            let obs: HashMap<&str, (f64, f64)> = spec
                .observations
                .get(&it.camera)
                .map(|o| o.iter().map(|o| (o.point.as_str(), (o.u, o.v))).collect())
                .unwrap_or_default();
            let mut tags: HashMap<&str, usize> = HashMap::new();
            for p in it.corners.keys() {
                let tag = p.rsplit_once(':').map_or(p.as_str(), |(t, _)| t);
                *tags.entry(tag).or_default() += 1;
            }
            legible += tags.len();
            for tag in tags.keys() {
                found += (0..4).all(|c| obs.contains_key(format!("{tag}:{c}").as_str())) as usize;
            }
            for (p, uv) in &it.corners {
                if let Some((u, v)) = obs.get(p.as_str()) {
                    let e = (u - uv[0]).hypot(v - uv[1]);
                    if e > 1.0 {
                        wrong += 1;
                    } else {
                        sq += e * e;
                        n += 1;
                    }
                }
            }
        }
        let (mut worst_t, mut worst_r, mut z, mut nees) = (0.0f64, 0.0f64, Vec::new(), Vec::new());
        // NEES only where every direction is determined: elsewhere the covariance is
        // singular along the held heights.
        let held = doc
            .singularity
            .as_ref()
            .is_some_and(|s| !s.unobservable_directions.is_empty());
        if doc.status != Status::Failed {
            for e in &doc.extrinsics {
                let truth = capture.truth.ref_from_cam[&e.value.camera];
                let est = ExtrinsicValue::pose(&e.value);
                let (dr, dt) = est.distance(&truth);
                worst_t = worst_t.max(dt * 1e3);
                worst_r = worst_r.max(dr.to_degrees());
                for a in 0..3 {
                    if let Some(s) = e.sigma_translation_m[a].filter(|s| *s > 0.0) {
                        z.push((est.trans[a] - truth.trans[a]) / s);
                    }
                }
                let inv = e
                    .covariance
                    .filter(|_| !held)
                    .and_then(|c| Matrix6::from_fn(|a, b| c[a][b]).try_inverse());
                if let Some(inv) = inv {
                    let x = error6(&est, &truth);
                    nees.push(x.dot(&(inv * x)));
                }
            }
        }
        out.push(CaptureTrial {
            seed: s,
            status: doc.status.as_str().to_string(),
            reasons: doc.reasons.iter().map(|r| r.code.clone()).collect(),
            legible_tags: legible,
            found_tags: found,
            wrong_corners: wrong,
            corner_rms_px: if n > 0 {
                (sq / n as f64).sqrt()
            } else {
                f64::NAN
            },
            sigma_px: doc.residuals.as_ref().map_or(f64::NAN, |r| r.sigma_px),
            worst_t_mm: worst_t,
            worst_r_deg: worst_r,
            z,
            nees,
            detection_s: doc.detection.as_ref().map_or(0.0, |d| d.seconds),
            total_s,
        });
        // A trial takes minutes (most of it rendering): say where the run is.
        eprintln!(
            "trial {}/{trials} (seed {s}): {}, worst {worst_t:.3} mm, {worst_r:.5}°",
            k + 1,
            doc.status.as_str()
        );
    }
    Ok(out)
}

pub fn print_table(preset: &str, rows: &[CaptureTrial]) {
    println!("preset {preset}: rendered captures through detection and calibration");
    println!(
        "{:>6} {:>10} {:>8} {:>8} {:>6} {:>9} {:>8} {:>9} {:>9} {:>7} {:>7} {:>6} {:>7} {:>7}",
        "seed",
        "status",
        "legible",
        "found%",
        "wrong",
        "rms px",
        "σ px",
        "worst mm",
        "worst °",
        "|z|max",
        "z rms",
        "NEES",
        "det s",
        "total s"
    );
    let mut all_z = Vec::new();
    let mut all_nees = Vec::new();
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    for r in rows {
        let zmax = r.z.iter().fold(0.0f64, |m, z| m.max(z.abs()));
        let zrms = (r.z.iter().map(|z| z * z).sum::<f64>() / r.z.len().max(1) as f64).sqrt();
        all_z.extend(r.z.iter().copied());
        all_nees.extend(r.nees.iter().copied());
        println!(
            "{:>6} {:>10} {:>8} {:>8.2} {:>6} {:>9.4} {:>8.4} {:>9.3} {:>9.5} {:>7.2} {:>7.2} {:>6.1} {:>7.1} {:>7.1}",
            r.seed,
            r.status,
            r.legible_tags,
            100.0 * r.found_tags as f64 / r.legible_tags.max(1) as f64,
            r.wrong_corners,
            r.corner_rms_px,
            r.sigma_px,
            r.worst_t_mm,
            r.worst_r_deg,
            zmax,
            zrms,
            mean(&r.nees),
            r.detection_s,
            r.total_s
        );
    }
    let ok = rows.iter().filter(|r| r.status != "failed").count();
    let zrms = (all_z.iter().map(|z| z * z).sum::<f64>() / all_z.len().max(1) as f64).sqrt();
    let zmax = all_z.iter().fold(0.0f64, |m, z| m.max(z.abs()));
    println!(
        "{ok}/{} not failed; over all cameras and axes: z rms {zrms:.2}, |z| max {zmax:.2} ({} axes); NEES mean {:.1} over {} camera poses (6 is honest)",
        rows.len(),
        all_z.len(),
        mean(&all_nees),
        all_nees.len()
    );
}
