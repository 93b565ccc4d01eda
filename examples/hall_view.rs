//! Render one image of a hall preset and say how long it took:
//! `cargo run --release --example hall_view -- car-hall FRAME CAMERA OUT.png [SEED]`.

use rigcal_synth::hall::{hall, Hall, Nuisance};
use std::time::Instant;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    if a.len() < 5 {
        eprintln!("usage: hall_view PRESET FRAME CAMERA OUT.png [SEED]");
        std::process::exit(2);
    }
    let seed = a.get(5).and_then(|s| s.parse().ok()).unwrap_or(1);
    let h = hall(&a[1], seed, None).unwrap_or_else(|e| panic!("{e}"));
    let frame: usize = a[2].parse().expect("frame");
    let cam = h
        .cameras
        .iter()
        .position(|c| c.0 == a[3])
        .expect("camera id");
    let t = Instant::now();
    let img = h.render(frame, cam, &Nuisance::default(), 7);
    let ms = t.elapsed().as_secs_f64() * 1e3;
    let n = Nuisance {
        jpeg_quality: None,
        ..Default::default()
    };
    std::fs::write(&a[4], Hall::encode(&img, &n).expect("encode")).expect("write");
    println!(
        "{ms:.0} ms, {} visible tags",
        h.visible(frame, cam).len() / 4
    );
}
