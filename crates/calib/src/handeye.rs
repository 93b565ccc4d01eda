//! Linear initialisation of the extrinsics (Lébraly §3).
//!
//! Rotations, per camera: the null vector of the stacked `I₉ − R_A ⊗ R_B` (eq. 6-7) for
//! general motion; for planar motion the common axes aligned and the turn about them
//! solved from the in-plane translations (see `planar_rotation`: better conditioned than
//! the paper's eq. 10); for pure translation `ΔR t_B = t_A` (eq. 4b with `R_A = I`) by
//! Procrustes. Then, jointly, chordal rotation averaging over frames, scenes and
//! extrinsics: with scene permutation (eq. 18a/19a) a camera's rotation is measured
//! against the camera whose scene it sees.
//!
//! Translations, jointly for all cameras: every image that sees a scene gives
//! `world_from_scene = world_from_rig(k) · ref_from_cam(c) · cam_from_scene`, whose
//! translation part is linear in the unknown translations once rotations are known.
//! With one scene per camera this is eq. 8; when a camera sees another camera's scene
//! (U-turn) it contains eq. 19b, for any number of cameras. Directions the system
//! cannot determine (the height under planar motion) are set from `priors` or to 0 and
//! reported.

use super::motion::{classify, common_axis, MotionClass, MotionReport, MIN_ROTATION};
use super::trajectory::{SceneScale, Trajectories};
use nalgebra::{DMatrix, DVector};
use rigcal_core::geometry::{so3, Mat3, Pose, Vec3};
use rigcal_core::session::Session;
use std::collections::{BTreeMap, BTreeSet};

#[derive(Clone, Debug)]
pub struct InitOutput {
    pub ref_from_cam: Vec<Pose>,
    pub world_from_rig: Vec<Option<Pose>>,
    pub world_from_scene: Vec<Option<Pose>>,
    /// Factor taking each scene's coordinates to metres (near 1 for measured scenes:
    /// their mean scale comes from the distances, their relative scales from the rig).
    pub scene_scale: Vec<f64>,
    pub motion: MotionReport,
    /// Motion pairs used in eq. 6, and those dropped as uninformative.
    pub pairs_used: usize,
    pub pairs_dropped_small: usize,
    pub pairs_dropped_near_180: usize,
    /// Some scene is seen by two different cameras (scene permutation).
    pub permutation: bool,
    /// How the undetermined translation directions were set (`prior` or `zero`).
    pub height_source: Option<&'static str>,
}

#[derive(Debug, Clone, thiserror::Error)]
pub enum InitError {
    #[error("camera {0} has no pose in any frame where the reference camera has one")]
    CameraNotObserved(String),
    #[error("the reference camera {0} has fewer than 2 posed frames")]
    ReferenceNotObserved(String),
}

/// Rotations within this of 180° are dropped from eq. 6: the axis of a half-turn
/// is ill-conditioned (the fix OpenCV's hand-eye needed, opencv/opencv#24871).
const NEAR_180: f64 = 2.0 * std::f64::consts::PI / 180.0;

fn kron_rows(a: &Mat3, b: &Mat3) -> DMatrix<f64> {
    // (I₉ − A ⊗ B) with row-major vec: vec(A X Bᵀ) = (A ⊗ B) vec(X).
    let mut m = DMatrix::identity(9, 9);
    for i in 0..3 {
        for j in 0..3 {
            for k in 0..3 {
                for l in 0..3 {
                    m[(3 * i + k, 3 * j + l)] -= a[(i, j)] * b[(k, l)];
                }
            }
        }
    }
    m
}

/// Poses of camera `c` per scene: scene → (frame → cam_from_scene).
fn poses_by_scene(traj: &Trajectories, c: usize) -> BTreeMap<usize, BTreeMap<usize, Pose>> {
    let mut out: BTreeMap<usize, BTreeMap<usize, Pose>> = BTreeMap::new();
    for (s, scene) in traj.scenes.iter().enumerate() {
        for (&(f, ci), p) in &scene.poses {
            if ci == c {
                out.entry(s).or_default().insert(f, *p);
            }
        }
    }
    out
}

/// Relative motions `(A, B)` = (ref^k_from_ref^k0, cam^k_from_cam^k0) for camera `c`,
/// one group per (reference scene, camera scene) pair that shares frames.
fn motion_pairs(
    refp: &BTreeMap<usize, BTreeMap<usize, Pose>>,
    camp: &BTreeMap<usize, BTreeMap<usize, Pose>>,
) -> Vec<Vec<(Pose, Pose)>> {
    let mut out = Vec::new();
    for rs in refp.values() {
        for cs in camp.values() {
            let common: Vec<usize> = rs.keys().filter(|k| cs.contains_key(k)).copied().collect();
            let Some(&k0) = common.first() else { continue };
            let group: Vec<(Pose, Pose)> = common[1..]
                .iter()
                .map(|k| (rs[k] * rs[&k0].inverse(), cs[k] * cs[&k0].inverse()))
                .collect();
            if !group.is_empty() {
                out.push(group);
            }
        }
    }
    out
}

