//! Translations the solution leaves undetermined, brought back to their held value.
//!
//! A group of cameras that shares no scene with the reference can slide along a
//! direction that no observation sees (the rig's vertical under planar motion): the
//! cameras move by `δ` in the rig frame, the scenes only they see by `R δ` in the world,
//! and every residual stays as it was. Where the motion class says so at the
//! initialisation, [`crate::diagnostics::planar_height_directions`] holds such a height
//! from the start. Where the trajectories' noise made the motion look general, nothing
//! held it, and the adjustment ends wherever its steps left it along that direction —
//! metres out on a capture whose initialisation got a camera's rotation wrong — while
//! every other camera's undetermined height sits at 0. This moves it there too, the
//! scenes with it in the same step, so the cost does not change; the direction is still
//! reported as undetermined.

use nalgebra::{DVector, Vector3, Vector6};
use rigcal_solve::bundle::{BundleProblem, DirectionPrior, PointRef};
use rigcal_solve::Loss;

/// Largest rotation component, and largest difference between the cameras' translation
/// components, of a direction that is a rigid slide of a group of cameras (a numerical
/// null direction is exact to far better than this).
const SLIDE_TOLERANCE: f64 = 1e-3;

/// Largest rise of χ² (the cost in units of the pixel noise) a slide may leave once the
/// scenes have settled again: a 3σ move along one direction. A slide along a direction
/// the data do not see rises far less (~4 for metres on a dense hall capture, whose
/// σ along it is metres too); one that is no gauge, by pixels at thousands of corners.
const MAX_CHI2_RISE: f64 = 9.0;

/// Slide each group of cameras along the null directions `null` (unit vectors over the
/// free cameras `cams`, 6 per camera: translation then rotation, as
/// [`BundleProblem::extrinsic_information`] orders them) to where its component is the
/// held value `held(camera, u)` (the height along the unit rig-frame direction `u`),
/// carrying the points and bodies only those cameras see, then let `settle` adjust the
/// rest with the slid direction held (the rig's turns are planar only to the noise, so
/// the scenes' shifts are exact only to it). A direction that is not such a slide, or
/// whose slide raises the cost by more than noise `sigma_px` explains, is left alone.
/// `problem` must hold no priors. Returns the moved directions, each with the prior that
/// now holds it.
pub fn recentre(
    problem: &mut BundleProblem,
    cams: &[usize],
    null: &[DVector<f64>],
    held: impl Fn(usize, &Vector3<f64>) -> f64,
    sigma_px: f64,
    settle: impl Fn(&mut BundleProblem),
) -> Vec<(DVector<f64>, DirectionPrior)> {
    let mut moved = Vec::new();
    for v in null {
        let Some((members, u)) = slide(v, cams.len()) else {
            continue;
        };
        let k = (members.len() as f64).sqrt();
        // v·x over the stacked translations, and the value it is held at.
        let now: f64 = members
            .iter()
            .map(|&i| u.dot(&problem.rig_from_cam[cams[i]].trans) / k)
            .sum();
        let target: f64 = members.iter().map(|&i| held(cams[i], &u) / k).sum();
        let s = target - now;
        if s.abs() < 1e-9 {
            continue;
        }
        let group: Vec<usize> = members.iter().map(|&i| cams[i]).collect();
        let Some(mut candidate) = slid(problem, &group, u * (s / k)) else {
            continue;
        };
        let prior = DirectionPrior {
            terms: group
                .iter()
                .map(|&c| (c, Vector6::new(u.x / k, u.y / k, u.z / k, 0.0, 0.0, 0.0)))
                .collect(),
            origin: group.iter().map(|&c| candidate.rig_from_cam[c]).collect(),
            sigma: crate::rig_ba::HOLD_PRIOR_SIGMA,
        };
        candidate.priors = vec![prior];
        settle(&mut candidate);
        let prior = candidate.priors.pop();
        let (before, after) = (problem.cost(&Loss::Squared), candidate.cost(&Loss::Squared));
        if after.is_finite() && 2.0 * (after - before) <= MAX_CHI2_RISE * sigma_px * sigma_px {
            *problem = candidate;
            moved.extend(prior.map(|p| (v.clone(), p)));
        }
    }
    moved
}

