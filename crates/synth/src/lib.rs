//! Synthetic capture sessions with known truth, for tests, benchmarks and the README.
//!
//! A scenario is a rig (cameras mounted on a vehicle), a vehicle trajectory and static
//! scenes of points; rendering projects every visible point with Gaussian pixel noise
//! and measures a few distances per scene with 0.5 mm noise (Lébraly §5.1).

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use rigcal_core::geometry::{so3, Camera, Pose, Vec2, Vec3};
use rigcal_core::session::{
    CameraSpec, FrameSpec, Intrinsics, ObservationSpec, ScaleSpec, SessionManifest,
};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

pub const PRESETS: &[&str] = &[
    "lebraly-5.1",
    "car-planar-uturn",
    "car-planar",
    "car-planar-loop",
    "car-bump",
    "pure-translation",
    "single-axis",
    "wu-table2",
    "car-hall",
    "car-hall-planar",
    "car-hall-isolated",
    "fisheye-handheld",
];

pub mod hall;
pub mod render;
pub mod ring;
pub mod scene;
pub mod tagscene;

use hall::about_centre;

/// The ground truth written next to a synthetic session.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Truth {
    pub preset: String,
    pub reference_camera: String,
    /// Camera id → `ref_from_cam`.
    pub ref_from_cam: BTreeMap<String, Pose>,
    /// Per frame: `world_from_rig` (the reference camera's pose).
    pub world_from_rig: Vec<Pose>,
    /// The motion class the preset was built to have.
    pub motion: String,
    /// Scene points (id → world coordinates; world = the vehicle frame at frame 0).
    pub points: BTreeMap<String, [f64; 3]>,
}

struct Scenario {
    preset: String,
    motion: &'static str,
    cameras: Vec<(String, Camera, Pose)>,
    world_from_vehicle: Vec<Pose>,
    /// Scene points (id, world position).
    scenes: Vec<Vec<(String, Vec3)>>,
    /// Per scene: pairs of point indices whose distance is measured.
    scale_pairs: Vec<Vec<(usize, usize)>>,
}

/// Camera orientation looking along `dir` (vehicle frame, z up), pitched down by `pitch` rad.
pub(crate) fn look(dir: Vec3, pitch: f64) -> nalgebra::Matrix3<f64> {
    let z = dir.normalize();
    let x = z.cross(&Vec3::z()).normalize();
    let y = z.cross(&x);
    let r = nalgebra::Matrix3::from_columns(&[x, y, z]);
    r * so3::exp(&Vec3::new(-pitch, 0.0, 0.0))
}

/// Points in front of camera `world_from_cam`, inside the central part of its view.
fn scene_points(
    rng: &mut ChaCha8Rng,
    name: &str,
    cam: &Camera,
    world_from_cam: &Pose,
    n: usize,
    depth: (f64, f64),
    fill: f64,
) -> Vec<(String, Vec3)> {
    let (hx, hy) = (
        (cam.width as f64 / 2.0) / cam.fx,
        (cam.height as f64 / 2.0) / cam.fy,
    );
    (0..n)
        .map(|i| {
            let z = rng.gen_range(depth.0..depth.1);
            let x = rng.gen_range(-1.0..1.0) * hx * fill * z;
            let y = rng.gen_range(-1.0..1.0) * hy * fill * z;
            (
                format!("{name}:{i:02}"),
                world_from_cam.apply(&Vec3::new(x, y, z)),
            )
        })
        .collect()
}

/// One scene per camera, in front of it at vehicle pose 0, named `s-<camera>:<k>`.
fn camera_scenes(
    rng: &mut ChaCha8Rng,
    cameras: &[(String, Camera, Pose)],
    n: usize,
    depth: (f64, f64),
    fill: f64,
) -> Vec<Vec<(String, Vec3)>> {
    cameras
        .iter()
        .map(|(name, cam, v_from_c)| {
            scene_points(rng, &format!("s-{name}"), cam, v_from_c, n, depth, fill)
        })
        .collect()
}

