//! Exports of a result document: Kalibr camchain YAML, OpenCV YAML, ROS URDF snippet.
//! Each states its own frame convention in a comment, because the directions differ.

use crate::result::ResultDocument;
use crate::session::Session;

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

fn pose_of(doc: &ResultDocument, cam: &str) -> Option<crate::geometry::Pose> {
    let e = doc.extrinsics.iter().find(|e| e.value.camera == cam)?;
    Some(e.value.pose())
}

fn matrix_rows(p: &crate::geometry::Pose, indent: &str) -> String {
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

/// Render `doc` in `format`; `None` if the document has no extrinsics to export.
pub fn render(doc: &ResultDocument, session: &Session, format: Format) -> Option<String> {
    if format == Format::Json {
        return serde_json::to_string_pretty(doc).ok();
    }
    if doc.extrinsics.is_empty() {
        return None;
    }
    let mut out = String::new();
    match format {
        Format::Kalibr => {
            out.push_str("# Kalibr camchain. T_cn_cnm1 maps points from camera n-1 to camera n (cam_n_from_cam_n-1);\n");
            out.push_str("# rigcal also writes T_ref_cam (ref_from_cam: camera n to the reference camera).\n");
            let mut prev: Option<crate::geometry::Pose> = None;
            for (i, c) in session.cameras.iter().enumerate() {
                let p = pose_of(doc, &c.id)?;
                let k = &c.camera;
                let (cm, dm, coeffs) = match k.model {
                    crate::geometry::CameraModel::Pinhole => ("pinhole", "radtan", vec![0.0; 4]),
                    crate::geometry::CameraModel::Radtan { .. } => {
                        ("pinhole", "radtan", k.model.coefficients()[..4].to_vec())
                    }
                    crate::geometry::CameraModel::Equidistant { .. } => {
                        ("pinhole", "equidistant", k.model.coefficients())
                    }
                };
                out.push_str(&format!("cam{i}:\n  rostopic: /{}/image_raw\n  camera_model: {cm}\n  distortion_model: {dm}\n", c.id));
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
                let p = pose_of(doc, &c.id)?.inverse();
                let r = p.rot;
                out.push_str(&format!(
                    "{}_R: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ {:.12}, {:.12}, {:.12}, {:.12}, {:.12}, {:.12}, {:.12}, {:.12}, {:.12} ]\n",
                    c.id, r[(0, 0)], r[(0, 1)], r[(0, 2)], r[(1, 0)], r[(1, 1)], r[(1, 2)], r[(2, 0)], r[(2, 1)], r[(2, 2)]
                ));
                out.push_str(&format!("{}_T: !!opencv-matrix\n   rows: 3\n   cols: 1\n   dt: d\n   data: [ {:.12}, {:.12}, {:.12} ]\n", c.id, p.trans.x, p.trans.y, p.trans.z));
            }
        }
        Format::Urdf => {
            out.push_str(&format!("<!-- rigcal: joint origins are ref_from_cam (parent = {0}_optical, child = camera optical frame,\n     z forward, x right, y down). rpy is fixed-axis roll, pitch, yaw in radians. -->\n<robot name=\"rig\">\n  <link name=\"{0}_optical\"/>\n", doc.reference_camera));
            for c in &session.cameras {
                if c.id == doc.reference_camera {
                    continue;
                }
                let p = pose_of(doc, &c.id)?;
                let (r, pi, y) = crate::geometry::so3::to_rpy(&p.rot);
                out.push_str(&format!(
                    "  <link name=\"{1}_optical\"/>\n  <joint name=\"{0}_to_{1}\" type=\"fixed\">\n    <parent link=\"{0}_optical\"/>\n    <child link=\"{1}_optical\"/>\n    <origin xyz=\"{2:.9} {3:.9} {4:.9}\" rpy=\"{5:.12} {6:.12} {7:.12}\"/>\n  </joint>\n",
                    doc.reference_camera, c.id, p.trans.x, p.trans.y, p.trans.z, r, pi, y
                ));
            }
            out.push_str("</robot>\n");
        }
        Format::Json => unreachable!("handled above"),
    }
    Some(out)
}
