//! Capture-session manifests: the wire format (`raw`), and the validated domain type
//! ([`Session`]) that every stage downstream takes. Parse once, never re-validate.

mod lines;
mod raw;
mod slots;
mod validate;

pub use lines::{line_layout, LineObs, LineTargetDef, RingView, VanishingInput};
pub use raw::*;
pub use slots::{image_slots, undetected_images, ImageSlot};
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
    /// Both parts are bounded (`bounded`): a field path can hold a map key of the
    /// input, and a message can quote a value, and neither may echo megabytes back.
    pub fn new(field: impl Into<String>, expected: impl Into<String>) -> Self {
        Self {
            field: bounded(field.into(), MAX_FIELD_LEN),
            expected: bounded(expected.into(), MAX_DETAIL_LEN),
        }
    }
}

/// Longest identifier (camera, target, vehicle, vehicle model, tenant).
pub const MAX_IDENTIFIER_LEN: usize = 64;
/// Longest point id.
pub const MAX_POINT_ID_LEN: usize = 128;

/// Identifiers — camera, target, vehicle, vehicle model, tenant — are
/// `[A-Za-z0-9][A-Za-z0-9_.-]{0,63}`. They become YAML keys (Kalibr, OpenCV), XML
/// attributes and frame names (URDF, ROS), file names (exports) and SQL values, and are
/// copied into every job row and view: a grammar with no quotes, spaces, newlines,
/// colons, slashes or angle brackets cannot break any of those formats, and a bound keeps
/// rows small. Letters, digits, `_`, `.` and `-` cover the names rigs use (`cam0`,
/// `front-left`, `board_2.5m`).
pub fn check_identifier(field: &str, value: &str) -> Result<(), InputError> {
    let ok = !value.is_empty()
        && value.len() <= MAX_IDENTIFIER_LEN
        && value.as_bytes()[0].is_ascii_alphanumeric()
        && value
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'_' | b'.' | b'-'));
    if ok {
        Ok(())
    } else {
        Err(InputError::new(
            field,
            format!(
                "an identifier: 1-{MAX_IDENTIFIER_LEN} characters of A-Z a-z 0-9 _ . -, starting with a letter or digit, got {}",
                quoted_prefix(value)
            ),
        ))
    }
}

/// Point ids (`tag:12:3`, user-chosen names) are up to 128 printable ASCII characters
/// without spaces, quotes or backslashes.
pub fn check_point_id(field: &str, value: &str) -> Result<(), InputError> {
    let ok = !value.is_empty()
        && value.len() <= MAX_POINT_ID_LEN
        && value
            .bytes()
            .all(|b| b.is_ascii_graphic() && !matches!(b, b'"' | b'\\' | b'\''));
    if ok {
        Ok(())
    } else {
        Err(InputError::new(
            field,
            format!(
                "a point id: 1-{MAX_POINT_ID_LEN} printable ASCII characters without spaces, quotes or backslashes, got {}",
                quoted_prefix(value)
            ),
        ))
    }
}

/// A value as an error message shows it: quoted, escaped, and cut after 40 characters
/// (a 20 MB id is not echoed back).
/// Longest field path an error names.
pub const MAX_FIELD_LEN: usize = 256;
/// Longest error message.
pub const MAX_DETAIL_LEN: usize = 2048;

/// `s` cut to at most `max` bytes (at a character boundary) with the original length
/// said, so that an error about a huge value stays small.
pub fn bounded(s: String, max: usize) -> String {
    if s.len() <= max {
        return s;
    }
    let mut cut = max.saturating_sub(32);
    while !s.is_char_boundary(cut) {
        cut -= 1;
    }
    format!("{}… ({} bytes)", &s[..cut], s.len())
}

pub fn quoted_prefix(value: &str) -> String {
    let mut chars = value.chars();
    let head: String = chars.by_ref().take(40).collect();
    if chars.next().is_some() {
        format!("{head:?}… ({} bytes)", value.len())
    } else {
        format!("{head:?}")
    }
}
