//! Speed of the rig bundle adjustment on the benchmark rig of issue 2: `cameras`
//! cameras on a ring looking outwards, `poses` rig poses of general 3D motion, `points`
//! points per camera scene, 0.5 px noise; the solve starts from a perturbed truth.
//! With a window of W frames, each scene is seen only by W consecutive rig poses, and a
//! new scene begins every W/2 frames (as along a drive past targets): the reduced system
//! is then a band, the case for the sparse factorisation.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use rigcal_core::geometry::{Camera, Pose, Vec2, Vec3};
use rigcal_solve::bundle::{BundleProblem, BundleSummary, LmOptions, Obs, PointRef};

/// Build the benchmark problem (already perturbed) and its truth extrinsics; `window`
/// 0: every point in every frame.
pub fn problem(
    cameras: usize,
    poses: usize,
    points: usize,
    window: usize,
    seed: u64,
) -> (BundleProblem, Vec<Pose>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let cam = Camera::pinhole(800.0, 800.0, 639.5, 479.5, 1280, 960);
    // Ring of cameras, optical axes horizontal and outwards (rig frame: z up).
    let rig_from_cam: Vec<Pose> = (0..cameras)
        .map(|i| {
            let a = std::f64::consts::TAU * i as f64 / cameras as f64;
            let z = Vec3::new(a.cos(), a.sin(), 0.0);
            let x = z.cross(&Vec3::z());
            let y = z.cross(&x);
            Pose::new(
                nalgebra::Matrix3::from_columns(&[x, y, z]),
                z * 1.0 + Vec3::new(0.0, 0.0, 0.1 * i as f64),
            )
        })
        .collect();
    // Express everything relative to camera 0 (the reference).
    let ref_from_rig = rig_from_cam[0].inverse();
    let ref_from_cam: Vec<Pose> = rig_from_cam.iter().map(|p| ref_from_rig * *p).collect();
    let world_from_ref: Vec<Pose> = (0..poses)
        .map(|k| {
            if k == 0 {
                return Pose::identity();
            }
            let w = Vec3::new(
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
            ) * 0.08;
            let t = Vec3::new(
                rng.gen_range(-0.3..0.3),
                rng.gen_range(-0.3..0.3),
                rng.gen_range(-0.3..0.3),
            );
            Pose::from_rotvec(w, t)
        })
        .collect();
    // Scenes: (first frame, last frame + 1) of the rig poses that see them.
    let scenes: Vec<(usize, usize)> = if window == 0 || window >= poses {
        vec![(0, poses)]
    } else {
        let step = (window / 2).max(1);
        (0..poses)
            .step_by(step)
            .map(|s| (s, (s + window).min(poses)))
            .take_while(|&(s, _)| s == 0 || s + step < poses)
            .collect()
    };
    let mut world_points = Vec::new();
    let mut seen_by = Vec::new();
    for &frames in &scenes {
        for c in &ref_from_cam {
            for _ in 0..points {
                let z = rng.gen_range(3.0..6.0);
                let p = Vec3::new(
                    rng.gen_range(-0.5..0.5) * z,
                    rng.gen_range(-0.4..0.4) * z,
                    z,
                );
                world_points.push(c.apply(&p));
                seen_by.push(frames);
            }
        }
    }
    let noise = Normal::new(0.0, 0.5).expect("finite");
    let mut observations = Vec::new();
    for (k, w) in world_from_ref.iter().enumerate() {
        for (c, x) in ref_from_cam.iter().enumerate() {
            let cam_from_world = (*w * *x).inverse();
            for (i, p) in world_points.iter().enumerate() {
                if !(seen_by[i].0..seen_by[i].1).contains(&k) {
                    continue;
                }
                let q = cam_from_world.apply(p);
                if let Some(uv) = cam.project(&q) {
                    if cam.in_image(&uv) && q.z > 0.5 {
                        observations.push(Obs {
                            rig: k,
                            cam: c,
                            point: PointRef::Free(i),
                            uv: uv + Vec2::new(noise.sample(&mut rng), noise.sample(&mut rng)),
                        });
                    }
                }
            }
        }
    }
    let mut jitter = |s: f64| {
        Vec3::new(
            rng.gen_range(-s..s),
            rng.gen_range(-s..s),
            rng.gen_range(-s..s),
        )
    };
    let start_cams: Vec<Pose> = ref_from_cam
        .iter()
        .enumerate()
        .map(|(c, p)| {
            if c == 0 {
                *p
            } else {
                p.perturbed(&jitter(0.02), &jitter(0.01))
            }
        })
        .collect();
    let start_rigs: Vec<Pose> = world_from_ref
        .iter()
        .enumerate()
        .map(|(k, p)| {
            if k == 0 {
                *p
            } else {
                p.perturbed(&jitter(0.01), &jitter(0.005))
            }
        })
        .collect();
    let start_points: Vec<Vec3> = world_points.iter().map(|p| p + jitter(0.03)).collect();
    let problem = BundleProblem {
        cameras: vec![cam; cameras],
        rig_from_cam: start_cams,
        cam_fixed: (0..cameras).map(|c| c == 0).collect(),
        world_from_rig: start_rigs,
        rig_fixed: (0..poses).map(|k| k == 0).collect(),
        points: start_points,
        world_from_body: vec![],
        body_fixed: vec![],
        observations,
        distances: vec![],
        priors: vec![],
        pixel_sigma: 0.5,
    };
    (problem, ref_from_cam)
}

