//! Targets of thin printed lines in two orthogonal groups (a "#" grid or any layout of
//! [`LineLayout`]) in images: ridge points ([`super::ridge`]) linked into straight lines,
//! the lines of one print found by their crossings, split into the two groups, ordered
//! and labelled with the layout's line numbers.
//!
//! Everything geometric happens in the *ideal* image (the measured points undistorted
//! through the lens, never the image resampled), where the printed lines are straight.
//!
//! - **Linking.** Neighbouring line pixels whose normals agree within 6° and whose
//!   centres lie on one line are joined; chains are cut where the Hessian degenerates,
//!   i.e. at every crossing, a chain that still bends is cut into its straight pieces,
//!   and collinear pieces are merged back into one line.
//! - **One print.** Lines that cross each other (within their extents) belong to one
//!   print. A print's lines are two-coloured by "crosses": lines of one group never cross
//!   each other, so the colouring *is* the grouping, and no vanishing-point clustering is
//!   needed; the counts must be the layout's.
//! - **Labelling.** Within a group, lines are ordered along a line of the other group.
//!   Of the orderings, those seen from the printed side are kept: the image of the
//!   target's `+z` turns clockwise onto that of `+x` (image `y` down), as for the L; of
//!   these the one whose crossings fit the layout's by a homography best. A symmetric
//!   layout leaves several that fit equally; the first is reported and the vanishing
//!   method decides between them ([`rigcal_core::target::line_layout::LineLayout::symmetries`]).
//!   A layout with an orientation mark is read instead: each equally good labelling
//!   predicts the disc at another place on the paper, and the one that lands on ink wins
//!   (clearly, or the print is reported with why its mark could not be read).
//! - **Crossings.** No point within a stroke width (plus the smoothing's reach) of a
//!   crossing is kept: the other line's ink bends the profile there.

use super::gray::Gray;
use super::linetarget::DetectedLine;
use super::refine::Lens;
use super::ridge::{ridge_points, untilt, RidgePoint, SCALES};
use rigcal_core::geometry::homography::homography;
use rigcal_core::geometry::line2::{distance, fit_line, intersect, through};
use rigcal_core::geometry::{Vec2, Vec3};
use rigcal_core::target::line_layout::{Axis, LineLayout, Mark};
use serde::Serialize;

/// One print of thin lines found in an image.
#[derive(Clone, Debug, Serialize)]
pub struct LineGridDetection {
    /// Every line of the layout, `line` numbered as the layout's (1-based).
    pub lines: Vec<DetectedLine>,
    /// Centroid of the crossings (raw pixels).
    pub centre: [f64; 2],
    /// Median stroke width (px), from the scale each point was found at (`w ≈ 2σ`).
    pub stroke_px: f64,
    /// RMS distance (px) of the points from their lines.
    pub line_rms_px: f64,
    /// A line ends within reach of the image border: the print may be cut.
    pub touches_border: bool,
    /// How many labellings fit equally (the layout's symmetries seen in this image;
    /// 1 once an orientation mark decided between them).
    pub equivalent_labellings: usize,
    /// The layout has an orientation mark and it could not be read here: why. The lines
    /// are then labelled as the first equal fit, which may be the wrong way round.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mark_error: Option<String>,
}

/// Smallest line worth measuring (ideal px).
const MIN_LINE_PX: f64 = 24.0;
/// Points a chain needs to be a line fragment.
const MIN_CHAIN: usize = 8;

struct Chain {
    points: Vec<RidgePoint>,
    /// Ideal-image positions of `points`.
    ideal: Vec<Vec2>,
    line: Vec3,
    strength: f32,
}

/// Raw pixel → ideal pixel of the lens (the camera without distortion).
fn ideal(lens: Lens, p: Vec2) -> Option<Vec2> {
    match lens.0 {
        Some(c) => {
            let n = c.unproject(&p)?;
            Some(Vec2::new(c.fx * n.x + c.cx, c.fy * n.y + c.cy))
        }
        None => Some(p),
    }
}

/// Raw pixel of an ideal-image point (the inverse of [`ideal`]).
fn raw(lens: Lens, q: Vec2) -> Option<Vec2> {
    match lens.0 {
        Some(c) => c.project(&Vec3::new((q.x - c.cx) / c.fx, (q.y - c.cy) / c.fy, 1.0)),
        None => Some(q),
    }
}

