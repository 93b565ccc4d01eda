//! Subpixel corners from the tag's outer edges: the quad fit of the detector is only a
//! starting point.
//!
//! Each side of the black square is sampled across (profiles normal to the side, one
//! per pixel of its length, about a cell clear of the corners where AprilGrid crossing
//! squares touch it). On each profile the edge is where the grey level crosses the mean of the levels
//! at `±d` around it — for a symmetric blur that is exactly the edge, whatever the
//! contrast and shading. The edge points of a side are moved to undistorted normalised
//! coordinates (with the camera, so sides are straight lines even under strong
//! distortion), fitted by total least squares with outliers trimmed, and the corners
//! are the intersections of adjacent sides, projected back to raw pixels. Two passes,
//! the second sampling along the first's sides.

use super::gray::Gray;
use rigcal_core::geometry::line2::{distance, fit_line, intersect};
use rigcal_core::geometry::{normal_cdf_pdf, Camera, Vec2, Vec3};
use rigcal_solve::lm::{minimize, Damping, Dense, LeastSquares, Rules};
use rigcal_solve::loss::median;

/// Maps between raw pixels and the plane where a tag's sides are straight.
#[derive(Clone, Copy)]
pub struct Lens<'a>(pub Option<&'a Camera>);

impl Lens<'_> {
    pub fn to_plane(&self, px: Vec2) -> Option<Vec2> {
        match self.0 {
            Some(c) => c.unproject(&px),
            None => Some(px),
        }
    }

    /// [`to_plane`](Self::to_plane) of a pixel near one whose plane point `near` is
    /// known (a few pixels off): fewer iterations of the lens's inverse.
    pub fn to_plane_near(&self, px: Vec2, near: Vec2) -> Option<Vec2> {
        match self.0 {
            Some(c) => c.unproject_near(&px, near),
            None => Some(px),
        }
    }

    /// A quad's corners in the plane.
    pub fn quad_to_plane(&self, c: &[Vec2; 4]) -> Option<[Vec2; 4]> {
        Some([
            self.to_plane(c[0])?,
            self.to_plane(c[1])?,
            self.to_plane(c[2])?,
            self.to_plane(c[3])?,
        ])
    }

    pub fn to_pixel(&self, q: Vec2) -> Option<Vec2> {
        match self.0 {
            Some(c) => c.project(&Vec3::new(q.x, q.y, 1.0)),
            None => Some(q),
        }
    }

    /// The pixel of plane point `q` and the unit direction, in raw pixels, of the plane
    /// direction `dir` there (one projection: its Jacobian carries the direction).
    pub fn to_pixel_along(&self, q: Vec2, dir: Vec2) -> Option<(Vec2, Vec2)> {
        let (p, along) = match self.0 {
            Some(c) => {
                let (p, j) = c.project_with_jacobian(&Vec3::new(q.x, q.y, 1.0))?;
                (p, j.fixed_columns::<2>(0) * dir)
            }
            None => (q, dir),
        };
        let norm = along.norm();
        (norm > 0.0 && norm.is_finite()).then(|| (p, along / norm))
    }
}

/// A refined quad and how well its sides fit.
#[derive(Clone, Debug)]
pub struct Refined {
    pub corners: [Vec2; 4],
    /// RMS distance (px) of the edge points from their fitted sides.
    pub edge_rms: f64,
    /// Mean grey-level step across the sides (white − black).
    pub contrast: f64,
    /// The edges' blur ([`RefinedPolygon::blur`]).
    pub blur: Option<f64>,
}

