//! Captures that look like what users send (issue 17): the hall presets of
//! `rigcal synth`, as detections and as rendered JPEG images.

mod common;

use common::*;
use rigcal_bench::accuracy::{error6, observable, synthetic_session};
use rigcal_core::geometry::Vec3;
use rigcal_core::result::{ExtrinsicValue, ResultDocument, Status};
use rigcal_engine::pipeline::{calibrate, CalibOptions};
use rigcal_synth::hall::{hall, Hall, Nuisance};

/// A planar S-curve where every target is seen by one camera only: each non-reference
/// camera's height along the plane normal is unobservable, everything else is. The
/// result is `degraded` (`planar_motion`), names one direction per camera ("the height
/// of camera rear"), holds each height at 0 (no prior given) instead of wherever the
/// noise pushes it (it drifted 12-42 m), and the observable part is within 2× its
/// Cramér–Rao bound (pooled over the cameras and 4 drives at 0.15 px).
#[test]
fn an_isolated_planar_drive_is_degraded_with_each_height_held_and_named() {
    let sigma = 0.15;
    let (mut err2, mut crb2) = ((0.0, 0.0), (0.0, 0.0));
    for seed in 1..=4 {
        let (session, truth) = synthetic_session("car-hall-isolated", seed, sigma).unwrap();
        let doc = calibrate(&session, &CalibOptions::default());
        assert_eq!(
            doc.status,
            Status::Degraded,
            "seed {seed}: {:?}",
            doc.reasons
        );
        assert!(
            doc.reasons.iter().any(|r| r.code == "planar_motion"),
            "{:?}",
            doc.reasons
        );
        let sing = doc.singularity.as_ref().unwrap();
        let mut named: Vec<&str> = sing
            .unobservable_directions
            .iter()
            .map(|d| {
                assert_eq!(d.components.len(), 1, "{}", d.description);
                assert!(
                    d.description.starts_with("the height of camera"),
                    "{}",
                    d.description
                );
                d.components[0].camera.as_str()
            })
            .collect();
        named.sort();
        assert_eq!(named, ["left", "rear", "right"], "seed {seed}");
        // Held at 0 along the plane normal (the reference frame's motion axis).
        let n = Vec3::from(sing.axis);
        for e in &doc.extrinsics {
            let h = Vec3::from(e.value.translation).dot(&n);
            assert!(
                h.abs() < 1e-3,
                "seed {seed}: {} held at {h:.3} m, not 0",
                e.value.camera
            );
        }
        let obs = observable(&session, &truth, sigma).unwrap();
        assert_eq!(obs.null_dim, 3);
        let mut v = nalgebra::DVector::zeros(6 * obs.cams.len());
        for (i, &c) in obs.cams.iter().enumerate() {
            let est = ExtrinsicValue::pose(&doc.extrinsics[c].value);
            let e = error6(&est, &truth.ref_from_cam[&session.cameras[c].id]);
            v.rows_mut(6 * i, 6).copy_from(&e);
        }
        let e = &obs.projector * v;
        for i in 0..obs.cams.len() {
            err2.0 += e.rows(6 * i, 3).norm_squared();
            err2.1 += e.rows(6 * i + 3, 3).norm_squared();
            crb2.0 += (0..3).map(|k| obs.crb[(6 * i + k, 6 * i + k)]).sum::<f64>();
            crb2.1 += (3..6).map(|k| obs.crb[(6 * i + k, 6 * i + k)]).sum::<f64>();
        }
    }
    let (t, r) = ((err2.0 / crb2.0).sqrt(), (err2.1 / crb2.1).sqrt());
    assert!(
        t < 2.0 && r < 2.0,
        "observable part at {t:.2}× (translation), {r:.2}× (rotation) the bound"
    );
}

