//! ROS 2: `ros2` is a launch file (XML) of `tf2_ros static_transform_publisher` nodes,
//! one per camera, from the reference camera's optical frame to each camera's
//! (`<id>_optical_frame`, REP 103/105: z forward, x right, y down); `camera_info` is one
//! camera's `sensor_msgs/CameraInfo` in the YAML of `camera_calibration_parsers`.

use super::urdf::xml_attr;
use super::{yaml_floats, yaml_str, ExportError, Rig};
use rigcal_core::geometry::{so3, CameraModel, Pose};

pub(super) fn launch(rig: &Rig) -> String {
    let mut out = String::from(
        "<?xml version=\"1.0\"?>\n<!-- rigcal: static transforms parent = the reference camera's optical frame, child = each\n     camera's optical frame (z forward, x right, y down); translation in metres, rotation a unit\n     quaternion: the child's pose in the parent (ref_from_cam). -->\n<launch>\n",
    );
    let mut transforms: Vec<(String, String, String, &Pose)> = Vec::new();
    if let Some(v) = &rig.vehicle_from_ref {
        out.push_str("  <!-- base_link: the vehicle model's vehicle frame, parent of the reference camera (vehicle_from_ref). -->\n");
        transforms.push((
            "rigcal_tf_base_link".into(),
            super::VEHICLE_FRAME.into(),
            format!("{}_optical_frame", rig.reference),
            v,
        ));
    }
    for (c, p) in rig.session.cameras.iter().zip(&rig.ref_from_cam) {
        if c.id != rig.reference {
            transforms.push((
                format!("rigcal_tf_{}", c.id),
                format!("{}_optical_frame", rig.reference),
                format!("{}_optical_frame", c.id),
                p,
            ));
        }
    }
    for (name, parent, child, p) in transforms {
        let [w, x, y, z] = so3::to_quaternion(&p.rot);
        let reference = xml_attr(&parent);
        let child = xml_attr(&child);
        let args = format!(
            "--x {:?} --y {:?} --z {:?} --qx {x:?} --qy {y:?} --qz {z:?} --qw {w:?} --frame-id {reference} --child-frame-id {child}",
            p.trans.x, p.trans.y, p.trans.z
        );
        out.push_str(&format!(
            "  <node pkg=\"tf2_ros\" exec=\"static_transform_publisher\" name=\"{}\" args=\"{args}\"/>\n",
            xml_attr(&name)
        ));
    }
    out.push_str("</launch>\n");
    out
}

fn yaml_mat(rows: usize, cols: usize, data: &[f64]) -> String {
    format!(
        "\n  rows: {rows}\n  cols: {cols}\n  data: {}",
        yaml_floats(data)
    )
}

pub(super) fn camera_info(rig: &Rig, camera: &str) -> Result<String, ExportError> {
    let c = rig
        .session
        .cameras
        .iter()
        .find(|c| c.id == camera)
        .ok_or_else(|| {
            ExportError::Camera(format!(
                "one of {}, got {}",
                rig.session
                    .cameras
                    .iter()
                    .map(|c| c.id.as_str())
                    .collect::<Vec<_>>()
                    .join(", "),
                rigcal_core::session::quoted_prefix(camera)
            ))
        })?;
    let k = &c.camera;
    let (model, d) = match k.model {
        CameraModel::Pinhole => ("plumb_bob", vec![0.0; 5]),
        CameraModel::Radtan { .. } => ("plumb_bob", k.model.coefficients()),
        CameraModel::Equidistant { .. } => ("equidistant", k.model.coefficients()),
    };
    Ok(format!(
        "# rigcal: sensor_msgs/CameraInfo of camera {} (camera_calibration_parsers YAML); raw image,\n# no rectification (R = I, P = [K | 0]). Distortion k1, k2, p1, p2, k3 (plumb_bob) or k1..k4 (equidistant).\nimage_width: {}\nimage_height: {}\ncamera_name: {}\ncamera_matrix:{}\ndistortion_model: {model}\ndistortion_coefficients:{}\nrectification_matrix:{}\nprojection_matrix:{}\n",
        rigcal_core::session::quoted_prefix(&c.id),
        k.width,
        k.height,
        yaml_str(&c.id),
        yaml_mat(3, 3, &[k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0]),
        yaml_mat(1, d.len(), &d),
        yaml_mat(3, 3, &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]),
        yaml_mat(3, 4, &[k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0]),
    ))
}
