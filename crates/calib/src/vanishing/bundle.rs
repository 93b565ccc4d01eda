//! Point-to-line bundle adjustment for line targets: the refinement of one camera–target
//! pose (eq. 19) and the ring-closure optimisation (eq. 25) are the same problem with
//! different unknowns, so they share this solver.
//!
//! Unknowns: `ref_from_target` per target and `cam_from_ref` per view (image), each free or
//! held. Residual: the signed distance (px, undistorted) of every measured line point to
//! the projection of its feature line, the line through the projected end points. The
//! paper's eq. 19 measures corner-to-fitted-line distances instead (12 numbers per view);
//! using every point is the maximum-likelihood version of the same cost for Gaussian noise
//! on the points, and gives a residual σ to scale the covariance with.
//!
//! Dense normal equations: a ring of 8 targets and 8 auxiliary views has 90 unknowns.

use nalgebra::Dyn;
use nalgebra::{DMatrix, DVector, Matrix2x3, Matrix3};
use rigcal_core::geometry::{so3, Camera, Pose, Vec2, Vec3};
use rigcal_core::target::line_layout::{Axis, LineLayout, Print};
use rigcal_solve::lm::{minimize, Damping, Dense, LeastSquares, Rules};
use rigcal_solve::Loss;

/// Points measured on one feature line in one view (undistorted pixels).
#[derive(Clone, Debug)]
pub struct LinePoints {
    pub view: usize,
    pub target: usize,
    pub line: usize,
    pub points: Vec<Vec2>,
    /// Weight of each point's squared residual: the pooled point variance over this
    /// line's own (1 until [`LineBundle::weigh_by_line_scatter`]).
    pub weight: f64,
}

/// Lines with this many points count as much as the pooled variance when a line's own
/// scatter is estimated (shrinkage: a line of 5 points cannot claim to be 10× better).
const SCATTER_PRIOR_POINTS: f64 = 10.0;
/// Bounds of a line's weight relative to the pool.
const WEIGHT_RANGE: (f64, f64) = (0.05, 20.0);
/// The most the neighbours' correlation may inflate the covariance: points spaced as
/// the detectors keep them give at most ~1.8 under pure image noise; more is a model
/// failure the residuals report elsewhere, not a reason to claim nothing.
const MAX_CORRELATION_INFLATION: f64 = 3.0;

#[derive(Clone, Debug)]
pub struct LineBundle {
    pub geometry: Vec<LineLayout>,
    pub ref_from_target: Vec<Pose>,
    pub target_free: Vec<bool>,
    /// The ideal pinhole of each view (residuals live in its undistorted pixels).
    pub cameras: Vec<Camera>,
    pub cam_from_ref: Vec<Pose>,
    pub view_free: Vec<bool>,
    pub obs: Vec<LinePoints>,
}

#[derive(Clone, Debug)]
pub struct LineSummary {
    pub iterations: usize,
    pub initial_cost: f64,
    pub final_cost: f64,
    pub converged: bool,
    pub termination: String,
}

/// Signed distance of `q` to the line through `a` and `b`, and its derivatives with
/// respect to `a` and `b`.
pub fn point_line_residual(a: &Vec2, b: &Vec2, q: &Vec2) -> Option<(f64, Vec2, Vec2)> {
    let d = b - a;
    let w = q - a;
    let len = d.norm();
    if len < 1e-9 {
        return None;
    }
    let c = d.x * w.y - d.y * w.x;
    let dc_db = Vec2::new(w.y, -w.x);
    let dc_da = Vec2::new(d.y - w.y, w.x - d.x);
    let r = c / len;
    let dl_db = d / len;
    let dr_da = dc_da / len + c * dl_db / (len * len);
    let dr_db = dc_db / len - c * dl_db / (len * len);
    Some((r, dr_da, dr_db))
}

