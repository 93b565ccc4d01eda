//! Where the error of a calibration from images comes from (a debugging aid for the
//! reported σ): `cargo run --release --example debug_sigma -- PRESET SEED [WxH]`.
//! Renders and detects one capture as `rigcal bench capture` does (the detected session
//! is cached in `/tmp`), then calibrates it as detected and with every detected corner
//! replaced by its true projection plus Gaussian noise (`NOISE` px, default 0.015), and
//! prints each camera's per-axis error against its reported σ. `MODE=size:A-B` keeps the
//! detected corners of tags whose shortest side is in [A, B) px and uses truth elsewhere.
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rigcal_core::session::parse_session;
use rigcal_core::session::SessionManifest;
use rigcal_engine::pipeline::detection::{detect_session, MemorySource};
use rigcal_engine::pipeline::{calibrate_with, CalibOptions, Silent};
use rigcal_synth::hall::{hall, Hall, Nuisance};
use std::collections::HashMap;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let (preset, s) = (a[1].as_str(), a[2].parse::<u64>().expect("seed"));
    let size = a.get(3).map(|t| {
        let (w, h) = t.split_once('x').expect("WxH");
        (w.parse().expect("w"), h.parse().expect("h"))
    });
    let h = hall(preset, s, size).expect("preset");
    let capture = h.image_capture(true);
    let cache = format!(
        "/tmp/dbgsig_{preset}_{s}_{}.json",
        a.get(3).map_or("full", |x| x)
    );
    let detected: SessionManifest = match std::fs::read(&cache) {
        Ok(b) => serde_json::from_slice(&b).expect("cache"),
        Err(_) => {
            let nuisance = Nuisance::default();
            let mut files = HashMap::new();
            for (frame, spec) in capture.manifest.frames.iter().enumerate() {
                for (cam, path) in &spec.images {
                    let ci = h.cameras.iter().position(|c| &c.0 == cam).unwrap();
                    let img = h.render(
                        frame,
                        ci,
                        &nuisance,
                        s.wrapping_mul(7919) + (frame * 64 + ci) as u64,
                    );
                    files.insert(path.clone(), Hall::encode(&img, &nuisance).unwrap());
                }
            }
            let text = serde_json::to_string(&capture.manifest).unwrap();
            let session = parse_session(text.as_bytes()).unwrap();
            let (d, _) = detect_session(
                &session,
                &MemorySource(files),
                rigcal_core::result::DetectionQuality::Accurate,
                &Silent,
            )
            .unwrap_or_else(|e| panic!("{e:?}"));
            std::fs::write(&cache, serde_json::to_vec(&d.manifest).unwrap()).unwrap();
            d.manifest
        }
    };
    // The true projection of every point in every image.
    let truth_uv = |frame: usize, cam: &str, point: &str| -> Option<[f64; 2]> {
        let ci = h.cameras.iter().position(|c| c.0 == cam)?;
        let p = capture.truth.points.get(point)?;
        let pc = h
            .world_from_cam(frame, ci)
            .inverse()
            .apply(&rigcal_core::geometry::Vec3::new(p[0], p[1], p[2]));
        let uv = h.cameras[ci].1.project(&pc)?;
        Some([uv.x, uv.y])
    };
    // Shortest side (px) of each tag in each image, from the truth.
    let side = |frame: usize, cam: &str, tag: &str| -> f64 {
        let c: Vec<[f64; 2]> = (0..4)
            .filter_map(|k| truth_uv(frame, cam, &format!("{tag}:{k}")))
            .collect();
        if c.len() < 4 {
            return 0.0;
        }
        (0..4)
            .map(|k| (c[k][0] - c[(k + 1) % 4][0]).hypot(c[k][1] - c[(k + 1) % 4][1]))
            .fold(f64::MAX, f64::min)
    };
    // Detection error statistics by tag size.
    let bins = [0.0, 16.0, 20.0, 30.0, 46.0, 80.0, 1e9];
    let mut stats = vec![(0usize, 0.0f64, 0.0f64); bins.len() - 1];
    for (f, spec) in detected.frames.iter().enumerate() {
        for (cam, obs) in &spec.observations {
            for o in obs {
                let Some(t) = truth_uv(f, cam, &o.point) else {
                    continue;
                };
                let tag = o.point.rsplit_once(':').unwrap().0;
                let sd = side(f, cam, tag);
                let b = bins
                    .windows(2)
                    .position(|w| sd >= w[0] && sd < w[1])
                    .unwrap_or(0);
                let (du, dv) = (o.u - t[0], o.v - t[1]);
                stats[b].0 += 1;
                stats[b].1 += du * du + dv * dv;
                stats[b].2 = stats[b].2.max(du.hypot(dv));
            }
        }
    }
    for (b, (n, sq, mx)) in stats.iter().enumerate() {
        if *n > 0 {
            println!(
                "tags {:>3}-{:<4} px: {n:>6} corners, RMS {:.4} px, max {:.3} px",
                bins[b],
                bins[b + 1].min(999.0),
                (sq / (2.0 * *n as f64)).sqrt(),
                mx
            );
        }
    }
    let noise: f64 = std::env::var("NOISE").map_or(0.015, |v| v.parse().unwrap());
    let mode = std::env::var("MODE").unwrap_or_default();
    let keep_detected = |frame: usize, cam: &str, point: &str| -> bool {
        if let Some(r) = mode.strip_prefix("size:") {
            let (lo, hi) = r.split_once('-').unwrap();
            let (lo, hi): (f64, f64) = (lo.parse().unwrap(), hi.parse().unwrap());
            let sd = side(frame, cam, point.rsplit_once(':').unwrap().0);
            return sd >= lo && sd < hi;
        }
        if let Some(c) = mode.strip_prefix("cam:") {
            return c.split(',').any(|c| c == cam);
        }
        false
    };
    // `LIST=camera`: that camera's kept tags, corner by corner (offsets from the truth).
    if let Ok(list) = std::env::var("LIST") {
        for (f, spec) in detected.frames.iter().enumerate() {
            let Some(obs) = spec.observations.get(&list) else {
                continue;
            };
            let mut tags: std::collections::BTreeMap<&str, Vec<(usize, f64, f64)>> =
                Default::default();
            for o in obs {
                if !keep_detected(f, &list, &o.point) {
                    continue;
                }
                let Some(t) = truth_uv(f, &list, &o.point) else {
                    continue;
                };
                let (tag, k) = o.point.rsplit_once(':').unwrap();
                tags.entry(tag)
                    .or_default()
                    .push((k.parse().unwrap(), o.u - t[0], o.v - t[1]));
            }
            for (tag, c) in tags {
                let sd = side(f, &list, tag);
                let t0 = truth_uv(f, &list, &format!("{tag}:0")).unwrap_or([0.0; 2]);
                let text: Vec<String> = c
                    .iter()
                    .map(|(k, du, dv)| format!("{k}:({du:+.3},{dv:+.3})"))
                    .collect();
                println!(
                    "f{f:<2} {tag:<8} side {sd:5.1} at ({:6.1},{:6.1}) {}",
                    t0[0],
                    t0[1],
                    text.join(" ")
                );
            }
        }
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(s);
    let px = Normal::new(0.0, noise).unwrap();
    let mut substituted = detected.clone();
    for (f, spec) in substituted.frames.iter_mut().enumerate() {
        for (cam, obs) in spec.observations.iter_mut() {
            for o in obs.iter_mut() {
                if keep_detected(f, cam, &o.point) {
                    continue;
                }
                if let Some(t) = truth_uv(f, cam, &o.point) {
                    o.u = t[0] + px.sample(&mut rng);
                    o.v = t[1] + px.sample(&mut rng);
                }
            }
        }
    }
    let opts = CalibOptions {
        corner_sigma_floor_px: std::env::var("FLOOR").map_or(0.03, |v| v.parse().unwrap()),
        ..CalibOptions::default()
    };
    for (name, m) in [("detected", &detected), ("substituted", &substituted)] {
        let session = parse_session(serde_json::to_string(m).unwrap().as_bytes()).unwrap();
        let doc = calibrate_with(&session, &opts, &Silent).unwrap();
        println!(
            "{name}: {} ({})",
            doc.status.as_str(),
            doc.reasons
                .iter()
                .map(|r| r.code.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        );
        for e in &doc.extrinsics {
            let truth = capture.truth.ref_from_cam[&e.value.camera];
            let est = rigcal_core::result::ExtrinsicValue::pose(&e.value);
            let mut line = format!("  {:>6}", e.value.camera);
            for ax in 0..3 {
                let err = (est.trans[ax] - truth.trans[ax]) * 1e3;
                match e.sigma_translation_m[ax] {
                    Some(sg) if sg > 0.0 => {
                        line += &format!(
                            "  {err:+8.3} mm / {:.3} = {:+5.2}",
                            sg * 1e3,
                            err / (sg * 1e3)
                        )
                    }
                    _ => line += &format!("  {err:+8.3} mm (held)       "),
                }
            }
            println!("{line}");
        }
    }
}
