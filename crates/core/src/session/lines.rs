//! Validation of the vanishing method's inputs: line targets, rig cameras' line points,
//! the auxiliary camera and its ring of views. Structural problems are input errors
//! naming the field; geometric ones (a target no auxiliary view links, a broken ring)
//! are left to the solver, which explains them in the result document.

use super::raw::*;
use super::validate::{camera_from_spec, NamedCamera};
use super::InputError;
use crate::geometry::{Camera, Vec2};
use crate::target::line_layout::{Axis, LineLayout};
use std::collections::{BTreeMap, HashMap};

/// Points per line above which a session is refused (a 65 536 px line sampled twice per pixel).
pub const MAX_POINTS_PER_LINE: usize = 131_072;
/// Ring views above which a session is refused.
pub const MAX_RING_VIEWS: usize = 10_000;

/// A target of two orthogonal groups of parallel lines, by its layout.
#[derive(Clone, Debug)]
pub struct LineTargetDef {
    pub id: String,
    pub layout: LineLayout,
}

/// Lines per group and per target above which a session is refused.
pub const MAX_LINES_PER_GROUP: u32 = 64;

/// The layout of a line target spec (`at`: its field, e.g. `targets[2]`); structural
/// problems name their field.
pub fn line_layout(t: &TargetSpec, at: &str) -> Result<LineLayout, InputError> {
    let layout = match t {
        TargetSpec::LineTarget {
            length, spacing, ..
        } => {
            if spacing >= length {
                return Err(InputError::new(
                    format!("{at}.spacing"),
                    format!("a spacing L2 smaller than the length L1 = {length} m, got {spacing}"),
                ));
            }
            LineLayout::l_target(*length, *spacing)
        }
        TargetSpec::LineGrid {
            length,
            spacing,
            lines_x,
            lines_y,
            stroke,
            mark,
            ..
        } => {
            for (name, n) in [("lines_x", lines_x), ("lines_y", lines_y)] {
                if !(2..=MAX_LINES_PER_GROUP).contains(n) {
                    return Err(InputError::new(
                        format!("{at}.{name}"),
                        format!("between 2 and {MAX_LINES_PER_GROUP} lines (a vanishing point needs two), got {n}"),
                    ));
                }
            }
            // The outermost lines of each group must cross the other group's lines.
            let span = (*lines_x.max(lines_y) - 1) as f64 * spacing;
            if span >= *length {
                return Err(InputError::new(
                    format!("{at}.spacing"),
                    format!(
                        "a spacing for which every line crosses the other group's lines ((lines − 1) × spacing = {span} m shorter than length = {length} m), got {spacing}"
                    ),
                ));
            }
            if stroke * 2.0 >= *spacing {
                return Err(InputError::new(
                    format!("{at}.stroke"),
                    format!("a stroke narrower than half the spacing ({spacing} m), got {stroke}"),
                ));
            }
            with_mark(
                LineLayout::grid(
                    *length,
                    *spacing,
                    *lines_x as usize,
                    *lines_y as usize,
                    *stroke,
                ),
                mark,
                at,
            )?
        }
        TargetSpec::LineSegments {
            segments,
            stroke,
            mark,
            ..
        } => {
            let layout = LineLayout::from_sheet_segments(segments, *stroke)
                .map_err(|(k, why)| InputError::new(format!("{at}.segments[{k}]"), why))?;
            for axis in [Axis::X, Axis::Z] {
                let n = layout.group(axis).len();
                if !(2..=MAX_LINES_PER_GROUP as usize).contains(&n) {
                    let name = if axis == Axis::X { "x" } else { "y" };
                    return Err(InputError::new(
                        format!("{at}.segments"),
                        format!("between 2 and {MAX_LINES_PER_GROUP} segments along the sheet's {name} axis (a vanishing point needs two), got {n}"),
                    ));
                }
            }
            for (g, axis) in [(Axis::X, "x"), (Axis::Z, "y")] {
                let mut offsets: Vec<f64> = layout
                    .group(g)
                    .iter()
                    .map(|&m| {
                        let s = layout.segments[m];
                        if g == Axis::X {
                            s.from.z
                        } else {
                            s.from.x
                        }
                    })
                    .collect();
                offsets.sort_by(f64::total_cmp);
                if offsets.windows(2).any(|w| w[1] - w[0] <= 2.0 * stroke) {
                    return Err(InputError::new(
                        format!("{at}.segments"),
                        format!("segments along the sheet's {axis} axis on distinct lines more than two strokes ({stroke} m) apart"),
                    ));
                }
            }
            with_mark(layout, mark, at)?
        }
        _ => return Err(InputError::new(
            format!("{at}.type"),
            "line_target, line_grid or line_segments (the vanishing method uses only line targets)",
        )),
    };
    Ok(layout)
}

