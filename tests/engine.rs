//! End-to-end tests of the motion method on synthetic sessions with known truth, run
//! through the same entry points as the CLI (`parse_session` → `calibrate`).

use rigcal_core::geometry::Pose;
use rigcal_core::result::{ResultDocument, Status};
use rigcal_core::session::parse_session;
use rigcal_engine::pipeline::{calibrate, CalibOptions};
use rigcal_synth::{generate, Truth};

fn run(preset: &str, seed: u64, noise: f64) -> (ResultDocument, Truth) {
    let (manifest, truth) = generate(preset, seed, noise).expect("preset");
    let session =
        parse_session(serde_json::to_string(&manifest).unwrap().as_bytes()).expect("valid session");
    (calibrate(&session, &CalibOptions::default()), truth)
}

fn pose(doc: &ResultDocument, cam: &str) -> Pose {
    let m = doc
        .extrinsics
        .iter()
        .find(|e| e.value.camera == cam)
        .unwrap()
        .value
        .ref_from_cam;
    Pose::new(
        nalgebra::Matrix3::new(
            m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2],
        ),
        nalgebra::Vector3::new(m[0][3], m[1][3], m[2][3]),
    )
}

/// Error of the observable part: the translation error with the reported unobservable
/// translation directions of this camera projected out.
fn observable_error(doc: &ResultDocument, truth: &Truth, cam: &str) -> (f64, f64) {
    let est = pose(doc, cam);
    let t = truth.ref_from_cam[cam];
    let (dr, _) = est.distance(&t);
    let mut dt = est.trans - t.trans;
    let sing = doc.singularity.as_ref().unwrap();
    // Project out every null direction's component for this camera (Gram–Schmidt).
    let mut basis: Vec<nalgebra::Vector3<f64>> = Vec::new();
    for d in &sing.unobservable_directions {
        for c in d.components.iter().filter(|c| c.camera == cam) {
            let mut v = nalgebra::Vector3::from(c.translation);
            for b in &basis {
                v -= b * b.dot(&v);
            }
            if v.norm() > 1e-3 {
                basis.push(v.normalize());
            }
        }
    }
    for b in &basis {
        dt -= b * b.dot(&dt);
    }
    (dr, dt.norm())
}

#[test]
fn noise_free_presets_recover_the_observable_truth() {
    for preset in [
        "lebraly-5.1",
        "car-bump",
        "car-planar-loop",
        "car-planar",
        "car-planar-uturn",
    ] {
        let (doc, truth) = run(preset, 7, 0.0);
        assert_ne!(doc.status, Status::Failed, "{preset}: {:?}", doc.reasons);
        for cam in truth.ref_from_cam.keys() {
            let (dr, dt) = observable_error(&doc, &truth, cam);
            assert!(
                dr < 1e-6 && dt < 1e-6,
                "{preset}/{cam}: dR {dr} rad, dt {dt} m"
            );
        }
    }
}

#[test]
fn general_motion_succeeds_with_all_dof() {
    for preset in ["lebraly-5.1", "car-bump", "car-planar-loop"] {
        let (doc, _) = run(preset, 3, 0.0);
        assert_eq!(doc.status, Status::Succeeded, "{preset}: {:?}", doc.reasons);
        let s = doc.singularity.as_ref().unwrap();
        assert!(s.unobservable_directions.is_empty(), "{preset}");
        for c in &s.per_camera {
            assert_eq!(
                (c.observable_dof.rotation, c.observable_dof.translation),
                (3, 3),
                "{preset}/{}",
                c.camera
            );
        }
    }
}

#[test]
fn planar_drive_reports_height_unobservable_and_the_plane_normal() {
    let (doc, truth) = run("car-planar", 2, 0.5);
    assert_eq!(doc.status, Status::Degraded);
    assert!(doc.reasons.iter().any(|r| r.code == "planar_motion"));
    let s = doc.singularity.as_ref().unwrap();
    assert_eq!(s.motion_class, "planar");
    for c in s.per_camera.iter().filter(|c| c.camera != "front") {
        assert_eq!(
            (c.observable_dof.rotation, c.observable_dof.translation),
            (3, 2),
            "{}",
            c.camera
        );
    }
    // The plane normal is the vehicle's up axis seen from the front camera.
    // Frame 0 has the vehicle at the world origin, so world_from_rig[0] is vehicle_from_front.
    let up_in_front = truth.world_from_rig[0].rot.transpose() * nalgebra::Vector3::z();
    let n = nalgebra::Vector3::from(s.axis);
    let angle = n
        .dot(&up_in_front)
        .abs()
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees();
    assert!(angle < 2.0, "plane normal off by {angle}°");
    assert!(s.recommendations.iter().any(|r| r.contains("bump")));
}

