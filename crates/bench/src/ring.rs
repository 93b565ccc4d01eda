//! Accuracy of the vanishing method on Wu's Table 2 ring (`wu-table2`) over many noisy
//! trials: per camera, the RMS rotation (deg) and translation (mm) error of the chainwise
//! and of the globally optimised extrinsics (Wu Fig. 7-8), the mean reported 1-σ and the
//! normalised estimation error squared (NEES, 6 is ideal) of the global covariance.

use nalgebra::Matrix6;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rigcal_core::geometry::Pose;
use rigcal_core::result::{ResultDocument, Status};
use rigcal_engine::pipeline::{calibrate, CalibOptions};
use rigcal_synth::ring::{aux_camera, generate_split, rig_camera, ring_scene, RingLayout};
use rigcal_synth::Truth;

#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct RingRow {
    pub sigma_px: f64,
    pub camera: String,
    pub chain_transforms: usize,
    pub trials: usize,
    pub failed: usize,
    pub chain_r_deg: f64,
    pub chain_t_mm: f64,
    pub global_r_deg: f64,
    pub global_t_mm: f64,
    /// Mean reported 1-σ (norm over the three axes) of the global result.
    pub sigma_r_deg: f64,
    pub sigma_t_mm: f64,
    pub nees: f64,
}

fn err(est: &Pose, truth: &Pose) -> (f64, f64) {
    let (r, t) = est.distance(truth);
    (r.to_degrees(), t * 1e3)
}

/// Which images get the noise in a placement study.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NoiseOn {
    Both,
    /// The eight rig images only (the auxiliary ones exact).
    Rig,
    /// The auxiliary images only.
    Aux,
}

/// Run `trials` noisy sessions per noise level (pixels on the sampled line points) with
/// the targets and the auxiliary camera placed by `layout` and the noise on `on`; one row
/// per (noise, camera). With the default layout and `Both` these are the `wu-table2`
/// preset's sessions, seed for seed; otherwise a placement study.
pub fn ring_accuracy_layout(
    noise: &[f64],
    trials: usize,
    seed: u64,
    layout: &RingLayout,
    on: NoiseOn,
) -> Vec<RingRow> {
    let scene = ring_scene(layout);
    let (rig, aux) = (rig_camera(), aux_camera());
    study(noise, trials, |sigma, k| {
        let split = match on {
            NoiseOn::Both => [sigma, sigma],
            NoiseOn::Rig => [sigma, 0.0],
            NoiseOn::Aux => [0.0, sigma],
        };
        let mut rng = ChaCha8Rng::seed_from_u64(seed + k as u64);
        let (manifest, truth) = generate_split(&mut rng, split, &rig, &aux, &scene);
        let session = rigcal_core::session::from_manifest(manifest).ok()?;
        Some((calibrate(&session, &CalibOptions::default()), truth))
    })
}

/// The same from rendered images through the line-target detector: the noise is
/// grey-level noise of the 8-bit images (σ in grey levels), every trial 16 new renders
/// of `print` on the targets; clean PNGs, or with `nuisance` as a real capture shows
/// them (textured floor, blur, vignetting, gain and offset, JPEG).
pub fn ring_accuracy_images(
    noise_grey: &[f64],
    trials: usize,
    seed: u64,
    print: rigcal_synth::ring::RingPrint,
    nuisance: Option<rigcal_synth::hall::Nuisance>,
) -> Vec<RingRow> {
    let look = rigcal_synth::ring::RingImages { print, nuisance };
    let (rig, aux, scene) = (
        rigcal_synth::ring::rig_camera(),
        rigcal_synth::ring::aux_camera(),
        rigcal_synth::ring::table2_scene(),
    );
    study(noise_grey, trials, |sigma, k| {
        let (manifest, truth, files) = rigcal_synth::ring::image_session_with(
            &rig,
            &aux,
            &scene,
            &look,
            sigma,
            seed + k as u64,
        );
        let session = rigcal_core::session::from_manifest(manifest).ok()?;
        let source = rigcal_engine::pipeline::detection::MemorySource(files.into_iter().collect());
        let doc = match rigcal_engine::pipeline::run(
            &session,
            &source,
            &CalibOptions::default(),
            &rigcal_engine::pipeline::Silent,
        ) {
            Ok(doc) => doc,
            // Only a cancellation ends a run without a document, and `Silent` never
            // cancels: no trial is dropped here.
            Err(_) => return None,
        };
        Some((doc, truth))
    })
}

