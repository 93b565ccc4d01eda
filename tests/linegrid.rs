//! Thin-line targets ("#" grids) in rendered images with known truth: the ridge
//! detector's line points against the true centre lines, the labelling against the
//! layout, and whole rings of images through the vanishing method.

use rigcal_core::geometry::line2::{bisector, distance, through};
use rigcal_core::geometry::{Camera, CameraModel, Pose, Vec2, Vec3};
use rigcal_core::target::line_layout::{Axis, LineLayout, Print};
use rigcal_detect::gray::Gray;
use rigcal_detect::linegrid::{detect_line_grids, LineGridDetection};
use rigcal_detect::refine::Lens;
use rigcal_synth::hall::{Hall, Nuisance};
use rigcal_synth::render::RenderOptions;
use rigcal_synth::ring::{
    aux_camera, render_line_targets, render_line_targets_real, rig_camera, table2_scene, RingPrint,
};

fn opts(seed: u64, noise: f64) -> RenderOptions {
    RenderOptions::noisy(seed, noise)
}

/// RMS (px) of the detected points' distances to the true centres of the lines they
/// were labelled with.
fn errors(
    camera: &Camera,
    cam_from_target: &Pose,
    layout: &LineLayout,
    d: &LineGridDetection,
) -> f64 {
    let (mut sq, mut count) = (0.0, 0usize);
    for l in &d.lines {
        // The true centre of the stroke's image: the bisector of its two edges' images
        // (under perspective neither the image of the stroke's centre line nor the line
        // through the midpoints of its ends).
        let (a, b) = layout.segment(l.line - 1);
        let Print::Strokes { width } = layout.print else {
            panic!("a stroke layout")
        };
        let off = match layout.segments[l.line - 1].axis {
            Axis::X => Vec3::z(),
            Axis::Z => Vec3::x(),
        } * (width / 2.0);
        let plane = |x: Vec3| {
            let q = cam_from_target.apply(&x);
            Vec2::new(q.x / q.z, q.y / q.z)
        };
        let edge = |o: Vec3| through(&plane(a + o), &plane(b + o)).unwrap();
        let centre = bisector(&edge(off), &edge(-off)).unwrap();
        for p in &l.points {
            let q = camera.unproject(&Vec2::new(p[0], p[1])).unwrap();
            sq += (distance(&centre, &q) * camera.fx).powi(2);
            count += 1;
        }
    }
    (sq / count.max(1) as f64).sqrt()
}

/// The grid's frame in the detection's labelling: the symmetry that makes the labels
/// fit the truth best (the detector may report any of the equivalent labellings).
fn best_symmetry_rms(
    camera: &Camera,
    cam_from_target: &Pose,
    layout: &LineLayout,
    d: &LineGridDetection,
) -> f64 {
    layout
        .symmetries()
        .iter()
        .map(|s| {
            errors(
                camera,
                &(*cam_from_target * s.target_from_labelled),
                layout,
                d,
            )
        })
        .fold(f64::INFINITY, f64::min)
}

#[test]
fn every_rig_camera_finds_its_grid_with_centre_points_within_five_hundredths_of_a_pixel() {
    let scene = table2_scene();
    let cam = rig_camera();
    for print in [
        RingPrint::GRID,
        RingPrint::Grid {
            lines_x: 3,
            lines_y: 2,
            stroke: 0.010,
            marked: false,
        },
    ] {
        let layout = print.layout();
        let mut worst = 0.0f64;
        for k in 0..8 {
            let pose =
                scene.ecf_from_cam[k].inverse() * scene.ecf_from_target[k] * print.l_from_target();
            let img = render_line_targets(&cam, &[pose], &layout, &opts(k as u64, 2.0));
            let found = detect_line_grids(&Gray::from_luma8(&img), Lens(Some(&cam)), &layout);
            assert_eq!(
                found.len(),
                1,
                "{print:?} camera {k}: {} prints",
                found.len()
            );
            let d = &found[0];
            assert_eq!(d.lines.len(), layout.len());
            assert!(
                d.lines.iter().all(|l| l.points.len() >= 10),
                "{print:?} camera {k}"
            );
            let rms = best_symmetry_rms(&cam, &pose, &layout, d);
            worst = worst.max(rms);
        }
        assert!(worst <= 0.05, "{print:?}: line point RMS {worst:.4} px");
    }
}

