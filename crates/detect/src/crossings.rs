//! Where an AprilGrid with no tag found yet may lie: the X-junctions its crossing squares
//! make where they touch the tags' corners, outside the tags already found.
//!
//! The bright-grown searches for boards without a seed segment the whole image, and on a
//! textured scene that costs as much as the first search (a fifth of a dense 1080p hall
//! image's detection) while the board it looks for is usually out of view. A board in
//! view shows dozens of X-junctions (every crossing square touches four tag corners, and
//! the tags' bits touch each other at corners too); a textured background shows a few,
//! scattered. So those searches run only on crops round blocks with several junctions
//! that no found tag explains.

use rigcal_core::geometry::Vec2;

/// A crop of the image: columns `x0..x1`, rows `y0..y1`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Rect {
    pub x0: usize,
    pub y0: usize,
    pub x1: usize,
    pub y1: usize,
}

impl Rect {
    pub fn area(&self) -> usize {
        (self.x1 - self.x0) * (self.y1 - self.y0)
    }

    fn overlaps(&self, o: &Rect) -> bool {
        self.x0 < o.x1 && o.x0 < self.x1 && self.y0 < o.y1 && o.y0 < self.y1
    }

    fn union(&self, o: &Rect) -> Rect {
        Rect {
            x0: self.x0.min(o.x0),
            y0: self.y0.min(o.y0),
            x1: self.x1.max(o.x1),
            y1: self.y1.max(o.y1),
        }
    }
}

/// Side (px) of the blocks junctions are counted in.
const BLOCK: usize = 32;
/// Unexplained junctions that make a block a possible board: the smallest boards the
/// grown searches seed (12 px tags) put several in every block they cover.
const MIN_JUNCTIONS: usize = 4;
/// Active blocks a group needs to be searched. Fewer hold at most a few of the smallest
/// legible tags (12 px, 15.6 px apart with Kalibr's spacing: three in a row already
/// reach across two blocks, 3×3 of them across two by two), while a board in view
/// covers blocks by the dozen. Textured scenes make lone blocks and pairs, each a
/// 128-px crop searched for nothing: 7-9 % of `accurate`'s instructions on the hall
/// presets, for the same tags found.
const MIN_BLOCKS: usize = 3;
/// Margin (px) of a crop round its blocks: a tag must lie whole in a crop to be found,
/// and a board's junctions may sit in one corner of a block.
const MARGIN: usize = 48;
/// Above this share of the image the crops are searched as the whole image.
const MAX_CROP_SHARE: f64 = 0.5;
/// Found tags explain the junctions within this share of their size round them (an
/// AprilGrid's crossing squares sit in the spacing, 0.3 of a tag in Kalibr's default).
const EXPLAINED_REACH: f64 = 0.5;

rigcal_core::avx2_or_portable! {
/// Marks in `hits` (one per pixel of the row, `w − 4` long, for columns `2..w − 2`)
/// the X-junctions of row `r[2]` (rows `r[0..5]` are `y − 2 ..= y + 2`): on the ring
/// of a pixel's 8 neighbours at 2 px (1.4 px on the diagonals), opposite samples agree
/// and perpendicular ones differ (a saddle: the second angular harmonic dominates the
/// antisymmetric part), the ring's range reaches `min_range`, the centre is near the
/// ring's mean (a thin line through the pixel has the same harmonic with a dark
/// centre), and that mean is near the middle of the ring's range (a junction's ring is
/// half dark and half bright, its boundary samples mid-grey; a thin line's is dark only
/// where the line crosses it, so a line passing beside the pixel, which the centre test
/// lets through, is caught here: the grout of a tiled floor made most of the hall
/// presets' crops). Written as plain loops over equal-length slices so that they
/// vectorise.
fn junction_row(r: [&[u8]; 5], min_range: i16, hits: &mut [bool]) {
    let n = hits.len();
    let at = |row: usize, dx: usize| &r[row][dx..dx + n];
    // Ring: east, south-east, south, south-west, west, north-west, north, north-east.
    let (e, se, s, sw) = (at(2, 4), at(3, 3), at(4, 2), at(3, 1));
    let (w, nw, no, ne) = (at(2, 0), at(1, 1), at(0, 2), at(1, 3));
    let c = at(2, 2);
    for i in 0..n {
        let ring = [e[i], se[i], s[i], sw[i], w[i], nw[i], no[i], ne[i]].map(i16::from);
        let hi = ring.iter().copied().fold(0, i16::max);
        let lo = ring.iter().copied().fold(255, i16::min);
        let range = hi - lo;
        let [e, se, s, sw, w, nw, no, ne] = ring;
        let even = (e + w - s - no).abs() + (se + nw - sw - ne).abs();
        let odd = (e - w).abs() + (s - no).abs() + (se - nw).abs() + (sw - ne).abs();
        let sum: i16 = ring.iter().sum();
        let centre = (8 * i16::from(c[i]) - sum).abs();
        // Every product stays under 10 200, in i16. (`&`, not `&&`: no branch in the
        // loop, so it vectorises.)
        let balance = (sum - 4 * (hi + lo)).abs();
        hits[i] = (range >= min_range)
            & (balance <= range)
            & (10 * even >= 16 * range)
            & (10 * odd <= 15 * range)
            & (5 * centre <= 8 * range);
    }
}
}