#[test]
fn uturn_leaves_one_direction_shared_by_left_and_right() {
    for noise in [0.0, 1.0] {
        let (doc, _) = run("car-planar-uturn", 4, noise);
        let s = doc.singularity.as_ref().unwrap();
        assert!(s.scene_permutation);
        assert_eq!(
            s.unobservable_directions.len(),
            1,
            "noise {noise}: {:?}",
            s.unobservable_directions
        );
        let mut cams: Vec<&str> = s.unobservable_directions[0]
            .components
            .iter()
            .filter(|c| nalgebra::Vector3::from(c.translation).norm() > 0.3)
            .map(|c| c.camera.as_str())
            .collect();
        cams.sort();
        assert_eq!(cams, vec!["left", "right"]);
        let rear = s.per_camera.iter().find(|c| c.camera == "rear").unwrap();
        assert_eq!(rear.observable_dof.translation, 3);
    }
}

#[test]
fn degenerate_motions_are_detected() {
    let (doc, _) = run("pure-translation", 1, 0.5);
    assert_eq!(doc.status, Status::Failed);
    assert_eq!(doc.exit_code(), 1);
    assert!(doc.reasons.iter().any(|r| r.code == "pure_translation"));
    let (doc, _) = run("single-axis", 1, 0.5);
    assert_eq!(
        doc.singularity.as_ref().unwrap().motion_class,
        "single_axis"
    );
    assert!(doc.reasons.iter().any(|r| r.code == "single_axis_rotation"));
    assert_ne!(doc.status, Status::Succeeded);
}

#[test]
fn noisy_lebraly_protocol_within_stated_bounds() {
    // σ = 0.5 px, 10 trials: errors stay within 4σ of the reported uncertainty and the
    // refined result beats the linear initialisation on average.
    let mut init_err = 0.0;
    let mut ref_err = 0.0;
    for seed in 0..10 {
        let (doc, truth) = run("lebraly-5.1", 100 + seed, 0.5);
        // Known gap (issue 2 note): with noise a scene's scale points can fail to
        // triangulate; its scale then comes through the rig, reported as scale_missing.
        let only_known = doc
            .reasons
            .iter()
            .all(|r| matches!(r.code.as_str(), "outliers_removed" | "scale_missing"));
        assert!(
            only_known && doc.status != Status::Failed,
            "{:?}",
            doc.reasons
        );
        let est = pose(&doc, "cam2");
        let (_, dt) = est.distance(&truth.ref_from_cam["cam2"]);
        let e = &doc.extrinsics[1];
        let sig = e
            .sigma_translation_m
            .iter()
            .map(|s| s.unwrap().powi(2))
            .sum::<f64>()
            .sqrt();
        assert!(dt < 4.0 * sig + 1e-4, "seed {seed}: dt {dt} σ {sig}");
        let i = &doc.initialisation[1];
        init_err +=
            (nalgebra::Vector3::from(i.translation) - truth.ref_from_cam["cam2"].trans).norm();
        ref_err += dt;
    }
    assert!(ref_err < init_err, "refined {ref_err} vs init {init_err}");
}

