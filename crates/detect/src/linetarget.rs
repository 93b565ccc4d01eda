//! Wu's line targets in images: the feature lines `l1..l6`, their supporting points, the
//! corners `P1..P6` and the two vanishing points.
//!
//! The printed target is the L of [`rigcal_core::target::line_target`] filled dark on a
//! light ground, so the six feature lines are the L's outline and are measured as edges
//! (an edge-based equivalent of Steger's ridge points, which the issue allows): one
//! profile per pixel of each side, the mid-level crossing on each, a total-least-squares
//! line per side in the undistorted plane (the image is never resampled) — the same side
//! measurement as AprilTag corners ([`super::refine::refine_polygon`]).
//!
//! The coarse stage: Otsu threshold, dark connected components, their convex hull
//! reduced to its five corners (`P1 P2 P3 P5 P6`), the reflex corner `P4` as the outline
//! point deepest inside the hull. The L is symmetric about its diagonal, so `P2` and `P6`
//! differ only by handedness: the printed side faces the camera, and seen from there
//! `P1 → P2 → P3` turns clockwise on the page (image `y` down); see
//! [`label_corners`] and its test against rendered truth.

use super::gray::Gray;
use super::refine::{refine_polygon, Lens, SideSampling, FIT_BAND};
use rigcal_core::geometry::line2::vanishing_direction;
use rigcal_core::geometry::{Mat3, Vec2};
use rigcal_core::target::line_target::{LINES, X_GROUP, Z_GROUP};
use serde::Serialize;