/// The grey range an X-junction must reach: the segmentation's own noise-adaptive
/// contrast floor (7σ: the ring's 8 samples of noise alone span ~3σ), and at least 20
/// grey, over the faint tile corners of a textured floor.
fn junction_range(segmentation_floor: u8) -> i16 {
    i16::from(segmentation_floor).max(20)
}

/// Crops of the `w × h` image `px` where a board without a found tag may lie: blocks
/// with at least [`MIN_JUNCTIONS`] X-junctions (of the range [`junction_range`] gives
/// for the segmentation's contrast floor) outside the `found` tags' surroundings,
/// joined where they touch into groups of at least [`MIN_BLOCKS`], widened by
/// [`MARGIN`] and merged where they overlap. Empty when there are none; the whole image
/// when the crops would cover most of it.
pub fn board_crops(
    px: &[u8],
    w: usize,
    h: usize,
    segmentation_floor: u8,
    found: &[[Vec2; 4]],
) -> Vec<Rect> {
    let whole = vec![Rect {
        x0: 0,
        y0: 0,
        x1: w,
        y1: h,
    }];
    if w < 5 || h < 5 || px.len() != w * h {
        return whole;
    }
    let (bw, bh) = (w.div_ceil(BLOCK), h.div_ceil(BLOCK));
    let explained = explained_mask(w, h, found);
    let cells_w = w.div_ceil(4);
    let min_range = junction_range(segmentation_floor);
    let mut counts = vec![0usize; bw * bh];
    let mut hits = vec![false; w - 4];
    for y in 2..h - 2 {
        let r = [y - 2, y - 1, y, y + 1, y + 2].map(|yy| &px[yy * w..(yy + 1) * w]);
        junction_row(r, min_range, &mut hits);
        let (row_counts, row_explained) = (
            &mut counts[(y / BLOCK) * bw..(y / BLOCK + 1) * bw],
            &explained[(y / 4) * cells_w..(y / 4 + 1) * cells_w],
        );
        // Hits are a few in ten thousand pixels: a run of pixels with none is passed over
        // by a sum that vectorises, where a loop over every hit was most of the scan.
        for (run, run_hits) in hits.chunks(BLOCK).enumerate() {
            if !run_hits.iter().fold(false, |any, &hit| any | hit) {
                continue;
            }
            for (i, _) in run_hits.iter().enumerate().filter(|(_, &hit)| hit) {
                let x = run * BLOCK + i + 2;
                if !row_explained[x / 4] {
                    row_counts[x / BLOCK] += 1;
                }
            }
        }
    }
    let active: Vec<bool> = counts.iter().map(|&c| c >= MIN_JUNCTIONS).collect();
    let crops = merge_overlapping(join_blocks(&active, bw, bh, w, h));
    let area: usize = crops.iter().map(Rect::area).sum();
    if area as f64 > MAX_CROP_SHARE * (w * h) as f64 {
        return whole;
    }
    crops
}

/// A mask of 4×4-px cells (row-major, `⌈w/4⌉` wide) that the found tags explain: each
/// tag's bounding box widened by [`EXPLAINED_REACH`] of its size.
fn explained_mask(w: usize, h: usize, found: &[[Vec2; 4]]) -> Vec<bool> {
    let (cw, ch) = (w.div_ceil(4), h.div_ceil(4));
    let mut mask = vec![false; cw * ch];
    for c in found {
        let (mut lo, mut hi) = (c[0], c[0]);
        for p in &c[1..] {
            lo = lo.inf(p);
            hi = hi.sup(p);
        }
        let reach = EXPLAINED_REACH * (hi - lo).max();
        let cell = |v: f64, n: usize| ((v / 4.0).floor().max(0.0) as usize).min(n - 1);
        let (x0, x1) = (cell(lo.x - reach, cw), cell(hi.x + reach, cw));
        let (y0, y1) = (cell(lo.y - reach, ch), cell(hi.y + reach, ch));
        for row in mask.chunks_mut(cw).take(y1 + 1).skip(y0) {
            row[x0..=x1].fill(true);
        }
    }
    mask
}

