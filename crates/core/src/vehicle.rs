//! A vehicle model: the nominal (CAD) rig of every vehicle of one model, the mounting
//! tolerances of each camera, where the vehicle frame sits relative to the reference
//! camera, and optionally acceptance thresholds of its own. See `docs/formats.md`.
//!
//! Why the deviation is measured as it is: the result's extrinsics are `ref_from_cam`, so
//! the deviation of a calibrated camera from its nominal is `t − t_nom` (reference axes)
//! and the rotation vector of `R · R_nomᵀ` (a left perturbation in the reference frame,
//! the same convention as the result's covariance). Per-axis tolerances bound those
//! components; a scalar tolerance bounds their norm (the rotation angle).

use crate::geometry::{so3, Pose};
use crate::result::ExtrinsicValue;
use crate::session::{check_identifier, InputError};
use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// The model as it travels (JSON).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct VehicleModel {
    pub reference_camera: String,
    pub cameras: Vec<NominalCamera>,
    /// The reference camera's pose in the vehicle frame: exports in the vehicle frame
    /// (`--frame vehicle`) compose every camera with it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vehicle_from_ref: Option<PoseSpec>,
    /// Acceptance thresholds for this model's jobs, in place of the tenant's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub acceptance_thresholds: Option<AcceptanceThresholds>,
    /// Robust z-score above which a vehicle's latest calibration is a fleet outlier
    /// (why 5 by default: `rigcal_service::fleet`).
    #[serde(default = "default_outlier_z")]
    pub fleet_outlier_z: f64,
}

fn default_outlier_z() -> f64 {
    5.0
}

/// One camera's nominal `ref_from_cam` and its tolerance.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct NominalCamera {
    pub id: String,
    pub translation: [f64; 3],
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rpy_deg: Option<[f64; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub quaternion_wxyz: Option<[f64; 4]>,
    /// The reference camera needs none (it is the frame).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tolerance: Option<Tolerance>,
}

/// A pose: translation (m) and either `rpy_deg` (`R = Rz(yaw)·Ry(pitch)·Rx(roll)`, as in
/// the result) or a unit quaternion `quaternion_wxyz`.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct PoseSpec {
    pub translation: [f64; 3],
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rpy_deg: Option<[f64; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub quaternion_wxyz: Option<[f64; 4]>,
}

/// A bound: one number bounds the norm, three bound each axis of the reference frame.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
#[serde(untagged)]
pub enum Bound {
    Norm(f64),
    PerAxis([f64; 3]),
}

#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Tolerance {
    pub translation_mm: Bound,
    pub rotation_deg: Bound,
}

/// Acceptance thresholds: a finished job passes when it succeeded and its residual RMS
/// and worst 1-σ are within them (and, with a vehicle model, every camera within its
/// mounting tolerance).
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct AcceptanceThresholds {
    pub max_rms_px: f64,
    pub max_sigma_translation_m: f64,
    pub max_sigma_rotation_deg: f64,
}

impl AcceptanceThresholds {
    /// Each a positive finite number within what a calibration can mean; `at` prefixes
    /// the field names (`acceptance_thresholds.` inside a vehicle model).
    pub fn check(&self, at: &str) -> Result<(), InputError> {
        for (field, v, max, unit) in [
            ("max_rms_px", self.max_rms_px, 100.0, "pixels"),
            (
                "max_sigma_translation_m",
                self.max_sigma_translation_m,
                10.0,
                "metres",
            ),
            (
                "max_sigma_rotation_deg",
                self.max_sigma_rotation_deg,
                180.0,
                "degrees",
            ),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= max) {
                return Err(InputError::new(
                    format!("{at}{field}"),
                    format!("a positive number of {unit} up to {max}, got {v}"),
                ));
            }
        }
        Ok(())
    }
}

impl NominalCamera {
    pub fn pose_spec(&self) -> PoseSpec {
        PoseSpec {
            translation: self.translation,
            rpy_deg: self.rpy_deg,
            quaternion_wxyz: self.quaternion_wxyz,
        }
    }
}

