//! The one Levenberg–Marquardt driver of every estimator (a pose, an edge profile, a
//! whole tag, the vanishing ring bundle, the rig bundle): one place for the damping, the
//! step acceptance and the stopping rules, so a fix to any of them reaches every fit.
//! As Ceres and COLMAP's `optim/` separate them, the problem supplies the residual side
//! (its linearisation, its cost, and how a step moves a point on its manifold), its
//! linearisation supplies the linear solve (dense Cholesky for the small fits, the Schur
//! complement of the rig bundle), and the driver the iteration.
//!
//! Damping scales the normal matrix's diagonal, `λ·max(Hᵢᵢ, floor)` (Marquardt's; the
//! floor gives a parameter the data does not yet constrain a bounded step). It is
//! updated either by fixed factors ([`Damping::Marquardt`]) or from the gain ratio of
//! the actual to the predicted decrease ([`Damping::Nielsen`]).

use nalgebra::allocator::Allocator;
use nalgebra::{DefaultAllocator, Dim, OMatrix, OVector};
use std::fmt;

/// A linearisation of a least-squares problem at a point: its normal equations, and the
/// damped linear solve that turns them into a step.
pub trait NormalEquations {
    type Step;

    /// The cost at the point as these equations weigh it, when that differs from
    /// [`LeastSquares::cost`] there (a problem reweighted at each linearisation);
    /// `None`: the same.
    fn cost(&self) -> Option<f64> {
        None
    }

    /// The largest absolute component of the gradient `Jᵀr`.
    fn gradient_max(&self) -> f64;

    /// The step `δ` solving `(H + λ·D) δ = −g`, `D = diag(max(Hᵢᵢ, floor))`; `None` when
    /// the damped matrix is not positive definite.
    fn solve_damped(&self, lambda: f64, floor: f64) -> Option<Self::Step>;

    /// The decrease of the damped quadratic model along `step`, `½ δᵀ(λ·D·δ − g)`.
    fn predicted_decrease(&self, step: &Self::Step, lambda: f64, floor: f64) -> f64;

    /// The Euclidean norm of a step.
    fn step_norm(step: &Self::Step) -> f64;
}

/// The step type of a problem.
pub type StepOf<P> = <<P as LeastSquares>::Normal as NormalEquations>::Step;

/// A nonlinear least-squares problem.
pub trait LeastSquares {
    /// A point of the problem's parameter space (a pose, a parameter vector, a rig).
    type Point: Clone;
    type Normal: NormalEquations;

    /// The normal equations at `x`, weights and robust loss applied; `None` when they
    /// cannot be formed there (a step to `x` is then refused).
    fn linearize(&mut self, x: &Self::Point) -> Option<Self::Normal>;

    /// The cost at `x`; `None` where it is undefined or `x` is not admissible (a step
    /// there is refused like one that increases the cost).
    fn cost(&mut self, x: &Self::Point) -> Option<f64>;

    /// `x` moved by `step` (on the manifold: a pose is perturbed, a vector added).
    fn retract(&self, x: &Self::Point, step: &StepOf<Self>) -> Self::Point;

    /// Whether an accepted `step`, which led to `x`, ends the fit by the problem's own
    /// measure (a corner that moved less than its settling size, a step small against
    /// the parameters). Never, unless said.
    fn settled(&self, _x: &Self::Point, _step: &StepOf<Self>) -> bool {
        false
    }

    /// Whether every point of finite cost can be linearised, with the cost its
    /// linearisation reports equal to [`cost`](Self::cost)'s. Then a step whose small
    /// decrease ends the fit is taken without linearising where it leads (for the rig
    /// bundle that last linearisation was a sixth of the solve). Not unless said.
    fn linearizable_where_finite(&self) -> bool {
        false
    }

    /// Whether `step`, solved at damping `lambda`, is small enough to be taken on the
    /// word of the quadratic model without evaluating the cost there; it ends the fit.
    /// Never, unless said (a whole-tag fit skips its last model evaluation so).
    fn trusted(&self, _step: &StepOf<Self>, _lambda: f64) -> bool {
        false
    }
}

