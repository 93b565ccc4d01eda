//! Synthetic vanishing-method sessions: the ring of Wu et al. §5.1 (Table 2), eight
//! cameras 150 mm above the ground looking outwards, each with a line target on the
//! ground in front of it, and an auxiliary camera photographing each neighbouring pair
//! from 40° above the ground (the best pitch of their §4.1).
//!
//! Frames (the paper's ECF): `y` down, the ground is `y = 0`; camera `k` sits at Table 2's
//! `(x, y, z)` with yaw about `y` (0° looks along `+z`, 90° along `+x`). As in the paper,
//! every feature line is sampled with one point per pixel of its image length and each
//! point gets Gaussian noise of `noise_px` on both coordinates.

use super::{camera_spec, Truth};
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use rigcal_core::geometry::line2::{bisector, distance, through};
use rigcal_core::geometry::{so3, Camera, Pose, Vec2, Vec3};
use rigcal_core::session::{FrameSpec, LineSpec, MarkSpec, RingSpec, SessionManifest, TargetSpec};
use rigcal_core::target::line_layout::{Axis, LineLayout, Print};
use rigcal_core::target::line_target::{LineTarget, LINES};
use std::collections::BTreeMap;

/// Table 2: camera positions (mm) and yaw (deg); pitch and roll are 0.
pub const TABLE2: [(f64, f64, f64, f64); 8] = [
    (100.0, -150.0, 0.0, 28.0),
    (600.0, -150.0, -400.0, 64.0),
    (600.0, -150.0, -500.0, 125.0),
    (200.0, -150.0, -1000.0, 158.0),
    (-200.0, -150.0, -1000.0, 202.0),
    (-600.0, -150.0, -500.0, 235.0),
    (-600.0, -150.0, -400.0, 296.0),
    (-100.0, -150.0, 0.0, 332.0),
];
/// Wu §5.1: L1 = 500 mm, L2 = 200 mm.
pub const TARGET: LineTarget = LineTarget {
    length: 0.5,
    spacing: 0.2,
};
/// The print on each target of the ring: Wu's filled L or a grid of thin lines of the
/// same L1 and L2 (`lines_x` × `lines_y`, stroke in metres), with or without an
/// orientation mark ([`MARK`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RingPrint {
    FilledL,
    Grid {
        lines_x: usize,
        lines_y: usize,
        stroke: f64,
        marked: bool,
    },
}

/// The orientation mark of a marked grid: sheet `(x, y, radius)` (m), a 60 mm disc in
/// the middle of a cell of the 3 × 3 grid (lines at 0 and ±L2).
pub const MARK: [f64; 3] = [0.1, 0.1, 0.03];

impl RingPrint {
    /// The "#" most people print: 3 × 3 lines, 12 mm strokes.
    pub const GRID: RingPrint = RingPrint::Grid {
        lines_x: 3,
        lines_y: 3,
        stroke: 0.012,
        marked: false,
    };
    /// The same with a printed orientation mark, which removes the symmetry.
    pub const GRID_MARKED: RingPrint = RingPrint::Grid {
        lines_x: 3,
        lines_y: 3,
        stroke: 0.012,
        marked: true,
    };

    pub fn layout(&self) -> LineLayout {
        match *self {
            RingPrint::FilledL => LineLayout::l_target(TARGET.length, TARGET.spacing),
            RingPrint::Grid {
                lines_x,
                lines_y,
                stroke,
                marked,
            } => {
                let g = LineLayout::grid(TARGET.length, TARGET.spacing, lines_x, lines_y, stroke);
                if marked {
                    g.with_mark(MARK[0], MARK[1], MARK[2])
                } else {
                    g
                }
            }
        }
    }

    pub fn spec(&self, id: &str) -> TargetSpec {
        match *self {
            RingPrint::FilledL => TargetSpec::LineTarget {
                id: id.into(),
                length: TARGET.length,
                spacing: TARGET.spacing,
            },
            RingPrint::Grid {
                lines_x,
                lines_y,
                stroke,
                marked,
            } => TargetSpec::LineGrid {
                id: id.into(),
                length: TARGET.length,
                spacing: TARGET.spacing,
                lines_x: lines_x as u32,
                lines_y: lines_y as u32,
                stroke,
                mark: marked.then_some(MarkSpec {
                    x: MARK[0],
                    y: MARK[1],
                    radius: MARK[2],
                }),
            },
        }
    }