/// Smallest radius (px) at which an orientation mark is read: its inner half, which is
/// what is sampled, then still spans a pixel beyond the blur.
const MIN_MARK_RADIUS_PX: f64 = 2.0;
/// The mark's place must be at most this fraction of the grey of the other places
/// (paper) to be read as ink: ink is a fifth to a third of paper, while vignetting
/// varies paper by a few percent across one print.
const MARK_INK_RATIO: f64 = 0.6;

/// Which of the equally fitting labellings (`plane_to_ideal` homographies of sheet
/// `(x, y)`) puts the layout's mark on ink: `Ok(index)`, or why it cannot be told. All
/// places must be in the image, so the mark's true place is always among those compared.
fn read_mark(
    img: &Gray,
    lens: Lens,
    mark: &Mark,
    plane_to_ideal: &[nalgebra::Matrix3<f64>],
) -> Result<usize, String> {
    let to_raw = |h: &nalgebra::Matrix3<f64>, x: f64, z: f64| {
        let v = h * Vec3::new(x, z, 1.0);
        (v.z.abs() > 1e-12)
            .then(|| Vec2::new(v.x / v.z, v.y / v.z))
            .and_then(|q| raw(lens, q))
    };
    let (mx, mz, r) = (mark.centre.x, mark.centre.z, mark.radius);
    let mut greys = Vec::with_capacity(plane_to_ideal.len());
    for h in plane_to_ideal {
        let c = to_raw(h, mx, mz).ok_or("its place projects outside the lens's domain")?;
        let radius_px = [(r, 0.0), (-r, 0.0), (0.0, r), (0.0, -r)]
            .iter()
            .filter_map(|(dx, dz)| Some((to_raw(h, mx + dx, mz + dz)? - c).norm()))
            .fold(f64::INFINITY, f64::min);
        if !radius_px.is_finite() {
            return Err("its place projects outside the lens's domain".into());
        }
        if radius_px < MIN_MARK_RADIUS_PX {
            return Err(format!(
                "the orientation mark is {radius_px:.1} px in radius here, at least {MIN_MARK_RADIUS_PX} px is needed to read it"
            ));
        }
        // The inner half of the disc: the centre and two rings of 8.
        let mut sum = img
            .sample(c)
            .ok_or("a place of the orientation mark is outside the image")?;
        for ring in [0.25, 0.5] {
            for k in 0..8 {
                let a = k as f64 * std::f64::consts::FRAC_PI_4;
                let p = c + ring * radius_px * Vec2::new(a.cos(), a.sin());
                sum += img
                    .sample(p)
                    .ok_or("a place of the orientation mark is outside the image")?;
            }
        }
        greys.push(sum / 17.0);
    }
    let mut order: Vec<usize> = (0..greys.len()).collect();
    order.sort_by(|&a, &b| greys[a].total_cmp(&greys[b]));
    match order.as_slice() {
        [dark, next, ..] if greys[*dark] <= MARK_INK_RATIO * greys[*next] => Ok(*dark),
        [dark, next, ..] => Err(format!(
            "no place of the orientation mark is clearly dark (grey {:.0} against {:.0} at the next place)",
            greys[*dark], greys[*next]
        )),
        _ => Ok(0),
    }
}

/// Union-find root with path halving.
fn root(parent: &mut [usize], mut i: usize) -> usize {
    while parent[i] != i {
        parent[i] = parent[parent[i]];
        i = parent[i];
    }
    i
}

