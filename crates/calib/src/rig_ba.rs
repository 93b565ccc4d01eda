//! Rig bundle adjustment (Lébraly §4): master-camera (reference) poses, extrinsics and
//! scene points (or rigid bodies) refined together.
//!
//! Gauge: the reference camera's first posed frame is fixed (6 DOF), the metric scale
//! comes from rigid bodies or measured distances. The paper leaves the gauge free under
//! LM damping; fixing it gives the same minimum and a well-posed covariance.
//!
//! Two passes: a robust pass (Huber) to find gross outliers, then a least-squares pass
//! on the inliers, so the estimate is efficient and the covariance honest.

use super::handeye::InitOutput;
use super::trajectory::Trajectories;
use nalgebra::{DMatrix, DVector};
use rigcal_core::geometry::Vec2;
use rigcal_core::session::Session;
use rigcal_solve::bundle::{BundleProblem, BundleSummary, DirectionPrior, LmOptions, Obs};
use rigcal_solve::{robust_sigma, Loss};
use std::collections::HashMap;

#[derive(Clone, Debug)]
pub struct RigBaOptions {
    /// Robust loss of the first pass; its scale is in pixels.
    pub loss: Loss,
    /// Residuals above `max(outlier_sigmas · σ̂, min_outlier_px)` are outliers.
    pub outlier_sigmas: f64,
    pub min_outlier_px: f64,
    pub max_iterations: usize,
}

impl Default for RigBaOptions {
    fn default() -> Self {
        Self {
            loss: Loss::Huber { scale: 2.0 },
            outlier_sigmas: 5.0,
            min_outlier_px: 1.0,
            max_iterations: 100,
        }
    }
}

/// An observation of the session in the rig problem: (frame, camera, point) and its obs.
#[derive(Clone, Copy, Debug)]
pub struct ObsKey {
    pub frame: usize,
    pub camera: usize,
    pub point: usize,
}

pub struct RigBaOutput {
    pub problem: BundleProblem,
    pub keys: Vec<ObsKey>,
    /// Outliers removed after the robust pass: (key, residual px).
    pub outliers: Vec<(ObsKey, f64)>,
    pub summary: BundleSummary,
    /// Pixel noise estimated from the final inlier cost and the redundancy.
    pub sigma_px: f64,
    /// Free cameras and their joint marginal information (unit pixel noise).
    pub information: Option<(Vec<usize>, DMatrix<f64>)>,
    /// Frame index (position in `session.frames`) of every rig pose.
    pub rig_frames: Vec<usize>,
    /// The planar heights held at the initialisation (unit vectors over the free cameras
    /// of `information`).
    pub held_directions: Vec<DVector<f64>>,
    /// The directions the solution left undetermined that were slid back to their held
    /// value ([`crate::undetermined`]; same space).
    pub recentred_directions: Vec<DVector<f64>>,
}

/// 1-σ (m or rad) of the priors holding undeterminable directions at the initial value:
/// tight, because along such a direction the data carry no information at all.
pub const HOLD_PRIOR_SIGMA: f64 = 1e-4;

/// Priors holding every direction of the extrinsics that the data leave undetermined:
/// the planar heights of the motion class, and what the information at the
/// initialisation does not determine (see [`crate::diagnostics`]). Returns the
/// priors and the held planar heights (unit vectors over the free cameras).
fn hold_priors(
    problem: &BundleProblem,
    decision_sigma_px: f64,
    heights: impl FnOnce(&[usize]) -> Vec<DVector<f64>>,
) -> (Vec<DirectionPrior>, Vec<DVector<f64>>) {
    let Some((cams, info)) = problem.extrinsic_information(&Loss::Squared) else {
        return (vec![], vec![]);
    };
    let held = heights(&cams);
    let others = crate::diagnostics::null_directions_besides(&info, decision_sigma_px, &held);
    let priors = held
        .iter()
        .cloned()
        .chain(others)
        .map(|v| {
            let terms: Vec<(usize, nalgebra::Vector6<f64>)> = cams
                .iter()
                .enumerate()
                .map(|(i, c)| {
                    (
                        *c,
                        nalgebra::Vector6::from_iterator((0..6).map(|k| v[6 * i + k])),
                    )
                })
                .filter(|(_, x)| x.norm() > 1e-9)
                .collect();
            let origin = terms
                .iter()
                .map(|(c, _)| problem.rig_from_cam[*c])
                .collect();
            DirectionPrior {
                terms,
                origin,
                sigma: HOLD_PRIOR_SIGMA,
            }
        })
        .collect();
    (priors, held)
}

