//! Solver speed (see docs/performance.md).