/// Per noise level, `trials` runs of `trial(sigma, k)` (a result and its truth; `None`
/// when no session could be made), accumulated per camera.
fn study(
    noise: &[f64],
    trials: usize,
    trial: impl Fn(f64, usize) -> Option<(ResultDocument, Truth)>,
) -> Vec<RingRow> {
    let mut rows = Vec::new();
    for &sigma in noise {
        let mut acc: Vec<RingRow> = Vec::new();
        for k in 0..trials {
            let Some((doc, truth)) = trial(sigma, k) else {
                continue;
            };
            if doc.status == Status::Failed {
                // Said, not only left out of the table (its trial count shows it too).
                let why = serde_json::to_string(&doc.reasons).unwrap_or_default();
                eprintln!("σ {sigma}, trial {k}: failed: {why}");
            }
            let report = doc.vanishing.as_ref();
            if acc.is_empty() {
                acc = truth
                    .ref_from_cam
                    .keys()
                    .map(|c| RingRow {
                        sigma_px: sigma,
                        camera: c.clone(),
                        ..Default::default()
                    })
                    .collect();
            }
            for row in acc.iter_mut() {
                row.trials += 1;
                let (Some(t), Some(r)) = (truth.ref_from_cam.get(&row.camera), report) else {
                    row.failed += 1;
                    continue;
                };
                let g = doc.extrinsics.iter().find(|e| e.value.camera == row.camera);
                let c = r.cameras.iter().find(|c| c.camera == row.camera);
                let (Some(g), Some(c)) = (g, c) else {
                    row.failed += 1;
                    continue;
                };
                if doc.status == Status::Failed {
                    row.failed += 1;
                    continue;
                }
                row.chain_transforms = c.chain_transforms;
                let (cr, ct) = err(&c.chainwise.pose(), t);
                let est = g.value.pose();
                let (gr, gt) = err(&est, t);
                row.chain_r_deg += cr * cr;
                row.chain_t_mm += ct * ct;
                row.global_r_deg += gr * gr;
                row.global_t_mm += gt * gt;
                let n = |a: &[Option<f64>; 3]| {
                    a.iter()
                        .map(|x| x.unwrap_or(0.0).powi(2))
                        .sum::<f64>()
                        .sqrt()
                };
                row.sigma_r_deg += n(&g.sigma_rotation_deg);
                row.sigma_t_mm += n(&g.sigma_translation_m) * 1e3;
                if let Some(cov) = g.covariance {
                    let m = Matrix6::from_fn(|i, j| cov[i][j]);
                    let e = super::accuracy::error6(&est, t);
                    if let Some(inv) = m.try_inverse() {
                        row.nees += (e.transpose() * inv * e)[(0, 0)];
                    }
                }
            }
        }
        for mut row in acc {
            let n = (row.trials - row.failed).max(1) as f64;
            row.chain_r_deg = (row.chain_r_deg / n).sqrt();
            row.chain_t_mm = (row.chain_t_mm / n).sqrt();
            row.global_r_deg = (row.global_r_deg / n).sqrt();
            row.global_t_mm = (row.global_t_mm / n).sqrt();
            row.sigma_r_deg /= n;
            row.sigma_t_mm /= n;
            row.nees /= n;
            rows.push(row);
        }
    }
    rows
}

pub fn print_table(rows: &[RingRow]) {
    println!(
        "Vanishing method on wu-table2 (Wu et al. Table 2 ring, 8 cameras), RMS errors per camera"
    );
    println!(
        "{:>6} {:>6} {:>5} {:>6} | {:>10} {:>10} | {:>10} {:>10} | {:>9} {:>9} {:>6}",
        "σ px",
        "camera",
        "hops",
        "trials",
        "chain °",
        "chain mm",
        "global °",
        "global mm",
        "σ̂ °",
        "σ̂ mm",
        "NEES"
    );
    for r in rows {
        println!(
            "{:>6.2} {:>6} {:>5} {:>6} | {:>10.4} {:>10.3} | {:>10.4} {:>10.3} | {:>9.4} {:>9.3} {:>6.2}",
            r.sigma_px,
            r.camera,
            r.chain_transforms,
            r.trials - r.failed,
            r.chain_r_deg,
            r.chain_t_mm,
            r.global_r_deg,
            r.global_t_mm,
            r.sigma_r_deg,
            r.sigma_t_mm,
            r.nees
        );
    }
}
