//! Nonlinear least squares for bundle problems: Levenberg–Marquardt with a Schur
//! complement on the points and rigid bodies, robust losses, and the marginal
//! information of chosen parameter blocks (for covariances and observability).

pub mod bundle;
pub mod loss;

pub use bundle::{BundleProblem, BundleSummary, LmOptions, Obs, PointRef};
pub use loss::{median, robust_sigma, Loss};
