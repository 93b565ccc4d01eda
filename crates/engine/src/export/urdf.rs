//! A ROS URDF snippet: one fixed joint per camera from the reference camera's optical
//! frame (REP 103 optical-frame naming, `<id>_optical_frame`).

use super::Rig;

pub(super) use rigcal_core::xml::escape as xml_attr;

pub(super) fn render(rig: &Rig) -> String {
    let reference = xml_attr(rig.reference);
    // Ids stay out of the comment: `--` is not allowed inside one.
    let mut out = String::from("<!-- rigcal: joint origins are ref_from_cam (parent = the reference camera's optical frame,\n     child = the camera's optical frame, z forward, x right, y down). rpy is fixed-axis roll, pitch, yaw in radians. -->\n<robot name=\"rig\">\n",
    );
    if let Some(v) = &rig.vehicle_from_ref {
        let (r, pi, y) = rigcal_core::geometry::so3::to_rpy(&v.rot);
        out.push_str(&format!(
            "  <!-- {0}: the vehicle model's vehicle frame; its joint origin is vehicle_from_ref. -->\n  <link name=\"{0}\"/>\n  <joint name=\"{0}_to_{1}\" type=\"fixed\">\n    <parent link=\"{0}\"/>\n    <child link=\"{1}_optical_frame\"/>\n    <origin xyz=\"{2:?} {3:?} {4:?}\" rpy=\"{5:?} {6:?} {7:?}\"/>\n  </joint>\n",
            super::VEHICLE_FRAME, reference, v.trans.x, v.trans.y, v.trans.z, r, pi, y
        ));
    }
    out.push_str(&format!("  <link name=\"{reference}_optical_frame\"/>\n"));
    for (c, p) in rig.session.cameras.iter().zip(&rig.ref_from_cam) {
        if c.id == rig.reference {
            continue;
        }
        let (r, pi, y) = rigcal_core::geometry::so3::to_rpy(&p.rot);
        out.push_str(&format!(
            "  <link name=\"{1}_optical_frame\"/>\n  <joint name=\"{0}_to_{1}\" type=\"fixed\">\n    <parent link=\"{0}_optical_frame\"/>\n    <child link=\"{1}_optical_frame\"/>\n    <origin xyz=\"{2:?} {3:?} {4:?}\" rpy=\"{5:?} {6:?} {7:?}\"/>\n  </joint>\n",
            reference, xml_attr(&c.id), p.trans.x, p.trans.y, p.trans.z, r, pi, y
        ));
    }
    out.push_str("</robot>\n");
    out
}
