//! The result document: what `rigcal calibrate` prints and `GET /v1/jobs/{id}/result`
//! returns. One definition for both, documented in `docs/formats.md`.

use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    Succeeded,
    Degraded,
    Failed,
}

impl Status {
    pub fn as_str(&self) -> &'static str {
        match self {
            Status::Succeeded => "succeeded",
            Status::Degraded => "degraded",
            Status::Failed => "failed",
        }
    }
}

/// A stable reason code with a human message (and the camera concerned, if any).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Reason {
    pub code: String,
    pub message: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera: Option<String>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ObservableDof {
    pub rotation: u8,
    pub translation: u8,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ExtrinsicValue {
    pub camera: String,
    /// 4×4 `ref_from_cam`, row-major: maps camera coordinates to reference-camera coordinates.
    pub ref_from_cam: [[f64; 4]; 4],
    /// Metres, in the reference camera frame.
    pub translation: [f64; 3],
    /// Unit quaternion (w, x, y, z) of the rotation of `ref_from_cam`.
    pub quaternion_wxyz: [f64; 4],
    /// Roll, pitch, yaw in degrees: `R = Rz(yaw)·Ry(pitch)·Rx(roll)`.
    pub rpy_deg: [f64; 3],
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Extrinsic {
    #[serde(flatten)]
    pub value: ExtrinsicValue,
    /// 1-σ of the translation (m) along the reference axes; `null` where unobservable.
    pub sigma_translation_m: [Option<f64>; 3],
    /// 1-σ of the rotation (deg) about the reference axes; `null` where unobservable.
    pub sigma_rotation_deg: [Option<f64>; 3],
    pub observable_dof: ObservableDof,
    /// Full 6×6 covariance of `[dt (m), dφ (rad)]` (left perturbation in the reference
    /// frame: `t ← t + dt`, `R ← exp(dφ)·R`), unobservable directions removed; `null`
    /// for the reference camera.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub covariance: Option<[[f64; 6]; 6]>,
}

#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Stats {
    pub count: usize,
    pub rms: f64,
    pub median: f64,
    pub p95: f64,
    pub max: f64,
}

impl Stats {
    pub fn of(values: &[f64]) -> Stats {
        if values.is_empty() {
            return Stats::default();
        }
        let mut v = values.to_vec();
        v.sort_by(f64::total_cmp);
        let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
        Stats {
            count: v.len(),
            rms: (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt(),
            median: q(0.5),
            p95: q(0.95),
            max: v[v.len() - 1],
        }
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CameraStats {
    pub camera: String,
    #[serde(flatten)]
    pub stats: Stats,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FrameStats {
    pub frame: i64,
    #[serde(flatten)]
    pub stats: Stats,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Histogram {
    /// Bin edges in pixels (one more than `counts`); the last bin is open-ended.
    pub edges_px: Vec<f64>,
    pub counts: Vec<usize>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Outlier {
    pub frame: i64,
    pub camera: String,
    pub point: String,
    pub residual_px: f64,
}

/// Reprojection residual norms (pixels) of the inliers, after refinement.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Residuals {
    #[serde(flatten)]
    pub all: Stats,
    pub inliers: usize,
    pub outliers: usize,
    /// Estimated pixel noise σ (from the inlier cost and the degrees of freedom).
    pub sigma_px: f64,
    pub per_camera: Vec<CameraStats>,
    pub per_frame: Vec<FrameStats>,
    pub histogram: Histogram,
    pub outlier_list: Vec<Outlier>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DirectionComponent {
    pub camera: String,
    /// Translation part of the direction (reference frame).
    pub translation: [f64; 3],
    /// Rotation part of the direction (axis scaled, reference frame).
    pub rotation: [f64; 3],
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct UnobservableDirection {
    /// The unit vector in the joint extrinsic space, split per camera.
    pub components: Vec<DirectionComponent>,
    /// 1-σ along this direction at the estimated pixel noise (m or rad), `null` if none.
    pub sigma: Option<f64>,
    pub description: String,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CameraObservability {
    pub camera: String,
    pub observable_dof: ObservableDof,
    /// Eigenvalues of this camera's 6×6 marginal information (1/px² units, [m, rad]).
    pub information_eigenvalues: Vec<f64>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Singularity {
    pub motion_class: String,
    /// Motion-plane normal (planar) or principal rotation axis, reference frame.
    pub axis: [f64; 3],
    pub motions: usize,
    pub informative_motions: usize,
    pub max_rotation_deg: f64,
    pub max_out_of_axis_deg: f64,
    pub scene_permutation: bool,
    pub motion_pairs_used: usize,
    pub motion_pairs_dropped_small_rotation: usize,
    pub motion_pairs_dropped_near_180: usize,
    pub per_camera: Vec<CameraObservability>,
    pub unobservable_directions: Vec<UnobservableDirection>,
    /// What resolved the singular directions: `scene_permutation`, `prior`, or `none`.
    pub resolved_by: Vec<String>,
    pub recommendations: Vec<String>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SolverReport {
    pub iterations: usize,
    pub initial_cost: f64,
    pub final_cost: f64,
    pub converged: bool,
    pub termination: String,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Stage {
    pub name: String,
    pub seconds: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ResultDocument {
    pub rigcal_version: String,
    pub method: String,
    pub status: Status,
    pub reasons: Vec<Reason>,
    pub reference_camera: String,
    pub extrinsics: Vec<Extrinsic>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub residuals: Option<Residuals>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub singularity: Option<Singularity>,
    /// The linear initialisation, for comparison with the refined extrinsics.
    pub initialisation: Vec<ExtrinsicValue>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub solver: Option<SolverReport>,
    pub stages: Vec<Stage>,
}

impl ResultDocument {
    /// The CLI's exit code for this verdict.
    pub fn exit_code(&self) -> i32 {
        match self.status {
            Status::Succeeded => 0,
            Status::Degraded => 3,
            Status::Failed => 1,
        }
    }
}
