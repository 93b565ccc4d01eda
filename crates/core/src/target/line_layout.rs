//! Any target of two mutually orthogonal groups of parallel lines (Wu et al.: "two groups
//! of parallel lines"), as the vanishing method sees it: straight segments in the target's
//! plane, each along the target's `x` or its `z` axis.
//!
//! The frame is Wu's (see [`super::line_target`]): the sheet is the target's `x–z` plane.
//! Users describe prints in the sheet's own 2-D coordinates `(x, y)`; sheet `y` is target
//! `z`, so a sheet read from the front keeps its handedness (target `y = z × x` is the
//! sheet's normal, pointing away from the printed side).
//!
//! Three prints are layouts: the filled L (its six outline edges), the thin-line grid
//! (`lines_x` lines along `x`, `lines_y` along sheet `y`, all `length` long, centred, a
//! group's lines `spacing` apart), and an explicit list of segments. The estimators use
//! the segments, their two groups, the crossings of every `x` line with every `z` line
//! (points of known target coordinates where the infinite lines meet, which fix the
//! translation), and the layout's symmetries, which make a line's label in one image
//! ambiguous. An optional printed orientation mark (a filled disc off the centre of
//! symmetry) breaks them: the detector reads which way round the print was seen.

use crate::geometry::{so3, Pose, Vec3};

/// The target axis a line runs along.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Axis {
    X,
    Z,
}

/// One printed line (or outline edge) in the target frame (`y = 0`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Segment {
    pub from: Vec3,
    pub to: Vec3,
    pub axis: Axis,
}

/// A proper rotation of the sheet about its normal that maps the layout onto itself:
/// `target_from_image_label` turns the frame a labelling implied into the frame the
/// layout defines, and line `m` of that labelling is physically line `line_of[m]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Symmetry {
    /// Rotation about the target normal, degrees (0, 90, 180, 270).
    pub degrees: u32,
    pub target_from_labelled: Pose,
    pub line_of: Vec<usize>,
}

/// How the lines are printed, which decides how they are measured in images.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Print {
    /// A filled dark region whose outline edges are the lines (the L).
    Outline,
    /// Thin dark strokes of this width (m): the lines are ridges (Steger).
    Strokes { width: f64 },
}

/// A filled dark disc printed on the sheet to tell the layout's symmetric labellings
/// apart: only one of them puts the disc where the print has it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Mark {
    /// Centre in the target frame (`y = 0`).
    pub centre: Vec3,
    /// Radius (m).
    pub radius: f64,
}

#[derive(Clone, Debug, PartialEq)]
pub struct LineLayout {
    pub segments: Vec<Segment>,
    pub print: Print,
    pub mark: Option<Mark>,
}

/// Relative tolerance on coordinates when matching a layout with its rotation.
const SAME: f64 = 1e-9;

impl LineLayout {
    /// Wu's filled L: outline length L1, arm width L2 (see [`super::line_target`]).
    pub fn l_target(length: f64, spacing: f64) -> Self {
        let t = super::line_target::LineTarget { length, spacing };
        let segments = (0..super::line_target::LINES)
            .map(|m| {
                let (from, to) = t.segment(m);
                let axis = if super::line_target::Z_GROUP.contains(&m) {
                    Axis::Z
                } else {
                    Axis::X
                };
                Segment { from, to, axis }
            })
            .collect();
        Self {
            segments,
            print: Print::Outline,
            mark: None,
        }
    }

    /// A grid of thin lines centred on the sheet's origin: lines `1..=lines_x` run along
    /// `x` (ordered by increasing sheet `y`), then `lines_y` along sheet `y` (ordered by
    /// increasing `x`); every line `length` long, a group's lines `spacing` apart.
    pub fn grid(length: f64, spacing: f64, lines_x: usize, lines_y: usize, stroke: f64) -> Self {
        let offset = |k: usize, n: usize| (k as f64 - (n as f64 - 1.0) / 2.0) * spacing;
        let h = length / 2.0;
        let mut segments = Vec::with_capacity(lines_x + lines_y);
        for k in 0..lines_x {
            let z = offset(k, lines_x);
            segments.push(Segment {
                from: Vec3::new(-h, 0.0, z),
                to: Vec3::new(h, 0.0, z),
                axis: Axis::X,
            });
        }
        for k in 0..lines_y {
            let x = offset(k, lines_y);
            segments.push(Segment {
                from: Vec3::new(x, 0.0, -h),
                to: Vec3::new(x, 0.0, h),
                axis: Axis::Z,
            });
        }
        Self {
            segments,
            print: Print::Strokes { width: stroke },
            mark: None,
        }
    }

