//! Thin dark lines (ridges) with subpixel centres: Steger's detector of curvilinear
//! structures ("An unbiased detector of curvilinear structures", PAMI 1998).
//!
//! The image is smoothed by a Gaussian of scale `σ` and differentiated (first and second
//! derivatives, separable kernels). At each pixel the Hessian's eigenvector of largest
//! eigenvalue is the normal `n` across a dark line; the second-order Taylor expansion of
//! the smoothed profile along `n` has its extremum at `t = −(∇r·n) / (nᵀ H n)`, and the
//! pixel holds a line point when that extremum lies inside it (`|t·n| ≤ ½` per axis).
//! For a symmetric bar (ink on paper, the same white on both sides) the extremum of the
//! smoothed profile is the bar's centre at every `σ ≥ w / (2√3)` (`w` the width), so the
//! centre is unbiased. Vignetting breaks that symmetry: it multiplies the print by a
//! brightness that varies across the stroke, and the smoothed profile's extremum then
//! moves by `−g / κ` (`g` the slope the brightness puts on the smoothed profile at the
//! centre, `κ` the curvature there): 0.06 px for a 15 px stroke where 25 % corner
//! vignetting tilts 200 grey of paper by 0.16 grey/px. Steger's own correction is for
//! lines whose two sides differ in grey; ours is for this multiplicative tilt. For
//! `I = (1 + βu)·p(u)` with `p` symmetric about the centre `c`, the slope at the centre
//! is exactly `β·∫(u²/σ²)G(u)p(u)du = β·(r(c) + σ²κ)`, all measured at the centre, so
//! the centre moves by `β·(r(c) + σ²κ)/κ` along `n`. The relative tilt `β` is read off
//! the paper on either side, `(r_n(c + D) + r_n(c − D)) / (r(c + D) + r(c − D))` at `D`
//! 4σ beyond the stroke's edges (where the smoothed stroke is flat, so its own slope
//! cancels: the tilt also multiplies what is left of the stroke's slope there, unevenly
//! on the two sides, which at 3σ read the tilt 1–2 % high and left 0.003–0.006 px of a
//! 22 px stroke's 0.12–0.24 px shift; at 4σ, 0.3 %). One reading is as noisy as the gradient of the smoothed noise (≈ 0.1 grey/px
//! at σ 2, as large as the tilt itself), but vignetting is smooth: under a radial
//! falloff the tilt across a straight line is the same all along it. So each point
//! carries its reading and [`untilt`] moves the points of one line by the line's median
//! tilt. Where the paper on either side is out of the image or darker than the stroke (a
//! crossing, a neighbouring print) the point has no reading.
//!
//! Scale: strokes of 3–15 px need σ from about 1 to 7.5. Each pixel keeps the scale at
//! which its `σ²`-normalised response `σ²·λ` is largest (for a bar of width `w` that is
//! `σ = w/2`, inside Steger's condition), so one detector serves every stroke width and
//! obliquity. The width is measured from the smoothed gradient's extrema on either side.

use super::gray::Gray;
use rigcal_core::geometry::Vec2;

/// One line point.
#[derive(Clone, Copy, Debug)]
pub struct RidgePoint {
    /// Subpixel centre (pixel-centre convention).
    pub pos: Vec2,
    /// Unit normal across the line.
    pub normal: Vec2,
    /// `σ²·λ`: the scale-normalised second derivative across the line (grey levels).
    pub strength: f32,
    pub sigma: f32,
    /// The pixel holding the point.
    pub pixel: (u32, u32),
    /// The paper's relative brightness slope across the line (1/px) as a vector along
    /// the normal (so independent of the normal's sign), where it could be read.
    pub paper_tilt: Option<Vec2>,
    /// How far (px, along the normal) a unit relative tilt across the line moves the
    /// smoothed profile's extremum: `(r(c) + σ²κ) / κ`.
    pub tilt_lever: f64,
}

/// Scales (px) the detector tries: geometric, about √2 apart, for strokes of 2–14 px.
pub const SCALES: [f32; 7] = [1.0, 1.5, 2.2, 3.2, 4.6, 6.6, 9.4];

fn kernels(sigma: f32) -> [Vec<f32>; 3] {
    let r = (3.5 * sigma).ceil() as i32;
    let mut g = Vec::new();
    let mut d1 = Vec::new();
    let mut d2 = Vec::new();
    let s2 = sigma * sigma;
    for i in -r..=r {
        let x = i as f32;
        let e = (-x * x / (2.0 * s2)).exp();
        g.push(e);
        // The fields are correlations (`Σ k[i]·f(x + i)`), so the odd kernel is mirrored.
        d1.push(x / s2 * e);
        d2.push((x * x - s2) / (s2 * s2) * e);
    }
    let sum: f32 = g.iter().sum();
    for v in g.iter_mut().chain(d1.iter_mut()).chain(d2.iter_mut()) {
        *v /= sum;
    }
    [g, d1, d2]
}

