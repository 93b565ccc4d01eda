//! Rigid transforms named `a_from_b` (COLMAP's convention): `a_from_b.apply(p_b) = p_a`.

use super::{so3, Mat3, Vec3};
use serde::{Deserialize, Serialize};

/// A rigid transform `p_a = rot · p_b + trans`. Variables holding one are named
/// `a_from_b`; composing `a_from_b * b_from_c` gives `a_from_c`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub rot: Mat3,
    pub trans: Vec3,
}

impl Default for Pose {
    fn default() -> Self {
        Self::identity()
    }
}

impl Pose {
    pub fn identity() -> Self {
        Self {
            rot: Mat3::identity(),
            trans: Vec3::zeros(),
        }
    }

    pub fn new(rot: Mat3, trans: Vec3) -> Self {
        Self { rot, trans }
    }

    /// From a rotation vector (radians) and a translation.
    pub fn from_rotvec(w: Vec3, trans: Vec3) -> Self {
        Self {
            rot: so3::exp(&w),
            trans,
        }
    }

    pub fn apply(&self, p: &Vec3) -> Vec3 {
        self.rot * p + self.trans
    }

    pub fn inverse(&self) -> Self {
        let rt = self.rot.transpose();
        Self {
            rot: rt,
            trans: -(rt * self.trans),
        }
    }

    /// The 4×4 homogeneous matrix, row-major rows.
    pub fn matrix(&self) -> [[f64; 4]; 4] {
        let r = &self.rot;
        let t = &self.trans;
        [
            [r[(0, 0)], r[(0, 1)], r[(0, 2)], t.x],
            [r[(1, 0)], r[(1, 1)], r[(1, 2)], t.y],
            [r[(2, 0)], r[(2, 1)], r[(2, 2)], t.z],
            [0.0, 0.0, 0.0, 1.0],
        ]
    }

    /// Rotation angle (rad) and translation distance between two transforms.
    pub fn distance(&self, other: &Pose) -> (f64, f64) {
        (
            so3::angle_between(&self.rot, &other.rot),
            (self.trans - other.trans).norm(),
        )
    }

    /// Left perturbation in the decoupled parametrisation used by every solver here:
    /// `rot ← exp(dφ)·rot`, `trans ← trans + dt`. Decoupled so that the translation
    /// block of a covariance is directly metres in the outer frame.
    pub fn perturbed(&self, dt: &Vec3, dphi: &Vec3) -> Self {
        Self {
            rot: so3::exp(dphi) * self.rot,
            trans: self.trans + dt,
        }
    }
}

impl std::ops::Mul for Pose {
    type Output = Pose;
    fn mul(self, rhs: Pose) -> Pose {
        Pose {
            rot: self.rot * rhs.rot,
            trans: self.rot * rhs.trans + self.trans,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compose_and_inverse() {
        let a_from_b = Pose::from_rotvec(Vec3::new(0.1, 0.2, -0.3), Vec3::new(1.0, -2.0, 0.5));
        let b_from_c = Pose::from_rotvec(Vec3::new(-0.4, 0.0, 0.3), Vec3::new(0.0, 0.3, -1.0));
        let p_c = Vec3::new(0.3, 0.4, 2.0);
        let a_from_c = a_from_b * b_from_c;
        assert!((a_from_c.apply(&p_c) - a_from_b.apply(&b_from_c.apply(&p_c))).norm() < 1e-12);
        let id = a_from_c * a_from_c.inverse();
        assert!(
            id.distance(&Pose::identity()).0 < 1e-12 && id.distance(&Pose::identity()).1 < 1e-12
        );
    }
}
