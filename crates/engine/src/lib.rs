//! The engine: a session in, a result document out (detection, the method's stages,
//! diagnostics), and the result written in the formats other tools read.

pub mod export;
pub mod pipeline;