#[test]
fn gross_outliers_are_listed_and_do_not_spoil_the_result() {
    let (mut manifest, truth) = generate("car-bump", 5, 0.5).unwrap();
    let (clean_doc, _) = run("car-bump", 5, 0.5);
    let mut injected = 0;
    for (fi, f) in manifest.frames.iter_mut().enumerate() {
        for obs in f.observations.values_mut() {
            for (k, o) in obs.iter_mut().enumerate() {
                if (fi * 31 + k * 7) % 20 == 3 {
                    o.u += 25.0;
                    injected += 1;
                }
            }
        }
    }
    let session = parse_session(serde_json::to_string(&manifest).unwrap().as_bytes()).unwrap();
    let doc = calibrate(&session, &CalibOptions::default());
    let res = doc.residuals.as_ref().unwrap();
    assert!(
        res.outliers as f64 >= 0.9 * injected as f64,
        "{} of {injected} flagged",
        res.outliers
    );
    for cam in ["rear", "left", "right"] {
        let (_, dt_clean) = pose(&clean_doc, cam).distance(&truth.ref_from_cam[cam]);
        let (_, dt) = pose(&doc, cam).distance(&truth.ref_from_cam[cam]);
        assert!(
            dt < 1.5 * dt_clean + 0.01,
            "{cam}: {dt} vs clean {dt_clean}"
        );
    }
}

#[test]
fn input_errors_name_the_camera_and_field() {
    // A camera that never sees anything.
    let (mut manifest, _) = generate("lebraly-5.1", 1, 0.0).unwrap();
    for f in manifest.frames.iter_mut() {
        f.observations.remove("cam2");
    }
    manifest.scale.retain(|s| s.a.starts_with("s-cam1"));
    let session = parse_session(serde_json::to_string(&manifest).unwrap().as_bytes()).unwrap();
    let doc = calibrate(&session, &CalibOptions::default());
    assert_eq!(doc.status, Status::Failed);
    assert!(doc
        .reasons
        .iter()
        .any(|r| r.code == "camera_not_observed" && r.camera.as_deref() == Some("cam2")));
    // Fewer than 3 frames.
    let (mut manifest, _) = generate("lebraly-5.1", 1, 0.0).unwrap();
    manifest.frames.truncate(2);
    manifest.scale.clear();
    let session = parse_session(serde_json::to_string(&manifest).unwrap().as_bytes()).unwrap();
    let doc = calibrate(&session, &CalibOptions::default());
    assert!(doc.reasons.iter().any(|r| r.code == "too_few_motions"));
    // Unknown point in scale[].
    let (mut manifest, _) = generate("lebraly-5.1", 1, 0.0).unwrap();
    manifest.scale[0].b = "nowhere".into();
    let err = parse_session(serde_json::to_string(&manifest).unwrap().as_bytes()).unwrap_err();
    assert_eq!(err.field, "scale[0].b");
}

#[test]
fn exports_state_their_convention() {
    let (manifest, _) = generate("lebraly-5.1", 1, 0.0).unwrap();
    let session = parse_session(serde_json::to_string(&manifest).unwrap().as_bytes()).unwrap();
    let doc = calibrate(&session, &CalibOptions::default());
    use rigcal_engine::export::{render, Format};
    assert!(render(&doc, &session, Format::Kalibr)
        .unwrap()
        .contains("T_cn_cnm1"));
    assert!(render(&doc, &session, Format::Opencv)
        .unwrap()
        .starts_with("%YAML:1.0"));
    assert!(render(&doc, &session, Format::Urdf)
        .unwrap()
        .contains("<joint name=\"cam1_to_cam2\""));
}

