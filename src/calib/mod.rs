//! Calibration estimators. Each file one estimator, tested beside it.

pub mod pnp;
pub mod twoview;
pub mod trajectory;
pub mod motion;
pub mod handeye;
pub mod rig_ba;
pub mod diagnostics;