    /// Explicit segments `[[x0, y0], [x1, y1]]` in sheet coordinates; each must run along
    /// sheet `x` or sheet `y`. `Err((index, what))` names the offending segment.
    pub fn from_sheet_segments(
        segments: &[[[f64; 2]; 2]],
        stroke: f64,
    ) -> Result<Self, (usize, String)> {
        let scale = segments
            .iter()
            .flat_map(|s| s.iter().flat_map(|p| p.iter().map(|v| v.abs())))
            .fold(0.0, f64::max)
            .max(1e-300);
        let mut out = Vec::with_capacity(segments.len());
        for (i, [a, b]) in segments.iter().enumerate() {
            if !a.iter().chain(b).all(|v| v.is_finite()) {
                return Err((i, "finite coordinates (m)".into()));
            }
            let (dx, dy) = ((b[0] - a[0]).abs(), (b[1] - a[1]).abs());
            let axis = if dy <= SAME * scale && dx > SAME * scale {
                Axis::X
            } else if dx <= SAME * scale && dy > SAME * scale {
                Axis::Z
            } else {
                return Err((
                    i,
                    format!(
                        "a segment of non-zero length along the sheet's x or y axis, got {a:?} → {b:?}"
                    ),
                ));
            };
            out.push(Segment {
                from: Vec3::new(a[0], 0.0, a[1]),
                to: Vec3::new(b[0], 0.0, b[1]),
                axis,
            });
        }
        Ok(Self {
            segments: out,
            print: Print::Strokes { width: stroke },
            mark: None,
        })
    }

    /// The layout with an orientation mark at sheet `(x, y)`, `radius` m.
    pub fn with_mark(self, x: f64, y: f64, radius: f64) -> Self {
        Self {
            mark: Some(Mark {
                centre: Vec3::new(x, 0.0, y),
                radius,
            }),
            ..self
        }
    }

    pub fn len(&self) -> usize {
        self.segments.len()
    }

    pub fn is_empty(&self) -> bool {
        self.segments.is_empty()
    }

    /// End points of line `m` (0-based).
    pub fn segment(&self, m: usize) -> (Vec3, Vec3) {
        (self.segments[m].from, self.segments[m].to)
    }

    /// Lines along `axis`, in layout order.
    pub fn group(&self, axis: Axis) -> Vec<usize> {
        (0..self.len())
            .filter(|&m| self.segments[m].axis == axis)
            .collect()
    }

    /// Where each `x` line's infinite line meets each `z` line's: `(x line, z line, point)`.
    pub fn crossings(&self) -> Vec<(usize, usize, Vec3)> {
        let mut out = Vec::new();
        for i in self.group(Axis::X) {
            for j in self.group(Axis::Z) {
                let p = Vec3::new(self.segments[j].from.x, 0.0, self.segments[i].from.z);
                out.push((i, j, p));
            }
        }
        out
    }

    /// The centre of the segments' end points: the centre of any symmetry.
    pub fn centre(&self) -> Vec3 {
        let sum: Vec3 = self.segments.iter().map(|s| s.from + s.to).sum();
        sum / (2.0 * self.len().max(1) as f64)
    }

    /// Half the largest extent: the scale of "same point" tolerances.
    fn extent(&self) -> f64 {
        let c = self.centre();
        self.segments
            .iter()
            .flat_map(|s| [(s.from - c).norm(), (s.to - c).norm()])
            .fold(0.0, f64::max)
    }

    /// The rotations about the sheet normal through [`Self::centre`] (identity first)
    /// that map every segment onto a segment and the mark, if any, onto itself: the
    /// labellings one image cannot tell apart. The L has only the identity; a 3×2 grid a
    /// half-turn; a 3×3 grid quarter-turns; a marked grid only the identity.
    pub fn symmetries(&self) -> Vec<Symmetry> {
        let tol = 1e-6 * self.extent().max(1e-12);
        let mut out = self.line_symmetries();
        if let Some(m) = self.mark {
            out.retain(|g| (g.target_from_labelled.apply(&m.centre) - m.centre).norm() < tol);
        }
        out
    }

