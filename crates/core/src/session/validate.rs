//! Validation: the manifest becomes a [`Session`] or an [`InputError`] naming the field.

use super::lines::{validate_vanishing, VanishingInput};
use super::raw::*;
use super::InputError;
use crate::geometry::{Camera, CameraModel, Vec2, Vec3};
use crate::target::board::{tag_corner, GridLayout};
use std::collections::{BTreeMap, HashMap, HashSet};

/// Largest accepted counts; beyond them a session is refused, not truncated.
pub const MAX_CAMERAS: usize = 64;
pub const MAX_FRAMES: usize = 100_000;
pub const MAX_IMAGE_SIDE: u32 = 65_536;
/// Default 1-σ of a measured distance (Lébraly §5.1 uses 0.5 mm).
pub const DEFAULT_DISTANCE_SIGMA: f64 = 5e-4;

#[derive(Clone, Debug)]
pub struct NamedCamera {
    pub id: String,
    pub camera: Camera,
}

#[derive(Clone, Copy, Debug)]
pub struct Observation {
    /// Index into [`ResolvedPoints::ids`].
    pub point: usize,
    pub uv: Vec2,
}

#[derive(Clone, Debug)]
pub struct Frame {
    pub index: i64,
    /// Observations per camera (indexed like [`Session::cameras`]).
    pub observations: Vec<Vec<Observation>>,
}

#[derive(Clone, Debug)]
pub struct Distance {
    pub a: usize,
    pub b: usize,
    pub distance: f64,
    pub sigma: f64,
}

/// What we know of a point's geometry.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PointKind {
    /// Unknown coordinates: reconstructed (two-view SfM, triangulation) and refined.
    Free,
    /// A point of a rigid body of known geometry, at `local` in the body's frame.
    Body { body: usize, local: Vec3 },
}

/// A rigid body: an AprilGrid board, one tag of an `apriltags` target, or a `points` target.
#[derive(Clone, Debug)]
pub struct Body {
    pub name: String,
    pub planar: bool,
}

/// Every point id the session mentions, with its kind.
#[derive(Clone, Debug, Default)]
pub struct ResolvedPoints {
    pub ids: Vec<String>,
    pub kinds: Vec<PointKind>,
    pub bodies: Vec<Body>,
    index: HashMap<String, usize>,
}

impl ResolvedPoints {
    pub fn get(&self, id: &str) -> Option<usize> {
        self.index.get(id).copied()
    }
    fn insert(&mut self, id: &str, kind: PointKind) -> usize {
        if let Some(&i) = self.index.get(id) {
            return i;
        }
        self.ids.push(id.to_string());
        self.kinds.push(kind);
        self.index.insert(id.to_string(), self.ids.len() - 1);
        self.ids.len() - 1
    }
}

/// A validated capture session.
#[derive(Clone, Debug)]
pub struct Session {
    pub manifest: SessionManifest,
    pub cameras: Vec<NamedCamera>,
    pub reference: usize,
    pub frames: Vec<Frame>,
    pub points: ResolvedPoints,
    pub distances: Vec<Distance>,
    /// Per camera: prior height above the reference camera along the motion-plane normal.
    pub height_priors: Vec<Option<f64>>,
    /// The vanishing method's targets, line points and ring (method `vanishing` only).
    pub vanishing: Option<VanishingInput>,
}

impl Session {
    pub fn camera_index(&self, id: &str) -> Option<usize> {
        self.cameras.iter().position(|c| c.id == id)
    }
}

fn finite(field: String, x: f64) -> Result<f64, InputError> {
    if x.is_finite() {
        Ok(x)
    } else {
        Err(InputError::new(field, "a finite number"))
    }
}

/// Parse a session manifest from JSON bytes and validate it.
pub fn parse_session(bytes: &[u8]) -> Result<Session, InputError> {
    let de = &mut serde_json::Deserializer::from_slice(bytes);
    let manifest: SessionManifest = serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let path = if path == "." {
            "(document)".to_string()
        } else {
            path
        };
        InputError::new(path, e.inner().to_string())
    })?;
    validate(manifest)
}