/// A kernel of odd length `2r + 1` whose taps mirror about the centre: `k[r + j] =
/// parity·k[r − j]`. Every Gaussian derivative kernel does (even orders symmetric, odd
/// antisymmetric), which halves the multiplications and keeps the inner loops plain
/// slice arithmetic the compiler vectorises.
struct Mirrored<'a> {
    /// `k[r..]`: the centre tap, then the taps on the `+` side.
    half: &'a [f32],
    odd: bool,
}

impl<'a> Mirrored<'a> {
    fn of(k: &'a [f32]) -> Self {
        let r = k.len() / 2;
        let odd = k.len() > 1 && k[r] == 0.0 && k[r + 1] == -k[r - 1];
        debug_assert!((1..=r).all(|j| {
            let m = if odd { -k[r - j] } else { k[r - j] };
            (k[r + j] - m).abs() <= 1e-6 * k[r + j].abs().max(1e-12)
        }));
        Self { half: &k[r..], odd }
    }

    /// `out = k[r]·centre`: the first term of the correlation.
    #[inline(always)]
    fn start(&self, out: &mut [f32], centre: &[f32]) {
        let c = self.half[0];
        for (o, &v) in out.iter_mut().zip(centre) {
            *o = c * v;
        }
    }

    /// `out += k[r + j]·(ahead ± behind)`: the two taps `j` from the centre (`j ≥ 1`).
    #[inline(always)]
    fn add(&self, out: &mut [f32], j: usize, ahead: &[f32], behind: &[f32]) {
        let c = self.half[j];
        if self.odd {
            for ((o, &a), &b) in out.iter_mut().zip(ahead).zip(behind) {
                *o += c * (a - b);
            }
        } else {
            for ((o, &a), &b) in out.iter_mut().zip(ahead).zip(behind) {
                *o += c * (a + b);
            }
        }
    }
}

/// Each row correlated with `k` (`Σ k[i]·f(x + i − r)`), clamped at the border.
#[inline(always)]
fn correlate_rows(src: &[f32], w: usize, k: &[f32]) -> Vec<f32> {
    let r = k.len() / 2;
    let k = Mirrored::of(k);
    let mut out = vec![0f32; src.len()];
    let mut padded = vec![0f32; w + 2 * r];
    for (row, dst) in src.chunks_exact(w).zip(out.chunks_exact_mut(w)) {
        padded[..r].fill(row[0]);
        padded[r..r + w].copy_from_slice(row);
        padded[r + w..].fill(row[w - 1]);
        k.start(dst, &padded[r..][..w]);
        for j in 1..=r {
            k.add(dst, j, &padded[r + j..][..w], &padded[r - j..][..w]);
        }
    }
    out
}

/// Each column correlated with each of `ks` (kernels of one length), clamped at the
/// border. The kernels share one pass, so each pair of source rows is read once for all.
#[inline(always)]
fn correlate_columns<const N: usize>(
    src: &[f32],
    w: usize,
    h: usize,
    ks: [&[f32]; N],
) -> [Vec<f32>; N] {
    let r = ks[0].len() / 2;
    debug_assert!(ks.iter().all(|k| k.len() == 2 * r + 1));
    let ks = ks.map(Mirrored::of);
    let mut outs: [Vec<f32>; N] = std::array::from_fn(|_| vec![0f32; w * h]);
    let row = |y: isize| {
        let y = y.clamp(0, h as isize - 1) as usize;
        &src[y * w..(y + 1) * w]
    };
    for y in 0..h {
        let at = y * w..(y + 1) * w;
        for (k, out) in ks.iter().zip(outs.iter_mut()) {
            k.start(&mut out[at.clone()], row(y as isize));
        }
        for j in 1..=r {
            let (ahead, behind) = (row((y + j) as isize), row(y as isize - j as isize));
            for (k, out) in ks.iter().zip(outs.iter_mut()) {
                k.add(&mut out[at.clone()], j, ahead, behind);
            }
        }
    }
    outs
}

/// The image smoothed at one scale and its first and second derivatives, each a
/// row-major field of the image's size.
struct Smoothed {
    r: Vec<f32>,
    rx: Vec<f32>,
    ry: Vec<f32>,
    rxx: Vec<f32>,
    rxy: Vec<f32>,
    ryy: Vec<f32>,
}

rigcal_core::avx2_or_portable! {
/// Three row passes (value, first, second derivative) and three column passes, one per
/// row pass: each field is its row kernel along `x` times its column kernel along `y`.
fn smoothed(img: &Gray, sigma: f32) -> Smoothed {
    Smoothed::of_portable(img, sigma)
}
}

