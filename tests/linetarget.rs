//! Line-target detection on rendered images with known truth: Wu's Table 2 ring (every
//! rig camera's own target, every auxiliary image's pair) and oblique views through
//! distorting lenses. Corners, line points and vanishing points against the truth.

use rigcal_core::geometry::{so3, Camera, Pose, Vec2, Vec3};
use rigcal_core::target::line_target::{LineTarget, LINES, X_GROUP, Z_GROUP};
use rigcal_detect::gray::Gray;
use rigcal_detect::linetarget::{detect_line_targets, LineTargetDetection};
use rigcal_detect::refine::Lens;
use rigcal_synth::render::RenderOptions;
use rigcal_synth::ring::{aux_camera, render_line_targets, rig_camera, table2_scene, TARGET};
use rigcal_synth::tagscene::Lens as SynthLens;

fn opts(seed: u64, noise: f64) -> RenderOptions {
    RenderOptions::noisy(seed, noise)
}

/// Errors of one detection against the truth: max corner error (px), RMS distance of
/// the line points from the true lines (px, measured along the image normal of the
/// true projected line), and the angle (deg) between detected and true vanishing
/// directions.
fn errors(
    camera: &Camera,
    cam_from_target: &Pose,
    target: &LineTarget,
    d: &LineTargetDetection,
) -> (f64, f64, f64) {
    let truth = target.corners();
    let proj = |x: Vec3| camera.project(&cam_from_target.apply(&x)).unwrap();
    let corner = (0..LINES)
        .map(|k| (Vec2::new(d.corners[k][0], d.corners[k][1]) - proj(truth[k])).norm())
        .fold(0.0, f64::max);
    let (mut sq, mut n) = (0.0, 0usize);
    for l in &d.lines {
        let (a, b) = target.segment(l.line - 1);
        // The true line through the points: in the undistorted plane it is straight.
        let qa = cam_from_target.apply(&a);
        let qb = cam_from_target.apply(&b);
        let (pa, pb) = (
            Vec2::new(qa.x / qa.z, qa.y / qa.z),
            Vec2::new(qb.x / qb.z, qb.y / qb.z),
        );
        let normal = Vec2::new(pb.y - pa.y, pa.x - pb.x).normalize();
        for p in &l.points {
            let q = camera.unproject(&Vec2::new(p[0], p[1])).unwrap();
            // Back to pixels: the distance in the plane times the local focal length.
            sq += (normal.dot(&(q - pa)) * camera.fx).powi(2);
            n += 1;
        }
    }
    let line_rms = (sq / n.max(1) as f64).sqrt();
    let mut vp_err: f64 = 0.0;
    for (g, axis) in [(Z_GROUP, Vec3::z()), (X_GROUP, Vec3::x())] {
        let _ = g;
        let i = if axis == Vec3::z() { 0 } else { 1 };
        let v = d.vanishing_points[i];
        let dir = Vec3::new(v[0], v[1], v[2]).normalize();
        let truth = (cam_from_target.rot * axis).normalize();
        let ang = dir.dot(&truth).abs().min(1.0).acos().to_degrees();
        vp_err = vp_err.max(ang);
    }
    (corner, line_rms, vp_err)
}

/// Auxiliary image `k` of the Table 2 ring (targets `k` and `k + 1`) and the two
/// `aux_from_target` poses.
fn aux_view(
    scene: &rigcal_synth::ring::RingScene,
    aux: &Camera,
    k: usize,
) -> (image::GrayImage, Vec<Pose>) {
    let poses = aux_poses(scene, k);
    let img = render_line_targets(aux, &poses, &TARGET.layout(), &opts(100 + k as u64, 2.0));
    (img, poses)
}

/// `aux_from_target` of auxiliary view `k`'s two targets.
fn aux_poses(scene: &rigcal_synth::ring::RingScene, k: usize) -> Vec<Pose> {
    [k, (k + 1) % 8]
        .iter()
        .map(|t| scene.ecf_from_aux[k].inverse() * scene.ecf_from_target[*t])
        .collect()
}