/// Issue 24: ids that pass the identifier grammar but that YAML or XML would misread
/// unquoted (`yes`, `1e5`, `null`, `a--b`, ...) come back intact from every export, read
/// by real parsers (libyaml through serde_norway, roxmltree); what OpenCV's keys cannot
/// hold is refused with the reason.
#[test]
fn exports_quote_hostile_but_valid_ids() {
    use rigcal_engine::export::{render, ExportError, Format};
    let (manifest, _) = generate("lebraly-5.1", 1, 0.0).unwrap();
    let text = serde_json::to_string(&manifest).unwrap();
    let plain = parse_session(text.as_bytes()).unwrap();
    let ids: Vec<String> = plain.cameras.iter().map(|c| c.id.clone()).collect();
    let hostile = ["yes", "1e5", "null", "a--b", "0x1F", "NaN", "a.b_c-d", "x"];
    for pair in hostile.chunks(ids.len().min(hostile.len())) {
        let mut t = text.clone();
        for (id, new) in ids.iter().zip(pair) {
            t = t.replace(&format!("\"{id}\""), &format!("\"{new}\""));
        }
        let session = parse_session(t.as_bytes()).unwrap();
        let doc = calibrate(&session, &CalibOptions::default());
        let names: Vec<&str> = session.cameras.iter().map(|c| c.id.as_str()).collect();

        let kalibr: serde_norway::Value =
            serde_norway::from_str(&render(&doc, &session, Format::Kalibr).unwrap()).unwrap();
        for (i, id) in names.iter().enumerate() {
            assert_eq!(
                kalibr[format!("cam{i}").as_str()]["rostopic"].as_str(),
                Some(format!("/{id}/image_raw").as_str()),
                "{kalibr:?}"
            );
        }

        let urdf = render(&doc, &session, Format::Urdf).unwrap();
        let xml = roxmltree::Document::parse(&urdf).unwrap_or_else(|e| panic!("{e}: {urdf}"));
        let links: Vec<&str> = xml
            .descendants()
            .filter(|n| n.has_tag_name("link"))
            .filter_map(|n| n.attribute("name"))
            .collect();
        for id in &names {
            assert!(
                links.contains(&format!("{id}_optical_frame").as_str()),
                "{links:?}"
            );
        }

        let opencv_ok = names.iter().all(|id| {
            id.starts_with(|c: char| c.is_ascii_alphabetic())
                && id
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        });
        match render(&doc, &session, Format::Opencv) {
            Ok(yaml) => {
                assert!(opencv_ok, "{names:?} written as OpenCV keys");
                // OpenCV's own directive line is not YAML 1.x; the rest is.
                let body = yaml.split_once("---\n").unwrap().1;
                let v: serde_norway::Value = serde_norway::from_str(body).unwrap();
                for id in &names {
                    assert!(v.get(format!("{id}_R").as_str()).is_some(), "{body}");
                }
            }
            Err(ExportError::Unrepresentable(why)) => {
                assert!(!opencv_ok, "{names:?}: {why}");
                assert!(why.contains("OpenCV FileStorage key"), "{why}");
            }
            Err(e) => panic!("{e:?}"),
        }
    }
}

#[test]
fn uncertainty_is_honest_and_the_estimate_reaches_the_cramer_rao_bound() {
    // 200 noisy trials of the paper's protocol at σ = 0.5 px.
    let rows = rigcal_bench::accuracy::accuracy("lebraly-5.1", &[0.5], 200, 5000);
    let r = &rows[0];
    assert_eq!(r.failed, 0);
    assert!(r.nees > 0.8 * 6.0 && r.nees < 1.25 * 6.0, "NEES {}", r.nees);
    assert!(
        r.refined_t_mm < 1.2 * r.crb_t_mm && r.refined_r_deg < 1.2 * r.crb_r_deg,
        "{r:?}"
    );
    assert!(r.init_t_mm < 5.0 * r.refined_t_mm, "{r:?}");
}

#[test]
fn a_noisy_loop_is_right_or_says_it_failed() {
    // All four scenes merge into one 360° scene here. Its incremental reconstruction used
    // to fold in 10-15 % of noisy trials; since the start/triangulation/resection rules,
    // the split of an unreachable rest and the verified eigen-decomposition, 1 in 100
    // (bench accuracy, 50 trials at 0.5 and 1 px). Whatever fails must say so.
    let mut answered = 0;
    for seed in 0..10 {
        let (doc, truth) = run("car-planar-loop", 1000 + seed, 0.5);
        if doc.status == Status::Failed {
            assert!(
                doc.reasons
                    .iter()
                    .any(|r| r.code == "inconsistent_rig" || r.code == "no_convergence"),
                "{:?}",
                doc.reasons
            );
            continue;
        }
        answered += 1;
        for e in doc.extrinsics.iter().filter(|e| e.value.camera != "front") {
            let (_, dt) =
                pose(&doc, &e.value.camera).distance(&truth.ref_from_cam[&e.value.camera]);
            let sig = e
                .sigma_translation_m
                .iter()
                .map(|s| s.unwrap_or(0.0).powi(2))
                .sum::<f64>()
                .sqrt();
            assert!(
                dt < 5.0 * sig + 1e-3,
                "seed {seed} {}: {dt} m vs σ {sig}",
                e.value.camera
            );
        }
    }
    assert!(answered >= 9, "only {answered} of 10 loops answered");
}

