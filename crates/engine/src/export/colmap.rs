//! COLMAP (≥ 3.12) `rig_config.json`, for `colmap rig_configurator`: one rig whose
//! reference sensor is rigcal's reference camera, each camera with `cam_from_rig`
//! (rotation as a unit quaternion w, x, y, z) and its intrinsics as a COLMAP camera
//! model. Images are expected in one folder per camera named by its id (`front/…`), as
//! COLMAP's rig workflow organises them. JSON has no comments: the convention is stated
//! here and in docs/formats.md.

use super::{ExportError, Rig};
use rigcal_core::geometry::{so3, CameraModel};
use serde_json::{json, Value};

pub(super) fn render(rig: &Rig) -> Result<String, ExportError> {
    let cameras: Vec<Value> = rig
        .session
        .cameras
        .iter()
        .zip(&rig.ref_from_cam)
        .map(|(c, ref_from_cam)| {
            let k = &c.camera;
            let (model, mut params) = match k.model {
                CameraModel::Pinhole => ("PINHOLE", vec![]),
                CameraModel::Radtan { k3: 0.0, .. } => {
                    ("OPENCV", k.model.coefficients()[..4].to_vec())
                }
                CameraModel::Radtan { .. } => {
                    let mut p = k.model.coefficients();
                    p.extend([0.0; 3]); // FULL_OPENCV's rational k4, k5, k6
                    ("FULL_OPENCV", p)
                }
                CameraModel::Equidistant { .. } => ("OPENCV_FISHEYE", k.model.coefficients()),
            };
            params.splice(0..0, [k.fx, k.fy, k.cx, k.cy]);
            let mut cam = json!({
                "image_prefix": format!("{}/", c.id),
                "camera_model_name": model,
                "camera_params": params,
            });
            if c.id == rig.reference {
                cam["ref_sensor"] = json!(true);
            } else {
                let cam_from_rig = ref_from_cam.inverse();
                cam["cam_from_rig_rotation"] = json!(so3::to_quaternion(&cam_from_rig.rot));
                let t = cam_from_rig.trans;
                cam["cam_from_rig_translation"] = json!([t.x, t.y, t.z]);
            }
            cam
        })
        .collect();
    serde_json::to_string_pretty(&json!([{ "cameras": cameras }]))
        .map_err(|e| ExportError::Unrepresentable(e.to_string()))
}