pub fn refine(
    session: &Session,
    traj: &Trajectories,
    init: &InitOutput,
    opts: &RigBaOptions,
) -> RigBaOutput {
    let nc = session.cameras.len();
    let rig_frames: Vec<usize> = (0..session.frames.len())
        .filter(|f| init.world_from_rig[*f].is_some())
        .collect();
    let rig_of_frame: HashMap<usize, usize> = rig_frames
        .iter()
        .enumerate()
        .map(|(i, f)| (*f, i))
        .collect();
    // Points and bodies in the world frame (the base frame of the reference camera).
    let mut points = Vec::new();
    let mut point_index = HashMap::new();
    let mut bodies = Vec::new();
    let mut body_index = HashMap::new();
    for (s, scene) in traj.scenes.iter().enumerate() {
        let Some(w_from_s) = init.world_from_scene[s] else {
            continue;
        };
        let scale = init.scene_scale.get(s).copied().unwrap_or(1.0);
        for (p, x) in &scene.points {
            point_index.insert(*p, points.len());
            points.push(w_from_s.apply(&(x * scale)));
        }
        for (b, s_from_b) in &scene.bodies {
            body_index.insert(*b, bodies.len());
            bodies.push(
                w_from_s * rigcal_core::geometry::Pose::new(s_from_b.rot, s_from_b.trans * scale),
            );
        }
    }
    let point_ref =
        |p: usize| super::point_ref(session.points.kinds[p], p, &point_index, &body_index);
    let mut observations = Vec::new();
    let mut keys = Vec::new();
    for (fi, f) in session.frames.iter().enumerate() {
        let Some(&rig) = rig_of_frame.get(&fi) else {
            continue;
        };
        for (ci, obs) in f.observations.iter().enumerate() {
            for o in obs {
                if let Some(point) = point_ref(o.point) {
                    observations.push(Obs {
                        rig,
                        cam: ci,
                        point,
                        uv: o.uv,
                    });
                    keys.push(ObsKey {
                        frame: fi,
                        camera: ci,
                        point: o.point,
                    });
                }
            }
        }
    }
    let distances = super::distance_constraints(session, point_ref);
    let base = rig_frames
        .iter()
        .position(|f| {
            init.world_from_rig[*f]
                .is_some_and(|p| p.trans.norm() == 0.0 && p.rot == nalgebra::Matrix3::identity())
        })
        .unwrap_or(0);
    let mut problem = BundleProblem {
        cameras: session.cameras.iter().map(|c| c.camera.clone()).collect(),
        rig_from_cam: init.ref_from_cam.clone(),
        cam_fixed: (0..nc).map(|c| c == session.reference).collect(),
        world_from_rig: rig_frames
            .iter()
            .map(|f| init.world_from_rig[*f].unwrap_or_default())
            .collect(),
        rig_fixed: (0..rig_frames.len()).map(|i| i == base).collect(),
        points,
        world_from_body: bodies.clone(),
        body_fixed: vec![false; bodies.len()],
        observations,
        distances,
        priors: vec![],
        pixel_sigma: 1.0,
    };
    // Observations behind their camera at the start cannot be linearised: drop them.
    let keep = problem.drop_unprojectable();
    let mut k = keep.iter();
    keys.retain(|_| *k.next().unwrap_or(&false));

    // Hold what the data cannot determine, judged at the noise level the per-scene
    // adjustments saw.
    let decision_sigma = traj.median_scene_sigma().unwrap_or(1.0);
    let (priors, held_directions) = hold_priors(&problem, decision_sigma, |cams| {
        crate::diagnostics::planar_height_directions(traj, init, session.reference, cams)
    });
    problem.priors = priors;

    let lm = |loss| LmOptions {
        max_iterations: opts.max_iterations,
        loss,
        ..LmOptions::default()
    };
    let robust = problem.solve_annealed(&lm(opts.loss));
    // Outliers by a robust estimate of σ.
    let norms: Vec<f64> = problem
        .observations
        .iter()
        .map(|o| problem.residual(o).map_or(f64::INFINITY, |r| r.norm()))
        .collect();
    let sigma_robust = robust_sigma(&norms).unwrap_or(0.0);
    let threshold = (opts.outlier_sigmas * sigma_robust).max(opts.min_outlier_px);
    let mut outliers = Vec::new();
    let mut inlier_obs = Vec::new();
    let mut inlier_keys = Vec::new();
    for ((o, key), e) in problem.observations.iter().zip(&keys).zip(&norms) {
        if *e > threshold {
            outliers.push((*key, *e));
        } else {
            inlier_obs.push(*o);
            inlier_keys.push(*key);
        }
    }
    problem.observations = inlier_obs;
    problem.pixel_sigma = sigma_robust.max(0.05);
    let mut summary = problem.solve(&lm(Loss::Squared));
    summary.iterations += robust.iterations;
    summary.initial_cost = robust.initial_cost;
    summary.seconds += robust.seconds;

    // σ̂² = Σ r² / (m − n): redundancy of the inlier problem.
    let m = 2 * problem.observations.len() + problem.distances.len();
    let free_rigs = problem.rig_fixed.iter().filter(|f| !**f).count();
    let free_cams = problem.cam_fixed.iter().filter(|f| !**f).count();
    let n = 6 * (free_rigs + free_cams + problem.world_from_body.len()) + 3 * problem.points.len();
    let ss: f64 = problem
        .observations
        .iter()
        .filter_map(|o| problem.residual(o))
        .map(|r: Vec2| r.norm_squared())
        .sum();
    let sigma_px = if m > n {
        (ss / (m - n) as f64).sqrt()
    } else {
        f64::NAN
    };
    // Report observability from the data alone: the holding priors are taken out.
    let priors = std::mem::take(&mut problem.priors);
    let mut information = problem.extrinsic_information(&Loss::Squared);
    // What nothing held from the start and the data leave undetermined goes back to
    // its held value, as the held heights are (0, or the session's height prior).
    let moved = match &information {
        Some((cams, info)) => {
            let null =
                crate::diagnostics::null_directions_besides(info, decision_sigma, &held_directions);
            let axis = nalgebra::Vector3::from(init.motion.axis).normalize();
            let held = |c: usize, u: &nalgebra::Vector3<f64>| {
                let along = axis.dot(u);
                match session.height_priors[c] {
                    Some(h) if along.abs() > 0.99 => h * along,
                    _ => 0.0,
                }
            };
            let settle = |p: &mut BundleProblem| {
                p.solve(&lm(Loss::Squared));
            };
            crate::undetermined::recentre(&mut problem, cams, &null, held, sigma_px, settle)
        }
        None => vec![],
    };
    if !moved.is_empty() {
        information = problem.extrinsic_information(&Loss::Squared);
    }
    let (recentred_directions, added_priors): (Vec<_>, Vec<_>) = moved.into_iter().unzip();
    problem.priors = priors;
    problem.priors.extend(added_priors);
    RigBaOutput {
        problem,
        keys: inlier_keys,
        outliers,
        summary,
        sigma_px,
        information,
        rig_frames,
        held_directions,
        recentred_directions,
    }
}
