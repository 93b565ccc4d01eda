//! Realistic captures (`rigcal synth --preset car-hall --images`): a rig driven through
//! a calibration hall, rendered as users' cameras deliver it.
//!
//! The hall has a tiled floor and panelled walls with stains and signs on them, eight
//! AprilGrids of mixed tag sizes on stands around the car (two per camera direction,
//! some cut by the image border as the car moves) and AprilTags of two sizes scattered
//! on the walls. Each image is rendered exactly (the tag corners are known to ~1e-3 px)
//! and then degraded as a camera does: optics blur, vignetting, per-image gain and
//! offset, sensor noise, JPEG. The truth of every fully visible tag's corners is kept
//! per image, for the detection tables.

use super::render::{quantise, render_field};
use super::scene::{printed_tags, visible_corners, Paint, PrintedTag, Surface, View};
use super::{camera_spec, look, planar_pose, Truth};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use rigcal_core::geometry::{so3, Camera, CameraModel, Mat3, Pose, Vec3};
use rigcal_core::session::{FrameSpec, ObservationSpec, SessionManifest, TargetSpec};
use rigcal_core::target::board::GridLayout;
use serde::Serialize;
use std::collections::BTreeMap;

/// The realistic presets: a car in a hall with a U-turn and a speed bump (general
/// motion), the same hall driven in a planar S-curve, that drive with every target seen
/// by one camera only (boards only), and a hand-held pair of fisheyes.
pub const PRESETS: &[&str] = &[
    "car-hall",
    "car-hall-planar",
    "car-hall-isolated",
    "fisheye-handheld",
];

/// How the images are degraded (the defaults are those of the vehicle captures).
#[derive(Clone, Debug)]
pub struct Nuisance {
    /// Optics blur σ (px).
    pub blur: f64,
    /// Sensor noise σ (grey levels).
    pub noise: f64,
    /// Light lost at the image corners (fraction; quadratic in the radius).
    pub vignetting: f64,
    /// Per-image gain drawn in `1 ± gain` and offset in `± offset` grey levels.
    pub gain: f64,
    pub offset: f64,
    /// JPEG quality (1-100); `None` writes PNG.
    pub jpeg_quality: Option<u8>,
    /// Fine cells per side of an edge pixel (the renderer's accuracy/cost trade).
    pub edge_cells: usize,
    /// A colour camera's white balance: the rendered level scaled per channel (R, G, B)
    /// and written as a colour image, as vehicle cameras deliver theirs; `None` writes
    /// grey. The render itself is grey (the prints are black and white).
    pub colour: Option<[f64; 3]>,
}

/// A colour camera's white balance a little off neutral: reds low, blues high, as
/// under the cold light of a hall.
pub const HALL_WHITE_BALANCE: [f64; 3] = [0.88, 1.0, 1.07];

impl Default for Nuisance {
    fn default() -> Self {
        Self {
            blur: 0.5,
            noise: 1.0,
            vignetting: 0.25,
            gain: 0.15,
            offset: 8.0,
            jpeg_quality: Some(92),
            edge_cells: 12,
            colour: None,
        }
    }
}

/// A hall scenario: the rig, its drive, the surfaces and the session's targets.
#[derive(Clone, Debug)]
pub struct Hall {
    pub preset: String,
    pub motion: &'static str,
    /// Camera id, camera, `vehicle_from_cam`.
    pub cameras: Vec<(String, Camera, Pose)>,
    pub world_from_vehicle: Vec<Pose>,
    pub surfaces: Vec<Surface>,
    pub targets: Vec<TargetSpec>,
    tags: Vec<PrintedTag>,
}

/// The true corners of one image's fully visible tags.
#[derive(Clone, Debug, Serialize)]
pub struct ImageTruth {
    pub camera: String,
    pub frame: usize,
    pub path: String,
    /// Point id (`tag:<id>:<k>`) → raw pixel.
    pub corners: BTreeMap<String, [f64; 2]>,
}

/// A capture: the session, its truth and each image's true corners.
pub struct Capture {
    pub manifest: SessionManifest,
    pub truth: Truth,
    pub images: Vec<ImageTruth>,
}

/// Corners this close to the image border (px) do not count as fully visible.
const VISIBLE_MARGIN: f64 = 4.0;

