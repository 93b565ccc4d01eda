//! The pose of a camera relative to one line target seen in one image: vanishing points
//! and the known length L1 (Wu et al. §3.1, eq. 10-17), then the point-to-line refinement
//! (eq. 19) in [`super::bundle`].
//!
//! Derivation (what eq. 11-17 say once the garbled text is undone). A 3D direction `d` in
//! camera coordinates images to the vanishing point `v ~ K d`, so the two groups of
//! parallel lines give the target's `z` axis (`d1`, lines l1 l3 l5) and `x` axis (`d2`,
//! l2 l4 l6) in the camera, up to sign; `R = [d2, d1 × d2, d1]` (eq. 13, re-orthogonalised
//! since noisy `d1`, `d2` are not exactly perpendicular). The paper then places `P1`, `P2`
//! on their rays `z1·r1`, `z2·r2` (`r = K⁻¹ p̃`) with `P1P2 ⟂ d2`, i.e.
//! `z1/z2 = d2·r2 / d2·r1` (eq. 14-15), scaled by `|P1P2| = L1` (eq. 16), `t = z1·r1`
//! (eq. 17). That ratio is 0/0 when `d2` is perpendicular to the ray through `P1`, which
//! happens in ordinary views (an auxiliary view of the Table 2 ring at 0.5 px noise gave
//! a pose 180° off). So the translation here comes from all crossings at once, linearly
//! (`[r]×(R·X + t) = 0`, which uses L1 and L2 through the crossings' coordinates; the
//! crossings of every `x` line with every `z` line, which for the L include its six
//! corners), and the signs of `d1`, `d2` are the ones of the four candidate rotations
//! whose translation puts every crossing in front of the camera with the smallest
//! reprojection error. Nothing here is specific to the L: any
//! [`LineLayout`] with two lines per group works the same way.

use super::bundle::{LineBundle, LinePoints};
use nalgebra::DMatrix;
use rigcal_core::geometry::line2::{fit_line, intersect, vanishing_direction};
use rigcal_core::geometry::{so3, Camera, Mat3, Pose, Vec2, Vec3};
use rigcal_core::target::line_layout::{Axis, LineLayout};
use rigcal_solve::Loss;

/// A line direction closer than this to the image plane puts its vanishing point "at
/// infinity": its image lines are almost parallel and their intersection, hence the
/// rotation, is ill-conditioned (Wu §4.1: errors grow as the optical axis turns
/// perpendicular to the target).
pub const MIN_ELEVATION_DEG: f64 = 3.0;
/// Points a feature line needs to be fitted (and to constrain the refinement).
pub const MIN_POINTS_PER_LINE: usize = 3;

/// The camera whose pixels the residuals live in: the real camera without distortion.
pub fn ideal_camera(c: &Camera) -> Camera {
    Camera::pinhole(c.fx, c.fy, c.cx, c.cy, c.width, c.height)
}

/// Raw pixels → pixels of the ideal camera (the measured points undistorted, never the
/// image). Points whose unprojection does not converge are dropped.
pub fn undistort(c: &Camera, points: &[Vec2]) -> Vec<Vec2> {
    points
        .iter()
        .filter_map(|p| c.unproject(p))
        .map(|n| Vec2::new(c.fx * n.x + c.cx, c.fy * n.y + c.cy))
        .collect()
}

fn intrinsic_matrix(c: &Camera) -> Mat3 {
    Mat3::new(c.fx, 0.0, c.cx, 0.0, c.fy, c.cy, 0.0, 0.0, 1.0)
}

/// How the pose was initialised.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Init {
    VanishingPoints,
    /// Fallback when a vanishing point is at infinity: the homography of the crossings.
    Homography,
}