/// Chains of ridge points: neighbours with agreeing normals on one line.
fn chains(img: &Gray, lens: Lens, pts: &[RidgePoint]) -> Vec<Chain> {
    let w = img.width;
    let mut at = vec![usize::MAX; img.width * img.height];
    for (k, p) in pts.iter().enumerate() {
        at[p.pixel.1 as usize * w + p.pixel.0 as usize] = k;
    }
    let mut parent: Vec<usize> = (0..pts.len()).collect();
    let cos6 = 6f64.to_radians().cos();
    for (k, p) in pts.iter().enumerate() {
        let (x, y) = (p.pixel.0 as i64, p.pixel.1 as i64);
        for (dx, dy) in [(1, 0), (0, 1), (1, 1), (-1, 1)] {
            let (nx, ny) = (x + dx, y + dy);
            if nx < 0 || ny < 0 || nx >= w as i64 || ny >= img.height as i64 {
                continue;
            }
            let j = at[ny as usize * w + nx as usize];
            if j == usize::MAX {
                continue;
            }
            let q = &pts[j];
            if p.normal.dot(&q.normal).abs() < cos6 || (q.pos - p.pos).dot(&p.normal).abs() > 0.7 {
                continue;
            }
            let (a, b) = (root(&mut parent, k), root(&mut parent, j));
            if a != b {
                parent[a] = b;
            }
        }
    }
    let mut groups: std::collections::HashMap<usize, Vec<usize>> = Default::default();
    for k in 0..pts.len() {
        let r = root(&mut parent, k);
        groups.entry(r).or_default().push(k);
    }
    let mut out = Vec::new();
    for (_, members) in groups {
        if members.len() < MIN_CHAIN {
            continue;
        }
        let points: Vec<RidgePoint> = members.iter().map(|&k| pts[k]).collect();
        let Some(ideal_pts) = points
            .iter()
            .map(|p| ideal(lens, p.pos))
            .collect::<Option<Vec<_>>>()
        else {
            continue;
        };
        straight_pieces(points, ideal_pts, &mut out);
    }
    out
}

/// Largest RMS distance (ideal px) of a chain's points from its line: beyond it the
/// chain is a curve, a blob or texture, not (only) a printed line.
const MAX_CHAIN_RMS: f64 = 0.6;

/// RMS distance (px) of `pts` from `line`.
fn rms_from(line: &Vec3, pts: &[Vec2]) -> f64 {
    (pts.iter().map(|q| distance(line, q).powi(2)).sum::<f64>() / pts.len().max(1) as f64).sqrt()
}

/// The straight pieces of one linked chain, pushed onto `out`. Linking follows normals
/// that turn by under 6° per pixel, so a chain can bend: at the short stub a stroke
/// leaves beyond its last crossing, where the end and the crossing line both pull the
/// smoothed profile, the centres curve into the crossing and on along the stroke. Such
/// a chain is cut where it strays farthest from the chord between its ends (as
/// Douglas–Peucker simplifies a polyline) until each piece is straight, so the curve
/// costs only its own points, not the whole stroke's.
fn straight_pieces(points: Vec<RidgePoint>, ideal: Vec<Vec2>, out: &mut Vec<Chain>) {
    let mut todo = vec![(points, ideal)];
    while let Some((points, ideal)) = todo.pop() {
        if points.len() < MIN_CHAIN {
            continue;
        }
        let Some(line) = fit_line(&ideal) else {
            continue;
        };
        if rms_from(&line, &ideal) <= MAX_CHAIN_RMS {
            let mut s: Vec<f32> = points.iter().map(|p| p.strength).collect();
            s.sort_by(f32::total_cmp);
            out.push(Chain {
                strength: s[s.len() / 2],
                points,
                ideal,
                line,
            });
            continue;
        }
        // Along the chain (its principal direction), then the point farthest from the
        // chord between the two ends.
        let d = direction(&line);
        let mut order: Vec<usize> = (0..points.len()).collect();
        order.sort_by(|&a, &b| ideal[a].dot(&d).total_cmp(&ideal[b].dot(&d)));
        let (first, last) = (ideal[order[0]], ideal[order[order.len() - 1]]);
        let Some(chord) = through(&first, &last) else {
            continue;
        };
        let far = (1..order.len() - 1)
            .max_by(|&a, &b| {
                distance(&chord, &ideal[order[a]])
                    .abs()
                    .total_cmp(&distance(&chord, &ideal[order[b]]).abs())
            })
            .unwrap_or(order.len() / 2);
        for part in [&order[..far], &order[far + 1..]] {
            todo.push((
                part.iter().map(|&k| points[k]).collect(),
                part.iter().map(|&k| ideal[k]).collect(),
            ));
        }
    }
}

/// A merged printed line: its points (raw and ideal), fitted line and extent.
struct Line {
    points: Vec<RidgePoint>,
    ideal: Vec<Vec2>,
    line: Vec3,
    /// Extent along the line direction: `(t_min, t_max)` of `foot(t)`.
    span: (f64, f64),
    sigma: f64,
}

fn direction(l: &Vec3) -> Vec2 {
    Vec2::new(-l.y, l.x)
}