/// A tag whose shortest side in the image is under this (px, 1.5 px per cell of its 8)
/// is in view but not legible, by any detector: it does not count as visible.
pub const LEGIBLE_SIDE_PX: f64 = 12.0;

/// Build a preset's hall; `size` overrides the image size (intrinsics scale with it).
/// Errors name the argument at fault (`--preset`, `--size`) or the board that found no
/// place.
pub fn hall(preset: &str, seed: u64, size: Option<(u32, u32)>) -> Result<Hall, String> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x4a11);
    let handheld = preset == "fisheye-handheld";
    let (w, h) = size.unwrap_or(if handheld { (1024, 768) } else { (1920, 1080) });
    if !(64..=8192).contains(&w) || !(64..=8192).contains(&h) {
        return Err(format!("--size: 64x64 to 8192x8192, got {w}x{h}"));
    }
    let radtan = |rng: &mut ChaCha8Rng| {
        let mut c = lens_camera(w, h, 0.55, rng);
        c.model = CameraModel::Radtan {
            k1: -0.22 + rng.gen_range(-0.02..0.02),
            k2: 0.05,
            p1: 6e-4,
            p2: -4e-4,
            k3: 0.0,
        };
        c
    };
    let fisheye = |rng: &mut ChaCha8Rng| {
        let mut c = lens_camera(w, h, 0.42, rng);
        c.model = CameraModel::Equidistant {
            k1: 0.04,
            k2: -0.008,
            k3: 0.002,
            k4: -0.0005,
        };
        c
    };
    // Vehicle frame: x forward, y left, z up, on the floor. The car's mounts are
    // symmetric about x = 0.5 so a U-turn there swaps front↔rear and left↔right.
    let cameras: Vec<(String, Camera, Pose)> = if handheld {
        vec![
            (
                "a".into(),
                fisheye(&mut rng),
                Pose::new(look(Vec3::x(), 0.1), Vec3::new(0.0, 0.0, 1.4)),
            ),
            (
                "b".into(),
                fisheye(&mut rng),
                Pose::new(
                    look(Vec3::new(0.2, 1.0, 0.0), 0.15),
                    Vec3::new(0.05, 0.12, 1.38),
                ),
            ),
        ]
    } else {
        let mounts = [
            ("front", Vec3::new(2.0, 0.0, 1.3), Vec3::x(), 0.14, false),
            ("rear", Vec3::new(-1.0, 0.05, 1.0), -Vec3::x(), 0.12, false),
            ("left", Vec3::new(0.5, 0.9, 1.1), Vec3::y(), 0.3, true),
            ("right", Vec3::new(0.5, -0.9, 1.15), -Vec3::y(), 0.28, true),
        ];
        mounts
            .iter()
            .map(|(n, p, d, pitch, fish)| {
                let cam = if *fish {
                    fisheye(&mut rng)
                } else {
                    radtan(&mut rng)
                };
                (n.to_string(), cam, Pose::new(look(*d, *pitch), *p))
            })
            .collect()
    };
    let (motion, world_from_vehicle) = match preset {
        "car-hall" => ("general", uturn_and_bump(&mut rng)),
        "car-hall-planar" | "car-hall-isolated" => ("planar", s_curve(14, &mut rng)),
        "fisheye-handheld" => ("general", handheld_motion(12, &mut rng)),
        _ => {
            return Err(format!(
                "--preset: one of {}, got {preset:?}",
                PRESETS.join(", ")
            ))
        }
    };
    let (hx, hy) = if handheld { (4.5, 3.5) } else { (11.0, 7.0) };
    let mut surfaces = room(hx, hy, seed);
    let mut targets = Vec::new();
    // Boards: two per camera direction (three for the hand-held pair), in front of it at
    // the first pose, facing it give or take 20°.
    let per_camera = if handheld { 3 } else { 2 };
    let mut first_id = 0;
    for (ci, (name, cam, v_from_c)) in cameras.iter().enumerate() {
        for b in 0..per_camera {
            let tag_size = if handheld {
                rng.gen_range(0.05..0.09)
            } else {
                rng.gen_range(0.12..0.25)
            };
            let layout = GridLayout {
                rows: 6,
                cols: 6,
                tag_size,
                spacing: 0.3,
                first_id,
            };
            first_id += layout.tag_count();
            let id = format!("board-{name}-{b}");
            let fish = matches!(cam.model, CameraModel::Equidistant { .. });
            let isolated = preset == "car-hall-isolated";
            // Re-drawn until the board is inside the hall and, for the isolated preset,
            // no other camera sees any of its tags at any pose.
            let mut placed = None;
            for attempt in 0..400 {
                // Pulled towards the optical axis the longer no place is found.
                let spread = 1.0 - attempt as f64 / 500.0;
                let s = board_surface(
                    &layout,
                    v_from_c,
                    (b, per_camera),
                    fish,
                    handheld,
                    spread,
                    &mut rng,
                );
                let c = s.world_from_surface.trans;
                if c.x.abs() > hx - 0.5 || c.y.abs() > hy - 0.5 {
                    continue;
                }
                if isolated {
                    let trial: Vec<Surface> = surfaces
                        .iter()
                        .cloned()
                        .chain(std::iter::once(s.clone()))
                        .collect();
                    let k = trial.len() - 1;
                    let tags: Vec<PrintedTag> = printed_tags(&trial)
                        .into_iter()
                        .filter(|t| t.surface == k)
                        .collect();
                    let seen_by_other = cameras.iter().enumerate().any(|(cj, (_, cam_j, vj))| {
                        cj != ci
                            && world_from_vehicle.iter().any(|wv| {
                                let wc = *wv * *vj;
                                let view = View::new(cam_j, &wc, &trial);
                                tags.iter()
                                    .any(|t| partly_visible(cam_j, &wc, &view, &trial, t))
                            })
                    });
                    if seen_by_other {
                        continue;
                    }
                }
                placed = Some(s);
                break;
            }
            let s = placed.ok_or_else(|| {
                format!("--seed {seed}: board {id} found no place that only camera {name} sees; try another seed")
            })?;
            surfaces.push(s);
            targets.push(TargetSpec::Aprilgrid {
                id,
                rows: layout.rows,
                cols: layout.cols,
                tag_size: layout.tag_size,
                tag_spacing: layout.spacing,
                first_id: layout.first_id,
            });
        }
    }
    if preset != "car-hall-isolated" && !handheld {
        wall_tags(
            &mut surfaces,
            &mut targets,
            first_id.max(300),
            hx,
            hy,
            &mut rng,
        );
    }
    let tags = printed_tags(&surfaces);
    Ok(Hall {
        preset: preset.into(),
        motion,
        cameras,
        world_from_vehicle,
        surfaces,
        targets,
        tags,
    })
}