/// A camera model from its manifest entry; `at` is the entry's field path for errors.
pub fn camera_from_spec(spec: &CameraSpec, at: &str) -> Result<Camera, InputError> {
    let d = &spec.distortion;
    for (k, x) in d.iter().enumerate() {
        finite(format!("{at}.distortion[{k}]"), *x)?;
    }
    let model = match spec.model.as_str() {
        "pinhole" if d.is_empty() || d.iter().all(|x| *x == 0.0) => CameraModel::Pinhole,
        "pinhole" => {
            return Err(InputError::new(
                format!("{at}.distortion"),
                "no coefficients for model pinhole (use radtan or equidistant)",
            ))
        }
        "radtan" if d.len() == 4 || d.len() == 5 => CameraModel::Radtan {
            k1: d[0],
            k2: d[1],
            p1: d[2],
            p2: d[3],
            k3: d.get(4).copied().unwrap_or(0.0),
        },
        "radtan" => {
            return Err(InputError::new(
                format!("{at}.distortion"),
                format!(
                    "4 or 5 coefficients [k1, k2, p1, p2, (k3)] for radtan, got {}",
                    d.len()
                ),
            ))
        }
        "equidistant" if d.len() == 4 => CameraModel::Equidistant {
            k1: d[0],
            k2: d[1],
            k3: d[2],
            k4: d[3],
        },
        "equidistant" => {
            return Err(InputError::new(
                format!("{at}.distortion"),
                format!(
                    "4 coefficients [k1, k2, k3, k4] for equidistant, got {}",
                    d.len()
                ),
            ))
        }
        other => {
            return Err(InputError::new(
                format!("{at}.model"),
                format!("one of pinhole, radtan, equidistant, got {other:?}"),
            ))
        }
    };
    if spec.width == 0
        || spec.height == 0
        || spec.width > MAX_IMAGE_SIDE
        || spec.height > MAX_IMAGE_SIDE
    {
        return Err(InputError::new(
            format!("{at}.width"),
            format!(
                "width and height between 1 and {MAX_IMAGE_SIDE} pixels, got {}×{}",
                spec.width, spec.height
            ),
        ));
    }
    let k = &spec.intrinsics;
    for (name, x) in [("fx", k.fx), ("fy", k.fy), ("cx", k.cx), ("cy", k.cy)] {
        finite(format!("{at}.intrinsics.{name}"), x)?;
    }
    let (w, h) = (spec.width as f64, spec.height as f64);
    if k.fx <= 0.0 || k.fy <= 0.0 || k.fx > 100.0 * w || k.fy > 100.0 * h {
        return Err(InputError::new(
            format!("{at}.intrinsics.fx"),
            format!(
                "positive focal lengths below 100× the image size, got fx={} fy={}",
                k.fx, k.fy
            ),
        ));
    }
    if k.cx < -0.5 || k.cx > w - 0.5 || k.cy < -0.5 || k.cy > h - 0.5 {
        return Err(InputError::new(
            format!("{at}.intrinsics.cx"),
            format!(
                "a principal point inside the {}×{} image, got ({}, {})",
                spec.width, spec.height, k.cx, k.cy
            ),
        ));
    }
    Ok(Camera {
        model,
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
        width: spec.width,
        height: spec.height,
    })
}

/// Image paths are relative to the manifest and stay inside the session.
pub(super) fn check_image_path(path: &str, field: &str) -> Result<(), InputError> {
    let safe = !path.is_empty()
        && path.len() <= 512
        && !path.starts_with('/')
        && !path.contains('\\')
        && path
            .split('/')
            .all(|p| !p.is_empty() && p != "." && p != "..");
    if safe {
        Ok(())
    } else {
        Err(InputError::new(
            field,
            format!("a relative image path without '..' (at most 512 characters), got {path:?}"),
        ))
    }
}

/// Parse `tag:<id>:<corner>`.
fn parse_tag_point(id: &str) -> Option<(u32, usize)> {
    let mut it = id.strip_prefix("tag:")?.split(':');
    let tag = it.next()?.parse().ok()?;
    let corner: usize = it.next()?.parse().ok()?;
    (it.next().is_none() && corner < 4).then_some((tag, corner))
}

/// A 2D board point on the target plane `z = 0`.
fn on_plane(p: crate::geometry::Vec2) -> Vec3 {
    Vec3::new(p.x, p.y, 0.0)
}