/// Where along the profile `s ↦ I(p + s·n)` (dark at `s < 0`, bright at `s > 0`) the
/// edge crosses, searched within `±reach` of 0, with symmetric levels at `±d`; to within
/// `tol` px (the crossing is the measurement itself only where the pixel-model fit
/// cannot run; elsewhere it is a start and a coarse `tol` saves most of the samples).
fn edge_offset(img: &Gray, p: Vec2, n: Vec2, reach: f64, d: f64, tol: f64) -> Option<(f64, f64)> {
    let at = |s: f64| img.sample(p + n * s);
    // Coarse: the steepest dark→bright step, from one sampling of the profile every
    // STEP px (the step at s is I(s + ½) − I(s − ½), `2·half` samples apart). The
    // samples stay on the stack for the usual reaches. Every ½ px: the steepest step
    // only has to land in the bisection's bracket, and at ¼ px (twice the samples) the
    // corners of hall and fisheye captures came out the same to four digits of their
    // RMS, 5 % slower.
    const STEP: f64 = 0.5;
    let half = (0.5 / STEP).round() as usize;
    let k = (reach / STEP).ceil() as i32;
    let count = 2 * k as usize + 1 + 2 * half;
    let mut stack = [0.0; 64];
    let mut heap = Vec::new();
    let levels: &mut [f64] = if count <= stack.len() {
        &mut stack[..count]
    } else {
        heap.resize(count, 0.0);
        &mut heap
    };
    // Sample `i` is at s = (i − k − half)·STEP.
    let s_of = |i: usize| (i as f64 - k as f64 - half as f64) * STEP;
    for (i, l) in levels.iter_mut().enumerate() {
        *l = at(s_of(i))?;
    }
    let levels = &*levels;
    let mut best = (f64::NEG_INFINITY, 0.0);
    for i in 0..=(2 * k) as usize {
        let g = levels[i + 2 * half] - levels[i];
        if g > best.0 {
            best = (g, (i as i32 - k) as f64 * STEP);
        }
    }
    if best.0 <= 0.0 {
        return None;
    }
    // The sample at or below `s`, where sampled.
    let index_of = |s: f64| -> Option<usize> {
        let i = (s / STEP).floor() as i64 + k as i64 + half as i64;
        usize::try_from(i).ok().filter(|&i| i < levels.len())
    };
    let mut e = best.1;
    let mut contrast = 0.0;
    for _ in 0..3 {
        let (dark, bright) = (at(e - d)?, at(e + d)?);
        contrast = bright - dark;
        if contrast <= 0.0 {
            return None;
        }
        let mid = 0.5 * (dark + bright);
        // Bisection of I(s) = mid on [e − d, e + d] (monotone across a clean edge). The
        // bracket is first narrowed on the samples already taken: the bisection's own
        // first steps would read the same profile at about that spacing.
        let (mut lo, mut hi) = (e - d, e + d);
        if let (Some(i0), Some(i1)) = (index_of(lo), index_of(hi)) {
            // The samples strictly inside (lo, hi), in order: the last one below `mid`
            // before the first one at or above it.
            let (a, b) = (lo, hi);
            for i in i0..=i1 {
                let (s, v) = (s_of(i), levels[i]);
                if s <= a || s >= b {
                    continue;
                }
                if v < mid {
                    lo = s;
                } else {
                    hi = s;
                    break;
                }
            }
        }
        while hi - lo > tol {
            let m = 0.5 * (lo + hi);
            if at(m)? < mid {
                lo = m;
            } else {
                hi = m;
            }
        }
        let next = 0.5 * (lo + hi);
        let moved = (next - e).abs();
        e = next;
        if e.abs() > reach + d || moved < tol {
            break;
        }
    }
    (e.abs() <= reach + d).then_some((e, contrast))
}

/// How far (px) from the image's origin a point may lie and still be measured
/// geometry: far beyond any image, and far within the integers that pixel coordinates
/// become (sample counts, region bounds).
const FAR_PX: f64 = 1e7;

/// Whether `p` is not finite or beyond [`FAR_PX`]: a degenerate homography's point,
/// refused while it is a float, before it sizes or indexes anything.
pub(crate) fn far_out(p: Vec2) -> bool {
    !(p.x.abs() < FAR_PX && p.y.abs() < FAR_PX)
}

/// Crossing tolerance (px) where it is the measurement, and where it only starts the
/// pixel-model fit or the coarse pass.
const CROSSING_TOL: f64 = 1e-3;
const START_TOL: f64 = 0.03;

/// Smallest half-width (px) of the pixel-model edge fit: from ±2.5 px its bias on a
/// blurred step is under 0.005 px for optics σ 0.4-1.6 px; at ±1.85 px it reaches
/// 0.06 px for σ 0.5 (1-D study of the fit on exact pixel samples).
const MIN_FIT_WINDOW: f64 = 2.5;

/// Half-width (px) of the band of pixels along a profile that its edge fit reads. With
/// one profile per pixel of side, neighbouring edge points share pixels (and noise):
/// only points `2·FIT_BAND + 1` profiles apart are independent.
pub const FIT_BAND: f64 = 1.0;

/// Where a blurred-step fit starts besides its edge position: levels from the
/// interpolated crossing's contrast and the blur of a typical lens, or the step fitted on
/// the profile before on the same side (its levels and blur change little from one
/// profile to the next, and starting there saves iterations).
#[derive(Clone, Copy, Debug)]
enum Start {
    Contrast(f64),
    Neighbour(nalgebra::Vector4<f64>),
}

/// The pixels an edge fit reads: within `along` px of the edge along the profile and
/// `across` px either side of it.
#[derive(Clone, Copy, Debug)]
struct Window {
    along: f64,
    across: f64,
}

/// The blur σ (px: the optics and the pixel's own area) of the edge that crosses the
/// profile through `p` along `n` (dark at `s < 0`) within `reach`, with its levels read
/// `d` either side: [`fit_edge`]'s σ, which, fitted to pixel centres, does not depend on
/// where the edge falls between them (a steepest interpolated rise read 0.40-0.58 px on
/// the four sides of one tag).
pub fn edge_sigma(img: &Gray, p: Vec2, n: Vec2, reach: f64, d: f64) -> Option<f64> {
    let (e, contrast) = edge_offset(img, p, n, reach, d, START_TOL)?;
    let window = Window {
        along: (d + 0.5).max(MIN_FIT_WINDOW),
        across: FIT_BAND,
    };
    fit_edge(img, p, n, e, window, Start::Contrast(contrast)).map(|x| x[3])
}