/// No lens, radtan (barrel, 8 % at the image corner) and equidistant (a fisheye of the
/// same focal length).
const LENSES: [CameraModel; 3] = [
    CameraModel::Pinhole,
    CameraModel::Radtan {
        k1: -0.25,
        k2: 0.08,
        p1: 0.0005,
        p2: -0.0004,
        k3: 0.0,
    },
    CameraModel::Equidistant {
        k1: 0.02,
        k2: -0.01,
        k3: 0.0,
        k4: 0.0,
    },
];

/// The rig camera with one of the [`LENSES`].
fn rig_lens(model: CameraModel) -> Camera {
    Camera {
        model,
        ..rig_camera()
    }
}

#[test]
fn grids_in_realistic_captures_are_found_at_every_lens() {
    // As a real capture shows them: a textured tile floor around the sheet, blur,
    // vignetting, per-image gain and offset, sensor noise σ 2 grey, JPEG q 92.
    let scene = table2_scene();
    let print = RingPrint::GRID;
    let layout = print.layout();
    let nuisance = Nuisance {
        noise: 2.0,
        ..Nuisance::default()
    };
    // Each lens on every third camera of the ring (all eight once over the three).
    for (i, model) in LENSES.into_iter().enumerate() {
        let cam = rig_lens(model);
        let mut worst = 0.0f64;
        for k in (i..8).step_by(3) {
            let pose =
                scene.ecf_from_cam[k].inverse() * scene.ecf_from_target[k] * print.l_from_target();
            let img = render_line_targets_real(&cam, &[pose], &layout, &nuisance, 40 + k as u64);
            let jpeg = Hall::encode(&img, &nuisance).unwrap();
            let gray = Gray::from_luma8(&image::load_from_memory(&jpeg).unwrap().to_luma8());
            let found = detect_line_grids(&gray, Lens(Some(&cam)), &layout);
            assert_eq!(
                found.len(),
                1,
                "{model:?} camera {k}: {} prints",
                found.len()
            );
            let d = &found[0];
            assert_eq!(d.lines.len(), layout.len());
            assert!(
                d.lines.iter().all(|l| l.points.len() >= 10),
                "{model:?} camera {k}"
            );
            worst = worst.max(best_symmetry_rms(&cam, &pose, &layout, d));
        }
        // Measured 0.0076-0.0086 px (0.019-0.021 before the centres were settled on
        // derivatives evaluated in place and oblique crossings kept farther off).
        assert!(worst <= 0.05, "{model:?}: line point RMS {worst:.4} px");
    }
}

#[test]
fn auxiliary_views_find_both_grids_left_to_right() {
    let scene = table2_scene();
    let aux = aux_camera();
    let print = RingPrint::GRID;
    let layout = print.layout();
    for i in 0..8 {
        let (k, j) = scene.pair_of(i);
        let poses: Vec<Pose> = [k, j]
            .iter()
            .map(|&t| {
                scene.ecf_from_aux[i].inverse() * scene.ecf_from_target[t] * print.l_from_target()
            })
            .collect();
        let img = render_line_targets(&aux, &poses, &layout, &opts(100 + i as u64, 2.0));
        let found = detect_line_grids(&Gray::from_luma8(&img), Lens(Some(&aux)), &layout);
        let complete: Vec<&LineGridDetection> =
            found.iter().filter(|d| !d.touches_border).collect();
        assert_eq!(
            complete.len(),
            2,
            "view {i}: {} complete prints of {}",
            complete.len(),
            found.len()
        );
        for d in complete {
            let rms = poses
                .iter()
                .map(|p| best_symmetry_rms(&aux, p, &layout, d))
                .fold(f64::INFINITY, f64::min);
            // Measured 0.0045-0.0088 px (0.0066-0.011 before the centres were settled
            // on derivatives evaluated in place, 0.08 px before the stroke model was the
            // bisector of the edges' images).
            assert!(rms <= 0.02, "view {i}: RMS {rms:.4} px");
        }
    }
}

/// One view of a sweep: a `lines_x` × `lines_z` grid with strokes `width_px` wide (at
/// its centre, seen square on) 1-2 m in front of the camera, turned by `turn` (target
/// frame to camera, after the square-on pose).
struct SweepView {
    width_px: f64,
    turn: nalgebra::Matrix3<f64>,
    lines: (usize, usize),
}