/// A hall capture rendered as a vehicle's cameras deliver it (JPEG q 92, blur,
/// vignetting, gain/offset, noise; AprilGrids of mixed sizes, wall tags, boards cut by
/// the border; two radtan and two fisheye cameras; two of them colour, white balance
/// off neutral, two grey), at 1024×576 to keep the test short, uploaded to the real
/// service as one tar archive: the job detects and calibrates it to a `succeeded`
/// result within 2 mm and 0.02° of the truth, every truth within 3 σ.
#[tokio::test]
async fn a_rendered_hall_capture_calibrates_through_the_service() {
    let h = hall("car-hall", 2, Some((1024, 576))).unwrap();
    let grey = Nuisance::default();
    let colour = Nuisance {
        colour: Some(rigcal_synth::hall::HALL_WHITE_BALANCE),
        ..Nuisance::default()
    };
    let capture = h.image_capture(true);
    let mut files: Vec<(String, Vec<u8>)> = vec![(
        "capture/session.json".into(),
        serde_json::to_vec(&capture.manifest).unwrap(),
    )];
    for (frame, spec) in capture.manifest.frames.iter().enumerate() {
        for (cam, path) in &spec.images {
            let ci = h.cameras.iter().position(|c| &c.0 == cam).unwrap();
            let nuisance = if ci % 2 == 1 { &colour } else { &grey };
            let img = h.render(frame, ci, nuisance, (frame * 8 + ci) as u64);
            files.push((
                format!("capture/{path}"),
                Hall::encode(&img, nuisance).unwrap(),
            ));
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &["--workers", "1"]);
    let c = client(&key);
    let v = create_archive_session(&c, &s, &files).await;
    assert_eq!(v["images_received"], 72, "{v}");
    let done = run_job(
        &c,
        &s,
        v["id"].as_str().unwrap(),
        std::time::Duration::from_secs(300),
    )
    .await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let doc: ResultDocument = c
        .get(s.url(&format!("/v1/jobs/{}/result", done["id"].as_str().unwrap())))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let det = doc.detection.as_ref().unwrap();
    assert_eq!(det.images_total, 72);
    assert_eq!(det.images_skipped, 0);
    for e in &doc.extrinsics {
        let truth = capture.truth.ref_from_cam[&e.value.camera];
        let est = ExtrinsicValue::pose(&e.value);
        let (dr, dt) = est.distance(&truth);
        assert!(
            dt < 2e-3 && dr.to_degrees() < 0.02,
            "{}: {:.2} mm, {:.4}°",
            e.value.camera,
            dt * 1e3,
            dr.to_degrees()
        );
        for a in 0..3 {
            if let Some(sigma) = e.sigma_translation_m[a].filter(|s| *s > 0.0) {
                let z = (est.trans[a] - truth.trans[a]) / sigma;
                assert!(z.abs() <= 3.0, "{} axis {a}: {z:.1} σ", e.value.camera);
            }
        }
    }
}

/// A planar S-curve whose cameras are linked only through small wall tags: in these
/// two drives (0.1 px) a side camera sees another camera's scene through a tag posed
/// with the wrong one of its two planar solutions. That link used to turn the side
/// cameras 70-100° about the plane normal away from where their own 13 motions put
/// them, and the rig adjustment ended `failed` (`inconsistent_rig`, 3-60 px). The
/// robust average from the hand-eye rotations now competes with the plain one, and the
/// rotations that explain the motions' translations win, every rotation right (and the
/// tags then link the cameras' heights: `succeeded`). The other way round, on the
/// U-turn hall (seed 1014), the right camera's hand-eye rotation is 12° off and the
/// scene it shares along the drive is right: that must still win (`succeeded`).
#[test]
fn a_wrong_link_between_cameras_does_not_turn_a_planar_rig() {
    for (preset, seed, status) in [
        ("car-hall-planar", 1000, Status::Succeeded),
        ("car-hall-planar", 1001, Status::Succeeded),
        ("car-hall", 1014, Status::Succeeded),
    ] {
        let (session, truth) = synthetic_session(preset, seed, 0.1).unwrap();
        let doc = calibrate(&session, &CalibOptions::default());
        assert_eq!(doc.status, status, "{preset} {seed}: {:?}", doc.reasons);
        for (c, cam) in session.cameras.iter().enumerate() {
            let est = ExtrinsicValue::pose(&doc.extrinsics[c].value);
            let e = error6(&est, &truth.ref_from_cam[&cam.id]);
            let deg = e.rows(3, 3).norm().to_degrees();
            // Measured 0.0012-0.0040° (planar), 0.0015-0.0024° (U-turn).
            assert!(deg < 0.02, "{preset} {seed}: {} off by {deg:.4}°", cam.id);
        }
    }
}

/// The U-turn hall at 0.3 px (seed 1017): the chain of boards along the drive is
/// reconstructed as four scenes, three split off the first. Each is made of boards of
/// known size, so each is in metres; the initialisation used to give the split-off ones
/// a free scale, shrank them to 0.23-0.57 to absorb its rotations' 1° of noise, put the
/// cameras 0.7-1.4 m from the truth, and the rig adjustment ended `failed`
/// (`inconsistent_rig`, 4.7 px). A scene of known geometry now keeps its scale.
#[test]
fn scenes_split_off_a_chain_of_boards_keep_their_metric_scale() {
    // Measured 0.21-0.34 mm, 0.0013-0.0061°.
    calibrates_within("car-hall", 1017, 0.3, 2.0, 0.03);
}

/// Calibrates the preset's session (detections with `sigma` px of noise) to
/// `succeeded`, every camera within `mm` and `deg` of the truth.
fn calibrates_within(preset: &str, seed: u64, sigma: f64, mm: f64, deg: f64) {
    let (session, truth) = synthetic_session(preset, seed, sigma).unwrap();
    let doc = calibrate(&session, &CalibOptions::default());
    assert_eq!(
        doc.status,
        Status::Succeeded,
        "{preset} {seed}: {:?}",
        doc.reasons
    );
    for (c, cam) in session.cameras.iter().enumerate() {
        let est = ExtrinsicValue::pose(&doc.extrinsics[c].value);
        let e = error6(&est, &truth.ref_from_cam[&cam.id]);
        let (dt, dr) = (e.rows(0, 3).norm() * 1e3, e.rows(3, 3).norm().to_degrees());
        assert!(
            dt < mm && dr < deg,
            "{preset} {seed}: {} off by {dt:.3} mm, {dr:.4}°",
            cam.id
        );
    }
}

/// A planar S-curve whose cameras share only small wall tags (seed 1005, 0.1 px): each
/// has two planar poses that fit, no scene places them, and every camera's height
/// relative to the front one was held at 0 (`degraded`, 200-225 mm off). With the
/// rig's rotations known, the orientation that views from different cameras agree on
/// places each tag, and the tags link the heights: `succeeded`, every camera within a
/// few times the bound (Cramér–Rao 0.46 mm RMS on these drives). Where no target at
/// all is shared between the front pair and the rear pair (seed 1011), their relative
/// height stays unobservable and is held and said so.
#[test]
fn cameras_that_share_only_small_tags_are_linked_by_the_rig() {
    // Measured 0.22-0.58 mm, 0.0008-0.0025°.
    calibrates_within("car-hall-planar", 1005, 0.1, 2.0, 0.02);

    let (session, _) = synthetic_session("car-hall-planar", 1011, 0.1).unwrap();
    let doc = calibrate(&session, &CalibOptions::default());
    assert_eq!(doc.status, Status::Degraded, "{:?}", doc.reasons);
    let held: Vec<&str> = doc
        .singularity
        .as_ref()
        .unwrap()
        .unobservable_directions
        .iter()
        .flat_map(|d| d.components.iter().map(|c| c.camera.as_str()))
        .collect();
    assert_eq!(held, ["rear", "right"]);
}

/// A planar drive whose trajectories are noisy enough (car-hall-planar seed 113 at
/// 1024×576, 0.1 px) to look general (1.2° out of axis), so no height is held from the
/// start, and whose initialisation turns the rear camera wrongly, so its height looks
/// determined there. The rear shares no target with the others: at the solution its
/// height is undetermined, and the adjustment had left it wherever its steps ended,
/// 16.4 m out along it. It is now set where the held heights are (0: the true height
/// difference, 0.30 m, is the error), said so, and every other camera is within bounds.
#[test]
fn a_height_nothing_held_ends_where_the_held_ones_are() {
    let capture = hall("car-hall-planar", 113, Some((1024, 576)))
        .unwrap()
        .detection_capture(0.1, 113)
        .unwrap();
    let bytes = serde_json::to_vec(&capture.manifest).unwrap();
    let session = rigcal_core::session::parse_session(&bytes).unwrap();
    let doc = calibrate(&session, &CalibOptions::default());
    assert_eq!(doc.status, Status::Degraded, "{:?}", doc.reasons);
    let directions = &doc.singularity.as_ref().unwrap().unobservable_directions;
    assert_eq!(directions.len(), 1);
    assert!(
        directions[0].description.contains("set to the prior or 0"),
        "{}",
        directions[0].description
    );
    for (c, cam) in session.cameras.iter().enumerate() {
        let est = ExtrinsicValue::pose(&doc.extrinsics[c].value);
        let e = error6(&est, &capture.truth.ref_from_cam[&cam.id]);
        let (dt, dr) = (e.rows(0, 3).norm() * 1e3, e.rows(3, 3).norm().to_degrees());
        // Measured: rear 299.99 mm (the true height difference) and 0.006°, left and
        // right 0.30-0.64 mm, 0.004°.
        let bound = if cam.id == "rear" { 310.0 } else { 2.0 };
        assert!(dt < bound && dr < 0.02, "{}: {dt:.2} mm, {dr:.4}°", cam.id);
    }
}

/// A scale that every corner of a camera shares (a focal length a few ppm off, a radial
/// bias of the detector) does not average down over the thousands of corners a capture
/// has, as their noise does: on the hand-held fisheye pair the extrinsic is determined
/// to 10⁻⁶ along one direction, where 1.5 ppm is as large as its σ. With both cameras'
/// corners scaled by 1.5 ppm about their principal points (the sign alternating over
/// the captures; rigcal's detector reads its renders at −0.4 to −2 ppm in every camera),
/// the covariance from the noise alone is optimistic (NEES mean 14.1 over six captures,
/// where 6 is honest); with the 2 ppm consider term that corners detected from images
/// get, it is not (4.8).
#[test]
fn the_covariance_allows_for_a_scale_all_of_a_cameras_corners_share() {
    let nees_mean = |corner_scale_sigma: f64| {
        let mut nees = Vec::new();
        for seed in 1..=6u64 {
            let (mut session, truth) = synthetic_session("fisheye-handheld", seed, 0.01).unwrap();
            for (c, cam) in session.cameras.clone().iter().enumerate() {
                let scale = if seed % 2 == 0 { 1.5e-6 } else { -1.5e-6 };
                let centre = rigcal_core::geometry::Vec2::new(cam.camera.cx, cam.camera.cy);
                for f in &mut session.frames {
                    for o in &mut f.observations[c] {
                        o.uv += (o.uv - centre) * scale;
                    }
                }
            }
            let opts = CalibOptions {
                corner_scale_sigma,
                ..CalibOptions::default()
            };
            let doc = calibrate(&session, &opts);
            assert_eq!(
                doc.status,
                Status::Succeeded,
                "seed {seed}: {:?}",
                doc.reasons
            );
            let reference = &session.cameras[session.reference].id;
            for e in doc
                .extrinsics
                .iter()
                .filter(|e| &e.value.camera != reference)
            {
                let cov = e.covariance.unwrap();
                let inv = nalgebra::Matrix6::from_fn(|a, b| cov[a][b])
                    .try_inverse()
                    .unwrap();
                let x = error6(
                    &ExtrinsicValue::pose(&e.value),
                    &truth.ref_from_cam[&e.value.camera],
                );
                nees.push(x.dot(&(inv * x)));
            }
        }
        nees.iter().sum::<f64>() / nees.len() as f64
    };
    let (without, with) = (nees_mean(0.0), nees_mean(2e-6));
    assert!(
        without > 9.0,
        "the scale no longer shows: NEES {without:.1}"
    );
    assert!(
        with < 6.0,
        "NEES {with:.1} with the 2 ppm term, {without:.1} without"
    );
}
