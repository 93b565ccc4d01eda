//! Diagnostics of a refined rig: extrinsic covariance with the unobservable directions
//! removed, observable DOF per camera, the unobservable directions themselves, and
//! residual statistics. Observability is computed from the information matrix of the
//! actual problem, not read off Table 1 of the paper.

use super::handeye::InitOutput;
use super::motion::MotionClass;
use super::rig_ba::RigBaOutput;
use super::trajectory::Trajectories;
use nalgebra::{DMatrix, DVector};
use rigcal_core::geometry::{Vec2, Vec3};
use rigcal_core::result::*;
use rigcal_core::session::Session;
use rigcal_solve::bundle::{BundleProblem, Obs};
use std::collections::BTreeMap;

/// A direction is unobservable when its 1-σ (at ≥ 0.1 px noise) exceeds this many
/// metres (translation) or radians (rotation), or its eigenvalue is numerically zero.
pub const UNOBSERVABLE_SIGMA: f64 = 0.5;
/// Relative eigenvalue below which a direction carries no information at all.
pub const NULL_RELATIVE: f64 = 1e-9;
/// Floor of the pixel noise used for the observability decision (noise-free data
/// would otherwise make every direction look perfectly determined).
pub const MIN_DECISION_SIGMA_PX: f64 = 0.1;

fn is_unobservable(l: f64, lmax: f64, decision_sigma: f64) -> bool {
    l <= NULL_RELATIVE * lmax
        || decision_sigma.max(MIN_DECISION_SIGMA_PX) / l.max(1e-300).sqrt() > UNOBSERVABLE_SIGMA
}

/// Unit directions of the joint extrinsic space that the information `info` (unit
/// pixel noise) does not determine at pixel noise `decision_sigma`.
pub fn null_directions(info: &DMatrix<f64>, decision_sigma: f64) -> Vec<DVector<f64>> {
    let eig = rigcal_core::linalg::symmetric_eigen(info);
    let lmax = eig.eigenvalues.amax().max(1e-300);
    (0..info.nrows())
        .filter(|&k| is_unobservable(eig.eigenvalues[k], lmax, decision_sigma))
        .map(|k| eig.eigenvectors.column(k).into_owned())
        .collect()
}

/// [`null_directions`] made orthogonal to the directions already `held` (unit vectors
/// in the same space), those left with under half their length dropped.
pub fn null_directions_besides(
    info: &DMatrix<f64>,
    decision_sigma: f64,
    held: &[DVector<f64>],
) -> Vec<DVector<f64>> {
    let null = null_directions(info, decision_sigma);
    orthogonalised(held, null.into_iter().map(|v| (v, ())))
        .into_iter()
        .map(|(v, _)| v)
        .collect()
}

/// Directions that planar motion leaves undetermined whatever the noise. The rig turns
/// only about the plane normal `n`, so a camera moved along `n` (rig frame) sees its
/// scene displaced by the same world vector at every pose, which displacing that scene
/// undoes; only a scene shared with a camera that stays put ties the height. So: one
/// direction per group of cameras linked by shared scenes, the reference's group
/// excepted — all of the group's cameras along `n`. Unit vectors in the joint space of
/// the free cameras `cams` (6 per camera: translation, then rotation); empty unless the
/// motion is planar.
///
/// The numerical information cannot be trusted to find these at the initialisation:
/// there the rig's rotation axes scatter by the trajectories' noise, which makes each
/// height look determined to centimetres by thousands of corners, while the data hold
/// no information on it at all.
pub fn planar_height_directions(
    traj: &Trajectories,
    init: &InitOutput,
    reference: usize,
    cams: &[usize],
) -> Vec<DVector<f64>> {
    if init.motion.class != MotionClass::Planar {
        return vec![];
    }
    let n = Vec3::from(init.motion.axis).normalize();
    let group = traj.linked_cameras(init.ref_from_cam.len());
    let fixed = group[reference];
    let mut by_group: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for (i, &c) in cams.iter().enumerate() {
        let g = group[c];
        if g != fixed {
            by_group.entry(g).or_default().push(i);
        }
    }
    by_group
        .into_values()
        .map(|members| {
            let mut v = DVector::zeros(6 * cams.len());
            for i in members {
                v.fixed_rows_mut::<3>(6 * i).copy_from(&n);
            }
            v.normalize()
        })
        .collect()
}

