//! Read a tag's bits through its quad, to confirm that a predicted tag is really there
//! with the expected id (AprilGrid completion) — never to guess an id.

use super::gray::Gray;
use super::refine::Lens;
use rigcal_core::geometry::homography::homography_of_general_position as homography;
use rigcal_core::geometry::{Mat3, Vec2, Vec3};
use rigcal_core::target::tag36h11::{BIT_CELLS, CODES, WIDTH_AT_BORDER};

/// What the cells of a quad say.
#[derive(Clone, Debug)]
pub struct Reading {
    /// Bit errors against the expected code.
    pub hamming: u32,
    /// Black border cells read as black (of 28).
    pub border_black: u32,
    /// Mean white − mean black cell level, in grey levels.
    pub margin: f64,
}

/// How far from a cell's centre (in cells) its 3×3 samples reach: over the middle half
/// of the cell, but never closer than [`EDGE_CLEARANCE_PX`] to its edge. At 1.5-2 px per
/// cell (a 12-16 px tag) the optics blur spreads a neighbour's level that far: samples a
/// quarter cell out read an isolated bit as its neighbours (3 bit errors on every such tag
/// of a hand-held fisheye capture, where the centre reads 0-2).
fn sample_spread(corners: &[Vec2; 4]) -> f64 {
    (0.5 - EDGE_CLEARANCE_PX / cell_px(corners)).clamp(0.0, 0.25)
}

/// A tag's cell (px) along its shortest side: its smallest bit in the image.
pub(crate) fn cell_px(corners: &[Vec2; 4]) -> f64 {
    let side = (0..4)
        .map(|k| (corners[(k + 1) % 4] - corners[k]).norm())
        .fold(f64::MAX, f64::min);
    side / WIDTH_AT_BORDER as f64
}

/// Pixels a bit's samples keep from its cell's edge (≈ the blur of a sharp lens plus the
/// bilinear interpolation's reach).
const EDGE_CLEARANCE_PX: f64 = 0.6;

/// Sample the 8×8 cells of the tag whose corners (raw pixels, `k` order) are given and
/// compare them with the code of `id`.
pub fn read_tag(img: &Gray, corners: &[Vec2; 4], lens: Lens, id: u32) -> Option<Reading> {
    let code = *CODES.get(id as usize)?;
    let plane = lens.quad_to_plane(corners)?;
    // Tag cell coordinates: (0, 0) top-left, (8, 8) bottom-right as printed; corner k=0
    // (bottom-left) is (0, 8).
    let n = WIDTH_AT_BORDER as f64;
    let cells = [
        Vec2::new(0.0, n),
        Vec2::new(n, n),
        Vec2::new(n, 0.0),
        Vec2::new(0.0, 0.0),
    ];
    let h: Mat3 = homography(&cells, &plane)?;
    let o = sample_spread(corners);
    let level = |cx: f64, cy: f64| -> Option<f64> {
        // Mean of a 3×3 pattern around the cell's centre.
        let mut acc = 0.0;
        for dy in [-o, 0.0, o] {
            for dx in [-o, 0.0, o] {
                let p = h * Vec3::new(cx + 0.5 + dx, cy + 0.5 + dy, 1.0);
                let q = lens.to_pixel(Vec2::new(p.x / p.z, p.y / p.z))?;
                acc += img.sample(q)?;
            }
        }
        Some(acc / 9.0)
    };
    let mut border = Vec::new();
    for i in 0..8 {
        for (x, y) in [(i, 0), (7, i), (7 - i, 7), (0, 7 - i)] {
            if i < 7 {
                border.push(level(x as f64, y as f64)?);
            }
        }
    }
    let bits: Vec<f64> = BIT_CELLS
        .iter()
        .map(|&(x, y)| level(x as f64, y as f64))
        .collect::<Option<_>>()?;
    // White reference: the expected-white bits; black: the border and expected-black bits.
    let expected = |i: usize| code >> (35 - i) & 1 == 1;
    let whites: Vec<f64> = (0..36).filter(|&i| expected(i)).map(|i| bits[i]).collect();
    let blacks: Vec<f64> = (0..36)
        .filter(|&i| !expected(i))
        .map(|i| bits[i])
        .chain(border.iter().copied())
        .collect();
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let (w, b) = (mean(&whites), mean(&blacks));
    let threshold = 0.5 * (w + b);
    let hamming = bit_errors(&bits, expected);
    let border_black = border.iter().filter(|&&v| v < threshold).count() as u32;
    Some(Reading {
        hamming,
        border_black,
        margin: w - b,
    })
}