    /// The symmetries of the lines alone (what a detector sees before it reads a mark).
    pub fn line_symmetries(&self) -> Vec<Symmetry> {
        let c = self.centre();
        let tol = 1e-6 * self.extent().max(1e-12);
        let mut out = Vec::new();
        for quarter in 0..4u32 {
            let rot = so3::exp(&Vec3::new(
                0.0,
                quarter as f64 * std::f64::consts::FRAC_PI_2,
                0.0,
            ));
            // X ↦ c + R (X − c): a rotation about the normal through the centre.
            let q = Pose::new(rot, c - rot * c);
            let mut line_of = Vec::with_capacity(self.len());
            for s in &self.segments {
                let (a, b) = (q.apply(&s.from), q.apply(&s.to));
                let hit = self.segments.iter().position(|t| {
                    (t.from - a).norm() < tol && (t.to - b).norm() < tol
                        || (t.from - b).norm() < tol && (t.to - a).norm() < tol
                });
                match hit {
                    Some(k) => line_of.push(k),
                    None => break,
                }
            }
            if line_of.len() == self.len() {
                out.push(Symmetry {
                    degrees: 90 * quarter,
                    target_from_labelled: q,
                    line_of,
                });
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_l_has_no_symmetry_and_nine_crossings_including_its_corners() {
        let l = LineLayout::l_target(0.5, 0.2);
        assert_eq!(l.symmetries().len(), 1);
        let crossings = l.crossings();
        assert_eq!(crossings.len(), 9);
        let corners = super::super::line_target::LineTarget {
            length: 0.5,
            spacing: 0.2,
        }
        .corners();
        for c in corners {
            assert!(crossings.iter().any(|(_, _, p)| (p - c).norm() < 1e-15));
        }
    }

    #[test]
    fn grids_have_the_symmetries_of_their_counts() {
        let g32 = LineLayout::grid(0.5, 0.2, 3, 2, 0.012);
        let s = g32.symmetries();
        assert_eq!(s.iter().map(|s| s.degrees).collect::<Vec<_>>(), [0, 180]);
        // The half-turn reverses both groups' order.
        assert_eq!(s[1].line_of, [2, 1, 0, 4, 3]);
        let g33 = LineLayout::grid(0.5, 0.2, 3, 3, 0.012);
        assert_eq!(g33.symmetries().len(), 4);
        // Each symmetry maps the layout onto itself, segment by segment.
        for sym in g33.symmetries() {
            for (m, s) in g33.segments.iter().enumerate() {
                let t = g33.segments[sym.line_of[m]];
                let a = sym.target_from_labelled.apply(&s.from);
                let b = sym.target_from_labelled.apply(&s.to);
                let d = ((a - t.from).norm() + (b - t.to).norm())
                    .min((a - t.to).norm() + (b - t.from).norm());
                assert!(d < 1e-12, "{} {m}", sym.degrees);
            }
        }
        // An uneven explicit layout breaks the symmetry.
        let uneven = LineLayout::from_sheet_segments(
            &[
                [[-0.25, -0.2], [0.25, -0.2]],
                [[-0.25, 0.0], [0.25, 0.0]],
                [[-0.25, 0.25], [0.25, 0.25]],
                [[-0.1, -0.25], [-0.1, 0.25]],
                [[0.1, -0.25], [0.1, 0.25]],
            ],
            0.01,
        )
        .unwrap();
        assert_eq!(uneven.symmetries().len(), 1);
        // A mark off the centre leaves only the identity; one at the centre changes nothing.
        let marked = g33.clone().with_mark(0.1, 0.1, 0.03);
        assert_eq!(marked.symmetries().len(), 1);
        assert_eq!(marked.line_symmetries().len(), 4);
        assert_eq!(g33.with_mark(0.0, 0.0, 0.03).symmetries().len(), 4);
    }

    #[test]
    fn explicit_segments_must_run_along_an_axis() {
        let e = LineLayout::from_sheet_segments(&[[[0.0, 0.0], [0.1, 0.1]]], 0.01).unwrap_err();
        assert_eq!(e.0, 0);
        let e = LineLayout::from_sheet_segments(&[[[0.0, 0.0], [0.0, 0.0]]], 0.01).unwrap_err();
        assert_eq!(e.0, 0);
        let ok = LineLayout::from_sheet_segments(&[[[0.0, 0.0], [0.0, 0.3]]], 0.01).unwrap();
        assert_eq!(ok.segments[0].axis, Axis::Z);
        assert_eq!(ok.segments[0].to, Vec3::new(0.0, 0.0, 0.3));
    }
}