/// A projected end point: pixel, d(pixel)/d(point in camera), and d(point in camera)/d of
/// the view's dφ, the target's dt and the target's dφ.
type ProjectedEnd = (
    Vec2,
    Matrix2x3<f64>,
    Matrix3<f64>,
    Matrix3<f64>,
    Matrix3<f64>,
);

/// Jacobian blocks of one residual: `(view param columns, target param columns)`.
type RowJacobian = ([f64; 6], [f64; 6]);

impl LineBundle {
    /// Column offset of each free target and view in the parameter vector.
    fn layout(&self) -> (Vec<Option<usize>>, Vec<Option<usize>>, usize) {
        let mut n = 0;
        let mut next = |free: bool| {
            free.then(|| {
                n += 6;
                n - 6
            })
        };
        let t: Vec<_> = self.target_free.iter().map(|f| next(*f)).collect();
        let v: Vec<_> = self.view_free.iter().map(|f| next(*f)).collect();
        (t, v, n)
    }

    /// Number of unknowns.
    pub fn parameters(&self) -> usize {
        self.layout().2
    }

    /// Column of target `t`'s block in the covariance, if free.
    pub fn target_column(&self, t: usize) -> Option<usize> {
        self.layout().0[t]
    }

    /// Projected end points of a feature line with their Jacobians with respect to the
    /// view's and the target's `[dt, dφ]` perturbations, each as weighted image points.
    ///
    /// An outline's feature line has one edge; a printed stroke has two, `±width/2`
    /// from its centre line in the sheet, each with weight ½ (see [`Self::rows`]).
    fn endpoints(
        &self,
        view: usize,
        target: usize,
        line: usize,
    ) -> Option<[Vec<(f64, ProjectedEnd)>; 2]> {
        let layout = &self.geometry[target];
        let (a, b) = layout.segment(line);
        let cam_from_ref = &self.cam_from_ref[view];
        let ref_from_target = &self.ref_from_target[target];
        let cam = &self.cameras[view];
        let one = |x: Vec3| {
            let in_ref = ref_from_target.apply(&x);
            let in_cam = cam_from_ref.apply(&in_ref);
            let (uv, jp) = cam.project_with_jacobian(&in_cam)?;
            // d(in_cam)/d(view dφ), d(in_cam)/d(target dt), d(in_cam)/d(target dφ).
            let dv_phi = -so3::skew(&(cam_from_ref.rot * in_ref));
            let dt_t = cam_from_ref.rot;
            let dt_phi = -cam_from_ref.rot * so3::skew(&(ref_from_target.rot * x));
            Some((uv, jp, dv_phi, dt_t, dt_phi))
        };
        let end = |x: Vec3| -> Option<Vec<(f64, ProjectedEnd)>> {
            match layout.print {
                Print::Outline => Some(vec![(1.0, one(x)?)]),
                Print::Strokes { width } => {
                    // In the sheet, perpendicular to the line.
                    let n = match layout.segments[line].axis {
                        Axis::X => Vec3::z(),
                        Axis::Z => Vec3::x(),
                    } * (width / 2.0);
                    Some(vec![(0.5, one(x + n)?), (0.5, one(x - n)?)])
                }
            }
        };
        Some([end(a)?, end(b)?])
    }