fn span(line: &Vec3, pts: &[Vec2]) -> (f64, f64) {
    let d = direction(line);
    pts.iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
            let t = p.dot(&d);
            (a.min(t), b.max(t))
        })
}

/// Merge collinear chains (a printed line is cut at every crossing) into lines.
fn merge(mut chains: Vec<Chain>) -> Vec<Line> {
    chains.sort_by_key(|c| std::cmp::Reverse(c.points.len()));
    let mut lines: Vec<Line> = Vec::new();
    for c in chains {
        let (c_lo, c_hi) = span(&c.line, &c.ideal);
        let target = lines.iter_mut().find(|l| {
            let cos = direction(&l.line).dot(&direction(&c.line)).abs();
            if cos < 3f64.to_radians().cos() {
                return false;
            }
            // Within half a stroke (σ ≈ w/2) or 2 px of the line: the same ink.
            let tol = l.sigma.max(2.0);
            let near = c.ideal.iter().all(|q| distance(&l.line, q).abs() < tol);
            // Projected on the merged line's direction, the gap between extents.
            let d = direction(&l.line);
            let (a, b) = c
                .ideal
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
                    (a.min(p.dot(&d)), b.max(p.dot(&d)))
                });
            let gap = (a - l.span.1).max(l.span.0 - b).max(0.0);
            near && gap < 0.5 * (l.span.1 - l.span.0) + 12.0 * l.sigma
        });
        let sigma = c.points.iter().map(|p| p.sigma as f64).sum::<f64>() / c.points.len() as f64;
        match target {
            Some(l) => {
                l.points.extend(c.points);
                l.ideal.extend(c.ideal);
                if let Some(f) = fit_line(&l.ideal) {
                    l.line = f;
                }
                l.span = span(&l.line, &l.ideal);
                l.sigma =
                    l.points.iter().map(|p| p.sigma as f64).sum::<f64>() / l.points.len() as f64;
            }
            None => lines.push(Line {
                points: c.points,
                ideal: c.ideal,
                line: c.line,
                span: (c_lo, c_hi),
                sigma,
            }),
        }
    }
    lines.retain(|l| l.span.1 - l.span.0 >= MIN_LINE_PX);
    lines
}

/// Correct a line's points for the vignetting tilt across it (see `ridge`), then its
/// ideal points, fit and extent.
fn untilt_line(lens: Lens, l: &mut Line) {
    let mut points = l.points.clone();
    if untilt(&mut points).is_none() {
        return;
    }
    // A point moved by hundredths of a pixel out of the lens's domain: keep the line as found.
    let Some(ideal_pts) = points.iter().map(|p| ideal(lens, p.pos)).collect() else {
        return;
    };
    l.points = points;
    l.ideal = ideal_pts;
    if let Some(f) = fit_line(&l.ideal) {
        l.line = f;
    }
    l.span = span(&l.line, &l.ideal);
}

/// Do lines `a` and `b` cross within their extents (with `slack` px)?
fn crossing(a: &Line, b: &Line) -> Option<Vec2> {
    if direction(&a.line).dot(&direction(&b.line)).abs() > 5f64.to_radians().cos() {
        return None; // within 5° of parallel: no reliable crossing
    }
    let x = intersect(&a.line, &b.line)?;
    let inside = |l: &Line| {
        let t = x.dot(&direction(&l.line));
        let slack = 4.0 * l.sigma + 3.0;
        t >= l.span.0 - slack && t <= l.span.1 + slack
    };
    (inside(a) && inside(b)).then_some(x)
}

