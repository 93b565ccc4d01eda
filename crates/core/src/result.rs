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

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
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

impl ExtrinsicValue {
    /// Camera `camera` at `ref_from_cam`, every field from the one pose (the inverse of
    /// [`ExtrinsicValue::pose`]).
    pub fn of(camera: &str, ref_from_cam: &crate::geometry::Pose) -> Self {
        use crate::geometry::so3;
        let (r, p, y) = so3::to_rpy(&ref_from_cam.rot);
        let t = ref_from_cam.trans;
        ExtrinsicValue {
            camera: camera.to_string(),
            ref_from_cam: ref_from_cam.matrix(),
            translation: [t.x, t.y, t.z],
            quaternion_wxyz: so3::to_quaternion(&ref_from_cam.rot),
            rpy_deg: [r.to_degrees(), p.to_degrees(), y.to_degrees()],
        }
    }

    /// `ref_from_cam` as a pose (from the 4×4 matrix, the field every format is built on).
    pub fn pose(&self) -> crate::geometry::Pose {
        let m = self.ref_from_cam;
        crate::geometry::Pose::new(
            nalgebra::Matrix3::new(
                m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2],
            ),
            nalgebra::Vector3::new(m[0][3], m[1][3], m[2][3]),
        )
    }
}

impl Status {
    /// The verdict from what was found: failed beats degraded beats succeeded.
    pub fn from_findings(fatal: bool, degrading: bool) -> Status {
        if fatal {
            Status::Failed
        } else if degrading {
            Status::Degraded
        } else {
            Status::Succeeded
        }
    }
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
    /// Statistics of the finite values (a residual that could not be computed is
    /// reported elsewhere, never as a `null` here).
    pub fn of(values: &[f64]) -> Stats {
        let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return Stats::default();
        }
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

impl Histogram {
    /// `bins` equal bins from 0 to the largest value.
    pub fn of(values: &[f64], bins: usize) -> Histogram {
        let maxv = values.iter().copied().fold(0.0, f64::max);
        let top = if maxv > 0.0 { maxv } else { 1.0 };
        let edges_px = (0..=bins).map(|i| top * i as f64 / bins as f64).collect();
        let mut counts = vec![0; bins];
        for e in values {
            counts[((e / top * bins as f64) as usize).min(bins - 1)] += 1;
        }
        Histogram { edges_px, counts }
    }
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

/// Chain closure error: how far the pair transforms chained round the ring miss the
/// reference before the global optimisation.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ClosureError {
    /// The closing pair (the auxiliary view not used by the chain).
    pub pair: [String; 2],
    pub translation_m: f64,
    pub rotation_deg: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PairReport {
    pub targets: [String; 2],
    /// Auxiliary views of this pair that were used (fused when more than one).
    pub views: usize,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct VanishingCamera {
    pub camera: String,
    pub target: String,
    /// Targets from the reference target to this camera's, in chain order.
    pub chain: Vec<String>,
    /// Pair transforms composed by the chainwise initialisation (eq. 23).
    pub chain_transforms: usize,
    /// The chainwise extrinsic (before the ring-closure optimisation).
    pub chainwise: ExtrinsicValue,
    pub chainwise_sigma_translation_m: [f64; 3],
    pub chainwise_sigma_rotation_deg: [f64; 3],
    /// 1-σ of this camera's own camera–target pose (camera frame): with the chain's, the
    /// two contributions to the extrinsic's σ.
    pub target_pose_sigma_translation_m: [f64; 3],
    pub target_pose_sigma_rotation_deg: [f64; 3],
    /// `vanishing_points`, or `homography` where a vanishing point was at infinity.
    pub initialised_from: String,
    /// Angle (deg) of the target's z and x line directions above the image plane; near 0
    /// puts the vanishing point at infinity.
    pub line_elevation_deg: [f64; 2],
    /// Point-to-line residuals (px) of this camera's own image.
    pub residuals: Stats,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RingViewReport {
    pub index: i64,
    pub targets: [String; 2],
    pub initialised_from: [String; 2],
    /// Point-to-line residuals (px) after the ring-closure optimisation.
    pub residuals: Stats,
}

/// What the vanishing method adds to the result document.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct VanishingReport {
    pub reference_target: String,
    /// Some auxiliary view closes a loop of targets (the ring constraint was used).
    pub ring_closed: bool,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub closure_error: Option<ClosureError>,
    pub pairs: Vec<PairReport>,
    pub cameras: Vec<VanishingCamera>,
    pub ring_views: Vec<RingViewReport>,
    /// Symmetric line grids: which way round each was labelled in each auxiliary view.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub labelling: Vec<LabellingReport>,
}

/// The labelling chosen for a symmetric target in one auxiliary view.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LabellingReport {
    pub ring_index: i64,
    pub target: String,
    /// Rotation about the target's centre relative to the detected labelling.
    pub rotation_deg: u32,
    /// `closure`, `rig_compactness` or `undetermined`.
    pub criterion: String,
    /// Runner-up score over best; `None` when there is no runner-up.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub margin: Option<f64>,
    pub clear: bool,
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
    /// Vanishing method only: chainwise vs global results, ring closure, per-view residuals.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vanishing: Option<VanishingReport>,
    /// The linear initialisation (motion) or the chainwise result (vanishing), for comparison with the refined extrinsics.
    pub initialisation: Vec<ExtrinsicValue>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub solver: Option<SolverReport>,
    pub stages: Vec<Stage>,
    /// Motion method: the rig (reference camera) at every frame the rig bundle adjustment
    /// used, in the rig frame of the first of them — the drive the dashboard draws.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub trajectory: Vec<RigPose>,
    /// Sessions of images: what detection found in each image, and the skipped ones.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub detection: Option<DetectionReport>,
}

/// The rig at one frame: `first_rig_from_rig` as translation (m) and quaternion.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RigPose {
    pub frame: i64,
    pub translation: [f64; 3],
    pub quaternion_wxyz: [f64; 4],
}

/// How much work detection spends on an image (`--detect-quality`, job option
/// `detection.quality`). `accurate`, the default, finds every tag a human could read at
/// ~0.01 px. `fast` searches the decimated image only, fits whole only the tags under
/// 30 px and measures sides with a third of the edge fits: about a third of the work on
/// dense scenes, at the price of some small oblique single tags and a corner error ~1.5×
/// larger (docs/performance.md, "Detection quality" and "`fast`'s edge measurement").
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DetectionQuality {
    Fast,
    #[default]
    Accurate,
}

impl DetectionQuality {
    pub fn as_str(self) -> &'static str {
        match self {
            DetectionQuality::Fast => "fast",
            DetectionQuality::Accurate => "accurate",
        }
    }
}