/// Detect every view at every lens (σ 2 grey): the worst line-point RMS over the grids
/// found and the views that found none.
fn sweep(views: &[(String, SweepView)], mut seed: u64) -> (f64, Vec<String>) {
    let (mut worst, mut missed) = (0.0f64, Vec::new());
    for model in LENSES {
        let cam = rig_lens(model);
        for (name, v) in views {
            let z = 2.0 - (v.width_px - 3.0) / 12.0;
            let stroke = v.width_px * z / cam.fx;
            let layout = LineLayout::grid(0.5, 0.2, v.lines.0, v.lines.1, stroke);
            // Target x → camera x, its normal (y) away from the camera, z → up.
            let square_on = nalgebra::Matrix3::from_columns(&[Vec3::x(), Vec3::z(), -Vec3::y()]);
            let rot = v.turn * square_on;
            let pose = Pose::new(rot, Vec3::new(0.0, 0.0, z) - rot * layout.centre());
            seed += 1;
            let img = render_line_targets(&cam, &[pose], &layout, &opts(seed, 2.0));
            let found = detect_line_grids(&Gray::from_luma8(&img), Lens(Some(&cam)), &layout);
            let view = format!("{model:?}, {name}");
            assert!(found.len() <= 1, "{view}: {} grids", found.len());
            let Some(d) = found.first() else {
                missed.push(view);
                continue;
            };
            let rms = best_symmetry_rms(&cam, &pose, &layout, d);
            assert!(rms <= 0.05, "{view}: RMS {rms:.4} px");
            worst = worst.max(rms);
        }
    }
    (worst, missed)
}

fn turn(axis: Vec3, deg: f64) -> nalgebra::Matrix3<f64> {
    rigcal_core::geometry::so3::exp(&(axis * deg.to_radians()))
}

#[test]
fn line_points_are_within_five_hundredths_of_a_pixel_for_strokes_of_3_to_15_px_up_to_60_degrees() {
    // The sweep: strokes 3-15 px wide, the sheet turned 0-60° about its
    // horizontal axis, no lens, barrel radtan and a fisheye.
    let mut views = Vec::new();
    for width_px in [3.0, 6.0, 10.0, 15.0] {
        for tilt_deg in [0.0f64, 30.0, 60.0] {
            let v = SweepView {
                width_px,
                turn: turn(Vec3::x(), tilt_deg),
                lines: (3, 3),
            };
            views.push((format!("{width_px} px, {tilt_deg}°"), v));
        }
    }
    let (worst, missed) = sweep(&views, 500);
    eprintln!("worst line-point RMS {worst:.4} px; missed {missed:?}");
    // Measured 0.0038-0.0132 px. Every view finds its grid: the radtan lens with 15 px
    // strokes at 60° once found none (the stub beyond the last crossing curved its
    // chain into the stroke, and the whole chain was refused as a curve).
    assert!(missed.is_empty(), "missed {missed:?}");
}

#[test]
fn grids_turned_about_every_axis_and_in_their_plane_are_found() {
    // Yawed, pitched and rolled sheets, "#" (3×3) and 3×2 grids, the thinnest and the
    // widest strokes. Before chains were cut into straight pieces, 7 of 144 such views
    // (all with 15 px strokes at 60° of yaw or 40° of yaw and pitch) found no grid.
    let mut views = Vec::new();
    for width_px in [3.0, 15.0] {
        for (yaw, pitch, roll) in [
            (30.0, 0.0, 0.0),
            (60.0, 0.0, 0.0),
            (0.0, 30.0, 20.0),
            (0.0, 45.0, 45.0),
            (40.0, 40.0, 30.0),
            (-50.0, 20.0, 10.0),
        ] {
            for lines in [(3, 3), (3, 2)] {
                let v = SweepView {
                    width_px,
                    turn: turn(Vec3::y(), yaw) * turn(Vec3::x(), pitch) * turn(Vec3::z(), roll),
                    lines,
                };
                let name =
                    format!("{width_px} px, yaw {yaw}° pitch {pitch}° roll {roll}°, {lines:?}");
                views.push((name, v));
            }
        }
    }
    let (worst, missed) = sweep(&views, 900);
    eprintln!("worst line-point RMS {worst:.4} px; missed {missed:?}");
    assert!(missed.is_empty(), "missed {missed:?}");
}

#[test]
fn a_blank_or_noisy_image_has_no_grid() {
    let cam = rig_camera();
    let layout = RingPrint::GRID.layout();
    let far = Pose::new(nalgebra::Matrix3::identity(), Vec3::new(0.0, 0.0, -5.0));
    let img = render_line_targets(&cam, &[far], &layout, &opts(1, 2.0));
    assert!(detect_line_grids(&Gray::from_luma8(&img), Lens(Some(&cam)), &layout).is_empty());
}

