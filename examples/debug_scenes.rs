//! Print the per-scene reconstruction summary of a session (a debugging aid).
fn main() {
    let path = std::env::args().nth(1).expect("session.json");
    let s =
        rigcal_core::session::parse_session(&std::fs::read(path).expect("read")).expect("valid");
    let t = rigcal_calib::trajectory::estimate(&s, &Default::default()).expect("trajectories");
    for (i, sc) in t.scenes.iter().enumerate() {
        println!(
            "scene {i}: {} points, {} bodies, {} posed images, scale {:?}, sigma {:.3}",
            sc.points.len(),
            sc.bodies.len(),
            sc.poses.len(),
            sc.scale,
            sc.sigma_px
        );
    }
    for (s, why) in &t.failed_scenes {
        println!("scene {s} failed: {why}");
    }
}