pub struct SpeedRow {
    pub poses: usize,
    pub observations: usize,
    pub summary: BundleSummary,
    pub extrinsic_error_mm: f64,
    /// The extrinsics' marginal information at the solution (what the calibration's
    /// covariances come from), timed apart from the solve.
    pub information_seconds: f64,
}

/// The stopping rule of the benchmark; exported with the problem so a peer solver can be
/// given the same tolerances.
pub fn bench_options() -> LmOptions {
    LmOptions {
        max_iterations: 50,
        function_tolerance: 1e-10,
        parameter_tolerance: 1e-10,
        gradient_tolerance: 1e-10,
        ..LmOptions::default()
    }
}

/// Run the benchmark for each K. With `export`, each problem is also written as
/// `ba_K.json` there (start, observations, rigcal's final state and summary), so that a
/// peer bundle adjuster (`benches/peers/colmap_ba.py`) solves the identical problem from
/// the identical start and both end states can be scored by one cost function.
pub fn run(
    cameras: usize,
    poses: &[usize],
    points: usize,
    window: usize,
    export: Option<&std::path::Path>,
) -> std::io::Result<Vec<SpeedRow>> {
    poses
        .iter()
        .map(|&k| {
            let (mut p, truth) = problem(cameras, k, points, window, 7);
            let start = export.map(|_| state_json(&p));
            let options = bench_options();
            let summary = p.solve(&options);
            // Scale is free in this problem (no distances); compare up to scale via the
            // direction-insensitive rotation and the scale-corrected translation.
            let s = truth[1].trans.norm() / p.rig_from_cam[1].trans.norm();
            let err = (1..cameras)
                .map(|c| ((p.rig_from_cam[c].trans * s) - truth[c].trans).norm())
                .fold(0.0, f64::max)
                * 1e3;
            if let (Some(dir), Some(start)) = (export, start) {
                write_export(dir, k, &p, start, &summary, &options)?;
            }
            let clock = std::time::Instant::now();
            let information = p.extrinsic_information(&rigcal_solve::Loss::Squared);
            let information_seconds = clock.elapsed().as_secs_f64();
            if information.is_none() {
                return Err(std::io::Error::other(format!(
                    "K = {k}: no extrinsic information at the solution (a point behind its camera)"
                )));
            }
            Ok(SpeedRow {
                poses: k,
                observations: p.observations.len(),
                summary,
                extrinsic_error_mm: err,
                information_seconds,
            })
        })
        .collect()
}

