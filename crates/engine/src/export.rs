//! Exports of a result document: Kalibr camchain YAML, OpenCV YAML, ROS URDF snippet.
//! Each states its own frame convention in a comment, because the directions differ.
//!
//! Identifiers are validated at the boundary (`session::check_identifier`), and every
//! exporter still quotes or escapes what it writes (defence in depth: the grammar allows
//! ids such as `yes`, `1e5` or `a--b` that YAML or XML would misread unquoted). What a
//! format cannot represent at all (an OpenCV FileStorage key that starts with a digit)
//! is refused with the reason, never written mangled.

use rigcal_core::result::ResultDocument;
use rigcal_core::session::Session;

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    Json,
    Kalibr,
    Opencv,
    Urdf,
}

impl std::str::FromStr for Format {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "json" => Ok(Format::Json),
            "kalibr" => Ok(Format::Kalibr),
            "opencv" => Ok(Format::Opencv),
            "urdf" => Ok(Format::Urdf),
            _ => Err(format!(
                "format: one of json, kalibr, opencv, urdf, got {s:?}"
            )),
        }
    }
}

fn pose_of(doc: &ResultDocument, cam: &str) -> Option<rigcal_core::geometry::Pose> {
    let e = doc.extrinsics.iter().find(|e| e.value.camera == cam)?;
    Some(e.value.pose())
}

fn matrix_rows(p: &rigcal_core::geometry::Pose, indent: &str) -> String {
    p.matrix()
        .iter()
        .map(|r| {
            format!(
                "{indent}- [{:.12}, {:.12}, {:.12}, {:.12}]\n",
                r[0], r[1], r[2], r[3]
            )
        })
        .collect()
}

/// Why a document was not exported.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ExportError {
    /// The calibration gave no extrinsics.
    NothingToExport,
    /// An identifier the format cannot hold, with the reason.
    Unrepresentable(String),
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

/// Text escaped for an XML attribute value in double quotes.
fn xml_attr(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&apos;"),
            c => out.push(c),
        }
    }
    out
}

/// An OpenCV FileStorage key: a letter or `_` first, then letters, digits, `_` or `-`
/// (what its YAML reader accepts; keys are never quoted there).
fn opencv_key(id: &str) -> Result<(), ExportError> {
    let mut chars = id.chars();
    let first_ok = chars
        .next()
        .is_some_and(|c| c.is_ascii_alphabetic() || c == '_');
    if first_ok && chars.all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-') {
        Ok(())
    } else {
        Err(ExportError::Unrepresentable(format!(
            "camera id {}: an OpenCV FileStorage key starts with a letter or _ and holds only letters, digits, _ and -; export as json or kalibr, or name the camera so",
            rigcal_core::session::quoted_prefix(id)
        )))
    }
}

/// Render `doc` in `format`.
pub fn render(
    doc: &ResultDocument,
    session: &Session,
    format: Format,
) -> Result<String, ExportError> {
    if format == Format::Json {
        return serde_json::to_string_pretty(doc)
            .map_err(|e| ExportError::Unrepresentable(e.to_string()));
    }
    if doc.extrinsics.is_empty() {
        return Err(ExportError::NothingToExport);
    }
    let pose_of = |cam: &str| pose_of(doc, cam).ok_or(ExportError::NothingToExport);
    let mut out = String::new();
    match format {
        Format::Kalibr => {
            out.push_str("# Kalibr camchain. T_cn_cnm1 maps points from camera n-1 to camera n (cam_n_from_cam_n-1);\n");
            out.push_str("# rigcal also writes T_ref_cam (ref_from_cam: camera n to the reference camera).\n");
            let mut prev: Option<rigcal_core::geometry::Pose> = None;
            for (i, c) in session.cameras.iter().enumerate() {
                let p = pose_of(&c.id)?;
                let k = &c.camera;
                let (cm, dm, coeffs) = match k.model {
                    rigcal_core::geometry::CameraModel::Pinhole => {
                        ("pinhole", "radtan", vec![0.0; 4])
                    }
                    rigcal_core::geometry::CameraModel::Radtan { .. } => {
                        ("pinhole", "radtan", k.model.coefficients()[..4].to_vec())
                    }
                    rigcal_core::geometry::CameraModel::Equidistant { .. } => {
                        ("pinhole", "equidistant", k.model.coefficients())
                    }
                };
                out.push_str(&format!(
                    "cam{i}:\n  rostopic: {}\n  camera_model: {cm}\n  distortion_model: {dm}\n",
                    yaml_str(&format!("/{}/image_raw", c.id))
                ));
                out.push_str(&format!("  distortion_coeffs: {coeffs:?}\n  intrinsics: [{}, {}, {}, {}]\n  resolution: [{}, {}]\n", k.fx, k.fy, k.cx, k.cy, k.width, k.height));
                out.push_str("  T_ref_cam:\n");
                out.push_str(&matrix_rows(&p, "  "));
                if let Some(pp) = prev {
                    out.push_str("  T_cn_cnm1:\n");
                    out.push_str(&matrix_rows(&(p.inverse() * pp), "  "));
                }
                prev = Some(p);
            }
        }
        Format::Opencv => {
            out.push_str("%YAML:1.0\n---\n# OpenCV stereo convention: R, T map reference-camera points into this camera,\n# x_cam = R x_ref + T (cam_from_ref). rigcal's ref_from_cam is the inverse.\n");
            for c in &session.cameras {
                opencv_key(&c.id)?;
                let p = pose_of(&c.id)?.inverse();
                let r = p.rot;
                out.push_str(&format!(
                    "{}_R: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ {:.12}, {:.12}, {:.12}, {:.12}, {:.12}, {:.12}, {:.12}, {:.12}, {:.12} ]\n",
                    c.id, r[(0, 0)], r[(0, 1)], r[(0, 2)], r[(1, 0)], r[(1, 1)], r[(1, 2)], r[(2, 0)], r[(2, 1)], r[(2, 2)]
                ));
                out.push_str(&format!("{}_T: !!opencv-matrix\n   rows: 3\n   cols: 1\n   dt: d\n   data: [ {:.12}, {:.12}, {:.12} ]\n", c.id, p.trans.x, p.trans.y, p.trans.z));
            }
        }
        Format::Urdf => {
            // Ids stay out of the comment: `--` is not allowed inside one.
            out.push_str(&format!("<!-- rigcal: joint origins are ref_from_cam (parent = the reference camera's optical link,\n     child = the camera's optical frame, z forward, x right, y down). rpy is fixed-axis roll, pitch, yaw in radians. -->\n<robot name=\"rig\">\n  <link name=\"{}_optical\"/>\n", xml_attr(&doc.reference_camera)));
            for c in &session.cameras {
                if c.id == doc.reference_camera {
                    continue;
                }
                let p = pose_of(&c.id)?;
                let (r, pi, y) = rigcal_core::geometry::so3::to_rpy(&p.rot);
                out.push_str(&format!(
                    "  <link name=\"{1}_optical\"/>\n  <joint name=\"{0}_to_{1}\" type=\"fixed\">\n    <parent link=\"{0}_optical\"/>\n    <child link=\"{1}_optical\"/>\n    <origin xyz=\"{2:.9} {3:.9} {4:.9}\" rpy=\"{5:.12} {6:.12} {7:.12}\"/>\n  </joint>\n",
                    xml_attr(&doc.reference_camera), xml_attr(&c.id), p.trans.x, p.trans.y, p.trans.z, r, pi, y
                ));
            }
            out.push_str("</robot>\n");
        }
        Format::Json => unreachable!("handled above"),
    }
    Ok(out)
}
