//! What a printed target looks like: tag cell patterns and the Kalibr AprilGrid layout.
//!
//! One place for the geometry of the print, shared by the detector (which predicts and
//! verifies tags through it), the renderer (which draws it) and the session resolver's
//! corner numbering (`tag:<id>:<k>`, counter-clockwise from the tag's bottom-left, board
//! `x` right and `y` up as printed), which `session::validate` resolves through here.

use super::tag36h11::{BIT_CELLS, CODES, WIDTH_AT_BORDER};
use crate::geometry::Vec2;

/// Is cell `(cx, cy)` of tag `id`'s 8×8 grid white? `cy` counts down from the top, as
/// printed; the outer ring of cells is the black border.
pub fn cell_white(id: u32, cx: usize, cy: usize) -> bool {
    let Some(code) = CODES.get(id as usize) else {
        return false;
    };
    match BIT_OF_CELL.get(cy * 8 + cx) {
        Some(&i) if i >= 0 => code >> (35 - i) & 1 == 1,
        _ => false,
    }
}

/// The code bit read at each cell of the 8×8 grid (`cy * 8 + cx`), −1 on the border:
/// [`BIT_CELLS`] inverted, so the renderer's and the fit's per-sample lookups are O(1).
static BIT_OF_CELL: [i8; 64] = {
    let mut t = [-1i8; 64];
    let mut i = 0;
    while i < BIT_CELLS.len() {
        let (x, y) = BIT_CELLS[i];
        t[y as usize * 8 + x as usize] = i as i8;
        i += 1;
    }
    t
};

/// Tag-local position of corner `k` (0..4, counter-clockwise from bottom-left) of a tag
/// of side `s` whose bottom-left corner is the origin.
pub fn tag_corner(s: f64, k: usize) -> Vec2 {
    match k % 4 {
        0 => Vec2::new(0.0, 0.0),
        1 => Vec2::new(s, 0.0),
        2 => Vec2::new(s, s),
        _ => Vec2::new(0.0, s),
    }
}

/// Shade of a tag-local point `(x, y)` (bottom-left origin, side `s`) when it lies on the
/// tag's black square: `Some(white?)`, `None` outside the square.
pub fn tag_shade(id: u32, s: f64, x: f64, y: f64) -> Option<bool> {
    if !(0.0..s).contains(&x) || !(0.0..s).contains(&y) {
        return None;
    }
    let n = WIDTH_AT_BORDER as f64;
    let cx = ((x / s) * n) as usize;
    let cy = (((s - y) / s) * n) as usize;
    Some(cell_white(id, cx.min(7), cy.min(7)))
}

/// A Kalibr AprilGrid: `rows × cols` tags of side `tag_size`, gaps of
/// `spacing · tag_size` with a black square at every gap crossing (also round the edge).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridLayout {
    pub rows: u32,
    pub cols: u32,
    pub tag_size: f64,
    pub spacing: f64,
    pub first_id: u32,
}

impl GridLayout {
    /// The layout of an `aprilgrid` target; `None` for other kinds.
    pub fn of(target: &crate::session::TargetSpec) -> Option<GridLayout> {
        match *target {
            crate::session::TargetSpec::Aprilgrid {
                rows,
                cols,
                tag_size,
                tag_spacing,
                first_id,
                ..
            } => Some(GridLayout {
                rows,
                cols,
                tag_size,
                spacing: tag_spacing,
                first_id,
            }),
            _ => None,
        }
    }

    pub fn pitch(&self) -> f64 {
        self.tag_size * (1.0 + self.spacing)
    }

    pub fn gap(&self) -> f64 {
        self.tag_size * self.spacing
    }

    pub fn tag_count(&self) -> u32 {
        self.rows * self.cols
    }

    /// `(row, col)` of a tag id on this board.
    pub fn cell_of(&self, id: u32) -> Option<(u32, u32)> {
        let k = id.checked_sub(self.first_id)?;
        (k < self.tag_count()).then(|| (k / self.cols, k % self.cols))
    }

    pub fn ids(&self) -> impl Iterator<Item = u32> + '_ {
        self.first_id..self.first_id + self.tag_count()
    }

    /// Board coordinates (m) of corner `k` of tag `id`.
    pub fn corner(&self, id: u32, k: usize) -> Option<Vec2> {
        let (r, c) = self.cell_of(id)?;
        let o = Vec2::new(c as f64 * self.pitch(), r as f64 * self.pitch());
        Some(o + tag_corner(self.tag_size, k))
    }

    /// Shade of board point `(x, y)`: `Some(white?)` on the printed board (tags, gap
    /// squares, a white margin of one gap beyond the outer squares), `None` off it.
    pub fn shade(&self, x: f64, y: f64) -> Option<bool> {
        let (p, g, s) = (self.pitch(), self.gap(), self.tag_size);
        let (w, h) = (self.cols as f64 * p, self.rows as f64 * p);
        if x < -2.0 * g || y < -2.0 * g || x > w + g || y > h + g {
            return None;
        }
        let (c, r) = ((x / p).floor(), (y / p).floor());
        let (lx, ly) = (x - c * p, y - r * p);
        if lx < s && ly < s {
            if (0.0..self.cols as f64).contains(&c) && (0.0..self.rows as f64).contains(&r) {
                let id = self.first_id + r as u32 * self.cols + c as u32;
                return tag_shade(id, s, lx, ly);
            }
            return Some(true);
        }
        // In a gap: black where both coordinates are in a gap (a crossing square).
        let crossing = lx >= s && ly >= s;
        let inside = c >= -1.0 && r >= -1.0 && c < self.cols as f64 && r < self.rows as f64;
        Some(!(crossing && inside))
    }
}

/// A single tag with a white quiet zone of two cells round it, centred on the origin.
pub fn single_tag_shade(id: u32, s: f64, x: f64, y: f64) -> Option<bool> {
    let margin = 2.0 * s / WIDTH_AT_BORDER as f64;
    let h = s / 2.0;
    if x.abs() > h + margin || y.abs() > h + margin {
        return None;
    }
    Some(tag_shade(id, s, x + h, y + h).unwrap_or(true))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn border_is_black_and_code_bits_read_back() {
        for id in [0u32, 1, 17, 586] {
            for i in 0..8 {
                for (x, y) in [(i, 0), (0, i), (7, i), (i, 7)] {
                    assert!(!cell_white(id, x, y), "border cell {x},{y} of tag {id}");
                }
            }
            let mut code = 0u64;
            for &(x, y) in BIT_CELLS.iter() {
                code = code << 1 | cell_white(id, x as usize, y as usize) as u64;
            }
            assert_eq!(code, CODES[id as usize]);
        }
    }

    #[test]
    fn grid_corners_follow_the_session_convention() {
        let g = GridLayout {
            rows: 6,
            cols: 6,
            tag_size: 0.1,
            spacing: 0.3,
            first_id: 0,
        };
        // tag 7 = row 1, col 1; corner 2 is its top-right.
        let c = g.corner(7, 2).unwrap();
        assert!((c - Vec2::new(0.13 + 0.1, 0.13 + 0.1)).norm() < 1e-12);
        assert_eq!(g.cell_of(36), None);
        // A crossing square between tags 0, 1, 6, 7 is black; the gap beside a tag is white.
        assert_eq!(g.shade(0.115, 0.115), Some(false));
        assert_eq!(g.shade(0.115, 0.05), Some(true));
        // Tag border is black, off the board is None.
        assert_eq!(g.shade(0.005, 0.05), Some(false));
        assert_eq!(g.shade(-1.0, 0.0), None);
    }
}