#[test]
fn the_initialisation_with_scene_permutation_stays_near_the_refined_result() {
    // The linear initialisation must not need the adjustment to rescue it: with scene
    // permutation (a U-turn, a 360° loop) each extrinsic rotation is also measured
    // against the reference through the scene both saw. Pooled RMS over 8 seeds at 1 px,
    // rotation (fully observable in both) and, on the loop, translation. The 50-trial
    // bench (docs/accuracy.md) has 2.0-3.0×; 8 seeds scatter, hence 3.5 here. Before
    // the permutation entered the rotations the loop's initialisation was 20-40× the
    // refined error, the U-turn's 12× in rotation, and 1 U-turn in 20 started 180° off.
    use rigcal_core::result::ExtrinsicValue;
    for (preset, with_translation) in [("car-planar-loop", true), ("car-planar-uturn", false)] {
        let (mut init_r, mut ba_r, mut init_t, mut ba_t) = (0.0, 0.0, 0.0, 0.0);
        for seed in 0..8 {
            let (doc, truth) = run(preset, 1000 + seed, 1.0);
            if doc.status == Status::Failed {
                continue;
            }
            for (c, e) in doc.extrinsics.iter().enumerate() {
                let t = truth.ref_from_cam[&e.value.camera];
                let (r0, t0) = ExtrinsicValue::pose(&doc.initialisation[c]).distance(&t);
                let (r1, t1) = ExtrinsicValue::pose(&e.value).distance(&t);
                init_r += r0 * r0;
                ba_r += r1 * r1;
                init_t += t0 * t0;
                ba_t += t1 * t1;
            }
        }
        let ratio_r = (init_r / ba_r).sqrt();
        let ratio_t = (init_t / ba_t).sqrt();
        eprintln!("{preset}: init/BA rotation {ratio_r:.2}, translation {ratio_t:.2}");
        assert!(
            ratio_r < 3.5,
            "{preset}: initial rotation {ratio_r:.2}× the refined"
        );
        if with_translation {
            assert!(
                ratio_t < 3.5,
                "{preset}: initial translation {ratio_t:.2}× the refined"
            );
        }
    }
}

/// What a format cannot hold is refused, not dropped: radtan's `k3` has no place in
/// Kalibr's four-coefficient radtan; COLMAP takes it as FULL_OPENCV.
#[test]
fn radtan_k3_is_refused_by_kalibr_and_kept_by_colmap() {
    use rigcal_engine::export::{render, ExportError, Format};
    let (mut manifest, _) = generate("lebraly-5.1", 1, 0.0).unwrap();
    for c in &mut manifest.cameras {
        c.model = "radtan".into();
        c.distortion = vec![0.0, 0.0, 0.0, 0.0, 0.0];
    }
    let with_k3 = |k3: f64| {
        let mut m = manifest.clone();
        m.cameras[1].distortion[4] = k3;
        let session = parse_session(&serde_json::to_vec(&m).unwrap()).unwrap();
        let doc = calibrate(&session, &CalibOptions::default());
        (
            render(&doc, &session, Format::Kalibr),
            render(&doc, &session, Format::Colmap),
        )
    };
    let (kalibr, colmap) = with_k3(0.0);
    assert!(kalibr.is_ok());
    assert!(colmap.unwrap().contains("\"OPENCV\""));
    let (kalibr, colmap) = with_k3(1e-3);
    match kalibr {
        Err(ExportError::Unrepresentable(why)) => assert!(why.contains("k3"), "{why}"),
        other => panic!("k3 exported to Kalibr: {other:?}"),
    }
    let colmap: serde_json::Value = serde_json::from_str(&colmap.unwrap()).unwrap();
    let cams = colmap[0]["cameras"].as_array().unwrap();
    assert_eq!(cams[1]["camera_model_name"], "FULL_OPENCV");
    assert_eq!(cams[1]["camera_params"][8], 1e-3);
}
