//! Nonlinear least squares: the one Levenberg–Marquardt driver of the small dense fits
//! ([`lm`]), bundle problems (LM with a Schur complement on the points and rigid
//! bodies), robust losses, and the marginal information of chosen parameter blocks (for
//! covariances and observability).

pub mod bundle;
pub mod lm;
pub mod loss;
pub mod sparse;

pub use bundle::{BundleProblem, BundleSummary, LmOptions, Obs, PointRef};
pub use loss::{median, robust_sigma, Loss};
