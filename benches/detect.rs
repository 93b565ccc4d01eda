//! `cargo bench --bench detect`: detection of one dense realistic 1920×1080 image (the
//! `car-hall` preset, seed 1, frame 0 of the front camera: 8 AprilGrids and wall tags,
//! 77 tags; blur, vignetting, gain, noise, JPEG q 92), so that regressions of the
//! detector's speed show, at both detection qualities. The image is rendered once per run (a few seconds).
//! Medians over samples; see docs/performance.md.

use rigcal_detect::gray::Gray;
use rigcal_detect::{detect_tags, DetectOptions, Quality};
use rigcal_synth::hall::{hall, Hall, Nuisance};

fn main() {
    divan::main();
}

#[divan::bench(sample_count = 10, args = [Quality::Accurate, Quality::Fast])]
fn dense_hall_image_1080p(bencher: divan::Bencher, quality: Quality) {
    let h = hall("car-hall", 1, None).expect("preset");
    let nuisance = Nuisance::default();
    let jpeg = Hall::encode(&h.render(0, 0, &nuisance, 7), &nuisance).expect("encode");
    let img = Gray::from_dynamic(&image::load_from_memory(&jpeg).expect("decode"));
    let camera = &h.cameras[0].1;
    let opts = DetectOptions::of_quality(quality);
    rigcal_detect::quads::warm_up(&opts.quads).expect("detector");
    bencher.bench(|| detect_tags(&img, &h.targets, Some(camera), &opts).expect("detect"));
}