/// Resolve a point id against the targets: a body point if a target defines it, free otherwise.
pub fn resolve_points(
    targets: &[TargetSpec],
    ids: impl IntoIterator<Item = String>,
) -> ResolvedPoints {
    let mut out = ResolvedPoints::default();
    let mut tag_bodies: HashMap<(usize, u32), usize> = HashMap::new();
    let mut target_body: HashMap<usize, usize> = HashMap::new();
    for id in ids {
        if out.get(&id).is_some() {
            continue;
        }
        let mut kind = PointKind::Free;
        for (ti, t) in targets.iter().enumerate() {
            match t {
                TargetSpec::Aprilgrid { id: name, .. } => {
                    let corner = parse_tag_point(&id)
                        .and_then(|(tag, c)| GridLayout::of(t).and_then(|g| g.corner(tag, c)));
                    if let Some(local) = corner {
                        let body = *target_body.entry(ti).or_insert_with(|| {
                            out.bodies.push(Body {
                                name: name.clone(),
                                planar: true,
                            });
                            out.bodies.len() - 1
                        });
                        kind = PointKind::Body {
                            body,
                            local: on_plane(local),
                        };
                        break;
                    }
                }
                TargetSpec::Apriltags {
                    id: name,
                    tag_size,
                    ids,
                } => {
                    if let Some((tag, c)) = parse_tag_point(&id) {
                        if ids.as_ref().is_none_or(|v| v.contains(&tag)) {
                            let body = *tag_bodies.entry((ti, tag)).or_insert_with(|| {
                                out.bodies.push(Body {
                                    name: format!("{name}/tag:{tag}"),
                                    planar: true,
                                });
                                out.bodies.len() - 1
                            });
                            let h = tag_size / 2.0;
                            kind = PointKind::Body {
                                body,
                                local: on_plane(
                                    tag_corner(*tag_size, c) - crate::geometry::Vec2::new(h, h),
                                ),
                            };
                            break;
                        }
                    }
                }
                TargetSpec::Points { id: name, points } => {
                    if let Some(xyz) = points.get(&id) {
                        let body = *target_body.entry(ti).or_insert_with(|| {
                            out.bodies.push(Body {
                                name: name.clone(),
                                planar: points_planar(points),
                            });
                            out.bodies.len() - 1
                        });
                        kind = PointKind::Body {
                            body,
                            local: Vec3::new(xyz[0], xyz[1], xyz[2]),
                        };
                        break;
                    }
                }
                TargetSpec::LineTarget { .. }
                | TargetSpec::LineGrid { .. }
                | TargetSpec::LineSegments { .. } => {}
            }
        }
        out.insert(&id, kind);
    }
    out
}

/// Are the points (nearly) coplanar? Decides homography vs DLT for their pose.
fn points_planar(points: &BTreeMap<String, [f64; 3]>) -> bool {
    let pts: Vec<Vec3> = points
        .values()
        .map(|p| Vec3::new(p[0], p[1], p[2]))
        .collect();
    crate::geometry::plane::is_planar(&pts)
}

/// Validate a manifest already in memory (e.g. after the detection stage filled in
/// observations): the same checks as [`parse_session`].
pub fn from_manifest(m: SessionManifest) -> Result<Session, InputError> {
    validate(m)
}

