//! `cargo bench --bench detect`: detection of one dense realistic 1920×1080 image (the
//! `car-hall` preset, seed 1, frame 0 of the front camera: 8 AprilGrids and wall tags,
//! 77 tags; blur, vignetting, gain, noise, JPEG q 92), so that regressions of the
//! detector's speed show, at both detection qualities. The image is rendered once per run (a few seconds).
//! Also the X-junction scan for unseeded boards on that image, the decoding of that image
//! as a colour JPEG, and one realistic view of a thin-line "#" grid (`line_grid_rig_view`).
//! Medians over samples; see docs/performance.md.

use rigcal_detect::gray::Gray;
use rigcal_detect::{detect_tags, DetectOptions, Quality};
use rigcal_synth::hall::{hall, Hall, Nuisance};

fn main() {
    divan::main();
}

/// The hall and its dense image (front camera, frame 0).
fn dense_hall() -> (Hall, Gray) {
    let h = hall("car-hall", 1, None).expect("preset");
    let nuisance = Nuisance::default();
    let jpeg = Hall::encode(&h.render(0, 0, &nuisance, 7), &nuisance).expect("encode");
    let img = Gray::from_dynamic(&image::load_from_memory(&jpeg).expect("decode"));
    (h, img)
}

#[divan::bench(sample_count = 10, args = [Quality::Accurate, Quality::Fast])]
fn dense_hall_image_1080p(bencher: divan::Bencher, quality: Quality) {
    let (h, img) = dense_hall();
    let camera = &h.cameras[0].1;
    let opts = DetectOptions::of_quality(quality);
    rigcal_detect::quads::warm_up(&opts.quads).expect("detector");
    bencher.bench(|| detect_tags(&img, &h.targets, Some(camera), &opts).expect("detect"));
}

/// Decoding a colour 1080p JPEG into the detector's grey levels: the luma plane
/// (`imageio::decode_gray`) against the general decoder's RGB turned grey, on the dense
/// hall image tinted (channels × 0.85 / 0.97 / 1.08) and encoded at quality 92.
#[divan::bench(sample_count = 20, args = ["luma plane", "rgb then grey"])]
fn colour_jpeg_1080p_to_grey(bencher: divan::Bencher, path: &str) {
    let (_, img) = dense_hall();
    let rgb = image::RgbImage::from_fn(img.width as u32, img.height as u32, |x, y| {
        let v = img.data[y as usize * img.width + x as usize];
        image::Rgb([0.85 * v, 0.97 * v, (1.08 * v).min(255.0)].map(|c| c.round() as u8))
    });
    let mut jpeg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 92)
        .encode_image(&rgb)
        .expect("encode");
    let luma = path == "luma plane";
    bencher.bench(|| {
        if luma {
            rigcal_detect::imageio::decode_gray(&jpeg, None, u64::MAX)
                .expect("decode")
                .1
        } else {
            Gray::from_dynamic(&image::load_from_memory(&jpeg).expect("decode"))
        }
    });
}

/// The X-junction scan that places the bright-grown searches for unseeded boards
/// (`crossings::board_crops`) on the same image, with no tag found (every board's
/// junctions unexplained: its most expensive case).
#[divan::bench(sample_count = 20)]
fn board_crops_dense_hall_1080p(bencher: divan::Bencher) {
    let (_, img) = dense_hall();
    let px = img.to_u8();
    let floor = rigcal_detect::quads::QuadOptions::default().contrast_for(&img);
    bencher.bench(|| rigcal_detect::crossings::board_crops(&px, img.width, img.height, floor, &[]));
}

/// Thin-line targets: one realistic 1024×768 rig view of the "#" grid of Wu's ring
/// (camera 0 of Table 2's scene, radtan lens, textured floor, blur, vignetting, noise σ 2
/// grey, JPEG q 92), ridge points at every scale through labelling.
#[divan::bench(sample_count = 10)]
fn line_grid_rig_view(bencher: divan::Bencher) {
    use rigcal_core::geometry::{Camera, CameraModel};
    use rigcal_detect::linegrid::detect_line_grids;
    use rigcal_detect::refine::Lens;
    use rigcal_synth::ring::{render_line_targets_real, rig_camera, table2_scene, RingPrint};
    let scene = table2_scene();
    let print = RingPrint::GRID;
    let layout = print.layout();
    let nuisance = Nuisance {
        noise: 2.0,
        ..Nuisance::default()
    };
    let cam = Camera {
        model: CameraModel::Radtan {
            k1: -0.25,
            k2: 0.08,
            p1: 0.0005,
            p2: -0.0004,
            k3: 0.0,
        },
        ..rig_camera()
    };
    let pose = scene.ecf_from_cam[0].inverse() * scene.ecf_from_target[0] * print.l_from_target();
    let img = render_line_targets_real(&cam, &[pose], &layout, &nuisance, 40);
    let jpeg = Hall::encode(&img, &nuisance).expect("encode");
    let gray = Gray::from_dynamic(&image::load_from_memory(&jpeg).expect("decode"));
    bencher.bench(|| {
        let found = detect_line_grids(&gray, Lens(Some(&cam)), &layout);
        assert_eq!(found.len(), 1, "one print");
        found
    });
}