/// `layout` with the orientation mark of its spec (`at.mark`), which must be readable:
/// clear of every stroke by a stroke width, and moved by every symmetry of the lines by
/// more than its diameter (so no other labelling puts a disc where the mark is).
fn with_mark(
    layout: LineLayout,
    mark: &Option<MarkSpec>,
    at: &str,
) -> Result<LineLayout, InputError> {
    let Some(m) = mark else {
        return Ok(layout);
    };
    for (name, v) in [("x", m.x), ("y", m.y)] {
        if !v.is_finite() {
            return Err(InputError::new(
                format!("{at}.mark.{name}"),
                format!("a finite sheet coordinate (m), got {v}"),
            ));
        }
    }
    if !(m.radius.is_finite() && m.radius > 0.0) {
        return Err(InputError::new(
            format!("{at}.mark.radius"),
            format!("a positive radius in metres, got {}", m.radius),
        ));
    }
    let stroke = match layout.print {
        crate::target::line_layout::Print::Strokes { width } => width,
        crate::target::line_layout::Print::Outline => 0.0,
    };
    let centre = crate::geometry::Vec3::new(m.x, 0.0, m.y);
    for (k, s) in layout.segments.iter().enumerate() {
        // Distance from the centre to the segment (both in the target's y = 0 plane).
        let d = s.to - s.from;
        let t = ((centre - s.from).dot(&d) / d.norm_squared()).clamp(0.0, 1.0);
        let gap = (centre - (s.from + t * d)).norm() - m.radius - stroke / 2.0;
        if gap < stroke {
            return Err(InputError::new(
                format!("{at}.mark"),
                format!(
                    "a disc clear of every stroke by at least a stroke width ({stroke} m); it is {gap:.4} m from line {}",
                    k + 1
                ),
            ));
        }
    }
    let layout = layout.with_mark(m.x, m.y, m.radius);
    for g in layout.line_symmetries().iter().skip(1) {
        let moved = (g.target_from_labelled.apply(&centre) - centre).norm();
        if moved <= 2.0 * m.radius {
            return Err(InputError::new(
                format!("{at}.mark"),
                format!(
                    "a disc away from the print's centre of symmetry (a {}° turn moves it by {moved:.4} m, less than its diameter, so it cannot tell the labellings apart)",
                    g.degrees
                ),
            ));
        }
    }
    Ok(layout)
}

/// Points measured on feature line `line` (0-based: `l1` is 0) of target `target`
/// (an index into [`VanishingInput::targets`]), in raw pixels.
#[derive(Clone, Debug)]
pub struct LineObs {
    pub target: usize,
    pub line: usize,
    pub points: Vec<Vec2>,
}

/// One auxiliary image of neighbouring targets.
#[derive(Clone, Debug)]
pub struct RingView {
    pub index: i64,
    pub targets: [usize; 2],
    pub lines: Vec<LineObs>,
}

/// The vanishing method's validated input.
#[derive(Clone, Debug)]
pub struct VanishingInput {
    pub targets: Vec<LineTargetDef>,
    pub auxiliary: NamedCamera,
    /// Per rig camera (indexed like `Session::cameras`): its line observations.
    pub rig: Vec<Vec<LineObs>>,
    pub ring: Vec<RingView>,
}