fn errors_vs_truth(
    doc: &rigcal_core::result::ResultDocument,
    truth: &rigcal_synth::Truth,
) -> (f64, f64) {
    let (mut mm, mut deg) = (0.0f64, 0.0f64);
    for (cam, t) in &truth.ref_from_cam {
        let e = doc
            .extrinsics
            .iter()
            .find(|e| &e.value.camera == cam)
            .unwrap_or_else(|| panic!("no extrinsic for {cam}: {:?}", doc.reasons));
        let (r, d) = e.value.pose().distance(t);
        mm = mm.max(d * 1e3);
        deg = deg.max(r.to_degrees());
    }
    (mm, deg)
}

#[test]
fn grid_detections_recover_the_ring_exactly_whichever_way_round_each_view_labelled_them() {
    use rand::SeedableRng;
    let print = RingPrint::GRID;
    let layout = print.layout();
    let syms = layout.symmetries();
    assert_eq!(syms.len(), 4);
    let mut rng = rand::rngs::StdRng::seed_from_u64(3);
    let (mut m, truth) = rigcal_synth::ring::generate_print(
        &mut rng,
        [0.0, 0.0],
        &rig_camera(),
        &aux_camera(),
        &table2_scene(),
        print,
    );
    // Relabel each auxiliary view's targets by a symmetry, as a detector that cannot tell
    // which way round a "#" lies would: line m reported as the line the symmetry puts there.
    for (i, r) in m.ring.iter_mut().enumerate() {
        for (k, t) in r.targets.clone().iter().enumerate() {
            let g = &syms[if std::env::var_os("NOREL").is_some() {
                0
            } else {
                (i + k) % 4
            }];
            for l in r.lines.iter_mut().filter(|l| &l.target == t) {
                let physical = l.line as usize - 1;
                let label = g.line_of.iter().position(|&p| p == physical).unwrap();
                l.line = label as u8 + 1;
            }
        }
    }
    let session = rigcal_core::session::from_manifest(m).unwrap();
    let doc = rigcal_engine::pipeline::calibrate(&session, &Default::default());
    // Not failed, right, and every view's labelling found; a near-tie of the closure
    // search (some of the 4⁸ relative labellings close within millimetres) is reported
    // as `line_labelling_ambiguous`, so the status may be degraded.
    assert_ne!(
        doc.status,
        rigcal_core::result::Status::Failed,
        "{:?}",
        doc.reasons
    );
    let (mm, deg) = errors_vs_truth(&doc, &truth);
    // Exact: the synthetic points lie on the bisector of each stroke's edge images,
    // which is what the line bundle models.
    assert!(mm < 1e-6 && deg < 1e-7, "{mm} mm {deg}°");
    let report = &doc.vanishing.as_ref().unwrap().labelling;
    assert_eq!(report.len(), 16);
    for c in report {
        let i = c.ring_index as usize;
        let k = usize::from(c.target != format!("t{}", i + 1));
        assert_eq!(c.rotation_deg, syms[(i + k) % 4].degrees, "{c:?}");
    }
}

/// Wu's Table 2 ring printed with `print`, rendered with `noise` grey of sensor noise
/// (0: noise-free, 16-bit): session, truth, images.
fn ring_images(
    print: RingPrint,
    noise: f64,
) -> (
    rigcal_core::session::SessionManifest,
    rigcal_synth::Truth,
    std::collections::BTreeMap<String, Vec<u8>>,
) {
    let look = rigcal_synth::ring::RingImages {
        print,
        nuisance: None,
    };
    rigcal_synth::ring::image_session_with(
        &rig_camera(),
        &aux_camera(),
        &table2_scene(),
        &look,
        noise,
        1,
    )
}

/// That ring calibrated from its images: the result and its errors (mm, °).
fn ring_from_images(print: RingPrint) -> (rigcal_core::result::ResultDocument, f64, f64) {
    let (m, truth, files) = ring_images(print, 0.0);
    let session = rigcal_core::session::from_manifest(m).unwrap();
    let source = rigcal_engine::pipeline::detection::MemorySource(files.into_iter().collect());
    let doc = rigcal_engine::pipeline::run(
        &session,
        &source,
        &Default::default(),
        &rigcal_engine::pipeline::Silent,
    )
    .unwrap();
    let (mm, deg) = errors_vs_truth(&doc, &truth);
    (doc, mm, deg)
}