/// One line target found in an image.
#[derive(Clone, Debug, Serialize)]
pub struct LineTargetDetection {
    /// `P1..P6` in raw pixels.
    pub corners: [[f64; 2]; LINES],
    /// Feature lines `l1..l6`: the edge points supporting each (raw pixels, what the
    /// vanishing method fits) and the line in the undistorted plane `[a, b, c]`
    /// (`a u + b v + c = 0`, normalised coordinates when a camera is given, else pixels).
    pub lines: Vec<DetectedLine>,
    /// Vanishing points of the `z` lines (`l1 l3 l5`) and the `x` lines (`l2 l4 l6`),
    /// homogeneous, unit norm, in the same plane as the lines (`w ≈ 0`: at infinity).
    pub vanishing_points: [[f64; 3]; 2],
    /// RMS distance (px) of the edge points from their lines.
    pub edge_rms_px: f64,
    /// Mean grey step across the outline (light − dark).
    pub contrast: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct DetectedLine {
    /// 1..6.
    pub line: usize,
    pub points: Vec<[f64; 2]>,
    pub plane_line: [f64; 3],
}

/// Edge points reported per line: every `2·FIT_BAND + 1`-th, so no two share a pixel.
const INDEPENDENT_EVERY: usize = 2 * FIT_BAND as usize + 1;

/// Smallest target worth measuring: shortest side in pixels.
const MIN_SIDE_PX: f64 = 8.0;

/// Sides of an L: levels read and edges searched within a quarter of its narrowest arm.
const L_SIDES: SideSampling = SideSampling {
    corner_clearance: 0.06,
    room: |side| 0.25 * side.shortest,
    corner_slack: 0.1,
    spacing: 1.0,
};

/// Every line target in the image, ordered left to right (by the centroid of its
/// corners): the order the `targets` of a ring entry name them in.
pub fn detect_line_targets(img: &Gray, lens: Lens) -> Vec<LineTargetDetection> {
    // A print on a ground of another grey has three levels: the L is dark against the
    // paper, not necessarily against the ground. Otsu's split of all levels, and of each
    // side of it, between them separate the L from its paper.
    let mid = otsu(img, 0.0, 256.0);
    let thresholds = [mid, otsu(img, 0.0, mid), otsu(img, mid, 256.0)];
    let mut found: Vec<LineTargetDetection> = Vec::new();
    for t in thresholds {
        for boundary in dark_components(img, t) {
            let rough = coarse_corners(&boundary);
            let Some(d) = rough.and_then(|rough| measure(img, lens, &rough)) else {
                continue;
            };
            // The same target found at another threshold shares most of its corners (a
            // noisy threshold can cut a corner off and the sides still fit loosely: seen
            // at σ 10 grey, one corner 10 px off, edge RMS 0.42 px against 0.08 px): the
            // better fitting one is kept.
            let same = |e: &LineTargetDetection| {
                (0..LINES)
                    .filter(|&k| {
                        (e.corners[k][0] - d.corners[k][0]).hypot(e.corners[k][1] - d.corners[k][1])
                            < 2.0
                    })
                    .count()
                    >= LINES / 2
            };
            match found.iter_mut().find(|e| same(e)) {
                Some(e) if d.edge_rms_px < e.edge_rms_px => *e = d,
                Some(_) => {}
                None => found.push(d),
            }
        }
    }
    found.sort_by(|a, b| {
        let cx = |d: &LineTargetDetection| d.corners.iter().map(|c| c[0]).sum::<f64>();
        cx(a).total_cmp(&cx(b))
    });
    found
}

/// Otsu's threshold of the grey levels in `[lo, hi)` (0..256).
fn otsu(img: &Gray, lo: f64, hi: f64) -> f64 {
    let mut hist = [0u64; 256];
    for v in &img.data {
        let v = *v as f64;
        if v >= lo && v < hi {
            hist[v.clamp(0.0, 255.0) as usize] += 1;
        }
    }
    let total = hist.iter().sum::<u64>() as f64;
    let sum_all: f64 = hist
        .iter()
        .enumerate()
        .map(|(i, n)| i as f64 * *n as f64)
        .sum();
    let (mut w0, mut sum0, mut best, mut at) = (0.0, 0.0, -1.0, 0.5 * (lo + hi));
    for (i, n) in hist.iter().enumerate() {
        w0 += *n as f64;
        sum0 += i as f64 * *n as f64;
        let w1 = total - w0;
        if w0 == 0.0 || w1 == 0.0 {
            continue;
        }
        let (m0, m1) = (sum0 / w0, (sum_all - sum0) / w1);
        let between = w0 * w1 * (m0 - m1) * (m0 - m1);
        if between > best {
            best = between;
            at = i as f64 + 0.5;
        }
    }
    at
}

/// Outline pixels (centres) of each dark 4-connected component that does not touch the
/// image border and is big enough to be a target.
fn dark_components(img: &Gray, threshold: f64) -> Vec<Vec<Vec2>> {
    let (w, h) = (img.width, img.height);
    let dark = |i: usize| (img.data[i] as f64) < threshold;
    let mut label = vec![u32::MAX; w * h];
    let mut out = Vec::new();
    let mut stack = Vec::new();
    for start in 0..w * h {
        if label[start] != u32::MAX || !dark(start) {
            continue;
        }
        let id = out.len() as u32;
        label[start] = id;
        stack.push(start);
        let mut pixels = Vec::new();
        let mut touches_border = false;
        while let Some(i) = stack.pop() {
            pixels.push(i);
            let (x, y) = (i % w, i / w);
            if x == 0 || y == 0 || x + 1 == w || y + 1 == h {
                touches_border = true;
                continue;
            }
            for j in [i - 1, i + 1, i - w, i + w] {
                if label[j] == u32::MAX && dark(j) {
                    label[j] = id;
                    stack.push(j);
                }
            }
        }
        let boundary: Vec<Vec2> = if touches_border || pixels.len() < 200 {
            vec![]
        } else {
            pixels
                .iter()
                .filter(|&&i| [i - 1, i + 1, i - w, i + w].iter().any(|&j| label[j] != id))
                .map(|&i| Vec2::new((i % w) as f64, (i / w) as f64))
                .collect()
        };
        out.push(boundary);
    }
    out.into_iter().filter(|b| b.len() >= 40).collect()
}

/// Convex hull (counter-clockwise in `x`-right `y`-up terms), Andrew's monotone chain.
fn convex_hull(points: &[Vec2]) -> Vec<Vec2> {
    let mut p: Vec<Vec2> = points.to_vec();
    p.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.y.total_cmp(&b.y)));
    p.dedup();
    if p.len() < 3 {
        return p;
    }
    let cross = |o: Vec2, a: Vec2, b: Vec2| (a.x - o.x) * (b.y - o.y) - (a.y - o.y) * (b.x - o.x);
    let mut hull: Vec<Vec2> = Vec::with_capacity(2 * p.len());
    for pass in 0..2 {
        let start = hull.len();
        let iter: Box<dyn Iterator<Item = &Vec2>> = if pass == 0 {
            Box::new(p.iter())
        } else {
            Box::new(p.iter().rev())
        };
        for &q in iter {
            while hull.len() >= start + 2
                && cross(hull[hull.len() - 2], hull[hull.len() - 1], q) <= 0.0
            {
                hull.pop();
            }
            hull.push(q);
        }
        hull.pop();
    }
    hull
}

