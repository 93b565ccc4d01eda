//! Run the detection stage on a session of images and write the detected session (a
//! debugging aid): `cargo run --release --example detect_session -- DIR/session.json OUT.json`.
use rigcal_engine::pipeline::detection::{detect_session, DirSource};

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let path = std::path::PathBuf::from(&a[1]);
    let s =
        rigcal_core::session::parse_session(&std::fs::read(&path).expect("read")).expect("valid");
    let dir = path.parent().expect("a directory").to_path_buf();
    let (detected, report) = detect_session(
        &s,
        &DirSource(dir),
        rigcal_core::result::DetectionQuality::Accurate,
        &rigcal_engine::pipeline::Silent,
    )
    .unwrap_or_else(|e| panic!("{e:?}"));
    std::fs::write(
        &a[2],
        serde_json::to_vec_pretty(&detected.manifest).expect("json"),
    )
    .expect("write");
    if let Some(r) = report {
        eprintln!(
            "{} images, {} points, {:.1} s",
            r.images_total, r.points_total, r.seconds
        );
    }
}