/// How the damping follows the steps.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Damping {
    /// λ multiplied by `raise` after a refused step and by `lower` (floored at
    /// `min_lambda`) after an accepted one.
    Marquardt {
        raise: f64,
        lower: f64,
        min_lambda: f64,
    },
    /// Nielsen's update from the gain ratio ρ of actual to predicted decrease: after an
    /// accepted step λ·max(⅓, 1 − (2ρ − 1)³), after a refused one λ·ν with ν doubling.
    /// The problem's cost must then be `½Σρ(r²)`, the scale of the predicted decrease.
    Nielsen,
}

/// The driver's damping and stopping rules.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rules {
    /// Linear solves tried, accepted or not (as Ceres counts iterations).
    pub max_iterations: usize,
    pub damping: Damping,
    pub initial_lambda: f64,
    /// Floor of a diagonal entry of `H` under the damping.
    pub diagonal_floor: f64,
    /// Refused steps in a row after which no step lowers the cost (converged).
    pub tries: usize,
    /// Damping above which no step lowers the cost (converged) or, when the damped
    /// matrix is still not positive definite, the system is singular (not converged).
    pub max_lambda: f64,
    /// Converged when an accepted step lowers the cost by at most this fraction of it.
    pub function_tolerance: f64,
    /// Converged when an accepted step is shorter (Euclidean norm) than this.
    pub min_step: f64,
    /// Converged (stationary) when `max |g| ≤ gradient_tolerance · (1 + cost)`.
    pub gradient_tolerance: f64,
    /// At the iteration limit, converged when the last accepted step lowered the cost
    /// by less than this fraction (still creeping along a flat direction, as Ceres
    /// judges); 0 makes the limit a failure.
    pub creep_tolerance: f64,
}

impl Default for Rules {
    fn default() -> Self {
        Rules {
            max_iterations: 100,
            damping: Damping::Marquardt {
                raise: 4.0,
                lower: 1.0 / 3.0,
                min_lambda: 1e-12,
            },
            initial_lambda: 1e-3,
            diagonal_floor: 1e-12,
            tries: 10,
            max_lambda: 1e20,
            function_tolerance: 1e-14,
            min_step: 1e-14,
            gradient_tolerance: 0.0,
            creep_tolerance: 0.0,
        }
    }
}

/// Why a fit ended.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Termination {
    /// The gradient vanished (an exact minimum, or one within the gradient tolerance).
    Stationary,
    /// An accepted step lowered the cost by less than the function tolerance.
    SmallDecrease,
    /// An accepted step was below the step tolerance or the problem's settling size.
    SmallStep,
    /// No step at any damping tried lowers the cost: a minimum to machine precision.
    NoDecrease,
    /// The damped normal matrix stayed singular up to the largest damping.
    Singular,
    /// The normal equations could not be formed at the starting point.
    NotLinearizable,
    /// The iteration limit, with the last accepted step's relative decrease.
    IterationLimit { last_relative_decrease: f64 },
}

impl fmt::Display for Termination {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Termination::Stationary => write!(f, "gradient below tolerance"),
            Termination::SmallDecrease => write!(f, "cost decrease below tolerance"),
            Termination::SmallStep => write!(f, "step below tolerance"),
            Termination::NoDecrease => write!(f, "no further decrease possible"),
            Termination::Singular => write!(f, "damping exhausted (singular system)"),
            Termination::NotLinearizable => {
                write!(f, "normal equations undefined at the starting point")
            }
            Termination::IterationLimit {
                last_relative_decrease,
            } => write!(
                f,
                "iteration limit reached (last relative decrease {last_relative_decrease:.1e})"
            ),
        }
    }
}

/// How a fit ended.
#[derive(Clone, Debug, PartialEq)]
pub struct Fit<P> {
    pub point: P,
    pub initial_cost: f64,
    pub cost: f64,
    /// Linear solves tried (accepted or not).
    pub iterations: usize,
    /// Steps accepted.
    pub accepted: usize,
    pub termination: Termination,
    /// Ended at a minimum by a stopping rule (or creeping along a flat direction at
    /// the iteration limit, see [`Rules::creep_tolerance`]).
    pub converged: bool,
}

