//! Camera pose from known 3D points (PnP): a homography for planar point sets, the
//! DLT otherwise, both on undistorted normalised coordinates, then Levenberg–Marquardt
//! on the pixel reprojection error with the full camera model.

use nalgebra::{DMatrix, Matrix3x4, Matrix6, Vector6, U6};
use rigcal_core::geometry::homography::homography;
use rigcal_core::geometry::plane::{is_planar, principal_axes};
use rigcal_core::geometry::{so3, Camera, Mat3, Pose, Vec2, Vec3};
use rigcal_core::linalg::null_vector;
use rigcal_solve::lm::{minimize, Dense, LeastSquares, Rules};

/// `cam_from_local` from at least 4 (planar) or 6 (general) correspondences.
pub fn estimate_pose(camera: &Camera, local: &[Vec3], uv: &[Vec2]) -> Option<Pose> {
    solve_pose(camera, local, uv).map(|f| f.pose)
}

/// A pose and whether the data single it out.
#[derive(Clone, Copy, Debug)]
pub struct PoseFit {
    pub pose: Pose,
    /// Sum of squared reprojection errors (px²).
    pub cost: f64,
    /// Another pose, rotated more than [`DISTINCT_DEG`] from this one, explains the
    /// points nearly as well (see [`ambiguous`]).
    pub ambiguous: bool,
}

/// Poses closer than this (deg) are one solution reached twice.
pub const DISTINCT_DEG: f64 = 1.0;

/// A plane seen small, far away or nearly head-on has two poses of almost the same
/// reprojection error: the true one and its mirror about the line of sight (the two
/// minima that IPPE finds). Noise of a few hundredths of a pixel decides between them
/// on a 20 px tag, and the wrong one is tilted by twice the angle between the normal and
/// the line of sight — a "motion" of tens of degrees that never happened. So the mirror
/// is refined too and compared: the fit is ambiguous when it is not worse by a clear
/// margin (`Δχ² < 16`, with σ² from the best fit's own residual, at least 0.1 px).
pub fn ambiguous(best: f64, second: f64, observations: usize) -> bool {
    let dof = (2 * observations).saturating_sub(6).max(1) as f64;
    let sigma2 = (best / dof).max(MIN_AMBIGUITY_SIGMA_PX * MIN_AMBIGUITY_SIGMA_PX);
    second - best < 16.0 * sigma2
}

const MIN_AMBIGUITY_SIGMA_PX: f64 = 0.5;

/// [`estimate_pose`] with both planar solutions refined: the better one, its cost, and
/// whether the other is nearly as good. A non-planar point set has one solution.
pub fn solve_pose(camera: &Camera, local: &[Vec3], uv: &[Vec2]) -> Option<PoseFit> {
    let xy: Vec<Vec2> = uv
        .iter()
        .map(|p| camera.unproject(p))
        .collect::<Option<_>>()?;
    if !is_planar(local) {
        let pose = refine_pose(camera, local, uv, dlt_pose(local, &xy)?);
        return Some(PoseFit {
            pose,
            cost: reprojection_cost(camera, local, uv, &pose),
            ambiguous: false,
        });
    }
    let first = refine_pose(camera, local, uv, planar_pose(local, &xy)?);
    let second = refine_pose(camera, local, uv, mirrored(&first, local));
    let fits = [first, second].map(|p| (reprojection_cost(camera, local, uv, &p), p));
    let (best, other) = if fits[0].0 <= fits[1].0 {
        (fits[0], fits[1])
    } else {
        (fits[1], fits[0])
    };
    let distinct = so3::angle_between(&best.1.rot, &other.1.rot).to_degrees() > DISTINCT_DEG;
    Some(PoseFit {
        pose: best.1,
        cost: best.0,
        ambiguous: distinct && ambiguous(best.0, other.0, local.len()),
    })
}

/// The other planar solution: the plane's normal reflected about the line of sight to
/// its centroid, the centroid kept.
pub fn mirrored(cam_from_local: &Pose, local: &[Vec3]) -> Pose {
    let (centroid, axes, _) = principal_axes(local);
    let n = cam_from_local.rot * axes.column(2);
    let c = cam_from_local.apply(&centroid);
    let v = c.normalize();
    let n2 = v * (2.0 * n.dot(&v)) - n;
    let axis = n.cross(&n2);
    let s = axis.norm();
    let turn = if s < 1e-12 {
        Mat3::identity()
    } else {
        so3::exp(&(axis / s * s.atan2(n.dot(&n2))))
    };
    let rot = turn * cam_from_local.rot;
    Pose::new(rot, c - rot * centroid)
}

