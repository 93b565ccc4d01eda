//! Rigid-body geometry and camera models.
//!
//! Everything here is pure math on `nalgebra` values: no I/O, no allocation-heavy
//! containers, so the estimators above can call it in tight loops and the tests can
//! check every Jacobian against finite differences.

pub mod camera;
pub mod line2;
pub mod pose;
pub mod so3;

pub use camera::{Camera, CameraModel};
pub use pose::Pose;

pub type Vec2 = nalgebra::Vector2<f64>;
pub type Vec3 = nalgebra::Vector3<f64>;
pub type Mat3 = nalgebra::Matrix3<f64>;