/// A pose as its 3×3 rotation (row-major) then translation: matrices, not quaternions,
/// so no convention (wxyz vs xyzw, active vs passive) can be crossed on the way out.
fn pose_json(p: &Pose) -> serde_json::Value {
    let r = &p.rot;
    serde_json::json!([
        r[(0, 0)],
        r[(0, 1)],
        r[(0, 2)],
        r[(1, 0)],
        r[(1, 1)],
        r[(1, 2)],
        r[(2, 0)],
        r[(2, 1)],
        r[(2, 2)],
        p.trans.x,
        p.trans.y,
        p.trans.z
    ])
}

/// The variable part of a problem: extrinsics (`ref_from_cam`), rig poses
/// (`world_from_ref`) and points.
fn state_json(p: &BundleProblem) -> serde_json::Value {
    serde_json::json!({
        "ref_from_cam": p.rig_from_cam.iter().map(pose_json).collect::<Vec<_>>(),
        "world_from_ref": p.world_from_rig.iter().map(pose_json).collect::<Vec<_>>(),
        "points": p.points.iter().map(|x| [x.x, x.y, x.z]).collect::<Vec<_>>(),
    })
}

fn write_export(
    dir: &std::path::Path,
    k: usize,
    p: &BundleProblem,
    start: serde_json::Value,
    summary: &BundleSummary,
    options: &LmOptions,
) -> std::io::Result<()> {
    let cam = &p.cameras[0];
    let observations: Vec<_> = p
        .observations
        .iter()
        .map(|o| {
            let PointRef::Free(i) = o.point else {
                unreachable!("the speed benchmark has free points only")
            };
            serde_json::json!([o.rig, o.cam, i, o.uv.x, o.uv.y])
        })
        .collect();
    let doc = serde_json::json!({
        "model": "pinhole",
        "intrinsics": [cam.fx, cam.fy, cam.cx, cam.cy],
        "width": cam.width,
        "height": cam.height,
        "fixed": {"camera": 0, "rig_pose": 0},
        "cost": "0.5 * sum of squared pixel residuals, no robust loss",
        "tolerances": {
            "max_iterations": options.max_iterations,
            "function": options.function_tolerance,
            "parameter": options.parameter_tolerance,
            "gradient": options.gradient_tolerance,
        },
        "start": start,
        "observations": observations,
        "rigcal": {
            "seconds": summary.seconds,
            "iterations": summary.iterations,
            "initial_cost": summary.initial_cost,
            "final_cost": summary.final_cost,
            "termination": summary.termination,
            "final": state_json(p),
        },
    });
    std::fs::create_dir_all(dir)?;
    let file = std::fs::File::create(dir.join(format!("ba_{k}.json")))?;
    serde_json::to_writer(std::io::BufWriter::new(file), &doc).map_err(std::io::Error::other)
}

pub fn print_table(cameras: usize, points: usize, rows: &[SpeedRow]) {
    println!("rig BA: {cameras} cameras, {points} points per scene, 0.5 px noise, perturbed start");
    println!(
        "{:>6} {:>9} {:>8} {:>6} {:>14} {:>14} {:>10} {:>10} {:>9}",
        "K",
        "obs",
        "reduced",
        "iters",
        "initial cost",
        "final cost",
        "seconds",
        "max dt mm",
        "info s"
    );
    for r in rows {
        println!(
            "{:>6} {:>9} {:>8} {:>6} {:>14.4e} {:>14.6e} {:>10.3} {:>10.3} {:>9.3}",
            r.poses,
            r.observations,
            r.summary.reduced_dimension,
            r.summary.iterations,
            r.summary.initial_cost,
            r.summary.final_cost,
            r.summary.seconds,
            r.extrinsic_error_mm,
            r.information_seconds
        );
    }
}
