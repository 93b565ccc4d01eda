//! Tags that link cameras, placed by the rig's rigidity where no scene could place them.
//!
//! A small tag seen far away or nearly head-on has two planar poses of almost the same
//! reprojection error ([`pnp::ambiguous`]); the per-scene reconstruction refuses to
//! place it, because a flipped tag would become motions that never happened. On a
//! planar drive such tags may be the only targets two cameras both see, and without
//! them the cameras' relative heights are unobservable (held, `degraded`). The rig
//! settles what one view cannot: once the initialisation has the rig's rotations
//! (planar motion determines them), every view of the tag proposes two orientations in
//! the world, and the true one is the orientation views from *different* cameras agree
//! on. One camera cannot decide it: under planar motion it sees the tag from nearly the
//! same direction in every frame, so its mirrored poses agree with each other too.
//!
//! Each tag so decided becomes a scene of its own (its body at the scene's origin, in
//! metres), whose images link their cameras in the initialisation's translations and
//! the rig adjustment like any scene two cameras share.

use super::handeye::InitOutput;
use super::pnp;
use super::trajectory::{ImageKey, SceneRecon, SceneScale, Trajectories};
use rigcal_core::geometry::plane::{is_planar, principal_axes};
use rigcal_core::geometry::{so3, Mat3, Pose, Vec2, Vec3};
use rigcal_core::session::{PointKind, Session};
use std::collections::{BTreeMap, BTreeSet};

/// Two orientations of a tag in the world agree within this (deg). The rig's rotations
/// at the initialisation are good to a fraction of a degree on planar drives; a small
/// tag's own orientation scatters by a few degrees; its mirror is tilted by twice the
/// angle between its normal and the line of sight, tens of degrees for a tag that two
/// cameras pointing different ways both see.
const AGREE_DEG: f64 = 8.0;

/// A tag's corners in one image: their coordinates on the tag and in the image.
type Corners = (Vec<Vec3>, Vec<Vec2>);

/// A view of a tag: its image, the tag's corners, and its two planar poses.
struct View {
    key: ImageKey,
    local: Vec<Vec3>,
    candidates: [Candidate; 2],
}

impl View {
    /// The better-fitting of the candidates within [`AGREE_DEG`] of orientation `r`.
    fn nearest(&self, r: &Mat3) -> Option<Candidate> {
        self.candidates
            .iter()
            .filter(|c| so3::angle_between(&c.world_rot, r) < AGREE_DEG.to_radians())
            .min_by(|a, b| a.cost.total_cmp(&b.cost))
            .copied()
    }
}

/// One planar pose of a tag in one image.
#[derive(Clone, Copy)]
struct Candidate {
    cam_from_body: Pose,
    /// The tag's orientation in the world, through the rig.
    world_rot: Mat3,
    /// Sum of squared reprojection errors (px²).
    cost: f64,
}

impl Candidate {
    /// `cam_from_body` turned about the tag's centroid so that the tag has orientation
    /// `world_rot` in the world: its position is what links cameras, and both planar
    /// poses share it.
    fn turned_to(&self, local: &[Vec3], world_rot: &Mat3) -> Pose {
        let (centroid, _, _) = principal_axes(local);
        let p = self.cam_from_body;
        let rot = p.rot * self.world_rot.transpose() * world_rot;
        Pose::new(rot, p.apply(&centroid) - rot * centroid)
    }
}