    /// Every residual with its Jacobian blocks; `None` entries where the line does not
    /// project (behind the camera).
    ///
    /// The residual is the weighted mean of the point's signed distances to the images
    /// of the feature line's edges. For an outline that is the distance to its one edge.
    /// For a stroke it vanishes on the *bisector* of its two edges' images, which is
    /// where a ridge detector finds the centre of the band between them: the smoothed
    /// band is mirror-symmetric about that bisector. Under perspective the band is a
    /// wedge (the nearer end images wider), and neither the image of the stroke's centre
    /// line nor the line through the midpoints of its ends is the bisector: on Wu's ring
    /// with 12 mm strokes those sit 0.06-0.08 and up to 0.045 px off it, the same sign
    /// along each line, which biased whole rings by 0.3 mm.
    fn rows(&self, with_jacobian: bool) -> Vec<(usize, Option<(f64, RowJacobian)>)> {
        let mut out = Vec::new();
        for (oi, o) in self.obs.iter().enumerate() {
            let ends = self.endpoints(o.view, o.target, o.line);
            for q in &o.points {
                let row = ends.as_ref().and_then(|[ea, eb]| {
                    let mut r = 0.0;
                    let mut parts = Vec::with_capacity(2 * ea.len());
                    for ((w, a), (_, b)) in ea.iter().zip(eb) {
                        let (ri, dra, drb) = point_line_residual(&a.0, &b.0, q)?;
                        r += w * ri;
                        parts.push((dra * *w, a));
                        parts.push((drb * *w, b));
                    }
                    if !with_jacobian {
                        return Some((r, ([0.0; 6], [0.0; 6])));
                    }
                    let mut jv = [0.0; 6];
                    let mut jt = [0.0; 6];
                    for (dr, e) in parts {
                        let g = e.1.transpose() * dr; // dr/d(in_cam)
                        let gv_phi = e.2.transpose() * g;
                        let gt_t = e.3.transpose() * g;
                        let gt_phi = e.4.transpose() * g;
                        for k in 0..3 {
                            jv[k] += g[k];
                            jv[3 + k] += gv_phi[k];
                            jt[k] += gt_t[k];
                            jt[3 + k] += gt_phi[k];
                        }
                    }
                    Some((r, (jv, jt)))
                });
                out.push((oi, row));
            }
        }
        out
    }

    /// Signed residuals (px) per observation, `NaN` where the line does not project.
    pub fn residuals(&self) -> Vec<Vec<f64>> {
        let mut out: Vec<Vec<f64>> = self.obs.iter().map(|_| Vec::new()).collect();
        for (oi, row) in self.rows(false) {
            out[oi].push(row.map_or(f64::NAN, |r| r.0));
        }
        out
    }

    /// Robust cost of the weighted residuals; a line that does not project costs as much
    /// as a 1000 px residual per point.
    pub fn cost(&self, loss: &Loss) -> f64 {
        self.rows(false)
            .iter()
            .map(|(oi, r)| {
                r.map_or(loss.rho(1e6), |(r, _)| {
                    loss.rho(self.obs[*oi].weight * r * r)
                })
            })
            .sum()
    }

    /// Weigh each line by its own scatter: points of one line share their stroke's
    /// width, scale and image, and their noise differs from line to line (on Wu's ring
    /// the far, narrow strokes' points scatter four times more than the near, wide
    /// ones'), so one pooled σ both wastes the precise lines and overstates the
    /// uncertainty they leave. Each line's variance is its mean squared residual at the
    /// current solution, shrunk towards the pooled one by [`SCATTER_PRIOR_POINTS`]; its
    /// weight is the pooled variance over that. Call after a first solve, then solve
    /// again.
    pub fn weigh_by_line_scatter(&mut self) {
        let residuals = self.residuals();
        let stats: Vec<(f64, f64)> = residuals
            .iter()
            .map(|r| {
                let finite: Vec<f64> = r.iter().copied().filter(|v| v.is_finite()).collect();
                (finite.iter().map(|v| v * v).sum(), finite.len() as f64)
            })
            .collect();
        let (sum, count) = stats
            .iter()
            .fold((0.0, 0.0), |(s, c), (a, b)| (s + a, c + b));
        if count == 0.0 || sum <= 0.0 {
            return;
        }
        let pooled = sum / count;
        for (o, (s, n)) in self.obs.iter_mut().zip(stats) {
            let own = (s + SCATTER_PRIOR_POINTS * pooled) / (n + SCATTER_PRIOR_POINTS);
            o.weight = (pooled / own).clamp(WEIGHT_RANGE.0, WEIGHT_RANGE.1);
        }
    }

