//! The capture check: a cheap look at a session's detections before the full solve,
//! so an operator at the line learns in seconds that a capture must be redone.
//!
//! It reconstructs the per-camera trajectories (the first stage of the solve), classifies
//! the rig motion from the reference camera, and predicts the observable DOF per camera
//! from the motion class and the scene sharing (Lébraly Table 1, extended to chains of
//! shared scenes). The prediction is a rule; the full solve measures observability
//! numerically and may find less (e.g. noise), never more.

use super::motion::{classify, MotionClass, MotionReport};
use super::trajectory::{self, Trajectories};
use super::verdict::{motion_findings, planar_recommendation};
use rigcal_core::result::{ObservableDof, Reason};
use rigcal_core::session::undetected_images;
use rigcal_core::session::Session;
use rigcal_core::verdict::{worst, ReasonCode, Severity};
use rigcal_solve::bundle::LmOptions;
use serde::Serialize;
use std::collections::BTreeSet;
use std::time::Instant;

#[derive(Clone, Debug, Serialize)]
pub struct CameraCoverage {
    pub camera: String,
    /// Frames in which the camera has at least 4 observations.
    pub frames_seen: usize,
    /// Distinct points it observed.
    pub points_seen: usize,
    /// Observations in all frames.
    pub observations: usize,
    /// Images of this camera still waiting for detection.
    pub images_without_detections: usize,
    /// Frames in which a pose could be computed.
    pub posed_frames: usize,
    /// DOF the full solve is expected to determine (rule of Table 1).
    pub predicted_dof: ObservableDof,
}

#[derive(Clone, Debug, Serialize)]
pub struct CaptureCheck {
    /// `ok`: a full solve can determine every extrinsic; `degraded`: it will run but leave
    /// DOF undetermined; `insufficient`: it cannot succeed, re-capture.
    pub verdict: String,
    pub reasons: Vec<Reason>,
    pub recommendations: Vec<String>,
    pub cameras: Vec<CameraCoverage>,
    /// Motion of the rig as the reference camera measured it (absent without poses).
    pub motion: Option<MotionReport>,
    /// Some camera sees a scene another camera saw (U-turn, loop).
    pub scene_permutation: bool,
    pub non_planar_motion: bool,
    /// Vanishing method: whether the auxiliary views close the ring of targets.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ring_closed: Option<bool>,
    pub seconds: f64,
}

fn reason(code: ReasonCode, message: String, camera: Option<&str>) -> Reason {
    Reason::new(code, message, camera)
}

/// `insufficient` (a fatal reason, or `unusable`), `degraded` (a degrading one), `ok`.
fn verdict_of(reasons: &[Reason], unusable: bool) -> &'static str {
    match worst(reasons) {
        _ if unusable => "insufficient",
        Some(Severity::Fatal) => "insufficient",
        Some(Severity::Degrading) => "degraded",
        _ => "ok",
    }
}

/// Cameras whose height along the motion-plane normal is tied to the reference through
/// shared scenes: the reference, then every camera seeing a scene one of them saw.
fn height_connected(session: &Session, traj: &Trajectories) -> BTreeSet<usize> {
    let cams_of_scene: Vec<BTreeSet<usize>> = traj
        .scenes
        .iter()
        .map(|s| s.poses.keys().map(|(_, c)| *c).collect())
        .collect();
    let mut known = BTreeSet::from([session.reference]);
    loop {
        let before = known.len();
        for cams in &cams_of_scene {
            if cams.iter().any(|c| known.contains(c)) {
                known.extend(cams.iter().copied());
            }
        }
        if known.len() == before {
            return known;
        }
    }
}

impl CaptureCheck {
    /// The check that could not be computed for a fault of ours (`message` names the
    /// stage): `insufficient` with an `internal_error` reason, so it is reported as
    /// what it is rather than as a verdict on the capture or not at all.
    pub fn internal_error(message: String) -> CaptureCheck {
        CaptureCheck {
            verdict: "insufficient".into(),
            reasons: vec![reason(ReasonCode::InternalError, message, None)],
            recommendations: vec![
                "this is a fault of rigcal, not of the capture: report it; a job detects the images again itself".into(),
            ],
            cameras: vec![],
            motion: None,
            scene_permutation: false,
            non_planar_motion: false,
            ring_closed: None,
            seconds: 0.0,
        }
    }
}