/// The edge on a profile from the pixels around it, not from interpolated samples.
///
/// Why: the mid-level crossing of a bilinearly interpolated blurred step is off by up to
/// 0.02 px (optics σ 0.8 px), depending on where the edge falls between pixel centres. A
/// blurred step is not band-limited at the pixel pitch, so no interpolator removes this
/// (Keys' cubic does no better). Along a side nearly parallel to a pixel row or column
/// the phase changes slowly, so the error does not average out over the side: it bends
/// the points and tilts the fitted line (seen: ±0.02 px swings along a side 1° off
/// vertical in the ring's auxiliary image 7, ±0.006 px with this fit). Model: a pixel
/// centre at signed distance `s` along the profile has grey level `a + b·Φ((s − e)/σ)`
/// (a step blurred by the optics and the pixel's own area, close to Gaussian), the same at
/// every offset along the edge; `a, b, e, σ` by Gauss-Newton from the pixels of `window`
/// round `e0` on the profile, returned as `(a, b, e, σ)`. `None` when the fit does not
/// settle (the caller keeps `e0`).
fn fit_edge(
    img: &Gray,
    p: Vec2,
    n: Vec2,
    e0: f64,
    window: Window,
    start: Start,
) -> Option<nalgebra::Vector4<f64>> {
    let t = Vec2::new(-n.y, n.x);
    let centre = p + n * e0;
    let r = window.along.max(window.across) + 1.5;
    let (x0, x1) = ((centre.x - r).floor().max(0.0), (centre.x + r).ceil());
    let (y0, y1) = ((centre.y - r).floor().max(0.0), (centre.y + r).ceil());
    if x1 >= img.width as f64 || y1 >= img.height as f64 {
        return None;
    }
    // The pixels and the fit's scratch stay on the stack for the usual windows (a few
    // dozen pixels): this runs for every edge point of every tag.
    let mut stack = [(0.0, 0.0); STACK_SAMPLES];
    let mut heap = Vec::new();
    let mut len = 0;
    for y in y0 as usize..=y1 as usize {
        for x in x0 as usize..=x1 as usize {
            let c = Vec2::new(x as f64, y as f64) - p;
            let s = n.dot(&c);
            if t.dot(&c).abs() <= window.across && (s - e0).abs() <= window.along {
                let sample = (s, img.data[y * img.width + x] as f64);
                if len < STACK_SAMPLES {
                    stack[len] = sample;
                } else {
                    if heap.is_empty() {
                        heap.extend_from_slice(&stack);
                    }
                    heap.push(sample);
                }
                len += 1;
            }
        }
    }
    let samples: &[(f64, f64)] = if heap.is_empty() {
        &stack[..len]
    } else {
        &heap
    };
    if samples.len() < 8 {
        return None;
    }
    let init = match start {
        Start::Contrast(contrast) => {
            let mean = samples.iter().map(|s| s.1).sum::<f64>() / samples.len() as f64;
            nalgebra::Vector4::new(mean - 0.5 * contrast, contrast, e0, 0.9)
        }
        Start::Neighbour(x) => nalgebra::Vector4::new(x[0], x[1], e0, x[3]),
    };
    let mut phi_stack = [(0.0, 0.0); STACK_SAMPLES];
    let mut phi_heap = Vec::new();
    let phi: &mut [(f64, f64)] = if samples.len() <= STACK_SAMPLES {
        &mut phi_stack[..samples.len()]
    } else {
        phi_heap.resize(samples.len(), (0.0, 0.0));
        &mut phi_heap
    };
    let mut profile = StepProfile {
        samples,
        phi,
        phi_for: None,
    };
    let fit = minimize(&mut profile, init, &STEP_FIT)?;
    let x = fit.point;
    ((x[2] - e0).abs() < 1.0 && x[1] > 0.0).then_some(x)
}

/// The damping and stopping of the blurred-step fit: a few iterations suffice from the
/// interpolated crossing; it ends when the edge position settles ([`StepProfile`]).
const STEP_FIT: Rules = Rules {
    max_iterations: 40,
    damping: Damping::Marquardt {
        raise: 10.0,
        lower: 0.3,
        min_lambda: 1e-9,
    },
    initial_lambda: 1e-3,
    diagonal_floor: 0.0,
    tries: 8,
    max_lambda: f64::INFINITY,
    function_tolerance: 0.0,
    min_step: 0.0,
    gradient_tolerance: 0.0,
    creep_tolerance: 0.0,
};

/// The edge step (px) below which a blurred-step fit has settled. What is left is the
/// next step, quadratically smaller and far below a point's own noise (~0.03 px): the
/// corners of a dense 1080p hall were the same to four digits of their RMS as at
/// 10⁻⁵ px, for 3.9 iterations per fit instead of 5.1.
const STEP_SETTLED_PX: f64 = 1e-3;