/// A camera of `w × h` with focal length `f_rel · w` and a principal point a little off
/// centre.
fn lens_camera(w: u32, h: u32, f_rel: f64, rng: &mut ChaCha8Rng) -> Camera {
    let f = f_rel * w as f64 * rng.gen_range(0.98..1.02);
    Camera::pinhole(
        f,
        f * rng.gen_range(0.998..1.002),
        w as f64 / 2.0 - 0.5 + rng.gen_range(-8.0..8.0),
        h as f64 / 2.0 - 0.5 + rng.gen_range(-6.0..6.0),
        w,
        h,
    )
}

/// The floor (tiles) and four walls (panels), 5 m high, round `[-hx, hx] × [-hy, hy]`.
fn room(hx: f64, hy: f64, seed: u64) -> Vec<Surface> {
    let floor = Surface {
        world_from_surface: Pose::identity(),
        extent: [-hx, -hy, hx, hy],
        paint: Paint::Tiles {
            cell: [0.6, 0.6],
            joint: 0.012,
            grey: (105.0, 175.0),
            seed: seed ^ 0xf100,
        },
    };
    let height = 5.0;
    // Wall k: surface x along the wall (to the right as seen from inside), y up; the
    // plane through `at`.
    let wall = |k: u64, along: Vec3, at: Vec3, half: f64| Surface {
        world_from_surface: Pose::new(
            Mat3::from_columns(&[along, Vec3::z(), along.cross(&Vec3::z())]),
            at,
        ),
        extent: [-half, 0.0, half, height],
        paint: Paint::Tiles {
            cell: [1.2, 0.9],
            joint: 0.02,
            grey: (120.0, 195.0),
            seed: seed ^ (0xa110 + k),
        },
    };
    vec![
        floor,
        wall(0, -Vec3::y(), Vec3::new(hx, 0.0, 0.0), hy),
        wall(1, Vec3::y(), Vec3::new(-hx, 0.0, 0.0), hy),
        wall(2, Vec3::x(), Vec3::new(0.0, hy, 0.0), hx),
        wall(3, -Vec3::x(), Vec3::new(0.0, -hy, 0.0), hx),
    ]
}

