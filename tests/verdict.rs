//! The capture check (before the solve) and the motion method (after it) judge a drive
//! through one verdict table: fed the same sessions, one of every motion class, they
//! name the same motion findings, and a capture the check calls `insufficient` never
//! calibrates.

use rigcal_calib::check::capture_check;
use rigcal_core::session::{parse_session, SessionManifest};
use rigcal_core::verdict::ReasonCode;
use rigcal_engine::pipeline::calibrate;
use rigcal_engine::pipeline::CalibOptions;
use std::collections::BTreeSet;

/// The findings about the motion itself (not about the solve's numerics).
const MOTION_CODES: &[ReasonCode] = &[
    ReasonCode::TooFewMotions,
    ReasonCode::PureTranslation,
    ReasonCode::SingleAxisRotation,
];

fn motion_codes(codes: impl Iterator<Item = String>) -> BTreeSet<String> {
    codes
        .filter(|c| MOTION_CODES.iter().any(|m| m.as_str() == c))
        .collect()
}

/// A rig that never moved: every frame sees what the first one saw.
fn standing_still(mut m: SessionManifest) -> SessionManifest {
    let first = m.frames[0].observations.clone();
    for f in &mut m.frames {
        f.observations = first.clone();
    }
    m
}

/// Three frames, the third back where the first was: one motion that rotates, about
/// one axis.
fn one_motion(mut m: SessionManifest) -> SessionManifest {
    m.frames.truncate(3);
    m.frames[2].observations = m.frames[0].observations.clone();
    m
}

/// The realistic hall drive as detections: AprilGrids of known layout, so every frame
/// has its poses whatever the rig did.
fn hall(seed: u64) -> SessionManifest {
    let dir = tempfile::tempdir().unwrap();
    let hall = rigcal_synth::hall::hall("car-hall", seed, None).unwrap();
    rigcal_synth::hall::write_capture(&hall, dir.path(), None, 0.2, seed).unwrap();
    serde_json::from_slice(&std::fs::read(dir.path().join("session.json")).unwrap()).unwrap()
}

#[test]
fn the_check_and_the_solve_name_the_same_motion_findings() {
    let generated = |p: &str| rigcal_synth::generate(p, 3, 0.2).unwrap().0;
    let cases: Vec<(&str, SessionManifest, &[&str])> = vec![
        ("general", generated("lebraly-5.1"), &[]),
        ("planar", generated("car-planar"), &[]),
        (
            "pure translation",
            generated("pure-translation"),
            &["pure_translation"],
        ),
        (
            "single axis",
            generated("single-axis"),
            &["single_axis_rotation"],
        ),
        ("still", standing_still(hall(3)), &["too_few_motions"]),
        ("one motion", one_motion(hall(3)), &["single_axis_rotation"]),
    ];
    for (name, manifest, expected) in cases {
        let session = parse_session(&serde_json::to_vec(&manifest).unwrap()).unwrap();
        let check = capture_check(&session);
        let doc = calibrate(&session, &CalibOptions::default());
        let from_check = motion_codes(check.reasons.iter().map(|r| r.code.clone()));
        let from_solve = motion_codes(doc.reasons.iter().map(|r| r.code.clone()));
        let expected: BTreeSet<String> = expected.iter().map(|s| s.to_string()).collect();
        assert_eq!(
            from_check, expected,
            "{name}: the check said {:?}",
            check.reasons
        );
        assert_eq!(
            from_solve, expected,
            "{name}: the solve said {:?}",
            doc.reasons
        );
        if check.verdict == "insufficient" {
            assert_eq!(
                doc.status,
                rigcal_core::result::Status::Failed,
                "{name}: the check refused what the solve accepted: {:?}",
                doc.reasons
            );
        }
    }
}