/// A blurred step `a + b·Φ((s − e)/σ)` fitted to `(s, grey)` samples across an edge;
/// parameters `(a, b, e, σ)`, σ kept within (0.2, 4) px (a wider or sharper step is no
/// lens blur: such a point is refused).
///
/// The fit asks for the cost at a point and then, if it is kept, the linearisation
/// there: Φ and its density at every sample are computed once for both (`phi`, valid
/// for the `(e, σ)` of `phi_for`), which is most of the arithmetic of a fit.
struct StepProfile<'a> {
    samples: &'a [(f64, f64)],
    phi: &'a mut [(f64, f64)],
    phi_for: Option<(f64, f64)>,
}

/// Samples of an edge fit kept on the stack (a ±3 px window 3 px wide reads ~30).
const STACK_SAMPLES: usize = 64;

impl StepProfile<'_> {
    /// Φ and its density at every sample for `(e, σ) = (x[2], x[3])`.
    fn phi_at(&mut self, x: &nalgebra::Vector4<f64>) -> &[(f64, f64)] {
        if self.phi_for != Some((x[2], x[3])) {
            for ((s, _), phi) in self.samples.iter().zip(self.phi.iter_mut()) {
                *phi = normal_cdf_pdf((s - x[2]) / x[3]);
            }
            self.phi_for = Some((x[2], x[3]));
        }
        self.phi
    }
}

impl LeastSquares for StepProfile<'_> {
    type Point = nalgebra::Vector4<f64>;
    type Normal = Dense<nalgebra::U4>;

    fn linearize(&mut self, x: &nalgebra::Vector4<f64>) -> Option<Dense<nalgebra::U4>> {
        let mut jtj = nalgebra::Matrix4::<f64>::zeros();
        let mut jtr = nalgebra::Vector4::<f64>::zeros();
        let samples = self.samples;
        for ((s, v), &(cdf, pdf)) in samples.iter().zip(self.phi_at(x)) {
            let z = (s - x[2]) / x[3];
            let r = x[0] + x[1] * cdf - v;
            let j = nalgebra::Vector4::new(1.0, cdf, -x[1] * pdf / x[3], -x[1] * pdf * z / x[3]);
            jtj += j * j.transpose();
            jtr += j * r;
        }
        Some(Dense::new(jtj, jtr))
    }

    fn cost(&mut self, x: &nalgebra::Vector4<f64>) -> Option<f64> {
        if !(x[3] > 0.2 && x[3] < 4.0) {
            return None;
        }
        let samples = self.samples;
        Some(
            samples
                .iter()
                .zip(self.phi_at(x))
                .map(|((_, v), &(cdf, _))| (x[0] + x[1] * cdf - v).powi(2))
                .sum(),
        )
    }

    fn retract(
        &self,
        x: &nalgebra::Vector4<f64>,
        step: &nalgebra::Vector4<f64>,
    ) -> nalgebra::Vector4<f64> {
        x + step
    }

    /// The edge position moved less than [`STEP_SETTLED_PX`].
    fn settled(&self, _: &nalgebra::Vector4<f64>, step: &nalgebra::Vector4<f64>) -> bool {
        step[2].abs() < STEP_SETTLED_PX
    }

    /// A settling step at low damping is taken without evaluating the profile there
    /// (an evaluation and a linearisation of every pixel saved per edge point): over
    /// such a step the cost is its quadratic model, and the fit ends with it anyway.
    fn trusted(&self, step: &nalgebra::Vector4<f64>, lambda: f64) -> bool {
        lambda < 1e-2 && self.settled(step, step)
    }
}

/// How a polygon's sides are sampled: the fraction of each side kept clear of its
/// corners, and how far (px) the nearest other edge may be from a side (levels are read
/// and edges searched only well within that).
#[derive(Clone, Copy, Debug)]
pub struct SideSampling {
    pub corner_clearance: f64,
    /// Room (px) either side of a side, across it.
    pub room: fn(&SideExtent) -> f64,
    /// How far a corner may move in a pass beyond the search reach, as a fraction of the
    /// shortest side: rough corners found by thresholding lose the tips of acute corners
    /// (seen: 11 px on a 190 px side at grazing view), while the sides' lines are right.
    pub corner_slack: f64,
    /// Distance (px) along a side between the measuring pass's profiles: 1 reads each
    /// pixel in `2·FIT_BAND + 1` fits; wider, each fit reads the pixels half way to its
    /// neighbours', so every pixel in one.
    pub spacing: f64,
}

/// Fewest profiles of a measuring pass on a side (of at least as many pixels) whatever
/// its spacing: the corners of small seeds measured from fewer wander enough that the
/// neighbours predicted from them misread (fisheye boards of 12-20 px tags: 3 whole
/// boards lost in 12 views at 3 px spacing, none with this floor).
const MIN_FINE_PROFILES: f64 = 12.0;

