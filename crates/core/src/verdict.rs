//! What a finding means for the verdict: every reason code rigcal emits, its stable
//! snake_case string (the API's `reasons[].code`) and its severity, in one table. The
//! capture check, the motion method and the vanishing method all judge through
//! [`Severity`] here, so one code cannot be fatal in one of them and harmless in another.
//!
//! The wire type [`Reason`] keeps its code as a string so that documents stored by other
//! versions still load; everything rigcal writes goes through [`ReasonCode`].

use crate::result::{Reason, Status};

/// How a finding weighs on the verdict.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Severity {
    /// Said, but the result is as good as without it (outliers removed, open ring).
    Note,
    /// The result stands with something undetermined or weaker: `degraded`.
    Degrading,
    /// No result can be trusted: `failed` (`insufficient` in the capture check).
    Fatal,
}

macro_rules! reason_codes {
    ($($variant:ident = $code:literal, $severity:ident;)*) => {
        /// Every reason rigcal reports.
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
        pub enum ReasonCode {
            $($variant,)*
        }

        impl ReasonCode {
            pub const ALL: &'static [ReasonCode] = &[$(ReasonCode::$variant,)*];

            /// The code as the API writes it.
            pub const fn as_str(self) -> &'static str {
                match self {
                    $(ReasonCode::$variant => $code,)*
                }
            }

            pub const fn severity(self) -> Severity {
                match self {
                    $(ReasonCode::$variant => Severity::$severity,)*
                }
            }
        }
    };
}

reason_codes! {
    // Input and the stages before the solve.
    InternalError = "internal_error", Fatal;
    Cancelled = "cancelled", Fatal;
    InputMissing = "input_missing", Fatal;
    DetectionUnavailable = "detection_unavailable", Fatal;
    DetectionFailed = "detection_failed", Fatal;
    DetectionsPending = "detections_pending", Degrading;
    MethodNotSupported = "method_not_supported", Fatal;
    TooFewCameras = "too_few_cameras", Fatal;
    CameraNotObserved = "camera_not_observed", Fatal;
    // Motion method: what the motion determines.
    TooFewMotions = "too_few_motions", Fatal;
    PureTranslation = "pure_translation", Fatal;
    SingleAxisRotation = "single_axis_rotation", Degrading;
    PlanarMotion = "planar_motion", Degrading;
    PoorlyDetermined = "poorly_determined", Degrading;
    SceneNotReconstructed = "scene_not_reconstructed", Degrading;
    ScaleMissing = "scale_missing", Degrading;
    // Motion method: the solve.
    NoConvergence = "no_convergence", Fatal;
    InconsistentRig = "inconsistent_rig", Fatal;
    TooManyOutliers = "too_many_outliers", Fatal;
    OutliersRemoved = "outliers_removed", Note;
    // Vanishing method.
    LinesUnusable = "lines_unusable", Fatal;
    VanishingPointAtInfinity = "vanishing_point_at_infinity", Degrading;
    RingViewUnusable = "ring_view_unusable", Degrading;
    LineLabellingAmbiguous = "line_labelling_ambiguous", Degrading;
    TargetNotLinked = "target_not_linked", Fatal;
    RingBroken = "ring_broken", Fatal;
    InconsistentRing = "inconsistent_ring", Fatal;
    RingOpen = "ring_open", Note;
}

impl ReasonCode {
    /// The code of an API string, `None` for one this build does not emit.
    pub fn parse(code: &str) -> Option<ReasonCode> {
        Self::ALL.iter().copied().find(|c| c.as_str() == code)
    }
}

impl std::fmt::Display for ReasonCode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl Reason {
    pub fn new(code: ReasonCode, message: impl Into<String>, camera: Option<&str>) -> Reason {
        Reason {
            code: code.as_str().into(),
            message: message.into(),
            camera: camera.map(str::to_string),
        }
    }

    /// Its severity; a code this build does not know (a document of another version)
    /// counts as degrading: never silently harmless, never a failure we did not find.
    pub fn severity(&self) -> Severity {
        ReasonCode::parse(&self.code).map_or(Severity::Degrading, ReasonCode::severity)
    }

    pub fn is(&self, code: ReasonCode) -> bool {
        self.code == code.as_str()
    }
}

/// The worst severity among `reasons` (`None` if there are none).
pub fn worst(reasons: &[Reason]) -> Option<Severity> {
    reasons.iter().map(Reason::severity).max()
}

/// The status the reasons give: any fatal one fails, any degrading one (or
/// `undetermined`, directions the data left open) degrades.
pub fn status_of(reasons: &[Reason], undetermined: bool) -> Status {
    match worst(reasons) {
        Some(Severity::Fatal) => Status::Failed,
        Some(Severity::Degrading) => Status::Degraded,
        _ if undetermined => Status::Degraded,
        _ => Status::Succeeded,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_are_unique_snake_case_and_round_trip() {
        let mut seen = std::collections::BTreeSet::new();
        for c in ReasonCode::ALL {
            let s = c.as_str();
            assert!(seen.insert(s), "{s} twice");
            assert!(
                s.bytes().all(|b| b.is_ascii_lowercase() || b == b'_'),
                "{s}"
            );
            assert_eq!(ReasonCode::parse(s), Some(*c));
        }
        assert_eq!(ReasonCode::parse("no_such_code"), None);
    }

    #[test]
    fn status_follows_the_worst_reason() {
        let r = |c| Reason::new(c, "m", None);
        assert_eq!(status_of(&[], false), Status::Succeeded);
        assert_eq!(status_of(&[], true), Status::Degraded);
        assert_eq!(
            status_of(
                &[r(ReasonCode::OutliersRemoved), r(ReasonCode::RingOpen)],
                false
            ),
            Status::Succeeded
        );
        assert_eq!(
            status_of(
                &[r(ReasonCode::OutliersRemoved), r(ReasonCode::PlanarMotion)],
                false
            ),
            Status::Degraded
        );
        assert_eq!(
            status_of(
                &[r(ReasonCode::PlanarMotion), r(ReasonCode::NoConvergence)],
                false
            ),
            Status::Failed
        );
        let unknown = Reason {
            code: "from_a_later_version".into(),
            message: String::new(),
            camera: None,
        };
        assert_eq!(unknown.severity(), Severity::Degrading);
    }
}
