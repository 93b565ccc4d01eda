//! Diagnostics of a refined rig: extrinsic covariance with the unobservable directions
//! removed, observable DOF per camera, the unobservable directions themselves, and
//! residual statistics. Observability is computed from the information matrix of the
//! actual problem, not read off Table 1 of the paper.

use super::rig_ba::RigBaOutput;
use crate::result::*;
use crate::session::Session;
use nalgebra::{DMatrix, DVector};

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
    let eig = crate::solver::eigen::symmetric_eigen(info);
    let lmax = eig.eigenvalues.amax().max(1e-300);
    (0..info.nrows())
        .filter(|&k| is_unobservable(eig.eigenvalues[k], lmax, decision_sigma))
        .map(|k| eig.eigenvectors.column(k).into_owned())
        .collect()
}

pub struct Observability {
    /// Per free camera (index into session cameras): covariance 6×6 (m, rad) with nulls removed.
    pub cov: Vec<(usize, DMatrix<f64>)>,
    /// Unit null directions in the joint space of the free cameras.
    pub null: Vec<(DVector<f64>, Option<f64>)>,
    pub cams: Vec<usize>,
    pub per_camera_eigen: Vec<Vec<f64>>,
}

pub fn observability(ba: &RigBaOutput) -> Option<Observability> {
    let (cams, info) = ba.information.clone()?;
    let n = info.nrows();
    let sym = (&info + info.transpose()) * 0.5;
    let eig = crate::solver::eigen::symmetric_eigen(&sym);
    let lmax = eig.eigenvalues.amax().max(1e-300);
    let sigma = if ba.sigma_px.is_finite() {
        ba.sigma_px
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
    let per_cov = cams
        .iter()
        .enumerate()
        .map(|(i, c)| (*c, cov.view((6 * i, 6 * i), (6, 6)).into_owned()))
        .collect();
    let per_camera_eigen = (0..cams.len())
        .map(|i| {
            let b = sym.view((6 * i, 6 * i), (6, 6)).into_owned();
            let b = crate::solver::eigen::symmetric_eigen(&b);
            let mut e: Vec<f64> = b.eigenvalues.iter().copied().collect();
            e.sort_by(|a, b| b.total_cmp(a));
            e
        })
        .collect();
    Some(Observability {
        cov: per_cov,
        null,
        cams,
        per_camera_eigen,
    })
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

/// Is axis `axis` of rows `[off, off+3)` touched by a null direction?
pub fn axis_unobservable(null: &[(DVector<f64>, Option<f64>)], off: usize, axis: usize) -> bool {
    null.iter().any(|(v, _)| v[off + axis].abs() > 0.1)
}

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
