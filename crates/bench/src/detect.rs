//! Detector accuracy on rendered views with known corners: detection rate, wrong ids,
//! corner RMS error of rigcal's refined corners and of the quad detector's own (so the
//! refinement's gain is visible), and time per image.

use rigcal_detect as detect;
use rigcal_detect::{corner, gray::Gray, quads, DetectOptions, Quality};
use rigcal_synth::render::RenderOptions;
use rigcal_synth::tagscene::{scene, Lens, SceneParams};
use std::time::Instant;

#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct DetectRow {
    pub label: String,
    pub images: usize,
    /// Tags entirely in view.
    pub visible: usize,
    pub found: usize,
    pub wrong_id: usize,
    /// Found by the board layout rather than the quad detector.
    pub from_layout: usize,
    pub corner_rms_px: f64,
    pub corner_max_px: f64,
    /// Corner RMS (px) by head-on tag size: under 40 px, 40-80 px, 80 px and over
    /// (`NaN` where the cell has no such views).
    pub corner_rms_by_size_px: [f64; 3],
    /// The quad detector's corners (after the ½-px convention fix) on the same tags.
    pub quad_rms_px: f64,
    pub median_ms: f64,
    /// The quad detector alone.
    pub quad_median_ms: f64,
    /// The same detection with the whole-tag fit off (edge-measured corners only), on the
    /// same tags found by both: corner RMS and median time per image.
    pub edge_only_rms_px: f64,
    pub edge_only_median_ms: f64,
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

impl DetectRow {
    pub fn rate(&self) -> f64 {
        self.found as f64 / self.visible.max(1) as f64
    }
}

/// A study cell: `n` views with tag sizes in `sizes`, obliquities up to `max_obliquity`.
#[derive(Clone, Debug)]
pub struct Cell {
    pub grid: bool,
    pub lens: Lens,
    pub sizes: (f64, f64),
    pub max_obliquity: f64,
    pub n: usize,
    pub width: u32,
    pub height: u32,
    pub noise: f64,
    pub blur: f64,
    /// The detection quality the cell is detected at.
    pub quality: Quality,
}

pub fn run_cell(cell: &Cell, seed: u64) -> DetectRow {
    let mut row = DetectRow {
        label: format!(
            "{} {:?} {:.0}-{:.0}px ≤{:.0}°",
            if cell.grid { "grid" } else { "tag" },
            cell.lens,
            cell.sizes.0,
            cell.sizes.1,
            cell.max_obliquity
        ),
        ..Default::default()
    };
    let (mut sq, mut n, mut qsq, mut qn) = (0.0, 0usize, 0.0, 0usize);
    let mut by_size = [(0.0, 0usize); 3];
    let mut times = Vec::new();
    let mut quad_times = Vec::new();
    let (mut esq, mut en, mut edge_times) = (0.0, 0usize, Vec::new());
    let opts = DetectOptions::of_quality(cell.quality);
    let edge_only = DetectOptions {
        whole_fit_below: 0.0,
        ..opts.clone()
    };
    for i in 0..cell.n {
        let params = cell_params(cell, i, seed);
        let band = SIZE_BANDS.iter().filter(|&&b| params.tag_px >= b).count();
        let s = scene(&params);
        let gray = Gray::from_luma8(&s.image);
        let start = Instant::now();
        let out = detect::detect_tags(&gray, &s.targets, Some(&s.camera), &opts);
        times.push(start.elapsed().as_secs_f64() * 1e3);
        row.images += 1;
        row.visible += s.truth.len();
        let Ok(out) = out else { continue };
        for tag in &out.tags {
            match s.truth.get(&tag.id) {
                Some(truth) => {
                    row.found += 1;
                    row.from_layout += (tag.source == "layout") as usize;
                    for (k, t) in truth.iter().enumerate() {
                        let e = (corner(tag, k) - t).norm();
                        sq += e * e;
                        n += 1;
                        by_size[band].0 += e * e;
                        by_size[band].1 += 1;
                        row.corner_max_px = row.corner_max_px.max(e);
                    }
                }
                // A tag partly out of view is not in the truth; any other id is wrong.
                None if tag_in_print(&s, tag.id) => {}
                None => row.wrong_id += 1,
            }
        }
        let start = Instant::now();
        let edge = detect::detect_tags(&gray, &s.targets, Some(&s.camera), &edge_only);
        edge_times.push(start.elapsed().as_secs_f64() * 1e3);
        for tag in edge.iter().flat_map(|e| &e.tags) {
            if let Some(truth) = s.truth.get(&tag.id) {
                for (k, t) in truth.iter().enumerate() {
                    esq += (corner(tag, k) - t).norm_squared();
                    en += 1;
                }
            }
        }
        let start = Instant::now();
        let raw = quads::detect(&gray, &quads::QuadOptions::default());
        quad_times.push(start.elapsed().as_secs_f64() * 1e3);
        if let Ok(raw) = raw {
            for c in raw {
                if let Some(truth) = s.truth.get(&c.id) {
                    for k in 0..4 {
                        let e = (c.corners[k] - truth[k]).norm();
                        qsq += e * e;
                        qn += 1;
                    }
                }
            }
        }
    }
    row.corner_rms_px = (sq / n.max(1) as f64).sqrt();
    row.corner_rms_by_size_px = by_size.map(|(sq, n)| (sq / n as f64).sqrt());
    row.quad_rms_px = (qsq / qn.max(1) as f64).sqrt();
    row.median_ms = median(&mut times);
    row.quad_median_ms = median(&mut quad_times);
    row.edge_only_rms_px = (esq / en.max(1) as f64).sqrt();
    row.edge_only_median_ms = median(&mut edge_times);
    row
}