/// A board on a stand in front of camera `vehicle_from_cam` (vehicle = world at the first
/// pose): the `b`-th of `n`, spread across the view (`spread` of the default width),
/// facing the camera ±20°.
fn board_surface(
    layout: &GridLayout,
    vehicle_from_cam: &Pose,
    (b, n): (usize, usize),
    fish: bool,
    handheld: bool,
    spread: f64,
    rng: &mut ChaCha8Rng,
) -> Surface {
    let side = layout.cols as f64 * layout.pitch() - layout.gap();
    let optical = vehicle_from_cam.rot * Vec3::z();
    let ahead = Vec3::new(optical.x, optical.y, 0.0).normalize();
    let spread = spread * if fish { 42.0 } else { 24.0 };
    let slot = if n == 1 {
        0.0
    } else {
        -1.0 + 2.0 * b as f64 / (n - 1) as f64
    };
    let yaw = (slot * spread + rng.gen_range(-8.0..8.0)).to_radians();
    let dir = so3::exp(&(Vec3::z() * yaw)) * ahead;
    let distance = if handheld {
        rng.gen_range(1.2..2.4)
    } else {
        rng.gen_range(2.5..5.0)
    };
    let cam = vehicle_from_cam.trans;
    let centre_h = rng.gen_range((side / 2.0 + 0.05).max(0.5)..(side / 2.0 + 0.9).max(1.9));
    let centre = Vec3::new(cam.x, cam.y, 0.0) + dir * distance + Vec3::z() * centre_h;
    // Facing the camera: board z towards it, x to the right as the camera sees it, then
    // turned about the vertical and tilted back a little.
    let to_cam = Vec3::new(cam.x - centre.x, cam.y - centre.y, 0.0).normalize();
    let right = Vec3::z().cross(&to_cam);
    let facing = Mat3::from_columns(&[right, Vec3::z(), right.cross(&Vec3::z())]);
    let turn = so3::exp(&(Vec3::z() * rng.gen_range(-20f64..20.0).to_radians()))
        * so3::exp(&(right * rng.gen_range(-10f64..10.0).to_radians()));
    let rot = turn * facing;
    let m = 2.0 * layout.gap() + 0.002;
    Surface {
        world_from_surface: Pose::new(rot, centre - rot * Vec3::new(side / 2.0, side / 2.0, 0.0)),
        extent: [-m, -m, side + m, side + m],
        paint: Paint::Grid {
            layout: *layout,
            black: rng.gen_range(22.0..38.0),
            white: rng.gen_range(200.0..225.0),
        },
    }
}

/// AprilTags of two sizes (0.16 and 0.24 m) scattered on the walls, 2 mm proud of them,
/// as two `apriltags` targets.
fn wall_tags(
    surfaces: &mut Vec<Surface>,
    targets: &mut Vec<TargetSpec>,
    first_id: u32,
    hx: f64,
    hy: f64,
    rng: &mut ChaCha8Rng,
) {
    let count = rng.gen_range(24..=40);
    let sizes = [0.16, 0.24];
    let mut ids: [Vec<u32>; 2] = [Vec::new(), Vec::new()];
    let mut placed: Vec<(usize, f64, f64)> = Vec::new();
    let mut id = first_id;
    while placed.len() < count && id < 587 {
        let wall = 1 + rng.gen_range(0..4usize);
        let half = if wall <= 2 { hy } else { hx };
        let (x, y) = (
            rng.gen_range(-half + 0.5..half - 0.5),
            rng.gen_range(0.4..2.8),
        );
        if placed
            .iter()
            .any(|&(w, px, py)| w == wall && (px - x).hypot(py - y) < 0.6)
        {
            continue;
        }
        placed.push((wall, x, y));
        let k = placed.len() % 2;
        let size = sizes[k];
        let w = &surfaces[wall].world_from_surface;
        let normal_in = -(w.rot * Vec3::z()) * w.trans.dot(&(w.rot * Vec3::z())).signum();
        let at = w.apply(&Vec3::new(x, y, 0.0)) + normal_in * 0.002;
        let m = size * 0.75;
        surfaces.push(Surface {
            world_from_surface: Pose::new(w.rot, at),
            extent: [-m, -m, m, m],
            paint: Paint::Tag {
                id,
                size,
                black: rng.gen_range(22.0..38.0),
                white: rng.gen_range(200.0..225.0),
            },
        });
        ids[k].push(id);
        id += 1;
    }
    for (k, size) in sizes.iter().enumerate() {
        targets.push(TargetSpec::Apriltags {
            id: format!("wall-tags-{}", (size * 100.0).round()),
            tag_size: *size,
            ids: Some(ids[k].clone()),
        });
    }
}

