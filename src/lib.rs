//! rigcal: extrinsic calibration of multi-camera rigs with non-overlapping fields of view.
//!
//! Layers (data flows one way): `pipeline → calib → geometry, solver`; the numerical
//! core does no I/O. See `docs/architecture.md`.

// Index loops mirror the matrix formulas of the papers (rows, blocks, Kronecker terms);
// iterator chains would hide which index is which.
#![allow(clippy::needless_range_loop)]

pub mod bench;
pub mod calib;
pub mod export;
pub mod geometry;
pub mod pipeline;
pub mod result;
pub mod session;
pub mod solver;
pub mod synth;
