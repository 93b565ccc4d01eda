//! The Levenberg–Marquardt driver of the small dense fits (a pose, an edge profile, a
//! whole tag): one place for the damping, the step acceptance and the stopping rules,
//! so a fix to any of them reaches every estimator that uses it. As Ceres and COLMAP's
//! `optim/` separate them, the problem supplies the residual side (its normal
//! equations, its cost, and how a step moves a point on its manifold) and the driver
//! the iteration. The rig and ring bundles keep their own sparse (Schur) linear solves.
//!
//! Damping is Marquardt's: `λ·diag(JᵀJ)` added to the normal matrix (with a floor, so a
//! parameter the data does not yet constrain still gets a bounded step), raised after a
//! refused step and lowered after an accepted one.

use nalgebra::{SMatrix, SVector};

/// A nonlinear least-squares problem over `N` parameters.
pub trait LeastSquares<const N: usize> {
    /// A point of the problem's parameter space (a pose, a parameter vector).
    type Point: Clone;

    /// The Gauss–Newton normal equations `(JᵀJ, Jᵀr)` at `x`, weights and robust loss
    /// applied; `None` when they cannot be formed (the fit stops at `x`).
    fn linearize(&self, x: &Self::Point) -> Option<(SMatrix<f64, N, N>, SVector<f64, N>)>;

    /// The cost at `x`; `None` where it is undefined or `x` is not admissible (a step
    /// there is refused like one that increases the cost).
    fn cost(&self, x: &Self::Point) -> Option<f64>;

    /// `x` moved by `step` (on the manifold: a pose is perturbed, a vector added).
    fn retract(&self, x: &Self::Point, step: &SVector<f64, N>) -> Self::Point;

    /// Whether an accepted `step` ends the fit by the problem's own measure (a corner
    /// that moved less than its settling size, say). Never, unless said.
    fn settled(&self, _step: &SVector<f64, N>) -> bool {
        false
    }
}

/// The driver's damping and stopping rules.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rules {
    pub max_iterations: usize,
    /// Damping increases tried in one iteration before the fit gives up.
    pub tries: usize,
    pub initial_lambda: f64,
    /// λ is multiplied by `raise` after a refused step and by `lower` (floored at
    /// `min_lambda`) after an accepted one.
    pub raise: f64,
    pub lower: f64,
    pub min_lambda: f64,
    /// The fit has converged when an accepted step lowers the cost by less than this
    /// fraction of it, or is shorter (Euclidean norm) than `min_step`.
    pub rel_decrease: f64,
    pub min_step: f64,
    /// Floor of a diagonal entry of `JᵀJ` under the damping.
    pub diagonal_floor: f64,
}

impl Default for Rules {
    fn default() -> Self {
        Rules {
            max_iterations: 50,
            tries: 10,
            initial_lambda: 1e-3,
            raise: 4.0,
            lower: 1.0 / 3.0,
            min_lambda: 1e-12,
            rel_decrease: 1e-14,
            min_step: 1e-14,
            diagonal_floor: 1e-12,
        }
    }
}

/// How a fit ended.
#[derive(Clone, Debug, PartialEq)]
pub struct Fit<P> {
    pub point: P,
    pub cost: f64,
    /// Accepted steps.
    pub iterations: usize,
    /// Ended by a stopping rule (not by the iteration limit, a refused step at every
    /// damping tried, or normal equations that could not be formed).
    pub converged: bool,
}

