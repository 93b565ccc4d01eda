//! Measurement harnesses behind `rigcal bench`: accuracy against ground truth (with the
//! Cramér–Rao bound of the same problem), and solver speed. They print tables; the
//! numbers are recorded in `docs/accuracy.md` and `docs/performance.md`.

pub mod accuracy;
pub mod capture;
pub mod detect;
pub mod ring;
pub mod speed;