/// Where a target's centre lands across the image (u, px): left-to-right order.
fn centre_u(camera: &Camera, cam_from_target: &Pose) -> f64 {
    let c: Vec3 = TARGET.corners().iter().sum::<Vec3>() / LINES as f64;
    camera.project(&cam_from_target.apply(&c)).unwrap().x
}

/// Rendered views are kept for inspection.
fn save(img: &image::GrayImage, name: &str) {
    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("linetarget-views");
    let _ = std::fs::create_dir_all(&dir);
    let _ = img.save(dir.join(format!("{name}.png")));
}

#[test]
fn table2_ring_rig_and_auxiliary_images() {
    let scene = table2_scene();
    let (rig, aux) = (rig_camera(), aux_camera());
    let mut worst = (0.0f64, 0.0f64, 0.0f64);
    // Sums of squared corner-max and vanishing-direction errors, and their count.
    let mut sq = (0.0f64, 0.0f64, 0usize);
    for k in 0..8 {
        let cam_from_target = scene.ecf_from_cam[k].inverse() * scene.ecf_from_target[k];
        let img = render_line_targets(
            &rig,
            &[cam_from_target],
            &TARGET.layout(),
            &opts(k as u64, 2.0),
        );
        save(&img, &format!("rig{}", k + 1));
        let found = detect_line_targets(&Gray::from_luma8(&img), Lens(Some(&rig)));
        assert_eq!(
            found.len(),
            1,
            "rig camera {}: {} targets",
            k + 1,
            found.len()
        );
        let e = errors(&rig, &cam_from_target, &TARGET, &found[0]);
        eprintln!(
            "rig cam{}: corner max {:.3} px, line rms {:.3} px, vp {:.3}°",
            k + 1,
            e.0,
            e.1,
            e.2
        );
        worst = (worst.0.max(e.0), worst.1.max(e.1), worst.2.max(e.2));
        sq = (sq.0 + e.0 * e.0, sq.1 + e.2 * e.2, sq.2 + 1);
        // Each line is supported along (nearly) its whole visible length.
        for l in &found[0].lines {
            assert!(
                l.points.len() >= 20,
                "cam{} l{}: {} points",
                k + 1,
                l.line,
                l.points.len()
            );
        }
    }
    for k in 0..8 {
        let (img, poses) = aux_view(&scene, &aux, k);
        save(&img, &format!("aux{k}"));
        let found = detect_line_targets(&Gray::from_luma8(&img), Lens(Some(&aux)));
        assert_eq!(found.len(), 2, "aux image {k}: {} targets", found.len());
        // Left to right: match the truth by the projected centroid.
        let centre_u = |p: &Pose| centre_u(&aux, p);
        let mut order = poses.clone();
        order.sort_by(|a, b| centre_u(a).total_cmp(&centre_u(b)));
        for (d, p) in found.iter().zip(&order) {
            let e = errors(&aux, p, &TARGET, d);
            eprintln!(
                "aux {k}: corner max {:.3} px, line rms {:.3} px, vp {:.3}°",
                e.0, e.1, e.2
            );
            worst = (worst.0.max(e.0), worst.1.max(e.1), worst.2.max(e.2));
            sq = (sq.0 + e.0 * e.0, sq.1 + e.2 * e.2, sq.2 + 1);
        }
    }
    let (corner_rms, vp_rms) = ((sq.0 / sq.2 as f64).sqrt(), (sq.1 / sq.2 as f64).sqrt());
    eprintln!(
        "worst: corner {:.3} px, line rms {:.3} px, vp {:.3}°; RMS over the {} targets: corner (max of 6) {corner_rms:.3} px, vp {vp_rms:.4}°",
        worst.0, worst.1, worst.2, sq.2
    );
    assert!(worst.0 < 0.15, "corner error {:.3} px", worst.0);
    assert!(worst.1 < 0.1, "line point RMS {:.3} px", worst.1);
    // Issue 3: corners ≤ 0.05 px RMS, vanishing directions within 0.02° (RMS; the
    // auxiliary views' small Ls reach 0.035° at worst).
    assert!(corner_rms <= 0.05, "corner RMS {corner_rms:.3} px");
    assert!(vp_rms <= 0.02, "vanishing direction RMS {vp_rms:.4}°");
}

