//! Exports of a result document in the formats other tools read: Kalibr camchain YAML,
//! OpenCV FileStorage YAML, a ROS URDF snippet, ROS 2 (a tf2 static-transform launch file
//! and per-camera `camera_info`) and a COLMAP (≥ 3.12) `rig_config.json`.
//! One file per format; each states its frame convention in the file it writes, because
//! the directions differ.
//!
//! Identifiers are validated at the boundary (`session::check_identifier`), and every
//! exporter still quotes or escapes what it writes (defence in depth: the grammar allows
//! ids such as `yes`, `1e5` or `a--b` that YAML or XML would misread unquoted). What a
//! format cannot represent (an OpenCV FileStorage key that starts with a digit, radtan's
//! `k3` in Kalibr) is refused with the reason, never written mangled or dropped.

mod colmap;
mod kalibr;
mod opencv;
mod ros2;
mod urdf;

use rigcal_core::geometry::Pose;
use rigcal_core::result::ResultDocument;
use rigcal_core::session::Session;

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    Json,
    Kalibr,
    Opencv,
    Urdf,
    Colmap,
    /// ROS 2 launch file of tf2 static transforms.
    Ros2,
    /// One camera's `sensor_msgs/CameraInfo` YAML (needs the camera).
    #[serde(rename = "camera_info")]
    CameraInfo,
}

impl Format {
    pub const ALL: [Format; 7] = [
        Format::Json,
        Format::Kalibr,
        Format::Opencv,
        Format::Urdf,
        Format::Colmap,
        Format::Ros2,
        Format::CameraInfo,
    ];

    pub const fn as_str(self) -> &'static str {
        match self {
            Format::Json => "json",
            Format::Kalibr => "kalibr",
            Format::Opencv => "opencv",
            Format::Urdf => "urdf",
            Format::Colmap => "colmap",
            Format::Ros2 => "ros2",
            Format::CameraInfo => "camera_info",
        }
    }

    /// Media type and file extension of the export.
    pub const fn media(self) -> (&'static str, &'static str) {
        match self {
            Format::Json | Format::Colmap => ("application/json", "json"),
            Format::Urdf => ("application/xml", "urdf"),
            Format::Ros2 => ("application/xml", "launch.xml"),
            Format::Kalibr | Format::Opencv | Format::CameraInfo => ("application/yaml", "yaml"),
        }
    }

    /// "one of json, kalibr, …" for error messages.
    pub fn expected() -> String {
        let names: Vec<&str> = Self::ALL.iter().map(|f| f.as_str()).collect();
        format!("one of {}", names.join(", "))
    }
}

impl std::str::FromStr for Format {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Self::ALL
            .into_iter()
            .find(|f| f.as_str() == s)
            .ok_or_else(|| format!("format: {}, got {s:?}", Self::expected()))
    }
}

/// Why a document was not exported.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ExportError {
    /// The calibration gave no extrinsics, or failed.
    NothingToExport,
    /// What the format cannot hold, with the reason.
    Unrepresentable(String),
    /// The camera of a per-camera format is missing, unknown, or given to a rig format.
    Camera(String),
}

/// Render `doc` in `format`.
pub fn render(
    doc: &ResultDocument,
    session: &Session,
    format: Format,
) -> Result<String, ExportError> {
    render_for(doc, session, format, None)
}

/// The frame the rig is exported in.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Frame {
    /// The reference camera's (the result's own).
    Reference,
    /// The vehicle frame of a vehicle model: `vehicle_from_ref` places the reference
    /// camera in it.
    Vehicle(Pose),
}

/// Render `doc` in `format`; `camera` names the camera of the per-camera formats
/// (`camera_info`) and must be absent for the others.
pub fn render_for(
    doc: &ResultDocument,
    session: &Session,
    format: Format,
    camera: Option<&str>,
) -> Result<String, ExportError> {
    render_in(doc, session, format, camera, Frame::Reference)
}