/// Solve the rotation of one camera from its motion pairs, grouped by the pair of
/// scenes they were measured in (one group per (reference scene, camera scene)).
fn rotation(
    groups: &[Vec<(Pose, Pose)>],
    class: MotionClass,
    stats: &mut (usize, usize, usize),
) -> Mat3 {
    let pairs: Vec<(Pose, Pose)> = groups.iter().flatten().copied().collect();
    match class {
        MotionClass::Planar | MotionClass::SingleAxis => {
            if let Some(r) = planar_rotation(groups) {
                // Every pair enters, whatever its angle: a small turn still carries its
                // translation direction, a half-turn its in-plane (I − R_A).
                stats.0 += pairs.len();
                return r;
            }
        }
        MotionClass::PureTranslation | MotionClass::None => {
            // ΔR t_B = t_A: Procrustes (Kabsch) on the translation directions.
            let mut h = Mat3::zeros();
            for (a, b) in &pairs {
                h += a.trans * b.trans.transpose();
            }
            return so3::project_to_so3(&h);
        }
        MotionClass::General => {}
    }
    general_rotation(&pairs, stats)
}

/// Eq. 6-7: the null vector of the stacked `I₉ − R_A ⊗ R_B`, scaled to det = +1 and
/// re-orthogonalised. Pairs with a tiny or near-half-turn rotation carry no axis and
/// are dropped (counted in `stats`).
fn general_rotation(pairs: &[(Pose, Pose)], stats: &mut (usize, usize, usize)) -> Mat3 {
    let mut l = Vec::new();
    for (a, b) in pairs {
        let th = so3::log(&a.rot).norm();
        if th < MIN_ROTATION {
            stats.1 += 1;
        } else if th > std::f64::consts::PI - NEAR_180 {
            stats.2 += 1;
        } else {
            stats.0 += 1;
            l.push(kron_rows(&a.rot, &b.rot));
        }
    }
    let mut m = DMatrix::zeros(l.len() * 9, 9);
    for (i, blk) in l.iter().enumerate() {
        m.view_mut((9 * i, 0), (9, 9)).copy_from(blk);
    }
    let v = rigcal_core::linalg::null_vector(&m)
        .unwrap_or_else(|| DVector::from_row_slice(Mat3::identity().transpose().as_slice()));
    let vm = Mat3::from_row_slice(v.as_slice());
    let det = vm.determinant();
    let vm = if det != 0.0 {
        vm * det.signum() * det.abs().powf(-1.0 / 3.0)
    } else {
        vm
    };
    so3::project_to_so3(&vm)
}

/// `vee(R − Rᵀ) = 2 sin θ ŵ`: the rotation's axis scaled by the sine of its angle,
/// well defined at every angle (unlike the axis of `log R` near a half-turn).
fn sine_axis(r: &Mat3) -> Vec3 {
    let k = r - r.transpose();
    Vec3::new(k[(2, 1)], k[(0, 2)], k[(1, 0)])
}

/// The smallest rotation taking unit vector `from` to unit vector `to`.
fn align(from: &Vec3, to: &Vec3) -> Mat3 {
    let c = from.cross(to);
    let s = c.norm();
    let d = from.dot(to);
    if s < 1e-12 {
        if d > 0.0 {
            return Mat3::identity();
        }
        // Opposite: a half-turn about any axis perpendicular to `from`.
        let p = if from.x.abs() < 0.9 {
            Vec3::x()
        } else {
            Vec3::y()
        };
        let axis = from.cross(&p).normalize();
        return so3::exp(&(axis * std::f64::consts::PI));
    }
    so3::exp(&(c / s * s.atan2(d)))
}