/// The bounding boxes (px, widened by [`MARGIN`], clipped to the image) of the
/// 8-connected groups of at least [`MIN_BLOCKS`] active blocks.
fn join_blocks(active: &[bool], bw: usize, bh: usize, w: usize, h: usize) -> Vec<Rect> {
    let mut seen = vec![false; active.len()];
    let mut crops = Vec::new();
    for start in 0..active.len() {
        if !active[start] || seen[start] {
            continue;
        }
        seen[start] = true;
        let mut stack = vec![start];
        let (mut bx0, mut by0, mut bx1, mut by1) = (bw, bh, 0, 0);
        let mut blocks = 0;
        while let Some(i) = stack.pop() {
            blocks += 1;
            let (bx, by) = (i % bw, i / bw);
            (bx0, by0, bx1, by1) = (bx0.min(bx), by0.min(by), bx1.max(bx), by1.max(by));
            for ny in by.saturating_sub(1)..(by + 2).min(bh) {
                for nx in bx.saturating_sub(1)..(bx + 2).min(bw) {
                    let j = ny * bw + nx;
                    if active[j] && !seen[j] {
                        seen[j] = true;
                        stack.push(j);
                    }
                }
            }
        }
        if blocks < MIN_BLOCKS {
            continue;
        }
        crops.push(Rect {
            x0: (bx0 * BLOCK).saturating_sub(MARGIN),
            y0: (by0 * BLOCK).saturating_sub(MARGIN),
            x1: ((bx1 + 1) * BLOCK + MARGIN).min(w),
            y1: ((by1 + 1) * BLOCK + MARGIN).min(h),
        });
    }
    crops
}