/// [`render_for`] in `frame`. A format whose rig frame is fixed (COLMAP's is its
/// reference sensor; the JSON document is the result itself) refuses the vehicle frame.
pub fn render_in(
    doc: &ResultDocument,
    session: &Session,
    format: Format,
    camera: Option<&str>,
    frame: Frame,
) -> Result<String, ExportError> {
    if let (Frame::Vehicle(_), Format::Json | Format::Colmap) = (frame, format) {
        return Err(ExportError::Unrepresentable(match format {
            Format::Json => "the JSON result is the calibration itself, always in the reference camera's frame; the vehicle frame is for the kalibr, opencv, urdf and ros2 exports".into(),
            _ => "COLMAP's rig frame is its reference sensor (ref_sensor has no cam_from_rig), so a COLMAP rig has no vehicle frame; export it in the reference frame".into(),
        }));
    }
    let camera_info_of = match (format, camera) {
        (Format::CameraInfo, Some(c)) => Some(c),
        (Format::CameraInfo, None) => {
            let ids: Vec<&str> = session.cameras.iter().map(|c| c.id.as_str()).collect();
            return Err(ExportError::Camera(format!(
                "camera_info describes one camera: one of {}",
                ids.join(", ")
            )));
        }
        (_, Some(_)) => {
            return Err(ExportError::Camera(format!(
                "camera: only for format camera_info, not {}",
                format.as_str()
            )))
        }
        (_, None) => None,
    };
    if format == Format::Json {
        return serde_json::to_string_pretty(doc)
            .map_err(|e| ExportError::Unrepresentable(e.to_string()));
    }
    // A failed calibration's numbers never leave as a file another tool would load as a
    // calibration; its JSON document says why it failed.
    if doc.extrinsics.is_empty() || doc.status == rigcal_core::result::Status::Failed {
        return Err(ExportError::NothingToExport);
    }
    let mut rig = Rig::of(doc, session)?;
    if let Frame::Vehicle(p) = frame {
        rig.vehicle_from_ref = Some(p);
    }
    match format {
        Format::Kalibr => kalibr::render(&rig),
        Format::Opencv => opencv::render(&rig),
        Format::Urdf => Ok(urdf::render(&rig)),
        Format::Colmap => colmap::render(&rig),
        Format::Ros2 => Ok(ros2::launch(&rig)),
        // (`camera_info_of` is `Some` for this format: checked at the top.)
        Format::CameraInfo => camera_info_of.map_or_else(
            || Err(ExportError::Camera("camera_info needs a camera".into())),
            |c| ros2::camera_info(&rig, c),
        ),
        Format::Json => unreachable!("handled above"),
    }
}

/// What every exporter needs: the session's cameras in order with their `ref_from_cam`,
/// and the vehicle frame when the export is in it.
struct Rig<'a> {
    session: &'a Session,
    reference: &'a str,
    ref_from_cam: Vec<Pose>,
    vehicle_from_ref: Option<Pose>,
}

impl<'a> Rig<'a> {
    fn of(doc: &'a ResultDocument, session: &'a Session) -> Result<Self, ExportError> {
        let ref_from_cam = session
            .cameras
            .iter()
            .map(|c| {
                doc.extrinsics
                    .iter()
                    .find(|e| e.value.camera == c.id)
                    .map(|e| e.value.pose())
                    .ok_or(ExportError::NothingToExport)
            })
            .collect::<Result<_, _>>()?;
        Ok(Rig {
            session,
            reference: &doc.reference_camera,
            ref_from_cam,
            vehicle_from_ref: None,
        })
    }
}

/// The vehicle frame's name in the ROS formats (REP 105's `base_link`).
const VEHICLE_FRAME: &str = "base_link";

/// A float that YAML 1.1 (PyYAML, which Kalibr and ROS use) and YAML 1.2 both read as a
/// float, at full precision: digits, a point, and a signed exponent if any. Rust's
/// shortest form writes `1273` as `1273` for `{}` and `3e-5` for `{:?}`, which PyYAML
/// reads as an integer and a string.
fn yaml_float(x: f64) -> String {
    if x.is_nan() {
        return ".nan".into();
    }
    if x.is_infinite() {
        return if x > 0.0 { ".inf" } else { "-.inf" }.into();
    }
    let s = format!("{x:?}");
    let with_point = |m: &str| {
        if m.contains('.') {
            m.to_string()
        } else {
            format!("{m}.0")
        }
    };
    match s.split_once('e') {
        Some((m, e)) => {
            let sign = if e.starts_with('-') { "" } else { "+" };
            format!("{}e{sign}{e}", with_point(m))
        }
        None => with_point(&s),
    }
}

/// `[a, b, …]` of [`yaml_float`]s.
fn yaml_floats(xs: &[f64]) -> String {
    let items: Vec<String> = xs.iter().map(|&x| yaml_float(x)).collect();
    format!("[{}]", items.join(", "))
}

/// The 4×4 matrix of `p` as YAML rows at `indent`.
fn yaml_matrix(p: &Pose, indent: &str) -> String {
    p.matrix()
        .iter()
        .map(|r| format!("{indent}- {}\n", yaml_floats(r)))
        .collect()
}

/// A YAML double-quoted scalar: a string in YAML 1.1 and 1.2 whatever it holds (quote
/// and backslash escaped, control characters as `\uXXXX`).
fn yaml_str(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if c.is_control() => out.push_str(&format!("\\u{:04x}", c as u32)),
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn yaml_floats_always_have_a_point_and_a_signed_exponent() {
        for (x, s) in [
            (1273.0, "1273.0"),
            (3e-5, "3.0e-5"),
            (-2.5e-7, "-2.5e-7"),
            (1e20, "1.0e+20"),
            (0.1, "0.1"),
            (-0.0, "-0.0"),
            (f64::NAN, ".nan"),
        ] {
            assert_eq!(yaml_float(x), s);
            if x.is_finite() {
                assert_eq!(yaml_float(x).parse::<f64>().unwrap(), x);
            }
        }
    }
}
