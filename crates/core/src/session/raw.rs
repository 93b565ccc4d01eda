//! The session manifest as it travels (JSON). See `docs/formats.md`.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SessionManifest {
    #[serde(default = "default_version")]
    pub version: u32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vehicle_id: Option<String>,
    /// The vehicle model (`PUT /v1/vehicle-models/{model}`) whose nominal rig and
    /// tolerances the result is judged against.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vehicle_model: Option<String>,
    #[serde(default)]
    pub method: Method,
    pub reference_camera: String,
    pub cameras: Vec<CameraSpec>,
    #[serde(default)]
    pub targets: Vec<TargetSpec>,
    #[serde(default)]
    pub scale: Vec<ScaleSpec>,
    #[serde(default)]
    pub frames: Vec<FrameSpec>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub priors: Option<Priors>,
    /// Vanishing method: the hand-held camera that photographs neighbouring target pairs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub auxiliary_camera: Option<CameraSpec>,
    /// Vanishing method: the auxiliary camera's views, each of (at least) two targets.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub ring: Vec<RingSpec>,
}

fn default_version() -> u32 {
    1
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    #[default]
    Motion,
    Vanishing,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    pub id: String,
    pub model: String,
    pub width: u32,
    pub height: u32,
    pub intrinsics: Intrinsics,
    #[serde(default)]
    pub distortion: Vec<f64>,
}

#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum TargetSpec {
    /// Kalibr AprilGrid: `rows × cols` tags of side `tag_size` (m), gap `tag_spacing × tag_size`.
    Aprilgrid {
        id: String,
        rows: u32,
        cols: u32,
        tag_size: f64,
        tag_spacing: f64,
        first_id: u32,
    },
    /// Scattered AprilTags of known size, layout unknown. `ids` restricts which tags belong here.
    Apriltags {
        id: String,
        tag_size: f64,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        ids: Option<Vec<u32>>,
    },
    /// Wu's line target (vanishing method): line length L1 and spacing L2 (m).
    LineTarget {
        id: String,
        length: f64,
        spacing: f64,
    },
    /// Thin printed lines (vanishing method): `lines_x` lines along the sheet's `x`,
    /// `lines_y` along its `y`, each `length` long and centred, a group's lines
    /// `spacing` apart, strokes `stroke` wide (m).
    LineGrid {
        id: String,
        length: f64,
        spacing: f64,
        lines_x: u32,
        lines_y: u32,
        stroke: f64,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        mark: Option<MarkSpec>,
    },
    /// Thin printed lines at explicit places: segments `[[x0, y0], [x1, y1]]` (m) in
    /// sheet coordinates, each along the sheet's `x` or `y`, strokes `stroke` wide.
    LineSegments {
        id: String,
        segments: Vec<[[f64; 2]; 2]>,
        stroke: f64,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        mark: Option<MarkSpec>,
    },
    /// Points of known coordinates (m) in the target's own frame: a rigid body.
    Points {
        id: String,
        points: BTreeMap<String, [f64; 3]>,
    },
}

impl TargetSpec {
    /// A target of the vanishing method (two orthogonal groups of parallel lines).
    pub fn is_line_target(&self) -> bool {
        matches!(
            self,
            TargetSpec::LineTarget { .. }
                | TargetSpec::LineGrid { .. }
                | TargetSpec::LineSegments { .. }
        )
    }

    pub fn id(&self) -> &str {
        match self {
            TargetSpec::Aprilgrid { id, .. }
            | TargetSpec::Apriltags { id, .. }
            | TargetSpec::LineTarget { id, .. }
            | TargetSpec::LineGrid { id, .. }
            | TargetSpec::LineSegments { id, .. }
            | TargetSpec::Points { id, .. } => id,
        }
    }
}

/// An orientation mark on a thin-line target: a filled dark disc of `radius` (m) centred
/// at sheet `(x, y)`, off the print's centre of symmetry.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MarkSpec {
    pub x: f64,
    pub y: f64,
    pub radius: f64,
}

/// A measured distance between two points (Lébraly §2), fixing the metric scale.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScaleSpec {
    pub a: String,
    pub b: String,
    /// Metres.
    pub distance: f64,
    /// 1-σ of the measurement in metres (default 0.5 mm).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma: Option<f64>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameSpec {
    pub index: i64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub timestamp: Option<f64>,
    /// Camera id → image path (relative to the manifest) for sessions of images.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub images: BTreeMap<String, String>,
    /// Camera id → detections.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub observations: BTreeMap<String, Vec<ObservationSpec>>,
    /// Camera id → points of the feature lines of line targets (vanishing method).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub lines: BTreeMap<String, Vec<LineSpec>>,
    /// Rig camera id → the id of the line target it sees (vanishing method, sessions of
    /// images: which target a detected L is).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub line_targets: BTreeMap<String, String>,
}

/// Points measured along one feature line `l1..l6` of a line target (Wu et al. Fig. 1),
/// in raw (distorted) pixels. See `docs/formats.md` for the line numbering.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LineSpec {
    pub target: String,
    /// 1..=6.
    pub line: u8,
    /// `[u, v]` pixel coordinates of points on the line.
    pub points: Vec<[f64; 2]>,
}

/// One image of the auxiliary camera showing two neighbouring targets.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RingSpec {
    pub index: i64,
    /// The ids of the two line targets in view.
    pub targets: Vec<String>,
    /// Image path (relative to the manifest), for sessions of images.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image: Option<String>,
    /// Detected line points of both targets.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub lines: Vec<LineSpec>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObservationSpec {
    pub point: String,
    pub u: f64,
    pub v: f64,
}

#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Priors {
    /// Camera id → its height (m) above the reference camera along the motion-plane
    /// normal, used only where planar motion leaves it unobservable.
    #[serde(default)]
    pub height_offsets: BTreeMap<String, f64>,
}
