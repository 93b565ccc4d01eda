//! Which legible tags detection misses, and which corners it gets wrong, on one rendered
//! capture (a debugging aid): `cargo run --release --example debug_misses -- PRESET SEED
//! [WxH]`. Renders every image exactly as `rigcal bench capture` does. Environment:
//! `ONLY=f<frame>_<camera>` one image; `DUMP=DIR` writes the images with misses (and
//! 6× crops around each miss); `TAG=<id>` prints that tag's detection (and with `DUMP`, a 12× crop); `SHOW=1` every
//! true corner beside the detected one; `NOFIT=1` the edge measurement alone.
use rigcal_core::session::parse_session;
use rigcal_detect::{detect_tags, DetectOptions};
use rigcal_engine::pipeline::detection::decode_gray;
use rigcal_synth::hall::{hall, Hall, Nuisance};
use std::collections::{BTreeMap, HashMap};

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let s: u64 = a[2].parse().expect("seed");
    let size = a.get(3).map(|t| {
        let (w, h) = t.split_once('x').expect("WxH");
        (w.parse().expect("w"), h.parse().expect("h"))
    });
    let dump = std::env::var("DUMP").ok();
    let h = hall(&a[1], s, size).expect("preset");
    let capture = h.image_capture(true);
    let session =
        parse_session(serde_json::to_string(&capture.manifest).unwrap().as_bytes()).unwrap();
    let nuisance = Nuisance::default();
    let mut opts = DetectOptions::default();
    if std::env::var("NOFIT").is_ok() {
        opts.whole_fit_below = 0.0;
    }
    let (mut legible, mut found) = (0, 0);
    for it in &capture.images {
        if let Ok(only) = std::env::var("ONLY") {
            if only != format!("f{}_{}", it.frame, it.camera) {
                continue;
            }
        }
        let ci = h.cameras.iter().position(|c| c.0 == it.camera).unwrap();
        let img = h.render(
            it.frame,
            ci,
            &nuisance,
            s.wrapping_mul(7919) + (it.frame * 64 + ci) as u64,
        );
        let bytes = Hall::encode(&img, &nuisance).unwrap();
        let gray = decode_gray(&bytes, None, u64::MAX).unwrap();
        let cam = &session.cameras[session.camera_index(&it.camera).unwrap()].camera;
        let d = detect_tags(&gray, &session.manifest.targets, Some(cam), &opts).unwrap();
        let obs: HashMap<&str, (f64, f64)> = d
            .points
            .iter()
            .map(|p| (p.point.as_str(), (p.u, p.v)))
            .collect();
        let mut tags: BTreeMap<&str, Vec<[f64; 2]>> = BTreeMap::new();
        for (p, uv) in &it.corners {
            let tag = p.rsplit_once(':').map_or(p.as_str(), |(t, _)| t);
            tags.entry(tag).or_default().push(*uv);
        }
        let (w, hh) = (gray.width as f64, gray.height as f64);
        let mut missed_here = false;
        for (tag, uv) in &tags {
            legible += 1;
            let all = (0..4).all(|c| obs.contains_key(format!("{tag}:{c}").as_str()));
            found += all as usize;
            if !all {
                missed_here = true;
                let c = uv
                    .iter()
                    .fold([0.0, 0.0], |s, p| [s[0] + p[0] / 4.0, s[1] + p[1] / 4.0]);
                let side = (0..4)
                    .map(|k| (uv[k][0] - uv[(k + 1) % 4][0]).hypot(uv[k][1] - uv[(k + 1) % 4][1]))
                    .fold(f64::MAX, f64::min);
                let r = (c[0] - w / 2.0).hypot(c[1] - hh / 2.0) / (w / 2.0).hypot(hh / 2.0);
                let n = (0..4)
                    .filter(|k| obs.contains_key(format!("{tag}:{k}").as_str()))
                    .count();
                let id: u32 = tag.rsplit(':').next().unwrap().parse().unwrap_or(0);
                let why: Vec<&str> = d
                    .rejected
                    .iter()
                    .filter(|r| r.id == id)
                    .map(|r| r.reason.as_str())
                    .collect();
                if let Some(dir) = &dump {
                    let (x0, y0) = (
                        (c[0] as i64 - 40).max(0) as u32,
                        (c[1] as i64 - 40).max(0) as u32,
                    );
                    let crop = image::imageops::crop_imm(&img, x0, y0, 80, 80).to_image();
                    let big = image::imageops::resize(
                        &crop,
                        480,
                        480,
                        image::imageops::FilterType::Nearest,
                    );
                    big.save(format!("{dir}/f{}_{}_{}.png", it.frame, it.camera, id))
                        .unwrap();
                }
                println!(
                    "MISS f{} {} {tag} side {side:.1} px at ({:.0},{:.0}) r {r:.2} corners {n}/4 {why:?}",
                    it.frame, it.camera, c[0], c[1]
                );
            }
        }
        if let Ok(t) = std::env::var("TAG") {
            for d in d.tags.iter().filter(|d| d.id.to_string() == t) {
                println!("DET {d:?}");
                if let Some(dir) = &dump {
                    let c = d
                        .corners
                        .iter()
                        .fold([0.0, 0.0], |s, p| [s[0] + p[0] / 4.0, s[1] + p[1] / 4.0]);
                    let (x0, y0) = (
                        (c[0] as i64 - 20).max(0) as u32,
                        (c[1] as i64 - 20).max(0) as u32,
                    );
                    let crop = image::imageops::crop_imm(&img, x0, y0, 40, 40).to_image();
                    image::imageops::resize(&crop, 480, 480, image::imageops::FilterType::Nearest)
                        .save(format!("{dir}/tag_f{}_{}_{t}.png", it.frame, it.camera))
                        .unwrap();
                }
            }
        }
        if std::env::var("SHOW").is_ok() {
            for (p, uv) in &it.corners {
                println!(
                    "TRUE {p} {:.2} {:.2} got {:?}",
                    uv[0],
                    uv[1],
                    obs.get(p.as_str())
                );
            }
        }
        for (p, uv) in &it.corners {
            if let Some((u, v)) = obs.get(p.as_str()) {
                let e = (u - uv[0]).hypot(v - uv[1]);
                if e > 1.0 {
                    println!(
                        "WRONG f{} {} {p} {e:.2} px at ({:.0},{:.0})",
                        it.frame, it.camera, uv[0], uv[1]
                    );
                }
            }
        }
        if missed_here || std::env::var("ONLY").is_ok() {
            if let Some(dir) = &dump {
                std::fs::write(format!("{dir}/f{}_{}.jpg", it.frame, it.camera), &bytes).unwrap();
            }
        }
    }
    println!(
        "found {found}/{legible} = {:.2} %",
        100.0 * found as f64 / legible as f64
    );
}