fn line_obs(
    spec: &LineSpec,
    at: &str,
    camera: &Camera,
    cam_name: &str,
    target_index: &HashMap<&str, usize>,
    lines_of: &[usize],
) -> Result<LineObs, InputError> {
    let target = *target_index.get(spec.target.as_str()).ok_or_else(|| {
        InputError::new(
            format!("{at}.target"),
            format!(
                "the id of a line_target in targets[], got {:?}",
                spec.target
            ),
        )
    })?;
    let n = lines_of[target];
    if !(1..=n).contains(&(spec.line as usize)) {
        return Err(InputError::new(
            format!("{at}.line"),
            format!(
                "a line number 1..{n} of target {}, got {}",
                spec.target, spec.line
            ),
        ));
    }
    if spec.points.len() > MAX_POINTS_PER_LINE {
        return Err(InputError::new(
            format!("{at}.points"),
            format!(
                "at most {MAX_POINTS_PER_LINE} points per line, got {}",
                spec.points.len()
            ),
        ));
    }
    let mut points = Vec::with_capacity(spec.points.len());
    for (k, p) in spec.points.iter().enumerate() {
        let uv = Vec2::new(p[0], p[1]);
        if !(p[0].is_finite() && p[1].is_finite() && camera.in_image(&uv)) {
            return Err(InputError::new(
                format!("{at}.points[{k}]"),
                format!(
                    "a finite pixel inside the {}×{} image of camera {cam_name}, got [{}, {}]",
                    camera.width, camera.height, p[0], p[1]
                ),
            ));
        }
        points.push(uv);
    }
    Ok(LineObs {
        target,
        line: spec.line as usize - 1,
        points,
    })
}

/// Every (target, line) once per image.
fn unique_lines(obs: &[LineObs], at: &str) -> Result<(), InputError> {
    let mut seen = BTreeMap::new();
    for (i, o) in obs.iter().enumerate() {
        if let Some(prev) = seen.insert((o.target, o.line), i) {
            return Err(InputError::new(
                format!("{at}[{i}].line"),
                format!(
                    "each feature line of a target once per image; line {} repeats {at}[{prev}]",
                    o.line + 1
                ),
            ));
        }
    }
    Ok(())
}