/// Any corner of the tag in view (for the isolated preset's check).
fn partly_visible(
    cam: &Camera,
    w_from_c: &Pose,
    view: &View,
    surfaces: &[Surface],
    t: &PrintedTag,
) -> bool {
    let c_from_s = w_from_c.inverse() * surfaces[t.surface].world_from_surface;
    t.corners.iter().any(|p| {
        let c = c_from_s.apply(&Vec3::new(p.x, p.y, 0.0));
        c.z > 0.0
            && cam.project(&c).is_some_and(|uv| {
                cam.in_image(&uv)
                    && view
                        .nearest(uv, c / c.z)
                        .is_some_and(|(k, _, _)| k == t.surface)
            })
    })
}

/// The car turned about its centre (x = 0.5) by `yaw_deg`, after `p`.
pub(crate) fn about_centre(p: &Pose, yaw_deg: f64) -> Pose {
    let c = Vec3::new(0.5, 0.0, 0.0);
    let r = so3::exp(&Vec3::new(0.0, 0.0, yaw_deg.to_radians()));
    Pose::new(r, c - r * c) * *p
}

/// 9 poses manoeuvring on the spot, one over a speed bump, 8 after a U-turn.
fn uturn_and_bump(rng: &mut ChaCha8Rng) -> Vec<Pose> {
    let local = |n: usize, rng: &mut ChaCha8Rng| -> Vec<Pose> {
        (0..n)
            .map(|_| {
                planar_pose(
                    rng.gen_range(-0.8..0.8),
                    rng.gen_range(-0.4..0.4),
                    rng.gen_range(-12.0..12.0),
                )
            })
            .collect()
    };
    let mut poses = vec![Pose::identity()];
    poses.extend(local(8, rng));
    poses.push(Pose::new(
        so3::exp(&Vec3::new(
            2f64.to_radians(),
            -3f64.to_radians(),
            4f64.to_radians(),
        )),
        Vec3::new(0.4, 0.1, 0.08),
    ));
    poses.extend(local(8, rng).iter().map(|p| about_centre(p, 180.0)));
    poses
}

/// An S-curve: forward 2.4 m, weaving ±0.35 m, yaw within ±7°, flat floor.
fn s_curve(n: usize, rng: &mut ChaCha8Rng) -> Vec<Pose> {
    (0..n)
        .map(|k| {
            let s = k as f64 / (n - 1) as f64;
            let phase = s * std::f64::consts::TAU;
            planar_pose(
                -1.2 + 2.4 * s + rng.gen_range(-0.05..0.05),
                0.35 * phase.sin(),
                6.5 * phase.cos() * (1.0 - 0.1 * rng.gen::<f64>()),
            )
        })
        .enumerate()
        .map(|(k, p)| if k == 0 { Pose::identity() } else { p })
        .collect()
}

/// A hand-held rig waved about: rotations of 6-15° about random axes, 0.3 m moves.
fn handheld_motion(n: usize, rng: &mut ChaCha8Rng) -> Vec<Pose> {
    let mut poses = vec![Pose::identity()];
    while poses.len() < n {
        let axis = Vec3::new(
            rng.gen_range(-1.0..1.0),
            rng.gen_range(-1.0..1.0),
            rng.gen_range(-1.0..1.0),
        );
        if axis.norm() < 0.2 {
            continue;
        }
        let angle = rng.gen_range(6.0f64..15.0).to_radians();
        let t = Vec3::new(
            rng.gen_range(-0.3..0.3),
            rng.gen_range(-0.3..0.3),
            rng.gen_range(-0.2..0.2),
        );
        // About the rig's own position (1.4 m up), not the floor's origin.
        let r = so3::exp(&(axis.normalize() * angle));
        let pivot = Vec3::new(0.0, 0.0, 1.4);
        poses.push(Pose::new(r, pivot - r * pivot + t));
    }
    poses
}

