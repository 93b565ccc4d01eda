//! Per-camera error of the linear initialisation against the truth (a debugging aid):
//! `cargo run --release --example debug_init -- PRESET SEED SIGMA`.
use rigcal_core::geometry::so3;
fn main() {
    let a: Vec<String> = std::env::args().collect();
    let preset = a.get(1).map(String::as_str).unwrap_or("car-planar-loop");
    let seed: u64 = a.get(2).and_then(|s| s.parse().ok()).unwrap_or(1000);
    let sigma: f64 = a.get(3).and_then(|s| s.parse().ok()).unwrap_or(1.0);
    let (s, truth) =
        rigcal_bench::accuracy::synthetic_session(preset, seed, sigma).expect("preset");
    let lm = rigcal_solve::bundle::LmOptions {
        loss: rigcal_solve::Loss::Huber { scale: 2.0 },
        ..Default::default()
    };
    let t = rigcal_calib::trajectory::estimate(&s, &lm).expect("trajectories");
    for (i, sc) in t.scenes.iter().enumerate() {
        println!(
            "scene {i}: {} poses, {} points, scale {:?}, part_of {:?}",
            sc.poses.len(),
            sc.points.len(),
            sc.scale,
            sc.part_of
        );
    }
    for (i, sc) in t.scenes.iter().enumerate() {
        let keys: Vec<_> = sc.poses.keys().copied().collect();
        let mut ratios = vec![];
        for a in &keys {
            for b in &keys {
                if a.1 != b.1 || a.0 >= b.0 {
                    continue;
                }
                let est = sc.poses[b] * sc.poses[a].inverse();
                let x = truth.ref_from_cam[&s.cameras[a.1].id];
                let tru = (truth.world_from_rig[b.0] * x).inverse() * truth.world_from_rig[a.0] * x;
                if tru.trans.norm() > 0.2 {
                    ratios.push(est.trans.norm() / tru.trans.norm());
                }
            }
        }
        ratios.sort_by(|a, b| a.total_cmp(b));
        if !ratios.is_empty() {
            println!(
                "scene {i} motion length ratio median {:.5}",
                ratios[ratios.len() / 2]
            );
        }
    }
    let init = rigcal_calib::handeye::initialise(&s, &t).expect("init");
    println!(
        "class {:?} axis {:?} pairs used {} small {} near180 {} perm {} scale {:?}",
        init.motion.class,
        init.motion.axis,
        init.pairs_used,
        init.pairs_dropped_small,
        init.pairs_dropped_near_180,
        init.permutation,
        init.scene_scale
    );
    let doc =
        rigcal_engine::pipeline::calibrate(&s, &rigcal_engine::pipeline::CalibOptions::default());
    let w0 = truth.world_from_rig[0].inverse();
    let mut line = String::from("rig dR deg:");
    for (f, w) in init.world_from_rig.iter().enumerate() {
        if let Some(w) = w {
            let t = w0 * truth.world_from_rig[f];
            line += &format!(" {:.3}", so3::angle_between(&w.rot, &t.rot).to_degrees());
        }
    }
    println!("{line}");
    for (c, cam) in s.cameras.iter().enumerate() {
        let tr = truth.ref_from_cam[&cam.id];
        let e = init.ref_from_cam[c];
        let dr = so3::angle_between(&e.rot, &tr.rot).to_degrees();
        let dt = (e.trans - tr.trans) * 1e3;
        let ax = rigcal_core::geometry::Vec3::from(init.motion.axis);
        let w = so3::log(&(e.rot * tr.rot.transpose()));
        let about = w.dot(&ax).to_degrees();
        let tilt = (w - ax * w.dot(&ax)).norm().to_degrees();
        let ba = rigcal_core::result::ExtrinsicValue::pose(&doc.extrinsics[c].value);
        let wb = so3::log(&(ba.rot * tr.rot.transpose()));
        println!(
            "{:>6}: dR {:.4} deg (about axis {:.4}, tilt {:.4})  dt [{:.1} {:.1} {:.1}] mm | BA about {:.4} tilt {:.4}",
            cam.id, dr, about, tilt, dt[0], dt[1], dt[2], wb.dot(&ax).to_degrees(), (wb - ax * wb.dot(&ax)).norm().to_degrees()
        );
    }
}
