//! The vanishing method (Wu et al.) end to end on synthetic rings with known truth:
//! session JSON → parser → engine → result document.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rigcal_core::geometry::{so3, Camera, CameraModel, Pose, Vec3};
use rigcal_core::result::{ResultDocument, Status};
use rigcal_core::session::{parse_session, SessionManifest};
use rigcal_engine::pipeline::{calibrate, CalibOptions};
use rigcal_synth::ring::{
    aux_camera, generate_with, rig_camera, ring_scene, table2_scene, RingLayout, RingScene,
};
use rigcal_synth::Truth;

fn session(
    seed: u64,
    noise: f64,
    rig: &Camera,
    aux: &Camera,
    scene: &RingScene,
) -> (SessionManifest, Truth) {
    generate_with(&mut ChaCha8Rng::seed_from_u64(seed), noise, rig, aux, scene)
}

fn run(m: &SessionManifest) -> ResultDocument {
    let s = parse_session(serde_json::to_string(m).unwrap().as_bytes()).expect("valid session");
    calibrate(&s, &CalibOptions::default())
}

/// Per camera: (global rotation error rad, translation error m, chainwise rotation, translation).
fn errors(doc: &ResultDocument, truth: &Truth) -> Vec<(String, f64, f64, f64, f64)> {
    let report = doc.vanishing.as_ref().expect("vanishing report");
    doc.extrinsics
        .iter()
        .map(|e| {
            let t = &truth.ref_from_cam[&e.value.camera];
            let c = report
                .cameras
                .iter()
                .find(|c| c.camera == e.value.camera)
                .unwrap();
            let (gr, gt) = e.value.pose().distance(t);
            let (cr, ct) = c.chainwise.pose().distance(t);
            (e.value.camera.clone(), gr, gt, cr, ct)
        })
        .collect()
}

fn codes(doc: &ResultDocument) -> Vec<&str> {
    doc.reasons.iter().map(|r| r.code.as_str()).collect()
}

#[test]
fn noise_free_table2_ring_is_recovered_exactly_with_and_without_distortion() {
    let radtan = Camera {
        model: CameraModel::Radtan {
            k1: -0.25,
            k2: 0.07,
            p1: 8e-4,
            p2: -5e-4,
            k3: 0.0,
        },
        ..rig_camera()
    };
    let fisheye = Camera {
        model: CameraModel::Equidistant {
            k1: 0.05,
            k2: -0.01,
            k3: 0.002,
            k4: -0.0005,
        },
        ..aux_camera()
    };
    for (rig, aux) in [(rig_camera(), aux_camera()), (radtan, fisheye)] {
        let (m, truth) = session(1, 0.0, &rig, &aux, &table2_scene());
        let doc = run(&m);
        assert_eq!(doc.status, Status::Succeeded, "{:?}", doc.reasons);
        assert_eq!(doc.method, "vanishing");
        for (cam, gr, gt, cr, ct) in errors(&doc, &truth) {
            assert!(gr < 1e-6 && gt < 1e-6, "{cam} global {gr} rad {gt} m");
            assert!(cr < 1e-6 && ct < 1e-6, "{cam} chainwise {cr} rad {ct} m");
        }
        let v = doc.vanishing.as_ref().unwrap();
        assert!(v.ring_closed);
        let c = v.closure_error.as_ref().unwrap();
        assert!(c.translation_m < 1e-6 && c.rotation_deg < 1e-5, "{c:?}");
        let hops: Vec<usize> = v.cameras.iter().map(|c| c.chain_transforms).collect();
        assert_eq!(hops, vec![0, 1, 2, 3, 4, 3, 2, 1]);
        assert!(v
            .cameras
            .iter()
            .all(|c| c.initialised_from == "vanishing_points"));
        assert!(doc.residuals.as_ref().unwrap().all.rms < 1e-6);
    }
}