/// Rotation for motion about one axis (planar, single-axis), where eq. 6 leaves the
/// turn about the axis free. The axes fix all but that turn: `ΔR = Rot(a, φ) · R₀`
/// with `R₀ b = a` (a, b: the common axes of A and B). The in-plane part of
/// `(R_A − I) t_X = R_X t_B − t_A` is then linear in the in-plane `t_X` and in
/// `(cos φ, sin φ)`: two rows per motion pair, four unknowns per group. Unlike eq. 10,
/// which differences every motion against the largest one, each pair enters once and
/// half-turns are as well conditioned as any other turn. Groups are solved apart
/// because each (reference scene, camera scene) pair may carry its own scale (a scene
/// split off a long chain); only the direction of `(cos φ, sin φ)` is kept from each.
fn planar_rotation(groups: &[Vec<(Pose, Pose)>]) -> Option<Mat3> {
    let all = || groups.iter().flatten();
    let informative =
        |(n, largest): (Vec3, f64)| (largest >= MIN_ROTATION * MIN_ROTATION).then_some(n);
    let a = informative(common_axis(all().map(|(a, _)| &a.rot)))?;
    let b = informative(common_axis(all().map(|(_, b)| &b.rot)))?;
    // A and B are conjugate, so each pair turns by the same signed angle about a and
    // about the corresponding b: every pair votes for the relative sign, weighted by how
    // much it turns. (The sign of a sum of turns is unreliable: a drive that swings
    // left and right sums to almost nothing, and noise then picks the sign.)
    let vote: f64 = all()
        .map(|(pa, pb)| sine_axis(&pa.rot).dot(&a) * sine_axis(&pb.rot).dot(&b))
        .sum();
    let b = if vote < 0.0 { -b } else { b };
    let r0 = align(&b, &a);
    let e1 = if a.x.abs() < 0.9 {
        a.cross(&Vec3::x()).normalize()
    } else {
        a.cross(&Vec3::y()).normalize()
    };
    let e2 = a.cross(&e1);
    let plane = |v: &Vec3| nalgebra::Vector2::new(e1.dot(v), e2.dot(v));
    let mut sum = nalgebra::Vector2::zeros();
    for g in groups {
        let mut ata = nalgebra::Matrix4::<f64>::zeros();
        let mut atb = nalgebra::Vector4::<f64>::zeros();
        for (pa, pb) in g {
            let d = pa.rot - Mat3::identity();
            let pv = plane(&(r0 * pb.trans));
            let jpv = nalgebra::Vector2::new(-pv.y, pv.x);
            let rhs = -plane(&pa.trans);
            let cols = [d * e1, d * e2];
            for i in 0..2 {
                let e = if i == 0 { e1 } else { e2 };
                let row = nalgebra::Vector4::new(e.dot(&cols[0]), e.dot(&cols[1]), -pv[i], -jpv[i]);
                ata += row * row.transpose();
                atb += row * rhs[i];
            }
        }
        let Some(x) = ata.cholesky().map(|c| c.solve(&atb)) else {
            continue;
        };
        let cs = nalgebra::Vector2::new(x[2], x[3]);
        if cs.norm() > 1e-12 && cs.iter().all(|v| v.is_finite()) {
            sum += cs.normalize() * g.len() as f64;
        }
    }
    if sum.norm() < 1e-12 {
        return None;
    }
    let phi = sum.y.atan2(sum.x);
    Some(so3::exp(&(a * phi)) * r0)
}

/// A camera the shared scenes turn this far (rad) from its hand-eye rotation has a link
/// that disagrees with its motions ([`relink`] decides which is right): the hand-eye
/// turn about a planar axis is off by 1-3° at 1 px of corner noise.
const LINK_CONFLICT: f64 = 10.0 * std::f64::consts::PI / 180.0;
/// Scale (rad) of the Cauchy weight of a link in the robust average.
const LINK_SCALE: f64 = 3.0 * std::f64::consts::PI / 180.0;
/// How many links' worth a camera's own motions count in the robust average: more than
/// a scene it shares in one or two frames, less than one it shares along the drive
/// (the hand-eye rotation itself was 12° off on a U-turn drive whose shared scene had it
/// right).
const PRIOR_LINKS: f64 = 2.5;

/// Cauchy weight of a camera's prior at rotation `x`.
fn prior_weight(x: &Mat3, prior: &Mat3) -> f64 {
    let t = angle(x, prior) / LINK_SCALE;
    PRIOR_LINKS / (1.0 + t * t)
}

/// The rotations of the averaging: extrinsics, frames, scenes.
#[derive(Clone)]
struct Graph {
    rot: Vec<Mat3>,
    rw: Vec<Option<Mat3>>,
    rs: Vec<Option<Mat3>>,
}

/// How badly extrinsic rotation `x` explains a camera's motion pairs' translations:
/// the least-squares residual (m²) of `(R_A − I) t_X − s_g x t_B = −t_A` over `t_X` and
/// a scale `s_g` per group (see [`planar_rotation`]). Under planar motion the rotations
/// cannot tell a turn about the axis (they commute with it); the translations can.
fn translation_misfit(groups: &[Vec<(Pose, Pose)>], x: &Mat3) -> f64 {
    let n: usize = groups.iter().map(Vec::len).sum();
    if n == 0 {
        return 0.0;
    }
    let cols = 3 + groups.len();
    let mut a = DMatrix::zeros(3 * n, cols);
    let mut b = DVector::zeros(3 * n);
    let mut row = 0;
    for (g, pairs) in groups.iter().enumerate() {
        for (pa, pb) in pairs {
            let d = pa.rot - Mat3::identity();
            let xt = x * pb.trans;
            for i in 0..3 {
                for j in 0..3 {
                    a[(row + i, j)] = d[(i, j)];
                }
                a[(row + i, 3 + g)] = -xt[i];
                b[row + i] = -pa.trans[i];
            }
            row += 3;
        }
    }
    match a.clone().svd(true, true).solve(&b, 1e-9) {
        Ok(sol) => (a * sol - b).norm_squared(),
        // Only refused when U or V was not computed, and both are: a rotation that cannot
        // be judged explains nothing.
        Err(_) => f64::INFINITY,
    }
}