/// `traj` with the cameras of different linked groups ([`Trajectories::linked_cameras`])
/// linked through the tags they both see: an image of a tag a scene placed is posed in
/// that scene with the tag's pose nearest the orientation the scene gives it; a tag no
/// scene placed becomes a scene of its own where views from two groups agree on its
/// orientation. `None` when nothing was linked.
pub fn link_cameras_through_tags(
    session: &Session,
    traj: &Trajectories,
    init: &InitOutput,
) -> Option<Trajectories> {
    let nc = session.cameras.len();
    let group = traj.linked_cameras(nc);
    if group.iter().collect::<BTreeSet<_>>().len() < 2 {
        return None;
    }
    // The scene that placed each body, where that scene is placed in the world (a rest
    // split off a chain may place bodies and pose no image).
    let home: BTreeMap<usize, usize> = traj
        .scenes
        .iter()
        .enumerate()
        .filter(|(s, sc)| !sc.poses.is_empty() && init.world_from_scene[*s].is_some())
        .flat_map(|(s, sc)| sc.bodies.keys().map(move |b| (*b, s)))
        .collect();
    // Corners of every body, per image of a posed rig frame.
    let mut seen: BTreeMap<usize, BTreeMap<ImageKey, Corners>> = BTreeMap::new();
    for (f, frame) in session.frames.iter().enumerate() {
        if init.world_from_rig[f].is_none() {
            continue;
        }
        for (c, obs) in frame.observations.iter().enumerate() {
            for o in obs {
                if let PointKind::Body { body, local } = session.points.kinds[o.point] {
                    let e = seen.entry(body).or_default().entry((f, c)).or_default();
                    e.0.push(local);
                    e.1.push(o.uv);
                }
            }
        }
    }
    let mut out = traj.clone();
    let mut linked = false;
    for (body, images) in seen {
        let groups: BTreeSet<usize> = images.keys().map(|k| group[k.1]).collect();
        if groups.len() < 2 {
            continue;
        }
        if let Some(&s) = home.get(&body) {
            // Only images the scene does not pose, from other groups than its own: the
            // two poses of each cost a PnP.
            let scene = &out.scenes[s];
            let own = scene.poses.keys().next().map(|k| group[k.1]);
            let views: Vec<View> = images
                .into_iter()
                .filter(|(key, _)| Some(group[key.1]) != own && !scene.poses.contains_key(key))
                .filter_map(|(key, (local, uv))| view(session, init, key, local, uv))
                .collect();
            linked |= pose_in_home(&mut out.scenes[s], init.world_from_scene[s], body, views);
            continue;
        }
        let views: Vec<View> = images
            .into_iter()
            .filter_map(|(key, (local, uv))| view(session, init, key, local, uv))
            .collect();
        let Some(placed) = place(&views, &group) else {
            continue;
        };
        for scene in &mut out.scenes {
            scene.bodies.remove(&body);
        }
        let s = out.scenes.len();
        for (p, kind) in session.points.kinds.iter().enumerate() {
            if matches!(kind, PointKind::Body { body: b, .. } if *b == body) {
                out.scene_of_point[p] = Some(s);
            }
        }
        out.scenes.push(placed.into_scene(body));
        linked = true;
    }
    linked.then_some(out)
}

/// Poses in `scene`, which placed `body`, for `views` of the tag (images from cameras of
/// other groups than the scene's, which it does not pose): the tag's pose nearest the
/// orientation the scene gives it in the world, turned to that orientation about the
/// tag's centroid. Returns whether any image was posed.
fn pose_in_home(
    scene: &mut SceneRecon,
    world_from_scene: Option<Pose>,
    body: usize,
    views: Vec<View>,
) -> bool {
    let (Some(world_from_scene), Some(&scene_from_body)) =
        (world_from_scene, scene.bodies.get(&body))
    else {
        return false;
    };
    let world_rot = world_from_scene.rot * scene_from_body.rot;
    let mut posed = false;
    for v in views {
        if let Some(c) = v.nearest(&world_rot) {
            let cam_from_body = c.turned_to(&v.local, &world_rot);
            scene
                .poses
                .insert(v.key, cam_from_body * scene_from_body.inverse());
            posed = true;
        }
    }
    posed
}

