//! Accuracy of the motion method on a synthetic preset over many noisy trials: RMS
//! errors of the linear initialisation and of the refined result, the Cramér–Rao bound
//! computed from the same problem's Jacobian at the truth, and the normalised
//! estimation error squared (NEES) of the reported covariance.

use nalgebra::{DMatrix, SVector};
use rigcal_core::geometry::{so3, Pose, Vec3};
use rigcal_core::result::{ExtrinsicValue, ResultDocument, Status};
use rigcal_core::session::{parse_session, PointKind, Session};
use rigcal_engine::pipeline::{calibrate, CalibOptions};
use rigcal_solve::bundle::{BundleProblem, DistanceConstraint, Obs, PointRef};
use rigcal_solve::Loss;
use rigcal_synth::{generate, Truth};
use std::collections::HashMap;

#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct AccuracyRow {
    pub sigma_px: f64,
    pub trials: usize,
    pub failed: usize,
    pub init_t_mm: f64,
    pub init_r_deg: f64,
    pub refined_t_mm: f64,
    pub refined_r_deg: f64,
    pub crb_t_mm: f64,
    pub crb_r_deg: f64,
    /// Mean NEES of the 6 extrinsic parameters (6 is ideal).
    pub nees: f64,
    /// Directions the motion leaves undetermined (heights under planar motion); the
    /// errors above are of the observable part only.
    pub unobservable: usize,
}

/// Error `[dt; dφ]` of `est` against `truth` in the parametrisation of the covariance.
pub fn error6(est: &Pose, truth: &Pose) -> SVector<f64, 6> {
    let dt = est.trans - truth.trans;
    let dphi = so3::log(&(est.rot * truth.rot.transpose()));
    SVector::<f64, 6>::from_iterator(dt.iter().chain(dphi.iter()).copied())
}

/// A preset's session, through the same parser users' sessions go through, and its truth.
pub fn synthetic_session(preset: &str, seed: u64, sigma: f64) -> Option<(Session, Truth)> {
    let (manifest, truth) = generate(preset, seed, sigma)?;
    let session = parse_session(serde_json::to_string(&manifest).ok()?.as_bytes()).ok()?;
    Some((session, truth))
}

/// Covariance of the extrinsics at the truth for pixel noise `sigma` (the CRB): cameras
/// in session order except the reference, 6×6 blocks `[dt, dφ]`.
pub fn cramer_rao(
    session: &Session,
    truth: &Truth,
    sigma: f64,
) -> Option<HashMap<usize, DMatrix<f64>>> {
    let (cams, info) = truth_information(session, truth, sigma)?;
    let cov = info.try_inverse()? * (sigma * sigma);
    Some(
        cams.iter()
            .enumerate()
            .map(|(i, c)| (*c, cov.view((6 * i, 6 * i), (6, 6)).into_owned()))
            .collect(),
    )
}

/// The part of the extrinsics the data determine, from the information at the truth:
/// the projector onto its range and the bound (pseudo-inverse × σ²) on that range.
/// Under planar motion the heights are exactly unobservable at the truth, so their
/// eigenvalues are zero to rounding; errors along them say nothing of an estimator
/// (both the initialisation and the adjustment hold them at the prior).
pub struct Observable {
    pub cams: Vec<usize>,
    pub projector: DMatrix<f64>,
    pub crb: DMatrix<f64>,
    /// Number of unobservable directions.
    pub null_dim: usize,
}

pub fn observable(session: &Session, truth: &Truth, sigma: f64) -> Option<Observable> {
    let (cams, info) = truth_information(session, truth, sigma)?;
    let eig = rigcal_core::linalg::symmetric_eigen(&info);
    let max = eig.eigenvalues.max();
    let n = info.nrows();
    let mut projector = DMatrix::zeros(n, n);
    let mut crb = DMatrix::zeros(n, n);
    let mut null_dim = 0;
    for (i, &l) in eig.eigenvalues.iter().enumerate() {
        let v = eig.eigenvectors.column(i);
        if l > 1e-9 * max {
            projector += v * v.transpose();
            crb += v * v.transpose() * (sigma * sigma / l);
        } else {
            null_dim += 1;
        }
    }
    Some(Observable {
        cams,
        projector,
        crb,
        null_dim,
    })
}