/// Minimise `problem` from `init`. `None` when the cost is undefined at `init`.
pub fn minimize<P: LeastSquares>(
    problem: &mut P,
    init: P::Point,
    rules: &Rules,
) -> Option<Fit<P::Point>> {
    let start_cost = problem.cost(&init)?;
    let mut fit = Fit {
        point: init,
        initial_cost: start_cost,
        cost: start_cost,
        iterations: 0,
        accepted: 0,
        termination: Termination::NotLinearizable,
        converged: false,
    };
    let Some(mut normal) = problem.linearize(&fit.point) else {
        return Some(fit);
    };
    fit.cost = normal.cost().unwrap_or(start_cost);
    fit.initial_cost = fit.cost;
    let mut damping = DampingState::new(rules);
    let mut last_relative_decrease = f64::INFINITY;
    let end = |fit: &mut Fit<P::Point>, t: Termination, converged: bool| {
        fit.termination = t;
        fit.converged = converged;
    };
    for it in 0..rules.max_iterations {
        fit.iterations = it + 1;
        // At an exact minimum no step lowers the cost: that is convergence, not failure.
        let gmax = normal.gradient_max();
        if fit.cost == 0.0 || gmax <= rules.gradient_tolerance * (1.0 + fit.cost) {
            end(&mut fit, Termination::Stationary, true);
            return Some(fit);
        }
        let lambda = damping.lambda;
        let Some(step) = normal.solve_damped(lambda, rules.diagonal_floor) else {
            // Not positive definite at this damping: damp more.
            if damping.refuse(rules) {
                end(&mut fit, Termination::Singular, false);
                return Some(fit);
            }
            continue;
        };
        if problem.trusted(&step, lambda) {
            fit.point = problem.retract(&fit.point, &step);
            fit.accepted += 1;
            end(&mut fit, Termination::SmallStep, true);
            return Some(fit);
        }
        let candidate = problem.retract(&fit.point, &step);
        let decrease = problem
            .cost(&candidate)
            .filter(|c| c.is_finite())
            .map_or(f64::NEG_INFINITY, |c| fit.cost - c);
        let predicted = match rules.damping {
            Damping::Nielsen => normal.predicted_decrease(&step, lambda, rules.diagonal_floor),
            Damping::Marquardt { .. } => f64::NAN,
        };
        let gain = decrease / predicted.max(1e-300);
        if decrease > 0.0 && problem.linearizable_where_finite() {
            let new_cost = fit.cost - decrease;
            if decrease <= rules.function_tolerance * new_cost.max(1e-300) || new_cost < 1e-24 {
                fit.point = candidate;
                fit.accepted += 1;
                fit.cost = new_cost;
                end(&mut fit, Termination::SmallDecrease, true);
                return Some(fit);
            }
        }
        // Linearise at the candidate before accepting it: a point that evaluates but
        // cannot be linearised (on the edge of a camera's depth range) is refused.
        let accepted = if decrease > 0.0 {
            problem.linearize(&candidate)
        } else {
            None
        };
        let Some(next) = accepted else {
            if damping.refuse(rules) {
                end(&mut fit, Termination::NoDecrease, true);
                return Some(fit);
            }
            continue;
        };
        let new_cost = fit.cost - decrease;
        last_relative_decrease = decrease / fit.cost.max(1e-300);
        fit.point = candidate;
        fit.accepted += 1;
        normal = next;
        fit.cost = normal.cost().unwrap_or(new_cost);
        damping.accept(rules, gain);
        if decrease <= rules.function_tolerance * fit.cost.max(1e-300) || fit.cost < 1e-24 {
            end(&mut fit, Termination::SmallDecrease, true);
            return Some(fit);
        }
        if P::Normal::step_norm(&step) < rules.min_step || problem.settled(&fit.point, &step) {
            end(&mut fit, Termination::SmallStep, true);
            return Some(fit);
        }
    }
    end(
        &mut fit,
        Termination::IterationLimit {
            last_relative_decrease,
        },
        last_relative_decrease < rules.creep_tolerance,
    );
    Some(fit)
}

/// λ (and Nielsen's ν) with the count of refused steps in a row.
struct DampingState {
    lambda: f64,
    nu: f64,
    refused: usize,
}