/// Image path of a camera's frame in a rendered capture.
pub fn image_path(camera: &str, frame: usize, jpeg: bool) -> String {
    format!(
        "images/{camera}/{frame:04}.{}",
        if jpeg { "jpg" } else { "png" }
    )
}

impl Hall {
    /// The same hall with the scattered wall tags taken down (AprilGrids only, as a peer
    /// toolbox that knows only boards is given).
    pub fn boards_only(mut self) -> Hall {
        self.surfaces
            .retain(|s| !matches!(s.paint, Paint::Tag { .. }));
        self.targets
            .retain(|t| matches!(t, TargetSpec::Aprilgrid { .. }));
        self.tags = printed_tags(&self.surfaces);
        self
    }

    pub fn world_from_cam(&self, frame: usize, cam: usize) -> Pose {
        self.world_from_vehicle[frame] * self.cameras[cam].2
    }

    /// The true corners of the fully visible tags in one image: in the image, nothing in
    /// front, and legible ([`LEGIBLE_SIDE_PX`]).
    pub fn visible(&self, frame: usize, cam: usize) -> BTreeMap<String, [f64; 2]> {
        let (_, camera, _) = &self.cameras[cam];
        let wc = self.world_from_cam(frame, cam);
        let view = View::new(camera, &wc, &self.surfaces);
        let mut out = BTreeMap::new();
        for t in &self.tags {
            if let Some(uv) = visible_corners(camera, &wc, &view, &self.surfaces, t, VISIBLE_MARGIN)
                .filter(|uv| (0..4).all(|k| (uv[k] - uv[(k + 1) % 4]).norm() >= LEGIBLE_SIDE_PX))
            {
                for (k, p) in uv.iter().enumerate() {
                    out.insert(format!("tag:{}:{k}", t.id), [p.x, p.y]);
                }
            }
        }
        out
    }

    /// One image, rendered and degraded; the nuisances are drawn from `seed`.
    pub fn render(
        &self,
        frame: usize,
        cam: usize,
        nuisance: &Nuisance,
        seed: u64,
    ) -> image::GrayImage {
        let (_, camera, _) = &self.cameras[cam];
        let wc = self.world_from_cam(frame, cam);
        let view = View::new(camera, &wc, &self.surfaces);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let jitter = rng.gen::<u64>();
        let value = render_field(
            camera,
            &|at, ray| view.hit(at, ray),
            nuisance.blur,
            nuisance.edge_cells,
            jitter,
        );
        degrade(camera, &value, nuisance, &mut rng)
    }

    /// The session of images (paths as [`image_path`]), with its truth and per-image
    /// corner truth.
    pub fn image_capture(&self, jpeg: bool) -> Capture {
        self.capture(jpeg, |frame, _, id| {
            let mut f = frame_spec(frame);
            f.images.insert(id.to_string(), image_path(id, frame, jpeg));
            f
        })
    }