    /// Weighted normal equations `H = Σ w JᵀJ`, `g = Σ w J r`, the weighted squared sum and
    /// the residual count.
    fn normal_equations(&self, loss: &Loss) -> (DMatrix<f64>, DVector<f64>, f64, usize) {
        let (tcol, vcol, n) = self.layout();
        let mut h = DMatrix::zeros(n, n);
        let mut g = DVector::zeros(n);
        let mut sum = 0.0;
        let mut count = 0;
        for (oi, row) in self.rows(true) {
            let Some((r, (jv, jt))) = row else { continue };
            let o = &self.obs[oi];
            let w = loss.weight(o.weight * r * r) * o.weight;
            sum += w * r * r;
            count += 1;
            let blocks: Vec<(usize, &[f64; 6])> = [(vcol[o.view], &jv), (tcol[o.target], &jt)]
                .into_iter()
                .filter_map(|(c, j)| c.map(|c| (c, j)))
                .collect();
            for &(ca, ja) in &blocks {
                for i in 0..6 {
                    g[ca + i] += w * ja[i] * r;
                    for &(cb, jb) in &blocks {
                        for k in 0..6 {
                            h[(ca + i, cb + k)] += w * ja[i] * jb[k];
                        }
                    }
                }
            }
        }
        (h, g, sum, count)
    }

    fn apply(&mut self, delta: &DVector<f64>) {
        let (tcol, vcol, _) = self.layout();
        let step = |p: &Pose, c: usize| {
            p.perturbed(
                &Vec3::new(delta[c], delta[c + 1], delta[c + 2]),
                &Vec3::new(delta[c + 3], delta[c + 4], delta[c + 5]),
            )
        };
        for (t, c) in tcol.iter().enumerate() {
            if let Some(c) = c {
                self.ref_from_target[t] = step(&self.ref_from_target[t], *c);
            }
        }
        for (v, c) in vcol.iter().enumerate() {
            if let Some(c) = c {
                self.cam_from_ref[v] = step(&self.cam_from_ref[v], *c);
            }
        }
    }

    /// Levenberg–Marquardt (the driver of `rigcal_solve::lm`, Marquardt's damping) over
    /// the free poses, at most `max_iterations` linear solves.
    pub fn solve(&mut self, loss: &Loss, max_iterations: usize) -> LineSummary {
        if self.parameters() == 0 {
            let cost = self.cost(loss);
            return LineSummary {
                iterations: 0,
                initial_cost: cost,
                final_cost: cost,
                converged: true,
                termination: "nothing to estimate".into(),
            };
        }
        let rules = Rules {
            max_iterations,
            damping: Damping::Marquardt {
                raise: 4.0,
                lower: 1.0 / 3.0,
                min_lambda: 1e-12,
            },
            initial_lambda: 1e-4,
            diagonal_floor: 1e-9,
            tries: usize::MAX,
            max_lambda: 1e12,
            function_tolerance: 1e-12,
            min_step: 1e-12,
            gradient_tolerance: 1e-14,
            creep_tolerance: 0.0,
        };
        let mut problem = LineFit { loss: *loss };
        // The cost is defined everywhere (a line that does not project costs a fixed
        // penalty), so the fit always starts; were it not, that is said, not hidden.
        let Some(fit) = minimize(&mut problem, self.clone(), &rules) else {
            return LineSummary {
                iterations: 0,
                initial_cost: f64::NAN,
                final_cost: f64::NAN,
                converged: false,
                termination: "the cost is undefined at the starting point".into(),
            };
        };
        *self = fit.point;
        LineSummary {
            iterations: fit.iterations,
            initial_cost: fit.initial_cost,
            final_cost: fit.cost,
            converged: fit.converged,
            termination: fit.termination.to_string(),
        }
    }

    /// [`Self::solve`], then, if that reached a solution, again with every line weighed
    /// by its own scatter there ([`Self::weigh_by_line_scatter`]). The summary is the
    /// second solve's (its costs are of the weighted residuals) with both iterations.
    pub fn solve_weighing_lines(&mut self, loss: &Loss, max_iterations: usize) -> LineSummary {
        let first = self.solve(loss, max_iterations);
        let reached = first.converged || first.final_cost < first.initial_cost;
        if !reached || !first.final_cost.is_finite() || self.obs.len() < 2 {
            return first;
        }
        self.weigh_by_line_scatter();
        let second = self.solve(loss, max_iterations);
        LineSummary {
            iterations: first.iterations + second.iterations,
            ..second
        }
    }