impl PoseSpec {
    /// The pose, checked: finite translation within 1 km, exactly one rotation given, a
    /// quaternion of unit norm (within 1e-6).
    pub fn pose(&self, at: &str) -> Result<Pose, InputError> {
        if !self
            .translation
            .iter()
            .all(|x| x.is_finite() && x.abs() <= 1000.0)
        {
            return Err(InputError::new(
                format!("{at}translation"),
                "three finite numbers of metres within ±1000",
            ));
        }
        let rot = match (self.rpy_deg, self.quaternion_wxyz) {
            (Some(r), None) => {
                if !r.iter().all(|x| x.is_finite() && x.abs() <= 360.0) {
                    return Err(InputError::new(
                        format!("{at}rpy_deg"),
                        "three finite angles in degrees within ±360",
                    ));
                }
                so3::from_rpy(r[0].to_radians(), r[1].to_radians(), r[2].to_radians())
            }
            (None, Some(q)) => {
                let n = q.iter().map(|x| x * x).sum::<f64>().sqrt();
                if !(n.is_finite() && (n - 1.0).abs() <= 1e-6) {
                    return Err(InputError::new(
                        format!("{at}quaternion_wxyz"),
                        format!("a unit quaternion (w, x, y, z), got norm {n}"),
                    ));
                }
                let uq = UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]));
                *uq.to_rotation_matrix().matrix()
            }
            _ => {
                return Err(InputError::new(
                    format!("{at}rpy_deg"),
                    "exactly one of rpy_deg and quaternion_wxyz",
                ))
            }
        };
        Ok(Pose::new(rot, Vector3::from(self.translation)))
    }
}

impl Bound {
    fn check(&self, field: &str, unit: &str, max: f64) -> Result<(), InputError> {
        let ok = |x: f64| x.is_finite() && x > 0.0 && x <= max;
        let good = match self {
            Bound::Norm(x) => ok(*x),
            Bound::PerAxis(xs) => xs.iter().all(|&x| ok(x)),
        };
        if good {
            Ok(())
        } else {
            Err(InputError::new(
                field,
                format!("a positive number of {unit} up to {max} (a bound on the norm) or three (one per axis)"),
            ))
        }
    }

    /// The sentences of the components of `v` (or its norm) that exceed the bound.
    fn exceeded(&self, v: &[f64; 3], what: &str, unit: &str) -> Vec<String> {
        const AXES: [&str; 3] = ["x", "y", "z"];
        match *self {
            Bound::Norm(max) => {
                let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
                if n > max {
                    vec![format!(
                        "{what} {n:.3} {unit} from nominal exceeds {max} {unit}"
                    )]
                } else {
                    vec![]
                }
            }
            Bound::PerAxis(max) => (0..3)
                .filter(|&i| v[i].abs() > max[i])
                .map(|i| {
                    format!(
                        "{what} along {} {:.3} {unit} from nominal exceeds {} {unit}",
                        AXES[i], v[i], max[i]
                    )
                })
                .collect(),
        }
    }
}

/// The most cameras a model may list.
pub const MAX_CAMERAS: usize = 64;

impl VehicleModel {
    /// Parse and check a model document; every error names its field.
    pub fn parse(bytes: &[u8]) -> Result<VehicleModel, InputError> {
        let m: VehicleModel = serde_json::from_slice(bytes).map_err(|e| {
            let msg = e.to_string();
            InputError::new("body", format!("a vehicle model (JSON): {msg}"))
        })?;
        m.check()?;
        Ok(m)
    }

    pub fn check(&self) -> Result<(), InputError> {
        check_identifier("reference_camera", &self.reference_camera)?;
        if self.cameras.is_empty() || self.cameras.len() > MAX_CAMERAS {
            return Err(InputError::new(
                "cameras",
                format!("1 to {MAX_CAMERAS} cameras, got {}", self.cameras.len()),
            ));
        }
        if !self.cameras.iter().any(|c| c.id == self.reference_camera) {
            return Err(InputError::new(
                "reference_camera",
                "one of the model's cameras",
            ));
        }
        for (i, c) in self.cameras.iter().enumerate() {
            let at = format!("cameras[{i}].");
            check_identifier(&format!("{at}id"), &c.id)?;
            if self.cameras[..i].iter().any(|o| o.id == c.id) {
                return Err(InputError::new(
                    format!("{at}id"),
                    format!("a camera id not listed before, got {} twice", c.id),
                ));
            }
            let pose = c.pose_spec().pose(&at)?;
            if c.id == self.reference_camera {
                if pose.trans.norm() > 1e-9 || so3::log(&pose.rot).norm() > 1e-9 {
                    return Err(InputError::new(
                        format!("{at}translation"),
                        "the reference camera at the origin with no rotation (it is the frame)",
                    ));
                }
            } else if let Some(t) = &c.tolerance {
                t.translation_mm
                    .check(&format!("{at}tolerance.translation_mm"), "mm", 10_000.0)?;
                t.rotation_deg
                    .check(&format!("{at}tolerance.rotation_deg"), "degrees", 180.0)?;
            } else {
                return Err(InputError::new(
                    format!("{at}tolerance"),
                    "{\"translation_mm\": …, \"rotation_deg\": …} for every camera but the reference",
                ));
            }
        }
        if let Some(v) = &self.vehicle_from_ref {
            v.pose("vehicle_from_ref.")?;
        }
        if let Some(t) = &self.acceptance_thresholds {
            t.check("acceptance_thresholds.")?;
        }
        if !(self.fleet_outlier_z.is_finite()
            && self.fleet_outlier_z >= 1.0
            && self.fleet_outlier_z <= 100.0)
        {
            return Err(InputError::new(
                "fleet_outlier_z",
                format!(
                    "a robust z-score between 1 and 100, got {}",
                    self.fleet_outlier_z
                ),
            ));
        }
        Ok(())
    }

