//! Read a tag's bits through its quad, to confirm that a predicted tag is really there
//! with the expected id (AprilGrid completion) — never to guess an id.

use super::gray::Gray;
use super::refine::Lens;
use rigcal_core::geometry::homography::homography;
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
    let level = |cx: f64, cy: f64| -> Option<f64> {
        // Mean of a 3×3 pattern over the middle half of the cell.
        let mut acc = 0.0;
        for dy in [-0.25, 0.0, 0.25] {
            for dx in [-0.25, 0.0, 0.25] {
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
    let hamming = (0..36)
        .filter(|&i| (bits[i] > threshold) != expected(i))
        .count() as u32;
    let border_black = border.iter().filter(|&&v| v < threshold).count() as u32;
    Some(Reading {
        hamming,
        border_black,
        margin: w - b,
    })
}