/// `dirs` made orthogonal to the unit vectors `against` and to each other (those left
/// with less than half their length are dropped), each kept with its tag.
pub fn orthogonalised<T>(
    against: &[DVector<f64>],
    dirs: impl IntoIterator<Item = (DVector<f64>, T)>,
) -> Vec<(DVector<f64>, T)> {
    let mut basis: Vec<DVector<f64>> = against.to_vec();
    let mut out = Vec::new();
    for (v, tag) in dirs {
        let mut u = v;
        for b in &basis {
            let d = b.dot(&u);
            u -= b * d;
        }
        if u.norm() > 0.5 {
            let u = u.normalize();
            basis.push(u.clone());
            out.push((u, tag));
        }
    }
    out
}

pub struct Observability {
    /// Per free camera (index into session cameras): covariance 6×6 (m, rad) with nulls removed.
    pub cov: Vec<(usize, DMatrix<f64>)>,
    /// Unit null directions in the joint space of the free cameras: first the planar
    /// heights ([`planar_height_directions`], `held` of them), then the others.
    pub null: Vec<(DVector<f64>, Option<f64>)>,
    pub held: usize,
    pub cams: Vec<usize>,
    pub per_camera_eigen: Vec<Vec<f64>>,
}

/// `sigma_floor_px`: the least corner noise the covariance assumes (see
/// `pipeline::detected_corner_sigma_floor_px`); `corner_scale_sigma`: the relative scale
/// error of each camera's corners about its principal point the covariance allows for
/// besides (0: none; see [`corner_scale_covariance`]).
pub fn observability(
    ba: &RigBaOutput,
    sigma_floor_px: f64,
    corner_scale_sigma: f64,
) -> Option<Observability> {
    let (cams, info) = ba.information.clone()?;
    let n = info.nrows();
    let sym = (&info + info.transpose()) * 0.5;
    // The planar heights carry no information whatever the numbers say: taken out of
    // the information, so the covariance excludes them and they lead the null list.
    let held = &ba.held_directions;
    let keep = held
        .iter()
        .fold(DMatrix::identity(n, n), |p, s| p - s * s.transpose());
    let eig = rigcal_core::linalg::symmetric_eigen(&(&keep * &sym * &keep));
    let lmax = eig.eigenvalues.amax().max(1e-300);
    let sigma = if ba.sigma_px.is_finite() {
        ba.sigma_px.max(sigma_floor_px)
    } else {
        1.0
    };
    let mut cov = DMatrix::zeros(n, n);
    let mut null = Vec::new();
    for k in 0..n {
        let l = eig.eigenvalues[k];
        let v = eig.eigenvectors.column(k).into_owned();
        if is_unobservable(l, lmax, sigma) {
            let s = if l > NULL_RELATIVE * lmax {
                Some(sigma / l.sqrt())
            } else {
                None
            };
            null.push((v, s));
        } else {
            cov += &v * v.transpose() * (sigma * sigma / l);
        }
    }
    if corner_scale_sigma > 0.0 {
        // Along the observable directions only: the others are reported as null.
        let observable = (0..n)
            .filter(|&k| !is_unobservable(eig.eigenvalues[k], lmax, sigma))
            .map(|k| eig.eigenvectors.column(k).into_owned())
            .fold(DMatrix::zeros(n, n), |p, v| p + &v * v.transpose());
        let scale = corner_scale_covariance(&ba.problem, &cams, corner_scale_sigma)?;
        cov += &observable * scale * &observable;
    }
    let per_cov = cams
        .iter()
        .enumerate()
        .map(|(i, c)| (*c, cov.view((6 * i, 6 * i), (6, 6)).into_owned()))
        .collect();
    let per_camera_eigen = (0..cams.len())
        .map(|i| {
            let b = sym.view((6 * i, 6 * i), (6, 6)).into_owned();
            let b = rigcal_core::linalg::symmetric_eigen(&b);
            let mut e: Vec<f64> = b.eigenvalues.iter().copied().collect();
            e.sort_by(|a, b| b.total_cmp(a));
            e
        })
        .collect();
    let mut all: Vec<(DVector<f64>, Option<f64>)> =
        held.iter().map(|s| (s.clone(), None)).collect();
    all.extend(orthogonalised(held, null));
    Some(Observability {
        cov: per_cov,
        null: all,
        held: held.len(),
        cams,
        per_camera_eigen,
    })
}