impl std::str::FromStr for DetectionQuality {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "fast" => Ok(DetectionQuality::Fast),
            "accurate" => Ok(DetectionQuality::Accurate),
            other => Err(format!("one of fast, accurate, got {other:?}")),
        }
    }
}

impl std::fmt::Display for DetectionQuality {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The detection stage's account of one image.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ImageReport {
    /// The manifest field naming the image (`frames[2].images.front`).
    pub field: String,
    pub camera: String,
    pub frame: i64,
    pub path: String,
    pub tags: usize,
    /// Of `tags`, those found through the AprilGrid layout (missed by the quad detector).
    pub tags_from_layout: usize,
    pub points: usize,
    /// Candidates refused, with why (duplicate id, not on any target, edges unmeasurable).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub rejected: Vec<String>,
    /// Why the image was skipped (unreadable, not an image, wrong size, too large).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Its bytes could not be read at all (a missing file, a lost blob): the input's
    /// fault, not the capture's.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub unreadable: bool,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DetectionReport {
    /// The quality the images were detected at (images reused from their upload were
    /// detected at `accurate`, the upload's quality).
    #[serde(default)]
    pub quality: DetectionQuality,
    pub images_total: usize,
    pub images_skipped: usize,
    pub points_total: usize,
    pub seconds: f64,
    /// Of `images_total`, those whose detections were made when the image was uploaded
    /// (same bytes, same detector) and reused rather than detected again.
    #[serde(default)]
    pub images_reused: usize,
    pub images: Vec<ImageReport>,
}

impl DetectionReport {
    /// The report of these images' outcomes (no time measured, none reused).
    pub fn of(images: Vec<ImageReport>) -> DetectionReport {
        DetectionReport {
            quality: DetectionQuality::default(),
            images_total: images.len(),
            images_skipped: images.iter().filter(|r| r.error.is_some()).count(),
            points_total: images.iter().map(|r| r.points).sum(),
            seconds: 0.0,
            images_reused: 0,
            images,
        }
    }
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