/// Validate the vanishing-method parts of a manifest. `cameras` are the validated rig cameras.
pub fn validate_vanishing(
    m: &SessionManifest,
    cameras: &[NamedCamera],
) -> Result<VanishingInput, InputError> {
    let mut targets = Vec::new();
    let mut target_index = HashMap::new();
    for (i, t) in m.targets.iter().enumerate() {
        let layout = line_layout(t, &format!("targets[{i}]"))?;
        target_index.insert(t.id(), targets.len());
        targets.push(LineTargetDef {
            id: t.id().to_string(),
            layout,
        });
    }
    let lines_of: Vec<usize> = targets.iter().map(|t| t.layout.len()).collect();
    if targets.len() < 2 {
        return Err(InputError::new(
            "targets",
            "at least two line_target entries (one per rig camera)",
        ));
    }
    let aux_spec = m.auxiliary_camera.as_ref().ok_or_else(|| {
        InputError::new(
            "auxiliary_camera",
            "the auxiliary camera (id, model, size, intrinsics) for method vanishing",
        )
    })?;
    let auxiliary = NamedCamera {
        id: aux_spec.id.clone(),
        camera: camera_from_spec(aux_spec, "auxiliary_camera")?,
    };
    super::check_identifier("auxiliary_camera.id", &aux_spec.id)?;
    if cameras.iter().any(|c| c.id == aux_spec.id) {
        return Err(InputError::new(
            "auxiliary_camera.id",
            format!(
                "an id different from the rig cameras', got {:?}",
                aux_spec.id
            ),
        ));
    }
    if m.frames.len() > 1 {
        return Err(InputError::new(
            "frames",
            format!(
                "one frame (the rig is static in the vanishing method), got {}",
                m.frames.len()
            ),
        ));
    }
    let mut rig = vec![Vec::new(); cameras.len()];
    let mut rig_targets = vec![None; cameras.len()];
    if let Some(f) = m.frames.first() {
        for (cam, t) in &f.line_targets {
            let at = format!("frames[0].line_targets.{cam}");
            let ci = cameras
                .iter()
                .position(|c| &c.id == cam)
                .ok_or_else(|| InputError::new(&at, "a rig camera id declared in cameras[]"))?;
            let ti = *target_index.get(t.as_str()).ok_or_else(|| {
                InputError::new(
                    &at,
                    format!("the id of a line_target in targets[], got {t:?}"),
                )
            })?;
            rig_targets[ci] = Some(ti);
        }
        if !f.observations.is_empty() {
            return Err(InputError::new(
                "frames[0].observations",
                "no point observations in a vanishing session (give frames[0].lines)",
            ));
        }
        for (cam, specs) in &f.lines {
            let ci = cameras.iter().position(|c| &c.id == cam).ok_or_else(|| {
                InputError::new(
                    format!("frames[0].lines.{cam}"),
                    "a camera id declared in cameras[]",
                )
            })?;
            let mut obs = Vec::new();
            for (i, s) in specs.iter().enumerate() {
                let at = format!("frames[0].lines.{cam}[{i}]");
                obs.push(line_obs(
                    s,
                    &at,
                    &cameras[ci].camera,
                    cam,
                    &target_index,
                    &lines_of,
                )?);
            }
            unique_lines(&obs, &format!("frames[0].lines.{cam}"))?;
            if let Some(o) = obs.iter().position(|o| o.target != obs[0].target) {
                return Err(InputError::new(
                    format!("frames[0].lines.{cam}[{o}].target"),
                    format!(
                        "the one target camera {cam} sees ({}), got {:?}",
                        targets[obs[0].target].id, targets[obs[o].target].id
                    ),
                ));
            }
            if let (Some(t), Some(o)) = (rig_targets[ci], obs.first()) {
                if o.target != t {
                    return Err(InputError::new(
                        format!("frames[0].lines.{cam}[0].target"),
                        format!(
                            "the target frames[0].line_targets names for {cam} ({}), got {:?}",
                            targets[t].id, targets[o.target].id
                        ),
                    ));
                }
            }
            rig[ci] = obs;
        }
    }
    if m.ring.len() > MAX_RING_VIEWS {
        return Err(InputError::new(
            "ring",
            format!("at most {MAX_RING_VIEWS} views, got {}", m.ring.len()),
        ));
    }
    let mut ring = Vec::new();
    let mut indices = std::collections::HashSet::new();
    for (ri, r) in m.ring.iter().enumerate() {
        let at = format!("ring[{ri}]");
        if !indices.insert(r.index) {
            return Err(InputError::new(
                format!("{at}.index"),
                format!("an index unique among ring views, {} repeats", r.index),
            ));
        }
        if r.targets.len() != 2 || r.targets[0] == r.targets[1] {
            return Err(InputError::new(
                format!("{at}.targets"),
                format!(
                    "the ids of the two different line targets in view, got {:?}",
                    r.targets
                ),
            ));
        }
        let mut pair = [0usize; 2];
        for (k, t) in r.targets.iter().enumerate() {
            pair[k] = *target_index.get(t.as_str()).ok_or_else(|| {
                InputError::new(
                    format!("{at}.targets[{k}]"),
                    format!("the id of a line_target in targets[], got {t:?}"),
                )
            })?;
        }
        if let Some(path) = &r.image {
            super::validate::check_image_path(path, &format!("{at}.image"))?;
        }
        let mut lines = Vec::new();
        for (i, s) in r.lines.iter().enumerate() {
            let li = format!("{at}.lines[{i}]");
            let o = line_obs(
                s,
                &li,
                &auxiliary.camera,
                &auxiliary.id,
                &target_index,
                &lines_of,
            )?;
            if !pair.contains(&o.target) {
                return Err(InputError::new(
                    format!("{li}.target"),
                    format!(
                        "one of the view's targets {:?}, got {:?}",
                        r.targets, s.target
                    ),
                ));
            }
            lines.push(o);
        }
        unique_lines(&lines, &format!("{at}.lines"))?;
        ring.push(RingView {
            index: r.index,
            targets: pair,
            lines,
        });
    }
    Ok(VanishingInput {
        targets,
        auxiliary,
        rig,
        ring,
    })
}