    /// Covariance of the free unknowns (`[dt, dφ]` blocks in layout order) scaled by the
    /// residual variance, and that σ (px). `None` if the information matrix is singular
    /// or there are no more residuals than unknowns.
    pub fn covariance(&self, loss: &Loss) -> Option<(DMatrix<f64>, f64)> {
        let (h, _, sum, count) = self.normal_equations(loss);
        let n = h.nrows();
        if count <= n {
            return None;
        }
        let sigma2 = sum / (count - n) as f64;
        let inv = h.cholesky()?.inverse();
        let inflation = self.correlation_inflation(loss, &inv, sigma2);
        Some((inv * (sigma2 * inflation), sigma2.sqrt()))
    }

    /// How much more the unknowns vary than independent points would make them: `1 +
    /// 2 Σₖ ρₖ` over the correlations `ρₖ` of the weighted residuals `k` points apart
    /// along a line, with `ρₖ = ρ₁^(k²)` (the shape Gaussian smoothing gives) and `ρ₁`
    /// pooled over neighbours on every line. `inv` is the inverse information matrix
    /// and `sigma2` the residual variance of the solution.
    ///
    /// Why: a line point is where the smoothed profile's slope vanishes, and the noise
    /// in that slope is the image noise smoothed by the same Gaussian along the line, so
    /// points `Δ` apart share it with correlation `exp(−Δ²/4σ²)`: 0.37 at the ⌈2σ⌉
    /// spacing the detectors keep. Counted as independent they made σ̂ optimistic as
    /// soon as noise, not the sampling phase, dominated (NEES 8-10 against 6 on Wu's
    /// ring at σ 2-5 grey). The fit itself pulls residuals `a`, `b` apart by
    /// `σ²·P_ab` (`P` its hat matrix); that is added back, so independent points give
    /// `ρ = 0` however few points a line has. Neighbours across a gap (a crossing left
    /// out) are not neighbours.
    fn correlation_inflation(&self, loss: &Loss, inv: &DMatrix<f64>, sigma2: f64) -> f64 {
        let (tcol, vcol, _) = self.layout();
        // Per observation: each point's weighted residual and weighted Jacobian blocks.
        type Row = (f64, Vec<(usize, [f64; 6])>);
        let mut per_line: Vec<Vec<Option<Row>>> = self.obs.iter().map(|_| Vec::new()).collect();
        for (oi, row) in self.rows(true) {
            let o = &self.obs[oi];
            per_line[oi].push(row.map(|(r, (jv, jt))| {
                let sw = (loss.weight(o.weight * r * r) * o.weight).sqrt();
                let blocks = [(vcol[o.view], jv), (tcol[o.target], jt)]
                    .into_iter()
                    .filter_map(|(c, j)| c.map(|c| (c, j.map(|v| v * sw))))
                    .collect();
                (r * sw, blocks)
            }));
        }
        let hat = |a: &Row, b: &Row| -> f64 {
            let mut sum = 0.0;
            for (ca, ja) in &a.1 {
                for (cb, jb) in &b.1 {
                    for (i, x) in ja.iter().enumerate() {
                        for (k, y) in jb.iter().enumerate() {
                            sum += x * inv[(ca + i, cb + k)] * y;
                        }
                    }
                }
            }
            sum
        };
        let (mut lagged, mut pairs) = (0.0f64, 0usize);
        for (o, rows) in self.obs.iter().zip(&per_line) {
            let Some(rows) = rows.iter().cloned().collect::<Option<Vec<Row>>>() else {
                continue;
            };
            if rows.len() < 2 || rows.len() != o.points.len() {
                continue;
            }
            // Gaps measured along the line only: a step across it is the residuals'
            // difference, and choosing neighbours by it would choose alike residuals.
            let along = (o.points[o.points.len() - 1] - o.points[0]).normalize();
            let steps: Vec<f64> = o
                .points
                .windows(2)
                .map(|w| (w[1] - w[0]).dot(&along))
                .collect();
            let mut sorted = steps.clone();
            sorted.sort_by(f64::total_cmp);
            let spacing = sorted[sorted.len() / 2];
            for (i, step) in steps.iter().enumerate() {
                if *step <= 1.5 * spacing {
                    let (a, b) = (&rows[i], &rows[i + 1]);
                    lagged += a.0 * b.0 + sigma2 * hat(a, b);
                    pairs += 1;
                }
            }
        }
        if pairs == 0 || sigma2.is_nan() || sigma2 <= 0.0 {
            return 1.0;
        }
        // Not clamped at 0: independent points estimate ρ₁ around 0 either way, and
        // cutting off the negative half would inflate every covariance a little.
        let rho = (lagged / pairs as f64 / sigma2).clamp(-0.25, 0.95);
        let inflation = 1.0 + 2.0 * (1..=5).map(|k| rho.powi(k * k)).sum::<f64>();
        inflation.min(MAX_CORRELATION_INFLATION)
    }
}