    /// `ref_from_cam` of camera `id` (a checked model: the pose parses).
    pub fn nominal(&self, id: &str) -> Option<Pose> {
        let c = self.cameras.iter().find(|c| c.id == id)?;
        c.pose_spec().pose("").ok()
    }

    pub fn vehicle_from_ref(&self) -> Option<Pose> {
        self.vehicle_from_ref.as_ref()?.pose("").ok()
    }

    /// Whether a session's cameras fit the model: the same reference camera and every
    /// camera of one in the other. `Err` names the session's field.
    pub fn fits(&self, reference_camera: &str, cameras: &[&str]) -> Result<(), InputError> {
        if reference_camera != self.reference_camera {
            return Err(InputError::new(
                "reference_camera",
                format!(
                    "the vehicle model's reference camera {}, got {reference_camera}",
                    self.reference_camera
                ),
            ));
        }
        let model: Vec<&str> = self.cameras.iter().map(|c| c.id.as_str()).collect();
        let mut a = model.clone();
        let mut b = cameras.to_vec();
        a.sort_unstable();
        b.sort_unstable();
        if a != b {
            return Err(InputError::new(
                "cameras",
                format!(
                    "the cameras of the vehicle model ({}), got {}",
                    model.join(", "),
                    cameras.join(", ")
                ),
            ));
        }
        Ok(())
    }

    /// Every non-reference camera's deviation from its nominal, in the model's order;
    /// a camera the result lacks is reported missing (outside its tolerance). `Err` only
    /// for a model that never passed [`VehicleModel::check`] (a bug or a corrupt store):
    /// named, never skipped.
    pub fn deviations(&self, extrinsics: &[ExtrinsicValue]) -> Result<Vec<Deviation>, String> {
        let mut out = Vec::new();
        for c in self
            .cameras
            .iter()
            .filter(|c| c.id != self.reference_camera)
        {
            let internal = |why: String| format!("internal: vehicle model camera {}: {why}", c.id);
            let nominal = c
                .pose_spec()
                .pose("")
                .map_err(|e| internal(e.to_string()))?;
            let tol = c.tolerance.ok_or_else(|| internal("no tolerance".into()))?;
            out.push(match extrinsics.iter().find(|e| e.camera == c.id) {
                Some(e) => Deviation::of(&c.id, &nominal, &e.pose(), tol),
                None => Deviation {
                    camera: c.id.clone(),
                    translation_mm: None,
                    rotation_deg: None,
                    translation_norm_mm: None,
                    rotation_angle_deg: None,
                    tolerance: tol,
                    within_tolerance: false,
                    exceeded: vec![format!("camera {} has no calibrated extrinsic", c.id)],
                },
            });
        }
        Ok(out)
    }
}

/// One camera's deviation from its nominal pose and the verdict of its tolerance.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Deviation {
    pub camera: String,
    /// `t − t_nom` (mm, reference axes); `null` when the camera was not calibrated.
    pub translation_mm: Option<[f64; 3]>,
    /// Rotation vector of `R · R_nomᵀ` (deg, reference axes).
    pub rotation_deg: Option<[f64; 3]>,
    pub translation_norm_mm: Option<f64>,
    pub rotation_angle_deg: Option<f64>,
    pub tolerance: Tolerance,
    pub within_tolerance: bool,
    /// One sentence per exceeded bound.
    pub exceeded: Vec<String>,
}