/// The members (indices into the free cameras) of the group `v` slides and the unit
/// rig-frame direction it slides them along, if `v` is a rigid slide: no rotation, the
/// same translation for every camera it touches.
fn slide(v: &DVector<f64>, n: usize) -> Option<(Vec<usize>, Vector3<f64>)> {
    let part =
        |i: usize, off: usize| Vector3::new(v[6 * i + off], v[6 * i + off + 1], v[6 * i + off + 2]);
    if (0..n).any(|i| part(i, 3).norm() > SLIDE_TOLERANCE) {
        return None;
    }
    let members: Vec<usize> = (0..n)
        .filter(|&i| part(i, 0).norm() > SLIDE_TOLERANCE)
        .collect();
    let first = part(*members.first()?, 0);
    if members
        .iter()
        .any(|&i| (part(i, 0) - first).norm() > SLIDE_TOLERANCE)
    {
        return None;
    }
    Some((members, first.normalize()))
}

/// `problem` with the cameras `group` moved by `delta` (rig frame) and every point and
/// body they see by `delta` turned into the world at the rig poses they were seen from
/// (the same vector where the slide is a true null direction). `None` if something the
/// group sees is also seen by another camera: then the slide is no gauge.
fn slid(problem: &BundleProblem, group: &[usize], delta: Vector3<f64>) -> Option<BundleProblem> {
    let mut shift_point = vec![(Vector3::zeros(), 0usize); problem.points.len()];
    let mut shift_body = vec![(Vector3::zeros(), 0usize); problem.world_from_body.len()];
    let mut foreign_point = vec![false; problem.points.len()];
    let mut foreign_body = vec![false; problem.world_from_body.len()];
    for o in &problem.observations {
        let ours = group.contains(&o.cam);
        let world = problem.world_from_rig[o.rig].rot * delta;
        let (shift, foreign) = match o.point {
            PointRef::Free(p) => (&mut shift_point[p], &mut foreign_point[p]),
            PointRef::Body { body, .. } => (&mut shift_body[body], &mut foreign_body[body]),
        };
        if ours {
            shift.0 += world;
            shift.1 += 1;
        } else {
            *foreign = true;
        }
    }
    let shared = |shift: &[(Vector3<f64>, usize)], foreign: &[bool]| {
        shift.iter().zip(foreign).any(|((_, n), f)| *n > 0 && *f)
    };
    if shared(&shift_point, &foreign_point) || shared(&shift_body, &foreign_body) {
        return None;
    }
    let mut out = problem.clone();
    for &c in group {
        out.rig_from_cam[c].trans += delta;
    }
    for (x, (sum, n)) in out.points.iter_mut().zip(&shift_point) {
        if *n > 0 {
            *x += sum / *n as f64;
        }
    }
    for (b, (sum, n)) in out.world_from_body.iter_mut().zip(&shift_body) {
        if *n > 0 {
            b.trans += sum / *n as f64;
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diagnostics::null_directions;
    use rigcal_core::geometry::{Camera, Pose, Vec2, Vec3};
    use rigcal_solve::bundle::{DistanceConstraint, LmOptions, Obs};

    /// A two-camera rig turning about the vertical (y) only, planar motion, its second
    /// camera turned 57° to the right and 0.3 m below the reference, seeing a scene of
    /// its own: its height is a gauge. `shared`: the reference also sees one of that
    /// scene's points, which ties it.
    fn planar_rig(shared: bool) -> BundleProblem {
        let cam = Camera::pinhole(700.0, 700.0, 320.0, 240.0, 640, 480);
        let rig_from_cam = vec![
            Pose::identity(),
            Pose::from_rotvec(Vec3::new(0.0, 1.0, 0.0), Vec3::new(0.4, 0.3, -0.5)),
        ];
        let world_from_rig: Vec<Pose> = (0..8)
            .map(|k| {
                let k = k as f64;
                Pose::from_rotvec(
                    Vec3::new(0.0, 0.12 * k - 0.4, 0.0),
                    Vec3::new(0.1 * (1.3 * k).sin(), 0.0, 0.3 * k),
                )
            })
            .collect();
        let mut p = BundleProblem {
            cameras: vec![cam.clone(), cam],
            rig_from_cam,
            cam_fixed: vec![true, false],
            world_from_rig,
            rig_fixed: (0..8).map(|k| k == 0).collect(),
            points: vec![],
            world_from_body: vec![],
            body_fixed: vec![],
            observations: vec![],
            // The metric scale: two of the reference's points a measured distance apart.
            distances: vec![DistanceConstraint {
                a: PointRef::Free(0),
                b: PointRef::Free(11),
                distance: 0.0,
                sigma: 1e-4,
            }],
            priors: vec![],
            pixel_sigma: 1.0,
        };
        for c in 0..2 {
            let world_from_cam = p.world_from_rig[3] * p.rig_from_cam[c];
            for i in 0..12 {
                let p_cam = Vec3::new(
                    -0.5 + 0.09 * i as f64,
                    0.35 * ((i % 3) as f64 - 1.0),
                    3.0 + 0.4 * (i % 4) as f64,
                );
                p.add_point_seen_from_every_rig(world_from_cam.apply(&p_cam), c);
            }
        }
        if shared {
            // The second camera's last point, in front of the reference too.
            p.observations.push(Obs {
                rig: 5,
                cam: 0,
                point: PointRef::Free(p.points.len() - 1),
                uv: Vec2::zeros(),
            });
        }
        assert_eq!(p.observe_exactly(), 0, "every point in front of its camera");
        p.distances[0].distance = (p.points[0] - p.points[11]).norm();
        p
    }

    /// The second camera and its scene `dz` metres down: the same residuals.
    fn raised(p: &BundleProblem, dz: f64) -> BundleProblem {
        slid(p, &[1], Vec3::new(0.0, dz, 0.0)).expect("the rear's scene is its own")
    }

    fn settle(p: &mut BundleProblem) {
        p.solve(&LmOptions {
            loss: Loss::Squared,
            ..LmOptions::default()
        });
    }

    fn recentred(p: &mut BundleProblem, sigma_px: f64) -> usize {
        let (cams, info) = p
            .extrinsic_information(&Loss::Squared)
            .expect("information");
        let null = null_directions(&info, sigma_px);
        recentre(p, &cams, &null, |_, _| 0.0, sigma_px, settle).len()
    }

    #[test]
    fn a_slid_height_comes_back_to_its_held_value_with_its_scene() {
        let mut p = raised(&planar_rig(false), 5.0);
        assert!(p.cost(&Loss::Squared) < 1e-16, "the slide is a gauge");
        assert_eq!(recentred(&mut p, 0.01), 1);
        let t = p.rig_from_cam[1].trans;
        // (The null direction's numerical tilt, ~10⁻⁷, over the 5 m it slides.)
        assert!(t.y.abs() < 1e-6, "held at 0: {t:?}");
        assert!(
            (t.x - 0.4).abs() < 1e-9 && (t.z + 0.5).abs() < 1e-9,
            "{t:?}"
        );
        assert!(p.cost(&Loss::Squared) < 1e-16);
    }

    #[test]
    fn with_noise_the_slide_lands_on_the_held_value_at_no_significant_cost() {
        let sigma = 0.5;
        let mut p = planar_rig(false);
        let mut rng = 12345u64;
        for o in &mut p.observations {
            let mut gauss = || {
                // Box–Muller from a 64-bit LCG: reproducible, no dependency.
                let mut u = || {
                    rng = rng
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    ((rng >> 11) as f64 + 0.5) / (1u64 << 53) as f64
                };
                (-2.0 * u().ln()).sqrt() * (std::f64::consts::TAU * u()).cos()
            };
            o.uv += Vec2::new(sigma * gauss(), sigma * gauss());
        }
        settle(&mut p);
        let mut p = raised(&p, -7.0);
        let before = p.cost(&Loss::Squared);
        assert_eq!(recentred(&mut p, sigma), 1);
        let t = p.rig_from_cam[1].trans;
        // Held at 0 along the null direction as the noisy data put it (tilted ~10⁻³).
        assert!(t.y.abs() < 5e-3, "held at 0: {t:?}");
        assert!(
            (t.x - 0.4).abs() < 0.05 && (t.z + 0.5).abs() < 0.05,
            "{t:?}"
        );
        let rise = 2.0 * (p.cost(&Loss::Squared) - before) / (sigma * sigma);
        assert!(rise < MAX_CHI2_RISE, "χ² rose by {rise}");
    }

    #[test]
    fn a_height_a_shared_point_ties_is_left_alone() {
        let mut p = planar_rig(true);
        let (cams, _) = p
            .extrinsic_information(&Loss::Squared)
            .expect("information");
        // Offered the slide anyway: the shared point refuses it.
        let mut v = DVector::zeros(6 * cams.len());
        v[1] = 1.0;
        p.rig_from_cam[1].trans.y += 1.0;
        let before = p.rig_from_cam[1].trans;
        assert!(recentre(&mut p, &cams, &[v], |_, _| 0.0, 0.01, settle).is_empty());
        assert_eq!(p.rig_from_cam[1].trans, before);
    }
}
