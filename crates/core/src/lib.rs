//! The types every layer of rigcal shares: geometry and camera models, the linear
//! algebra the estimators build on, what a printed target looks like, and the two
//! documents at the ends of the pipeline (the session that comes in, the result that
//! goes out). No I/O, no estimators.

pub mod geometry;
pub mod linalg;
pub mod par;
pub mod result;
pub mod session;
pub mod simd;
pub mod target;
pub mod vehicle;
pub mod verdict;
pub mod xml;