/// Run the capture check. Never panics on input; a session without usable detections
/// gets `insufficient` with the reason.
pub fn capture_check(session: &Session) -> CaptureCheck {
    if let Some(input) = &session.vanishing {
        return ring_check(session, input);
    }
    let t0 = Instant::now();
    let nc = session.cameras.len();
    let undetected = undetected_images(session);
    let mut reasons = Vec::new();
    let mut recommendations = Vec::new();
    let mut coverage: Vec<CameraCoverage> = session
        .cameras
        .iter()
        .enumerate()
        .map(|(c, cam)| {
            let mut points = BTreeSet::new();
            let mut obs = 0;
            for f in &session.frames {
                obs += f.observations[c].len();
                points.extend(f.observations[c].iter().map(|o| o.point));
            }
            CameraCoverage {
                camera: cam.id.clone(),
                frames_seen: session
                    .frames
                    .iter()
                    .filter(|f| f.observations[c].len() >= 4)
                    .count(),
                points_seen: points.len(),
                observations: obs,
                images_without_detections: undetected
                    .iter()
                    .filter(|p| p.ends_with(&format!(".images.{}", cam.id)))
                    .count(),
                posed_frames: 0,
                predicted_dof: ObservableDof {
                    rotation: 0,
                    translation: 0,
                },
            }
        })
        .collect();
    if !undetected.is_empty() {
        reasons.push(reason(
            ReasonCode::DetectionsPending,
            format!(
                "{} image(s) have no detections yet; the check covers the detections present",
                undetected.len()
            ),
            None,
        ));
    }
    for cov in &coverage {
        if cov.frames_seen < 3 {
            reasons.push(reason(
                if cov.frames_seen == 0 {
                    ReasonCode::CameraNotObserved
                } else {
                    ReasonCode::TooFewMotions
                },
                format!(
                    "camera {} sees a target or points in {} frame(s); at least 3 are needed",
                    cov.camera, cov.frames_seen
                ),
                Some(&cov.camera),
            ));
        }
    }
    let traj = if nc >= 2 && reasons.iter().all(|r| r.is(ReasonCode::DetectionsPending)) {
        // Its only error is "no camera observes any point", which the coverage reasons
        // above already name per camera.
        trajectory::estimate(session, &LmOptions::default()).ok()
    } else {
        None
    };
    let mut motion = None;
    let mut permutation = false;
    if let Some(traj) = &traj {
        for (c, cov) in coverage.iter_mut().enumerate() {
            cov.posed_frames = traj
                .scenes
                .iter()
                .flat_map(|s| s.poses.keys())
                .filter(|(_, cc)| *cc == c)
                .map(|(f, _)| *f)
                .collect::<BTreeSet<_>>()
                .len();
        }
        permutation = traj.scenes.iter().any(|s| {
            s.poses
                .keys()
                .map(|(_, c)| *c)
                .collect::<BTreeSet<_>>()
                .len()
                > 1
        });
        let r = session.reference;
        let mut ref_motions = Vec::new();
        for s in &traj.scenes {
            let mut it = s.poses.iter().filter(|((_, c), _)| *c == r).map(|(_, p)| p);
            if let Some(p0) = it.next() {
                ref_motions.extend(it.map(|p| *p * p0.inverse()));
            }
        }
        if ref_motions.is_empty() {
            reasons.push(reason(
                ReasonCode::CameraNotObserved,
                format!(
                    "the reference camera {} has fewer than 2 posed frames",
                    session.cameras[r].id
                ),
                Some(&session.cameras[r].id),
            ));
        } else {
            let report = classify(&ref_motions);
            let heights = height_connected(session, traj);
            for (c, cov) in coverage.iter_mut().enumerate() {
                let (rot, trans) = if c == r {
                    (3, 3)
                } else if cov.posed_frames < 2 {
                    (0, 0)
                } else {
                    match report.class {
                        MotionClass::General => (3, 3),
                        MotionClass::Planar if heights.contains(&c) => (3, 3),
                        MotionClass::Planar => (3, 2),
                        MotionClass::SingleAxis => (2, 2),
                        MotionClass::PureTranslation => (3, 0),
                        MotionClass::None => (0, 0),
                    }
                };
                cov.predicted_dof = ObservableDof {
                    rotation: rot,
                    translation: trans,
                };
            }
            let found = motion_findings(&report);
            reasons.extend(found.reasons);
            recommendations.extend(found.recommendations);
            if report.class == MotionClass::Planar {
                let missing: Vec<&str> = coverage
                    .iter()
                    .filter(|c| c.predicted_dof.translation < 3 && c.posed_frames >= 2)
                    .map(|c| c.camera.as_str())
                    .collect();
                if !missing.is_empty() {
                    let cams = missing.join(", ");
                    reasons.push(reason(
                        ReasonCode::PlanarMotion,
                        format!("planar motion: the height of {cams} will not be observable"),
                        None,
                    ));
                    recommendations.push(planar_recommendation(&cams));
                }
            }
            motion = Some(report);
        }
    }
    if nc < 2 {
        reasons.push(reason(
            ReasonCode::TooFewCameras,
            "a rig calibration needs at least 2 cameras".into(),
            None,
        ));
    }
    let verdict = verdict_of(&reasons, traj.is_none() && nc >= 2 && undetected.is_empty());
    let non_planar = motion
        .as_ref()
        .is_some_and(|m| m.class == MotionClass::General);
    CaptureCheck {
        verdict: verdict.into(),
        reasons,
        recommendations,
        cameras: coverage,
        motion,
        scene_permutation: permutation,
        non_planar_motion: non_planar,
        ring_closed: None,
        seconds: t0.elapsed().as_secs_f64(),
    }
}