#[test]
fn a_ring_of_grids_calibrates_from_images() {
    let (doc, mm, deg) = ring_from_images(RingPrint::GRID);
    // The bound for noise-free renders, the detector's own error: measured
    // 0.0148 mm / 0.00084° (16-bit, 48 cells per edge pixel). Rendered at 8 bits with 16
    // cells it was 0.0178 mm / 0.00187°, the render's own noise; before that 0.041 mm /
    // 0.0022° with the derivatives interpolated and points beside oblique crossings,
    // 0.34 mm / 0.008° while the bundle modelled a stroke by the midpoints of its ends.
    assert_ne!(
        doc.status,
        rigcal_core::result::Status::Failed,
        "{:?}",
        doc.reasons
    );
    eprintln!("ring from images: {mm:.4} mm {deg:.5}°");
    assert!(mm < 0.02 && deg < 0.001, "{mm} mm {deg}°");
}

#[test]
fn a_ring_of_marked_grids_leaves_no_labelling_to_decide() {
    let (doc, mm, deg) = ring_from_images(RingPrint::GRID_MARKED);
    // Unmarked, one loop cannot tell 4⁸ labellings apart clearly and the ring is
    // `degraded` (line_labelling_ambiguous); the mark decides every image.
    assert_eq!(
        doc.status,
        rigcal_core::result::Status::Succeeded,
        "{:?}",
        doc.reasons
    );
    assert!(mm < 0.1 && deg < 0.006, "{mm} mm {deg}°");
}

#[test]
fn the_mark_labels_every_view_as_printed_and_a_missing_mark_is_reported() {
    let scene = table2_scene();
    let aux = aux_camera();
    let marked = RingPrint::GRID_MARKED;
    let layout = marked.layout();
    assert_eq!(layout.symmetries().len(), 1);
    for i in 0..8 {
        let (k, j) = scene.pair_of(i);
        let poses: Vec<Pose> = [k, j]
            .iter()
            .map(|&t| {
                scene.ecf_from_aux[i].inverse() * scene.ecf_from_target[t] * marked.l_from_target()
            })
            .collect();
        let img = render_line_targets(&aux, &poses, &layout, &opts(300 + i as u64, 2.0));
        let gray = Gray::from_luma8(&img);
        let found = detect_line_grids(&gray, Lens(Some(&aux)), &layout);
        let complete: Vec<&LineGridDetection> =
            found.iter().filter(|d| !d.touches_border).collect();
        assert_eq!(complete.len(), 2, "view {i}");
        for d in complete {
            assert_eq!(
                (d.equivalent_labellings, &d.mark_error),
                (1, &None),
                "view {i}"
            );
            // The layout's own labels, no symmetry allowed.
            let rms = poses
                .iter()
                .map(|p| errors(&aux, p, &layout, d))
                .fold(f64::INFINITY, f64::min);
            assert!(rms <= 0.02, "view {i}: RMS {rms:.4} px");
        }
        // The same view printed without the disc: the layout's mark is nowhere.
        let unmarked = render_line_targets(
            &aux,
            &poses,
            &RingPrint::GRID.layout(),
            &opts(300 + i as u64, 2.0),
        );
        let found = detect_line_grids(&Gray::from_luma8(&unmarked), Lens(Some(&aux)), &layout);
        for d in found.iter().filter(|d| !d.touches_border) {
            let why = d.mark_error.as_deref().unwrap_or_default();
            assert!(why.contains("clearly dark"), "view {i}: {why:?}");
        }
    }
}

#[test]
fn an_image_whose_mark_cannot_be_read_is_an_image_error_naming_its_target() {
    // The session says the grids carry a mark; the images were printed without it.
    let (m, _, _) = ring_images(RingPrint::GRID_MARKED, 2.0);
    let (_, _, unmarked) = ring_images(RingPrint::GRID, 2.0);
    let session = rigcal_core::session::from_manifest(m).unwrap();
    let source = rigcal_engine::pipeline::detection::MemorySource(unmarked.into_iter().collect());
    let slot = &rigcal_core::session::image_slots(&session)[0];
    let d = rigcal_engine::pipeline::detection::detect_image(
        &session,
        slot,
        &source,
        Default::default(),
    );
    let why = d.report.error.unwrap_or_default();
    assert!(
        why.contains("not which way round") && why.contains("orientation mark"),
        "{why:?}"
    );
}