/// Upper ends (head-on px) of the first two size bands of [`DetectRow::corner_rms_by_size_px`].
const SIZE_BANDS: [f64; 2] = [40.0, 80.0];

/// View `i` of a cell: sizes spread geometrically, obliquities evenly (shuffled).
pub fn cell_params(cell: &Cell, i: usize, seed: u64) -> SceneParams {
    let t = (i as f64 + 0.5) / cell.n as f64;
    SceneParams {
        grid: cell.grid,
        tag_px: cell.sizes.0 * (cell.sizes.1 / cell.sizes.0).powf(t),
        obliquity_deg: cell.max_obliquity * ((i * 7) % cell.n) as f64 / cell.n as f64,
        lens: cell.lens,
        width: cell.width,
        height: cell.height,
        render: RenderOptions {
            noise_sigma: cell.noise,
            blur_sigma: cell.blur,
            ..Default::default()
        },
        seed: seed + i as u64,
    }
}

/// Is `id` printed in the scene (possibly partly out of view)?
fn tag_in_print(s: &rigcal_synth::tagscene::TagScene, id: u32) -> bool {
    s.targets
        .iter()
        .filter_map(rigcal_core::target::board::GridLayout::of)
        .any(|g| g.cell_of(id).is_some())
}

/// The study of issue 3: single tags and 6×6 AprilGrids, 24-200 px, up to 60°, pinhole
/// and distorted, σ = 2 grey levels.
pub fn study(n: usize, width: u32, height: u32) -> Vec<Cell> {
    let mut cells = Vec::new();
    for grid in [false, true] {
        for lens in [Lens::Pinhole, Lens::Radtan, Lens::Equidistant] {
            let sizes = if grid { (24.0, 120.0) } else { (24.0, 200.0) };
            cells.push(Cell {
                grid,
                lens,
                sizes,
                max_obliquity: 60.0,
                n,
                width,
                height,
                noise: 2.0,
                blur: 0.8,
                quality: Quality::Accurate,
            });
        }
    }
    cells
}

pub fn print_table(rows: &[DetectRow]) {
    println!(
        "{:<34} {:>6} {:>7} {:>7} {:>8} {:>6} {:>7} {:>10} {:>9} {:>9} {:>8} {:>8} | {:>7} {:>7} {:>7} | {:>9} {:>8}",
        "cell",
        "images",
        "visible",
        "found",
        "rate %",
        "wrong",
        "layout",
        "rms px",
        "max px",
        "quad rms",
        "med ms",
        "quad ms",
        "<40px",
        "40-80",
        "≥80",
        "edge rms",
        "edge ms"
    );
    for r in rows {
        println!(
            "{:<34} {:>6} {:>7} {:>7} {:>8.2} {:>6} {:>7} {:>10.4} {:>9.3} {:>9.3} {:>8.1} {:>8.1} | {:>7.4} {:>7.4} {:>7.4} | {:>9.4} {:>8.1}",
            r.label,
            r.images,
            r.visible,
            r.found,
            100.0 * r.rate(),
            r.wrong_id,
            r.from_layout,
            r.corner_rms_px,
            r.corner_max_px,
            r.quad_rms_px,
            r.median_ms,
            r.quad_median_ms,
            r.corner_rms_by_size_px[0],
            r.corner_rms_by_size_px[1],
            r.corner_rms_by_size_px[2],
            r.edge_only_rms_px,
            r.edge_only_median_ms
        );
    }
}

/// Write every view of the study as `NNNN.png` plus `truth.json` (per image: camera,
/// and the true corners of the tags in view), for the peers script.
pub fn write_views(cells: &[Cell], seed: u64, dir: &std::path::Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir)?;
    let mut truth = Vec::new();
    let mut k = 0;
    for (ci, cell) in cells.iter().enumerate() {
        for i in 0..cell.n {
            let s = scene(&cell_params(cell, i, seed + 1000 * ci as u64));
            let name = format!("{k:04}.png");
            s.image.save(dir.join(&name))?;
            let tags: Vec<_> = s
                .truth
                .iter()
                .map(|(id, c)| serde_json::json!({"id": id, "corners": c.map(|p| [p.x, p.y])}))
                .collect();
            truth.push(serde_json::json!({
                "image": name, "cell": ci, "grid": cell.grid, "lens": cell.lens,
                "camera": rigcal_synth::camera_spec("cam", &s.camera),
                "targets": s.targets, "tags": tags,
            }));
            k += 1;
        }
    }
    std::fs::write(dir.join("truth.json"), serde_json::to_vec_pretty(&truth)?)?;
    Ok(())
}