/// Every print of `layout` in the image, left to right.
pub fn detect_line_grids(img: &Gray, lens: Lens, layout: &LineLayout) -> Vec<LineGridDetection> {
    let noise = img.noise_sigma() as f32;
    let pts = ridge_points(img, &SCALES, 6.0 + 4.0 * noise);
    let mut chains = chains(img, lens, &pts);
    // Ink on white paper is the strongest line in a calibration image; grout, seams and
    // texture are weaker. Keep chains at least a third as strong as the strongest.
    let strongest = chains.iter().map(|c| c.strength).fold(0.0, f32::max);
    chains.retain(|c| c.strength >= strongest / 3.0);
    let mut lines = merge(chains);
    for l in &mut lines {
        untilt_line(lens, l);
    }

    // Prints: components of the "crosses" graph, two-coloured.
    let n = lines.len();
    let mut adj = vec![Vec::new(); n];
    for i in 0..n {
        for j in i + 1..n {
            if crossing(&lines[i], &lines[j]).is_some() {
                adj[i].push(j);
                adj[j].push(i);
            }
        }
    }
    let len = |i: usize| lines[i].span.1 - lines[i].span.0;
    let mut seen = vec![false; n];
    let mut out = Vec::new();
    for start in 0..n {
        if seen[start] || adj[start].is_empty() {
            continue;
        }
        // The component, then only its long lines: a print's lines are all long, while
        // the stubs at stroke ends and the sheet's corners are short.
        let mut members = vec![start];
        seen[start] = true;
        let mut k = 0;
        while k < members.len() {
            for &j in &adj[members[k]] {
                if !seen[j] {
                    seen[j] = true;
                    members.push(j);
                }
            }
            k += 1;
        }
        let longest = members.iter().map(|&i| len(i)).fold(0.0, f64::max);
        members.retain(|&i| len(i) >= 0.3 * longest);
        let Some(groups) = two_colour(&members, &adj) else {
            continue;
        };
        if let Some(d) = label(img, lens, layout, &lines, &groups) {
            out.push(d);
        }
    }
    out.sort_by(|a, b| a.centre[0].total_cmp(&b.centre[0]));
    out
}

/// Split `members` into the two sides of the "crosses" graph, or `None` if two lines
/// of one side cross (not a print of two groups) or a line crosses none.
fn two_colour(members: &[usize], adj: &[Vec<usize>]) -> Option<[Vec<usize>; 2]> {
    let inside: std::collections::HashSet<usize> = members.iter().copied().collect();
    let mut colour: std::collections::HashMap<usize, u8> = Default::default();
    let mut groups = [Vec::new(), Vec::new()];
    for &s in members {
        if colour.contains_key(&s) {
            continue;
        }
        colour.insert(s, 0);
        groups[0].push(s);
        let mut queue = std::collections::VecDeque::from([s]);
        while let Some(i) = queue.pop_front() {
            let c = colour[&i];
            for &j in adj[i].iter().filter(|j| inside.contains(j)) {
                match colour.get(&j) {
                    None => {
                        colour.insert(j, 1 - c);
                        groups[1 - c as usize].push(j);
                        queue.push_back(j);
                    }
                    Some(&cj) if cj == c => return None,
                    Some(_) => {}
                }
            }
        }
    }
    Some(groups)
}

/// Layout lines of `axis` sorted by their offset (`z` for `x` lines, `x` for `z` lines).
fn sorted_group(layout: &LineLayout, axis: Axis) -> Vec<usize> {
    let mut g = layout.group(axis);
    let key = |m: &usize| {
        let s = layout.segments[*m];
        if axis == Axis::X {
            s.from.z
        } else {
            s.from.x
        }
    };
    g.sort_by(|a, b| key(a).total_cmp(&key(b)));
    g
}

/// Image lines of `group` ordered along line `along` (of the other group).
fn ordered(lines: &[Line], group: &[usize], along: usize) -> Vec<usize> {
    let d = direction(&lines[along].line);
    let mut keyed: Vec<(f64, usize)> = group
        .iter()
        .filter_map(|&g| Some((intersect(&lines[g].line, &lines[along].line)?.dot(&d), g)))
        .collect();
    keyed.sort_by(|a, b| a.0.total_cmp(&b.0));
    keyed.into_iter().map(|(_, g)| g).collect()
}

