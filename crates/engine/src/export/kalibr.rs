//! Kalibr camchain YAML, as Kalibr's `ConfigReader` reads it: float intrinsics and
//! distortion coefficients, integer resolution, `T_cn_cnm1` (camera n-1 to camera n) for
//! every camera after the first, and `cam_overlaps`.

use super::{yaml_floats, yaml_matrix, yaml_str, ExportError, Rig};
use rigcal_core::geometry::CameraModel;
use rigcal_core::session::Session;
use std::collections::BTreeSet;

pub(super) fn render(rig: &Rig) -> Result<String, ExportError> {
    let session = rig.session;
    let overlaps = overlaps(session);
    let mut out = String::from(
        "# Kalibr camchain. T_cn_cnm1 maps points from camera n-1 to camera n (cam_n_from_cam_n-1);\n\
         # rigcal also writes T_ref_cam (ref_from_cam: camera n to the reference camera).\n\
         # cam_overlaps: the cameras that saw a point in the same frame as this one.\n",
    );
    if rig.vehicle_from_ref.is_some() {
        out.push_str(
            "# T_vehicle_cam (vehicle_from_cam): camera n in the vehicle model's vehicle frame.\n",
        );
    }
    for (i, c) in session.cameras.iter().enumerate() {
        let k = &c.camera;
        let (dm, coeffs) = match k.model {
            CameraModel::Pinhole => ("radtan", vec![0.0; 4]),
            CameraModel::Radtan { k1, k2, p1, p2, k3 } => {
                if k3 != 0.0 {
                    return Err(ExportError::Unrepresentable(format!(
                        "camera {}: radtan k3 = {k3} (Kalibr's radtan model has k1, k2, p1, p2 only); export as opencv or json",
                        rigcal_core::session::quoted_prefix(&c.id)
                    )));
                }
                ("radtan", vec![k1, k2, p1, p2])
            }
            CameraModel::Equidistant { .. } => ("equidistant", k.model.coefficients()),
        };
        out.push_str(&format!(
            "cam{i}:\n  rostopic: {}\n  camera_model: pinhole\n  intrinsics: {}\n  distortion_model: {dm}\n  distortion_coeffs: {}\n  resolution: [{}, {}]\n  cam_overlaps: [{}]\n",
            yaml_str(&format!("/{}/image_raw", c.id)),
            yaml_floats(&[k.fx, k.fy, k.cx, k.cy]),
            yaml_floats(&coeffs),
            k.width,
            k.height,
            overlaps[i].iter().map(|j| j.to_string()).collect::<Vec<_>>().join(", "),
        ));
        out.push_str("  T_ref_cam:\n");
        out.push_str(&yaml_matrix(&rig.ref_from_cam[i], "  "));
        if let Some(v) = &rig.vehicle_from_ref {
            out.push_str("  T_vehicle_cam:\n");
            out.push_str(&yaml_matrix(&(*v * rig.ref_from_cam[i]), "  "));
        }
        if i > 0 {
            let cn_from_cnm1 = rig.ref_from_cam[i].inverse() * rig.ref_from_cam[i - 1];
            out.push_str("  T_cn_cnm1:\n");
            out.push_str(&yaml_matrix(&cn_from_cnm1, "  "));
        }
    }
    Ok(out)
}

/// For every camera, the others that observed one of its points in the same frame.
fn overlaps(session: &Session) -> Vec<BTreeSet<usize>> {
    let n = session.cameras.len();
    let mut out = vec![BTreeSet::new(); n];
    for f in &session.frames {
        let seen: Vec<BTreeSet<usize>> = f
            .observations
            .iter()
            .map(|o| o.iter().map(|x| x.point).collect())
            .collect();
        for a in 0..n {
            for b in a + 1..n {
                if !seen[a].is_disjoint(&seen[b]) {
                    out[a].insert(b);
                    out[b].insert(a);
                }
            }
        }
    }
    out
}