/// Sum of squared pixel reprojection errors of `cam_from_local` (a point that does not
/// project counts 1e12).
pub fn reprojection_cost(
    camera: &Camera,
    local: &[Vec3],
    uv: &[Vec2],
    cam_from_local: &Pose,
) -> f64 {
    local
        .iter()
        .zip(uv)
        .map(|(x, m)| {
            camera
                .project(&cam_from_local.apply(x))
                .map_or(1e12, |p| (p - m).norm_squared())
        })
        .sum()
}

/// Homography between the points' plane and the normalised image, decomposed.
fn planar_pose(local: &[Vec3], xy: &[Vec2]) -> Option<Pose> {
    if local.len() < 4 {
        return None;
    }
    let (c, basis, _) = principal_axes(local);
    let plane_from_local = Pose::new(basis.transpose(), -(basis.transpose() * c));
    let ab: Vec<Vec2> = local
        .iter()
        .map(|p| plane_from_local.apply(p).xy())
        .collect();
    let h = homography(&ab, xy)?;
    let (h1, h2, h3) = (
        h.column(0).into_owned(),
        h.column(1).into_owned(),
        h.column(2).into_owned(),
    );
    let mut s = 2.0 / (h1.norm() + h2.norm());
    if h3.z * s < 0.0 {
        s = -s;
    }
    let (r1, r2) = (h1 * s, h2 * s);
    let rot = so3::project_to_so3(&Mat3::from_columns(&[r1, r2, r1.cross(&r2)]));
    Some(Pose::new(rot, h3 * s) * plane_from_local)
}

/// Direct linear transform of a 3×4 projection on normalised coordinates.
fn dlt_pose(local: &[Vec3], xy: &[Vec2]) -> Option<Pose> {
    if local.len() < 6 {
        return None;
    }
    let c = local.iter().sum::<Vec3>() / local.len() as f64;
    let d = local.iter().map(|p| (p - c).norm()).sum::<f64>() / local.len() as f64;
    let s = if d > 0.0 { 3f64.sqrt() / d } else { 1.0 };
    let mut m = DMatrix::zeros(2 * local.len(), 12);
    for (i, (p, q)) in local.iter().zip(xy).enumerate() {
        let x = (p - c) * s;
        let h = [x.x, x.y, x.z, 1.0];
        for k in 0..4 {
            m[(2 * i, k)] = h[k];
            m[(2 * i, 8 + k)] = -q.x * h[k];
            m[(2 * i + 1, 4 + k)] = h[k];
            m[(2 * i + 1, 8 + k)] = -q.y * h[k];
        }
    }
    let v = null_vector(&m)?;
    let mut p = Matrix3x4::from_row_slice(v.as_slice());
    let mut mm: Mat3 = p.fixed_view::<3, 3>(0, 0).into_owned();
    if mm.determinant() < 0.0 {
        p = -p;
        mm = -mm;
    }
    let svd = mm.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let scale = svd.singular_values.mean();
    let rot = so3::project_to_so3(&(u * vt));
    let t_norm = p.column(3) / scale;
    // Undo the normalisation: X_n = s (X − c)  ⇒  t = t_n·(1/s)... expressed in metres.
    let trans = t_norm / s - rot * c;
    Some(Pose::new(rot, trans))
}

/// A pose fit as a problem of the LM driver: normal equations and cost given as
/// closures, steps `pose.perturbed(δt, δω)`.
struct PoseFit6<N, C> {
    normal: N,
    cost: C,
}

impl<N, C> LeastSquares for PoseFit6<N, C>
where
    N: Fn(&Pose) -> Option<(Matrix6<f64>, Vector6<f64>)>,
    C: Fn(&Pose) -> Option<f64>,
{
    type Point = Pose;
    type Normal = Dense<U6>;
    fn linearize(&mut self, pose: &Pose) -> Option<Dense<U6>> {
        (self.normal)(pose).map(|(h, g)| Dense::new(h, g))
    }
    fn cost(&mut self, pose: &Pose) -> Option<f64> {
        (self.cost)(pose)
    }
    fn retract(&self, pose: &Pose, step: &Vector6<f64>) -> Pose {
        pose.perturbed(
            &Vec3::new(step[0], step[1], step[2]),
            &Vec3::new(step[3], step[4], step[5]),
        )
    }
}