impl Smoothed {
    #[inline(always)]
    fn of_portable(img: &Gray, sigma: f32) -> Self {
        let (w, h) = (img.width, img.height);
        let [g, d1, d2] = kernels(sigma);
        let row_g = correlate_rows(&img.data, w, &g);
        let row_d1 = correlate_rows(&img.data, w, &d1);
        let row_d2 = correlate_rows(&img.data, w, &d2);
        let [r, ry, ryy] = correlate_columns(&row_g, w, h, [&g, &d1, &d2]);
        let [rx, rxy] = correlate_columns(&row_d1, w, h, [&g, &d1]);
        let [rxx] = correlate_columns(&row_d2, w, h, [&g]);
        Self {
            r,
            rx,
            ry,
            rxx,
            rxy,
            ryy,
        }
    }
}

/// Line points of dark lines at one scale whose strength is at least `min_strength`;
/// `best` (one value per pixel) is raised to each line pixel's strength at this scale,
/// whether or not the pixel holds the centre.
fn points_at(img: &Gray, sigma: f32, min_strength: f32, best: &mut [f32]) -> Vec<RidgePoint> {
    let (w, h) = (img.width, img.height);
    let Smoothed {
        r,
        rx,
        ry,
        rxx,
        rxy,
        ryy,
    } = smoothed(img, sigma);
    let s2 = sigma * sigma;
    let margin = (2.0 * sigma).ceil() as usize + 1;
    let mut out = Vec::new();
    for y in margin..h.saturating_sub(margin) {
        for x in margin..w.saturating_sub(margin) {
            let i = y * w + x;
            let (a, b, c) = (rxx[i], rxy[i], ryy[i]);
            // Largest eigenvalue of [[a, b], [b, c]] and its eigenvector.
            let m = 0.5 * (a + c);
            let d = (0.25 * (a - c) * (a - c) + b * b).sqrt();
            let (l1, l2) = (m + d, m - d);
            if l1 * s2 < min_strength || l1 <= 2.0 * l2.abs() {
                continue; // not a dark line, or a blob / crossing (both curvatures large)
            }
            best[i] = best[i].max(l1 * s2);
            // Eigenvector of l1: (l1 − c, b) or (b, l1 − a), whichever is not ~0.
            let (vx, vy) = if a >= c { (l1 - c, b) } else { (b, l1 - a) };
            let n = (vx * vx + vy * vy).sqrt();
            if n <= 0.0 {
                continue;
            }
            let (nx, ny) = (vx / n, vy / n);
            let curv = a * nx * nx + 2.0 * b * nx * ny + c * ny * ny;
            let t = -(rx[i] * nx + ry[i] * ny) / curv;
            if t.abs() > 1.0 {
                continue;
            }
            // The Taylor step from the pixel centre is only second-order accurate (a
            // centre 0.5 px away comes out 0.04 px off at σ 1.5): Newton steps along `n`
            // on the interpolated derivatives until the first derivative vanishes. The
            // point belongs to the pixel it lands in, so neighbours do not repeat it.
            let (mut px, mut py) = (x as f32 + t * nx, y as f32 + t * ny);
            let mut ok = true;
            let mut kappa = curv;
            for _ in 0..4 {
                let Some(at) = Bilinear::at(w, h, px, py) else {
                    ok = false;
                    break;
                };
                let [gx, gy, a, b, c] = [&rx, &ry, &rxx, &rxy, &ryy].map(|f| at.of(f));
                let curv = a * nx * nx + 2.0 * b * nx * ny + c * ny * ny;
                if curv <= 0.0 {
                    ok = false;
                    break;
                }
                kappa = curv;
                let step = -(gx * nx + gy * ny) / curv;
                px += step * nx;
                py += step * ny;
                if step.abs() < 1e-4 {
                    break;
                }
            }
            if ok && (px.round() as usize, py.round() as usize) == (x, y) {
                let normal = Vec2::new(nx as f64, ny as f64);
                let fields = [&rx[..], &ry[..], &r[..]];
                let tilt = paper_tilt(&fields, w, (px, py), (nx, ny), sigma, kappa);
                let paper_tilt = tilt.map(|beta| normal * beta as f64);
                let tilt_lever = bilinear(&r, w, px, py)
                    .map_or(0.0, |c| ((c + sigma * sigma * kappa) / kappa) as f64);
                out.push(RidgePoint {
                    pos: Vec2::new(px as f64, py as f64),
                    normal,
                    strength: l1 * s2,
                    sigma,
                    pixel: (x as u32, y as u32),
                    paper_tilt,
                    tilt_lever,
                });
            }
        }
    }
    out
}

