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
#[inline]
pub fn normal_cdf(x: f64) -> f64 {
    normal_cdf_pdf(x).0
}

/// The standard normal CDF ([`normal_cdf`]) and density at `x` together: both need
/// `exp(−x²/2)`, the costly part, which is computed once (fits of blurred edges evaluate
/// the pair for every pixel at every iteration).
#[inline]
pub fn normal_cdf_pdf(x: f64) -> (f64, f64) {
    let gauss = (-0.5 * x * x).exp();
    let z = x.abs() / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.327_591_1 * z);
    let poly = t
        * (0.254_829_592
            + t * (-0.284_496_736
                + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    let erf = 1.0 - poly * gauss;
    let cdf = 0.5 * (1.0 + if x >= 0.0 { erf } else { -erf });
    (cdf, gauss * FRAC_1_SQRT_2PI)
}

/// 1/√(2π), the standard normal density's peak.
const FRAC_1_SQRT_2PI: f64 = 0.398_942_280_401_432_7;

#[cfg(test)]
mod tests {
    use super::*;

    /// Φ against tabulated values, its density against the closed form and against Φ's
    /// own slope.
    #[test]
    fn the_normal_cdf_and_density_are_right() {
        for (x, phi) in [
            (0.0, 0.5),
            (1.0, 0.841_344_746_068_543),
            (-1.0, 0.158_655_253_931_457),
            (1.96, 0.975_002_104_851_780),
            (-3.0, 0.001_349_898_031_630),
        ] {
            let (cdf, pdf) = normal_cdf_pdf(x);
            assert!((cdf - phi).abs() < 2e-7, "Φ({x}) = {cdf}, expected {phi}");
            assert_eq!(cdf, normal_cdf(x));
            let exact = (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt();
            assert!(
                (pdf - exact).abs() < 1e-15,
                "φ({x}) = {pdf}, expected {exact}"
            );
            let h = 1e-3;
            let slope = (normal_cdf(x + h) - normal_cdf(x - h)) / (2.0 * h);
            assert!((slope - pdf).abs() < 2e-4, "Φ'({x}) = {slope}, φ = {pdf}");
        }
    }
}