#[cfg(test)]
mod tests {
    use crate::session::parse_session;
    use serde_json::{json, Value};

    fn ring() -> Value {
        let cam = |id: &str| json!({"id": id, "model": "pinhole", "width": 1024, "height": 768, "intrinsics": {"fx": 800, "fy": 800, "cx": 512, "cy": 384}});
        let line = |t: &str, l: u8| json!({"target": t, "line": l, "points": [[100.0, 100.0], [200.0, 110.0], [300.0, 120.0]]});
        json!({
            "method": "vanishing",
            "reference_camera": "c1",
            "cameras": [cam("c1"), cam("c2")],
            "auxiliary_camera": cam("aux"),
            "targets": [
                {"id": "t1", "type": "line_target", "length": 0.5, "spacing": 0.2},
                {"id": "t2", "type": "line_target", "length": 0.5, "spacing": 0.2}
            ],
            "frames": [{"index": 0, "lines": {"c1": [line("t1", 1)], "c2": [line("t2", 1)]}}],
            "ring": [{"index": 0, "targets": ["t1", "t2"], "lines": [line("t1", 1), line("t2", 6)]}]
        })
    }

    fn field(v: Value) -> String {
        parse_session(v.to_string().as_bytes()).unwrap_err().field
    }

    #[test]
    fn a_ring_session_parses_and_every_error_names_its_field() {
        let s = parse_session(ring().to_string().as_bytes()).unwrap();
        let v = s.vanishing.unwrap();
        assert_eq!(v.rig[1][0].target, 1);
        assert_eq!(v.ring[0].lines[1].line, 5);

        let mut m = ring();
        m.as_object_mut().unwrap().remove("auxiliary_camera");
        assert_eq!(field(m), "auxiliary_camera");
        let mut m = ring();
        m["auxiliary_camera"]["id"] = json!("c2");
        assert_eq!(field(m), "auxiliary_camera.id");
        let mut m = ring();
        m["ring"][0]["targets"] = json!(["t1"]);
        assert_eq!(field(m), "ring[0].targets");
        let mut m = ring();
        m["ring"][0]["targets"][1] = json!("t9");
        assert_eq!(field(m), "ring[0].targets[1]");
        let mut m = ring();
        m["ring"][0]["lines"][1]["line"] = json!(7);
        assert_eq!(field(m), "ring[0].lines[1].line");
        let mut m = ring();
        m["ring"][0]["lines"][1]["target"] = json!("t1");
        m["ring"][0]["lines"][1]["line"] = json!(1);
        assert_eq!(field(m), "ring[0].lines[1].line");
        let mut m = ring();
        m["frames"][0]["lines"]["c1"][0]["points"][2] = json!([2000.0, 5.0]);
        assert_eq!(field(m), "frames[0].lines.c1[0].points[2]");
        let mut m = ring();
        m["frames"][0]["lines"]["c1"]
            .as_array_mut()
            .unwrap()
            .push(json!({"target": "t2", "line": 2, "points": []}));
        assert_eq!(field(m), "frames[0].lines.c1[1].target");
        let mut m = ring();
        m["frames"][0]["lines"]["c9"] = json!([]);
        assert_eq!(field(m), "frames[0].lines.c9");
        let mut m = ring();
        m["targets"][1]["spacing"] = json!(0.6);
        assert_eq!(field(m), "targets[1].spacing");
        let mut m = ring();
        m["targets"][1] = json!({"id": "t2", "type": "apriltags", "tag_size": 0.1});
        assert_eq!(field(m), "targets[1].type");
        let mut m = ring();
        m["ring"][0]["image"] = json!("../etc/passwd");
        assert_eq!(field(m), "ring[0].image");
        // Ring parts in a motion session are refused, not ignored.
        let mut m = ring();
        m["method"] = json!("motion");
        assert_eq!(field(m), "auxiliary_camera");
    }

