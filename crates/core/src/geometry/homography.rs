//! Plane-to-image homographies: the Hartley-normalised DLT that planar PnP, the tag
//! verifier and the grid completion share.

use super::{Mat3, Vec2};
use crate::linalg::{null_vector, null_vector_of_general_position};
use nalgebra::{DMatrix, DVector};

/// Hartley-normalised DLT homography `x ~ H a`.
pub fn homography(a: &[Vec2], x: &[Vec2]) -> Option<Mat3> {
    dlt(a, x, null_vector)
}

/// [`homography`] for points in general position by construction (a tag's corners, a
/// board's), its null vector by inverse iteration
/// ([`null_vector_of_general_position`]): ~20× cheaper, for the detector, which fits
/// hundreds per image.
pub fn homography_of_general_position(a: &[Vec2], x: &[Vec2]) -> Option<Mat3> {
    dlt(a, x, null_vector_of_general_position)
}

fn dlt(a: &[Vec2], x: &[Vec2], null: fn(&DMatrix<f64>) -> Option<DVector<f64>>) -> Option<Mat3> {
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
    let v = null(&m)?;
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

/// The homography taking the unit square's corners `(0,0), (1,0), (1,1), (0,1)` to
/// `q[0..4]`, in closed form (Heckbert's square-to-quadrilateral mapping), scaled so that
/// `H₃₃ = 1`. Four correspondences determine a homography exactly, so no least squares
/// is needed: this is a few dozen operations where [`homography`]'s SVD is ~50 000
/// instructions, and the whole-tag fit builds one per model evaluation and nine per
/// Jacobian. `None` when the quadrilateral is degenerate (three corners collinear).
pub fn square_to_quad(q: &[Vec2; 4]) -> Option<Mat3> {
    let sx = q[0].x - q[1].x + q[2].x - q[3].x;
    let sy = q[0].y - q[1].y + q[2].y - q[3].y;
    let (d1, d2) = (q[1] - q[2], q[3] - q[2]);
    let den = d1.x * d2.y - d2.x * d1.y;
    let scale = (q[1] - q[0]).norm() * (q[3] - q[0]).norm();
    if den.abs() <= 1e-12 * scale || !den.is_finite() {
        return None;
    }
    let g = (sx * d2.y - d2.x * sy) / den;
    let h = (d1.x * sy - sx * d1.y) / den;
    let m = Mat3::new(
        q[1].x - q[0].x + g * q[1].x,
        q[3].x - q[0].x + h * q[3].x,
        q[0].x,
        q[1].y - q[0].y + g * q[1].y,
        q[3].y - q[0].y + h * q[3].y,
        q[0].y,
        g,
        h,
        1.0,
    );
    // Three corners on a line (any three) make `H` singular.
    let ok = m.iter().all(|v| v.is_finite()) && m.determinant().abs() > 1e-12 * scale;
    ok.then_some(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn apply(h: &Mat3, p: Vec2) -> Vec2 {
        let x = h * super::super::Vec3::new(p.x, p.y, 1.0);
        Vec2::new(x.x / x.z, x.y / x.z)
    }

    #[test]
    fn square_to_quad_maps_the_corners_exactly_and_agrees_with_the_dlt() {
        let square = [
            Vec2::new(0.0, 0.0),
            Vec2::new(1.0, 0.0),
            Vec2::new(1.0, 1.0),
            Vec2::new(0.0, 1.0),
        ];
        let quads = [
            // Affine (a parallelogram), strongly projective, and a tiny one far off.
            [(10.0, 20.0), (50.0, 25.0), (45.0, 70.0), (5.0, 65.0)],
            [
                (100.0, 100.0),
                (180.0, 110.0),
                (150.0, 140.0),
                (110.0, 130.0),
            ],
            [
                (1500.0, 900.0),
                (1512.0, 901.0),
                (1511.5, 915.0),
                (1499.0, 913.0),
            ],
        ];
        for q in quads {
            let q = q.map(|(x, y)| Vec2::new(x, y));
            let h = square_to_quad(&q).expect("a convex quadrilateral");
            let dlt = homography(&square, &q).expect("dlt");
            for k in 0..4 {
                assert!(
                    (apply(&h, square[k]) - q[k]).norm() < 1e-9,
                    "corner {k} of {q:?}"
                );
            }
            for (u, v) in [(0.3, 0.7), (0.5, 0.5), (-0.25, 1.4)] {
                let p = Vec2::new(u, v);
                assert!(
                    (apply(&h, p) - apply(&dlt, p)).norm() < 1e-7,
                    "{p:?} of {q:?}"
                );
            }
        }
        for collinear in [
            [(0.0, 0.0), (1.0, 1.0), (2.0, 2.0), (0.0, 1.0)],
            [(0.0, 0.0), (3.0, 1.0), (2.0, 2.0), (1.0, 3.0)],
            [(5.0, 5.0), (5.0, 5.0), (6.0, 7.0), (4.0, 7.0)],
        ] {
            let q = collinear.map(|(x, y)| Vec2::new(x, y));
            assert!(square_to_quad(&q).is_none(), "{q:?}");
        }
    }
}