fn far_pairs(points: &[(String, Vec3)], count: usize) -> Vec<(usize, usize)> {
    let mut pairs: Vec<(usize, usize, f64)> = Vec::new();
    for i in 0..points.len() {
        for j in i + 1..points.len() {
            pairs.push((i, j, (points[i].1 - points[j].1).norm()));
        }
    }
    pairs.sort_by(|a, b| b.2.total_cmp(&a.2));
    let mut used = vec![false; points.len()];
    let mut out = Vec::new();
    for (i, j, _) in pairs {
        if out.len() == count {
            break;
        }
        if !used[i] && !used[j] {
            used[i] = true;
            used[j] = true;
            out.push((i, j));
        }
    }
    out
}

pub(crate) fn planar_pose(x: f64, y: f64, yaw_deg: f64) -> Pose {
    Pose::new(
        so3::exp(&Vec3::new(0.0, 0.0, yaw_deg.to_radians())),
        Vec3::new(x, y, 0.0),
    )
}

fn lebraly(rng: &mut ChaCha8Rng) -> Scenario {
    let cam = Camera::pinhole(1273.0, 1273.0, 799.5, 599.5, 1600, 1200);
    let ext = Pose::new(
        so3::from_rpy(
            -179f64.to_radians(),
            -4f64.to_radians(),
            171f64.to_radians(),
        ),
        Vec3::new(0.1, 0.1, -2.0),
    );
    let cameras = vec![
        ("cam1".to_string(), cam.clone(), Pose::identity()),
        ("cam2".to_string(), cam.clone(), ext),
    ];
    // 10 rig poses, general 3D motion: rotations of 5–12° about random axes.
    let mut world_from_vehicle = vec![Pose::identity()];
    while world_from_vehicle.len() < 10 {
        let axis = Vec3::new(
            rng.gen_range(-1.0..1.0),
            rng.gen_range(-1.0..1.0),
            rng.gen_range(-1.0..1.0),
        )
        .normalize();
        let angle = rng.gen_range(5.0f64..12.0).to_radians();
        let t = Vec3::new(
            rng.gen_range(-0.15..0.15),
            rng.gen_range(-0.15..0.15),
            rng.gen_range(-0.15..0.15),
        );
        world_from_vehicle.push(Pose::from_rotvec(axis * angle, t));
    }
    let scenes = camera_scenes(rng, &cameras, 11, (0.8, 1.3), 0.45);
    let scale_pairs = scenes.iter().map(|s| far_pairs(s, 2)).collect();
    Scenario {
        preset: "lebraly-5.1".into(),
        motion: "general",
        cameras,
        world_from_vehicle,
        scenes,
        scale_pairs,
    }
}