/// Levenberg–Marquardt over one pose (the driver of `rigcal_solve::lm`), steps
/// `pose.perturbed(δt, δω)`. `normal(pose)` gives the normal equations (JᵀJ, Jᵀr)
/// there, `None` when they cannot be formed (the fit stops at the pose it has);
/// `cost(pose)` the cost, `None` where it is undefined (such a step is refused like a
/// worse one). Returns `init` when the cost is undefined there.
pub fn damped_pose_fit(
    init: Pose,
    rules: &Rules,
    normal: impl Fn(&Pose) -> Option<(Matrix6<f64>, Vector6<f64>)>,
    cost: impl Fn(&Pose) -> Option<f64>,
) -> Pose {
    minimize(&mut PoseFit6 { normal, cost }, init, rules).map_or(init, |fit| fit.point)
}

/// Gauss–Newton with Levenberg damping on the pixel reprojection error.
pub fn refine_pose(camera: &Camera, local: &[Vec3], uv: &[Vec2], init: Pose) -> Pose {
    let normal = |pose: &Pose| {
        let mut h = Matrix6::zeros();
        let mut g = Vector6::zeros();
        for (x, m) in local.iter().zip(uv) {
            let p = pose.apply(x);
            let Some((proj, jp)) = camera.project_with_jacobian(&p) else {
                continue;
            };
            let r = proj - m;
            let mut j = nalgebra::SMatrix::<f64, 2, 6>::zeros();
            j.fixed_view_mut::<2, 3>(0, 0).copy_from(&jp);
            j.fixed_view_mut::<2, 3>(0, 3)
                .copy_from(&(-jp * so3::skew(&(pose.rot * x))));
            h += j.transpose() * j;
            g += j.transpose() * r;
        }
        Some((h, g))
    };
    damped_pose_fit(init, &Rules::default(), normal, |pose| {
        Some(reprojection_cost(camera, local, uv, pose))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rigcal_core::geometry::CameraModel;

    fn check(local: &[Vec3], camera: &Camera) {
        let truth = Pose::from_rotvec(Vec3::new(0.3, -0.4, 0.2), Vec3::new(0.1, -0.2, 3.0));
        let uv: Vec<Vec2> = local
            .iter()
            .map(|x| camera.project(&truth.apply(x)).unwrap())
            .collect();
        let est = estimate_pose(camera, local, &uv).unwrap();
        let (dr, dt) = est.distance(&truth);
        assert!(dr < 1e-9 && dt < 1e-9, "dr {dr} dt {dt}");
    }

    #[test]
    fn planar_and_general_pnp_exact() {
        let cam = Camera {
            model: CameraModel::Radtan {
                k1: -0.2,
                k2: 0.05,
                p1: 1e-3,
                p2: 0.0,
                k3: 0.0,
            },
            ..Camera::pinhole(900.0, 900.0, 640.0, 480.0, 1280, 960)
        };
        let planar: Vec<Vec3> = (0..12)
            .map(|i| Vec3::new(0.1 * (i % 4) as f64, 0.12 * (i / 4) as f64, 0.0))
            .collect();
        check(&planar, &cam);
        let general: Vec<Vec3> = (0..10)
            .map(|i| {
                Vec3::new(
                    0.1 * (i % 4) as f64 - 0.2,
                    0.12 * (i / 4) as f64,
                    0.05 * ((i * 7) % 5) as f64,
                )
            })
            .collect();
        check(&general, &cam);
    }

    #[test]
    fn noisy_pnp_is_close() {
        use rand::{Rng, SeedableRng};
        let cam = Camera::pinhole(1000.0, 1000.0, 640.0, 480.0, 1280, 960);
        let truth = Pose::from_rotvec(Vec3::new(0.1, 0.2, -0.1), Vec3::new(0.0, 0.1, 2.0));
        let local: Vec<Vec3> = (0..20)
            .map(|i| {
                Vec3::new(
                    0.2 * (i % 5) as f64 - 0.4,
                    0.2 * (i / 5) as f64 - 0.3,
                    0.1 * (i % 3) as f64,
                )
            })
            .collect();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let uv: Vec<Vec2> = local
            .iter()
            .map(|x| {
                cam.project(&truth.apply(x)).unwrap()
                    + Vec2::new(rng.gen_range(-0.5..0.5), rng.gen_range(-0.5..0.5))
            })
            .collect();
        let est = estimate_pose(&cam, &local, &uv).unwrap();
        let (dr, dt) = est.distance(&truth);
        assert!(dr < 5e-3 && dt < 1e-2, "dr {dr} dt {dt}");
    }
}