/// The line bundle as a problem of the LM driver: a point is a whole bundle state.
struct LineFit {
    loss: Loss,
}

impl LeastSquares for LineFit {
    type Point = LineBundle;
    type Normal = Dense<Dyn>;

    fn linearize(&mut self, x: &LineBundle) -> Option<Dense<Dyn>> {
        let (h, g, _, _) = x.normal_equations(&self.loss);
        Some(Dense::new(h, g))
    }

    fn cost(&mut self, x: &LineBundle) -> Option<f64> {
        Some(x.cost(&self.loss))
    }

    fn retract(&self, x: &LineBundle, step: &DVector<f64>) -> LineBundle {
        let mut out = x.clone();
        out.apply(step);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rigcal_core::geometry::line2::{bisector, distance, through};

    fn problem(layout: LineLayout) -> LineBundle {
        let geometry = vec![layout; 2];
        let cam = Camera::pinhole(800.0, 790.0, 512.0, 384.0, 1024, 768);
        let obs = (0..2)
            .flat_map(|t| {
                (0..6).map(move |m| LinePoints {
                    view: 0,
                    target: t,
                    line: m,
                    points: vec![Vec2::new(400.0 + 10.0 * m as f64, 300.0 + t as f64 * 50.0)],
                    weight: 1.0,
                })
            })
            .collect();
        LineBundle {
            geometry,
            ref_from_target: vec![
                Pose::identity(),
                Pose::from_rotvec(Vec3::new(0.1, 0.7, -0.05), Vec3::new(0.9, 0.02, -0.2)),
            ],
            target_free: vec![false, true],
            cameras: vec![cam],
            cam_from_ref: vec![Pose::from_rotvec(
                Vec3::new(-0.9, 0.1, 0.05),
                Vec3::new(-0.3, 0.2, 1.5),
            )],
            view_free: vec![true],
            obs,
        }
    }

    #[test]
    fn point_line_derivatives_match_finite_differences() {
        let (a, b, q) = (
            Vec2::new(10.0, 20.0),
            Vec2::new(200.0, 90.0),
            Vec2::new(60.0, 70.0),
        );
        let (r, da, db) = point_line_residual(&a, &b, &q).unwrap();
        let h = 1e-6;
        for k in 0..2 {
            let mut e = Vec2::zeros();
            e[k] = h;
            let fa = (point_line_residual(&(a + e), &b, &q).unwrap().0
                - point_line_residual(&(a - e), &b, &q).unwrap().0)
                / (2.0 * h);
            let fb = (point_line_residual(&a, &(b + e), &q).unwrap().0
                - point_line_residual(&a, &(b - e), &q).unwrap().0)
                / (2.0 * h);
            assert!((fa - da[k]).abs() < 1e-7, "{fa} {}", da[k]);
            assert!((fb - db[k]).abs() < 1e-7, "{fb} {}", db[k]);
        }
        // Signed distance: q is left of a→b here.
        let n = Vec2::new(-(b - a).y, (b - a).x).normalize();
        assert!((r - n.dot(&(q - a))).abs() < 1e-12);
    }

    #[test]
    fn pose_jacobians_match_finite_differences() {
        for layout in [
            LineLayout::l_target(0.5, 0.2),
            LineLayout::grid(0.5, 0.2, 3, 3, 0.012),
        ] {
            pose_jacobians_match_finite_differences_for(layout);
        }
    }

    #[test]
    fn a_strokes_residual_vanishes_on_the_bisector_of_its_edges_images() {
        let p = problem(LineLayout::grid(0.5, 0.2, 3, 3, 0.05));
        let [ea, eb] = p.endpoints(0, 1, 4).unwrap();
        let edge = |k: usize| through(&ea[k].1 .0, &eb[k].1 .0).unwrap();
        let centre = bisector(&edge(0), &edge(1)).unwrap();
        let mid = (ea[0].1 .0 + ea[1].1 .0) / 2.0;
        // The midpoint across the stroke's end is off the bisector (the wedge), its foot
        // on the bisector is on the model line.
        assert!(distance(&centre, &mid).abs() > 1e-3);
        let foot = mid - centre.xy() * distance(&centre, &mid);
        let mut q = p.clone();
        q.obs = vec![LinePoints {
            view: 0,
            target: 1,
            line: 4,
            points: vec![foot, mid],
            weight: 1.0,
        }];
        let r = &q.residuals()[0];
        assert!(r[0].abs() < 1e-9, "{r:?}");
        let off = distance(&centre, &mid).abs();
        assert!((r[1].abs() - off).abs() < 1e-3 * off, "{r:?} {off}");
    }

    /// The grid's twelve lines seen by one view, 60 points along each (the middle 80 %),
    /// moved off their lines by noise of 0.1 px correlated `rho^(k²)` between points `k`
    /// apart (as Gaussian smoothing correlates them), then refitted.
    fn refitted_with_noise(rho: f64, seed: u64) -> LineBundle {
        use rand::SeedableRng;
        use rand_distr::{Distribution, StandardNormal};
        const N: usize = 60;
        let shape = DMatrix::from_fn(N, N, |i, j| rho.powi(((i as i32) - (j as i32)).pow(2)));
        let l = shape.cholesky().unwrap().l() * 0.1;
        let mut p = problem(LineLayout::grid(0.5, 0.2, 3, 3, 0.012));
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let lines: Vec<(usize, usize)> = (0..2).flat_map(|t| (0..6).map(move |m| (t, m))).collect();
        p.obs = lines
            .into_iter()
            .map(|(t, m)| {
                let [ea, eb] = p.endpoints(0, t, m).unwrap();
                let edge = |k: usize| through(&ea[k].1 .0, &eb[k].1 .0).unwrap();
                let centre = bisector(&edge(0), &edge(1)).unwrap();
                let (a, b) = (
                    (ea[0].1 .0 + ea[1].1 .0) / 2.0,
                    (eb[0].1 .0 + eb[1].1 .0) / 2.0,
                );
                let z = DVector::from_fn(N, |_, _| StandardNormal.sample(&mut rng));
                let e = &l * z;
                let points = (0..N)
                    .map(|i| {
                        let q = a + (b - a) * (0.1 + 0.8 * i as f64 / (N - 1) as f64);
                        let foot = q - centre.xy() * distance(&centre, &q);
                        foot + centre.xy() * e[i]
                    })
                    .collect();
                LinePoints {
                    view: 0,
                    target: t,
                    line: m,
                    points,
                    weight: 1.0,
                }
            })
            .collect();
        p.solve(&Loss::Squared, 50);
        p
    }

    #[test]
    fn neighbours_correlated_along_a_line_inflate_the_covariance_independent_ones_do_not() {
        // 1 + 2 Σₖ ρ^(k²): 1 for independent points, 1.78 at the correlation of points
        // 2σ apart under Gaussian smoothing (e⁻¹). Twelve lines of 60 points, ten draws.
        for rho in [0.0, (-1.0f64).exp(), 0.6] {
            let expected = 1.0 + 2.0 * (1..=5).map(|k| rho.powi(k * k)).sum::<f64>();
            let mut sum = 0.0;
            for seed in 0..10 {
                let p = refitted_with_noise(rho, seed);
                let (h, _, ss, count) = p.normal_equations(&Loss::Squared);
                let sigma2 = ss / (count - h.nrows()) as f64;
                let inv = h.cholesky().unwrap().inverse();
                sum += p.correlation_inflation(&Loss::Squared, &inv, sigma2);
            }
            let mean = sum / 10.0;
            assert!(
                (mean - expected).abs() < 0.05 * expected,
                "ρ {rho}: inflation {mean:.3}, expected {expected:.3}"
            );
        }
    }

    #[test]
    fn each_line_is_weighed_by_its_own_scatter_shrunk_towards_the_pool() {
        let mut p = problem(LineLayout::l_target(0.5, 0.2));
        // 40 points on each of two lines, ±0.1 px and ±0.4 px off them.
        let on_line = |p: &LineBundle, line: usize, off: f64| -> Vec<Vec2> {
            let [ea, eb] = p.endpoints(0, 1, line).unwrap();
            let (a, b) = (ea[0].1 .0, eb[0].1 .0);
            let n = Vec2::new(-(b - a).y, (b - a).x).normalize();
            (0..40)
                .map(|i| {
                    let s = 0.1 + 0.02 * i as f64;
                    a + (b - a) * s + n * if i % 2 == 0 { off } else { -off }
                })
                .collect()
        };
        p.obs = vec![
            LinePoints {
                view: 0,
                target: 1,
                line: 0,
                points: on_line(&p, 0, 0.1),
                weight: 1.0,
            },
            LinePoints {
                view: 0,
                target: 1,
                line: 5,
                points: on_line(&p, 5, 0.4),
                weight: 1.0,
            },
        ];
        p.weigh_by_line_scatter();
        // Pooled variance 0.085; own (40·v + 10·0.085) / 50 = 0.025 and 0.145.
        assert!(
            (p.obs[0].weight - 0.085 / 0.025).abs() < 1e-9,
            "{}",
            p.obs[0].weight
        );
        assert!(
            (p.obs[1].weight - 0.085 / 0.145).abs() < 1e-9,
            "{}",
            p.obs[1].weight
        );
    }

    fn pose_jacobians_match_finite_differences_for(layout: LineLayout) {
        let p = problem(layout);
        let rows = p.rows(true);
        let (_, g0, _, _) = p.normal_equations(&Loss::Squared);
        assert_eq!(g0.len(), 12);
        let h = 1e-7;
        for (i, (oi, row)) in rows.iter().enumerate() {
            let (_, (jv, jt)) = row.unwrap();
            for k in 0..12 {
                let mut plus = p.clone();
                let mut minus = p.clone();
                let mut d = DVector::zeros(12);
                // Layout: free target 1 at 0, view 0 at 6.
                d[k] = h;
                plus.apply(&d);
                minus.apply(&(-d));
                let fd = (plus.residuals()[*oi][0] - minus.residuals()[*oi][0]) / (2.0 * h);
                let an = if k < 6 { jt[k] } else { jv[k - 6] };
                let an = if p.obs[*oi].target == 0 && k < 6 {
                    0.0
                } else {
                    an
                };
                assert!(
                    (fd - an).abs() < 1e-4 * (1.0 + an.abs()),
                    "row {i} param {k}: fd {fd} analytic {an}"
                );
            }
        }
    }
}