/// The paper's relative slope `β` across the line at `p` (along the normal `n`, with
/// `κ` the curvature there), read 4σ beyond the stroke's edges on either side (see the
/// module note). `None` where the paper is not there to read (out of the image, not
/// brighter than the stroke, or sloped more steeply than vignetting slopes anything).
fn paper_tilt(
    [rx, ry, r]: &[&[f32]; 3],
    w: usize,
    (px, py): (f32, f32),
    (nx, ny): (f32, f32),
    sigma: f32,
    curvature: f32,
) -> Option<f32> {
    let h = r.len() / w.max(1);
    let at = |f: &[f32], t: f32| bilinear(f, w, px + t * nx, py + t * ny);
    let slope_at = |t: f32| {
        let at = Bilinear::at(w, h, px + t * nx, py + t * ny)?;
        Some(at.of(rx) * nx + at.of(ry) * ny)
    };
    // The stroke's edges: the smoothed gradient's extremum on either side (the stroke
    // may be wider than the scale that found it), then the paper 4σ beyond the farther.
    let mut edge = 0.0f32;
    for side in [-1.0f32, 1.0] {
        let (mut best, mut at) = (0.0f32, 0.0f32);
        let mut t = 0.5;
        while t <= 12.0 * sigma {
            let g = slope_at(side * t)?.abs();
            if g > best {
                (best, at) = (g, t);
            } else if g < 0.5 * best {
                break;
            }
            t += 0.5;
        }
        edge = edge.max(at);
    }
    let d = edge + 4.0 * sigma;
    let mut slope = 0.0;
    let mut levels = [0.0f32; 2];
    for (k, side) in [-1.0f32, 1.0].into_iter().enumerate() {
        let (g, level) = (slope_at(side * d)?, at(r, side * d)?);
        if level <= 0.0 {
            return None;
        }
        slope += g;
        levels[k] = level;
    }
    let paper = levels[0] + levels[1];
    let centre = at(r, 0.0)?;
    let m2 = centre + sigma * sigma * curvature;
    if (levels[0] - levels[1]).abs() > 0.1 * paper
        || paper <= 2.0 * centre
        || !(0.0..=paper).contains(&m2)
    {
        return None;
    }
    // Each side alone also carries what is left of the stroke's own slope 4σ out (it
    // cancels in the sum); only the sum is the paper's.
    let tilt = slope / paper;
    (tilt.abs() <= MAX_RELATIVE_TILT).then_some(tilt)
}

/// Readings a line needs before its median tilt is trusted.
const MIN_TILT_READINGS: usize = 8;

