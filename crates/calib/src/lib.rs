//! Calibration estimators. Each file one estimator, tested beside it.

pub mod check;
pub mod diagnostics;
pub mod handeye;
pub mod link;
pub mod motion;
pub mod pnp;
pub mod rig_ba;
pub mod trajectory;
pub mod twoview;
pub mod undetermined;
pub mod vanishing;
pub mod verdict;

use rigcal_core::session::{PointKind, Session};
use rigcal_solve::bundle::{DistanceConstraint, PointRef};
use std::collections::HashMap;

/// Where session point `p` sits in a bundle problem whose free points and rigid bodies
/// were numbered by `points` and `bodies` (session index → problem index); `None` if
/// the problem does not contain it.
pub(crate) fn point_ref(
    kind: PointKind,
    p: usize,
    points: &HashMap<usize, usize>,
    bodies: &HashMap<usize, usize>,
) -> Option<PointRef> {
    match kind {
        PointKind::Free => points.get(&p).map(|&i| PointRef::Free(i)),
        PointKind::Body { body, local } => bodies
            .get(&body)
            .map(|&b| PointRef::Body { body: b, local }),
    }
}

/// The session's measured distances whose two points `point_ref` can place.
pub(crate) fn distance_constraints(
    session: &Session,
    point_ref: impl Fn(usize) -> Option<PointRef>,
) -> Vec<DistanceConstraint> {
    session
        .distances
        .iter()
        .filter_map(|d| {
            Some(DistanceConstraint {
                a: point_ref(d.a)?,
                b: point_ref(d.b)?,
                distance: d.distance,
                sigma: d.sigma,
            })
        })
        .collect()
}