/// Minimise `problem` from `init`. `None` when the cost is undefined at `init`.
pub fn minimize<const N: usize, P: LeastSquares<N>>(
    problem: &P,
    init: P::Point,
    rules: &Rules,
) -> Option<Fit<P::Point>> {
    let mut cost = problem.cost(&init)?;
    let mut fit = Fit {
        point: init,
        cost,
        iterations: 0,
        converged: false,
    };
    let mut lambda = rules.initial_lambda;
    for _ in 0..rules.max_iterations {
        let Some((h, g)) = problem.linearize(&fit.point) else {
            return Some(fit);
        };
        // At an exact minimum no step lowers the cost: that is convergence, not failure.
        if cost == 0.0 || g.iter().all(|v| *v == 0.0) {
            fit.converged = true;
            return Some(fit);
        }
        let mut accepted = false;
        for _ in 0..rules.tries {
            let mut damped = h;
            for i in 0..N {
                damped[(i, i)] += lambda * h[(i, i)].max(rules.diagonal_floor);
            }
            // A normal matrix that is not positive definite at this damping: damp more.
            let Some(step) = damped.cholesky().map(|ch| ch.solve(&(-g))) else {
                lambda *= rules.raise;
                continue;
            };
            let cand = problem.retract(&fit.point, &step);
            match problem.cost(&cand).filter(|&c| c < cost) {
                Some(c) => {
                    let done = cost - c < rules.rel_decrease * cost.max(1e-30)
                        || step.norm() < rules.min_step
                        || problem.settled(&step);
                    fit.point = cand;
                    fit.cost = c;
                    fit.iterations += 1;
                    cost = c;
                    lambda = (lambda * rules.lower).max(rules.min_lambda);
                    if done {
                        fit.converged = true;
                        return Some(fit);
                    }
                    accepted = true;
                    break;
                }
                None => lambda *= rules.raise,
            }
        }
        if !accepted {
            return Some(fit);
        }
    }
    Some(fit)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix2, Vector2};

    /// Rosenbrock as least squares: r = (10 (y − x²), 1 − x).
    struct Rosenbrock;

    impl LeastSquares<2> for Rosenbrock {
        type Point = Vector2<f64>;
        fn linearize(&self, p: &Vector2<f64>) -> Option<(Matrix2<f64>, Vector2<f64>)> {
            let r = Vector2::new(10.0 * (p.y - p.x * p.x), 1.0 - p.x);
            let j = Matrix2::new(-20.0 * p.x, 10.0, -1.0, 0.0);
            Some((j.transpose() * j, j.transpose() * r))
        }
        fn cost(&self, p: &Vector2<f64>) -> Option<f64> {
            Some((10.0 * (p.y - p.x * p.x)).powi(2) + (1.0 - p.x).powi(2))
        }
        fn retract(&self, p: &Vector2<f64>, s: &Vector2<f64>) -> Vector2<f64> {
            p + s
        }
    }

    #[test]
    fn finds_the_minimum_of_a_curved_valley_exactly() {
        let fit = minimize(&Rosenbrock, Vector2::new(-1.2, 1.0), &Rules::default()).unwrap();
        assert!(fit.converged, "{fit:?}");
        assert!(
            (fit.point - Vector2::new(1.0, 1.0)).norm() < 1e-9,
            "{fit:?}"
        );
        assert!(fit.cost < 1e-20);
    }

    /// A line fit to noisy points: the fit is the linear least-squares solution.
    struct Line(Vec<(f64, f64)>);

    impl LeastSquares<2> for Line {
        type Point = Vector2<f64>;
        fn linearize(&self, p: &Vector2<f64>) -> Option<(Matrix2<f64>, Vector2<f64>)> {
            let mut h = Matrix2::zeros();
            let mut g = Vector2::zeros();
            for (x, y) in &self.0 {
                let j = Vector2::new(*x, 1.0);
                h += j * j.transpose();
                g += j * (p.x * x + p.y - y);
            }
            Some((h, g))
        }
        fn cost(&self, p: &Vector2<f64>) -> Option<f64> {
            Some(
                self.0
                    .iter()
                    .map(|(x, y)| (p.x * x + p.y - y).powi(2))
                    .sum(),
            )
        }
        fn retract(&self, p: &Vector2<f64>, s: &Vector2<f64>) -> Vector2<f64> {
            p + s
        }
    }

    #[test]
    fn a_linear_problem_reaches_its_normal_equations_solution() {
        // Deterministic "noise" so the solution is known from the normal equations.
        let pts: Vec<(f64, f64)> = (0..20)
            .map(|i| {
                let x = i as f64 * 0.5;
                (
                    x,
                    2.0 * x - 1.0 + 0.1 * ((i * 7919 % 13) as f64 / 13.0 - 0.5),
                )
            })
            .collect();
        let line = Line(pts);
        let (h, g) = line.linearize(&Vector2::zeros()).unwrap();
        let exact = -h.cholesky().unwrap().solve(&g);
        let fit = minimize(&line, Vector2::new(5.0, 5.0), &Rules::default()).unwrap();
        assert!((fit.point - exact).norm() < 1e-10, "{fit:?} vs {exact}");
        assert!((fit.point - Vector2::new(2.0, -1.0)).norm() < 0.05);
    }

    /// Points where the cost is undefined are refused like worse ones; the fit stays in
    /// the admissible region and still reaches the constrained problem's minimum.
    struct Bounded;

    impl LeastSquares<1> for Bounded {
        type Point = f64;
        fn linearize(&self, x: &f64) -> Option<(SMatrix<f64, 1, 1>, SVector<f64, 1>)> {
            // r = x − 3
            Some((SMatrix::identity(), SVector::from([x - 3.0])))
        }
        fn cost(&self, x: &f64) -> Option<f64> {
            (*x < 2.0).then(|| (x - 3.0).powi(2))
        }
        fn retract(&self, x: &f64, s: &SVector<f64, 1>) -> f64 {
            x + s[0]
        }
    }

    #[test]
    fn inadmissible_points_are_refused() {
        let fit = minimize(&Bounded, 0.0, &Rules::default()).unwrap();
        assert!(fit.point < 2.0 && fit.point > 1.99, "{fit:?}");
        assert!(minimize(&Bounded, 2.5, &Rules::default()).is_none());
    }
}
