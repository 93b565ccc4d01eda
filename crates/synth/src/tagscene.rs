//! Rendered views of AprilTags and Kalibr AprilGrids with their true corners, for the
//! detector's accuracy tests, `rigcal bench detect` and the peers script.

use super::render::{project_board, render, RenderOptions};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rigcal_core::geometry::{so3, Camera, CameraModel, Pose, Vec2, Vec3};
use rigcal_core::session::TargetSpec;
use rigcal_core::target::board::{single_tag_shade, tag_corner, GridLayout};
use std::collections::BTreeMap;

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Lens {
    Pinhole,
    Radtan,
    Equidistant,
}

impl Lens {
    pub fn parse(s: &str) -> Option<Lens> {
        match s {
            "pinhole" => Some(Lens::Pinhole),
            "radtan" => Some(Lens::Radtan),
            "equidistant" => Some(Lens::Equidistant),
            _ => None,
        }
    }

    /// A camera of this kind: f ≈ 0.8 × width; realistic, clearly visible distortion.
    pub fn camera(self, width: u32, height: u32) -> Camera {
        let f = 0.8 * width as f64;
        let mut c = Camera::pinhole(
            f,
            f,
            width as f64 / 2.0 - 0.3,
            height as f64 / 2.0 + 0.7,
            width,
            height,
        );
        c.model = match self {
            Lens::Pinhole => CameraModel::Pinhole,
            Lens::Radtan => CameraModel::Radtan {
                k1: -0.28,
                k2: 0.08,
                p1: 8e-4,
                p2: -5e-4,
                k3: 0.0,
            },
            Lens::Equidistant => CameraModel::Equidistant {
                k1: 0.05,
                k2: -0.01,
                k3: 0.004,
                k4: -0.001,
            },
        };
        c
    }
}

#[derive(Clone, Debug)]
pub struct SceneParams {
    /// `true`: a 6×6 Kalibr AprilGrid (spacing 0.3); `false`: one tag.
    pub grid: bool,
    /// Tag side in pixels when seen head-on at the image centre.
    pub tag_px: f64,
    /// Angle (deg) between the board normal and the viewing direction.
    pub obliquity_deg: f64,
    pub lens: Lens,
    pub width: u32,
    pub height: u32,
    pub render: RenderOptions,
    pub seed: u64,
}

pub struct TagScene {
    pub camera: Camera,
    pub targets: Vec<TargetSpec>,
    pub image: image::GrayImage,
    /// Tags entirely inside the image: id → true corners (raw pixels).
    pub truth: BTreeMap<u32, [Vec2; 4]>,
}

/// Tag side (m) used by the scenes; only ratios matter.
const TAG_SIZE: f64 = 0.1;

pub fn scene(p: &SceneParams) -> TagScene {
    let mut rng = ChaCha8Rng::seed_from_u64(p.seed);
    let camera = p.lens.camera(p.width, p.height);
    let depth = camera.fx * TAG_SIZE / p.tag_px;
    let first_id = rng.gen_range(0..500);
    let layout = GridLayout {
        rows: 6,
        cols: 6,
        tag_size: TAG_SIZE,
        spacing: 0.3,
        first_id: first_id.min(587 - 36),
    };
    let single_id = first_id;
    // Print centre and its shade function in board coordinates.
    let (centre, targets): (Vec2, Vec<TargetSpec>) = if p.grid {
        let side = layout.cols as f64 * layout.pitch() - layout.gap();
        (
            Vec2::new(side / 2.0, side / 2.0),
            vec![TargetSpec::Aprilgrid {
                id: "board".into(),
                rows: layout.rows,
                cols: layout.cols,
                tag_size: layout.tag_size,
                tag_spacing: layout.spacing,
                first_id: layout.first_id,
            }],
        )
    } else {
        (
            Vec2::zeros(),
            vec![TargetSpec::Apriltags {
                id: "tags".into(),
                tag_size: TAG_SIZE,
                ids: None,
            }],
        )
    };
    // Facing the camera (board y up = image up), turned in-plane, tilted about a random
    // in-plane axis.
    let facing = nalgebra::Matrix3::from_diagonal(&Vec3::new(1.0, -1.0, -1.0));
    let spin = so3::exp(&Vec3::new(0.0, 0.0, rng.gen_range(-3.1..3.1)));
    let axis_angle: f64 = rng.gen_range(0.0..std::f64::consts::TAU);
    let tilt = so3::exp(
        &(Vec3::new(axis_angle.cos(), axis_angle.sin(), 0.0) * p.obliquity_deg.to_radians()),
    );
    let rot = facing * spin * tilt;
    // Centre the print near the optical axis, shifted a little at random.
    let reach = if p.grid { 0.1 } else { 0.3 };
    let off = Vec3::new(
        rng.gen_range(-reach..reach) * p.width as f64 / camera.fx,
        rng.gen_range(-reach..reach) * p.height as f64 / camera.fy,
        1.0,
    );
    let at = off * depth;
    let pose = Pose::new(rot, at - rot * Vec3::new(centre.x, centre.y, 0.0));
    let mut opts = p.render.clone();
    opts.seed = p.seed ^ 0x5eed;
    let image = if p.grid {
        render(&camera, &pose, &|x, y| layout.shade(x, y), &opts)
    } else {
        render(
            &camera,
            &pose,
            &|x, y| single_tag_shade(single_id, TAG_SIZE, x, y),
            &opts,
        )
    };
    let mut truth = BTreeMap::new();
    let ids: Vec<u32> = if p.grid {
        layout.ids().collect()
    } else {
        vec![single_id]
    };
    let h = TAG_SIZE / 2.0;
    for id in ids {
        let mut corners = [Vec2::zeros(); 4];
        let mut inside = true;
        for (k, c) in corners.iter_mut().enumerate() {
            let b = if p.grid {
                layout.corner(id, k).unwrap_or_default()
            } else {
                tag_corner(TAG_SIZE, k) - Vec2::new(h, h)
            };
            match project_board(&camera, &pose, b) {
                Some(uv) if uv.x > 3.0 && uv.y > 3.0 => {
                    inside &= uv.x < p.width as f64 - 4.0 && uv.y < p.height as f64 - 4.0;
                    *c = uv;
                }
                _ => inside = false,
            }
        }
        if inside {
            truth.insert(id, corners);
        }
    }
    TagScene {
        camera,
        targets,
        image,
        truth,
    }
}