#[test]
fn distorted_oblique_views_and_noise_free_exactness() {
    let target = LineTarget {
        length: 0.5,
        spacing: 0.2,
    };
    for (lens, noise) in [
        (SynthLens::Pinhole, 0.0),
        (SynthLens::Radtan, 2.0),
        (SynthLens::Equidistant, 2.0),
    ] {
        let cam = lens.camera(1600, 1200);
        for (view, (tilt, yaw)) in [(20.0f64, 10.0f64), (45.0, -30.0), (55.0, 35.0)]
            .iter()
            .enumerate()
        {
            // The target 1.1 m ahead, its plane tilted away and turned; its printed side
            // (−y, as on the ring) faces the camera.
            let rot = so3::exp(&Vec3::new(0.0, yaw.to_radians(), 0.0))
                * so3::exp(&Vec3::new((90.0 - tilt).to_radians(), 0.0, 0.0));
            let centre = Vec3::new(0.25, 0.0, 0.25);
            let cam_from_target = Pose::new(rot, Vec3::new(0.0, 0.0, 1.1) - rot * centre);
            let img = render_line_targets(
                &cam,
                &[cam_from_target],
                &target.layout(),
                &opts(view as u64, noise),
            );
            save(&img, &format!("{lens:?}-{view}"));
            let found = detect_line_targets(&Gray::from_luma8(&img), Lens(Some(&cam)));
            assert_eq!(
                found.len(),
                1,
                "{lens:?} view {view}: {} targets",
                found.len()
            );
            let e = errors(&cam, &cam_from_target, &target, &found[0]);
            eprintln!("{lens:?} view {view} (tilt {tilt}°): corner max {:.3} px, line rms {:.3} px, vp {:.4}°", e.0, e.1, e.2);
            let (corner_tol, line_tol) = if noise == 0.0 {
                (0.02, 0.05)
            } else {
                (0.15, 0.1)
            };
            assert!(
                e.0 < corner_tol,
                "{lens:?} view {view}: corner {:.3} px",
                e.0
            );
            assert!(
                e.1 < line_tol,
                "{lens:?} view {view}: line rms {:.3} px",
                e.1
            );
        }
    }
}

#[test]
fn nothing_on_images_without_a_line_target() {
    let cam = SynthLens::Pinhole.camera(640, 480);
    // A filled square and a filled triangle on white: no notch, no L.
    let shapes = |x: f64, y: f64| -> Option<bool> {
        let square = (0.05..0.25).contains(&x) && (0.05..0.25).contains(&y);
        let triangle = x > 0.3 && y > 0.05 && x - 0.3 < (y - 0.05) && y < 0.25;
        Some(!(square || triangle))
    };
    let pose = Pose::new(
        so3::exp(&Vec3::new(0.0, 0.0, 0.0)),
        Vec3::new(-0.2, -0.15, 0.6),
    );
    let img = rigcal_synth::render::render(&cam, &pose, &shapes, &opts(7, 2.0));
    let found = detect_line_targets(&Gray::from_luma8(&img), Lens(Some(&cam)));
    assert!(found.is_empty(), "{} false targets", found.len());
    // Pure noise.
    let noise = rigcal_synth::render::render(&cam, &pose, &|_, _| None, &opts(8, 20.0));
    assert!(detect_line_targets(&Gray::from_luma8(&noise), Lens(Some(&cam))).is_empty());
}