fn car(preset: &str, rng: &mut ChaCha8Rng) -> Option<Scenario> {
    let cam = Camera::pinhole(700.0, 700.0, 639.5, 399.5, 1280, 800);
    // Vehicle frame: x forward, y left, z up. The rig is symmetric about x = 0.5 so a
    // U-turn about that point swaps front↔rear and left↔right.
    let mounts = [
        (
            "front",
            Vec3::new(2.0, 0.0, 1.3),
            Vec3::new(1.0, 0.0, 0.0),
            0.12,
        ),
        (
            "rear",
            Vec3::new(-1.0, 0.05, 1.0),
            Vec3::new(-1.0, 0.0, 0.0),
            0.1,
        ),
        (
            "left",
            Vec3::new(0.5, 0.9, 1.1),
            Vec3::new(0.0, 1.0, 0.0),
            0.25,
        ),
        (
            "right",
            Vec3::new(0.5, -0.9, 1.15),
            Vec3::new(0.0, -1.0, 0.0),
            0.2,
        ),
    ];
    let cameras: Vec<(String, Camera, Pose)> = mounts
        .iter()
        .map(|(n, p, d, pitch)| (n.to_string(), cam.clone(), Pose::new(look(*d, *pitch), *p)))
        .collect();
    let mut poses: Vec<Pose> = Vec::new();
    let local = |rng: &mut ChaCha8Rng, n: usize| -> Vec<Pose> {
        (0..n)
            .map(|k| {
                if k == 0 {
                    Pose::identity()
                } else {
                    planar_pose(
                        rng.gen_range(-0.8..0.8),
                        rng.gen_range(-0.4..0.4),
                        rng.gen_range(-14.0..14.0),
                    )
                }
            })
            .collect()
    };
    let motion = match preset {
        "car-planar" => {
            poses = local(rng, 12);
            "planar"
        }
        "car-bump" => {
            poses = local(rng, 12);
            // One speed bump: the car pitches 3° and rises 8 cm at one pose.
            poses.push(Pose::new(
                so3::exp(&Vec3::new(0.0, -3f64.to_radians(), 2f64.to_radians())),
                Vec3::new(0.3, 0.1, 0.08),
            ));
            "general"
        }
        "car-planar-uturn" => {
            let before = local(rng, 8);
            let after: Vec<Pose> = local(rng, 8)
                .iter()
                .map(|p| about_centre(p, 180.0))
                .collect();
            poses.extend(before);
            poses.extend(after);
            "planar"
        }
        "car-planar-loop" => {
            for k in 0..16 {
                let jitter = planar_pose(
                    rng.gen_range(-0.3..0.3),
                    rng.gen_range(-0.3..0.3),
                    rng.gen_range(-3.0..3.0),
                );
                poses.push(about_centre(&jitter, 22.5 * k as f64));
            }
            poses[0] = Pose::identity();
            "planar"
        }
        "pure-translation" => {
            poses = (0..10)
                .map(|k| {
                    if k == 0 {
                        Pose::identity()
                    } else {
                        planar_pose(rng.gen_range(-1.0..1.0), rng.gen_range(-0.5..0.5), 0.0)
                    }
                })
                .collect();
            poses
                .iter_mut()
                .skip(1)
                .for_each(|p| p.trans.z = rng.gen_range(-0.05..0.05));
            "pure_translation"
        }
        "single-axis" => {
            poses = (0..10)
                .map(|k| {
                    about_centre(
                        &Pose::identity(),
                        if k == 0 {
                            0.0
                        } else {
                            rng.gen_range(-20.0..20.0)
                        },
                    )
                })
                .collect();
            "single_axis"
        }
        _ => return None,
    };
    let scenes = camera_scenes(rng, &cameras, 40, (3.0, 6.0), 0.5);
    let scale_pairs = scenes.iter().map(|s| far_pairs(s, 2)).collect();
    Some(Scenario {
        preset: preset.into(),
        motion,
        cameras,
        world_from_vehicle: poses,
        scenes,
        scale_pairs,
    })
}

/// A camera as a session manifest declares it.
pub fn camera_spec(id: &str, c: &Camera) -> CameraSpec {
    CameraSpec {
        id: id.into(),
        model: c.model.name().into(),
        width: c.width,
        height: c.height,
        intrinsics: Intrinsics {
            fx: c.fx,
            fy: c.fy,
            cx: c.cx,
            cy: c.cy,
        },
        distortion: c.model.coefficients(),
    }
}

/// Build a preset's session (observations with `noise_px` Gaussian pixel noise) and truth.
/// The hall presets give their fully visible tags' true corners plus that noise.
pub fn generate(preset: &str, seed: u64, noise_px: f64) -> Option<(SessionManifest, Truth)> {
    generate_mounted(preset, seed, noise_px, &BTreeMap::new())
}

