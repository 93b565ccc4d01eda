//! Rigid-body geometry and camera models.
//!
//! Everything here is pure math on `nalgebra` values: no I/O, no allocation-heavy
//! containers, so the estimators above can call it in tight loops and the tests can
//! check every Jacobian against finite differences.

pub mod camera;
pub mod homography;
pub mod line2;
pub mod plane;
pub mod pose;
pub mod so3;

pub use camera::{Camera, CameraModel};
pub use pose::Pose;

pub type Vec2 = nalgebra::Vector2<f64>;
pub type Vec3 = nalgebra::Vector3<f64>;
pub type Mat3 = nalgebra::Matrix3<f64>;

/// Standard normal CDF; Abramowitz & Stegun 7.1.26 (|error| < 1.5e-7, far below what
/// an 8-bit grey level resolves).
pub fn normal_cdf(x: f64) -> f64 {
    let z = x.abs() / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.327_591_1 * z);
    let poly = t
        * (0.254_829_592
            + t * (-0.284_496_736
                + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    let erf = 1.0 - poly * (-z * z).exp();
    0.5 * (1.0 + if x >= 0.0 { erf } else { -erf })
}