/// Information of the extrinsics at the truth for pixel noise `sigma`: the cameras in
/// session order except the reference, and the joint matrix with 6×6 blocks `[dt, dφ]`.
fn truth_information(
    session: &Session,
    truth: &Truth,
    sigma: f64,
) -> Option<(Vec<usize>, DMatrix<f64>)> {
    let ids: Vec<&str> = session.cameras.iter().map(|c| c.id.as_str()).collect();
    let world_from_ref0 = truth.world_from_rig[0];
    // Express the truth in the estimator's gauge: world = reference camera at frame 0.
    let to_gauge = world_from_ref0.inverse();
    // Free points at their true position; rigid bodies (boards, tags) at the pose that
    // carries their known corners onto the true ones.
    let mut refs = Vec::with_capacity(session.points.ids.len());
    let mut points = Vec::new();
    let mut body_pairs: Vec<Vec<(Vec3, Vec3)>> = vec![Vec::new(); session.points.bodies.len()];
    for (p, id) in session.points.ids.iter().enumerate() {
        let x = truth.points.get(id)?;
        let world = to_gauge.apply(&Vec3::new(x[0], x[1], x[2]));
        refs.push(match session.points.kinds[p] {
            PointKind::Body { body, local } => {
                body_pairs[body].push((local, world));
                PointRef::Body { body, local }
            }
            PointKind::Free => {
                points.push(world);
                PointRef::Free(points.len() - 1)
            }
        });
    }
    let world_from_body: Vec<Pose> = body_pairs.iter().map(|p| fit_rigid(p)).collect();
    let mut observations = Vec::new();
    for (k, f) in session.frames.iter().enumerate() {
        for (c, obs) in f.observations.iter().enumerate() {
            for o in obs {
                observations.push(Obs {
                    rig: k,
                    cam: c,
                    point: refs[o.point],
                    uv: o.uv,
                });
            }
        }
    }
    let problem = BundleProblem {
        cameras: session.cameras.iter().map(|c| c.camera.clone()).collect(),
        rig_from_cam: ids.iter().map(|id| truth.ref_from_cam[*id]).collect(),
        cam_fixed: (0..ids.len()).map(|c| c == session.reference).collect(),
        world_from_rig: truth.world_from_rig.iter().map(|w| to_gauge * *w).collect(),
        rig_fixed: (0..truth.world_from_rig.len()).map(|k| k == 0).collect(),
        points,
        body_fixed: vec![false; world_from_body.len()],
        world_from_body,
        observations,
        distances: session
            .distances
            .iter()
            .map(|d| DistanceConstraint {
                a: refs[d.a],
                b: refs[d.b],
                distance: d.distance,
                sigma: d.sigma,
            })
            .collect(),
        priors: vec![],
        pixel_sigma: sigma,
    };
    problem.extrinsic_information(&Loss::Squared)
}

/// The rigid motion taking the `(local, world)` pairs' local points onto their world
/// points (Kabsch: SVD of the cross-covariance, reflection excluded).
fn fit_rigid(pairs: &[(Vec3, Vec3)]) -> Pose {
    if pairs.is_empty() {
        return Pose::identity();
    }
    let n = pairs.len() as f64;
    let cl = pairs.iter().map(|p| p.0).sum::<Vec3>() / n;
    let cw = pairs.iter().map(|p| p.1).sum::<Vec3>() / n;
    let h = pairs.iter().fold(nalgebra::Matrix3::zeros(), |h, (l, w)| {
        h + (w - cw) * (l - cl).transpose()
    });
    let svd = h.svd(true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
        return Pose::identity();
    };
    let d = (u * vt).determinant().signum();
    let rot = u * nalgebra::Matrix3::from_diagonal(&Vec3::new(1.0, 1.0, d)) * vt;
    Pose::new(rot, cw - rot * cl)
}