    /// The same capture as detections: every fully visible tag's true corners plus
    /// Gaussian noise of `noise_px`, drawn from `seed`.
    pub fn detection_capture(&self, noise_px: f64, seed: u64) -> Option<Capture> {
        let px = Normal::new(0.0, noise_px).ok()?;
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xde7);
        let visible: Vec<Vec<BTreeMap<String, [f64; 2]>>> = (0..self.world_from_vehicle.len())
            .map(|f| {
                (0..self.cameras.len())
                    .map(|c| self.visible(f, c))
                    .collect()
            })
            .collect();
        Some(self.capture(false, |frame, cam, _| {
            let mut f = frame_spec(frame);
            let obs: Vec<ObservationSpec> = visible[frame][cam]
                .iter()
                .map(|(point, uv)| ObservationSpec {
                    point: point.clone(),
                    u: uv[0] + px.sample(&mut rng),
                    v: uv[1] + px.sample(&mut rng),
                })
                .collect();
            if !obs.is_empty() {
                f.observations.insert(self.cameras[cam].0.clone(), obs);
            }
            f
        }))
    }

    fn capture(
        &self,
        jpeg: bool,
        mut image: impl FnMut(usize, usize, &str) -> FrameSpec,
    ) -> Capture {
        let mut frames = Vec::new();
        let mut images = Vec::new();
        for frame in 0..self.world_from_vehicle.len() {
            let mut spec = frame_spec(frame);
            for (ci, (id, _, _)) in self.cameras.iter().enumerate() {
                let one = image(frame, ci, id);
                spec.images.extend(one.images);
                spec.observations.extend(one.observations);
                images.push(ImageTruth {
                    camera: id.clone(),
                    frame,
                    path: image_path(id, frame, jpeg),
                    corners: self.visible(frame, ci),
                });
            }
            frames.push(spec);
        }
        let reference = self.cameras[0].0.clone();
        let ref_from_vehicle = self.cameras[0].2.inverse();
        let manifest = SessionManifest {
            version: 1,
            vehicle_id: Some(format!("synth-{}", self.preset)),
            vehicle_model: None,
            method: Default::default(),
            reference_camera: reference.clone(),
            cameras: self
                .cameras
                .iter()
                .map(|(n, c, _)| camera_spec(n, c))
                .collect(),
            targets: self.targets.clone(),
            scale: vec![],
            frames,
            priors: None,
            auxiliary_camera: None,
            ring: vec![],
        };
        let points = self
            .tags
            .iter()
            .flat_map(|t| {
                let ws = self.surfaces[t.surface].world_from_surface;
                t.corners.iter().enumerate().map(move |(k, c)| {
                    let p = ws.apply(&Vec3::new(c.x, c.y, 0.0));
                    (format!("tag:{}:{k}", t.id), [p.x, p.y, p.z])
                })
            })
            .collect();
        let truth = Truth {
            preset: self.preset.clone(),
            reference_camera: reference,
            ref_from_cam: self
                .cameras
                .iter()
                .map(|(n, _, v_from_c)| (n.clone(), ref_from_vehicle * *v_from_c))
                .collect(),
            world_from_rig: self
                .world_from_vehicle
                .iter()
                .map(|w| *w * self.cameras[0].2)
                .collect(),
            motion: self.motion.to_string(),
            points,
        };
        Capture {
            manifest,
            truth,
            images,
        }
    }

    /// Encode one rendered image as the capture stores it.
    pub fn encode(img: &image::GrayImage, nuisance: &Nuisance) -> image::ImageResult<Vec<u8>> {
        match nuisance.colour {
            Some(balance) => {
                let rgb = image::RgbImage::from_fn(img.width(), img.height(), |x, y| {
                    let v = f64::from(img.get_pixel(x, y)[0]);
                    image::Rgb(balance.map(|c| (v * c).round().clamp(0.0, 255.0) as u8))
                });
                encode_as(
                    rgb.as_raw(),
                    rgb.dimensions(),
                    image::ExtendedColorType::Rgb8,
                    nuisance.jpeg_quality,
                )
            }
            None => encode_as(
                img.as_raw(),
                img.dimensions(),
                image::ExtendedColorType::L8,
                nuisance.jpeg_quality,
            ),
        }
    }
}

/// Pixels `px` (`w × h`, 8-bit channels of `colour`) as a JPEG of quality
/// `jpeg_quality`, or a PNG.
fn encode_as(
    px: &[u8],
    (w, h): (u32, u32),
    colour: image::ExtendedColorType,
    jpeg_quality: Option<u8>,
) -> image::ImageResult<Vec<u8>> {
    let mut out = std::io::Cursor::new(Vec::new());
    match jpeg_quality {
        Some(q) => image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, q.clamp(1, 100))
            .encode(px, w, h, colour)?,
        None => {
            image::write_buffer_with_format(&mut out, px, w, h, colour, image::ImageFormat::Png)?
        }
    }
    Ok(out.into_inner())
}

/// What the camera does to the rendered grey levels: a per-image gain and offset drawn
/// from `rng`, vignetting, sensor noise, 8 bits.
pub(crate) fn degrade(
    camera: &Camera,
    value: &[f64],
    nuisance: &Nuisance,
    rng: &mut ChaCha8Rng,
) -> image::GrayImage {
    let gain = 1.0 + rng.gen_range(-1.0..=1.0) * nuisance.gain;
    let offset = rng.gen_range(-1.0..=1.0) * nuisance.offset;
    let w = camera.width as usize;
    let (cx, cy) = (camera.cx, camera.cy);
    let corner = (cx.max(camera.width as f64 - cx)).hypot(cy.max(camera.height as f64 - cy));
    let vig = nuisance.vignetting;
    quantise(
        camera,
        value,
        |k, x| {
            let (u, v) = ((k % w) as f64, (k / w) as f64);
            let r2 = ((u - cx).powi(2) + (v - cy).powi(2)) / (corner * corner);
            gain * x * (1.0 - vig * r2) + offset
        },
        nuisance.noise,
        rng,
    )
}