/// Drop the hull vertex whose removal loses the least area until `n` remain.
fn reduce_polygon(mut poly: Vec<Vec2>, n: usize) -> Vec<Vec2> {
    while poly.len() > n {
        let m = poly.len();
        let (mut best, mut at) = (f64::INFINITY, 0);
        for k in 0..m {
            let (a, b, c) = (poly[(k + m - 1) % m], poly[k], poly[(k + 1) % m]);
            let area = ((b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x)).abs();
            if area < best {
                best = area;
                at = k;
            }
        }
        poly.remove(at);
    }
    poly
}

fn dist_to_segment(p: Vec2, a: Vec2, b: Vec2) -> f64 {
    let ab = b - a;
    let t = ((p - a).dot(&ab) / ab.norm_squared().max(1e-300)).clamp(0.0, 1.0);
    (p - (a + ab * t)).norm()
}

/// Rough `P1..P6` of an L-shaped outline, or `None` if it is not one.
fn coarse_corners(boundary: &[Vec2]) -> Option<[Vec2; LINES]> {
    if boundary.is_empty() {
        return None;
    }
    let hull = reduce_polygon(convex_hull(boundary), 5);
    if hull.len() != 5 {
        return None;
    }
    let near_edge = |p: Vec2, k: usize| dist_to_segment(p, hull[k], hull[(k + 1) % 5]) < 2.0;
    // The bridge over the notch: the hull side the outline does not run along.
    let coverage = |k: usize| {
        boundary.iter().filter(|p| near_edge(**p, k)).count() as f64
            / (hull[(k + 1) % 5] - hull[k]).norm().max(1.0)
    };
    let bridge = (0..5).min_by(|&i, &j| coverage(i).total_cmp(&coverage(j)))?;
    // The reflex corner: of the outline points on no hull side (the notch), the one
    // farthest from the bridge.
    let (a, b) = (hull[bridge], hull[(bridge + 1) % 5]);
    let off_bridge = |p: Vec2| {
        let d = b - a;
        ((p - a).x * d.y - (p - a).y * d.x).abs() / d.norm().max(1e-300)
    };
    // Inside the reduced hull (a corner's pixels may stick out of it).
    let side = |p: Vec2, k: usize| {
        let (u, v) = (hull[k], hull[(k + 1) % 5]);
        (v.x - u.x) * (p.y - u.y) - (v.y - u.y) * (p.x - u.x)
    };
    let centroid = hull.iter().sum::<Vec2>() / 5.0;
    let inside = |p: Vec2| (0..5).all(|k| side(p, k) * side(centroid, k) > 0.0);
    let p4 = *boundary
        .iter()
        .filter(|p| inside(**p) && !(0..5).any(|k| near_edge(**p, k)))
        .max_by(|p, q| off_bridge(**p).total_cmp(&off_bridge(**q)))?;
    let span = (0..5)
        .map(|k| (hull[(k + 1) % 5] - hull[k]).norm())
        .fold(0.0, f64::max);
    if off_bridge(p4) < 0.1 * span || coverage(bridge) > 0.5 {
        return None; // no notch: not an L
    }
    // Walking the hull from one end of the bridge round the far side: a, x, y, z, b.
    let walk: [Vec2; 5] = std::array::from_fn(|k| hull[(bridge + 1 + k) % 5]);
    label_corners(walk, p4)
}

