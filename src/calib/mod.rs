//! Calibration estimators. Each file one estimator, tested beside it.

pub mod diagnostics;
pub mod handeye;
pub mod motion;
pub mod pnp;
pub mod rig_ba;
pub mod trajectory;
pub mod twoview;
