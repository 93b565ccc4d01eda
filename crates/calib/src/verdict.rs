//! What a measured motion means for a calibration, said once: the reasons and
//! recommendations of a motion class, for the capture check (before the solve) and the
//! motion method (after it), so the two cannot tell an operator different things about
//! the same drive. Severities are [`rigcal_core::verdict`]'s.

use crate::motion::{MotionClass, MotionReport};
use rigcal_core::result::Reason;
use rigcal_core::verdict::ReasonCode;

/// Reasons and the manoeuvres that would remove them.
#[derive(Clone, Debug, Default)]
pub struct Findings {
    pub reasons: Vec<Reason>,
    pub recommendations: Vec<String>,
}

impl Findings {
    fn push(&mut self, code: ReasonCode, message: impl Into<String>, recommendation: &str) {
        self.reasons.push(Reason::new(code, message, None));
        self.recommendations.push(recommendation.into());
    }
}

/// What the rig's motion class leaves undetermined, for every class but `general` and
/// `planar` (the planar finding names the cameras whose height is open, which the check
/// predicts and the solve measures; see [`planar_recommendation`]).
pub fn motion_findings(report: &MotionReport) -> Findings {
    let mut f = Findings::default();
    match report.class {
        MotionClass::None => f.push(
            ReasonCode::TooFewMotions,
            "the rig did not move",
            "Drive while capturing: turns (rotations about at least two different axes) and a speed bump.",
        ),
        MotionClass::PureTranslation => f.push(
            ReasonCode::PureTranslation,
            "the rig never rotated: the extrinsic translations are unobservable",
            "Turn the vehicle while capturing (rotations about at least two different axes, e.g. turns and a speed bump).",
        ),
        MotionClass::SingleAxis => f.push(
            ReasonCode::SingleAxisRotation,
            "the rig rotated about a single fixed axis: one rotation and one translation DOF per camera cannot be determined",
            "Add motion about a second axis: drive along a path (not a turn in place) and over a bump or ramp.",
        ),
        MotionClass::General | MotionClass::Planar if report.informative_motions < 2 => f.push(
            ReasonCode::TooFewMotions,
            format!(
                "only {} motion(s) rotate by more than 0.3°; at least 2 are needed",
                report.informative_motions
            ),
            "Capture more frames while turning: at least two motions that rotate the rig.",
        ),
        MotionClass::General | MotionClass::Planar => {}
    }
    f
}

/// The manoeuvre that makes the heights of `cameras` observable under planar motion.
pub fn planar_recommendation(cameras: &str) -> String {
    format!(
        "Drive over a speed bump or ramp (any non-planar motion) so the height of {cameras} becomes observable, or turn so that {cameras} see(s) the scene of a camera whose height is known (a full 360° loop shows every scene to every camera); a U-turn alone only swaps front↔rear and left↔right."
    )
}