/// Crops that overlap (their margins, mostly) replaced by their bounding box until none
/// do: one segmentation instead of two over the shared pixels.
fn merge_overlapping(mut crops: Vec<Rect>) -> Vec<Rect> {
    let mut i = 0;
    while i < crops.len() {
        match (i + 1..crops.len()).find(|&j| crops[i].overlaps(&crops[j])) {
            Some(j) => {
                let other = crops.swap_remove(j);
                crops[i] = crops[i].union(&other);
                i = 0;
            }
            None => i += 1,
        }
    }
    crops
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gray::Gray;
    use crate::quads::QuadOptions;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    use rigcal_synth::render::RenderOptions;
    use rigcal_synth::tagscene::{scene, Lens, SceneParams};

    /// Hits of [`junction_row`] on a 5×5 patch's centre.
    fn centre_hit(patch: [[u8; 5]; 5], min_range: i16) -> bool {
        let rows: Vec<Vec<u8>> = patch.iter().map(|r| r.to_vec()).collect();
        let mut hits = [false; 1];
        junction_row(
            [&rows[0], &rows[1], &rows[2], &rows[3], &rows[4]],
            min_range,
            &mut hits,
        );
        hits[0]
    }

    #[test]
    fn a_saddle_is_a_junction_and_edges_lines_and_flats_are_not() {
        let (b, w) = (20, 220);
        // Two black quadrants touching at the centre (the centre pixel mid-grey).
        let x = [
            [b, b, w, w, w],
            [b, b, w, w, w],
            [b, b, 120, w, w],
            [w, w, w, b, b],
            [w, w, w, b, b],
        ];
        assert!(centre_hit(x, 20));
        assert!(!centre_hit(x, 250), "a range under the floor counts");
        let edge = [[b, b, b, w, w]; 5];
        assert!(!centre_hit(edge, 20));
        // A thin dark line through the centre: the same second harmonic, dark centre.
        let line = [[w, w, b, w, w]; 5];
        assert!(!centre_hit(line, 20));
        assert!(!centre_hit([[128; 5]; 5], 1));
    }

    #[test]
    fn overlapping_crops_merge_into_their_bounding_box() {
        let r = |x0, y0, x1, y1| Rect { x0, y0, x1, y1 };
        let merged = merge_overlapping(vec![r(0, 0, 10, 10), r(50, 50, 60, 60), r(5, 5, 20, 20)]);
        assert_eq!(merged.len(), 2);
        assert!(merged.contains(&r(0, 0, 20, 20)));
        assert!(merged.contains(&r(50, 50, 60, 60)));
        // Chains merge through: a joins c only through b.
        let chain = merge_overlapping(vec![r(0, 0, 10, 10), r(30, 0, 40, 10), r(8, 0, 32, 10)]);
        assert_eq!(chain, vec![r(0, 0, 40, 10)]);
    }

    /// AprilGrids with no tag found, from the legibility limit (12 px tags) to large
    /// oblique ones, through three lenses, printed at full and at dim contrast (40 grey
    /// between black and white) under σ 2 grey noise: a crop always holds a whole tag,
    /// so the grown searches can seed the board, and the crops stay a part of the image.
    #[test]
    fn every_board_view_has_a_crop_round_a_whole_tag() {
        let views = [
            (12.0, 0.0),
            (15.0, 20.0),
            (30.0, 50.0),
            (38.0, 56.0),
            (60.0, 60.0),
        ];
        for lens in [Lens::Pinhole, Lens::Radtan, Lens::Equidistant] {
            for (i, &(tag_px, obliquity_deg)) in views.iter().enumerate() {
                for (black, white) in [(25.0, 230.0), (100.0, 140.0)] {
                    let s = scene(&SceneParams {
                        grid: true,
                        tag_px,
                        obliquity_deg,
                        lens,
                        width: 800,
                        height: 600,
                        render: RenderOptions {
                            black,
                            white,
                            background: (black + white) / 2.0,
                            seed: 7 + i as u64,
                            ..Default::default()
                        },
                        seed: 300 + i as u64,
                    });
                    let gray = Gray::from_luma8(&s.image);
                    let floor = QuadOptions::default().contrast_for(&gray);
                    let (w, h) = (gray.width, gray.height);
                    let crops = board_crops(&gray.to_u8(), w, h, floor, &[]);
                    let inside = |r: &Rect, c: &[Vec2; 4]| {
                        c.iter().all(|p| {
                            p.x >= r.x0 as f64 + 1.0
                                && p.y >= r.y0 as f64 + 1.0
                                && p.x <= r.x1 as f64 - 2.0
                                && p.y <= r.y1 as f64 - 2.0
                        })
                    };
                    let held = s
                        .truth
                        .values()
                        .filter(|c| crops.iter().any(|r| inside(r, c)))
                        .count();
                    let what = format!(
                        "{lens:?} {tag_px} px at {obliquity_deg}°, print {black}-{white}: {crops:?}"
                    );
                    assert!(held >= 1, "{what}: no crop holds a whole tag");
                    // The board's own extent, widened by the margin, bounds the crops.
                    let (mut lo, mut hi) = (Vec2::new(f64::MAX, f64::MAX), Vec2::zeros());
                    for p in s.truth.values().flatten() {
                        lo = lo.inf(p);
                        hi = hi.sup(p);
                    }
                    let board =
                        (hi.x - lo.x + 4.0 * BLOCK as f64) * (hi.y - lo.y + 4.0 * BLOCK as f64);
                    let area: usize = crops.iter().map(Rect::area).sum();
                    assert!(
                        area == w * h || area as f64 <= board.max(0.2 * (w * h) as f64),
                        "{what}: crops of {area} px for a board of {board:.0}"
                    );
                }
            }
        }
    }

    /// A lone patch of X-junctions (a checkered tile, a logo) makes no crop; a field of
    /// them as wide as a board does.
    #[test]
    fn lone_junctions_make_no_crop() {
        let (w, h) = (640, 480);
        // A checker of `n × n` squares of 6 px turned by 30°, its corner at (x0, y0),
        // each pixel the mean of 4 × 4 samples (the junctions of a sharp checker on
        // the pixel grid are not saddles at 2 px, as they are in any camera's image).
        let checker = |px: &mut [u8], x0: usize, y0: usize, n: usize| {
            let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
            let side = 6.0 * n as f64;
            for y in y0.saturating_sub(8)..y0 + 6 * n + 8 {
                for x in x0.saturating_sub(8)..x0 + 6 * n + 8 {
                    let (mut sum, mut inside) = (0.0, 0);
                    for k in 0..16 {
                        let dx = x as f64 - x0 as f64 + (k % 4) as f64 / 4.0 - 0.375;
                        let dy = y as f64 - y0 as f64 + (k / 4) as f64 / 4.0 - 0.375;
                        let (u, v) = (c * dx + s * dy, -s * dx + c * dy);
                        if (0.0..side).contains(&u) && (0.0..side).contains(&v) {
                            let dark = ((u / 6.0) as usize + (v / 6.0) as usize).is_multiple_of(2);
                            sum += if dark { 40.0 } else { 220.0 };
                            inside += 1;
                        }
                    }
                    if inside == 16 {
                        px[y * w + x] = (sum / 16.0) as u8;
                    }
                }
            }
        };
        let mut lone = vec![128u8; w * h];
        // 4 × 4 squares: 9 junctions, in one or two 32-px blocks.
        for (x0, y0) in [(40, 40), (300, 200), (500, 390)] {
            checker(&mut lone, x0, y0, 4);
        }
        assert!(board_crops(&lone, w, h, 10, &[]).is_empty());
        let mut field = lone.clone();
        checker(&mut field, 200, 64, 16);
        let crops = board_crops(&field, w, h, 10, &[]);
        assert_eq!(crops.len(), 1, "{crops:?}");
        let r = crops[0];
        assert!(
            r.x0 <= 200 && r.y0 <= 64 && r.x1 >= 296 && r.y1 >= 160,
            "{r:?}"
        );
    }

    /// A tiled floor's grout (thin dark lines, oblique, anti-aliased, between tiles of
    /// varied shade) makes no crop: on the hall presets such lines were most of the
    /// crops searched, for no board.
    #[test]
    fn thin_lines_make_no_crop() {
        let (w, h) = (640, 480);
        // Two families of lines 48 px apart, 3 px wide, at 12° and 102°, each pixel the
        // mean of 4 × 4 samples. (Without the ring's balance 198 pixels of it hit, and
        // the field made a crop; 2-4 px lines at 2-40° hit 2-8× less with it.)
        let (c, s) = (12f64.to_radians().cos(), 12f64.to_radians().sin());
        let mut px = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let mut sum = 0.0;
                for k in 0..16 {
                    let fx = x as f64 + (k % 4) as f64 / 4.0 - 0.375;
                    let fy = y as f64 + (k / 4) as f64 / 4.0 - 0.375;
                    let (u, v) = (c * fx + s * fy + 1000.0, -s * fx + c * fy + 1000.0);
                    let (tu, tv) = ((u / 48.0).floor(), (v / 48.0).floor());
                    let grout = u - 48.0 * tu < 3.0 || v - 48.0 * tv < 3.0;
                    let shade = 120.0 + 25.0 * ((tu * 7.0 + tv * 3.0) % 5.0 - 2.0);
                    sum += if grout { 40.0 } else { shade };
                }
                px[y * w + x] = (sum / 16.0) as u8;
            }
        }
        assert!(board_crops(&px, w, h, 10, &[]).is_empty());
    }

    /// Sensor noise alone, faint or strong, makes no crop.
    #[test]
    fn noise_makes_no_crop() {
        let (w, h) = (640, 480);
        for sigma in [2.0, 6.0] {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
            let n = Normal::new(128.0f64, sigma).unwrap();
            let px: Vec<u8> = (0..w * h)
                .map(|_| n.sample(&mut rng).clamp(0.0, 255.0) as u8)
                .collect();
            let gray = Gray {
                width: w,
                height: h,
                data: px.iter().map(|&v| v as f32).collect(),
            };
            let floor = QuadOptions::default().contrast_for(&gray);
            assert!(board_crops(&px, w, h, floor, &[]).is_empty(), "σ {sigma}");
        }
    }

    /// Junctions inside found tags' surroundings are explained: a board whose tags are
    /// all found makes no crop.
    #[test]
    fn found_tags_explain_their_junctions() {
        let s = scene(&SceneParams {
            grid: true,
            tag_px: 40.0,
            obliquity_deg: 20.0,
            lens: Lens::Pinhole,
            width: 800,
            height: 600,
            render: RenderOptions::default(),
            seed: 9,
        });
        let gray = Gray::from_luma8(&s.image);
        let floor = QuadOptions::default().contrast_for(&gray);
        let px = gray.to_u8();
        assert!(!board_crops(&px, 800, 600, floor, &[]).is_empty());
        let found: Vec<[Vec2; 4]> = s.truth.values().copied().collect();
        assert!(board_crops(&px, 800, 600, floor, &found).is_empty());
    }
}