/// Where the plain average (`averaged`) turned a camera far from its hand-eye rotation
/// (`start`, the graph propagated from the hand-eye rotations), some link disagrees with
/// the motions. Either the average is right (a hand-eye rotation 12° off from small
/// turns, corrected by a scene shared along a U-turn drive) or a link is wrong (a far tag
/// placed with the wrong one of its two planar poses, seen by another camera, turned
/// side cameras 70-100° on a planar drive). The alternative is the robust average from
/// the hand-eye rotations; of the two, the one whose rotations explain the cameras'
/// motion translations (`groups`, per camera) better is kept.
fn relink(
    edges: &[(usize, usize, usize, Pose)],
    groups: &[Vec<Vec<(Pose, Pose)>>],
    averaged: Graph,
    start: Graph,
    base: usize,
    r: usize,
) -> Graph {
    let prior = start.rot.clone();
    let mut robust = start;
    chordal_refinement(
        edges,
        &mut robust.rot,
        &mut robust.rw,
        &mut robust.rs,
        base,
        r,
        Some(&prior),
    );
    let misfit = |g: &Graph| -> f64 {
        g.rot
            .iter()
            .zip(groups)
            .map(|(x, gs)| translation_misfit(gs, x))
            .sum()
    };
    if misfit(&robust) < misfit(&averaged) {
        robust
    } else {
        averaged
    }
}

/// The angle (rad) between two rotations.
fn angle(a: &Mat3, b: &Mat3) -> f64 {
    so3::log(&(a * b.transpose())).norm()
}

/// Chordal rotation averaging over the graph `world_from_scene = W_f · X_c · P` by
/// Gauss–Seidel sweeps (frame `base` and the reference camera held), the extrinsic
/// rotations included. Where a camera sees a scene another camera saw (scene
/// permutation, eq. 18a/19a), its rotation is measured directly against that camera,
/// frame by frame: far better than the hand-eye solve, which for planar motion gets the
/// turn about the axis from translations only (on a loop it was off by 1-3° at 1 px).
/// Where no scene is shared, the turn about the planar axis is a flat direction of
/// these averages and stays where it was.
///
/// With `prior` (each camera's hand-eye rotation) the cameras' rotations are also held
/// by their own motions, as [`PRIOR_LINKS`] links would hold them, and every link and
/// prior is weighed by a Cauchy weight of how far it disagrees (scale [`LINK_SCALE`]).
fn chordal_refinement(
    edges: &[(usize, usize, usize, Pose)],
    rot: &mut [Mat3],
    rw: &mut [Option<Mat3>],
    rs: &mut [Option<Mat3>],
    base: usize,
    r: usize,
    prior: Option<&[Mat3]>,
) {
    let (nc, nf, ns) = (rot.len(), rw.len(), rs.len());
    let mut weight = vec![1.0; edges.len()];
    for _ in 0..100 {
        if prior.is_some() {
            for (wt, &(f, s, c, p)) in weight.iter_mut().zip(edges) {
                if let (Some(w), Some(sr)) = (rw[f], rs[s]) {
                    let t = angle(&sr, &(w * rot[c] * p.rot)) / LINK_SCALE;
                    *wt = 1.0 / (1.0 + t * t);
                }
            }
        }
        let mut acc_x = vec![Mat3::zeros(); nc];
        for (&wt, &(f, s, c, p)) in weight.iter().zip(edges) {
            if let (Some(w), Some(sr)) = (rw[f], rs[s]) {
                acc_x[c] += wt * w.transpose() * sr * p.rot.transpose();
            }
        }
        if let Some(prior) = prior {
            for ((a, p), x) in acc_x.iter_mut().zip(prior).zip(rot.iter()) {
                *a += prior_weight(x, p) * p;
            }
        }
        for c in 0..nc {
            if c != r && acc_x[c].norm() > 0.0 {
                rot[c] = so3::project_to_so3(&acc_x[c]);
            }
        }
        let mut acc_s = vec![Mat3::zeros(); ns];
        for (&wt, &(f, s, c, p)) in weight.iter().zip(edges) {
            if let Some(w) = rw[f] {
                acc_s[s] += wt * w * rot[c] * p.rot;
            }
        }
        for s in 0..ns {
            if rs[s].is_some() {
                rs[s] = Some(so3::project_to_so3(&acc_s[s]));
            }
        }
        let mut acc_w = vec![Mat3::zeros(); nf];
        for (&wt, &(f, s, c, p)) in weight.iter().zip(edges) {
            if let Some(sr) = rs[s] {
                acc_w[f] += wt * sr * (rot[c] * p.rot).transpose();
            }
        }
        for f in 0..nf {
            if rw[f].is_some() && f != base {
                rw[f] = Some(so3::project_to_so3(&acc_w[f]));
            }
        }
    }
}

