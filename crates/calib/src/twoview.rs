//! Two-view geometry for scenes of unknown structure: the essential matrix by the
//! normalised eight-point algorithm, its decomposition with the chirality test, and
//! linear multi-view triangulation. All inputs are undistorted normalised coordinates.

use nalgebra::{DMatrix, Matrix4};
use rigcal_core::geometry::homography::normalizer;
use rigcal_core::geometry::{so3, Mat3, Pose, Vec2, Vec3};
use rigcal_core::linalg::null_vector;

/// `cam2_from_cam1` with a unit-norm translation, from ≥ 8 correspondences in general
/// position (not all on one plane).
pub fn relative_pose(x1: &[Vec2], x2: &[Vec2]) -> Option<Pose> {
    if x1.len() < 8 {
        return None;
    }
    let (t1, n1) = normalizer(x1);
    let (t2, n2) = normalizer(x2);
    let mut m = DMatrix::zeros(x1.len(), 9);
    for i in 0..x1.len() {
        let (a, b) = (n1[i], n2[i]);
        let row = [
            b.x * a.x,
            b.x * a.y,
            b.x,
            b.y * a.x,
            b.y * a.y,
            b.y,
            a.x,
            a.y,
            1.0,
        ];
        for k in 0..9 {
            m[(i, k)] = row[k];
        }
    }
    let v = null_vector(&m)?;
    let e = t2.transpose() * Mat3::from_row_slice(v.as_slice()) * t1;
    let svd = e.svd(true, true);
    let (mut u, mut vt) = (svd.u?, svd.v_t?);
    if u.determinant() < 0.0 {
        u = -u;
    }
    if vt.determinant() < 0.0 {
        vt = -vt;
    }
    let w = Mat3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
    let t: Vec3 = u.column(2).into();
    let mut best: Option<(usize, Pose)> = None;
    for rot in [u * w * vt, u * w.transpose() * vt] {
        for sign in [1.0, -1.0] {
            let cand = Pose::new(so3::project_to_so3(&rot), t * sign);
            let front = (0..x1.len())
                .filter(|&i| {
                    triangulate(&[(Pose::identity(), x1[i]), (cand, x2[i])])
                        .is_some_and(|p| p.z > 0.0 && cand.apply(&p).z > 0.0)
                })
                .count();
            if best.as_ref().is_none_or(|(n, _)| front > *n) {
                best = Some((front, cand));
            }
        }
    }
    best.map(|(_, p)| p)
}

/// Linear (DLT) triangulation from `(cam_from_world, normalised point)` views.
pub fn triangulate(views: &[(Pose, Vec2)]) -> Option<Vec3> {
    if views.len() < 2 {
        return None;
    }
    let mut a = Matrix4::zeros();
    for (pose, x) in views {
        let p = pose_rows(pose);
        let r1 = p[0] - p[2] * x.x;
        let r2 = p[1] - p[2] * x.y;
        let r1 = r1 / r1.norm().max(1e-300);
        let r2 = r2 / r2.norm().max(1e-300);
        a += r1 * r1.transpose() + r2 * r2.transpose();
    }
    let eig = rigcal_core::linalg::symmetric_eigen(&nalgebra::DMatrix::from_column_slice(
        4,
        4,
        a.as_slice(),
    ));
    let k = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|x, y| x.1.total_cmp(y.1))?
        .0;
    let h = eig.eigenvectors.column(k);
    if h[3].abs() < 1e-12 {
        return None;
    }
    Some(Vec3::new(h[0] / h[3], h[1] / h[3], h[2] / h[3]))
}

fn pose_rows(p: &Pose) -> [nalgebra::Vector4<f64>; 3] {
    let r = &p.rot;
    let t = &p.trans;
    [
        nalgebra::Vector4::new(r[(0, 0)], r[(0, 1)], r[(0, 2)], t.x),
        nalgebra::Vector4::new(r[(1, 0)], r[(1, 1)], r[(1, 2)], t.y),
        nalgebra::Vector4::new(r[(2, 0)], r[(2, 1)], r[(2, 2)], t.z),
    ]
}

/// Angle (rad) between the two viewing rays of a point: small angles triangulate badly.
pub fn parallax(cam1_from_world: &Pose, cam2_from_world: &Pose, p: &Vec3) -> f64 {
    let c1 = cam1_from_world.inverse().trans;
    let c2 = cam2_from_world.inverse().trans;
    let (a, b) = (p - c1, p - c2);
    (a.dot(&b) / (a.norm() * b.norm()).max(1e-300))
        .clamp(-1.0, 1.0)
        .acos()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn essential_decomposition_and_triangulation_exact() {
        let pts: Vec<Vec3> = (0..15)
            .map(|i| {
                Vec3::new(
                    -0.7 + 0.1 * i as f64,
                    0.3 * ((i % 4) as f64 - 1.5),
                    3.0 + 0.4 * ((i * 5) % 7) as f64,
                )
            })
            .collect();
        let c2 = Pose::from_rotvec(Vec3::new(0.05, -0.2, 0.1), Vec3::new(-0.6, 0.1, 0.2));
        let x1: Vec<Vec2> = pts.iter().map(|p| p.xy() / p.z).collect();
        let x2: Vec<Vec2> = pts
            .iter()
            .map(|p| c2.apply(p))
            .map(|p| p.xy() / p.z)
            .collect();
        let est = relative_pose(&x1, &x2).unwrap();
        assert!(so3::angle_between(&est.rot, &c2.rot) < 1e-9);
        assert!((est.trans - c2.trans.normalize()).norm() < 1e-9);
        let scaled = Pose::new(est.rot, est.trans * c2.trans.norm());
        let p = triangulate(&[(Pose::identity(), x1[3]), (scaled, x2[3])]).unwrap();
        assert!((p - pts[3]).norm() < 1e-9);
    }
}
