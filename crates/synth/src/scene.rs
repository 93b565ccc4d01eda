//! Whole scenes for the renderer: planar surfaces (printed AprilGrids, single tags,
//! tiled floors and walls) placed in a world, and what one camera sees of them.
//!
//! Every surface is a plane with a rectangular extent and a paint made of regions of
//! constant grey, so [`super::render::render_field`] renders it exactly: the tag corners
//! are where the geometry puts them, whatever the clutter around them.

use super::render::Hit;
use rigcal_core::geometry::{Camera, Mat3, Pose, Vec2, Vec3};
use rigcal_core::target::board::{single_tag_shade, tag_corner, GridLayout};

/// What is printed or built on a surface, in surface coordinates (m).
#[derive(Clone, Debug)]
pub enum Paint {
    /// A Kalibr AprilGrid (board coordinates: origin at the bottom-left tag's corner).
    Grid {
        layout: GridLayout,
        black: f32,
        white: f32,
    },
    /// One tag of side `size` centred on the origin, with its white quiet zone.
    Tag {
        id: u32,
        size: f64,
        black: f32,
        white: f32,
    },
    /// Tiles or panels of `cell` (m) with dark joints `joint` wide; each tile its own
    /// grey in `grey`, some with a stain (a disc) or a sign (a rectangle) on them.
    Tiles {
        cell: [f64; 2],
        joint: f64,
        grey: (f32, f32),
        seed: u64,
    },
}

/// A painted rectangle `extent = [x0, y0, x1, y1]` of the plane `z = 0` of
/// `world_from_surface`.
#[derive(Clone, Debug)]
pub struct Surface {
    pub world_from_surface: Pose,
    pub extent: [f64; 4],
    pub paint: Paint,
}

/// Region ids within a surface; a surface's classes are `index << 32 | region`.
const BLACK: u32 = 1;
const WHITE: u32 = 2;

impl Paint {
    /// The region at surface point `(x, y)`: `None` where nothing is painted (a board's
    /// outline is not rectangular to the last millimetre).
    pub fn at(&self, x: f64, y: f64) -> Option<(u32, f32)> {
        let ink = |white: bool, b: f32, w: f32| {
            if white {
                (WHITE, w)
            } else {
                (BLACK, b)
            }
        };
        match *self {
            Paint::Grid {
                layout,
                black,
                white,
            } => layout.shade(x, y).map(|w| ink(w, black, white)),
            Paint::Tag {
                id,
                size,
                black,
                white,
            } => single_tag_shade(id, size, x, y).map(|w| ink(w, black, white)),
            Paint::Tiles {
                cell,
                joint,
                grey,
                seed,
            } => {
                let (i, j) = ((x / cell[0]).floor(), (y / cell[1]).floor());
                let (lx, ly) = (x - i * cell[0], y - j * cell[1]);
                if lx < joint || ly < joint {
                    return Some((BLACK, 0.45 * grey.0));
                }
                let h = hash3(seed, i as i64, j as i64);
                let u = |k: u32| ((h >> (8 * k)) & 0xff) as f64 / 255.0;
                let tile = (h as u32 | 4) & !3;
                let base = grey.0 + (grey.1 - grey.0) * u(0) as f32;
                // A stain: a disc of 10-30 % of the tile, darker.
                if u(1) < 0.3 {
                    let r = (0.1 + 0.2 * u(2)) * cell[0].min(cell[1]);
                    let c = Vec2::new(
                        joint + r + u(3) * (cell[0] - joint - 2.0 * r),
                        joint + r + u(4) * (cell[1] - joint - 2.0 * r),
                    );
                    if (Vec2::new(lx, ly) - c).norm() < r {
                        return Some((tile | 1, base * 0.6));
                    }
                }
                // A sign: a rectangle of any grey (the quad detector sees those too).
                if u(5) < 0.25 {
                    let (x0, y0) = (joint + 0.15 * cell[0], joint + 0.2 * cell[1]);
                    let (x1, y1) = (
                        x0 + (0.2 + 0.4 * u(6)) * cell[0],
                        y0 + (0.2 + 0.3 * u(7)) * cell[1],
                    );
                    if (x0..x1).contains(&lx) && (y0..y1).contains(&ly) {
                        return Some((tile | 2, 20.0 + 220.0 * u(2) as f32));
                    }
                }
                Some((tile, base))
            }
        }
    }
}