/// Both planar poses of a tag in one image, with their orientations in the world.
fn view(
    session: &Session,
    init: &InitOutput,
    key: ImageKey,
    local: Vec<Vec3>,
    uv: Vec<Vec2>,
) -> Option<View> {
    if local.len() < 4 || !is_planar(&local) {
        return None;
    }
    let cam = &session.cameras[key.1].camera;
    let world_from_cam = init.world_from_rig[key.0]? * init.ref_from_cam[key.1];
    let fit = pnp::solve_pose(cam, &local, &uv)?;
    let other = pnp::refine_pose(cam, &local, &uv, pnp::mirrored(&fit.pose, &local));
    let candidates = [fit.pose, other].map(|p| Candidate {
        cam_from_body: p,
        world_rot: world_from_cam.rot * p.rot,
        cost: pnp::reprojection_cost(cam, &local, &uv, &p),
    });
    Some(View {
        key,
        local,
        candidates,
    })
}

/// A placed tag, before its body index is known.
struct Placed {
    poses: BTreeMap<ImageKey, Pose>,
}

impl Placed {
    fn into_scene(self, body: usize) -> SceneRecon {
        SceneRecon {
            points: BTreeMap::new(),
            bodies: BTreeMap::from([(body, Pose::identity())]),
            poses: self.poses,
            scale: SceneScale::Bodies,
            // No adjustment measured its noise: the scenes' σ stays theirs.
            sigma_px: f64::NAN,
            part_of: None,
        }
    }
}

