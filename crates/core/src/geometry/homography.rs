//! Plane-to-image homographies: the Hartley-normalised DLT that planar PnP, the tag
//! verifier and the grid completion share.

use super::{Mat3, Vec2};
use crate::linalg::null_vector;
use nalgebra::DMatrix;

/// Hartley-normalised DLT homography `x ~ H a`.
pub fn homography(a: &[Vec2], x: &[Vec2]) -> Option<Mat3> {
    let (ta, na) = normalizer(a);
    let (tx, nx) = normalizer(x);
    let mut m = DMatrix::zeros(2 * a.len(), 9);
    for i in 0..a.len() {
        let (p, q) = (na[i], nx[i]);
        let row1 = [p.x, p.y, 1.0, 0.0, 0.0, 0.0, -q.x * p.x, -q.x * p.y, -q.x];
        let row2 = [0.0, 0.0, 0.0, p.x, p.y, 1.0, -q.y * p.x, -q.y * p.y, -q.y];
        for k in 0..9 {
            m[(2 * i, k)] = row1[k];
            m[(2 * i + 1, k)] = row2[k];
        }
    }
    let v = null_vector(&m)?;
    let hn = Mat3::from_row_slice(v.as_slice());
    Some(tx.try_inverse()? * hn * ta)
}

/// Isotropic normalisation: centroid to the origin, mean distance √2.
pub fn normalizer(p: &[Vec2]) -> (Mat3, Vec<Vec2>) {
    let c = p.iter().sum::<Vec2>() / p.len() as f64;
    let d = p.iter().map(|q| (q - c).norm()).sum::<f64>() / p.len() as f64;
    let s = if d > 1e-300 {
        std::f64::consts::SQRT_2 / d
    } else {
        1.0
    };
    let t = Mat3::new(s, 0.0, -s * c.x, 0.0, s, -s * c.y, 0.0, 0.0, 1.0);
    (t, p.iter().map(|q| (q - c) * s).collect())
}