/// A 64-bit hash of a seed and two integers (splitmix64 rounds).
fn hash3(seed: u64, a: i64, b: i64) -> u64 {
    let mut z = seed
        ^ (a as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (b as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A surface as one camera sees it: the plane in the camera frame.
struct Placed {
    /// `surface_from_cam` rotation and the camera centre's negation in surface coordinates
    /// (a ray `d` meets the plane at `λ·Rᵀd − o`, `λ = o.z / (Rᵀd).z`).
    rt: Mat3,
    o: Vec3,
}

/// The scene from one camera: which surfaces can be met in each 32-px tile of the image.
pub struct View<'a> {
    surfaces: &'a [Surface],
    placed: Vec<Placed>,
    tiles: Vec<Vec<u32>>,
    cols: usize,
    rows: usize,
    /// Grey where no surface is met (above the walls).
    pub background: f32,
}

const TILE: usize = 32;

/// Samples per side of an extent when bounding a surface's image.
const OUTLINE_SAMPLES: usize = 48;

impl<'a> View<'a> {
    pub fn new(camera: &Camera, world_from_cam: &Pose, surfaces: &'a [Surface]) -> View<'a> {
        let cam_from_world = world_from_cam.inverse();
        let (cols, rows) = (
            (camera.width as usize).div_ceil(TILE),
            (camera.height as usize).div_ceil(TILE),
        );
        let mut tiles = vec![Vec::new(); cols * rows];
        let mut placed = Vec::with_capacity(surfaces.len());
        for (k, s) in surfaces.iter().enumerate() {
            let cam_from_surface = cam_from_world * s.world_from_surface;
            let rt = cam_from_surface.rot.transpose();
            placed.push(Placed {
                rt,
                o: rt * cam_from_surface.trans,
            });
            // The image of the outline bounds the image of the surface; where the outline
            // is behind the camera or beyond the lens the surface may be anywhere.
            let mut lo = Vec2::repeat(f64::INFINITY);
            let mut hi = Vec2::repeat(f64::NEG_INFINITY);
            let (mut front, mut anywhere) = (0, false);
            for p in outline(&s.extent) {
                let c = cam_from_surface.apply(&Vec3::new(p.x, p.y, 0.0));
                if c.z <= 1e-3 {
                    anywhere = true;
                    continue;
                }
                front += 1;
                match camera.project(&c) {
                    Some(uv) => {
                        lo = lo.inf(&uv);
                        hi = hi.sup(&uv);
                    }
                    None => anywhere = true,
                }
            }
            if front == 0 {
                continue; // wholly behind the camera
            }
            let margin = 4.0;
            let clamp = |x: f64, n: usize| ((x / TILE as f64).floor().max(0.0) as usize).min(n - 1);
            let (i0, i1, j0, j1) = if anywhere {
                (0, cols - 1, 0, rows - 1)
            } else {
                if hi.x < -margin
                    || hi.y < -margin
                    || lo.x > camera.width as f64 + margin
                    || lo.y > camera.height as f64 + margin
                {
                    continue;
                }
                (
                    clamp(lo.x - margin, cols),
                    clamp(hi.x + margin, cols),
                    clamp(lo.y - margin, rows),
                    clamp(hi.y + margin, rows),
                )
            };
            for j in j0..=j1 {
                for i in i0..=i1 {
                    tiles[j * cols + i].push(k as u32);
                }
            }
        }
        View {
            surfaces,
            placed,
            tiles,
            cols,
            rows,
            background: 35.0,
        }
    }

    /// The nearest painted surface along `ray` (camera frame) through image point `at`:
    /// its index, depth, and the region met there (id, grey).
    pub fn nearest(&self, at: Vec2, ray: Vec3) -> Option<(usize, f64, (u32, f32))> {
        let i = ((at.x.max(0.0) as usize) / TILE).min(self.cols - 1);
        let j = ((at.y.max(0.0) as usize) / TILE).min(self.rows - 1);
        let mut best: Option<(usize, f64, (u32, f32))> = None;
        for &k in &self.tiles[j * self.cols + i] {
            let (p, s) = (&self.placed[k as usize], &self.surfaces[k as usize]);
            let d = p.rt * ray;
            let lambda = p.o.z / d.z;
            if !(lambda.is_finite() && lambda > 0.0) || best.is_some_and(|b| b.1 <= lambda) {
                continue;
            }
            let q = d * lambda - p.o;
            let [x0, y0, x1, y1] = s.extent;
            if q.x < x0 || q.y < y0 || q.x > x1 || q.y > y1 {
                continue;
            }
            if let Some(region) = s.paint.at(q.x, q.y) {
                best = Some((k as usize, lambda, region));
            }
        }
        best
    }

    /// What the ray meets, for the renderer.
    pub fn hit(&self, at: Vec2, ray: Vec3) -> Hit {
        match self.nearest(at, ray) {
            Some((k, _, (region, grey))) => Hit {
                class: (k as u64) << 32 | region as u64,
                grey,
                exact: !matches!(self.surfaces[k].paint, Paint::Tiles { .. }),
            },
            None => Hit {
                class: u64::MAX,
                grey: self.background,
                exact: false,
            },
        }
    }
}

/// Points round an extent's outline.
fn outline(e: &[f64; 4]) -> impl Iterator<Item = Vec2> + '_ {
    let [x0, y0, x1, y1] = *e;
    (0..4 * OUTLINE_SAMPLES).map(move |k| {
        let (side, t) = (
            k / OUTLINE_SAMPLES,
            (k % OUTLINE_SAMPLES) as f64 / OUTLINE_SAMPLES as f64,
        );
        match side {
            0 => Vec2::new(x0 + t * (x1 - x0), y0),
            1 => Vec2::new(x1, y0 + t * (y1 - y0)),
            2 => Vec2::new(x1 - t * (x1 - x0), y1),
            _ => Vec2::new(x0, y1 - t * (y1 - y0)),
        }
    })
}

/// A tag printed on a surface: where its corners are, in world coordinates.
#[derive(Clone, Debug)]
pub struct PrintedTag {
    pub id: u32,
    pub surface: usize,
    /// Corner `k` (counter-clockwise from the tag's bottom-left), surface coordinates.
    pub corners: [Vec2; 4],
}

/// Every tag printed on `surfaces`, with its corners in surface coordinates.
pub fn printed_tags(surfaces: &[Surface]) -> Vec<PrintedTag> {
    let mut out = Vec::new();
    for (k, s) in surfaces.iter().enumerate() {
        match &s.paint {
            Paint::Grid { layout, .. } => {
                for id in layout.ids() {
                    let corners = [0, 1, 2, 3].map(|c| layout.corner(id, c).unwrap_or_default());
                    out.push(PrintedTag {
                        id,
                        surface: k,
                        corners,
                    });
                }
            }
            Paint::Tag { id, size, .. } => {
                let h = Vec2::new(size / 2.0, size / 2.0);
                out.push(PrintedTag {
                    id: *id,
                    surface: k,
                    corners: [0, 1, 2, 3].map(|c| tag_corner(*size, c) - h),
                });
            }
            Paint::Tiles { .. } => {}
        }
    }
    out
}

/// Where a printed tag's corners land in the image, if the tag is fully visible: every
/// corner in front of the camera, `margin` px inside the image, and the tag's own surface
/// the nearest thing along the rays to its corners and centre (nothing in front of it).
pub fn visible_corners(
    camera: &Camera,
    world_from_cam: &Pose,
    view: &View,
    surfaces: &[Surface],
    tag: &PrintedTag,
    margin: f64,
) -> Option<[Vec2; 4]> {
    let cam_from_surface = world_from_cam.inverse() * surfaces[tag.surface].world_from_surface;
    let centre = tag.corners.iter().sum::<Vec2>() / 4.0;
    // Corners are tested a hair inside the tag, so the ray meets its surface's print.
    let probes = tag.corners.map(|c| c + (centre - c) * 1e-3);
    let mut uv = [Vec2::zeros(); 4];
    for (k, p) in probes.iter().chain(std::iter::once(&centre)).enumerate() {
        let c = cam_from_surface.apply(&Vec3::new(p.x, p.y, 0.0));
        if c.z <= 0.0 {
            return None;
        }
        let px = camera.project(&c)?;
        let (_, depth, _) = view.nearest(px, c / c.z)?;
        if (depth - c.z).abs() > 1e-6 * c.z.max(1.0) {
            return None;
        }
        if k < 4 {
            let corner =
                cam_from_surface.apply(&Vec3::new(tag.corners[k].x, tag.corners[k].y, 0.0));
            uv[k] = camera.project(&corner)?;
            let inside = uv[k].x >= margin
                && uv[k].y >= margin
                && uv[k].x <= camera.width as f64 - 1.0 - margin
                && uv[k].y <= camera.height as f64 - 1.0 - margin;
            if !inside {
                return None;
            }
        }
    }
    Some(uv)
}