/// The pose from the vanishing points, and the elevation (deg) of the `z` and `x`
/// directions above the image plane. `lines[m]` is line `m`'s fit (`None`: too few
/// points). `Err` says why it cannot be computed.
pub fn pose_from_vanishing(
    layout: &LineLayout,
    lines: &[Option<Vec3>],
    camera: &Camera,
) -> Result<(Pose, [f64; 2]), String> {
    let k = intrinsic_matrix(camera);
    let group = |axis: Axis| -> Vec<Vec3> {
        layout
            .group(axis)
            .into_iter()
            .filter_map(|m| lines[m])
            .collect()
    };
    let d1 = vanishing_direction(&group(Axis::Z), &k)
        .ok_or("no vanishing point of the lines along the target's z")?;
    let d2 = vanishing_direction(&group(Axis::X), &k)
        .ok_or("no vanishing point of the lines along the target's x")?;
    let elevation = [d1, d2].map(|d| d.z.abs().min(1.0).asin().to_degrees());
    let (local, corners) = crossings(layout, lines)?;
    let kinv = k.try_inverse().ok_or("singular intrinsics")?;
    let rays: Vec<Vec3> = corners
        .iter()
        .map(|p| kinv * Vec3::new(p.x, p.y, 1.0))
        .collect();
    // The signs of d1, d2: of the four rotations, the one whose translation puts every
    // crossing in front of the camera and reprojects them best.
    let mut best: Option<(f64, Pose)> = None;
    for (s1, s2) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
        let (z, x) = (d1 * s1, d2 * s2);
        let rot = so3::project_to_so3(&Mat3::from_columns(&[x, z.cross(&x), z]));
        let Some(trans) = translation_from_corners(&rot, &local, &rays) else {
            continue;
        };
        let pose = Pose::new(rot, trans);
        let mut err = 0.0;
        let mut in_front = true;
        for (x, p) in local.iter().zip(&corners) {
            let c = pose.apply(x);
            in_front &= c.z > 0.0;
            let h = k * c;
            err += (Vec2::new(h.x / h.z, h.y / h.z) - p).norm_squared();
        }
        if in_front && err.is_finite() && best.as_ref().is_none_or(|(e, _)| err < *e) {
            best = Some((err, pose));
        }
    }
    let (_, pose) = best.ok_or("no orientation puts the target in front of the camera")?;
    Ok((pose, elevation))
}

/// The crossings of every fitted `x` line with every fitted `z` line: target points and
/// their images.
fn crossings(
    layout: &LineLayout,
    lines: &[Option<Vec3>],
) -> Result<(Vec<Vec3>, Vec<Vec2>), String> {
    let mut local = Vec::new();
    let mut image = Vec::new();
    for (i, j, p) in layout.crossings() {
        let (Some(a), Some(b)) = (lines[i], lines[j]) else {
            continue;
        };
        let q = intersect(&a, &b)
            .ok_or_else(|| format!("lines l{} and l{} do not intersect", i + 1, j + 1))?;
        local.push(p);
        image.push(q);
    }
    if local.len() < 4 {
        return Err(format!(
            "{} crossing(s) of fitted lines; the pose needs at least 4",
            local.len()
        ));
    }
    Ok((local, image))
}

/// The translation that puts each corner `local[m]` (rotated by `rot`) on its ray: two
/// linear equations per corner, `[r]× (R·X + t) = 0`, solved in the least-squares sense.
fn translation_from_corners(rot: &Mat3, local: &[Vec3], rays: &[Vec3]) -> Option<Vec3> {
    let mut ata = Mat3::zeros();
    let mut atb = Vec3::zeros();
    for (x, r) in local.iter().zip(rays) {
        let r = r.normalize();
        let s = so3::skew(&r);
        ata += s.transpose() * s;
        atb -= s.transpose() * (s * (rot * x));
    }
    let t = ata.try_inverse()? * atb;
    t.iter().all(|v| v.is_finite()).then_some(t)
}

/// A refined camera–target pose with what the report needs.
#[derive(Clone, Debug)]
pub struct ViewPose {
    pub cam_from_target: Pose,
    /// Initial value, before the point-to-line refinement.
    pub initial: Pose,
    /// 6×6 covariance of `[dt, dφ]` (left perturbation in the camera frame).
    pub covariance: DMatrix<f64>,
    pub sigma_px: f64,
    pub init: Init,
    /// Elevation (deg) of the target's `z` and `x` directions above the image plane.
    pub elevation_deg: [f64; 2],
    /// Signed point-to-line residuals (px), all lines.
    pub residuals: Vec<f64>,
}