    /// Where this print's frame sits in the L's frame, which [`ring_scene`] places: a
    /// grid is centred where the L's centre is, its axes the L's.
    pub fn l_from_target(&self) -> Pose {
        match self {
            RingPrint::FilledL => Pose::identity(),
            RingPrint::Grid { .. } => {
                let c = TARGET.corners().iter().sum::<Vec3>() / LINES as f64;
                Pose::new(nalgebra::Matrix3::identity(), c)
            }
        }
    }
}

/// Where the targets and the auxiliary camera stand: the paper gives neither (Table 2
/// has the cameras only), so these are the factors of a placement study
/// (`rigcal bench ring --target-distance --aux-distance --aux-pitch`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RingLayout {
    /// Ground distance from a camera to its target's nearest corner (m).
    pub target_distance: f64,
    /// The auxiliary camera's pitch below the horizon (deg; Wu §4.1's best is 40°).
    pub aux_pitch_deg: f64,
    /// The auxiliary camera's distance to the midpoint of the pair it photographs (m).
    pub aux_distance: f64,
    /// Auxiliary images per pair: the first at `aux_pitch_deg`, the others steeper and
    /// shallower by [`AUX_VIEW_PITCH_STEP_DEG`], 2×, … .
    pub aux_views: usize,
}

/// Pitch step (deg) between the auxiliary views of one pair when there are several. A
/// pitch step, not a turn about the pair: turning the camera by 8-20° laid one line
/// group of some targets within 1° of the image plane (vanishing point at infinity).
pub const AUX_VIEW_PITCH_STEP_DEG: f64 = 8.0;

impl Default for RingLayout {
    fn default() -> Self {
        Self {
            target_distance: 0.35,
            aux_pitch_deg: 40.0,
            aux_distance: 1.0,
            aux_views: 1,
        }
    }
}

pub fn rig_camera() -> Camera {
    Camera::pinhole(796.44, 796.44, 512.0, 384.0, 1024, 768)
}

pub fn aux_camera() -> Camera {
    Camera::pinhole(512.0, 512.0, 512.0, 384.0, 1024, 768)
}

/// A camera at `position` looking along `forward` (unit), its `x` axis horizontal.
fn looking(position: Vec3, forward: Vec3) -> Pose {
    let z = forward.normalize();
    let x = Vec3::y().cross(&z).normalize();
    let y = z.cross(&x);
    Pose::new(nalgebra::Matrix3::from_columns(&[x, y, z]), position)
}

/// The scene in the ECF: `ecf_from_cam` per rig camera, `ecf_from_target` per target,
/// `ecf_from_aux[v·8 + k]` for view `v` of neighbouring pair `(k, k+1 mod 8)` (see
/// [`RingScene::pair_of`]).
pub struct RingScene {
    pub ecf_from_cam: Vec<Pose>,
    pub ecf_from_target: Vec<Pose>,
    pub ecf_from_aux: Vec<Pose>,
}

impl RingScene {
    /// The pair `(k, k+1 mod 8)` auxiliary view `i` photographs.
    pub fn pair_of(&self, i: usize) -> (usize, usize) {
        let k = i % 8;
        (k, (k + 1) % 8)
    }
}

/// Table 2's ring in the default [`RingLayout`].
pub fn table2_scene() -> RingScene {
    ring_scene(&RingLayout::default())
}