/// The orientation views from the most camera groups agree on, and every view's pose
/// of the tag in it; `None` unless views from two groups agree. Where the cameras see
/// the tag along nearly the same line in the world, its two poses are mirrored alike in
/// every view and both orientations are agreed on; they share the tag's position, which
/// is what links the cameras, and the one that fits the views better is taken.
fn place(views: &[View], group: &[usize]) -> Option<Placed> {
    // Support of an orientation: the groups most of whose views have a candidate near
    // it, the share of all views that do, and (negated, so larger is better) the cost
    // of those candidates.
    let support = |r: &Mat3| -> (usize, f64, f64) {
        let mut per_group: BTreeMap<usize, (usize, usize)> = BTreeMap::new();
        let mut cost = 0.0;
        for v in views {
            let e = per_group.entry(group[v.key.1]).or_default();
            e.1 += 1;
            if let Some(c) = v.nearest(r) {
                e.0 += 1;
                cost += c.cost;
            }
        }
        let groups = per_group.values().filter(|(k, n)| 2 * k > *n).count();
        let agreeing = per_group.values().map(|(k, _)| *k).sum::<usize>();
        (groups, agreeing as f64 / views.len() as f64, -cost)
    };
    let (best, best_support) = views
        .iter()
        .flat_map(|v| {
            v.candidates
                .iter()
                .map(|c| (c.world_rot, support(&c.world_rot)))
        })
        .max_by(|a, b| {
            (a.1 .0)
                .cmp(&b.1 .0)
                .then(a.1 .1.total_cmp(&b.1 .1))
                .then(a.1 .2.total_cmp(&b.1 .2))
        })?;
    if best_support.0 < 2 {
        return None;
    }
    // Each agreeing view's candidate; their chordal mean is the tag's orientation.
    let chosen: Vec<(&View, Candidate)> = views
        .iter()
        .filter_map(|v| Some((v, v.nearest(&best)?)))
        .collect();
    let linked: BTreeSet<usize> = chosen.iter().map(|(v, _)| group[v.key.1]).collect();
    if linked.len() < 2 {
        return None;
    }
    let sum: Mat3 = chosen.iter().map(|(_, c)| c.world_rot).sum();
    let world_from_body = so3::project_to_so3(&sum);
    let poses = chosen
        .iter()
        .map(|(v, c)| (v.key, c.turned_to(&v.local, &world_from_body)))
        .collect();
    Some(Placed { poses })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square() -> Vec<Vec3> {
        [(0.0, 0.0), (0.1, 0.0), (0.1, 0.1), (0.0, 0.1)]
            .map(|(x, y)| Vec3::new(x, y, 0.0))
            .to_vec()
    }

    /// A view whose camera is the world frame: its candidates' orientations are their
    /// `cam_from_body` rotations.
    fn view_of(key: ImageKey, candidates: [(Mat3, f64); 2]) -> View {
        View {
            key,
            local: square(),
            candidates: candidates.map(|(r, cost)| Candidate {
                cam_from_body: Pose::new(r, Vec3::new(0.1, -0.2, 6.0)),
                world_rot: r,
                cost,
            }),
        }
    }

    /// A few degrees of noise, different in every view.
    fn jitter(k: usize) -> Mat3 {
        let k = k as f64;
        so3::exp(&(Vec3::new((1.3 * k).sin(), (0.7 * k).cos(), 0.5) * 0.03))
    }

    /// Six views from each of two cameras; each camera's mirrors are tilted their own
    /// way, and in every other view the mirror fits better.
    fn two_cameras(truth: Mat3, mirrors: [Mat3; 2]) -> Vec<View> {
        let mut views = Vec::new();
        for (c, mirror) in mirrors.into_iter().enumerate() {
            for k in 0..6 {
                let (t, m) = if k % 2 == 0 { (0.1, 0.3) } else { (0.3, 0.1) };
                let j = jitter(6 * c + k);
                views.push(view_of((k, c), [(truth * j, t), (mirror * j, m)]));
            }
        }
        views
    }

    #[test]
    fn the_orientation_two_cameras_agree_on_is_the_tags() {
        let truth = so3::exp(&Vec3::new(0.3, -1.2, 0.4));
        let mirrors = [
            truth * so3::exp(&Vec3::new(0.8, 0.0, 0.0)),
            truth * so3::exp(&Vec3::new(0.0, 0.3, -0.9)),
        ];
        let views = two_cameras(truth, mirrors);
        let placed = place(&views, &[0, 1]).expect("two cameras agree");
        assert_eq!(placed.poses.len(), 12);
        for (key, pose) in &placed.poses {
            let deg = so3::angle_between(&pose.rot, &truth).to_degrees();
            assert!(deg < 2.0, "{key:?}: {deg:.2}° from the tag's orientation");
        }
        // One camera alone cannot tell: its mirrors agree with each other as well.
        assert!(place(&views, &[0, 0]).is_none());
    }

    /// Seen along the same line by both cameras, the tag's mirrors coincide: both
    /// orientations are agreed on, and the one that fits better is taken.
    #[test]
    fn where_both_orientations_are_agreed_on_the_better_fit_wins() {
        let truth = so3::exp(&Vec3::new(-0.5, 0.2, 2.0));
        let mirror = truth * so3::exp(&Vec3::new(0.0, 0.9, 0.0));
        let mut views = two_cameras(truth, [mirror, mirror]);
        for v in &mut views {
            v.candidates[0].cost = 0.1;
            v.candidates[1].cost = 0.2;
        }
        let placed = place(&views, &[0, 1]).expect("both agree");
        let (_, pose) = placed.poses.iter().next().unwrap();
        assert!(so3::angle_between(&pose.rot, &truth).to_degrees() < 2.0);
    }

    /// The pose turned to another orientation keeps the tag's centroid where the camera
    /// saw it.
    #[test]
    fn turning_a_pose_keeps_the_centroid() {
        let local = square();
        let r = so3::exp(&Vec3::new(0.2, 0.1, -0.3));
        let c = Candidate {
            cam_from_body: Pose::new(r, Vec3::new(0.3, 0.1, 4.0)),
            world_rot: so3::exp(&Vec3::new(0.0, 1.0, 0.0)) * r,
            cost: 0.0,
        };
        let target = so3::exp(&Vec3::new(0.1, 1.1, 0.05)) * r;
        let turned = c.turned_to(&local, &target);
        let centroid = Vec3::new(0.05, 0.05, 0.0);
        assert!((turned.apply(&centroid) - c.cam_from_body.apply(&centroid)).norm() < 1e-12);
        // world_from_cam = world_rot · cam_from_bodyᵀ; the turned pose has `target`.
        let world_from_cam = c.world_rot * r.transpose();
        assert!(so3::angle_between(&(world_from_cam * turned.rot), &target) < 1e-12);
    }
}