/// Move the points of one straight printed line by the line's median paper tilt (see
/// the module note); the tilt applied, or `None` (points unchanged) where too few points
/// could read the paper.
pub fn untilt(points: &mut [RidgePoint]) -> Option<Vec2> {
    let readings: Vec<Vec2> = points.iter().filter_map(|p| p.paper_tilt).collect();
    if readings.len() < MIN_TILT_READINGS.max(points.len() / 4) {
        return None;
    }
    let median = |f: fn(&Vec2) -> f64| {
        let mut v: Vec<f64> = readings.iter().map(f).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let tilt = Vec2::new(median(|v| v.x), median(|v| v.y));
    for p in points.iter_mut() {
        if p.tilt_lever.is_finite() && p.tilt_lever > 0.0 {
            p.pos += p.normal * (tilt.dot(&p.normal) * p.tilt_lever);
        }
    }
    Some(tilt)
}

/// The steepest relative slope (1/px) read as vignetting: 25 % at the corners of a
/// 1024×768 image tilts paper by 0.0007/px; four times that, for stronger lenses.
const MAX_RELATIVE_TILT: f32 = 0.003;

/// Bilinear interpolation of a row-major field; `None` outside it.
fn bilinear(f: &[f32], w: usize, x: f32, y: f32) -> Option<f32> {
    Some(Bilinear::at(w, f.len() / w.max(1), x, y)?.of(f))
}

/// Where and with which weights to interpolate fields of one size at one position, so
/// several fields are read at a point for the price of one lookup.
struct Bilinear {
    /// Index of the top-left sample.
    i: usize,
    w: usize,
    fx: f32,
    fy: f32,
}

impl Bilinear {
    /// `None` outside a `w × h` field.
    #[inline]
    fn at(w: usize, h: usize, x: f32, y: f32) -> Option<Self> {
        if !(x >= 0.0 && y >= 0.0) || x >= (w - 1) as f32 || y >= (h - 1) as f32 {
            return None;
        }
        let (x0, y0) = (x as usize, y as usize); // non-negative: truncation is floor
        Some(Self {
            i: y0 * w + x0,
            w,
            fx: x - x0 as f32,
            fy: y - y0 as f32,
        })
    }

    #[inline]
    fn of(&self, f: &[f32]) -> f32 {
        let (i, w, fx, fy) = (self.i, self.w, self.fx, self.fy);
        let top = f[i] * (1.0 - fx) + f[i + 1] * fx;
        let bottom = f[i + w] * (1.0 - fx) + f[i + w + 1] * fx;
        top * (1.0 - fy) + bottom * fy
    }
}

/// Line points of every dark line at least `min_strength` strong (σ²-normalised second
/// derivative, grey levels), each pixel at its best scale among `scales`.
pub fn ridge_points(img: &Gray, scales: &[f32], min_strength: f32) -> Vec<RidgePoint> {
    let (w, h) = (img.width, img.height);
    if w < 3 || h < 3 || img.data.len() != w * h {
        return Vec::new(); // nothing to differentiate (and no border to keep)
    }
    // The strongest point of each pixel over the scales: `found` holds the points,
    // `at` each pixel's index into it (a pixel map of indices, not of points, because
    // only a few per cent of the pixels hold one).
    const NONE: u32 = u32::MAX;
    let mut at = vec![NONE; w * h];
    let mut found: Vec<RidgePoint> = Vec::new();
    let mut best = vec![0.0f32; w * h];
    for &s in scales {
        for p in points_at(img, s, min_strength, &mut best) {
            let i = p.pixel.1 as usize * w + p.pixel.0 as usize;
            match at[i] {
                NONE => {
                    at[i] = found.len() as u32;
                    found.push(p);
                }
                k if p.strength > found[k as usize].strength => found[k as usize] = p,
                _ => {}
            }
        }
    }
    // Across the line only its centre survives: a point with a stronger point (of any
    // scale, a parallel normal) within its own reach along the normal sits on the flank
    // of a wider stroke (at small σ a wide bar's flat inside curves near each edge).
    let flank = |p: &RidgePoint| {
        let reach = (2.0 * p.sigma).ceil() as i64 + 1;
        let (x, y) = (p.pixel.0 as i64, p.pixel.1 as i64);
        (-reach..=reach).filter(|&k| k != 0).any(|k| {
            let qx = x + (p.normal.x * k as f64).round() as i64;
            let qy = y + (p.normal.y * k as f64).round() as i64;
            if qx < 0 || qy < 0 || qx >= w as i64 || qy >= h as i64 {
                return false;
            }
            let q = at[qy as usize * w + qx as usize];
            q != NONE && {
                let q = &found[q as usize];
                q.strength > p.strength && q.normal.dot(&p.normal).abs() > 0.9
            }
        })
    };
    // A pixel's point must come from (near) its best scale. Where the line's own scale
    // puts the centre in a neighbouring pixel, a much coarser scale can still put a
    // centre in this one, pulled off the line by everything else within its reach (a
    // 3 px stroke at 45° kept points at σ 9.4, 0.3-0.7 px off its centre). At a true
    // centre the strongest scale always holds a point (the centre of a bar is unbiased
    // at every σ that responds most), so only such strays are lost.
    let stray = |p: &RidgePoint| {
        best[p.pixel.1 as usize * w + p.pixel.0 as usize] > STRAY_RESPONSE_RATIO * p.strength
    };
    let keep: Vec<bool> = found.iter().map(|p| !flank(p) && !stray(p)).collect();
    let mut out: Vec<RidgePoint> = found
        .into_iter()
        .zip(keep)
        .filter_map(|(p, k)| k.then_some(p))
        .collect();
    // In pixel order (row-major), whichever scale found each: the linking numbers its
    // chains by their first point.
    out.sort_unstable_by_key(|p| (p.pixel.1, p.pixel.0));
    for p in &mut out {
        settle(img, p);
    }
    out
}

/// A point whose pixel responds this many times more strongly at another scale is a
/// stray of that scale (see [`ridge_points`]).
const STRAY_RESPONSE_RATIO: f32 = 1.5;

/// Below this scale the centre found on bilinearly interpolated derivatives is off by
/// more than the sampled kernels' own error (see [`settle`]).
const SETTLE_BELOW_SIGMA: f32 = 5.0;

/// Move a point to where the Gaussian derivatives evaluated *at* its subpixel position
/// (kernels sampled at the offsets of the pixels from it) make the slope across the line
/// vanish. Interpolating derivatives sampled at pixel centres bends the slope's zero by
/// up to `0.1·|r''''/(6κ)|` px, a periodic error in where the centre falls within its
/// pixel (0.012 / 0.007 px at strokes 3 / 4 px blurred by 0.8 px; evaluated in place,
/// under 0.0001 px, and 0.0012 px under a 0.5 px blur, which the sampled kernels alias);
/// on a line nearly parallel to the pixel rows the phase changes slowly, so it does not
/// average out along the line. Above [`SETTLE_BELOW_SIGMA`] the interpolation is as
/// good (0.0006 px at σ 6.6), and a window of 10σ square costlier to replace it.
fn settle(img: &Gray, p: &mut RidgePoint) {
    if p.sigma >= SETTLE_BELOW_SIGMA {
        return;
    }
    let n = p.normal;
    let mut pos = p.pos;
    for _ in 0..3 {
        let Some(d) = derivatives_at(img, p.sigma as f64, pos) else {
            return;
        };
        let slope = d.rx * n.x + d.ry * n.y;
        let curv = d.rxx * n.x * n.x + 2.0 * d.rxy * n.x * n.y + d.ryy * n.y * n.y;
        if curv <= 0.0 {
            return;
        }
        let step = -slope / curv;
        if step.abs() > 0.5 {
            return; // not the extremum this point was found at; keep it as found
        }
        pos += n * step;
        if step.abs() < 1e-5 {
            break;
        }
    }
    p.pos = pos;
}

/// Gaussian-smoothed first and second derivatives at a subpixel position.
struct Derivatives {
    rx: f64,
    ry: f64,
    rxx: f64,
    rxy: f64,
    ryy: f64,
}

/// The derivatives of the image smoothed at `sigma`, evaluated at `at` with kernels
/// sampled at each pixel's offset from it (out to 5σ, where the truncated tail moves a
/// centre by under 0.001 px); `None` where the window leaves the image.
fn derivatives_at(img: &Gray, sigma: f64, at: Vec2) -> Option<Derivatives> {
    let r = (5.0 * sigma).ceil() as i64;
    let (cx, cy) = (at.x.round() as i64, at.y.round() as i64);
    if !(at.x.is_finite() && at.y.is_finite())
        || cx - r < 0
        || cy - r < 0
        || cx + r >= img.width as i64
        || cy + r >= img.height as i64
    {
        return None;
    }
    let s2 = sigma * sigma;
    // Kernels at the offsets of the window's columns and rows: value, first, second
    // derivative of the unit-area Gaussian (the derivative kernels correlate, as in
    // `kernels`).
    let taps = |centre: i64, x: f64| -> Vec<[f64; 3]> {
        (centre - r..=centre + r)
            .map(|i| {
                let u = i as f64 - x;
                let e = (-u * u / (2.0 * s2)).exp() / (std::f64::consts::TAU.sqrt() * sigma);
                [e, u / s2 * e, (u * u - s2) / (s2 * s2) * e]
            })
            .collect()
    };
    let kx = taps(cx, at.x);
    let ky = taps(cy, at.y);
    let (mut rx, mut ry, mut rxx, mut rxy, mut ryy) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (j, ky) in (cy - r..=cy + r).zip(&ky) {
        let row = &img.data[j as usize * img.width..][..img.width];
        let (mut g, mut d1, mut d2) = (0.0, 0.0, 0.0);
        for (i, k) in (cx - r..=cx + r).zip(&kx) {
            let v = row[i as usize] as f64;
            g += k[0] * v;
            d1 += k[1] * v;
            d2 += k[2] * v;
        }
        rx += ky[0] * d1;
        ry += ky[1] * g;
        rxx += ky[0] * d2;
        rxy += ky[1] * d1;
        ryy += ky[2] * g;
    }
    Some(Derivatives {
        rx,
        ry,
        rxx,
        rxy,
        ryy,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `erf` to 1.2·10⁻⁷ (Numerical Recipes' Chebyshev fit of `erfc`).
    fn erf(x: f64) -> f64 {
        let t = 1.0 / (1.0 + 0.5 * x.abs());
        let poly = [
            -1.26551223,
            1.00002368,
            0.37409196,
            0.09678418,
            -0.18628806,
            0.27886807,
            -1.13520398,
            1.48851587,
            -0.82215223,
            0.17087277,
        ];
        let p = poly.iter().rev().fold(0.0, |acc, c| c + t * acc);
        let y = 1.0 - t * (-x * x + p).exp();
        y.copysign(x)
    }

    /// A vertical dark bar of width `width` centred at `x0`, blurred by a Gaussian of
    /// 0.5 px (the least a real lens and sensor blur) and integrated over each pixel.
    fn bar(x0: f64, width: f64) -> Gray {
        const BLUR: f64 = 0.5;
        // The integral of the blurred step `Φ((u − e)/BLUR)` over `u`.
        let ramp = |u: f64, e: f64| {
            let t = (u - e) / BLUR;
            let cdf = 0.5 * (1.0 + erf(t / std::f64::consts::SQRT_2));
            let pdf = (-0.5 * t * t).exp() / std::f64::consts::TAU.sqrt();
            BLUR * (t * cdf + pdf)
        };
        let (w, h) = (160usize, 64usize);
        let (e0, e1) = (x0 - width / 2.0, x0 + width / 2.0);
        let row: Vec<f32> = (0..w)
            .map(|x| {
                let (a, b) = (x as f64 - 0.5, x as f64 + 0.5);
                let cover = (ramp(b, e0) - ramp(a, e0)) - (ramp(b, e1) - ramp(a, e1));
                (220.0 - 190.0 * cover) as f32
            })
            .collect();
        Gray {
            width: w,
            height: h,
            data: (0..h).flat_map(|_| row.iter().copied()).collect(),
        }
    }

    /// `bar` under a brightness rising across it, `1 + beta·(x − x0)`, as vignetting
    /// tilts a print.
    fn tilted_bar(x0: f64, width: f64, beta: f64) -> Gray {
        let mut g = bar(x0, width);
        for (k, v) in g.data.iter_mut().enumerate() {
            let x = (k % g.width) as f64;
            *v = (*v as f64 * (1.0 + beta * (x - x0))) as f32;
        }
        g
    }

    /// The bar's centre on `row`, after the bar's points are untilted as one line.
    fn centre_on_row(img: &Gray, row: u32) -> Option<RidgePoint> {
        let mut bar: Vec<RidgePoint> = ridge_points(img, &SCALES, 5.0)
            .into_iter()
            .filter(|p| p.normal.x.abs() > 0.99)
            .collect();
        untilt(&mut bar);
        bar.into_iter()
            .filter(|p| p.pixel.1 == row)
            .max_by(|a, b| a.strength.total_cmp(&b.strength))
    }

    #[test]
    fn the_smoothed_fields_are_the_direct_correlations_with_the_sampled_kernels() {
        // The separable, mirrored passes against the plain double sum (clamped at the
        // border), on a textured image, at a small and the largest scale.
        let (w, h) = (57usize, 43usize);
        let img = Gray {
            width: w,
            height: h,
            data: (0..w * h)
                .map(|i| {
                    let (x, y) = ((i % w) as f32, (i / w) as f32);
                    100.0 + 60.0 * (0.37 * x + 0.11 * y * y).sin() + 0.5 * x - 0.8 * y
                })
                .collect(),
        };
        for sigma in [1.0, SCALES[SCALES.len() - 1]] {
            let [g, d1, d2] = kernels(sigma);
            let direct = |kx: &[f32], ky: &[f32], x: usize, y: usize| {
                let r = (kx.len() / 2) as isize;
                let mut acc = 0.0f64;
                for (j, cy) in ky.iter().enumerate() {
                    for (i, cx) in kx.iter().enumerate() {
                        let xx = (x as isize + i as isize - r).clamp(0, w as isize - 1);
                        let yy = (y as isize + j as isize - r).clamp(0, h as isize - 1);
                        acc += (cx * cy) as f64 * img.data[yy as usize * w + xx as usize] as f64;
                    }
                }
                acc
            };
            let s = smoothed(&img, sigma);
            let fields: [(&[f32], &[f32], &Vec<f32>); 6] = [
                (&g, &g, &s.r),
                (&d1, &g, &s.rx),
                (&g, &d1, &s.ry),
                (&d2, &g, &s.rxx),
                (&d1, &d1, &s.rxy),
                (&g, &d2, &s.ryy),
            ];
            for (k, (kx, ky, field)) in fields.into_iter().enumerate() {
                for (x, y) in [(0, 0), (3, 7), (28, 21), (56, 42), (40, 2)] {
                    let (want, got) = (direct(kx, ky, x, y), field[y * w + x] as f64);
                    assert!(
                        (want - got).abs() <= 1e-4 * want.abs().max(1.0),
                        "σ {sigma}, field {k} at ({x}, {y}): {got} against {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn vignetting_across_a_bar_does_not_move_its_centre() {
        // 0.16 grey/px on 220 grey of paper, what 25 % corner vignetting puts there at
        // 1024×768, and twice that the other way: uncorrected, the centres moved by
        // 0.004-0.12 px and 0.007-0.24 px (3-30 px strokes); corrected, what is left is
        // the linear step's (the shift is taken as `tilt/κ`, a few per cent short where it
        // is a sizeable fraction of σ) and the tilt reading's (0.3 %): at most 0.0019 px.
        // Measured against the same bar untilted, so the sampling-phase error (up to
        // 0.006 px) is not counted.
        let x0 = 80.3;
        for width in [3.0, 6.0, 10.0, 15.0, 22.0, 30.0] {
            let flat = centre_on_row(&tilted_bar(x0, width, 0.0), 32).expect("a point");
            for beta in [0.16 / 220.0, -0.32 / 220.0] {
                let p = centre_on_row(&tilted_bar(x0, width, beta), 32).expect("a point");
                assert!(
                    (p.pos.x - flat.pos.x).abs() < 0.0025,
                    "width {width}, β {beta}: {} against {} untilted (σ {})",
                    p.pos.x,
                    flat.pos.x,
                    p.sigma
                );
            }
        }
    }

    #[test]
    fn the_centre_of_a_bar_is_found_to_a_thousandth_of_a_pixel_wherever_it_falls() {
        // Every fifth of a pixel across one pixel: before the centres were settled on
        // derivatives evaluated in place, the interpolation put 2-4 px strokes up to
        // 0.03 px off, periodically in the phase. What is left is the sampled kernels'
        // aliasing of the 0.5 px blur (0.0019 px at 2 px, under 0.0012 px above).
        for width in [2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 15.0] {
            for k in 0..10 {
                let x0 = 30.0 + k as f64 / 10.0;
                let pts = ridge_points(&bar(x0, width), &SCALES, 5.0);
                let best = pts
                    .iter()
                    .filter(|p| p.pixel.1 == 32)
                    .max_by(|a, b| a.strength.total_cmp(&b.strength))
                    .unwrap_or_else(|| panic!("width {width} at {x0}: no point"));
                let tolerance = if width < 3.0 { 0.0025 } else { 0.0015 };
                assert!(
                    (best.pos.x - x0).abs() < tolerance,
                    "width {width} at {x0}: {} (σ {})",
                    best.pos.x,
                    best.sigma
                );
                assert!(best.normal.x.abs() > 0.999);
            }
        }
    }

    /// Two dark bars `width` px wide crossing at right angles near the image centre,
    /// the first at `angle` (radians, from the x axis), blurred by 0.5 px and averaged
    /// over 8×8 samples per pixel: the first bar's centre and normal.
    fn crossing_bars(width: f64, angle: f64) -> (Gray, Vec2, Vec2) {
        let (w, h) = (128usize, 128usize);
        let centre = Vec2::new(63.3, 64.1);
        let normal = Vec2::new(-angle.sin(), angle.cos());
        let along = Vec2::new(angle.cos(), angle.sin());
        let blur = |d: f64| 0.5 * (1.0 + erf(d / (0.5 * std::f64::consts::SQRT_2)));
        let band = |d: f64| blur(d + width / 2.0) - blur(d - width / 2.0);
        let data = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                let mut ink = 0.0;
                for sy in 0..8 {
                    for sx in 0..8 {
                        let q =
                            Vec2::new(x - 0.4375 + sx as f64 / 8.0, y - 0.4375 + sy as f64 / 8.0);
                        let (a, b) = (
                            band((q - centre).dot(&normal)),
                            band((q - centre).dot(&along)),
                        );
                        ink += a + b - a * b;
                    }
                }
                (220.0 - 190.0 * ink / 64.0) as f32
            })
            .collect();
        (
            Gray {
                width: w,
                height: h,
                data,
            },
            centre,
            normal,
        )
    }

    #[test]
    fn thin_oblique_bars_are_centred_to_two_hundredths_of_a_pixel_beside_a_crossing() {
        // Pixel staircases at 30-60° with the other bar's ink in reach of every scale.
        // (The strays of coarse scales that [`STRAY_RESPONSE_RATIO`] removes need more
        // around them than two bars, a whole grid on its sheet: `tests/linegrid.rs`,
        // `grids_turned_about_every_axis_and_in_their_plane_are_found`.)
        for (width, deg) in [(3.0, 45.0), (3.0, 30.0), (2.5, 60.0), (4.0, 45.0)] {
            let (img, centre, normal) = crossing_bars(width, f64::to_radians(deg));
            // The first bar's points, beyond the crossing's own reach (4σ of each bar).
            let pts: Vec<RidgePoint> = ridge_points(&img, &SCALES, 5.0)
                .into_iter()
                .filter(|p| p.normal.dot(&normal).abs() > 0.9)
                .filter(|p| (p.pos - centre).dot(&normal).abs() < 3.0)
                .filter(|p| (4.0 * width..50.0).contains(&(p.pos - centre).norm()))
                .collect();
            assert!(pts.len() > 40, "{width} px at {deg}°: {} points", pts.len());
            let worst = pts
                .iter()
                .map(|p| (p.pos - centre).dot(&normal).abs())
                .fold(0.0, f64::max);
            assert!(
                worst < 0.02,
                "{width} px at {deg}°: a point {worst:.3} px off"
            );
        }
    }
}