/// Name the corners of an L from its hull walk `a, x, y, z, b` (the bridge over the
/// notch is `b → a`) and the reflex corner: `P1` is the middle of the walk, `P4` the
/// notch, and `P2` is the neighbour of `P1` for which `P1 → P2 → P3` turns clockwise
/// on the page (the printed side facing the camera).
pub fn label_corners(walk: [Vec2; 5], p4: Vec2) -> Option<[Vec2; LINES]> {
    let [a, x, y, z, b] = walk;
    let cross = |o: Vec2, p: Vec2, q: Vec2| (p.x - o.x) * (q.y - o.y) - (p.y - o.y) * (q.x - o.x);
    // Image y is down: a positive cross product is a clockwise turn on the page.
    let [p2, p3, p5, p6] = if cross(y, z, b) > 0.0 {
        [z, b, a, x]
    } else {
        [x, a, b, z]
    };
    Some([y, p2, p3, p4, p5, p6])
}

/// Refine the rough outline and package lines, corners and vanishing points.
fn measure(img: &Gray, lens: Lens, rough: &[Vec2; LINES]) -> Option<LineTargetDetection> {
    let shortest = (0..LINES)
        .map(|k| (rough[(k + 1) % LINES] - rough[k]).norm())
        .fold(f64::INFINITY, f64::min);
    if shortest < MIN_SIDE_PX {
        return None;
    }
    let reach = (0.2 * shortest).clamp(1.5, 8.0);
    let r = refine_polygon(img, rough, lens, reach, &L_SIDES)?;
    // A clean print: a clear step and edges that are lines.
    if r.contrast < 20.0 || r.edge_rms > 0.5 {
        return None;
    }
    // The point nearest (least squares) to each group's three lines; in the plane the
    // lines live in, so the identity stands for the intrinsics.
    let vp = |group: [usize; 3]| {
        let lines = group.map(|k| r.side_lines[k]);
        let v = vanishing_direction(&lines, &Mat3::identity())?;
        let v = if v.z < 0.0 { -v } else { v };
        Some([v.x, v.y, v.z])
    };
    Some(LineTargetDetection {
        corners: std::array::from_fn(|k| [r.corners[k].x, r.corners[k].y]),
        lines: (0..LINES)
            .map(|k| DetectedLine {
                line: k + 1,
                // Every third edge point: their pixels do not overlap, so the points are
                // independent, as the vanishing method's point-to-line residuals and
                // their σ assume (all points, 3 sharing each pixel: NEES 11-14 from
                // images where 6 is honest).
                points: r.side_points[k]
                    .iter()
                    .step_by(INDEPENDENT_EVERY)
                    .map(|p| [p.x, p.y])
                    .collect(),
                plane_line: r.side_lines[k].into(),
            })
            .collect(),
        vanishing_points: [vp(Z_GROUP)?, vp(X_GROUP)?],
        edge_rms_px: r.edge_rms,
        contrast: r.contrast,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hull_and_reduction_find_a_pentagon_around_an_l() {
        // A pixelated L (arm 40, width 15), outline points only.
        let inside = |x: i32, y: i32| {
            (0..40).contains(&x) && (0..15).contains(&y)
                || (0..15).contains(&x) && (0..40).contains(&y)
        };
        let mut pts = Vec::new();
        for y in -1..41 {
            for x in -1..41 {
                if inside(x, y)
                    && [(1, 0), (-1, 0), (0, 1), (0, -1)]
                        .iter()
                        .any(|(dx, dy)| !inside(x + dx, y + dy))
                {
                    pts.push(Vec2::new(x as f64, y as f64));
                }
            }
        }
        let c = coarse_corners(&pts).expect("an L");
        // P1 is the outer corner, P4 the notch.
        assert!((c[0] - Vec2::new(0.0, 0.0)).norm() < 1.5, "{:?}", c[0]);
        assert!((c[3] - Vec2::new(14.0, 14.0)).norm() < 1.5, "{:?}", c[3]);
        // Clockwise on the page from P1 (x right, y down): P2 along +x here.
        assert!((c[1] - Vec2::new(39.0, 0.0)).norm() < 1.5, "{:?}", c[1]);
        assert!((c[5] - Vec2::new(0.0, 39.0)).norm() < 1.5, "{:?}", c[5]);
        // A square has no notch.
        let square: Vec<Vec2> = (0..40)
            .flat_map(|k| {
                let t = k as f64;
                [
                    Vec2::new(t, 0.0),
                    Vec2::new(t, 39.0),
                    Vec2::new(0.0, t),
                    Vec2::new(39.0, t),
                ]
            })
            .collect();
        assert!(coarse_corners(&square).is_none());
    }
}