/// Table 2's cameras with targets and auxiliary views placed by `layout`.
pub fn ring_scene(layout: &RingLayout) -> RingScene {
    let ecf_from_cam: Vec<Pose> = TABLE2
        .iter()
        .map(|&(x, y, z, yaw)| {
            Pose::new(
                so3::exp(&Vec3::new(0.0, yaw.to_radians(), 0.0)),
                Vec3::new(x, y, z) * 1e-3,
            )
        })
        .collect();
    let ecf_from_target: Vec<Pose> = ecf_from_cam
        .iter()
        .map(|c| {
            // Diagonal (the symmetry axis) pointing back at the camera, P1 nearest.
            let ahead = Vec3::new(c.rot[(0, 2)], 0.0, c.rot[(2, 2)]).normalize();
            let p1 = Vec3::new(c.trans.x, 0.0, c.trans.z) + ahead * layout.target_distance;
            let quarter = |a: f64| so3::exp(&Vec3::new(0.0, a.to_radians(), 0.0)) * ahead;
            let (x, z) = (quarter(45.0), quarter(-45.0));
            let y = z.cross(&x);
            Pose::new(nalgebra::Matrix3::from_columns(&[x, y, z]), p1)
        })
        .collect();
    let centre: Vec3 = ecf_from_cam.iter().map(|c| c.trans).sum::<Vec3>() / 8.0;
    let target_centre = |t: &Pose| {
        let c = TARGET.corners();
        t.apply(&(c.iter().sum::<Vec3>() / LINES as f64))
    };
    let ecf_from_aux = (0..8 * layout.aux_views.max(1))
        .map(|i| {
            let (k, v) = (i % 8, i / 8);
            let mid = (target_centre(&ecf_from_target[k])
                + target_centre(&ecf_from_target[(k + 1) % 8]))
                / 2.0;
            // View v: 0, +1, −1, +2, −2, … pitch steps.
            let step = v.div_ceil(2) as f64 * if v % 2 == 1 { 1.0 } else { -1.0 };
            let out = Vec3::new(mid.x - centre.x, 0.0, mid.z - centre.z).normalize();
            let p = (layout.aux_pitch_deg + AUX_VIEW_PITCH_STEP_DEG * step).to_radians();
            let forward = -out * p.cos() + Vec3::y() * p.sin();
            looking(mid - forward * layout.aux_distance, forward)
        })
        .collect();
    RingScene {
        ecf_from_cam,
        ecf_from_target,
        ecf_from_aux,
    }
}

/// Points along every feature line of `target` as `camera` at `cam_from_target` sees them
/// (a stroke's: the centre of its image band): one per pixel of image length, noisy,
/// those outside the image (8 px margin) dropped.
pub fn sample_lines(
    camera: &Camera,
    cam_from_target: &Pose,
    target: &LineLayout,
    target_id: &str,
    noise_px: f64,
    rng: &mut impl Rng,
) -> Vec<LineSpec> {
    let normal = Normal::new(0.0, noise_px.max(1e-300)).expect("finite σ");
    let margin = 8.0;
    (0..target.len())
        .map(|m| {
            let (a, b) = target.segment(m);
            let proj = |x: Vec3| camera.project(&cam_from_target.apply(&x));
            let n = match (proj(a), proj(b)) {
                (Some(pa), Some(pb)) => ((pa - pb).norm().round() as usize).max(2),
                _ => 0,
            };
            let points = (0..n)
                .filter_map(|i| {
                    let s = (i as f64 + 0.5) / n as f64;
                    // A stroke is seen as the band between its edges' images: its centre
                    // line (what a ridge detector measures, and the bundle models).
                    let x = a + (b - a) * s;
                    let p = match (target.print, target.segments[m].axis) {
                        (Print::Outline, _) => proj(x)?,
                        (Print::Strokes { width }, axis) => {
                            let n = match axis {
                                Axis::X => Vec3::z(),
                                Axis::Z => Vec3::x(),
                            } * (width / 2.0);
                            // In the ideal image the band is a wedge: its centre is the
                            // bisector of the edges' images, here at the foot of the
                            // midpoint across the stroke.
                            let ideal = |x: Vec3| {
                                let q = cam_from_target.apply(&x);
                                (q.z > 0.0).then(|| Vec2::new(q.x / q.z, q.y / q.z))
                            };
                            let edge = |o: Vec3| through(&ideal(a + o)?, &ideal(b + o)?);
                            let centre = bisector(&edge(n)?, &edge(-n)?)?;
                            let m = (ideal(x + n)? + ideal(x - n)?) / 2.0;
                            let foot = m - centre.xy() * distance(&centre, &m);
                            camera.project(&Vec3::new(foot.x, foot.y, 1.0))?
                        }
                    };
                    let p = if noise_px > 0.0 {
                        p + Vec2::new(normal.sample(rng), normal.sample(rng))
                    } else {
                        p
                    };
                    let inside = p.x >= margin
                        && p.y >= margin
                        && p.x <= camera.width as f64 - 1.0 - margin
                        && p.y <= camera.height as f64 - 1.0 - margin;
                    inside.then_some([p.x, p.y])
                })
                .collect();
            LineSpec {
                target: target_id.into(),
                line: m as u8 + 1,
                points,
            }
        })
        .collect()
}