/// An empty frame.
fn frame_spec(index: usize) -> FrameSpec {
    FrameSpec {
        index: index as i64,
        timestamp: Some(index as f64 * 0.5),
        images: BTreeMap::new(),
        observations: BTreeMap::new(),
        lines: BTreeMap::new(),
        line_targets: BTreeMap::new(),
    }
}

/// What [`write_capture`] wrote.
pub struct Written {
    pub images: usize,
    pub visible_tags: usize,
}

/// Write a capture of `hall` into `dir`: `session.json`, `truth.json`, `corners.json`
/// (every image's fully visible tag corners) and, when `nuisance` is given, the rendered
/// images; otherwise the session holds the true corners plus `noise_px` Gaussian noise.
pub fn write_capture(
    hall: &Hall,
    dir: &std::path::Path,
    nuisance: Option<&Nuisance>,
    noise_px: f64,
    seed: u64,
) -> anyhow::Result<Written> {
    use anyhow::Context;
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let capture = match nuisance {
        Some(n) => hall.image_capture(n.jpeg_quality.is_some()),
        None => hall
            .detection_capture(noise_px, seed)
            .context("--noise: a non-negative pixel σ")?,
    };
    let write = |name: &str, bytes: &[u8]| {
        let path = dir.join(name);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent)
                .with_context(|| format!("cannot create {}", parent.display()))?;
        }
        std::fs::write(&path, bytes).with_context(|| format!("cannot write {}", path.display()))
    };
    let mut images = 0;
    if let Some(n) = nuisance {
        for frame in 0..hall.world_from_vehicle.len() {
            for cam in 0..hall.cameras.len() {
                let img_seed = seed
                    .wrapping_mul(7919)
                    .wrapping_add((frame * 64 + cam) as u64);
                let img = hall.render(frame, cam, n, img_seed);
                let bytes = Hall::encode(&img, n).context("cannot encode a rendered image")?;
                write(
                    &image_path(&hall.cameras[cam].0, frame, n.jpeg_quality.is_some()),
                    &bytes,
                )?;
                images += 1;
            }
        }
    }
    write(
        "session.json",
        &serde_json::to_vec_pretty(&capture.manifest)?,
    )?;
    write("truth.json", &serde_json::to_vec_pretty(&capture.truth)?)?;
    write("corners.json", &serde_json::to_vec(&capture.images)?)?;
    Ok(Written {
        images,
        visible_tags: capture.images.iter().map(|i| i.corners.len() / 4).sum(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A colour camera's image is the grey render through its white balance, channel by
    /// channel (clipped at white); a grey one is the render as it is.
    #[test]
    fn colour_images_carry_the_render_through_the_white_balance() {
        let grey = image::GrayImage::from_fn(16, 8, |x, y| image::Luma([(x * 16 + y) as u8]));
        let lossless = |colour| Nuisance {
            colour,
            jpeg_quality: None,
            ..Nuisance::default()
        };
        let png = Hall::encode(&grey, &lossless(Some([0.5, 1.0, 2.0]))).unwrap();
        let rgb = image::load_from_memory(&png).unwrap();
        let image::DynamicImage::ImageRgb8(rgb) = rgb else {
            panic!("not an 8-bit RGB image: {:?}", rgb.color());
        };
        for (g, p) in grey.pixels().zip(rgb.pixels()) {
            let v = f64::from(g[0]);
            let want = [(v * 0.5).round(), v, (v * 2.0).min(255.0)].map(|c| c as u8);
            assert_eq!(p.0, want, "grey {v}");
        }
        let png = Hall::encode(&grey, &lossless(None)).unwrap();
        assert_eq!(
            image::load_from_memory(&png).unwrap(),
            image::DynamicImage::ImageLuma8(grey)
        );
    }
}