/// Linear initialisation of every extrinsic, rig pose and scene pose.
pub fn initialise(session: &Session, traj: &Trajectories) -> Result<InitOutput, InitError> {
    let nc = session.cameras.len();
    let r = session.reference;
    let by_cam: Vec<_> = (0..nc).map(|c| poses_by_scene(traj, c)).collect();

    // Classify the rig motion from the reference camera's relative motions.
    let mut ref_motions = Vec::new();
    for poses in by_cam[r].values() {
        let mut it = poses.values();
        if let Some(p0) = it.next() {
            for p in it {
                ref_motions.push(*p * p0.inverse());
            }
        }
    }
    if ref_motions.is_empty() {
        return Err(InitError::ReferenceNotObserved(
            session.cameras[r].id.clone(),
        ));
    }
    let motion = classify(&ref_motions);

    let mut stats = (0, 0, 0);
    let mut rot = vec![Mat3::identity(); nc];
    let mut groups = vec![Vec::new(); nc];
    for c in 0..nc {
        if c == r {
            continue;
        }
        let pairs = motion_pairs(&by_cam[r], &by_cam[c]);
        if pairs.is_empty() {
            return Err(InitError::CameraNotObserved(session.cameras[c].id.clone()));
        }
        rot[c] = rotation(&pairs, motion.class, &mut stats);
        groups[c] = pairs;
    }

    // Rotation graph over frames and scenes: world_from_scene = W_k · X_c · P.
    let nf = session.frames.len();
    let ns = traj.scenes.len();
    let mut edges: Vec<(usize, usize, usize, Pose)> = Vec::new(); // (frame, scene, cam, cam_from_scene)
    for (s, scene) in traj.scenes.iter().enumerate() {
        for (&(f, c), p) in &scene.poses {
            edges.push((f, s, c, *p));
        }
    }
    let mut rw: Vec<Option<Mat3>> = vec![None; nf];
    let mut rs: Vec<Option<Mat3>> = vec![None; ns];
    let base = edges
        .iter()
        .filter(|e| e.2 == r)
        .map(|e| e.0)
        .min()
        .unwrap_or(0);
    rw[base] = Some(Mat3::identity());
    loop {
        let mut changed = false;
        for &(f, s, c, p) in &edges {
            let m = rot[c] * p.rot;
            match (rw[f], rs[s]) {
                (Some(w), None) => {
                    rs[s] = Some(w * m);
                    changed = true;
                }
                (None, Some(sr)) => {
                    rw[f] = Some(sr * m.transpose());
                    changed = true;
                }
                _ => {}
            }
        }
        if !changed {
            break;
        }
    }
    let start = Graph {
        rot: rot.clone(),
        rw: rw.clone(),
        rs: rs.clone(),
    };
    chordal_refinement(&edges, &mut rot, &mut rw, &mut rs, base, r, None);
    if (0..nc).any(|c| angle(&rot[c], &start.rot[c]) > LINK_CONFLICT) {
        Graph { rot, rw, rs } = relink(&edges, &groups, Graph { rot, rw, rs }, start, base, r);
    }

    // Translations: unknowns [t_X (cams ≠ ref) | t_W (frames ≠ base) | t_S (scenes)].
    let cam_col: Vec<Option<usize>> = (0..nc)
        .scan(0, |n, c| {
            Some(if c == r {
                None
            } else {
                *n += 1;
                Some(*n - 1)
            })
        })
        .collect();
    let ncx = nc - 1;
    let frame_col: Vec<Option<usize>> = (0..nf)
        .scan(0, |n, f| {
            Some(if f == base || rw[f].is_none() {
                None
            } else {
                *n += 1;
                Some(ncx + *n - 1)
            })
        })
        .collect();
    let nfw = frame_col.iter().flatten().count();
    let scene_col = |s: usize| ncx + nfw + s;
    // A scene of known geometry (boards, tags) is in metres: its poses are used as they
    // are. Every other scene's scale is an unknown factor on its poses, solved with the
    // rest whenever some scene is metric. A scene split off a long chain has no scale
    // but the one the rig's motions give it. A scene scaled by measured distances is
    // only as good as the triangulation of the few points they join (1-2 % at 1 px on
    // the car presets, i.e. several centimetres on a camera 4 m from its scene's origin,
    // which the rotations then bent to absorb); the rig's rigid motion ties the scales
    // of all scenes together, so only their mean is taken from the distances (one row
    // below).
    let any_metric = traj
        .scenes
        .iter()
        .any(|s| s.scale.is_metric() && !s.poses.is_empty());
    let scale_col: Vec<Option<usize>> = traj
        .scenes
        .iter()
        .scan(0, |n, sc| {
            Some(
                if any_metric && !sc.poses.is_empty() && sc.scale != SceneScale::Bodies {
                    *n += 1;
                    Some(3 * (ncx + nfw + ns) + *n - 1)
                } else {
                    None
                },
            )
        })
        .collect();
    let metric_scale_cols: Vec<usize> = scale_col
        .iter()
        .zip(&traj.scenes)
        .filter(|(_, sc)| sc.scale == SceneScale::Distances)
        .filter_map(|(k, _)| *k)
        .collect();
    let dim = 3 * (ncx + nfw + ns) + scale_col.iter().flatten().count();
    let permutation = {
        let mut cams_per_scene: BTreeMap<usize, BTreeSet<usize>> = BTreeMap::new();
        for &(f, s, c, _) in &edges {
            if rw[f].is_some() && rs[s].is_some() {
                cams_per_scene.entry(s).or_default().insert(c);
            }
        }
        cams_per_scene.values().any(|cs| cs.len() > 1)
    };
    // Directions the motion class leaves undetermined (height along the plane normal;
    // every axis for rotation-degenerate motion) are only *nearly* null once the poses
    // are noisy, and plain least squares would amplify the noise along them by orders of
    // magnitude. A small Tikhonov term pulls them to `priors.height_offsets` (or 0),
    // weighted 1e-3 of the mean diagonal: negligible wherever the data constrain them,
    // which the rig bundle adjustment then corrects anyway.
    let n_axis = Vec3::from(motion.axis);
    let held: Vec<Vec3> = match motion.class {
        MotionClass::General => vec![],
        MotionClass::Planar => vec![n_axis],
        _ => vec![Vec3::x(), Vec3::y(), Vec3::z()],
    };
    let height_target = |c: usize| {
        if motion.class == MotionClass::Planar {
            session.height_priors[c]
        } else {
            None
        }
    };
    let height_source = (!held.is_empty()).then(|| {
        if (0..nc).any(|c| c != r && height_target(c).is_some()) {
            "prior"
        } else {
            "zero"
        }
    });
    // Translations (and scene scales) by linear least squares, rotations held.
    let x = {
        let mut ata = DMatrix::<f64>::zeros(dim, dim);
        let mut atb = DVector::<f64>::zeros(dim);
        for &(f, s, c, p) in &edges {
            let (Some(w), Some(_)) = (rw[f], rs[s]) else {
                continue;
            };
            // t_S − t_W − R_W t_X = σ_S R_W R_X t_P  (σ_S = 1 for metric scenes)
            let mut cols: Vec<(usize, Vec3)> = Vec::with_capacity(11);
            let mut block = |b: usize, m: Mat3| {
                for a in 0..3 {
                    cols.push((3 * b + a, m.column(a).into()));
                }
            };
            block(scene_col(s), Mat3::identity());
            if let Some(fc) = frame_col[f] {
                block(fc, -Mat3::identity());
            }
            if let Some(cc) = cam_col[c] {
                block(cc, -w);
            }
            let u = rot[c] * p.trans;
            let v = w * u;
            let rhs = match scale_col[s] {
                Some(k) => {
                    cols.push((k, -v));
                    Vec3::zeros()
                }
                None => v,
            };
            for (i, ci) in &cols {
                for (j, cj) in &cols {
                    ata[(*i, *j)] += ci.dot(cj);
                }
                atb[*i] += ci.dot(&rhs);
            }
        }
        let mean_diag = ata.trace() / dim.max(1) as f64;
        // Mean scale of the measured scenes = 1: a row 1e6 × heavier than any scale's
        // own data (a constraint, not a vote), and a feather-weight pull of every scale
        // to 1 for a scene whose scale no motion determines.
        let scale_w = scale_col
            .iter()
            .flatten()
            .map(|&k| ata[(k, k)])
            .fold(0.0, f64::max)
            .max(1.0);
        let heavy = 1e6 * scale_w;
        for &k in &metric_scale_cols {
            for &l in &metric_scale_cols {
                ata[(k, l)] += heavy;
            }
            atb[k] += heavy * metric_scale_cols.len() as f64;
        }
        for k in scale_col.iter().flatten() {
            ata[(*k, *k)] += 1e-9 * scale_w;
            atb[*k] += 1e-9 * scale_w;
        }
        if !held.is_empty() {
            let w2 = 1e-3 * mean_diag;
            for c in 0..nc {
                let Some(cc) = cam_col[c] else { continue };
                let target = height_target(c).unwrap_or(0.0);
                for d in &held {
                    for a in 0..3 {
                        for b in 0..3 {
                            ata[(3 * cc + a, 3 * cc + b)] += w2 * d[a] * d[b];
                        }
                        atb[3 * cc + a] += w2 * d[a] * target;
                    }
                }
            }
        }
        match ata.clone().cholesky() {
            Some(ch) => ch.solve(&atb),
            None => rigcal_core::linalg::symmetric_pseudo_inverse(&ata, 1e-12) * &atb,
        }
    };

    let ref_from_cam: Vec<Pose> = (0..nc)
        .map(|c| match cam_col[c] {
            None => Pose::identity(),
            Some(cc) => Pose::new(rot[c], Vec3::new(x[3 * cc], x[3 * cc + 1], x[3 * cc + 2])),
        })
        .collect();
    let world_from_rig = (0..nf)
        .map(|f| {
            let w = rw[f]?;
            let t = match frame_col[f] {
                Some(fc) => Vec3::new(x[3 * fc], x[3 * fc + 1], x[3 * fc + 2]),
                None => Vec3::zeros(),
            };
            Some(Pose::new(w, t))
        })
        .collect();
    let scene_scale: Vec<f64> = scale_col
        .iter()
        .map(|k| match k {
            Some(k) if x[*k].is_finite() && x[*k] > 0.0 => x[*k],
            _ => 1.0,
        })
        .collect();
    let world_from_scene = (0..ns)
        .map(|s| {
            let sc = scene_col(s);
            rs[s].map(|r| Pose::new(r, Vec3::new(x[3 * sc], x[3 * sc + 1], x[3 * sc + 2])))
        })
        .collect();
    Ok(InitOutput {
        ref_from_cam,
        world_from_rig,
        world_from_scene,
        scene_scale,
        motion,
        pairs_used: stats.0,
        pairs_dropped_small: stats.1,
        pairs_dropped_near_180: stats.2,
        permutation,
        height_source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A planar rig: the reference camera sees scene 0 in 12 frames, camera 1 (turned
    /// 90° about the plane normal) its own scene 1 in the same frames, and scene 0 once,
    /// through a pose turned 70° wrong. Alone, that link sets camera 1's turn; held by
    /// its motions (the prior) and weighed by agreement, it turns nothing.
    #[test]
    fn one_wrong_link_does_not_turn_a_camera_its_motions_hold() {
        let y = Vec3::y();
        let x1 = so3::exp(&(y * 90f64.to_radians()));
        let frames: Vec<Mat3> = (0..12)
            .map(|k| so3::exp(&(y * (6.0 * (k as f64 * 0.7).sin()).to_radians())))
            .collect();
        let scenes = [
            so3::exp(&Vec3::new(0.1, 0.4, -0.2)),
            so3::exp(&Vec3::new(-0.3, 1.9, 0.1)),
        ];
        let truth = [Mat3::identity(), x1];
        let pose = |r: Mat3| Pose::new(r, Vec3::zeros());
        // cam_from_scene = X_cᵀ W_fᵀ S_s.
        let mut edges = Vec::new();
        for (f, w) in frames.iter().enumerate() {
            edges.push((
                f,
                0,
                0,
                pose(truth[0].transpose() * w.transpose() * scenes[0]),
            ));
            edges.push((
                f,
                1,
                1,
                pose(truth[1].transpose() * w.transpose() * scenes[1]),
            ));
        }
        let wrong = so3::exp(&(y * 70f64.to_radians()));
        edges.push((
            3,
            0,
            1,
            pose(wrong * x1.transpose() * frames[3].transpose() * scenes[0]),
        ));
        let run = |prior: Option<&[Mat3]>| {
            let mut rot = truth.to_vec();
            let mut rw: Vec<Option<Mat3>> = frames.iter().map(|w| Some(*w)).collect();
            let mut rs: Vec<Option<Mat3>> = scenes.iter().map(|s| Some(*s)).collect();
            chordal_refinement(&edges, &mut rot, &mut rw, &mut rs, 0, 0, prior);
            angle(&rot[1], &x1).to_degrees()
        };
        let alone = run(None);
        assert!(
            alone > 30.0,
            "the wrong link alone turned camera 1 by {alone:.1}°"
        );
        let held = run(Some(&truth));
        assert!(
            held < 0.5,
            "held by its motions, camera 1 is {held:.2}° off"
        );
    }

    #[test]
    fn eq6_null_vector_is_the_rotation() {
        let x = Pose::from_rotvec(Vec3::new(0.3, -2.0, 0.4), Vec3::new(0.1, 0.2, -1.0));
        let pairs: Vec<(Pose, Pose)> = [
            Vec3::new(0.1, 0.2, 0.0),
            Vec3::new(0.0, -0.1, 0.3),
            Vec3::new(0.2, 0.0, -0.1),
        ]
        .iter()
        .map(|w| {
            let a = Pose::from_rotvec(*w, Vec3::new(0.3, -0.1, 0.2));
            (a, x.inverse() * a * x)
        })
        .collect();
        let r = rotation(&[pairs], MotionClass::General, &mut (0, 0, 0));
        assert!(so3::angle_between(&r, &x.rot) < 1e-9);
        // Planar: axes all parallel, eq. 10 resolves the rotation.
        let planar: Vec<(Pose, Pose)> = [(10.0f64, 0.3, 0.1), (-6.0, -0.2, 0.4), (4.0, 0.5, -0.3)]
            .iter()
            .map(|(d, tx, tz)| {
                let a = Pose::from_rotvec(
                    Vec3::new(0.0, d.to_radians(), 0.0),
                    Vec3::new(*tx, 0.0, *tz),
                );
                (a, x.inverse() * a * x)
            })
            .collect();
        let r = rotation(&[planar], MotionClass::Planar, &mut (0, 0, 0));
        assert!(
            so3::angle_between(&r, &x.rot) < 1e-9,
            "{}",
            so3::angle_between(&r, &x.rot)
        );
    }

    /// Motion pairs `(A, X⁻¹ A X)` of planar motions (yaw about y, translation in x-z),
    /// with B's translations scaled by `scale` (a scene of unknown scale).
    fn planar_pairs(x: &Pose, motions: &[(f64, f64, f64)], scale: f64) -> Vec<(Pose, Pose)> {
        motions
            .iter()
            .map(|(d, tx, tz)| {
                let a = Pose::from_rotvec(
                    Vec3::new(0.0, d.to_radians(), 0.0),
                    Vec3::new(*tx, 0.0, *tz),
                );
                let mut b = x.inverse() * a * *x;
                b.trans *= scale;
                (a, b)
            })
            .collect()
    }

    #[test]
    fn planar_rotation_is_exact_at_half_turns_across_scales_and_for_swinging_drives() {
        let x = Pose::from_rotvec(Vec3::new(0.3, -2.0, 0.4), Vec3::new(0.1, 0.2, -1.0));
        // Half-turns (a U-turn, a loop) are as good as any other turn.
        let loop_pairs = planar_pairs(
            &x,
            &[
                (179.5, 0.5, 3.0),
                (180.0, 1.0, 2.0),
                (90.0, 2.0, 1.0),
                (-135.0, -1.0, 2.0),
            ],
            1.0,
        );
        let r = rotation(
            std::slice::from_ref(&loop_pairs),
            MotionClass::Planar,
            &mut (0, 0, 0),
        );
        assert!(so3::angle_between(&r, &x.rot) < 1e-9);
        // A second group from a scene of another scale (a split-off rest of a loop).
        let rest = planar_pairs(&x, &[(20.0, 0.3, 1.0), (-40.0, 0.6, -0.5)], 0.37);
        let r = rotation(&[loop_pairs, rest], MotionClass::Planar, &mut (0, 0, 0));
        assert!(so3::angle_between(&r, &x.rot) < 1e-9);
        // A drive swinging left and right: the turns sum to nothing, so only the pairwise
        // vote can tell the sign of the axis of B from that of A.
        let swing = planar_pairs(
            &x,
            &[
                (10.0, 0.5, 0.1),
                (-10.0, 0.8, -0.2),
                (5.0, 1.2, 0.3),
                (-5.0, 1.6, 0.0),
            ],
            1.0,
        );
        let r = rotation(&[swing], MotionClass::Planar, &mut (0, 0, 0));
        assert!(
            so3::angle_between(&r, &x.rot) < 1e-9,
            "{}",
            so3::angle_between(&r, &x.rot)
        );
    }

    #[test]
    fn planar_rotation_error_under_noise_is_that_of_the_poses() {
        // 15 planar motions, each B perturbed by 0.1° and 5 mm: the rotation must come out
        // within a few tenths of a degree (eq. 10 against the largest motion gave 1-3°
        // on a loop at 1 px).
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let x = Pose::from_rotvec(Vec3::new(0.3, -2.0, 0.4), Vec3::new(0.5, 0.2, -1.5));
        let motions: Vec<(f64, f64, f64)> = (1..16)
            .map(|k| {
                (
                    22.5 * k as f64,
                    rng.gen_range(-2.0..2.0),
                    rng.gen_range(-2.0..2.0),
                )
            })
            .collect();
        let mut worst: f64 = 0.0;
        for _ in 0..20 {
            let pairs: Vec<(Pose, Pose)> = planar_pairs(&x, &motions, 1.0)
                .into_iter()
                .map(|(a, b)| {
                    let mut n = || rng.gen_range(-1.0..1.0);
                    let dr = Vec3::new(n(), n(), n()) * 0.1f64.to_radians();
                    let dt = Vec3::new(n(), n(), n()) * 0.005;
                    (a, Pose::new(so3::exp(&dr) * b.rot, b.trans + dt))
                })
                .collect();
            let r = rotation(&[pairs], MotionClass::Planar, &mut (0, 0, 0));
            worst = worst.max(so3::angle_between(&r, &x.rot).to_degrees());
        }
        assert!(worst < 0.3, "worst {worst}°");
    }
}
