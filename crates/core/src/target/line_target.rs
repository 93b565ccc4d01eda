//! The geometry of Wu's line target in its own frame.
//!
//! The paper's Fig. 1 is not in the extracted text; what the equations fix is: the target
//! lies in its `x-z` plane (`y = 0`); `l1` is the `z` axis and `l6` the `x` axis, meeting
//! at the origin `P1`; corner `Pm` lies on lines `lm` and `l(m-1)` (eq. 19-20, `l0 = l6`),
//! so the six lines close a hexagon whose edges alternate between the two directions;
//! `P1P2` is perpendicular to the `x` direction and `L1` long (eq. 14-16). The right-angled
//! hexagon with these properties, symmetric about the diagonal `x = z` (the "symmetry axis"
//! the paper turns towards the camera), is an L of arm length `L1` and arm width `L2`:
//!
//! ```text
//!  z ^  P2 ___ P3
//!    |   |   |
//!    |   |   |P4_______ P5
//!    |   |              |
//!    |  P1______________|P6 --> x
//! ```
//!
//! `l1 = P1P2, l2 = P2P3, l3 = P3P4, l4 = P4P5, l5 = P5P6, l6 = P6P1`; lines `l1, l3, l5` run
//! along `z` (their vanishing point gives the target's `z` axis), `l2, l4, l6` along `x`.

use super::line_layout::LineLayout;
use crate::geometry::Vec3;

/// Number of feature lines (and corners) of a line target.
pub const LINES: usize = 6;
/// Lines along the target's `z` axis (0-based).
pub const Z_GROUP: [usize; 3] = [0, 2, 4];
/// Lines along the target's `x` axis (0-based).
pub const X_GROUP: [usize; 3] = [1, 3, 5];

/// A line target of outer length `length` (L1) and spacing `spacing` (L2), metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LineTarget {
    pub length: f64,
    pub spacing: f64,
}

impl LineTarget {
    /// Corners `P1..P6` (0-based) in the target frame.
    pub fn corners(&self) -> [Vec3; LINES] {
        let (a, b) = (self.length, self.spacing);
        [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(0.0, 0.0, a),
            Vec3::new(b, 0.0, a),
            Vec3::new(b, 0.0, b),
            Vec3::new(a, 0.0, b),
            Vec3::new(a, 0.0, 0.0),
        ]
    }

    /// End points of feature line `m` (0-based): from corner `m` to corner `m + 1`.
    pub fn segment(&self, m: usize) -> (Vec3, Vec3) {
        let c = self.corners();
        (c[m], c[(m + 1) % LINES])
    }

    /// This L as one [`LineLayout`] among the vanishing method's layouts.
    pub fn layout(&self) -> LineLayout {
        LineLayout::l_target(self.length, self.spacing)
    }

    /// The other line through corner `m`: `l(m-1)`, with `l0 = l6` (eq. 20).
    pub fn previous_line(m: usize) -> usize {
        (m + LINES - 1) % LINES
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn corners_lie_on_their_two_lines_and_groups_are_parallel() {
        let t = LineTarget {
            length: 0.5,
            spacing: 0.2,
        };
        let c = t.corners();
        for m in 0..LINES {
            // Corner m starts line m and ends line m-1.
            assert_eq!(t.segment(m).0, c[m]);
            assert_eq!(t.segment(LineTarget::previous_line(m)).1, c[m]);
        }
        for g in Z_GROUP {
            let (a, b) = t.segment(g);
            assert!((b - a).cross(&Vec3::z()).norm() < 1e-15);
        }
        for g in X_GROUP {
            let (a, b) = t.segment(g);
            assert!((b - a).cross(&Vec3::x()).norm() < 1e-15);
        }
        assert!(((c[1] - c[0]).norm() - 0.5).abs() < 1e-15);
        assert!(c.iter().all(|p| p.y == 0.0));
    }
}
