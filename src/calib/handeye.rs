//! Linear initialisation of the extrinsics (Lébraly §3).
//!
//! Rotations, per camera: the null vector of the stacked `I₉ − R_A ⊗ R_B` (eq. 6-7) for
//! general motion; for planar motion eq. 10 (`ΔR t̃_B = t̃_A`, `ΔR n_B = n_A` and their
//! cross product) is concatenated and the least-squares solution re-orthogonalised; for
//! pure translation `ΔR t_B = t_A` (eq. 4b with `R_A = I`) by Procrustes.
//!
//! Translations, jointly for all cameras: every image that sees a scene gives
//! `world_from_scene = world_from_rig(k) · ref_from_cam(c) · cam_from_scene`, whose
//! translation part is linear in the unknown translations once rotations are known.
//! With one scene per camera this is eq. 8; when a camera sees another camera's scene
//! (U-turn) it contains eq. 19b, for any number of cameras. Directions the system
//! cannot determine (the height under planar motion) are set from `priors` or to 0 and
//! reported.

use super::motion::{classify, MotionClass, MotionReport, MIN_ROTATION};
use super::trajectory::Trajectories;
use crate::geometry::{so3, Mat3, Pose, Vec3};
use crate::session::Session;
use nalgebra::{DMatrix, DVector};
use std::collections::{BTreeMap, BTreeSet};

