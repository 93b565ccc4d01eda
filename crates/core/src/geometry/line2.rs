//! Image lines: total-least-squares fits, intersections, vanishing points. One home for
//! both the vanishing method (feature lines) and detection (tag and line-target sides).
//!
//! Lines are homogeneous `(a, b, c)` with `a·u + b·v + c = 0` and `a² + b² = 1`, so
//! `l·(u, v, 1)` is the signed distance in pixels. The fit is total least squares (the
//! principal axis of the points), which the paper's `u`-`v` regression (eq. 3) is not:
//! that one cannot represent lines through the origin and breaks on vertical lines.

use crate::geometry::{Mat3, Vec2, Vec3};

/// Total-least-squares line through the points; `None` for fewer than 2 distinct points.
pub fn fit_line(points: &[Vec2]) -> Option<Vec3> {
    if points.len() < 2 {
        return None;
    }
    let n = points.len() as f64;
    let mean = points.iter().sum::<Vec2>() / n;
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for p in points {
        let d = p - mean;
        sxx += d.x * d.x;
        sxy += d.x * d.y;
        syy += d.y * d.y;
    }
    if sxx + syy < 1e-18 {
        return None;
    }
    // Normal = eigenvector of the scatter matrix with the smaller eigenvalue.
    let theta = 0.5 * (2.0 * sxy).atan2(sxx - syy); // direction of the principal axis
    let normal = Vec2::new(-theta.sin(), theta.cos());
    Some(Vec3::new(normal.x, normal.y, -normal.dot(&mean)))
}

/// Signed distance (px) of a point to a normalised line.
pub fn distance(line: &Vec3, p: &Vec2) -> f64 {
    line.x * p.x + line.y * p.y + line.z
}

/// The normalised line through `p` and `q`, oriented from `p` to `q` (the left side,
/// image `y` down, is positive); `None` if they coincide.
pub fn through(p: &Vec2, q: &Vec2) -> Option<Vec3> {
    let d = q - p;
    let len = d.norm();
    (len > 1e-12).then(|| {
        let n = Vec2::new(d.y, -d.x) / len;
        Vec3::new(n.x, n.y, -n.dot(p))
    })
}

/// The bisector of two lines oriented the same way: the points at equal distance from
/// both on opposite sides, i.e. the centre line of the band (or wedge) between them.
/// `None` if they are antiparallel.
pub fn bisector(a: &Vec3, b: &Vec3) -> Option<Vec3> {
    let s = a + b;
    let n = s.xy().norm();
    (n > 1e-12).then(|| s / n)
}

/// Intersection of two lines as a pixel; `None` if they are (nearly) parallel.
pub fn intersect(a: &Vec3, b: &Vec3) -> Option<Vec2> {
    let x = a.cross(b);
    (x.z.abs() > 1e-12 * x.xy().norm().max(1.0)).then(|| Vec2::new(x.x / x.z, x.y / x.z))
}

/// The vanishing direction of a group of image lines, in camera coordinates: the point
/// (homogeneous, possibly at infinity) closest to all lines in the least-squares sense,
/// computed on the lines moved to normalised coordinates (`l_n = Kᵀ l`) so that the
/// result is directly the 3D direction `d ∝ K⁻¹ v` (eq. 11). Unit length, sign arbitrary.
pub fn vanishing_direction(lines: &[Vec3], k: &Mat3) -> Option<Vec3> {
    if lines.len() < 2 {
        return None;
    }
    let mut m = nalgebra::DMatrix::<f64>::zeros(lines.len(), 3);
    for (i, l) in lines.iter().enumerate() {
        let ln = k.transpose() * l;
        let ln = ln / ln.norm();
        for j in 0..3 {
            m[(i, j)] = ln[j];
        }
    }
    let svd = crate::linalg::symmetric_eigen(&(m.transpose() * &m));
    let i = svd.eigenvalues.imin();
    let d = Vec3::new(
        svd.eigenvectors[(0, i)],
        svd.eigenvectors[(1, i)],
        svd.eigenvectors[(2, i)],
    );
    d.iter().all(|x| x.is_finite()).then(|| d.normalize())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_bisector_of_a_wedge_is_equidistant_from_its_edges() {
        // Edges from (0, 0)/(0, 10) converging to (100, 4)/(100, 6): a band 10 px wide
        // narrowing to 2 px. Its bisector is the line y = 5.
        let a = through(&Vec2::new(0.0, 0.0), &Vec2::new(100.0, 4.0)).unwrap();
        let b = through(&Vec2::new(0.0, 10.0), &Vec2::new(100.0, 6.0)).unwrap();
        let m = bisector(&a, &b).unwrap();
        for x in [-50.0, 0.0, 37.0, 100.0, 400.0] {
            let p = Vec2::new(x, 5.0);
            assert!(distance(&m, &p).abs() < 1e-12);
            assert!((distance(&a, &p) + distance(&b, &p)).abs() < 1e-12);
        }
        // `through` is oriented: the left of p→q (image y down) is positive.
        assert!(distance(&a, &Vec2::new(50.0, -1.0)) > 0.0);
        assert!(bisector(&a, &(-a)).is_none());
    }

    #[test]
    fn fits_any_orientation_exactly_including_vertical() {
        for angle in [0.0f64, 0.3, 1.0, std::f64::consts::FRAC_PI_2, 2.5] {
            let dir = Vec2::new(angle.cos(), angle.sin());
            let pts: Vec<Vec2> = (0..20)
                .map(|i| Vec2::new(10.0, -4.0) + dir * i as f64)
                .collect();
            let l = fit_line(&pts).unwrap();
            assert!(pts.iter().all(|p| distance(&l, p).abs() < 1e-10), "{angle}");
        }
        assert!(fit_line(&[Vec2::new(1.0, 1.0)]).is_none());
        assert!(fit_line(&[Vec2::new(1.0, 1.0), Vec2::new(1.0, 1.0)]).is_none());
    }

    #[test]
    fn intersection_and_vanishing_direction() {
        let a = fit_line(&[Vec2::new(0.0, 0.0), Vec2::new(2.0, 2.0)]).unwrap();
        let b = fit_line(&[Vec2::new(0.0, 4.0), Vec2::new(4.0, 0.0)]).unwrap();
        let x = intersect(&a, &b).unwrap();
        assert!((x - Vec2::new(2.0, 2.0)).norm() < 1e-12);
        assert!(intersect(&a, &a).is_none());
        // Parallel 3D lines along d project to lines through K·d.
        let k = Mat3::new(800.0, 0.0, 512.0, 0.0, 780.0, 384.0, 0.0, 0.0, 1.0);
        let d = Vec3::new(0.3, -0.2, 0.9).normalize();
        let lines: Vec<Vec3> = [Vec3::new(0.1, 0.2, 2.0), Vec3::new(-0.5, 0.1, 3.0)]
            .iter()
            .map(|p| {
                let proj = |x: Vec3| {
                    let h = k * x;
                    Vec2::new(h.x / h.z, h.y / h.z)
                };
                fit_line(&[proj(*p), proj(p + d)]).unwrap()
            })
            .collect();
        let got = vanishing_direction(&lines, &k).unwrap();
        assert!(got.cross(&d).norm() < 1e-9);
    }
}