/// White paper around each print (m).
pub const PRINT_MARGIN: f64 = 0.05;

/// The print of `layout` in target coordinates `(x, z)`: `Some(true)` on white paper,
/// `Some(false)` on ink (the L filled, a grid's strokes), `None` off the sheet.
fn print_shade(layout: &LineLayout) -> impl Fn(f64, f64) -> Option<bool> + Sync {
    let half_stroke = match layout.print {
        Print::Strokes { width } => width / 2.0,
        Print::Outline => 0.0,
    };
    let (mut lo, mut hi) = (Vec2::repeat(f64::INFINITY), Vec2::repeat(f64::NEG_INFINITY));
    for s in &layout.segments {
        for p in [s.from, s.to] {
            lo = lo.inf(&Vec2::new(p.x, p.z));
            hi = hi.sup(&Vec2::new(p.x, p.z));
        }
    }
    let mark = layout
        .mark
        .map(|m| (Vec2::new(m.centre.x, m.centre.z), m.radius));
    if let Some((c, r)) = mark {
        lo = lo.inf(&(c - Vec2::repeat(r)));
        hi = hi.sup(&(c + Vec2::repeat(r)));
    }
    let pad = Vec2::repeat(PRINT_MARGIN + half_stroke);
    let (lo, hi) = (lo - pad, hi + pad);
    // The L's L1 (its x extent, l6) and L2 (its arm width, where l3 runs).
    let filled_l = (layout.print == Print::Outline)
        .then(|| (layout.segments[5].from.x, layout.segments[2].from.x));
    let boxes: Vec<[f64; 4]> = layout
        .segments
        .iter()
        .map(|s| {
            let (a, b) = (s.from, s.to);
            [
                a.x.min(b.x) - half_stroke,
                a.x.max(b.x) + half_stroke,
                a.z.min(b.z) - half_stroke,
                a.z.max(b.z) + half_stroke,
            ]
        })
        .collect();
    move |x: f64, z: f64| {
        let ink = match filled_l {
            Some((l1, l2)) => {
                (0.0..=l1).contains(&x) && (0.0..=l2).contains(&z)
                    || (0.0..=l2).contains(&x) && (0.0..=l1).contains(&z)
            }
            None => boxes
                .iter()
                .any(|b| (b[0]..=b[1]).contains(&x) && (b[2]..=b[3]).contains(&z)),
        } || mark.is_some_and(|(c, r)| (Vec2::new(x, z) - c).norm() <= r);
        if ink {
            Some(false)
        } else {
            ((lo.x..=hi.x).contains(&x) && (lo.y..=hi.y).contains(&z)).then_some(true)
        }
    }
}

/// Board (x, y, 0) of the renderer = target (x, 0, y): a proper rotation.
fn target_from_board() -> Pose {
    Pose::new(
        nalgebra::Matrix3::from_columns(&[Vec3::x(), Vec3::z(), -Vec3::y()]),
        Vec3::zeros(),
    )
}

/// Render line targets as `camera` sees them: each print on a white sheet on a grey
/// ground, clean (blur and noise of `opts` only). The targets must share one plane (the
/// ring's lie on the ground); `cam_from_targets[0]`'s plane is rendered.
pub fn render_line_targets(
    camera: &Camera,
    cam_from_targets: &[Pose],
    target: &LineLayout,
    opts: &crate::render::RenderOptions,
) -> image::GrayImage {
    let value = line_target_values(camera, cam_from_targets, target, opts);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(opts.seed);
    crate::render::quantise(camera, &value, |_, x| x, opts.noise_sigma, &mut rng)
}

/// [`render_line_targets`]' grey levels before the sensor, row-major.
fn line_target_values(
    camera: &Camera,
    cam_from_targets: &[Pose],
    target: &LineLayout,
    opts: &crate::render::RenderOptions,
) -> Vec<f64> {
    let first = cam_from_targets[0];
    let others: Vec<Pose> = cam_from_targets
        .iter()
        .map(|t| t.inverse() * first)
        .collect();
    let print = print_shade(target);
    let shade = move |bx: f64, by: f64| -> Option<bool> {
        let mut on_sheet = false;
        for t in &others {
            let p = t.apply(&Vec3::new(bx, 0.0, by));
            match print(p.x, p.z) {
                Some(false) => return Some(false),
                Some(true) => on_sheet = true,
                None => {}
            }
        }
        on_sheet.then_some(true)
    };
    crate::render::render_values(camera, &(first * target_from_board()), &shade, opts)
}

