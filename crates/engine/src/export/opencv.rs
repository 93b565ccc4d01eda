//! OpenCV FileStorage YAML: per camera its matrix `K`, distortion `D`, image size,
//! lens model, and `R`, `T` in OpenCV's stereo convention, everything
//! `cv2.stereoRectify` or `initUndistortRectifyMap` takes.

use super::{yaml_float, ExportError, Rig};
use rigcal_core::geometry::CameraModel;

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

fn matrix(name: &str, rows: usize, cols: usize, dt: &str, data: &[String]) -> String {
    format!(
        "{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: {dt}\n   data: [ {} ]\n",
        data.join(", ")
    )
}

fn floats(xs: &[f64]) -> Vec<String> {
    xs.iter().map(|&x| yaml_float(x)).collect()
}

pub(super) fn render(rig: &Rig) -> Result<String, ExportError> {
    let (base, to) = if rig.vehicle_from_ref.is_some() {
        (
            "vehicle-frame points (the vehicle model's vehicle frame)",
            "cam_from_vehicle = (vehicle_from_ref · ref_from_cam)⁻¹",
        )
    } else {
        (
            "reference-camera points",
            "cam_from_ref, the inverse of rigcal's ref_from_cam",
        )
    };
    let mut out = format!(
        "%YAML:1.0\n---\n\
         # OpenCV stereo convention: <id>_R, <id>_T map {base} into this camera,\n\
         # x_cam = R x + T: {to}. For a pair\n\
         # (a, b): R = R_b R_aᵀ, T = T_b − R T_a. <id>_K is the camera matrix, <id>_D the\n\
         # distortion (k1, k2, p1, p2, k3 for model pinhole; k1..k4 of cv2.fisheye for model\n\
         # fisheye), <id>_size [width, height] in pixels.\n",
    );
    for (c, ref_from_cam) in rig.session.cameras.iter().zip(&rig.ref_from_cam) {
        opencv_key(&c.id)?;
        let k = &c.camera;
        let (model, d) = match k.model {
            CameraModel::Pinhole => ("pinhole", vec![0.0; 5]),
            CameraModel::Radtan { .. } => ("pinhole", k.model.coefficients()),
            CameraModel::Equidistant { .. } => ("fisheye", k.model.coefficients()),
        };
        let id = &c.id;
        out.push_str(&format!("{id}_model: \"{model}\"\n"));
        out.push_str(&matrix(
            &format!("{id}_K"),
            3,
            3,
            "d",
            &floats(&[k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0]),
        ));
        out.push_str(&matrix(&format!("{id}_D"), 1, d.len(), "d", &floats(&d)));
        out.push_str(&matrix(
            &format!("{id}_size"),
            1,
            2,
            "i",
            &[k.width.to_string(), k.height.to_string()],
        ));
        let p = match &rig.vehicle_from_ref {
            Some(v) => (*v * *ref_from_cam).inverse(),
            None => ref_from_cam.inverse(),
        };
        let r = p.rot;
        let rows: Vec<f64> = (0..3)
            .flat_map(|i| (0..3).map(move |j| r[(i, j)]))
            .collect();
        out.push_str(&matrix(&format!("{id}_R"), 3, 3, "d", &floats(&rows)));
        out.push_str(&matrix(
            &format!("{id}_T"),
            3,
            1,
            "d",
            &floats(&[p.trans.x, p.trans.y, p.trans.z]),
        ));
    }
    Ok(out)
}
