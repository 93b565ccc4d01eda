//! Principal axes of point sets: is a target planar, and in which frame.

use super::{Mat3, Vec3};

/// Coplanarity test: the smallest principal extent is below 1e-6 of the largest.
pub fn is_planar(pts: &[Vec3]) -> bool {
    if pts.len() < 4 {
        return true;
    }
    let (_, _, sv) = principal_axes(pts);
    sv[2] <= 1e-6 * sv[0].max(1e-300)
}

/// Centroid, principal axes (columns, right-handed) and singular values of a point set.
pub fn principal_axes(pts: &[Vec3]) -> (Vec3, Mat3, Vec3) {
    let c = pts.iter().sum::<Vec3>() / pts.len() as f64;
    let mut cov = Mat3::zeros();
    for p in pts {
        let d = p - c;
        cov += d * d.transpose();
    }
    let (values, vectors) = crate::linalg::symmetric_eigen3(&cov);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| values[b].total_cmp(&values[a]));
    let e1: Vec3 = vectors.column(order[0]).into();
    let e2: Vec3 = vectors.column(order[1]).into();
    let e3 = e1.cross(&e2);
    let sv = Vec3::new(
        values[order[0]].max(0.0).sqrt(),
        values[order[1]].max(0.0).sqrt(),
        values[order[2]].max(0.0).sqrt(),
    );
    (c, Mat3::from_columns(&[e1, e2, e3]), sv)
}