#[test]
fn with_noise_the_global_result_beats_the_chain_far_from_the_reference() {
    // Wu Fig. 7-8: chainwise error grows along the chain and peaks at camera 5; the
    // ring-closure optimisation flattens it. σ = 0.5 px, 20 trials.
    let trials = 20;
    let mut sq = vec![[0.0f64; 4]; 8];
    let mut nees = Vec::new();
    for seed in 0..trials {
        let (m, truth) = session(
            100 + seed,
            0.5,
            &rig_camera(),
            &aux_camera(),
            &table2_scene(),
        );
        let doc = run(&m);
        assert_eq!(doc.status, Status::Succeeded, "{:?}", doc.reasons);
        for (k, (_, gr, gt, cr, ct)) in errors(&doc, &truth).into_iter().enumerate() {
            for (s, x) in sq[k].iter_mut().zip([gr, gt, cr, ct]) {
                *s += x * x;
            }
        }
        for e in doc.extrinsics.iter().skip(1) {
            let cov = nalgebra::Matrix6::from_fn(|i, j| e.covariance.unwrap()[i][j]);
            let t = e.value.pose();
            let truth_pose = truth.ref_from_cam[&e.value.camera];
            let dt = t.trans - truth_pose.trans;
            let dphi = so3::log(&(t.rot * truth_pose.rot.transpose()));
            let err = nalgebra::Vector6::new(dt.x, dt.y, dt.z, dphi.x, dphi.y, dphi.z);
            nees.push((err.transpose() * cov.try_inverse().unwrap() * err)[(0, 0)]);
        }
    }
    let rms: Vec<[f64; 4]> = sq
        .iter()
        .map(|s| s.map(|x| (x / trials as f64).sqrt()))
        .collect();
    for (k, r) in rms.iter().enumerate().skip(1) {
        let (gr, gt) = (r[0].to_degrees(), r[1] * 1e3);
        // Stated bound at 0.5 px for this scene (docs/accuracy.md: 0.04-0.08°, 0.7-1.4 mm).
        assert!(
            gr < 0.12 && gt < 2.2,
            "cam{} global {gr:.4}° {gt:.3} mm",
            k + 1
        );
    }
    for k in [3, 4, 5] {
        // cam4..cam6, 3-4 transforms from the reference.
        assert!(
            rms[k][0] < rms[k][2],
            "cam{} rotation: global {} chain {}",
            k + 1,
            rms[k][0],
            rms[k][2]
        );
        assert!(
            rms[k][1] < rms[k][3],
            "cam{} translation: global {} chain {}",
            k + 1,
            rms[k][1],
            rms[k][3]
        );
    }
    // The chainwise error peaks at camera 5 (4 transforms), not next to the reference.
    assert!(rms[4][3] > rms[1][3] && rms[4][3] > rms[7][3]);
    // The reported covariance is honest: mean NEES of 6 parameters near 6.
    let mean = nees.iter().sum::<f64>() / nees.len() as f64;
    assert!((3.5..9.0).contains(&mean), "mean NEES {mean}");
}

#[test]
fn an_open_chain_is_accepted_and_says_the_ring_is_open() {
    let (mut m, truth) = session(2, 0.0, &rig_camera(), &aux_camera(), &table2_scene());
    m.ring.retain(|r| r.index != 7); // no t8–t1 view
    let doc = run(&m);
    assert_eq!(doc.status, Status::Succeeded, "{:?}", doc.reasons);
    assert!(codes(&doc).contains(&"ring_open"));
    let v = doc.vanishing.as_ref().unwrap();
    assert!(!v.ring_closed && v.closure_error.is_none());
    assert_eq!(v.cameras[7].chain_transforms, 7);
    for (cam, gr, gt, _, _) in errors(&doc, &truth) {
        assert!(gr < 1e-6 && gt < 1e-6, "{cam}");
    }
}

#[test]
fn a_broken_ring_and_an_unlinked_target_fail_naming_the_cameras() {
    let (m, _) = session(3, 0.0, &rig_camera(), &aux_camera(), &table2_scene());
    // t5 appears in no auxiliary view.
    let mut a = m.clone();
    a.ring.retain(|r| r.index != 3 && r.index != 4);
    let doc = run(&a);
    assert_eq!(doc.status, Status::Failed);
    let r = doc
        .reasons
        .iter()
        .find(|r| r.code == "target_not_linked")
        .expect("target_not_linked");
    assert_eq!(r.camera.as_deref(), Some("cam5"));
    assert!(r.message.contains("t5"), "{}", r.message);
    // t4–t5–t6 linked among themselves but not to t1.
    let mut b = m.clone();
    b.ring.retain(|r| r.index != 2 && r.index != 5);
    let doc = run(&b);
    assert_eq!(doc.status, Status::Failed);
    let broken: Vec<&str> = doc
        .reasons
        .iter()
        .filter(|r| r.code == "ring_broken")
        .filter_map(|r| r.camera.as_deref())
        .collect();
    assert_eq!(broken, vec!["cam4", "cam5", "cam6"]);
    assert!(doc.extrinsics.is_empty());
}