/// Label one print's two groups with the layout's lines, or `None` if it is not one.
fn label(
    img: &Gray,
    lens: Lens,
    layout: &LineLayout,
    lines: &[Line],
    groups: &[Vec<usize>; 2],
) -> Option<LineGridDetection> {
    let (lx, lz) = (sorted_group(layout, Axis::X), sorted_group(layout, Axis::Z));
    let mut candidates = Vec::new();
    for (gx, gz) in [(0, 1), (1, 0)] {
        if groups[gx].len() != lx.len() || groups[gz].len() != lz.len() {
            continue;
        }
        let xs = ordered(lines, &groups[gx], groups[gz][0]);
        let zs = ordered(lines, &groups[gz], groups[gx][0]);
        if xs.len() != lx.len() || zs.len() != lz.len() {
            continue;
        }
        for rev_x in [false, true] {
            for rev_z in [false, true] {
                let mut xs = xs.clone();
                let mut zs = zs.clone();
                if rev_x {
                    xs.reverse();
                }
                if rev_z {
                    zs.reverse();
                }
                candidates.push((xs, zs));
            }
        }
    }
    let cross = |i: usize, j: usize| intersect(&lines[i].line, &lines[j].line);
    let mut fits = Vec::new();
    for (xs, zs) in candidates {
        // Seen from the printed side: the image of +z turns clockwise onto that of +x.
        let o = cross(xs[0], zs[0])?;
        let jx = cross(xs[0], *zs.last()?)? - o;
        let jz = cross(*xs.last()?, zs[0])? - o;
        if jz.x * jx.y - jz.y * jx.x <= 0.0 {
            continue;
        }
        let mut plane = Vec::new();
        let mut image = Vec::new();
        for (a, &i) in xs.iter().enumerate() {
            for (b, &j) in zs.iter().enumerate() {
                let (sx, sz) = (layout.segments[lz[b]].from.x, layout.segments[lx[a]].from.z);
                plane.push(Vec2::new(sx, sz));
                image.push(cross(i, j)?);
            }
        }
        let h = homography(&plane, &image)?;
        let rms = (plane
            .iter()
            .zip(&image)
            .map(|(p, q)| {
                let v = h * Vec3::new(p.x, p.y, 1.0);
                (Vec2::new(v.x / v.z, v.y / v.z) - q).norm_squared()
            })
            .sum::<f64>()
            / plane.len() as f64)
            .sqrt();
        fits.push((rms, xs, zs, image, h));
    }
    fits.sort_by(|a, b| a.0.total_cmp(&b.0));
    let best_rms = fits.first()?.0;
    // Crossings must sit where the layout puts them (a tolerance of a stroke or 2 px).
    let stroke = 2.0 * lines[fits[0].1[0]].sigma;
    if best_rms > stroke.max(2.0) {
        return None;
    }
    let mut equivalent = fits
        .iter()
        .filter(|f| f.0 <= best_rms + 0.1 * stroke.max(1.0))
        .count();
    let mut chosen = 0;
    let mut mark_error = None;
    if let Some(mark) = &layout.mark {
        let hs: Vec<_> = fits[..equivalent].iter().map(|f| f.4).collect();
        match read_mark(img, lens, mark, &hs) {
            Ok(k) => {
                chosen = k;
                equivalent = 1;
            }
            Err(why) => mark_error = Some(why),
        }
    }
    let (_, xs, zs, crossings, _) = fits.swap_remove(chosen);

    // Points: off the crossings and the ends (within two stroke widths of either, the
    // other line's ink or the stroke's end bends the profile: at one width the
    // noise-free error on Wu's ring was 3.5 times that at two), every ⌈2σ⌉-th (the
    // smoothing correlates neighbours; independent points keep the method's σ honest).
    // The smoothing reaches ~4σ from a point in every direction, and a line crossing
    // this one at an angle θ (or the square end of this stroke, cut along the other
    // group) is only `t·sin θ` from a point `t` along it: in a steep rig view (θ ≈ 22°)
    // the last points kept by the perpendicular rule were 0.04-0.09 px off.
    let mut detected = Vec::new();
    let mut widths = Vec::new();
    let mut sq = 0.0;
    let mut count = 0usize;
    let mut touches_border = false;
    let (w, h) = (img.width as f64, img.height as f64);
    for (k, &i) in xs.iter().chain(zs.iter()).enumerate() {
        let label = if k < xs.len() {
            lx[k]
        } else {
            lz[k - xs.len()]
        };
        let l = &lines[i];
        let d = direction(&l.line);
        let others: Vec<(f64, f64)> = if k < xs.len() { &zs } else { &xs }
            .iter()
            .filter_map(|&j| {
                let x = intersect(&l.line, &lines[j].line)?;
                let sin = direction(&lines[j].line).perp(&d).abs().max(0.2);
                let (sj, sl) = (lines[j].sigma, l.sigma);
                Some((x.dot(&d), (4.0 * (sj + sl)).max((sj + 4.0 * sl) / sin)))
            })
            .collect();
        let sin = if k < xs.len() { &zs } else { &xs }
            .iter()
            .map(|&j| direction(&lines[j].line).perp(&d).abs())
            .fold(1.0f64, f64::min)
            .max(0.2);
        let reach = 4.0 * l.sigma / sin;
        let mut keep: Vec<(f64, Vec2, Vec2)> = l
            .points
            .iter()
            .zip(&l.ideal)
            .filter(|(_, q)| {
                let t = q.dot(&d);
                t > l.span.0 + reach
                    && t < l.span.1 - reach
                    && others.iter().all(|(c, r)| (t - c).abs() > *r)
            })
            .map(|(p, q)| (q.dot(&d), p.pos, *q))
            .collect();
        keep.sort_by(|a, b| a.0.total_cmp(&b.0));
        let every = (2.0 * l.sigma).ceil().max(1.0) as usize;
        let keep: Vec<(f64, Vec2, Vec2)> = keep.into_iter().step_by(every).collect();
        for (_, _, q) in &keep {
            sq += distance(&l.line, q).powi(2);
            count += 1;
        }
        widths.extend(l.points.iter().map(|p| 2.0 * p.sigma as f64));
        for p in &l.points {
            let reach = 3.0 * p.sigma as f64 + 2.0;
            touches_border |= p.pos.x < reach
                || p.pos.y < reach
                || p.pos.x > w - 1.0 - reach
                || p.pos.y > h - 1.0 - reach;
        }
        detected.push(DetectedLine {
            line: label + 1,
            points: keep.iter().map(|(_, p, _)| [p.x, p.y]).collect(),
            plane_line: l.line.into(),
        });
    }
    detected.sort_by_key(|l| l.line);
    widths.sort_by(f64::total_cmp);
    let centre = crossings.iter().sum::<Vec2>() / crossings.len() as f64;
    // The centre in raw pixels (for ordering prints left to right).
    let centre = raw(lens, centre).unwrap_or(centre);
    Some(LineGridDetection {
        lines: detected,
        centre: [centre.x, centre.y],
        stroke_px: widths.get(widths.len() / 2).copied().unwrap_or(0.0),
        line_rms_px: (sq / count.max(1) as f64).sqrt(),
        touches_border,
        equivalent_labellings: equivalent,
        mark_error,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(pos: Vec2, normal: Vec2) -> RidgePoint {
        RidgePoint {
            pos,
            normal,
            strength: 50.0,
            sigma: 1.5,
            pixel: (pos.x as u32, pos.y as u32),
            paper_tilt: None,
            tilt_lever: 0.0,
        }
    }

    #[test]
    fn a_chain_that_bends_at_its_end_keeps_its_straight_run() {
        // 60 points along y = 100, then a quarter circle of radius 12 turning up.
        let mut pts: Vec<Vec2> = (0..60).map(|i| Vec2::new(i as f64, 100.0)).collect();
        for k in 1..=18 {
            let a = k as f64 / 18.0 * std::f64::consts::FRAC_PI_2;
            pts.push(Vec2::new(59.0 + 12.0 * a.sin(), 112.0 - 12.0 * a.cos()));
        }
        let points: Vec<RidgePoint> = pts.iter().map(|&p| point(p, Vec2::y())).collect();
        let whole = fit_line(&pts).unwrap();
        let rms = rms_from(&whole, &pts);
        assert!(
            rms > MAX_CHAIN_RMS,
            "the whole chain is a curve ({rms:.2} px)"
        );

        let mut out = Vec::new();
        straight_pieces(points, pts.clone(), &mut out);
        let longest = out.iter().max_by_key(|c| c.points.len()).unwrap();
        // Every point of the straight run but at most the last few, where the curve begins.
        let on_line = longest.ideal.iter().filter(|q| q.y == 100.0).count();
        assert!(on_line >= 55, "{on_line} of 60 straight points kept");
        assert!(longest.ideal.iter().all(|q| (q.y - 100.0).abs() < 1.0));
        for c in &out {
            assert!(rms_from(&c.line, &c.ideal) <= MAX_CHAIN_RMS);
        }
    }

    #[test]
    fn a_straight_chain_is_one_piece() {
        let pts: Vec<Vec2> = (0..40)
            .map(|i| Vec2::new(3.0 + 0.8 * i as f64, 7.0 + 0.6 * i as f64))
            .collect();
        let points = pts
            .iter()
            .map(|&p| point(p, Vec2::new(-0.6, 0.8)))
            .collect();
        let mut out = Vec::new();
        straight_pieces(points, pts, &mut out);
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].points.len(), 40);
    }
}
