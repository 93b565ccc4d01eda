//! Views of a `bench detect` cell where a tag in view was not found, saved as PNG (a
//! debugging aid): `cargo run --release --example debug_grid_views -- CELL VIEWS [SEED]`.
//! Cells as `rigcal bench detect` numbers them: 0-2 single tags, 3-5 AprilGrids
//! (pinhole, radtan, equidistant); the seed of cell `c` is `SEED + 1000·c` as there.
use rigcal_bench::detect::{cell_params, study};
use rigcal_detect::{detect_tags, gray::Gray, DetectOptions};
use rigcal_synth::tagscene::scene;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let arg = |i: usize, default: u64| a.get(i).and_then(|s| s.parse().ok()).unwrap_or(default);
    let (ci, views, seed) = (arg(1, 5) as usize, arg(2, 40) as usize, arg(3, 1000));
    let cells = study(views, 1600, 1200);
    let Some(c) = cells.get(ci) else {
        eprintln!("cell {ci}: 0..{}", cells.len());
        std::process::exit(2);
    };
    for i in 0..c.n {
        let p = cell_params(c, i, seed + 1000 * ci as u64);
        let s = scene(&p);
        let g = Gray::from_luma8(&s.image);
        let d = detect_tags(&g, &s.targets, Some(&s.camera), &DetectOptions::default())
            .expect("detector");
        let found = d
            .tags
            .iter()
            .filter(|t| s.truth.contains_key(&t.id))
            .count();
        if found < s.truth.len() {
            let path = format!("/tmp/rigcal-cell{ci}-view{i}.png");
            println!(
                "view {i}: tag {:.1} px, obliquity {:.0}°: {found}/{} found, refused {:?}; {path}",
                p.tag_px,
                p.obliquity_deg,
                s.truth.len(),
                d.rejected
            );
            s.image.save(&path).expect("writing the view");
        }
    }
}