/// Fit every line of one target in one view (undistorted pixels per line): `None` for a
/// line with fewer than [`MIN_POINTS_PER_LINE`] points (hidden or cut off). Each group
/// needs two fitted lines for its vanishing point.
pub fn fit_lines(layout: &LineLayout, points: &[Vec<Vec2>]) -> Result<Vec<Option<Vec3>>, String> {
    let mut out = vec![None; layout.len()];
    for (m, pts) in points.iter().enumerate().take(layout.len()) {
        if pts.len() >= MIN_POINTS_PER_LINE {
            out[m] =
                Some(fit_line(pts).ok_or_else(|| format!("line l{} is a single point", m + 1))?);
        }
    }
    for (axis, name) in [(Axis::Z, "z"), (Axis::X, "x")] {
        let group = layout.group(axis);
        if group.iter().filter(|&&m| out[m].is_some()).count() < 2 {
            let missing: Vec<String> = group
                .iter()
                .filter(|&&m| out[m].is_none())
                .map(|m| format!("l{} ({} points)", m + 1, points.get(*m).map_or(0, Vec::len)))
                .collect();
            return Err(format!(
                "fewer than 2 of the lines along the target's {name} have {MIN_POINTS_PER_LINE} points or more (a vanishing point needs two): {}",
                missing.join(", ")
            ));
        }
    }
    Ok(out)
}