impl DampingState {
    fn new(rules: &Rules) -> Self {
        DampingState {
            lambda: rules.initial_lambda,
            nu: 2.0,
            refused: 0,
        }
    }

    /// Damp more after a refused step; `true` when the damping is exhausted.
    fn refuse(&mut self, rules: &Rules) -> bool {
        match rules.damping {
            Damping::Marquardt { raise, .. } => self.lambda *= raise,
            Damping::Nielsen => {
                self.lambda *= self.nu;
                self.nu *= 2.0;
            }
        }
        self.refused += 1;
        self.lambda > rules.max_lambda || self.refused >= rules.tries
    }

    /// Damp less after an accepted step of gain ratio `gain`.
    fn accept(&mut self, rules: &Rules, gain: f64) {
        match rules.damping {
            Damping::Marquardt {
                lower, min_lambda, ..
            } => self.lambda = (self.lambda * lower).max(min_lambda),
            Damping::Nielsen => {
                self.lambda *= f64::max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0).powi(3));
                self.nu = 2.0;
            }
        }
        self.refused = 0;
    }
}

/// Dense normal equations `(JᵀJ, Jᵀr)` of any size (fixed, `U6`, or dynamic, `Dyn`),
/// solved by Cholesky.
#[derive(Clone, Debug)]
pub struct Dense<D: Dim>
where
    DefaultAllocator: Allocator<D, D> + Allocator<D>,
{
    pub h: OMatrix<f64, D, D>,
    pub g: OVector<f64, D>,
    /// See [`NormalEquations::cost`].
    pub cost: Option<f64>,
}

impl<D: Dim> Dense<D>
where
    DefaultAllocator: Allocator<D, D> + Allocator<D>,
{
    pub fn new(h: OMatrix<f64, D, D>, g: OVector<f64, D>) -> Self {
        Dense { h, g, cost: None }
    }

    fn scale(&self, i: usize, floor: f64) -> f64 {
        self.h[(i, i)].max(floor)
    }
}