/// Render line targets as a real capture shows them: a textured floor (tiles of 3 cm in
/// random greys, a darker grout), the prints, optics blur, per-image gain and offset,
/// vignetting and sensor noise of `nuisance` (JPEG is the encoder's: [`Hall::encode`]).
///
/// [`Hall::encode`]: crate::hall::Hall::encode
pub fn render_line_targets_real(
    camera: &Camera,
    cam_from_targets: &[Pose],
    target: &LineLayout,
    nuisance: &crate::hall::Nuisance,
    seed: u64,
) -> image::GrayImage {
    use crate::render::{render_field, Hit};
    let first = cam_from_targets[0];
    let board_to_cam = first * target_from_board();
    let others: Vec<Pose> = cam_from_targets
        .iter()
        .map(|t| t.inverse() * first)
        .collect();
    let print = print_shade(target);
    let rt = board_to_cam.rot.transpose();
    let o = rt * board_to_cam.trans;
    let (white, black) = (225.0f32, 30.0f32);
    let field = |_: Vec2, ray: Vec3| -> Hit {
        let d = rt * ray;
        let lambda = o.z / d.z;
        if !(lambda.is_finite() && lambda > 0.0) {
            return Hit {
                class: 0,
                grey: 90.0,
                exact: false,
            };
        }
        let p = d * lambda - o;
        for t in &others {
            let q = t.apply(&Vec3::new(p.x, 0.0, p.y));
            match print(q.x, q.z) {
                Some(false) => {
                    return Hit {
                        class: 1,
                        grey: black,
                        exact: true,
                    }
                }
                Some(true) => {
                    return Hit {
                        class: 2,
                        grey: white,
                        exact: true,
                    }
                }
                None => {}
            }
        }
        // The floor: 3 cm tiles of random grey with 4 mm grout.
        let (tx, ty) = ((p.x / 0.03).floor(), (p.y / 0.03).floor());
        let (fx, fy) = (p.x / 0.03 - tx, p.y / 0.03 - ty);
        if fx < 0.13 || fy < 0.13 {
            return Hit {
                class: 3,
                grey: 70.0,
                exact: false,
            };
        }
        let h = (tx as i64).wrapping_mul(73_856_093) ^ (ty as i64).wrapping_mul(19_349_663);
        let h = (h as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 40;
        Hit {
            class: 4 + (h & 0xFFFF),
            grey: 100.0 + (h % 60) as f32,
            exact: false,
        }
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let jitter = rng.gen::<u64>();
    let value = render_field(camera, &field, nuisance.blur, nuisance.edge_cells, jitter);
    crate::hall::degrade(camera, &value, nuisance, &mut rng)
}

/// How a ring is rendered as images: the print on its targets and, for realistic
/// captures, the nuisances (textured floor, photometry, JPEG); `None` renders clean PNGs.
#[derive(Clone, Debug)]
pub struct RingImages {
    pub print: RingPrint,
    pub nuisance: Option<crate::hall::Nuisance>,
}

impl Default for RingImages {
    fn default() -> Self {
        Self {
            print: RingPrint::FilledL,
            nuisance: None,
        }
    }
}

/// The ring as a session of images: `scene`'s 8 rig images (`rig/camK.png`, with
/// `frames[0].line_targets`) and 8 auxiliary images (`aux/K.png`, each pair named left
/// to right as the auxiliary camera sees it), rendered with grey-level noise
/// `noise_grey`; no line points. Returns the manifest, the truth and the PNG files by
/// path.
pub fn image_session(
    rig: &Camera,
    aux: &Camera,
    scene: &RingScene,
    noise_grey: f64,
    seed: u64,
) -> (SessionManifest, Truth, BTreeMap<String, Vec<u8>>) {
    image_session_with(rig, aux, scene, &RingImages::default(), noise_grey, seed)
}

/// Fine cells per side of an edge pixel in a noise-free render: the jittered edge
/// sampling is then the render's only error, and at the default 16 it was most of what
/// the noise-free Table 2 ring of line grids measured (camera errors up to 0.00167°;
/// 0.00116° at 32 cells, 0.00084° at 48, 0.00062° at 64, at 2.2× the render time per
/// step of 16).
const EXACT_EDGE_CELLS: usize = 48;

/// [`image_session`] with another print and, optionally, a realistic capture's nuisances
/// (then `noise_grey` replaces the nuisance's sensor noise and the files are JPEG).
pub fn image_session_with(
    rig: &Camera,
    aux: &Camera,
    scene: &RingScene,
    look: &RingImages,
    noise_grey: f64,
    seed: u64,
) -> (SessionManifest, Truth, BTreeMap<String, Vec<u8>>) {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let (mut m, truth) = generate_print(&mut rng, [0.0; 2], rig, aux, scene, look.print);
    let layout = look.print.layout();
    let placed = look.print.l_from_target();
    let exact = noise_grey == 0.0 && look.nuisance.is_none();
    let opts = |k: u64| crate::render::RenderOptions {
        noise_sigma: noise_grey,
        seed: seed.wrapping_mul(1000).wrapping_add(k),
        edge_cells: if exact {
            EXACT_EDGE_CELLS
        } else {
            crate::render::EDGE_SUPERSAMPLE
        },
        ..Default::default()
    };
    let ext = if look.nuisance.is_some() {
        "jpg"
    } else {
        "png"
    };
    let render = |camera: &Camera, poses: &[Pose], k: u64| -> Vec<u8> {
        match &look.nuisance {
            Some(n) => {
                let n = crate::hall::Nuisance {
                    noise: noise_grey,
                    ..n.clone()
                };
                let img = render_line_targets_real(camera, poses, &layout, &n, opts(k).seed);
                crate::hall::Hall::encode(&img, &n).unwrap_or_default()
            }
            // Noise-free, the render is written at 16 bits and its edges sampled
            // finely (EXACT_EDGE_CELLS): what is measured then is the detector's own
            // error, not the 8-bit rounding's nor the edge sampling's.
            None if exact => {
                let value = line_target_values(camera, poses, &layout, &opts(k));
                png(&crate::render::exact_16bit(camera, &value))
            }
            None => png(&render_line_targets(camera, poses, &layout, &opts(k))),
        }
    };
    let mut files = BTreeMap::new();
    let frame = &mut m.frames[0];
    frame.lines.clear();
    for k in 0..8 {
        let cam_from_target = scene.ecf_from_cam[k].inverse() * scene.ecf_from_target[k] * placed;
        let path = format!("rig/cam{}.{ext}", k + 1);
        files.insert(path.clone(), render(rig, &[cam_from_target], k as u64));
        frame.images.insert(format!("cam{}", k + 1), path);
    }
    let centre = layout.centre();
    for (i, r) in m.ring.iter_mut().enumerate() {
        let (k, j) = scene.pair_of(i);
        let poses =
            [k, j].map(|t| scene.ecf_from_aux[i].inverse() * scene.ecf_from_target[t] * placed);
        let u = |p: &Pose| aux.project(&p.apply(&centre)).map_or(0.0, |q| q.x);
        let (a, b) = (format!("t{}", k + 1), format!("t{}", j + 1));
        r.targets = if u(&poses[0]) <= u(&poses[1]) {
            vec![a, b]
        } else {
            vec![b, a]
        };
        let path = format!("aux/{i}.{ext}");
        files.insert(path.clone(), render(aux, &poses, 100 + i as u64));
        r.lines.clear();
        r.image = Some(path);
    }
    (m, truth, files)
}

/// A PNG file of `img`; empty if the encoder fails (it does not on an image in memory).
fn png<P: image::PixelWithColorType>(img: &image::ImageBuffer<P, Vec<P::Subpixel>>) -> Vec<u8>
where
    [P::Subpixel]: image::EncodableLayout,
{
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png)
        .map(|_| out.into_inner())
        .unwrap_or_default()
}

/// The `wu-table2` session and its truth.
pub fn generate(rng: &mut impl Rng, noise_px: f64) -> (SessionManifest, Truth) {
    generate_with(rng, noise_px, &rig_camera(), &aux_camera(), &table2_scene())
}

/// A ring session of `scene` seen through the given rig and auxiliary cameras (any model:
/// line points are sampled through the distortion, as a lens images them).
pub fn generate_with(
    rng: &mut impl Rng,
    noise_px: f64,
    rig: &Camera,
    aux: &Camera,
    scene: &RingScene,
) -> (SessionManifest, Truth) {
    generate_split(rng, [noise_px, noise_px], rig, aux, scene)
}

/// [`generate_with`] with separate noise on the rig images and on the auxiliary images
/// (`[rig, aux]`, px), to see which of the two limits the result.
pub fn generate_split(
    rng: &mut impl Rng,
    noise: [f64; 2],
    rig: &Camera,
    aux: &Camera,
    scene: &RingScene,
) -> (SessionManifest, Truth) {
    generate_print(rng, noise, rig, aux, scene, RingPrint::FilledL)
}

/// [`generate_split`] with targets of another print (line points on its layout).
pub fn generate_print(
    rng: &mut impl Rng,
    [rig_noise, aux_noise]: [f64; 2],
    rig: &Camera,
    aux: &Camera,
    scene: &RingScene,
    print: RingPrint,
) -> (SessionManifest, Truth) {
    let layout = print.layout();
    let placed = print.l_from_target();
    let cam_ids: Vec<String> = (1..=8).map(|k| format!("cam{k}")).collect();
    let target_ids: Vec<String> = (1..=8).map(|k| format!("t{k}")).collect();
    let mut lines = BTreeMap::new();
    for k in 0..8 {
        let cam_from_target = scene.ecf_from_cam[k].inverse() * scene.ecf_from_target[k] * placed;
        lines.insert(
            cam_ids[k].clone(),
            sample_lines(
                rig,
                &cam_from_target,
                &layout,
                &target_ids[k],
                rig_noise,
                rng,
            ),
        );
    }
    let ring = (0..scene.ecf_from_aux.len())
        .map(|i| {
            let (k, j) = scene.pair_of(i);
            let mut l = Vec::new();
            for t in [k, j] {
                let aux_from_target =
                    scene.ecf_from_aux[i].inverse() * scene.ecf_from_target[t] * placed;
                l.extend(sample_lines(
                    aux,
                    &aux_from_target,
                    &layout,
                    &target_ids[t],
                    aux_noise,
                    rng,
                ));
            }
            RingSpec {
                index: i as i64,
                targets: vec![target_ids[k].clone(), target_ids[j].clone()],
                image: None,
                lines: l,
            }
        })
        .collect();
    let manifest = SessionManifest {
        version: 1,
        vehicle_id: Some("synth-wu-table2".into()),
        vehicle_model: None,
        method: rigcal_core::session::Method::Vanishing,
        reference_camera: cam_ids[0].clone(),
        cameras: cam_ids.iter().map(|id| camera_spec(id, rig)).collect(),
        targets: target_ids.iter().map(|id| print.spec(id)).collect(),
        scale: vec![],
        frames: vec![FrameSpec {
            index: 0,
            timestamp: None,
            images: BTreeMap::new(),
            observations: BTreeMap::new(),
            lines,
            line_targets: (0..8)
                .map(|k| (cam_ids[k].clone(), target_ids[k].clone()))
                .collect(),
        }],
        priors: None,
        auxiliary_camera: Some(camera_spec("aux", aux)),
        ring,
    };
    let ref_from_ecf = scene.ecf_from_cam[0].inverse();
    let truth = Truth {
        preset: "wu-table2".into(),
        reference_camera: cam_ids[0].clone(),
        ref_from_cam: cam_ids
            .iter()
            .zip(&scene.ecf_from_cam)
            .map(|(id, p)| (id.clone(), ref_from_ecf * *p))
            .collect(),
        world_from_rig: vec![scene.ecf_from_cam[0]],
        motion: "static".into(),
        points: target_ids
            .iter()
            .zip(&scene.ecf_from_target)
            .flat_map(|(id, t)| {
                let t = *t * placed;
                layout
                    .crossings()
                    .into_iter()
                    .enumerate()
                    .map(move |(m, (_, _, c))| {
                        let p = t.apply(&c);
                        (format!("line:{id}:{}", m + 1), [p.x, p.y, p.z])
                    })
            })
            .collect(),
    };
    (manifest, truth)
}