/// Bits of the expected code (`expected(i)`, 1 = white) that the cell levels contradict,
/// judged against a model of the print seen through the optics: a cell's level is
/// `α + β·(own + κ·edge neighbours)`, fitted over the 36 bit cells, with the cross-talk
/// `κ` in `[0, MAX_CROSS_TALK]`. At 1.5-2 px per cell the blur carries a good part of a
/// cell's level into its neighbours, so an isolated white bit among blacks reads darker
/// than the mean of whites and one threshold calls it black (3-6 bit errors on 12-14 px
/// tags a human reads at a glance); the fitted cross-talk predicts that, and only a level
/// nearer the other value's prediction is an error. One cross-talk term, bounded, so a
/// wrong code cannot explain its wrong bits by its neighbours (with a second, diagonal
/// term a wrong code read within 4 bits; with this one, 6 or more): the model confirms,
/// never rescues, an id.
fn bit_errors(bits: &[f64], expected: impl Fn(usize) -> bool) -> u32 {
    let n = WIDTH_AT_BORDER;
    let mut printed = vec![0.0; n * n]; // the black border
    for (i, &(x, y)) in BIT_CELLS.iter().enumerate() {
        printed[y as usize * n + x as usize] = expected(i) as u8 as f64;
    }
    let at = |x: usize, y: usize| printed[y * n + x];
    // (own, edge neighbours) per bit cell; bit cells are inside the border, so every
    // neighbour is a cell of the tag.
    let cells: Vec<(f64, f64)> = BIT_CELLS
        .iter()
        .map(|&(x, y)| {
            let (x, y) = (x as usize, y as usize);
            let edge = at(x - 1, y) + at(x + 1, y) + at(x, y - 1) + at(x, y + 1);
            (at(x, y), edge)
        })
        .collect();
    // Least squares of `level = α + β·(own + κ·edge)` for a given κ: (α, β, residual²).
    let fit = |kappa: f64| -> Option<(f64, f64, f64)> {
        let m = bits.len() as f64;
        let xs: Vec<f64> = cells.iter().map(|(o, e)| o + kappa * e).collect();
        let (sx, sy) = (xs.iter().sum::<f64>(), bits.iter().sum::<f64>());
        let sxx: f64 = xs.iter().map(|x| x * x).sum();
        let sxy: f64 = xs.iter().zip(bits).map(|(x, y)| x * y).sum();
        let det = m * sxx - sx * sx;
        if det.abs() < 1e-9 {
            return None;
        }
        let beta = (m * sxy - sx * sy) / det;
        let alpha = (sy - beta * sx) / m;
        let ssr = xs
            .iter()
            .zip(bits)
            .map(|(x, y)| (y - alpha - beta * x).powi(2))
            .sum();
        Some((alpha, beta, ssr))
    };
    // κ on a fine grid over its bound: a one-dimensional search, exact enough for a
    // yes/no per bit and free of a constrained solver.
    let best = (0..=20)
        .filter_map(|k| {
            let kappa = MAX_CROSS_TALK * k as f64 / 20.0;
            fit(kappa).map(|f| (kappa, f))
        })
        .min_by(|a, b| a.1 .2.total_cmp(&b.1 .2));
    let Some((kappa, (alpha, beta, _))) = best else {
        return bits.len() as u32;
    };
    if beta <= 0.0 {
        return bits.len() as u32;
    }
    cells
        .iter()
        .zip(bits)
        .filter(|((own, edge), v)| {
            let residual = *v - (alpha + beta * (own + kappa * edge));
            if *own > 0.5 {
                residual < -0.5 * beta
            } else {
                residual > 0.5 * beta
            }
        })
        .count() as u32
}

/// Largest cross-talk of one edge neighbour into a cell, relative to the cell's own
/// level: a Gaussian blur of σ = 0.7 cell (a 12 px tag under σ 1 px optics, beyond
/// legible) gives 0.38; the fit on 13 px tags under σ 0.8 px gives ~0.35.
const MAX_CROSS_TALK: f64 = 0.45;

#[cfg(test)]
mod tests {
    use super::*;
    use rigcal_synth::render::RenderOptions;
    use rigcal_synth::tagscene::{scene, Lens as SceneLens, SceneParams};

    /// Boards of 13 px tags (1.6 px per cell, blur σ 0.8, noise σ 2) through every lens:
    /// each tag reads as its own id within 1 bit where one threshold over the mean levels
    /// made 3-6 errors on such tags, and as every other code of the family at least 6 bits
    /// off (the completion accepts 2), so the blur model confirms ids without inventing
    /// them.
    #[test]
    fn small_tags_read_as_their_own_id_and_no_other() {
        let mut own = Vec::new();
        let mut nearest_other = u32::MAX;
        for (k, lens) in [
            SceneLens::Pinhole,
            SceneLens::Radtan,
            SceneLens::Equidistant,
        ]
        .into_iter()
        .enumerate()
        {
            let s = scene(&SceneParams {
                grid: true,
                tag_px: 13.0,
                obliquity_deg: 30.0,
                lens,
                width: 640,
                height: 480,
                render: RenderOptions::default(),
                seed: 40 + k as u64,
            });
            let img = Gray::from_luma8(&s.image);
            for (id, corners) in &s.truth {
                let read = |code: u32| read_tag(&img, corners, Lens(Some(&s.camera)), code);
                own.push(read(*id).expect("inside the image").hamming);
                for other in (0..CODES.len() as u32).filter(|o| o != id) {
                    nearest_other = nearest_other.min(read(other).expect("inside").hamming);
                }
            }
        }
        assert!(own.len() >= 60, "{} tags", own.len());
        assert!(own.iter().all(|&h| h <= 1), "own ids read as {own:?}");
        assert!(
            nearest_other >= 6,
            "another code read within {nearest_other} bits"
        );
    }
}