/// Profile spacing at which a fit of the default band reads no pixel another reads: a
/// third of the fits of one profile per pixel (each reading half as many pixels again),
/// for corners as good (tags of 46-80 px on a dense 1080p hall: 0.0084 against 0.0082 px
/// sd; 0.0092 with the fits' bands left at ±1 px, which skipped a third of the pixels).
pub const INDEPENDENT_SPACING: f64 = 2.0 * FIT_BAND + 1.0;

/// What a side's room is judged from (raw pixels).
#[derive(Clone, Copy, Debug)]
pub struct SideExtent {
    /// The side's length.
    pub len: f64,
    /// The polygon's shortest side.
    pub shortest: f64,
    /// The polygon's extent across the side: the farthest corner from its line.
    pub across: f64,
}

/// A tag's black square: profiles ~1 cell clear of the corners (AprilGrid crossing
/// squares touch them), within the one-cell border — a border cell measured across the
/// side (an eighth of the tag's extent that way), not along it: on a tag foreshortened
/// 2:1 the long sides' cells are half as deep as they are long, and levels read a cell
/// along reached into the bits (seen: corners 0.34 px off at 57 × 26 px).
pub const TAG_SIDES: SideSampling = SideSampling {
    corner_clearance: 0.12,
    room: |side| side.across / 8.0,
    corner_slack: 0.0,
    spacing: 1.0,
};

/// A refined dark polygon on a bright ground, in the plane where its sides are straight.
#[derive(Clone, Debug)]
pub struct RefinedPolygon {
    /// Corners in raw pixels, in the order given.
    pub corners: Vec<Vec2>,
    /// Per side (from corner k to k+1): the edge points kept by the fit, raw pixels.
    pub side_points: Vec<Vec<Vec2>>,
    /// Per side: `[a, b, c]` with `a·x + b·y + c = 0`, `a² + b² = 1`, in the plane.
    pub side_lines: Vec<Vec3>,
    pub edge_rms: f64,
    pub contrast: f64,
    /// Median blur σ (px, the optics and the pixel's own area) of the edge profiles the
    /// measuring pass fitted; `None` where none was (sides too close to other edges).
    pub blur: Option<f64>,
}

/// Refine a tag's black square. `corners` in raw pixels, counter-clockwise in the tag's
/// frame (any consistent order round the quad works); `reach` (px) is how far the true
/// sides may be from the given ones; `spacing` (px) between the measuring profiles
/// ([`SideSampling::spacing`]).
pub fn refine_quad(
    img: &Gray,
    corners: &[Vec2; 4],
    lens: Lens,
    reach: f64,
    spacing: f64,
) -> Option<Refined> {
    let sampling = SideSampling {
        spacing,
        ..TAG_SIDES
    };
    let r = refine_polygon(img, corners, lens, reach, &sampling)?;
    Some(Refined {
        corners: [r.corners[0], r.corners[1], r.corners[2], r.corners[3]],
        edge_rms: r.edge_rms,
        contrast: r.contrast,
        blur: r.blur,
    })
}

/// Refine any simple dark polygon (convex or not) from rough corners in raw pixels:
/// two passes of side sampling, the second along the first's sides.
pub fn refine_polygon(
    img: &Gray,
    corners: &[Vec2],
    lens: Lens,
    reach: f64,
    sampling: &SideSampling,
) -> Option<RefinedPolygon> {
    let mut plane: Vec<Vec2> = corners
        .iter()
        .map(|c| lens.to_plane(*c))
        .collect::<Option<_>>()?;
    let mut reach = reach;
    let mut last = None;
    for fine in [false, true] {
        let pass = refine_once(img, &plane, lens, reach, sampling, fine)?;
        plane = pass.corners.clone();
        last = Some(pass);
        reach = 1.0;
    }
    let pass = last?;
    Some(RefinedPolygon {
        corners: plane
            .iter()
            .map(|q| lens.to_pixel(*q))
            .collect::<Option<_>>()?,
        side_points: pass.side_points,
        side_lines: pass.lines,
        edge_rms: pass.edge_rms,
        contrast: pass.contrast,
        blur: pass.blur,
    })
}

struct Pass {
    corners: Vec<Vec2>,
    lines: Vec<Vec3>,
    side_points: Vec<Vec<Vec2>>,
    edge_rms: f64,
    contrast: f64,
    blur: Option<f64>,
}

/// Profile spacing (px) of the first pass, which only has to bring the sides within the
/// second pass's 1 px reach: a third of the profiles, and no pixel-model fit.
const COARSE_SPACING: f64 = 3.0;

