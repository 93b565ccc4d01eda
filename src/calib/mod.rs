//! Calibration estimators. Each file one estimator, tested beside it.

pub mod check;
pub mod diagnostics;
pub mod handeye;
pub mod motion;
pub mod pnp;
pub mod rig_ba;
pub mod trajectory;
pub mod twoview;
pub mod vanishing;

use crate::session::PointKind;
use crate::solver::bundle::PointRef;
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
