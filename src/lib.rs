//! rigcal: extrinsic calibration of multi-camera rigs with non-overlapping fields of view.
//!
//! Layers (data flows one way): `pipeline → calib → geometry, solver`; the numerical
//! core does no I/O. See `docs/architecture.md`.

pub mod geometry;
pub mod session;
pub mod solver;
pub mod calib;
pub mod synth;
pub mod result;
pub mod pipeline;
pub mod export;