/// Covariance (joint, over the free cameras `cams`) of the extrinsics that a relative
/// scale error of σ `scale_sigma` in each camera's corners about its principal point
/// causes, one error per camera, independent between cameras.
///
/// Why: a systematic error that every corner of a camera shares does not average down
/// over thousands of corners the way their noise does, and where the extrinsics are
/// determined to 10⁻⁶ (a fisheye pair seeing 12 000 corners) a scale of 10⁻⁶ is as
/// large as their σ. A focal length a few ppm off is such a scale, and so is a radial
/// bias of the detector (docs/accuracy.md, "The whole covariance on images").
/// `None` when the state cannot be linearised, or when its free cameras are not `cams`
/// (an internal inconsistency).
pub fn corner_scale_covariance(
    problem: &BundleProblem,
    cams: &[usize],
    scale_sigma: f64,
) -> Option<DMatrix<f64>> {
    let about = |c: usize, o: &Obs| {
        if o.cam == c {
            let cam = &problem.cameras[c];
            o.uv - Vec2::new(cam.cx, cam.cy)
        } else {
            Vec2::zeros()
        }
    };
    let (free, sens) = problem.extrinsic_sensitivities(problem.cameras.len(), about)?;
    if free != cams {
        return None;
    }
    let n = 6 * cams.len();
    Some(
        sens.iter()
            .fold(DMatrix::zeros(n, n), |c, v| c + v * v.transpose())
            * (scale_sigma * scale_sigma),
    )
}

/// Rank of the null directions restricted to rows `[off, off+3)`: DOF lost there.
pub fn lost_dof(null: &[(DVector<f64>, Option<f64>)], off: usize) -> u8 {
    if null.is_empty() {
        return 0;
    }
    let m = DMatrix::from_fn(3, null.len(), |i, j| null[j].0[off + i]);
    let sv = m.singular_values();
    sv.iter().filter(|s| **s > 0.1).count() as u8
}

/// Is axis `axis` of rows `[off, off+3)` touched by a null direction? An axis with a
/// component of 1 % along a held direction moves by 1 % of whatever that direction is
/// off by (a held height: decimetres), which no σ of the observable part describes.
/// A height shared by two cameras along a plane normal tilted 8° from a camera's y
/// axis touches its z axis by 0.10: a threshold of 0.1 reported σ 0.5 mm there while
/// the axis was 31 mm off.
pub fn axis_unobservable(null: &[(DVector<f64>, Option<f64>)], off: usize, axis: usize) -> bool {
    null.iter().any(|(v, _)| v[off + axis].abs() > AXIS_TOUCHED)
}

/// Smallest component of a unit null direction on an axis that makes the axis
/// unobservable (numerical null directions are exact to far better than this).
const AXIS_TOUCHED: f64 = 0.01;

pub fn residual_report(session: &Session, ba: &RigBaOutput) -> Residuals {
    let nc = session.cameras.len();
    let mut all = Vec::new();
    let mut per_cam = vec![Vec::new(); nc];
    let mut per_frame: std::collections::BTreeMap<usize, Vec<f64>> = Default::default();
    for (o, k) in ba.problem.observations.iter().zip(&ba.keys) {
        if let Some(r) = ba.problem.residual(o) {
            let e = r.norm();
            all.push(e);
            per_cam[k.camera].push(e);
            per_frame.entry(k.frame).or_default().push(e);
        }
    }
    Residuals {
        all: Stats::of(&all),
        inliers: all.len(),
        outliers: ba.outliers.len(),
        sigma_px: ba.sigma_px,
        per_camera: (0..nc)
            .map(|c| CameraStats {
                camera: session.cameras[c].id.clone(),
                stats: Stats::of(&per_cam[c]),
            })
            .collect(),
        per_frame: per_frame
            .into_iter()
            .map(|(f, v)| FrameStats {
                frame: session.frames[f].index,
                stats: Stats::of(&v),
            })
            .collect(),
        histogram: Histogram::of(&all, 20),
        outlier_list: ba
            .outliers
            .iter()
            .map(|(k, e)| Outlier {
                frame: session.frames[k.frame].index,
                camera: session.cameras[k.camera].id.clone(),
                point: session.points.ids[k.point].clone(),
                residual_px: *e,
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One height shared by two cameras, along a plane normal tilted 8° towards the
    /// cameras' z axes: both cameras' y and z translations are unobservable, their x
    /// and every rotation are not.
    #[test]
    fn a_height_shared_by_two_cameras_touches_both_their_y_and_z() {
        let n = Vec3::new(0.0, 8f64.to_radians().cos(), 8f64.to_radians().sin());
        let mut v = DVector::zeros(12);
        v.fixed_rows_mut::<3>(0).copy_from(&n);
        v.fixed_rows_mut::<3>(6).copy_from(&n);
        let null = [(v.normalize(), None)];
        for cam in [0, 6] {
            assert!(!axis_unobservable(&null, cam, 0));
            assert!(axis_unobservable(&null, cam, 1));
            assert!(axis_unobservable(&null, cam, 2), "z of the camera at {cam}");
            for a in 0..3 {
                assert!(!axis_unobservable(&null, cam + 3, a));
            }
        }
    }
}
