//! Capture-session manifests: the wire format (`raw`), and the validated domain type
//! ([`Session`]) that every stage downstream takes. Parse once, never re-validate.

mod lines;
mod raw;
mod slots;
mod validate;

pub use lines::{LineObs, LineTargetDef, RingView, VanishingInput};
pub use raw::*;
pub use slots::{image_slots, ImageSlot};
pub use validate::{
    camera_from_spec, from_manifest, parse_session, resolve_points, PointKind, ResolvedPoints,
    Session,
};

/// An input error: which field, and what was expected there.
#[derive(Debug, Clone, PartialEq, thiserror::Error, serde::Serialize)]
#[error("{field}: {expected}")]
pub struct InputError {
    /// JSON path of the offending field, e.g. `frames[3].observations.rear[12].u`.
    pub field: String,
    /// What was expected, in words.
    pub expected: String,
}

impl InputError {
    pub fn new(field: impl Into<String>, expected: impl Into<String>) -> Self {
        Self {
            field: field.into(),
            expected: expected.into(),
        }
    }
}