    #[test]
    fn thin_line_targets_parse_and_their_errors_name_the_field() {
        let grid = json!({"id": "t1", "type": "line_grid", "length": 0.5, "spacing": 0.2, "lines_x": 3, "lines_y": 2, "stroke": 0.012});
        let mut m = ring();
        m["targets"][0] = grid.clone();
        let s = parse_session(m.to_string().as_bytes()).unwrap();
        assert_eq!(s.vanishing.unwrap().targets[0].layout.len(), 5);
        for (key, value, expected) in [
            ("lines_x", json!(1), "targets[0].lines_x"),
            ("spacing", json!(0.3), "targets[0].spacing"),
            ("stroke", json!(0.15), "targets[0].stroke"),
            ("stroke", json!(-1.0), "targets[0].stroke"),
        ] {
            let mut m = ring();
            m["targets"][0] = grid.clone();
            m["targets"][0][key] = value;
            assert_eq!(field(m), expected, "{key}");
        }
        // Line 6 of a 5-line grid.
        let mut m = ring();
        m["targets"][0] = grid.clone();
        m["frames"][0]["lines"]["c1"][0]["line"] = json!(6);
        assert_eq!(field(m), "frames[0].lines.c1[0].line");
        let seg = |a: [f64; 2], b: [f64; 2]| json!([a, b]);
        let mut m = ring();
        m["targets"][1] = json!({"id": "t2", "type": "line_segments", "stroke": 0.01, "segments": [
            seg([-0.2, 0.0], [0.2, 0.0]), seg([-0.2, 0.1], [0.2, 0.1]),
            seg([0.0, -0.2], [0.1, 0.2])]});
        assert_eq!(field(m), "targets[1].segments[2]");
        let mut m = ring();
        m["targets"][1] = json!({"id": "t2", "type": "line_segments", "stroke": 0.01, "segments": [
            seg([-0.2, 0.0], [0.2, 0.0]), seg([0.0, -0.2], [0.0, 0.2])]});
        assert_eq!(field(m), "targets[1].segments");
    }

    #[test]
    fn an_orientation_mark_breaks_the_symmetry_and_must_be_readable() {
        let grid = |mark: Value| json!({"id": "t1", "type": "line_grid", "length": 0.5, "spacing": 0.2, "lines_x": 2, "lines_y": 2, "stroke": 0.012, "mark": mark});
        let mut m = ring();
        m["targets"][0] = grid(json!({"x": 0.0, "y": 0.0, "radius": 0.03}));
        let mut unmarked = m.clone();
        unmarked["targets"][0]
            .as_object_mut()
            .unwrap()
            .remove("mark");
        let layout = |m: &Value| {
            parse_session(m.to_string().as_bytes())
                .unwrap()
                .vanishing
                .unwrap()
                .targets[0]
                .layout
                .clone()
        };
        // At the centre of symmetry it cannot tell labellings apart.
        assert_eq!(field(m.clone()), "targets[0].mark");
        assert_eq!(layout(&unmarked).symmetries().len(), 4);
        m["targets"][0] = grid(json!({"x": 0.2, "y": 0.0, "radius": 0.03}));
        let l = layout(&m);
        assert_eq!(l.symmetries().len(), 1);
        assert_eq!(
            l.mark.unwrap().centre,
            crate::geometry::Vec3::new(0.2, 0.0, 0.0)
        );
        for (mark, expected) in [
            // On the line x = 0.1.
            (
                json!({"x": 0.1, "y": 0.0, "radius": 0.03}),
                "targets[0].mark",
            ),
            (
                json!({"x": 0.2, "y": 0.0, "radius": -0.03}),
                "targets[0].mark.radius",
            ),
            (
                json!({"x": 0.2, "y": 0.0, "radius": 0.0}),
                "targets[0].mark.radius",
            ),
        ] {
            m["targets"][0] = grid(mark.clone());
            assert_eq!(field(m.clone()), expected, "{mark}");
        }
        m["targets"][0] = grid(json!({"x": 0.2, "y": 0.0}));
        assert!(parse_session(m.to_string().as_bytes()).is_err());
    }
}
