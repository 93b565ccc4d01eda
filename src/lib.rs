//! rigcal: extrinsic calibration of multi-camera rigs with non-overlapping fields of view.
//!
//! Layers (data flows one way): `api → jobs → pipeline → calib → geometry, solver`,
//! with `store` under `api` and `jobs`; the numerical core does no I/O. See `docs/architecture.md`.

// Index loops mirror the matrix formulas of the papers (rows, blocks, Kronecker terms);
// iterator chains would hide which index is which.
#![allow(clippy::needless_range_loop)]

pub mod api;
pub mod bench;
pub mod calib;
pub mod dashboard;
pub mod demo;
pub mod detect;
pub mod export;
pub mod geometry;
pub mod imageio;
pub mod jobs;
pub mod linalg;
pub mod pipeline;
pub mod result;
pub mod session;
pub mod signals;
pub mod solver;
pub mod store;
pub mod synth;
pub mod target;
pub mod telemetry;
