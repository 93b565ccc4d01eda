//! SO(3): exponential and logarithm maps, skew matrices, angle helpers.
//!
//! Rotations are plain `Matrix3<f64>` so the linear algebra of the hand-eye
//! initialisation (Kronecker products, SVD projections) needs no conversions.

use super::{Mat3, Vec3};

/// The cross-product matrix: `skew(a) * b == a.cross(&b)`.
pub fn skew(a: &Vec3) -> Mat3 {
    Mat3::new(0.0, -a.z, a.y, a.z, 0.0, -a.x, -a.y, a.x, 0.0)
}

/// Rodrigues' formula: the rotation by `|w|` radians about `w/|w|`.
pub fn exp(w: &Vec3) -> Mat3 {
    let theta2 = w.norm_squared();
    let k = skew(w);
    if theta2 < 1e-16 {
        // Second-order Taylor expansion keeps the result orthogonal to 1e-16.
        return Mat3::identity() + k + 0.5 * k * k;
    }
    let theta = theta2.sqrt();
    let a = theta.sin() / theta;
    let b = (1.0 - theta.cos()) / theta2;
    Mat3::identity() + a * k + b * k * k
}

/// Inverse of [`exp`]: the rotation vector of `r`, angle in `[0, π]`.
///
/// Near π the usual `(R - Rᵀ)/(2 sin θ)` formula loses all precision, so the axis is
/// read from the symmetric part instead (the largest diagonal of `R + I`).
pub fn log(r: &Mat3) -> Vec3 {
    let v = Vec3::new(
        r[(2, 1)] - r[(1, 2)],
        r[(0, 2)] - r[(2, 0)],
        r[(1, 0)] - r[(0, 1)],
    );
    // v = 2 sin θ · axis; atan2 keeps full precision at both ends of [0, π].
    let cos = (r.trace() - 1.0) * 0.5;
    let theta = (0.5 * v.norm()).atan2(cos);
    if theta < 1e-6 {
        return 0.5 * v;
    }
    if theta < std::f64::consts::PI - 1e-3 {
        return v * (theta / (2.0 * theta.sin()));
    }
    // Near π the antisymmetric part vanishes; read the axis from the symmetric part,
    // (R + Rᵀ)/2 = cos θ · I + (1 − cos θ) · a aᵀ, taking its largest column.
    let s = (r + r.transpose()) * 0.5 - Mat3::identity() * cos;
    let mut best = 0;
    for i in 1..3 {
        if s[(i, i)] > s[(best, best)] {
            best = i;
        }
    }
    let mut axis: Vec3 = s.column(best).into();
    axis /= axis.norm();
    if axis.dot(&v) < 0.0 {
        axis = -axis;
    }
    axis * theta
}

/// Angle in radians of the rotation `a⁻¹ b` (the geodesic distance, eq. 20 of Lébraly).
pub fn angle_between(a: &Mat3, b: &Mat3) -> f64 {
    log(&(a.transpose() * b)).norm()
}

/// Nearest rotation matrix (Frobenius norm) via SVD, with the determinant forced to +1.
pub fn project_to_so3(m: &Mat3) -> Mat3 {
    let svd = m.svd(true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
        return Mat3::identity();
    };
    let mut d = Mat3::identity();
    if (u * vt).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    u * d * vt
}

/// Rotation from roll, pitch, yaw in radians: `Rz(yaw) · Ry(pitch) · Rx(roll)`.
pub fn from_rpy(roll: f64, pitch: f64, yaw: f64) -> Mat3 {
    *nalgebra::Rotation3::from_euler_angles(roll, pitch, yaw).matrix()
}

/// Roll, pitch, yaw (radians) of `r`, the inverse of [`from_rpy`].
pub fn to_rpy(r: &Mat3) -> (f64, f64, f64) {
    nalgebra::Rotation3::from_matrix_unchecked(*r).euler_angles()
}

/// Unit quaternion `(w, x, y, z)` of `r`, with `w ≥ 0`.
pub fn to_quaternion(r: &Mat3) -> [f64; 4] {
    let q = nalgebra::UnitQuaternion::from_rotation_matrix(
        &nalgebra::Rotation3::from_matrix_unchecked(*r),
    );
    let s = if q.w < 0.0 { -1.0 } else { 1.0 };
    [s * q.w, s * q.i, s * q.j, s * q.k]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_log_roundtrip_including_near_pi() {
        let cases = [
            Vec3::new(0.1, -0.2, 0.3),
            Vec3::new(1e-9, 0.0, -2e-9),
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(3.1, 0.1, -0.05),
            Vec3::new(0.0, std::f64::consts::PI - 1e-7, 0.0),
            Vec3::new(-2.0, 1.0, 1.5),
        ];
        for w in cases {
            let r = exp(&w);
            assert!((r.transpose() * r - Mat3::identity()).norm() < 1e-12);
            assert!((r.determinant() - 1.0).abs() < 1e-12);
            let back = exp(&log(&r));
            assert!((back - r).norm() < 1e-9, "w = {w:?}");
        }
    }

    #[test]
    fn rpy_and_quaternion_roundtrip() {
        let r = from_rpy(
            -179f64.to_radians(),
            -4f64.to_radians(),
            171f64.to_radians(),
        );
        let (ro, pi, ya) = to_rpy(&r);
        assert!((from_rpy(ro, pi, ya) - r).norm() < 1e-12);
        let q = to_quaternion(&r);
        let uq = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            q[0], q[1], q[2], q[3],
        ));
        assert!((uq.to_rotation_matrix().matrix() - r).norm() < 1e-12);
    }

    #[test]
    fn projection_to_so3_recovers_noisy_rotation() {
        let r = exp(&Vec3::new(0.3, 0.2, -0.1));
        let noisy = r + Mat3::from_element(1e-3);
        assert!(angle_between(&project_to_so3(&noisy), &r) < 2e-3);
        assert!((project_to_so3(&r) - r).norm() < 1e-12);
    }
}