/// [`generate`] with cameras mounted off their design pose: `mounting[id]` is applied in
/// the camera's own frame (`vehicle_from_cam · δ`, a bracket turned or shifted), after
/// the scene is laid out, so one seed gives the same drive and scene for every mounting —
/// a fleet of one vehicle model. The truth is the mounted rig. Not for the hall and ring
/// presets (their scenes are laid out for the design rig): `None` there when `mounting`
/// is not empty.
pub fn generate_mounted(
    preset: &str,
    seed: u64,
    noise_px: f64,
    mounting: &BTreeMap<String, Pose>,
) -> Option<(SessionManifest, Truth)> {
    if !(noise_px.is_finite() && noise_px >= 0.0) {
        return None;
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let special = preset == "wu-table2" || hall::PRESETS.contains(&preset);
    if special && !mounting.is_empty() {
        return None;
    }
    if preset == "wu-table2" {
        return Some(ring::generate(&mut rng, noise_px));
    }
    if hall::PRESETS.contains(&preset) {
        let c = hall::hall(preset, seed, None)
            .ok()?
            .detection_capture(noise_px, seed)?;
        return Some((c.manifest, c.truth));
    }
    let mut sc = if preset == "lebraly-5.1" {
        lebraly(&mut rng)
    } else {
        car(preset, &mut rng)?
    };
    for (id, _, vehicle_from_cam) in &mut sc.cameras {
        if let Some(d) = mounting.get(id) {
            *vehicle_from_cam = *vehicle_from_cam * *d;
        }
    }
    Some(render(&sc, &mut rng, noise_px))
}

fn render(sc: &Scenario, rng: &mut ChaCha8Rng, noise_px: f64) -> (SessionManifest, Truth) {
    let px = Normal::new(0.0, noise_px).expect("noise checked finite and non-negative in generate");
    let mm = Normal::new(0.0, 5e-4).expect("finite");
    let ref_from_vehicle = sc.cameras[0].2.inverse();
    let mut frames = Vec::new();
    for (k, w_from_v) in sc.world_from_vehicle.iter().enumerate() {
        let mut observations = BTreeMap::new();
        for (name, cam, v_from_c) in &sc.cameras {
            let cam_from_world = (*w_from_v * *v_from_c).inverse();
            let margin = 8.0;
            let mut obs = Vec::new();
            for scene in &sc.scenes {
                for (id, x) in scene {
                    let p = cam_from_world.apply(x);
                    if p.z < 0.3 {
                        continue;
                    }
                    let Some(uv) = cam.project(&p) else { continue };
                    if uv.x < margin
                        || uv.y < margin
                        || uv.x > cam.width as f64 - 1.0 - margin
                        || uv.y > cam.height as f64 - 1.0 - margin
                    {
                        continue;
                    }
                    let n = Vec2::new(px.sample(rng), px.sample(rng));
                    obs.push(ObservationSpec {
                        point: id.clone(),
                        u: uv.x + n.x,
                        v: uv.y + n.y,
                    });
                }
            }
            if !obs.is_empty() {
                observations.insert(name.clone(), obs);
            }
        }
        frames.push(FrameSpec {
            index: k as i64,
            timestamp: Some(k as f64 * 0.5),
            images: BTreeMap::new(),
            observations,
            lines: BTreeMap::new(),
            line_targets: BTreeMap::new(),
        });
    }
    let mut scale = Vec::new();
    for (scene, pairs) in sc.scenes.iter().zip(&sc.scale_pairs) {
        for &(i, j) in pairs {
            let d = (scene[i].1 - scene[j].1).norm()
                + if noise_px > 0.0 { mm.sample(rng) } else { 0.0 };
            scale.push(ScaleSpec {
                a: scene[i].0.clone(),
                b: scene[j].0.clone(),
                distance: d,
                sigma: Some(5e-4),
            });
        }
    }
    let cameras = sc
        .cameras
        .iter()
        .map(|(name, c, _)| camera_spec(name, c))
        .collect();
    let reference = sc.cameras[0].0.clone();
    let manifest = SessionManifest {
        version: 1,
        vehicle_id: Some(format!("synth-{}", sc.preset)),
        vehicle_model: None,
        method: Default::default(),
        reference_camera: reference.clone(),
        cameras,
        targets: vec![],
        scale,
        frames,
        priors: None,
        auxiliary_camera: None,
        ring: vec![],
    };
    let truth = Truth {
        preset: sc.preset.clone(),
        reference_camera: reference,
        ref_from_cam: sc
            .cameras
            .iter()
            .map(|(n, _, v_from_c)| (n.clone(), ref_from_vehicle * *v_from_c))
            .collect(),
        world_from_rig: sc
            .world_from_vehicle
            .iter()
            .map(|w| *w * sc.cameras[0].2)
            .collect(),
        motion: sc.motion.to_string(),
        points: sc
            .scenes
            .iter()
            .flatten()
            .map(|(id, x)| (id.clone(), [x.x, x.y, x.z]))
            .collect(),
    };
    (manifest, truth)
}