impl Deviation {
    pub fn of(camera: &str, nominal: &Pose, calibrated: &Pose, tol: Tolerance) -> Deviation {
        let dt = (calibrated.trans - nominal.trans) * 1000.0;
        let dr = so3::log(&(calibrated.rot * nominal.rot.transpose())).map(f64::to_degrees);
        let t = [dt.x, dt.y, dt.z];
        let r = [dr.x, dr.y, dr.z];
        let mut exceeded =
            tol.translation_mm
                .exceeded(&t, &format!("camera {camera} translation"), "mm");
        exceeded.extend(
            tol.rotation_deg
                .exceeded(&r, &format!("camera {camera} rotation"), "deg"),
        );
        Deviation {
            camera: camera.to_string(),
            translation_mm: Some(t),
            rotation_deg: Some(r),
            translation_norm_mm: Some(dt.norm()),
            rotation_angle_deg: Some(dr.norm()),
            tolerance: tol,
            within_tolerance: exceeded.is_empty(),
            exceeded,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn model() -> serde_json::Value {
        json!({
            "reference_camera": "front",
            "cameras": [
                {"id": "front", "translation": [0.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 0.0]},
                {"id": "rear", "translation": [0.1, -0.2, -3.0], "rpy_deg": [0.0, 180.0, 0.0],
                 "tolerance": {"translation_mm": 5.0, "rotation_deg": [0.5, 0.5, 1.0]}},
                {"id": "left", "translation": [-0.8, 0.0, -1.5],
                 "quaternion_wxyz": [std::f64::consts::FRAC_1_SQRT_2, 0.0, -std::f64::consts::FRAC_1_SQRT_2, 0.0],
                 "tolerance": {"translation_mm": [2.0, 2.0, 2.0], "rotation_deg": 0.3}}
            ],
            "vehicle_from_ref": {"translation": [2.0, 0.0, 1.2], "rpy_deg": [-90.0, 0.0, -90.0]}
        })
    }

    fn parse(v: &serde_json::Value) -> Result<VehicleModel, InputError> {
        VehicleModel::parse(&serde_json::to_vec(v).unwrap())
    }

    #[test]
    fn the_nominal_rig_deviates_by_nothing_and_passes() {
        let m = parse(&model()).unwrap();
        assert_eq!(m.fleet_outlier_z, 5.0);
        let ex: Vec<_> = ["front", "rear", "left"]
            .iter()
            .map(|c| ExtrinsicValue::of(c, &m.nominal(c).unwrap()))
            .collect();
        let d = m.deviations(&ex).unwrap();
        assert_eq!(d.len(), 2);
        for d in &d {
            assert!(d.within_tolerance, "{d:?}");
            assert!(d.translation_norm_mm.unwrap() < 1e-9);
            assert!(d.rotation_angle_deg.unwrap() < 1e-9);
        }
    }

    #[test]
    fn a_known_offset_is_measured_exactly_and_judged_per_bound() {
        let m = parse(&model()).unwrap();
        let nom = m.nominal("rear").unwrap();
        // 3 mm along x, 3.9 mm along z (norm 4.92 mm, inside 5 mm); 0.6° about y
        // (outside the per-axis 0.5°), applied on the left as the deviation is measured.
        let dr = Vector3::new(0.0, 0.6f64.to_radians(), 0.0);
        let moved = Pose::new(
            so3::exp(&dr) * nom.rot,
            nom.trans + Vector3::new(0.003, 0.0, 0.0039),
        );
        let d = Deviation::of("rear", &nom, &moved, m.cameras[1].tolerance.unwrap());
        let t = d.translation_mm.unwrap();
        let r = d.rotation_deg.unwrap();
        assert!((t[0] - 3.0).abs() < 1e-9 && t[1].abs() < 1e-9 && (t[2] - 3.9).abs() < 1e-9);
        assert!((d.translation_norm_mm.unwrap() - 24.21f64.sqrt()).abs() < 1e-9);
        assert!(r[0].abs() < 1e-9 && (r[1] - 0.6).abs() < 1e-9 && r[2].abs() < 1e-9);
        assert!(!d.within_tolerance);
        assert_eq!(d.exceeded.len(), 1, "{:?}", d.exceeded);
        assert!(
            d.exceeded[0].contains("rotation along y"),
            "{:?}",
            d.exceeded
        );
        // 2° about the left camera's bracket: outside its 0.3° norm bound.
        let nl = m.nominal("left").unwrap();
        let off = Pose::new(
            so3::exp(&Vector3::new(0.0, 0.0, 2f64.to_radians())) * nl.rot,
            nl.trans,
        );
        let dl = m
            .deviations(&[
                ExtrinsicValue::of("front", &Pose::identity()),
                ExtrinsicValue::of("rear", &nom),
                ExtrinsicValue::of("left", &off),
            ])
            .unwrap();
        assert!(dl[0].within_tolerance);
        assert!(!dl[1].within_tolerance);
        assert!((dl[1].rotation_angle_deg.unwrap() - 2.0).abs() < 1e-9);
        assert!(
            dl[1].exceeded[0].contains("2.000 deg from nominal exceeds 0.3"),
            "{:?}",
            dl[1].exceeded
        );
    }

    #[test]
    fn a_camera_missing_from_the_result_is_outside_its_tolerance() {
        let m = parse(&model()).unwrap();
        let d = m
            .deviations(&[ExtrinsicValue::of("front", &Pose::identity())])
            .unwrap();
        assert!(d
            .iter()
            .all(|d| !d.within_tolerance && d.translation_mm.is_none()));
        assert!(d[0].exceeded[0].contains("no calibrated extrinsic"));
    }

    #[test]
    fn an_unchecked_model_is_an_internal_error_not_a_skipped_camera() {
        let mut m = parse(&model()).unwrap();
        m.cameras[2].tolerance = None;
        let e = m.deviations(&[]).unwrap_err();
        assert!(e.starts_with("internal: vehicle model camera left"), "{e}");
    }

    #[test]
    fn every_bad_field_is_named() {
        type Edit = Box<dyn Fn(&mut serde_json::Value)>;
        let cases: Vec<(&str, Edit)> = vec![
            (
                "reference_camera",
                Box::new(|v| v["reference_camera"] = json!("side")),
            ),
            ("cameras", Box::new(|v| v["cameras"] = json!([]))),
            (
                "cameras[2].id",
                Box::new(|v| v["cameras"][2]["id"] = json!("rear")),
            ),
            (
                "cameras[1].id",
                Box::new(|v| v["cameras"][1]["id"] = json!("re ar")),
            ),
            (
                "cameras[1].translation",
                Box::new(|v| v["cameras"][1]["translation"] = json!([0.0, 1e9, 0.0])),
            ),
            (
                "cameras[1].rpy_deg",
                Box::new(|v| {
                    v["cameras"][1]["quaternion_wxyz"] = json!([1.0, 0.0, 0.0, 0.0]);
                }),
            ),
            (
                "cameras[2].quaternion_wxyz",
                Box::new(|v| v["cameras"][2]["quaternion_wxyz"] = json!([1.0, 1.0, 0.0, 0.0])),
            ),
            (
                "cameras[1].tolerance",
                Box::new(|v| {
                    v["cameras"][1].as_object_mut().unwrap().remove("tolerance");
                }),
            ),
            (
                "cameras[1].tolerance.translation_mm",
                Box::new(|v| v["cameras"][1]["tolerance"]["translation_mm"] = json!(-1.0)),
            ),
            (
                "cameras[2].tolerance.rotation_deg",
                Box::new(|v| v["cameras"][2]["tolerance"]["rotation_deg"] = json!([0.1, 0.0, 0.1])),
            ),
            (
                "cameras[0].translation",
                Box::new(|v| v["cameras"][0]["translation"] = json!([0.0, 0.1, 0.0])),
            ),
            (
                "vehicle_from_ref.rpy_deg",
                Box::new(|v| v["vehicle_from_ref"]["rpy_deg"] = json!([0.0, f64::MAX, 0.0])),
            ),
            (
                "acceptance_thresholds.max_rms_px",
                Box::new(
                    |v| v["acceptance_thresholds"] = json!({"max_rms_px": 0.0, "max_sigma_translation_m": 0.01, "max_sigma_rotation_deg": 0.1}),
                ),
            ),
            (
                "fleet_outlier_z",
                Box::new(|v| v["fleet_outlier_z"] = json!(0.5)),
            ),
            ("body", Box::new(|v| v["colour"] = json!("red"))),
        ];
        for (field, edit) in cases {
            let mut v = model();
            edit(&mut v);
            let e = parse(&v).expect_err(field);
            assert_eq!(e.field, field, "{e}");
        }
        let fit = parse(&model()).unwrap();
        assert_eq!(
            fit.fits("rear", &["front", "rear", "left"])
                .unwrap_err()
                .field,
            "reference_camera"
        );
        assert_eq!(
            fit.fits("front", &["front", "rear"]).unwrap_err().field,
            "cameras"
        );
        assert!(fit.fits("front", &["left", "front", "rear"]).is_ok());
    }
}
