//! Compare per-camera relative motions with the truth (a debugging aid).
use rigcal_core::geometry::so3;
fn main() {
    let dir = std::path::PathBuf::from(std::env::args().nth(1).expect("dir"));
    let s = rigcal_core::session::parse_session(&std::fs::read(dir.join("session.json")).unwrap())
        .unwrap();
    let truth: rigcal_synth::Truth =
        serde_json::from_slice(&std::fs::read(dir.join("truth.json")).unwrap()).unwrap();
    let lm = rigcal_solve::bundle::LmOptions {
        loss: rigcal_solve::Loss::Huber { scale: 2.0 },
        ..Default::default()
    };
    let t = rigcal_calib::trajectory::estimate(&s, &lm).unwrap();
    for (si, sc) in t.scenes.iter().enumerate() {
        let keys: Vec<_> = sc.poses.keys().copied().collect();
        let k0 = keys[0];
        for k in &keys[1..] {
            let est = sc.poses[k] * sc.poses[&k0].inverse(); // cam_k from cam_k0
            let xc0 = truth.ref_from_cam[&s.cameras[k0.1].id];
            let xc = truth.ref_from_cam[&s.cameras[k.1].id];
            let tru = (truth.world_from_rig[k.0] * xc).inverse() * truth.world_from_rig[k0.0] * xc0;
            let (dr, dt) = est.distance(&tru);
            println!(
                "scene {si} img {:?} vs {:?}: dR {:.3} deg dt {:.1} mm (motion {:.1} deg)",
                k,
                k0,
                dr.to_degrees(),
                dt * 1e3,
                so3::log(&tru.rot).norm().to_degrees()
            );
        }
    }
}