/// Wu's Table 2 ring from rendered images: 8 rig images and 8 auxiliary images go
/// through `rigcal calibrate` (detection stage, then the vanishing method); every
/// camera's extrinsic against the truth.
#[test]
fn table2_ring_calibrates_from_rendered_images() {
    let dir = tempfile::tempdir().unwrap();
    let (manifest, truth, files) =
        rigcal_synth::ring::image_session(&rig_camera(), &aux_camera(), &table2_scene(), 2.0, 5);
    for (path, bytes) in &files {
        let p = dir.path().join(path);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, bytes).unwrap();
    }
    let m = serde_json::to_value(&manifest).unwrap();
    let path = dir.path().join("session.json");
    std::fs::write(&path, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_rigcal"))
        .arg("calibrate")
        .arg(&path)
        .output()
        .unwrap();
    let doc: serde_json::Value = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&out.stderr)));
    assert_eq!(
        doc["detection"]["images_total"], 16,
        "{:#}",
        doc["detection"]
    );
    assert_eq!(
        doc["detection"]["images_skipped"], 0,
        "{:#}",
        doc["detection"]
    );
    assert_eq!(doc["status"], "succeeded", "{:#}", doc["reasons"]);
    let (mut worst_t, mut worst_r) = (0.0f64, 0.0f64);
    for e in doc["extrinsics"].as_array().unwrap() {
        let cam = e["camera"].as_str().unwrap();
        let m: [[f64; 4]; 4] = serde_json::from_value(e["ref_from_cam"].clone()).unwrap();
        let rot = nalgebra::Matrix3::from_fn(|r, c| m[r][c]);
        let t = Vec3::new(m[0][3], m[1][3], m[2][3]);
        let want = &truth.ref_from_cam[cam];
        let (dt, dr) = (
            (t - want.trans).norm() * 1000.0,
            so3::angle_between(&rot, &want.rot).to_degrees(),
        );
        eprintln!("{cam}: {dt:.3} mm, {dr:.4}°");
        worst_t = worst_t.max(dt);
        worst_r = worst_r.max(dr);
    }
    eprintln!("worst: {worst_t:.3} mm, {worst_r:.4}°");
    // Wu claims 1.1 mm and 0.05° at σ ≤ 0.5 px on the line points; the detector's
    // points are good to ~0.03 px here (see the tests above).
    assert!(worst_t < 0.5 && worst_r < 0.02, "{worst_t} mm, {worst_r}°");
}

/// Heavy image noise (σ 10 grey levels of a 205-level step) on the whole ring: every
/// target still found and labelled. Rough corners from thresholding lose acute tips
/// under such noise (11 px seen on a grazing rig view); the sides still place them.
#[test]
fn heavy_noise_still_finds_every_target() {
    let scene = table2_scene();
    let (rig, aux) = (rig_camera(), aux_camera());
    let mut worst: f64 = 0.0;
    for seed in 0..2u64 {
        for k in 0..8 {
            let cam_from_target = scene.ecf_from_cam[k].inverse() * scene.ecf_from_target[k];
            let img = render_line_targets(
                &rig,
                &[cam_from_target],
                &TARGET.layout(),
                &opts(seed * 100 + k as u64, 10.0),
            );
            let found = detect_line_targets(&Gray::from_luma8(&img), Lens(Some(&rig)));
            assert_eq!(found.len(), 1, "seed {seed} rig {k}");
            worst = worst.max(errors(&rig, &cam_from_target, &TARGET, &found[0]).0);
            let poses = aux_poses(&scene, k);
            let img = render_line_targets(
                &aux,
                &poses,
                &TARGET.layout(),
                &opts(seed * 100 + 50 + k as u64, 10.0),
            );
            let found = detect_line_targets(&Gray::from_luma8(&img), Lens(Some(&aux)));
            assert_eq!(found.len(), 2, "seed {seed} aux {k}");
        }
    }
    eprintln!("σ 10 grey levels: worst rig corner error {worst:.3} px");
    assert!(worst < 0.25, "{worst}");
}
