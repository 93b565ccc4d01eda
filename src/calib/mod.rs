//! Calibration estimators. Each file one estimator, tested beside it.

pub mod pnp;
pub mod twoview;
