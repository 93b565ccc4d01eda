//! Motion classification (Lébraly Table 1), computed from the rig's relative motions
//! as measured by the reference camera, not assumed.

use rigcal_core::geometry::{so3, Mat3, Pose, Vec3};
use serde::Serialize;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum MotionClass {
    General,
    Planar,
    SingleAxis,
    PureTranslation,
    None,
}

impl MotionClass {
    pub fn as_str(&self) -> &'static str {
        match self {
            MotionClass::General => "general",
            MotionClass::Planar => "planar",
            MotionClass::SingleAxis => "single_axis",
            MotionClass::PureTranslation => "pure_translation",
            MotionClass::None => "none",
        }
    }
}

/// Rotations smaller than this carry no axis information.
pub const MIN_ROTATION: f64 = 0.3 * std::f64::consts::PI / 180.0;
/// Rotation components off the principal axis above this make the motion 3D. A speed
/// bump tilts by degrees; pose noise alone reaches a few tenths of a degree where the
/// scene is far and a pose's rotation is measured to ~0.2° (a 360° loop at 1 px: up to
/// 0.53° over 40 trials, twice a pose's error at half turns, where a tilt doubles).
pub const OUT_OF_AXIS: f64 = 1.0 * std::f64::consts::PI / 180.0;

#[derive(Clone, Debug, Serialize)]
pub struct MotionReport {
    pub class: MotionClass,
    /// Number of relative motions analysed, and how many rotate by more than 0.3°.
    pub motions: usize,
    pub informative_motions: usize,
    /// Largest rotation angle of the rig between two frames (deg).
    pub max_rotation_deg: f64,
    /// Largest tilt of the common rotation axis by any motion (deg): 0 for planar motion.
    pub max_out_of_axis_deg: f64,
    /// Principal rotation axis (the motion-plane normal when planar), reference frame.
    pub axis: [f64; 3],
    /// RMS distance (m) of the motions from one fixed rotation axis: ~0 for single-axis.
    pub axis_line_rms_m: f64,
}

/// The unit axis shared by rotations, and the largest eigenvalue (0 when none turns).
/// It minimises Σ|R_k n − n|²: the smallest eigenvector of Σ (R_k − I)ᵀ(R_k − I).
/// Unlike the axis of log(R_k), ill-conditioned near 180° (a U-turn, a loop), this is
/// well conditioned at every angle. Its sign is arbitrary.
pub fn common_axis<'a>(rots: impl Iterator<Item = &'a Mat3>) -> (Vec3, f64) {
    let mut m = Mat3::zeros();
    for r in rots {
        let d = r - Mat3::identity();
        m += d.transpose() * d;
    }
    let (values, vectors) = rigcal_core::linalg::symmetric_eigen3(&m);
    (vectors.column(values.imin()).into(), values.max())
}

/// Classify motions `ref^k_from_ref^k0` (in the reference camera's frame).
pub fn classify(motions: &[Pose]) -> MotionReport {
    let ws: Vec<Vec3> = motions.iter().map(|m| so3::log(&m.rot)).collect();
    let informative = ws.iter().filter(|w| w.norm() > MIN_ROTATION).count();
    let max_rot = ws.iter().map(|w| w.norm()).fold(0.0, f64::max);
    let max_t = motions.iter().map(|m| m.trans.norm()).fold(0.0, f64::max);
    let (n, _) = common_axis(motions.iter().map(|m| &m.rot));
    let n = if n.z < 0.0 { -n } else { n };
    // Tilt of each motion: the angle by which it moves the axis, 0 for rotations about n.
    let out_of_axis = motions
        .iter()
        .map(|mo| (mo.rot * n).dot(&n).clamp(-1.0, 1.0).acos())
        .fold(0.0, f64::max);
    // Fit one rotation axis line: (I − R_k) c = t_k⊥ for all k.
    let mut a = Mat3::zeros();
    let mut b = Vec3::zeros();
    for m in motions {
        let i_r = Mat3::identity() - m.rot;
        let t_perp = m.trans - n * m.trans.dot(&n);
        a += i_r.transpose() * i_r;
        b += i_r.transpose() * t_perp;
    }
    let c = rigcal_core::linalg::symmetric_pseudo_inverse(
        &nalgebra::DMatrix::from_column_slice(3, 3, a.as_slice()),
        1e-9,
    ) * nalgebra::DVector::from_column_slice(b.as_slice());
    let c = Vec3::new(c[0], c[1], c[2]);
    let line_rms = if motions.is_empty() {
        0.0
    } else {
        (motions
            .iter()
            .map(|m| {
                ((Mat3::identity() - m.rot) * c - (m.trans - n * m.trans.dot(&n))).norm_squared()
            })
            .sum::<f64>()
            / motions.len() as f64)
            .sqrt()
    };
    let t_rms = if motions.is_empty() {
        0.0
    } else {
        (motions
            .iter()
            .map(|m| (m.trans - n * m.trans.dot(&n)).norm_squared())
            .sum::<f64>()
            / motions.len() as f64)
            .sqrt()
    };
    let class = if informative == 0 {
        if max_t > 1e-3 {
            MotionClass::PureTranslation
        } else {
            MotionClass::None
        }
    } else if out_of_axis > OUT_OF_AXIS {
        MotionClass::General
    } else if line_rms < f64::max(0.01, 0.02 * t_rms) {
        MotionClass::SingleAxis
    } else {
        MotionClass::Planar
    };
    MotionReport {
        class,
        motions: motions.len(),
        informative_motions: informative,
        max_rotation_deg: max_rot.to_degrees(),
        max_out_of_axis_deg: out_of_axis.to_degrees(),
        axis: [n.x, n.y, n.z],
        axis_line_rms_m: line_rms,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn yaw(x: f64, y: f64, deg: f64) -> Pose {
        Pose::from_rotvec(Vec3::new(0.0, deg.to_radians(), 0.0), Vec3::new(x, 0.0, y))
    }

    #[test]
    fn classes() {
        let planar = vec![
            yaw(0.1, 0.5, 10.0),
            yaw(-0.4, 0.2, -7.0),
            yaw(0.3, -0.3, 4.0),
        ];
        let r = classify(&planar);
        assert_eq!(r.class, MotionClass::Planar);
        assert!((Vec3::from(r.axis).dot(&Vec3::y()).abs() - 1.0).abs() < 1e-9);
        let mut general = planar.clone();
        general.push(Pose::from_rotvec(
            Vec3::new(0.05, 0.1, 0.0),
            Vec3::new(0.1, 0.1, 0.1),
        ));
        assert_eq!(classify(&general).class, MotionClass::General);
        let trans = vec![
            Pose::from_rotvec(Vec3::zeros(), Vec3::new(0.5, 0.0, 0.1)),
            Pose::from_rotvec(Vec3::zeros(), Vec3::new(0.0, 0.0, 1.0)),
        ];
        assert_eq!(classify(&trans).class, MotionClass::PureTranslation);
        // Rotation about a fixed vertical line through (1, 0, 2): t = (I − R) c.
        let c = Vec3::new(1.0, 0.0, 2.0);
        let single: Vec<Pose> = [10.0f64, -15.0, 25.0]
            .iter()
            .map(|d| {
                let r = so3::exp(&Vec3::new(0.0, d.to_radians(), 0.0));
                Pose::new(r, (Mat3::identity() - r) * c)
            })
            .collect();
        assert_eq!(classify(&single).class, MotionClass::SingleAxis);
    }
}