/// The vanishing method's check: the solve itself takes a fraction of a second, so the
/// check runs it and reports what it found (lines per camera, ring links and closure,
/// ill-conditioned vanishing points) without the extrinsics.
fn ring_check(session: &Session, input: &rigcal_core::session::VanishingInput) -> CaptureCheck {
    use super::vanishing::{solve, VanishingOptions};
    let t0 = Instant::now();
    let (solution, findings) = solve(
        session,
        &VanishingOptions {
            loss: rigcal_solve::Loss::Huber { scale: 2.0 },
            max_iterations: 50,
        },
    );
    let undetected = undetected_images(session);
    let linked: BTreeSet<String> = solution
        .iter()
        .flat_map(|s| &s.cameras)
        .map(|c| session.cameras[c.camera].id.clone())
        .collect();
    let cameras = session
        .cameras
        .iter()
        .enumerate()
        .map(|(c, cam)| {
            let lines = &input.rig[c];
            let dof = if linked.contains(&cam.id) { 3 } else { 0 };
            CameraCoverage {
                camera: cam.id.clone(),
                frames_seen: usize::from(!lines.is_empty()),
                points_seen: lines.iter().map(|l| l.points.len()).sum(),
                observations: lines.len(),
                images_without_detections: undetected
                    .iter()
                    .filter(|p| p.ends_with(&format!(".images.{}", cam.id)))
                    .count(),
                posed_frames: usize::from(dof > 0),
                predicted_dof: ObservableDof {
                    rotation: dof,
                    translation: dof,
                },
            }
        })
        .collect();
    let mut reasons: Vec<Reason> = findings.iter().map(|f| f.reason()).collect();
    let mut recommendations = Vec::new();
    if !undetected.is_empty() {
        reasons.push(reason(
            ReasonCode::DetectionsPending,
            format!("{} image(s) have no detections yet", undetected.len()),
            None,
        ));
    }
    let fatal = solution.is_none() || worst(&reasons) == Some(Severity::Fatal);
    let closed = solution.as_ref().map(|s| s.closure.is_some());
    if closed == Some(false) {
        reasons.push(reason(
            ReasonCode::RingOpen,
            "no auxiliary view closes the ring; the error of the chain will not be corrected"
                .into(),
            None,
        ));
        recommendations.push("Photograph the last neighbouring pair too (the one closing the ring) so the ring-closure optimisation can spread the chain's error.".into());
    }
    if fatal {
        recommendations.push("Give every rig camera one image of its own target and photograph every neighbouring pair of targets with the auxiliary camera (about 40° above the target plane).".into());
    }
    let verdict = verdict_of(&reasons, fatal);
    CaptureCheck {
        verdict: verdict.into(),
        reasons,
        recommendations,
        cameras,
        motion: None,
        scene_permutation: false,
        non_planar_motion: false,
        ring_closed: closed,
        seconds: t0.elapsed().as_secs_f64(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rigcal_core::session::parse_session;
    use rigcal_synth as synth;

    fn check(preset: &str) -> CaptureCheck {
        let (m, _) = synth::generate(preset, 7, 0.3).expect("preset");
        let s = parse_session(&serde_json::to_vec(&m).unwrap()).unwrap();
        capture_check(&s)
    }

    #[test]
    fn a_ring_is_checked_and_a_missing_pair_is_named() {
        let c = check("wu-table2");
        assert_eq!(c.verdict, "ok", "{:?}", c.reasons);
        assert_eq!(c.ring_closed, Some(true));
        let (mut m, _) = synth::generate("wu-table2", 7, 0.3).unwrap();
        m.ring.retain(|r| r.index != 3 && r.index != 4);
        let s = parse_session(&serde_json::to_vec(&m).unwrap()).unwrap();
        let c = capture_check(&s);
        assert_eq!(c.verdict, "insufficient");
        assert!(c
            .reasons
            .iter()
            .any(|r| r.code == "target_not_linked" && r.camera.as_deref() == Some("cam5")));
        assert_eq!(c.cameras[4].predicted_dof.rotation, 0);
    }

    #[test]
    fn general_motion_is_ok_with_full_dof() {
        let c = check("lebraly-5.1");
        assert_eq!(c.verdict, "ok", "{:?}", c.reasons);
        assert!(c.non_planar_motion);
        for cam in &c.cameras {
            assert_eq!(
                (cam.predicted_dof.rotation, cam.predicted_dof.translation),
                (3, 3)
            );
        }
    }

    #[test]
    fn planar_drive_predicts_missing_height() {
        let c = check("car-planar");
        assert_eq!(c.verdict, "degraded");
        assert!(!c.non_planar_motion);
        assert!(c.reasons.iter().any(|r| r.code == "planar_motion"));
        let missing = c
            .cameras
            .iter()
            .filter(|x| x.predicted_dof.translation == 2)
            .count();
        assert_eq!(missing, c.cameras.len() - 1);
    }

    #[test]
    fn uturn_shares_scenes_and_resolves_the_rear_height() {
        let c = check("car-planar-uturn");
        assert!(c.scene_permutation);
        let rear = c.cameras.iter().find(|x| x.camera == "rear").unwrap();
        assert_eq!(rear.predicted_dof.translation, 3);
        let left = c.cameras.iter().find(|x| x.camera == "left").unwrap();
        assert_eq!(left.predicted_dof.translation, 2);
    }
}
