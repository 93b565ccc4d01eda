//! Hostile but well-formed sessions: the engine must answer every one with a result
//! document (failed, degraded or succeeded), never a panic.

use rand::{Rng, SeedableRng};
use rigcal_core::session::{parse_session, SessionManifest};
use rigcal_engine::pipeline::{calibrate, CalibOptions};
use rigcal_synth::generate;

fn mutate(m: &mut SessionManifest, kind: usize, rng: &mut rand_chacha::ChaCha8Rng) {
    match kind {
        // Every observation at the same pixel.
        0 => m
            .frames
            .iter_mut()
            .flat_map(|f| f.observations.values_mut())
            .flatten()
            .for_each(|o| {
                o.u = 100.0;
                o.v = 100.0;
            }),
        // Keep a random 30 % of the observations.
        1 => m
            .frames
            .iter_mut()
            .flat_map(|f| f.observations.values_mut())
            .for_each(|v| v.retain(|_| rng.gen_bool(0.3))),
        // Point ids shuffled within each image (wrong correspondences everywhere).
        2 => m
            .frames
            .iter_mut()
            .flat_map(|f| f.observations.values_mut())
            .for_each(|v| {
                let n = v.len();
                for i in 0..n {
                    let j = rng.gen_range(0..n);
                    let (a, b) = (v[i].point.clone(), v[j].point.clone());
                    v[i].point = b;
                    v[j].point = a;
                }
            }),
        // One camera reuses the other camera's point ids (a false scene permutation).
        3 => {
            let names: Vec<String> = m.cameras.iter().map(|c| c.id.clone()).collect();
            for f in &mut m.frames {
                if let Some(v) = f.observations.get_mut(&names[1]) {
                    for (k, o) in v.iter_mut().enumerate() {
                        o.point = format!("s-{}:{k:02}", names[0]);
                    }
                }
            }
        }
        // Exactly three frames, four points each.
        4 => {
            m.frames.truncate(3);
            m.frames
                .iter_mut()
                .flat_map(|f| f.observations.values_mut())
                .for_each(|v| v.truncate(4));
        }
        // The reference camera sees nothing after frame 0.
        5 => {
            let r = m.reference_camera.clone();
            m.frames.iter_mut().skip(1).for_each(|f| {
                f.observations.remove(&r);
            });
        }
        // Random pixel jitter of up to 300 px, clamped to the image.
        _ => {
            let (w, h) = (m.cameras[0].width as f64, m.cameras[0].height as f64);
            m.frames
                .iter_mut()
                .flat_map(|f| f.observations.values_mut())
                .flatten()
                .for_each(|o| {
                    o.u = (o.u + rng.gen_range(-300.0..300.0)).clamp(0.0, w - 1.0);
                    o.v = (o.v + rng.gen_range(-300.0..300.0)).clamp(0.0, h - 1.0);
                })
        }
    }
}

#[test]
fn hostile_sessions_get_a_document_not_a_panic() {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    for preset in ["lebraly-5.1", "car-planar-uturn"] {
        for kind in 0..7 {
            let (mut m, _) = generate(preset, 3, 0.5).unwrap();
            mutate(&mut m, kind, &mut rng);
            m.scale.retain(|s| {
                m.frames
                    .iter()
                    .flat_map(|f| f.observations.values())
                    .flatten()
                    .any(|o| o.point == s.a)
                    && m.frames
                        .iter()
                        .flat_map(|f| f.observations.values())
                        .flatten()
                        .any(|o| o.point == s.b)
            });
            let Ok(session) = parse_session(serde_json::to_string(&m).unwrap().as_bytes()) else {
                continue;
            };
            let out = std::panic::catch_unwind(|| calibrate(&session, &CalibOptions::default()));
            let doc = out.unwrap_or_else(|_| panic!("{preset}: mutation {kind} panicked"));
            // A degenerate capture must not pass as a plain success.
            if kind == 0 || kind == 2 {
                assert_ne!(
                    doc.status,
                    rigcal_core::result::Status::Succeeded,
                    "{preset}: mutation {kind}: {:?}",
                    doc.reasons
                );
            }
        }
    }
}