#[derive(Clone, Debug)]
pub struct InitOutput {
    pub ref_from_cam: Vec<Pose>,
    pub world_from_rig: Vec<Option<Pose>>,
    pub world_from_scene: Vec<Option<Pose>>,
    /// Factor taking each scene's coordinates to metres (1 for metric scenes).
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

/// Rows of `ΔR v_b = v_a` in row-major vec(ΔR).
fn vector_rows(vb: &Vec3, va: &Vec3, rows: &mut Vec<(Vec<f64>, f64)>) {
    for i in 0..3 {
        let mut r = vec![0.0; 9];
        for j in 0..3 {
            r[3 * i + j] = vb[j];
        }
        rows.push((r, va[i]));
    }
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

/// Relative motions `(A, B)` = (ref^k_from_ref^k0, cam^k_from_cam^k0) for camera `c`.
fn motion_pairs(
    refp: &BTreeMap<usize, BTreeMap<usize, Pose>>,
    camp: &BTreeMap<usize, BTreeMap<usize, Pose>>,
) -> Vec<(Pose, Pose)> {
    let mut out = Vec::new();
    for rs in refp.values() {
        for cs in camp.values() {
            let common: Vec<usize> = rs.keys().filter(|k| cs.contains_key(k)).copied().collect();
            let Some(&k0) = common.first() else { continue };
            for &k in &common[1..] {
                out.push((rs[&k] * rs[&k0].inverse(), cs[&k] * cs[&k0].inverse()));
            }
        }
    }
    out
}

/// Solve the rotation of one camera from its motion pairs.
fn rotation(pairs: &[(Pose, Pose)], class: MotionClass, stats: &mut (usize, usize, usize)) -> Mat3 {
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
    let mut rows: Vec<(Vec<f64>, f64)> = Vec::new();
    match class {
        MotionClass::General => {}
        MotionClass::Planar | MotionClass::SingleAxis => {
            // Eq. 10 around the motion with the largest rotation (index "1" of the paper).
            if let Some((i1, _)) = pairs.iter().enumerate().max_by(|x, y| {
                so3::log(&x.1 .0.rot)
                    .norm()
                    .total_cmp(&so3::log(&y.1 .0.rot).norm())
            }) {
                let (a1, b1) = pairs[i1];
                for (k, (a, b)) in pairs.iter().enumerate() {
                    let wa = so3::log(&a.rot);
                    let wb = so3::log(&b.rot);
                    if wa.norm() > MIN_ROTATION {
                        // The axis of a rotation is known to ∝ 1/sin θ: weight by sin θ.
                        let w = wa.norm().sin();
                        vector_rows(&(wb.normalize() * w), &(wa.normalize() * w), &mut rows);
                    }
                    if k == i1 {
                        continue;
                    }
                    let ta = (Mat3::identity() - a.rot) * a1.trans
                        - (Mat3::identity() - a1.rot) * a.trans;
                    let tb = (Mat3::identity() - b.rot) * b1.trans
                        - (Mat3::identity() - b1.rot) * b.trans;
                    let scale = 0.5 * (ta.norm() + tb.norm());
                    if scale < 1e-9 {
                        continue;
                    }
                    vector_rows(&(tb / scale), &(ta / scale), &mut rows);
                    if wa.norm() > MIN_ROTATION {
                        let (na, nb) = (wa.normalize(), wb.normalize());
                        vector_rows(
                            &(tb.cross(&nb) / scale),
                            &(ta.cross(&na) / scale),
                            &mut rows,
                        );
                    }
                }
            }
        }
        MotionClass::PureTranslation | MotionClass::None => {
            // ΔR t_B = t_A: Procrustes (Kabsch) on the translation directions.
            let mut h = Mat3::zeros();
            for (a, b) in pairs {
                h += a.trans * b.trans.transpose();
            }
            return so3::project_to_so3(&h);
        }
    }
    let n = l.len() * 9 + rows.len();
    let mut m = DMatrix::zeros(n, 9);
    let mut rhs = DVector::zeros(n);
    for (i, blk) in l.iter().enumerate() {
        m.view_mut((9 * i, 0), (9, 9)).copy_from(blk);
    }
    for (i, (r, b)) in rows.iter().enumerate() {
        for j in 0..9 {
            m[(l.len() * 9 + i, j)] = r[j];
        }
        rhs[l.len() * 9 + i] = *b;
    }
    let v = if rows.is_empty() {
        // Homogeneous: the null vector, scaled to det = +1 (eq. 7).
        super::pnp::null_vector(&m)
            .unwrap_or_else(|| DVector::from_row_slice(Mat3::identity().transpose().as_slice()))
    } else {
        // Least squares with a tiny pull towards the identity for directions no row fixes.
        let mut ata = m.transpose() * &m;
        let eps = 1e-12 * ata.trace().max(1e-12);
        for i in 0..9 {
            ata[(i, i)] += eps;
        }
        let id = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        let atb = m.transpose() * rhs + DVector::from_row_slice(&id) * eps;
        ata.cholesky()
            .map(|c| c.solve(&atb))
            .unwrap_or_else(|| DVector::from_row_slice(&id))
    };
    let vm = Mat3::from_row_slice(v.as_slice());
    let det = vm.determinant();
    let vm = if det != 0.0 {
        vm * det.signum() * det.abs().powf(-1.0 / 3.0)
    } else {
        vm
    };
    so3::project_to_so3(&vm)
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
    for c in 0..nc {
        if c == r {
            continue;
        }
        let pairs = motion_pairs(&by_cam[r], &by_cam[c]);
        if pairs.is_empty() {
            return Err(InitError::CameraNotObserved(session.cameras[c].id.clone()));
        }
        rot[c] = rotation(&pairs, motion.class, &mut stats);
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
    // Chordal refinement: alternate the averages of all edges (Gauss–Seidel sweeps).
    for _ in 0..10 {
        let mut acc_s = vec![Mat3::zeros(); ns];
        for &(f, s, c, p) in &edges {
            if let Some(w) = rw[f] {
                acc_s[s] += w * rot[c] * p.rot;
            }
        }
        for s in 0..ns {
            if rs[s].is_some() {
                rs[s] = Some(so3::project_to_so3(&acc_s[s]));
            }
        }
        let mut acc_w = vec![Mat3::zeros(); nf];
        for &(f, s, c, p) in &edges {
            if let Some(sr) = rs[s] {
                acc_w[f] += sr * (rot[c] * p.rot).transpose();
            }
        }
        for f in 0..nf {
            if rw[f].is_some() && f != base {
                rw[f] = Some(so3::project_to_so3(&acc_w[f]));
            }
        }
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
    // A scene without measured distances (one a long chain was split into) has its own
    // scale: an unknown factor on its poses, solved with the rest. Only when some scene
    // is metric; otherwise the overall scale has no anchor and every scene keeps its own.
    let any_metric = traj.scenes.iter().any(|s| s.metric && !s.poses.is_empty());
    let scale_col: Vec<Option<usize>> = traj
        .scenes
        .iter()
        .scan(0, |n, sc| {
            Some(if any_metric && !sc.metric && !sc.poses.is_empty() {
                *n += 1;
                Some(3 * (ncx + nfw + ns) + *n - 1)
            } else {
                None
            })
        })
        .collect();
    let dim = 3 * (ncx + nfw + ns) + scale_col.iter().flatten().count();
    let mut ata = DMatrix::<f64>::zeros(dim, dim);
    let mut atb = DVector::<f64>::zeros(dim);
    let mut any_foreign = BTreeSet::new();
    for &(f, s, c, p) in &edges {
        let (Some(w), Some(_)) = (rw[f], rs[s]) else {
            continue;
        };
        any_foreign.insert((s, c));
        // t_S − t_W − R_W t_X = σ_S R_W R_X t_P  (σ_S = 1 for metric scenes)
        let mut cols: Vec<(usize, Vec3)> = Vec::with_capacity(10);
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
        let v = w * rot[c] * p.trans;
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
    let permutation = {
        let mut cams_per_scene: BTreeMap<usize, BTreeSet<usize>> = BTreeMap::new();
        for (s, c) in &any_foreign {
            cams_per_scene.entry(*s).or_default().insert(*c);
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
    let mut height_source = None;
    if !held.is_empty() {
        let w2 = 1e-3 * ata.trace() / dim.max(1) as f64;
        let mut used_prior = false;
        for c in 0..nc {
            let Some(cc) = cam_col[c] else { continue };
            let h = if motion.class == MotionClass::Planar {
                session.height_priors[c]
            } else {
                None
            };
            used_prior |= h.is_some();
            for d in &held {
                let target = h.unwrap_or(0.0);
                for a in 0..3 {
                    for b in 0..3 {
                        ata[(3 * cc + a, 3 * cc + b)] += w2 * d[a] * d[b];
                    }
                    atb[3 * cc + a] += w2 * d[a] * target;
                }
            }
        }
        height_source = Some(if used_prior { "prior" } else { "zero" });
    }
    let x = match ata.clone().cholesky() {
        Some(ch) => ch.solve(&atb),
        None => crate::solver::bundle::symmetric_pseudo_inverse(&ata, 1e-12) * &atb,
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
        let r = rotation(&pairs, MotionClass::General, &mut (0, 0, 0));
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
        let r = rotation(&planar, MotionClass::Planar, &mut (0, 0, 0));
        assert!(
            so3::angle_between(&r, &x.rot) < 1e-9,
            "{}",
            so3::angle_between(&r, &x.rot)
        );
    }
}
