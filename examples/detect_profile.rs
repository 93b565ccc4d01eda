//! Time `detect_tags` on one thread over a capture written by `rigcal synth --images`
//! and score it against the capture's `corners.json` (a profiling aid, also run under
//! `perf record`): `cargo run --release --example detect_profile -- DIR [N] [edge-only]`
//! detects the first N frames of every camera (all when omitted) and prints the median
//! ms per image (the fastest of `REPEAT` runs each, default 1), the share of legible tags
//! found and the corner RMS; `edge-only` turns the whole-tag fits off, `decimated` the
//! full-resolution searches, `fast` both (`Quality::Fast`, its whole-tag fits below 30
//! px); `FIT_BELOW=px`, `SPACING=px` (between edge profiles) and `DECIMATE=f` (of the
//! first quad search) override those options. The digest it prints covers every
//! reported point bit for bit; `POINTS=1` prints every point.
use rigcal_detect::{detect_tags, DetectOptions};
use std::collections::BTreeMap;

#[derive(serde::Deserialize)]
struct Truth {
    camera: String,
    frame: usize,
    path: String,
    corners: BTreeMap<String, [f64; 2]>,
}

/// Upper bounds (px, shortest side) of the tag-size bins of the outward-bias table.
const SIZE_BINS: [f64; 4] = [20.0, 30.0, 46.0, 80.0];

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let dir = std::path::PathBuf::from(&a[1]);
    let frames: usize = a.get(2).and_then(|n| n.parse().ok()).unwrap_or(usize::MAX);
    let s = rigcal_core::session::parse_session(
        &std::fs::read(dir.join("session.json")).expect("read"),
    )
    .expect("valid");
    let truth: Vec<Truth> =
        serde_json::from_slice(&std::fs::read(dir.join("corners.json")).expect("read"))
            .expect("json");
    let mut opts = DetectOptions::default();
    match a.get(3).map(String::as_str) {
        Some("edge-only") => opts.whole_fit_below = 0.0,
        Some("fast") => opts = DetectOptions::of_quality(rigcal_detect::Quality::Fast),
        Some("decimated") => opts.full_resolution = false,
        _ => {}
    }
    if let Some(px) = std::env::var("FIT_BELOW").ok().and_then(|v| v.parse().ok()) {
        opts.whole_fit_below = px;
    }
    if let Some(px) = std::env::var("SPACING").ok().and_then(|v| v.parse().ok()) {
        opts.profile_spacing = px;
    }
    if let Some(d) = std::env::var("DECIMATE").ok().and_then(|v| v.parse().ok()) {
        opts.quads.decimate = d;
    }
    let repeat: usize = std::env::var("REPEAT")
        .ok()
        .and_then(|r| r.parse().ok())
        .unwrap_or(1);
    rigcal_detect::quads::warm_up(&opts.quads).expect("detector");
    let mut scale: BTreeMap<String, [f64; 2]> = BTreeMap::new();
    let mut outward: Vec<Vec<f64>> = vec![vec![]; SIZE_BINS.len() + 1];
    let (mut ms, mut legible, mut found, mut wrong, mut sq, mut n) = (vec![], 0, 0, 0, 0.0, 0);
    let mut digest: u64 = 0xcbf2_9ce4_8422_2325;
    for t in truth.iter().filter(|t| t.frame < frames) {
        let camera = &s
            .cameras
            .iter()
            .find(|c| c.id == t.camera)
            .expect("camera")
            .camera;
        let bytes = std::fs::read(dir.join(&t.path)).expect("image");
        let (_, g) = rigcal_detect::imageio::decode_gray(&bytes, None, u64::MAX).expect("decode");
        // The fastest of a few runs: this machine's other load only ever adds time.
        let mut best = f64::INFINITY;
        let mut d = None;
        for _ in 0..repeat {
            let clock = std::time::Instant::now();
            d = Some(detect_tags(&g, &s.manifest.targets, Some(camera), &opts).expect("detect"));
            best = best.min(clock.elapsed().as_secs_f64() * 1e3);
        }
        let d = d.expect("one run");
        ms.push(best);
        if std::env::var_os("POINTS").is_some() {
            for p in &d.points {
                println!("point {} {} {:.17e} {:.17e}", t.path, p.point, p.u, p.v);
            }
        }
        // FNV-1a over every reported point's name and coordinates' bits.
        for p in &d.points {
            for b in p
                .point
                .bytes()
                .chain(p.u.to_bits().to_le_bytes())
                .chain(p.v.to_bits().to_le_bytes())
            {
                digest = (digest ^ u64::from(b)).wrapping_mul(0x100_0000_01b3);
            }
        }
        let got: BTreeMap<&str, [f64; 2]> = d
            .points
            .iter()
            .map(|p| (p.point.as_str(), [p.u, p.v]))
            .collect();
        let tags: std::collections::BTreeSet<&str> = t
            .corners
            .keys()
            .map(|k| k.rsplit_once(':').expect("tag:id:k").0)
            .collect();
        legible += tags.len();
        let missed: Vec<&str> = tags
            .iter()
            .filter(|tag| !(0..4).all(|k| got.contains_key(format!("{tag}:{k}").as_str())))
            .copied()
            .collect();
        if !missed.is_empty() && std::env::var_os("MISSED").is_some() {
            println!("{}: missed {missed:?}", t.path);
        }
        found += tags.len() - missed.len();
        for tag in &tags {
            let truth: Option<Vec<[f64; 2]>> = (0..4)
                .map(|k| t.corners.get(&format!("{tag}:{k}")).copied())
                .collect();
            let det: Option<Vec<[f64; 2]>> = (0..4)
                .map(|k| got.get(format!("{tag}:{k}").as_str()).copied())
                .collect();
            let (Some(truth), Some(det)) = (truth, det) else {
                continue;
            };
            let c = truth
                .iter()
                .fold([0.0, 0.0], |a, p| [a[0] + p[0] / 4.0, a[1] + p[1] / 4.0]);
            let side = (0..4)
                .map(|k| {
                    let (a, b) = (truth[k], truth[(k + 1) % 4]);
                    (a[0] - b[0]).hypot(a[1] - b[1])
                })
                .fold(f64::INFINITY, f64::min);
            let bin = SIZE_BINS
                .iter()
                .position(|&b| side < b)
                .unwrap_or(SIZE_BINS.len());
            for k in 0..4 {
                let (q, p) = (truth[k], det[k]);
                let r = (q[0] - c[0]).hypot(q[1] - c[1]);
                let e = [p[0] - q[0], p[1] - q[1]];
                if e[0].hypot(e[1]) > 1.0 {
                    continue;
                }
                let out = (e[0] * (q[0] - c[0]) + e[1] * (q[1] - c[1])) / r;
                outward[bin].push(out);
                let d = [q[0] - g.width as f64 / 2.0, q[1] - g.height as f64 / 2.0];
                let sc = scale.entry(t.camera.clone()).or_insert([0.0; 2]);
                sc[0] += e[0] * d[0] + e[1] * d[1];
                sc[1] += d[0] * d[0] + d[1] * d[1];
            }
        }
        for (k, c) in &t.corners {
            if let Some(p) = got.get(k.as_str()) {
                let e = (p[0] - c[0]).hypot(p[1] - c[1]);
                if e > 1.0 {
                    wrong += 1;
                } else {
                    sq += e * e;
                    n += 1;
                }
            }
        }
    }
    ms.sort_by(f64::total_cmp);
    println!(
        "{} images: median {:.1} ms (min {:.1}); {found}/{legible} legible tags found ({:.2} %), {wrong} corners > 1 px off, RMS {:.4} px",
        ms.len(),
        ms[ms.len() / 2],
        ms[0],
        100.0 * found as f64 / legible.max(1) as f64,
        (sq / n.max(1) as f64).sqrt()
    );
    // Equal digests: the same points, bit for bit (a refactoring that claims so).
    println!("  points digest {digest:016x}");
    // Outward bias: the mean offset of detected corners away from the tag's centre, by
    // tag size; a tag that reads systematically larger or smaller biases every distance.
    for (i, o) in outward.iter().enumerate() {
        if o.is_empty() {
            continue;
        }
        let n = o.len() as f64;
        let m = o.iter().sum::<f64>() / n;
        let sd = (o.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n).sqrt();
        let lo = if i == 0 { 0.0 } else { SIZE_BINS[i - 1] };
        let hi = SIZE_BINS.get(i).copied().unwrap_or(f64::INFINITY);
        println!(
            "  sides {lo:>3}-{hi:<4} px: {:>6} corners, outward {:+.5} ± {:.5} px (sd {:.4})",
            o.len(),
            m,
            sd / n.sqrt(),
            sd
        );
    }
    // Scale about the image centre: corners shifted in proportion to their distance
    // from it read as a different focal length, i.e. a different distance to the target.
    for (cam, [num, den]) in &scale {
        println!(
            "  {cam}: scale about the image centre {:+.2} ppm",
            1e6 * num / den
        );
    }
}