impl<D: Dim> NormalEquations for Dense<D>
where
    DefaultAllocator: Allocator<D, D> + Allocator<D>,
{
    type Step = OVector<f64, D>;

    fn cost(&self) -> Option<f64> {
        self.cost
    }

    fn gradient_max(&self) -> f64 {
        self.g.amax()
    }

    fn solve_damped(&self, lambda: f64, floor: f64) -> Option<Self::Step> {
        let mut a = self.h.clone();
        for i in 0..a.nrows() {
            a[(i, i)] += lambda * self.scale(i, floor);
        }
        let step = a.cholesky()?.solve(&self.g);
        Some(-step)
    }

    fn predicted_decrease(&self, step: &Self::Step, lambda: f64, floor: f64) -> f64 {
        0.5 * (0..step.len())
            .map(|i| step[i] * (lambda * self.scale(i, floor) * step[i] - self.g[i]))
            .sum::<f64>()
    }

    fn step_norm(step: &Self::Step) -> f64 {
        step.norm()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, DVector, Dyn, Matrix2, Vector2, U1, U2};

    /// Rosenbrock as least squares: r = (10 (y − x²), 1 − x).
    struct Rosenbrock;

    impl LeastSquares for Rosenbrock {
        type Point = Vector2<f64>;
        type Normal = Dense<U2>;
        fn linearize(&mut self, p: &Vector2<f64>) -> Option<Dense<U2>> {
            let r = Vector2::new(10.0 * (p.y - p.x * p.x), 1.0 - p.x);
            let j = Matrix2::new(-20.0 * p.x, 10.0, -1.0, 0.0);
            Some(Dense::new(j.transpose() * j, j.transpose() * r))
        }
        fn cost(&mut self, p: &Vector2<f64>) -> Option<f64> {
            Some((10.0 * (p.y - p.x * p.x)).powi(2) + (1.0 - p.x).powi(2))
        }
        fn retract(&self, p: &Vector2<f64>, s: &Vector2<f64>) -> Vector2<f64> {
            p + s
        }
    }

    #[test]
    fn finds_the_minimum_of_a_curved_valley_exactly_under_either_damping() {
        let nielsen = Rules {
            damping: Damping::Nielsen,
            tries: usize::MAX,
            ..Rules::default()
        };
        for rules in [Rules::default(), nielsen] {
            let fit = minimize(&mut Rosenbrock, Vector2::new(-1.2, 1.0), &rules).unwrap();
            assert!(fit.converged, "{fit:?}");
            assert!(
                (fit.point - Vector2::new(1.0, 1.0)).norm() < 1e-9,
                "{fit:?}"
            );
            assert!(fit.cost < 1e-20);
            assert!(fit.accepted <= fit.iterations && fit.accepted > 0);
            assert!((fit.initial_cost - 24.2).abs() < 1e-12, "{fit:?}");
        }
    }

    /// A line fit to points, with its unknowns as a dynamic-size vector: the fit is the
    /// linear least-squares solution.
    struct Line(Vec<(f64, f64)>);

    impl Line {
        fn residuals(&self, p: &DVector<f64>) -> Vec<f64> {
            self.0.iter().map(|(x, y)| p[0] * x + p[1] - y).collect()
        }
    }

    impl LeastSquares for Line {
        type Point = DVector<f64>;
        type Normal = Dense<Dyn>;
        fn linearize(&mut self, p: &DVector<f64>) -> Option<Dense<Dyn>> {
            let j = DMatrix::from_fn(self.0.len(), 2, |i, k| [self.0[i].0, 1.0][k]);
            let r = DVector::from_vec(self.residuals(p));
            Some(Dense::new(j.transpose() * &j, j.transpose() * r))
        }
        fn cost(&mut self, p: &DVector<f64>) -> Option<f64> {
            Some(self.residuals(p).iter().map(|r| r * r).sum())
        }
        fn retract(&self, p: &DVector<f64>, s: &DVector<f64>) -> DVector<f64> {
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
        let mut line = Line(pts);
        let n = line.linearize(&DVector::zeros(2)).unwrap();
        let exact = -n.h.cholesky().unwrap().solve(&n.g);
        let fit = minimize(
            &mut line,
            DVector::from_vec(vec![5.0, 5.0]),
            &Rules::default(),
        )
        .unwrap();
        assert!(fit.converged, "{fit:?}");
        assert!((&fit.point - &exact).norm() < 1e-10, "{fit:?} vs {exact}");
        assert!((fit.point - DVector::from_vec(vec![2.0, -1.0])).norm() < 0.05);
    }

    /// A problem that says every finite point is linearisable is not linearised where
    /// its last (small-decrease) step leads; the fit is otherwise the same.
    #[test]
    fn a_fit_ending_on_a_small_decrease_skips_its_last_linearisation_when_allowed() {
        struct Counted {
            line: Line,
            finite_is_linearizable: bool,
            linearizations: usize,
        }
        impl LeastSquares for Counted {
            type Point = DVector<f64>;
            type Normal = Dense<Dyn>;
            fn linearize(&mut self, p: &DVector<f64>) -> Option<Dense<Dyn>> {
                self.linearizations += 1;
                self.line.linearize(p)
            }
            fn cost(&mut self, p: &DVector<f64>) -> Option<f64> {
                self.line.cost(p)
            }
            fn retract(&self, p: &DVector<f64>, s: &DVector<f64>) -> DVector<f64> {
                p + s
            }
            fn linearizable_where_finite(&self) -> bool {
                self.finite_is_linearizable
            }
        }
        let pts = vec![(0.0, 1.0), (1.0, 2.5), (2.0, 3.5), (3.0, 5.5), (4.0, 6.9)];
        let fits: Vec<_> = [false, true]
            .into_iter()
            .map(|finite_is_linearizable| {
                let mut p = Counted {
                    line: Line(pts.clone()),
                    finite_is_linearizable,
                    linearizations: 0,
                };
                let fit =
                    minimize(&mut p, DVector::from_vec(vec![5.0, 5.0]), &Rules::default()).unwrap();
                (fit, p.linearizations)
            })
            .collect();
        let ((full, n_full), (short, n_short)) = (&fits[0], &fits[1]);
        assert_eq!(full.termination, Termination::SmallDecrease, "{full:?}");
        assert_eq!(short.termination, Termination::SmallDecrease, "{short:?}");
        assert_eq!(full.point, short.point);
        assert_eq!(full.iterations, short.iterations);
        assert!((full.cost - short.cost).abs() <= 1e-12 * full.cost);
        assert_eq!(*n_short + 1, *n_full);
    }

    /// The predicted decrease is the damped model's: for a quadratic cost and no
    /// damping it equals the actual decrease of the Gauss–Newton step exactly.
    #[test]
    fn the_predicted_decrease_of_an_undamped_step_on_a_quadratic_is_exact() {
        let mut line = Line(vec![(0.0, 1.0), (1.0, 2.5), (2.0, 3.5), (3.0, 5.5)]);
        let x = DVector::from_vec(vec![0.3, -0.2]);
        let n = line.linearize(&x).unwrap();
        let step = n.solve_damped(0.0, 0.0).unwrap();
        // The cost here is Σr², twice the ½Σr² the model is written for.
        let actual = 0.5 * (line.cost(&x).unwrap() - line.cost(&(&x + &step)).unwrap());
        let predicted = n.predicted_decrease(&step, 0.0, 0.0);
        assert!(
            (actual - predicted).abs() < 1e-12,
            "{actual} vs {predicted}"
        );
    }

    /// Points where the cost is undefined are refused like worse ones; the fit stays in
    /// the admissible region and still reaches the constrained problem's minimum.
    struct Bounded;

    impl LeastSquares for Bounded {
        type Point = f64;
        type Normal = Dense<U1>;
        fn linearize(&mut self, x: &f64) -> Option<Dense<U1>> {
            // r = x − 3
            Some(Dense::new(
                nalgebra::Matrix1::identity(),
                nalgebra::Vector1::new(x - 3.0),
            ))
        }
        fn cost(&mut self, x: &f64) -> Option<f64> {
            (*x < 2.0).then(|| (x - 3.0).powi(2))
        }
        fn retract(&self, x: &f64, s: &nalgebra::Vector1<f64>) -> f64 {
            x + s[0]
        }
    }

    #[test]
    fn inadmissible_points_are_refused() {
        let fit = minimize(&mut Bounded, 0.0, &Rules::default()).unwrap();
        assert!(fit.point < 2.0 && fit.point > 1.99, "{fit:?}");
        assert!(minimize(&mut Bounded, 2.5, &Rules::default()).is_none());
    }

    /// A singular problem (two parameters, one residual, no floor under the damping)
    /// ends `Singular`, not converged; the iteration limit ends unconverged unless the
    /// fit was only creeping.
    #[test]
    fn a_singular_system_and_the_iteration_limit_are_reported() {
        struct Flat;
        impl LeastSquares for Flat {
            type Point = Vector2<f64>;
            type Normal = Dense<U2>;
            fn linearize(&mut self, _: &Vector2<f64>) -> Option<Dense<U2>> {
                Some(Dense::new(Matrix2::zeros(), Vector2::new(1.0, 0.0)))
            }
            fn cost(&mut self, p: &Vector2<f64>) -> Option<f64> {
                Some(1.0 + p.x)
            }
            fn retract(&self, p: &Vector2<f64>, s: &Vector2<f64>) -> Vector2<f64> {
                p + s
            }
        }
        let rules = Rules {
            diagonal_floor: 0.0,
            ..Rules::default()
        };
        let fit = minimize(&mut Flat, Vector2::zeros(), &rules).unwrap();
        assert_eq!(fit.termination, Termination::Singular);
        assert!(!fit.converged);
        assert_eq!(fit.point, Vector2::zeros());

        let short = Rules {
            max_iterations: 3,
            ..Rules::default()
        };
        let fit = minimize(&mut Rosenbrock, Vector2::new(-1.2, 1.0), &short).unwrap();
        assert!(
            matches!(fit.termination, Termination::IterationLimit { .. }),
            "{fit:?}"
        );
        assert!(!fit.converged);
        assert_eq!(fit.iterations, 3);
        assert!(fit
            .termination
            .to_string()
            .starts_with("iteration limit reached"));
    }
}