/// The pose of `camera` (ideal pinhole) relative to a target of `layout` from the points
/// measured on its lines: vanishing points (or the crossings' homography when one is at
/// infinity), then point-to-line Levenberg–Marquardt.
pub fn estimate_view_pose(
    camera: &Camera,
    layout: &LineLayout,
    points: &[Vec<Vec2>],
    loss: &Loss,
    max_iterations: usize,
) -> Result<ViewPose, String> {
    let lines = fit_lines(layout, points)?;
    let (initial, init, elevation_deg) = match pose_from_vanishing(layout, &lines, camera) {
        Ok((pose, elev)) if elev.iter().all(|e| *e >= MIN_ELEVATION_DEG) => {
            (pose, Init::VanishingPoints, elev)
        }
        other => {
            let elev = other.as_ref().map(|(_, e)| *e).unwrap_or([0.0; 2]);
            let (local, image) = crossings(layout, &lines)?;
            let pose = crate::pnp::estimate_pose(camera, &local, &image)
                .ok_or("neither the vanishing points nor the crossings' homography give a pose")?;
            (pose, Init::Homography, elev)
        }
    };
    let mut problem = LineBundle {
        geometry: vec![layout.clone()],
        ref_from_target: vec![Pose::identity()],
        target_free: vec![false],
        cameras: vec![camera.clone()],
        cam_from_ref: vec![initial],
        view_free: vec![true],
        obs: points
            .iter()
            .enumerate()
            .filter(|(_, p)| !p.is_empty())
            .map(|(m, p)| LinePoints {
                view: 0,
                target: 0,
                line: m,
                points: p.clone(),
                weight: 1.0,
            })
            .collect(),
    };
    let summary = problem.solve_weighing_lines(loss, max_iterations);
    if !summary.converged && summary.final_cost >= summary.initial_cost {
        return Err(format!(
            "the point-to-line refinement failed: {}",
            summary.termination
        ));
    }
    let (covariance, sigma_px) = problem
        .covariance(loss)
        .ok_or("the pose is not determined by the line points (too few points)")?;
    Ok(ViewPose {
        cam_from_target: problem.cam_from_ref[0],
        initial,
        covariance,
        sigma_px,
        init,
        elevation_deg,
        residuals: problem.residuals().concat(),
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, Normal};

    /// Points along each projected feature line, one per pixel of length, with noise.
    pub fn sample_lines(
        camera: &Camera,
        cam_from_target: &Pose,
        target: &LineLayout,
        noise_px: f64,
        rng: &mut impl Rng,
    ) -> Vec<Vec<Vec2>> {
        let normal = Normal::new(0.0, noise_px.max(1e-300)).unwrap();
        (0..target.len())
            .map(|m| {
                let (a, b) = target.segment(m);
                let (pa, pb) = (
                    camera.project(&cam_from_target.apply(&a)).unwrap(),
                    camera.project(&cam_from_target.apply(&b)).unwrap(),
                );
                let n = ((pb - pa).norm().round() as usize).max(2);
                (0..n)
                    .map(|i| {
                        let s = (i as f64 + 0.5) / n as f64;
                        let p = camera
                            .project(&cam_from_target.apply(&(a + (b - a) * s)))
                            .unwrap();
                        if noise_px > 0.0 {
                            p + Vec2::new(normal.sample(rng), normal.sample(rng))
                        } else {
                            p
                        }
                    })
                    .collect()
            })
            .collect()
    }

    fn setup() -> (Camera, LineLayout, Pose) {
        let camera = Camera::pinhole(796.44, 796.44, 512.0, 384.0, 1024, 768);
        let target = LineLayout::l_target(0.5, 0.2);
        // Looking down 35° at a target 1.2 m ahead, its diagonal towards the camera.
        let rot = so3::exp(&Vec3::new(-(55f64).to_radians(), 0.0, 0.0))
            * so3::exp(&Vec3::new(0.0, (225f64).to_radians(), 0.0));
        let cam_from_target = Pose::new(rot, Vec3::new(0.0, 0.1, 0.9))
            * Pose::new(Mat3::identity(), Vec3::new(-0.2, 0.0, -0.2));
        (camera, target, cam_from_target)
    }

    #[test]
    fn vanishing_points_and_length_recover_the_pose_exactly() {
        let (camera, target, truth) = setup();
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let pts = sample_lines(&camera, &truth, &target, 0.0, &mut rng);
        let lines = fit_lines(&target, &pts).unwrap();
        let (pose, elev) = pose_from_vanishing(&target, &lines, &camera).unwrap();
        let (dr, dt) = pose.distance(&truth);
        assert!(dr < 1e-9 && dt < 1e-9, "{dr} {dt}");
        assert!(elev.iter().all(|e| *e > MIN_ELEVATION_DEG));
        let v = estimate_view_pose(&camera, &target, &pts, &Loss::Squared, 50).unwrap();
        assert_eq!(v.init, Init::VanishingPoints);
        let (dr, dt) = v.cam_from_target.distance(&truth);
        assert!(dr < 1e-9 && dt < 1e-9, "{dr} {dt}");
    }

    #[test]
    fn with_noise_the_refined_pose_is_within_its_sigma_bound() {
        let (camera, target, truth) = setup();
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let (mut worst_r, mut worst_t) = (0.0f64, 0.0f64);
        for _ in 0..20 {
            let pts = sample_lines(&camera, &truth, &target, 0.5, &mut rng);
            let v = estimate_view_pose(&camera, &target, &pts, &Loss::Squared, 50).unwrap();
            let (dr, dt) = v.cam_from_target.distance(&truth);
            worst_r = worst_r.max(dr.to_degrees());
            worst_t = worst_t.max(dt);
            assert!((v.sigma_px - 0.5).abs() < 0.05, "{}", v.sigma_px);
            // Error within 5σ of the reported covariance.
            let st = (v.covariance[(0, 0)] + v.covariance[(1, 1)] + v.covariance[(2, 2)]).sqrt();
            assert!(dt < 5.0 * st, "{dt} vs σ {st}");
        }
        // 0.5 px on ~2000 line points at ~1 m: well under 0.1° and 1 mm.
        assert!(worst_r < 0.1 && worst_t < 1e-3, "{worst_r}° {worst_t} m");
    }

    #[test]
    fn a_fronto_parallel_target_falls_back_to_the_homography() {
        let (camera, target, _) = setup();
        let truth = Pose::new(
            so3::exp(&Vec3::new(std::f64::consts::FRAC_PI_2, 0.0, 0.0)),
            Vec3::new(-0.25, -0.25, 1.5),
        );
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let pts = sample_lines(&camera, &truth, &target, 0.0, &mut rng);
        let v = estimate_view_pose(&camera, &target, &pts, &Loss::Squared, 50).unwrap();
        assert_eq!(v.init, Init::Homography);
        assert!(v.elevation_deg.iter().any(|e| *e < MIN_ELEVATION_DEG));
        let (dr, dt) = v.cam_from_target.distance(&truth);
        assert!(dr < 1e-8 && dt < 1e-8, "{dr} {dt}");
    }

    #[test]
    fn too_few_points_is_an_explained_error() {
        let (camera, target, truth) = setup();
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let mut pts = sample_lines(&camera, &truth, &target, 0.0, &mut rng);
        // One line of a group hidden: the other two still give its vanishing point.
        pts[3].truncate(2);
        estimate_view_pose(&camera, &target, &pts, &Loss::Squared, 50).unwrap();
        pts[5].clear();
        let e = estimate_view_pose(&camera, &target, &pts, &Loss::Squared, 50).unwrap_err();
        assert!(
            e.contains("l4 (2 points)") && e.contains("l6 (0 points)"),
            "{e}"
        );
    }
}
