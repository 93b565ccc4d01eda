//! Per-scene body and image pose errors against a synthetic truth (a debugging aid):
//! `cargo run --release --example debug_bodies -- DIR` (DIR holds session.json with
//! observations and truth.json).
use rigcal_core::geometry::{so3, Pose, Vec3};
use rigcal_core::session::PointKind;

fn main() {
    let dir = std::path::PathBuf::from(std::env::args().nth(1).expect("dir"));
    let s = rigcal_core::session::parse_session(&std::fs::read(dir.join("session.json")).unwrap())
        .unwrap();
    let truth: rigcal_synth::Truth =
        serde_json::from_slice(&std::fs::read(dir.join("truth.json")).unwrap()).unwrap();
    let t = rigcal_calib::trajectory::estimate(&s, &Default::default()).unwrap();
    // world_from_body of the truth, from three of its corners.
    let truth_body = |b: usize| -> Option<Pose> {
        let pts: Vec<(Vec3, Vec3)> = s
            .points
            .kinds
            .iter()
            .enumerate()
            .filter_map(|(p, k)| match k {
                PointKind::Body { body, local } if *body == b => {
                    let w = truth.points.get(&s.points.ids[p])?;
                    Some((*local, Vec3::new(w[0], w[1], w[2])))
                }
                _ => None,
            })
            .collect();
        if pts.len() < 3 {
            return None;
        }
        // Frame from the first point and two far ones, same construction on both sides.
        let frame = |a: Vec3, b: Vec3, c: Vec3| {
            let x = (b - a).normalize();
            let z = x.cross(&(c - a)).normalize();
            let y = z.cross(&x);
            Pose::new(nalgebra::Matrix3::from_columns(&[x, y, z]), a)
        };
        let far = pts
            .iter()
            .max_by(|p, q| (p.0 - pts[0].0).norm().total_cmp(&(q.0 - pts[0].0).norm()))?;
        let third = pts.iter().max_by(|p, q| {
            let d = |r: &(Vec3, Vec3)| (r.0 - pts[0].0).cross(&(far.0 - pts[0].0)).norm();
            d(p).total_cmp(&d(q))
        })?;
        let lf = frame(pts[0].0, far.0, third.0);
        let wf = frame(pts[0].1, far.1, third.1);
        Some(wf * lf.inverse())
    };
    for (si, sc) in t.scenes.iter().enumerate() {
        // The body seen most often anchors the comparison.
        let mut count = std::collections::HashMap::<usize, usize>::new();
        for f in &s.frames {
            for obs in &f.observations {
                for o in obs {
                    if let PointKind::Body { body, .. } = s.points.kinds[o.point] {
                        if sc.bodies.contains_key(&body) {
                            *count.entry(body).or_default() += 1;
                        }
                    }
                }
            }
        }
        let Some((&anchor, _)) = count
            .iter()
            .max_by_key(|(b, c)| (**c, std::cmp::Reverse(**b)))
        else {
            continue;
        };
        let Some(w_anchor) = truth_body(anchor) else {
            continue;
        };
        let scene_from_anchor = sc.bodies[&anchor];
        println!(
            "scene {si}: anchor {} sigma {:.3}",
            s.points.bodies[anchor].name, sc.sigma_px
        );
        for (b, est) in &sc.bodies {
            let Some(wb) = truth_body(*b) else { continue };
            let tr = w_anchor.inverse() * wb;
            let est = scene_from_anchor.inverse() * *est;
            println!(
                "  body {:>28}: dR {:8.3} deg dt {:9.1} mm",
                s.points.bodies[*b].name,
                so3::angle_between(&est.rot, &tr.rot).to_degrees(),
                (est.trans - tr.trans).norm() * 1e3
            );
        }
        for (&(f, c), est) in &sc.poses {
            let cam = &s.cameras[c].id;
            let w_cam = truth.world_from_rig[f] * truth.ref_from_cam[cam];
            let tr = w_cam.inverse() * w_anchor;
            let est = *est * scene_from_anchor;
            let dr = so3::angle_between(&est.rot, &tr.rot).to_degrees();
            if dr > 0.05 {
                println!(
                    "  image ({f}, {cam}): dR {dr:8.3} deg dt {:9.1} mm",
                    (est.trans - tr.trans).norm() * 1e3
                );
            }
        }
    }
}