/// One pass of side sampling. `fine`: one profile per pixel and the pixel-model edge fit
/// (the measurement); otherwise every [`COARSE_SPACING`] px, interpolated crossings only.
fn refine_once(
    img: &Gray,
    plane: &[Vec2],
    lens: Lens,
    reach: f64,
    sampling: &SideSampling,
    fine: bool,
) -> Option<Pass> {
    let n_sides = plane.len();
    if n_sides < 3 {
        return None;
    }
    let px: Vec<Vec2> = plane
        .iter()
        .map(|q| lens.to_pixel(*q))
        .collect::<Option<_>>()?;
    // A polygon with a corner far outside the image (or not finite) has nothing to
    // measure there, and its side lengths would size the sampling below.
    if px.iter().any(|p| far_out(*p)) {
        return None;
    }
    // Orientation in raw pixels: the outward normal of side a→b is sign·(t.y, −t.x).
    let area2: f64 = (0..n_sides)
        .map(|k| {
            let (a, b) = (px[k], px[(k + 1) % n_sides]);
            a.x * b.y - a.y * b.x
        })
        .sum();
    let outward = if area2 >= 0.0 { 1.0 } else { -1.0 };
    let shortest = (0..n_sides)
        .map(|k| (px[(k + 1) % n_sides] - px[k]).norm())
        .fold(f64::INFINITY, f64::min);
    let mut lines = Vec::with_capacity(n_sides);
    let mut side_points = Vec::with_capacity(n_sides);
    let (mut sq, mut count, mut contrast_sum, mut contrast_n) = (0.0, 0usize, 0.0, 0usize);
    let mut blurs = Vec::new();
    for side in 0..n_sides {
        let (a, b) = (plane[side], plane[(side + 1) % n_sides]);
        let len_px = (px[(side + 1) % n_sides] - px[side]).norm();
        if len_px < 6.0 {
            return None;
        }
        let (pa, pb) = (px[side], px[(side + 1) % n_sides]);
        let normal = Vec2::new(pb.y - pa.y, pa.x - pb.x) / len_px.max(1e-300);
        let across = px
            .iter()
            .map(|v| (v - pa).dot(&normal).abs())
            .fold(0.0, f64::max);
        let room = (sampling.room)(&SideExtent {
            len: len_px,
            shortest,
            across,
        });
        // Levels at ±d: the farther from the edge the closer to the plateaus, the nearer
        // the bits or the next edge. 0.35 of the room (it was 0.45) cut corner RMS on 10
        // of the 12 cells and boards measured (grids 0.029-0.033 → 0.027-0.030 px, the
        // 38 px board at 56° 0.106 → 0.089); 0.28 was worse everywhere.
        let d = (0.35 * room).clamp(0.5, 2.5);
        let reach_here = reach.min(0.9 * room);
        let t0 = sampling.corner_clearance;
        let span = 1.0 - 2.0 * t0;
        let spacing = if fine {
            sampling.spacing
        } else {
            COARSE_SPACING
        };
        // A measuring pass thinned by its spacing keeps one profile per pixel up to
        // MIN_FINE_PROFILES.
        let floor = if fine {
            (len_px * span).ceil().min(MIN_FINE_PROFILES)
        } else {
            0.0
        };
        let samples = (len_px * span / spacing).ceil().max(floor).max(6.0) as usize;
        // Each fit reads the band of pixels half way to the next profile's, so that
        // profiles wider apart than the band still read every pixel of the side.
        let band = (0.5 * len_px * span / samples as f64).max(FIT_BAND);
        let mut pts = Vec::with_capacity(samples);
        let mut fitted: Option<nalgebra::Vector4<f64>> = None;
        for i in 0..samples {
            let t = t0 + span * (i as f64 + 0.5) / samples as f64;
            let on_side = a + (b - a) * t;
            let (p, tangent) = lens.to_pixel_along(on_side, b - a)?;
            let n = Vec2::new(tangent.y, -tangent.x) * outward;
            // The pixel model needs the levels either side: ±2.5 px at least (below
            // that its four unknowns are poorly separated and the interpolated crossing
            // is the better estimate), wherever the room allows, even where the levels
            // are read nearer: the crossing is biased by where the edge falls between
            // pixel centres, the same all along a side near a pixel row (tags of 30-46 px
            // on a dense 1080p hall: 0.032 px sd, 0.011 with the fit).
            let along = (d + 0.5).max(MIN_FIT_WINDOW).min(0.9 * room);
            let fit = fine && along >= MIN_FIT_WINDOW;
            let tol = if fine && !fit {
                CROSSING_TOL
            } else {
                START_TOL
            };
            if let Some((e, contrast)) = edge_offset(img, p, n, reach_here, d, tol) {
                let e = if fit {
                    // Where the fit does not settle, the precise crossing instead.
                    let window = Window {
                        along,
                        across: band,
                    };
                    let start = fitted.map_or(Start::Contrast(contrast), Start::Neighbour);
                    fitted = fit_edge(img, p, n, e, window, start);
                    blurs.extend(fitted.map(|x| x[3]));
                    fitted
                        .map(|x| x[2])
                        .or_else(|| Some(edge_offset(img, p, n, reach_here, d, CROSSING_TOL)?.0))
                        .unwrap_or(e)
                } else {
                    e
                };
                if let Some(q) = lens.to_plane_near(p + n * e, on_side) {
                    pts.push((q, p + n * e));
                    contrast_sum += contrast;
                    contrast_n += 1;
                }
            }
        }
        if pts.len() < 4 {
            return None;
        }
        let plane_pts: Vec<Vec2> = pts.iter().map(|p| p.0).collect();
        let mut line = fit_line(&plane_pts)?;
        // Trim outliers (a blot, a finger, a neighbouring edge) and refit.
        let scale = len_px / (b - a).norm().max(1e-300);
        let res: Vec<f64> = plane_pts
            .iter()
            .map(|q| distance(&line, q).abs() * scale)
            .collect();
        let mut sorted = res.clone();
        sorted.sort_by(|x, y| x.total_cmp(y));
        let med = sorted[sorted.len() / 2];
        let kept: Vec<(Vec2, Vec2)> = pts
            .iter()
            .zip(&res)
            .filter(|(_, r)| **r <= (3.0 * 1.4826 * med).max(0.05))
            .map(|(p, _)| *p)
            .collect();
        if kept.len() >= 4 {
            let keep: Vec<Vec2> = kept.iter().map(|p| p.0).collect();
            line = fit_line(&keep)?;
        }
        let kept = if kept.len() >= 4 { kept } else { pts };
        for (q, _) in &kept {
            let r = distance(&line, q) * scale;
            sq += r * r;
            count += 1;
        }
        lines.push(line);
        side_points.push(kept.into_iter().map(|p| p.1).collect());
    }
    let mut out = Vec::with_capacity(n_sides);
    for k in 0..n_sides {
        // Corner k joins side k−1 (from corner k−1) and side k (to corner k+1).
        out.push(intersect(&lines[(k + n_sides - 1) % n_sides], &lines[k])?);
    }
    // A refined polygon far from its start is a different edge, not a refinement.
    for k in 0..n_sides {
        let moved = (lens.to_pixel(out[k])? - px[k]).norm();
        if moved > reach + 2.0 + sampling.corner_slack * shortest {
            return None;
        }
    }
    Some(Pass {
        corners: out,
        lines,
        side_points,
        edge_rms: (sq / count.max(1) as f64).sqrt(),
        contrast: contrast_sum / contrast_n.max(1) as f64,
        blur: median(blurs),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_fit_and_intersect_in_any_orientation() {
        let v: Vec<Vec2> = (0..10).map(|i| Vec2::new(3.0, i as f64)).collect();
        let h: Vec<Vec2> = (0..10).map(|i| Vec2::new(i as f64, -2.0)).collect();
        let p = intersect(&fit_line(&v).unwrap(), &fit_line(&h).unwrap()).unwrap();
        assert!((p - Vec2::new(3.0, -2.0)).norm() < 1e-12);
    }

    /// A dark square `half · 200` px across turned 1° (its sides sweep every phase between
    /// pixel centres slowly, the worst case for interpolated crossings), rendered with
    /// blur and no noise, and its true corners.
    fn turned_square(half: f64) -> (Gray, [Vec2; 4]) {
        use rigcal_core::geometry::Pose;
        use rigcal_synth::render::{render, RenderOptions};
        let (f, size) = (100.0, 121u32);
        let c = (size / 2) as f64;
        let cam = Camera::pinhole(f, f, c, c, size, size);
        let pose = Pose::new(nalgebra::Matrix3::identity(), Vec3::new(0.0, 0.0, 1.0));
        let turn = 1f64.to_radians();
        let (cs, sn) = (turn.cos(), turn.sin());
        let inside = move |x: f64, y: f64| {
            let (u, v) = (cs * x + sn * y, -sn * x + cs * y);
            u.abs() < half && v.abs() < half
        };
        let opts = RenderOptions {
            noise_sigma: 0.0,
            ..Default::default()
        };
        let img = render(&cam, &pose, &|x, y| Some(!inside(x, y)), &opts);
        let truth = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)].map(|(a, b)| {
            let (x, y) = (half * a, half * b);
            Vec2::new(c + f * (cs * x - sn * y), c + f * (sn * x + cs * y))
        });
        (Gray::from_luma8(&img), truth)
    }

    /// Rough corners 0.7 px off, as the quad detector gives them.
    fn rough(truth: &[Vec2; 4]) -> [Vec2; 4] {
        [
            truth[0] + Vec2::new(0.7, -0.4),
            truth[1] + Vec2::new(-0.5, 0.6),
            truth[2] + Vec2::new(0.3, 0.7),
            truth[3] + Vec2::new(-0.7, -0.2),
        ]
    }

    /// The square's corners refined from [`rough`] ones at `spacing` are within 0.02 px.
    fn assert_refined_within_0_02(gray: &Gray, truth: &[Vec2; 4], spacing: f64) {
        let r = refine_quad(gray, &rough(truth), Lens(None), 2.0, spacing).expect("refined");
        for k in 0..4 {
            let err = (r.corners[k] - truth[k]).norm();
            assert!(err < 0.02, "spacing {spacing}, corner {k}: {err:.4} px");
        }
    }

    /// A 60 px square: corners to 0.02 px (0.006-0.015 measured; the interpolated
    /// crossings alone gave 0.036-0.049).
    #[test]
    fn corners_of_a_nearly_axis_aligned_square_are_exact() {
        let (gray, truth) = turned_square(0.3);
        assert_refined_within_0_02(&gray, &truth, 1.0);
    }

    /// Rough corners far outside the image or not finite are refused: a side 10¹⁹ px long
    /// once sized its sampling at ~10¹⁸ profiles (a capacity overflow, a panic).
    #[test]
    fn polygons_far_outside_the_image_are_refused() {
        let (gray, truth) = turned_square(0.3);
        for far in [1e19, -1e19, 1e12, f64::INFINITY, f64::NAN] {
            for k in 0..4 {
                let mut c = truth;
                c[k].x = far;
                for spacing in [1.0, INDEPENDENT_SPACING] {
                    assert!(
                        refine_quad(&gray, &c, Lens(None), 4.0, spacing).is_none(),
                        "{c:?}"
                    );
                }
            }
        }
    }

    /// A 40 px square, whose border cell (5 px) reads the levels nearer than the fit's
    /// ±2.5 px: its sides are fitted all the same (interpolated crossings left corners
    /// 0.05-0.12 px off on such tags), with a profile every pixel or every 3 px alike.
    #[test]
    fn a_tag_with_a_narrow_border_cell_is_fitted_at_either_spacing() {
        let (gray, truth) = turned_square(0.2);
        for spacing in [1.0, INDEPENDENT_SPACING] {
            assert_refined_within_0_02(&gray, &truth, spacing);
        }
    }

    /// The ends of side 0 → 1 of a [`turned_square`] and its normal towards the outside:
    /// the side runs along +x with the square below it, dark towards +y.
    fn first_side(truth: &[Vec2; 4]) -> (Vec2, Vec2, Vec2) {
        let (a, b) = (truth[0], truth[1]);
        let t = (b - a).normalize();
        (a, b, Vec2::new(t.y, -t.x))
    }

    /// An edge fit over a window of more pixels than it keeps on the stack
    /// (`STACK_SAMPLES`: ±8 px across a ±2.5 px window reads ~100) finds the edge where
    /// the usual window does: on the side itself.
    #[test]
    fn an_edge_fit_wider_than_its_stack_finds_the_same_edge() {
        let (gray, truth) = turned_square(0.3);
        let (a, b, n) = first_side(&truth);
        let p = a + (b - a) * 0.5;
        let (e, contrast) = edge_offset(&gray, p, n, 1.0, 2.0, START_TOL).expect("an edge");
        for across in [FIT_BAND, 8.0] {
            let window = Window {
                along: MIN_FIT_WINDOW,
                across,
            };
            let x = fit_edge(&gray, p, n, e, window, Start::Contrast(contrast)).expect("fits");
            assert!(
                x[2].abs() < 0.01,
                "±{across} px across: edge {:.4} px off",
                x[2]
            );
        }
    }

    /// Along a side, a fit started from the step its neighbour settled at settles where
    /// one started from the crossing's contrast and a typical blur does (both stop once
    /// the edge moves under [`STEP_SETTLED_PX`]), and reads the blur the render has.
    #[test]
    fn a_fit_started_from_its_neighbour_settles_where_a_fresh_one_does() {
        let (gray, truth) = turned_square(0.3);
        let (a, b, n) = first_side(&truth);
        let window = Window {
            along: MIN_FIT_WINDOW,
            across: FIT_BAND,
        };
        let mut previous = None;
        let mut fitted = 0;
        for i in 1..20 {
            let p = a + (b - a) * (0.1 + 0.04 * i as f64);
            let (e, contrast) = edge_offset(&gray, p, n, 1.0, 2.0, START_TOL).expect("an edge");
            let fresh = fit_edge(&gray, p, n, e, window, Start::Contrast(contrast)).expect("fits");
            if let Some(x) = previous {
                let warm = fit_edge(&gray, p, n, e, window, Start::Neighbour(x)).expect("fits");
                let d = (warm[2] - fresh[2]).abs();
                assert!(d < 2.0 * STEP_SETTLED_PX, "profile {i}: {d:.5} px apart");
                fitted += 1;
            }
            // Render blur 0.8 and the pixel's area: √(0.8² + 1/12) = 0.85.
            assert!(
                (fresh[3] - 0.85).abs() < 0.03,
                "profile {i}: σ {:.3}",
                fresh[3]
            );
            previous = Some(fresh);
        }
        assert_eq!(fitted, 18);
    }
}