#[test]
fn two_views_of_one_pair_are_both_used() {
    let (mut m, truth) = session(4, 0.3, &rig_camera(), &aux_camera(), &table2_scene());
    let (other, _) = session(5, 0.3, &rig_camera(), &aux_camera(), &table2_scene());
    let mut again = other.ring[0].clone();
    again.index = 100;
    m.ring.push(again);
    let doc = run(&m);
    assert_eq!(doc.status, Status::Succeeded, "{:?}", doc.reasons);
    let v = doc.vanishing.as_ref().unwrap();
    let pair = v.pairs.iter().find(|p| p.targets == ["t1", "t2"]).unwrap();
    assert_eq!(pair.views, 2);
    assert_eq!(v.ring_views.len(), 9);
    for (cam, gr, gt, _, _) in errors(&doc, &truth) {
        assert!(gr.to_degrees() < 0.1 && gt < 2e-3, "{cam} {gr} {gt}");
    }
}

/// Three auxiliary viewpoints per pair (pitch 40°, 48°, 32°): exact
/// noise-free, and with noise the far cameras' error falls by about √3 against one view
/// per pair (placement study in docs/accuracy.md: with two views per pair every camera
/// meets Wu's 0.05° / 1.1 mm at 0.5 px).
#[test]
fn several_auxiliary_viewpoints_per_pair_are_exact_and_average_the_noise() {
    let three = ring_scene(&RingLayout {
        aux_views: 3,
        ..Default::default()
    });
    let (m, truth) = session(11, 0.0, &rig_camera(), &aux_camera(), &three);
    assert_eq!(m.ring.len(), 24);
    let doc = run(&m);
    assert_eq!(doc.status, Status::Succeeded, "{:?}", doc.reasons);
    for (cam, gr, gt, cr, ct) in errors(&doc, &truth) {
        assert!(
            gr < 1e-6 && gt < 1e-6 && cr < 1e-6 && ct < 1e-6,
            "{cam}: {gr} {gt} {cr} {ct}"
        );
    }
    // Same seeds, one view vs three views per pair: RMS over 12 trials of the global
    // translation error of cameras 4-6 (3-4 transforms from the reference).
    let rms = |scene: &RingScene| {
        let mut sq = 0.0;
        let mut n = 0;
        for seed in 0..12 {
            let (m, truth) = session(200 + seed, 0.5, &rig_camera(), &aux_camera(), scene);
            let doc = run(&m);
            assert_eq!(doc.status, Status::Succeeded, "{:?}", doc.reasons);
            for (cam, _, gt, _, _) in errors(&doc, &truth) {
                if ["cam4", "cam5", "cam6"].contains(&cam.as_str()) {
                    sq += gt * gt;
                    n += 1;
                }
            }
        }
        (sq / n as f64).sqrt()
    };
    let (one, several) = (rms(&table2_scene()), rms(&three));
    assert!(
        several < 0.8 * one,
        "three views {several} m vs one {one} m"
    );
}

#[test]
fn a_fronto_parallel_view_is_explained_and_still_solved() {
    // Camera 3 looks straight down at its target from 0.8 m: both vanishing points at
    // infinity. The pose comes from the corner homography, and the report says so.
    let mut scene = table2_scene();
    let target = scene.ecf_from_target[2];
    let centre = target.apply(&Vec3::new(0.2, 0.0, 0.2));
    let rot = nalgebra::Matrix3::from_columns(&[Vec3::x(), -Vec3::z(), Vec3::y()]);
    scene.ecf_from_cam[2] = Pose::new(rot, centre - Vec3::y() * 0.8);
    let (m, truth) = session(6, 0.0, &rig_camera(), &aux_camera(), &scene);
    let doc = run(&m);
    assert_eq!(doc.status, Status::Degraded, "{:?}", doc.reasons);
    let r = doc
        .reasons
        .iter()
        .find(|r| r.code == "vanishing_point_at_infinity")
        .expect("explained");
    assert_eq!(r.camera.as_deref(), Some("cam3"));
    let v = doc.vanishing.as_ref().unwrap();
    assert_eq!(v.cameras[2].initialised_from, "homography");
    for (cam, gr, gt, _, _) in errors(&doc, &truth) {
        assert!(gr < 1e-6 && gt < 1e-6, "{cam} {gr} {gt}");
    }
}

#[test]
fn a_view_naming_the_wrong_targets_fails_as_inconsistent() {
    // The lines of t2 and t3 swapped in the auxiliary view of that pair: the pair
    // transform is inverted, the ring cannot close, and the result says so.
    let (mut m, _) = session(7, 0.3, &rig_camera(), &aux_camera(), &table2_scene());
    for l in &mut m.ring[1].lines {
        l.target = if l.target == "t2" {
            "t3".into()
        } else {
            "t2".into()
        };
    }
    let doc = run(&m);
    assert_eq!(doc.status, Status::Failed, "{:?}", doc.reasons);
    assert!(
        codes(&doc).contains(&"inconsistent_ring"),
        "{:?}",
        doc.reasons
    );
}