fn validate(m: SessionManifest) -> Result<Session, InputError> {
    if m.version != 1 {
        return Err(InputError::new("version", format!("1, got {}", m.version)));
    }
    if m.cameras.is_empty() {
        return Err(InputError::new("cameras", "at least one camera"));
    }
    if m.cameras.len() > MAX_CAMERAS {
        return Err(InputError::new(
            "cameras",
            format!("at most {MAX_CAMERAS} cameras, got {}", m.cameras.len()),
        ));
    }
    if m.frames.len() > MAX_FRAMES {
        return Err(InputError::new(
            "frames",
            format!("at most {MAX_FRAMES} frames, got {}", m.frames.len()),
        ));
    }
    if let Some(v) = &m.vehicle_id {
        super::check_identifier("vehicle_id", v)?;
    }
    if let Some(v) = &m.vehicle_model {
        super::check_identifier("vehicle_model", v)?;
    }
    let mut cameras = Vec::new();
    let mut seen = HashSet::new();
    for (i, c) in m.cameras.iter().enumerate() {
        let at = format!("cameras[{i}]");
        super::check_identifier(&format!("{at}.id"), &c.id)?;
        if !seen.insert(c.id.clone()) {
            return Err(InputError::new(
                format!("{at}.id"),
                format!("an id unique among cameras, got {:?}", c.id),
            ));
        }
        cameras.push(NamedCamera {
            id: c.id.clone(),
            camera: camera_from_spec(c, &at)?,
        });
    }
    let cam_index: HashMap<&str, usize> = cameras
        .iter()
        .enumerate()
        .map(|(i, c)| (c.id.as_str(), i))
        .collect();
    let reference = *cam_index.get(m.reference_camera.as_str()).ok_or_else(|| {
        InputError::new(
            "reference_camera",
            format!(
                "one of the camera ids {:?}, got {:?}",
                cameras.iter().map(|c| &c.id).collect::<Vec<_>>(),
                m.reference_camera
            ),
        )
    })?;

    let mut target_ids = HashSet::new();
    let mut point_owner: HashMap<&str, usize> = HashMap::new();
    for (i, t) in m.targets.iter().enumerate() {
        let at = format!("targets[{i}]");
        super::check_identifier(&format!("{at}.id"), t.id())?;
        if !target_ids.insert(t.id().to_string()) {
            return Err(InputError::new(
                format!("{at}.id"),
                format!("an id unique among targets, got {:?}", t.id()),
            ));
        }
        let positive = |name: &str, x: f64| -> Result<(), InputError> {
            if x.is_finite() && x > 0.0 {
                Ok(())
            } else {
                Err(InputError::new(
                    format!("{at}.{name}"),
                    format!("a positive length in metres, got {x}"),
                ))
            }
        };
        match t {
            TargetSpec::Aprilgrid {
                rows,
                cols,
                tag_size,
                tag_spacing,
                ..
            } => {
                positive("tag_size", *tag_size)?;
                if !(tag_spacing.is_finite() && *tag_spacing >= 0.0) {
                    return Err(InputError::new(
                        format!("{at}.tag_spacing"),
                        "a non-negative ratio of the tag size",
                    ));
                }
                if *rows == 0 || *cols == 0 || rows * cols > 100_000 {
                    return Err(InputError::new(
                        format!("{at}.rows"),
                        "between 1 and 100000 tags in the grid",
                    ));
                }
            }
            TargetSpec::Apriltags { tag_size, .. } => positive("tag_size", *tag_size)?,
            TargetSpec::LineTarget {
                length, spacing, ..
            } => {
                positive("length", *length)?;
                positive("spacing", *spacing)?;
            }
            TargetSpec::LineGrid {
                length,
                spacing,
                stroke,
                ..
            } => {
                positive("length", *length)?;
                positive("spacing", *spacing)?;
                positive("stroke", *stroke)?;
            }
            TargetSpec::LineSegments { stroke, .. } => positive("stroke", *stroke)?,
            TargetSpec::Points { points, .. } => {
                if points.len() < 4 {
                    return Err(InputError::new(
                        format!("{at}.points"),
                        "at least 4 points with coordinates",
                    ));
                }
                for (pid, xyz) in points {
                    super::check_point_id(&format!("{at}.points"), pid)?;
                    for (k, x) in xyz.iter().enumerate() {
                        finite(format!("{at}.points.{pid}[{k}]"), *x)?;
                    }
                    if let Some(prev) = point_owner.insert(pid, i) {
                        return Err(InputError::new(
                            format!("{at}.points.{pid}"),
                            format!("a point id not already defined by targets[{prev}]"),
                        ));
                    }
                }
            }
        }
    }
    let motion_only = |field: &str, present: bool| {
        if present && m.method == Method::Motion {
            Err(InputError::new(
                field,
                "absent in a motion-method session (it belongs to method \"vanishing\")",
            ))
        } else {
            Ok(())
        }
    };
    motion_only("auxiliary_camera", m.auxiliary_camera.is_some())?;
    motion_only("ring", !m.ring.is_empty())?;
    for (fi, f) in m.frames.iter().enumerate() {
        motion_only(&format!("frames[{fi}].lines"), !f.lines.is_empty())?;
        motion_only(
            &format!("frames[{fi}].line_targets"),
            !f.line_targets.is_empty(),
        )?;
    }
    if m.method == Method::Motion && m.targets.iter().any(TargetSpec::is_line_target) {
        return Err(InputError::new("targets", "no line_target, line_grid or line_segments in a motion-method session (line targets belong to method \"vanishing\")"));
    }

    // Frames: observations per camera, every number checked.
    let mut indices = HashSet::new();
    let mut all_ids: Vec<String> = Vec::new();
    for (fi, f) in m.frames.iter().enumerate() {
        if !indices.insert(f.index) {
            return Err(InputError::new(
                format!("frames[{fi}].index"),
                format!("a frame index unique in the session, {} repeats", f.index),
            ));
        }
        for cam in f.images.keys() {
            if !cam_index.contains_key(cam.as_str()) {
                return Err(InputError::new(
                    format!("frames[{fi}].images.{cam}"),
                    "a camera id declared in cameras[]",
                ));
            }
        }
        for (cam, path) in &f.images {
            check_image_path(path, &format!("frames[{fi}].images.{cam}"))?;
        }
        for (cam, obs) in &f.observations {
            let ci = *cam_index.get(cam.as_str()).ok_or_else(|| {
                InputError::new(
                    format!("frames[{fi}].observations.{cam}"),
                    "a camera id declared in cameras[]",
                )
            })?;
            let c = &cameras[ci].camera;
            let mut in_frame = HashSet::new();
            for (oi, o) in obs.iter().enumerate() {
                let at = format!("frames[{fi}].observations.{cam}[{oi}]");
                finite(format!("{at}.u"), o.u)?;
                finite(format!("{at}.v"), o.v)?;
                if !c.in_image(&Vec2::new(o.u, o.v)) {
                    return Err(InputError::new(
                        format!("{at}.u"),
                        format!(
                            "a pixel inside the {}×{} image of camera {cam}, got ({}, {})",
                            c.width, c.height, o.u, o.v
                        ),
                    ));
                }
                super::check_point_id(&format!("{at}.point"), &o.point)?;
                if !in_frame.insert(o.point.as_str()) {
                    return Err(InputError::new(
                        format!("{at}.point"),
                        format!("a point id seen once per image, got {:?}", o.point),
                    ));
                }
                all_ids.push(o.point.clone());
            }
        }
    }
    let points = resolve_points(&m.targets, all_ids);

    let frames = m
        .frames
        .iter()
        .map(|f| {
            let mut observations = vec![Vec::new(); cameras.len()];
            for (cam, obs) in &f.observations {
                let ci = cam_index[cam.as_str()];
                observations[ci] = obs
                    .iter()
                    .filter_map(|o| {
                        points.get(&o.point).map(|p| Observation {
                            point: p,
                            uv: Vec2::new(o.u, o.v),
                        })
                    })
                    .collect();
            }
            Frame {
                index: f.index,
                observations,
            }
        })
        .collect();

    let mut distances = Vec::new();
    for (i, s) in m.scale.iter().enumerate() {
        let at = format!("scale[{i}]");
        let a = points.get(&s.a).ok_or_else(|| {
            InputError::new(
                format!("{at}.a"),
                format!("a point id observed in some frame, got {:?}", s.a),
            )
        })?;
        let b = points.get(&s.b).ok_or_else(|| {
            InputError::new(
                format!("{at}.b"),
                format!("a point id observed in some frame, got {:?}", s.b),
            )
        })?;
        if a == b {
            return Err(InputError::new(
                format!("{at}.b"),
                "a point different from a",
            ));
        }
        if !(s.distance.is_finite() && s.distance > 0.0) {
            return Err(InputError::new(
                format!("{at}.distance"),
                format!("a positive distance in metres, got {}", s.distance),
            ));
        }
        let sigma = s.sigma.unwrap_or(DEFAULT_DISTANCE_SIGMA);
        if !(sigma.is_finite() && sigma > 0.0) {
            return Err(InputError::new(
                format!("{at}.sigma"),
                format!("a positive standard deviation in metres, got {sigma}"),
            ));
        }
        distances.push(Distance {
            a,
            b,
            distance: s.distance,
            sigma,
        });
    }

    let mut height_priors = vec![None; cameras.len()];
    if let Some(p) = &m.priors {
        for (cam, h) in &p.height_offsets {
            let ci = *cam_index.get(cam.as_str()).ok_or_else(|| {
                InputError::new(
                    format!("priors.height_offsets.{cam}"),
                    "a camera id declared in cameras[]",
                )
            })?;
            height_priors[ci] = Some(finite(format!("priors.height_offsets.{cam}"), *h)?);
        }
    }

    let vanishing = if m.method == Method::Vanishing {
        Some(validate_vanishing(&m, &cameras)?)
    } else {
        None
    };
    Ok(Session {
        vanishing,
        manifest: m,
        cameras,
        reference,
        frames,
        points,
        distances,
        height_priors,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn minimal() -> serde_json::Value {
        serde_json::json!({
            "reference_camera": "front",
            "cameras": [
                {"id": "front", "model": "pinhole", "width": 640, "height": 480, "intrinsics": {"fx": 500, "fy": 500, "cx": 320, "cy": 240}},
                {"id": "rear", "model": "radtan", "width": 640, "height": 480, "intrinsics": {"fx": 500, "fy": 500, "cx": 320, "cy": 240}, "distortion": [0.1, 0.0, 0.0, 0.0]}
            ],
            "targets": [{"id": "grid", "type": "aprilgrid", "rows": 2, "cols": 3, "tag_size": 0.1, "tag_spacing": 0.3, "first_id": 0}],
            "frames": [{"index": 0, "observations": {"front": [{"point": "tag:4:2", "u": 10.0, "v": 20.0}, {"point": "p7", "u": 1.0, "v": 2.0}]}}],
        })
    }

    fn err(v: serde_json::Value) -> InputError {
        parse_session(v.to_string().as_bytes()).unwrap_err()
    }

    #[test]
    fn resolves_aprilgrid_corners_and_free_points() {
        let s = parse_session(minimal().to_string().as_bytes()).unwrap();
        let p = s.points.get("tag:4:2").unwrap();
        // tag 4 is row 1, col 1; pitch 0.13; corner 2 is (+s, +s).
        match s.points.kinds[p] {
            PointKind::Body { local, .. } => {
                assert!((local - Vec3::new(0.23, 0.23, 0.0)).norm() < 1e-12)
            }
            k => panic!("{k:?}"),
        }
        assert_eq!(s.points.kinds[s.points.get("p7").unwrap()], PointKind::Free);
    }

    #[test]
    fn errors_name_the_field() {
        let mut v = minimal();
        v["frames"][0]["observations"]["front"][1]["u"] = serde_json::json!("x");
        assert_eq!(err(v).field, "frames[0].observations.front[1].u");

        let mut v = minimal();
        v["frames"][0]["observations"]["side"] = serde_json::json!([]);
        assert_eq!(err(v).field, "frames[0].observations.side");

        let mut v = minimal();
        v["cameras"][1]["intrinsics"]["cx"] = serde_json::json!(5000.0);
        assert_eq!(err(v).field, "cameras[1].intrinsics.cx");

        let mut v = minimal();
        v["cameras"][1]["distortion"] = serde_json::json!([0.1]);
        assert_eq!(err(v).field, "cameras[1].distortion");

        let mut v = minimal();
        v["scale"] = serde_json::json!([{"a": "p7", "b": "nope", "distance": 1.0}]);
        assert_eq!(err(v).field, "scale[0].b");

        let mut v = minimal();
        v["reference_camera"] = serde_json::json!("left");
        assert_eq!(err(v).field, "reference_camera");

        let mut v = minimal();
        v["frames"][0]["observations"]["front"][0]["v"] = serde_json::json!(1e308 * 10.0);
        assert!(err(v).field.starts_with("frames[0].observations.front[0]"));

        let mut v = minimal();
        v["frames"][0]["observations"]["front"][0]["u"] = serde_json::json!(900.0);
        assert_eq!(err(v).field, "frames[0].observations.front[0].u");

        assert!(parse_session(b"{not json").is_err());
    }
}