/// Run `trials` noisy trials per noise level; errors pooled over the non-reference cameras.
pub fn accuracy(preset: &str, sigmas: &[f64], trials: usize, seed0: u64) -> Vec<AccuracyRow> {
    let mut rows = Vec::new();
    for &sigma in sigmas {
        let mut row = AccuracyRow {
            sigma_px: sigma,
            ..Default::default()
        };
        let (mut it, mut ir, mut rt, mut rr, mut ct, mut cr, mut nees) =
            (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        let mut n = 0usize;
        let mut n_nees = 0usize;
        for trial in 0..trials {
            let Some((session, truth)) = synthetic_session(preset, seed0 + trial as u64, sigma)
            else {
                continue;
            };
            let doc: ResultDocument = calibrate(&session, &CalibOptions::default());
            row.trials += 1;
            if doc.status == Status::Failed {
                row.failed += 1;
                continue;
            }
            let Some(obs) = observable(&session, &truth, sigma) else {
                continue;
            };
            // Errors stacked like the information, then reduced to the observable part.
            let stack = |pick: &dyn Fn(usize) -> SVector<f64, 6>| {
                let mut v = nalgebra::DVector::zeros(6 * obs.cams.len());
                for (i, &c) in obs.cams.iter().enumerate() {
                    v.rows_mut(6 * i, 6).copy_from(&pick(c));
                }
                &obs.projector * v
            };
            let truth_of = |c: usize| truth.ref_from_cam[&session.cameras[c].id];
            let e_ba = stack(&|c| {
                error6(
                    &ExtrinsicValue::pose(&doc.extrinsics[c].value),
                    &truth_of(c),
                )
            });
            let e_init =
                stack(&|c| error6(&ExtrinsicValue::pose(&doc.initialisation[c]), &truth_of(c)));
            row.unobservable = obs.null_dim;
            for (i, &c) in obs.cams.iter().enumerate() {
                let e = e_ba.rows(6 * i, 6);
                let e0 = e_init.rows(6 * i, 6);
                it += e0.rows(0, 3).norm_squared();
                ir += e0.rows(3, 3).norm_squared();
                rt += e.rows(0, 3).norm_squared();
                rr += e.rows(3, 3).norm_squared();
                n += 1;
                ct += (0..3).map(|k| obs.crb[(6 * i + k, 6 * i + k)]).sum::<f64>();
                cr += (3..6).map(|k| obs.crb[(6 * i + k, 6 * i + k)]).sum::<f64>();
                // NEES only where every direction is determined, by the truth and by the
                // result: elsewhere the reported covariance is singular along the held
                // heights.
                let held = doc
                    .singularity
                    .as_ref()
                    .is_some_and(|s| !s.unobservable_directions.is_empty());
                if obs.null_dim > 0 || held {
                    continue;
                }
                if let Some(cov) = doc.extrinsics[c].covariance {
                    let m = DMatrix::from_fn(6, 6, |a, b| cov[a][b]);
                    if let Some(inv) = m.try_inverse() {
                        let ev = DMatrix::from_column_slice(6, 1, e.as_slice());
                        nees += (ev.transpose() * inv * &ev)[(0, 0)];
                        n_nees += 1;
                    }
                }
            }
        }
        let nf = n.max(1) as f64;
        row.init_t_mm = (it / nf).sqrt() * 1e3;
        row.init_r_deg = (ir / nf).sqrt().to_degrees();
        row.refined_t_mm = (rt / nf).sqrt() * 1e3;
        row.refined_r_deg = (rr / nf).sqrt().to_degrees();
        row.crb_t_mm = (ct / nf).sqrt() * 1e3;
        row.crb_r_deg = (cr / nf).sqrt().to_degrees();
        row.nees = if n_nees > 0 {
            nees / n_nees as f64
        } else {
            f64::NAN
        };
        rows.push(row);
    }
    rows
}

pub fn print_table(preset: &str, rows: &[AccuracyRow]) {
    println!("preset {preset}: RMS extrinsic errors over non-reference cameras (translation mm, rotation deg)");
    println!(
        "{:>6} {:>7} {:>7} | {:>9} {:>9} | {:>9} {:>9} | {:>9} {:>9} | {:>7} {:>7} | {:>6}",
        "σ px",
        "trials",
        "failed",
        "init t",
        "init R",
        "BA t",
        "BA R",
        "CRB t",
        "CRB R",
        "BA/CRB",
        "init/BA",
        "NEES"
    );
    for r in rows {
        println!(
            "{:>6.2} {:>7} {:>7} | {:>9.3} {:>9.4} | {:>9.3} {:>9.4} | {:>9.3} {:>9.4} | {:>7.2} {:>7.2} | {:>6.2}",
            r.sigma_px,
            r.trials,
            r.failed,
            r.init_t_mm,
            r.init_r_deg,
            r.refined_t_mm,
            r.refined_r_deg,
            r.crb_t_mm,
            r.crb_r_deg,
            r.refined_t_mm / r.crb_t_mm,
            r.init_t_mm / r.refined_t_mm,
            r.nees
        );
    }
    if let Some(r) = rows.iter().find(|r| r.unobservable > 0) {
        println!(
            "errors and bound of the observable part only: {} direction(s) the motion leaves undetermined are held at the prior (NEES not defined)",
            r.unobservable
        );
    }
}

/// One trial's per-camera trajectories for a hand-eye peer (OpenCV `calibrateHandEye`):
/// per frame where both the reference and `camera` are posed in their own scenes,
/// `ref_from_scene` and `cam_from_scene` (4×4), plus the truth and rigcal's answers.
#[derive(serde::Serialize)]
pub struct HandEyeTrial {
    pub camera: String,
    pub truth_ref_from_cam: [[f64; 4]; 4],
    pub rigcal_init: [[f64; 4]; 4],
    pub rigcal_refined: [[f64; 4]; 4],
    pub ref_from_scene: Vec<[[f64; 4]; 4]>,
    pub cam_from_scene: Vec<[[f64; 4]; 4]>,
}

/// Trials of `preset` at noise `sigma` exported for hand-eye peers (non-reference cameras).
pub fn handeye_trials(preset: &str, sigma: f64, trials: usize, seed0: u64) -> Vec<HandEyeTrial> {
    let mut out = Vec::new();
    for trial in 0..trials {
        let Some((session, truth)) = synthetic_session(preset, seed0 + trial as u64, sigma) else {
            continue;
        };
        let lm = rigcal_solve::bundle::LmOptions {
            loss: Loss::Huber { scale: 2.0 },
            ..Default::default()
        };
        let Ok(traj) = rigcal_calib::trajectory::estimate(&session, &lm) else {
            continue;
        };
        let doc = calibrate(&session, &CalibOptions::default());
        if doc.status == Status::Failed {
            continue;
        }
        // Each camera's own scene: the one it is posed in most often.
        let own = |c: usize| -> Option<usize> {
            (0..traj.scenes.len())
                .max_by_key(|s| traj.scenes[*s].poses.keys().filter(|k| k.1 == c).count())
        };
        let r = session.reference;
        let Some(sr) = own(r) else { continue };
        for (c, cam) in session.cameras.iter().enumerate() {
            if c == r {
                continue;
            }
            let Some(sc) = own(c) else { continue };
            let mut ref_from_scene = Vec::new();
            let mut cam_from_scene = Vec::new();
            for f in 0..session.frames.len() {
                if let (Some(a), Some(b)) = (
                    traj.scenes[sr].poses.get(&(f, r)),
                    traj.scenes[sc].poses.get(&(f, c)),
                ) {
                    ref_from_scene.push(a.matrix());
                    cam_from_scene.push(b.matrix());
                }
            }
            out.push(HandEyeTrial {
                camera: cam.id.clone(),
                truth_ref_from_cam: truth.ref_from_cam[&cam.id].matrix(),
                rigcal_init: doc.initialisation[c].ref_from_cam,
                rigcal_refined: doc.extrinsics[c].value.ref_from_cam,
                ref_from_scene,
                cam_from_scene,
            });
        }
    }
    out
}
