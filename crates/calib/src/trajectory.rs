//! Per-camera trajectories (Lébraly §2): each static scene is reconstructed on its own
//! and every image that sees it gets its pose `cam_from_scene`.
//!
//! A *scene* is a connected set of points: points seen together in one image, and the
//! corners of one rigid body, belong to the same scene. After a U-turn a camera sees
//! another camera's scene: its images then carry poses in that scene, which is what
//! the scene-permutation constraints of the initialisation use.
//!
//! Known geometry (bodies) → PnP; unknown geometry (free points) → two-view SfM
//! (essential matrix, triangulation), metric scale from the measured distances; then a
//! bundle adjustment per scene over all its images.

use super::{pnp, twoview};
use rigcal_core::geometry::plane::is_planar;
use rigcal_core::geometry::{Pose, Vec2, Vec3};
use rigcal_core::par::{cores, par_map};
use rigcal_core::session::{PointKind, Session};
use rigcal_solve::bundle::{BundleProblem, LmOptions, Obs};
use rigcal_solve::{median, robust_sigma};
use std::collections::{BTreeMap, BTreeSet, HashMap};

/// An image: (frame position in `session.frames`, camera index).
pub type ImageKey = (usize, usize);

#[derive(Clone, Debug)]
pub struct SceneRecon {
    /// Free points of the scene, in scene coordinates.
    pub points: BTreeMap<usize, Vec3>,
    /// Rigid bodies of the scene: `scene_from_body`.
    pub bodies: BTreeMap<usize, Pose>,
    /// `cam_from_scene` of every image that sees the scene and could be posed.
    pub poses: BTreeMap<ImageKey, Pose>,
    /// Where the scene's metric scale comes from, if anywhere.
    pub scale: SceneScale,
    /// Robust pixel noise σ of the scene bundle adjustment (median-based, so a few
    /// gross outliers do not inflate it).
    pub sigma_px: f64,
    /// The scene this one was split from (the part a long chain could not reach); its
    /// scale comes from the motions it shares with that scene, not from distances.
    pub part_of: Option<usize>,
}

/// Where a scene's metric scale comes from. The initialisation trusts each differently:
/// known geometry fixes a scale, measured distances hold it only as well as the
/// triangulation of the points they join, a borrowed scale is only a starting value.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SceneScale {
    /// Rigid bodies of known geometry (boards, tags of known size).
    Bodies,
    /// Measured distances between reconstructed points (`scale[]`).
    Distances,
    /// A split-off rest brought to metres through the camera motions it shares with a
    /// metric scene ([`scale_from_shared_motion`]).
    SharedMotion,
    /// No scale: the scene is in the arbitrary units of its reconstruction.
    Unknown,
}

impl SceneScale {
    pub fn is_metric(self) -> bool {
        self != SceneScale::Unknown
    }
}

#[derive(Clone, Debug)]
pub struct Trajectories {
    /// Scene index of every point (indexed like `session.points`), `None` if never seen.
    pub scene_of_point: Vec<Option<usize>>,
    pub scenes: Vec<SceneRecon>,
    /// Scenes that could not be reconstructed, with the reason.
    pub failed_scenes: Vec<(usize, String)>,
}

impl Trajectories {
    /// The cameras linked through scenes they share, directly or through others: a
    /// label per camera (of `n_cameras`), equal for linked cameras.
    pub fn linked_cameras(&self, n_cameras: usize) -> Vec<usize> {
        fn root(g: &mut [usize], mut i: usize) -> usize {
            while g[i] != i {
                g[i] = g[g[i]];
                i = g[i];
            }
            i
        }
        let mut group: Vec<usize> = (0..n_cameras).collect();
        for scene in &self.scenes {
            let seen: BTreeSet<usize> = scene.poses.keys().map(|&(_, c)| c).collect();
            let mut it = seen.into_iter();
            if let Some(first) = it.next() {
                for c in it {
                    let (a, b) = (root(&mut group, first), root(&mut group, c));
                    group[a] = b;
                }
            }
        }
        (0..n_cameras).map(|c| root(&mut group, c)).collect()
    }

    /// Median of the reconstructed scenes' robust pixel σ: the noise level the data
    /// show before any rig constraint is imposed.
    pub fn median_scene_sigma(&self) -> Option<f64> {
        median(
            self.scenes
                .iter()
                .map(|s| s.sigma_px)
                .filter(|x| x.is_finite())
                .collect(),
        )
    }
}

#[derive(Debug, thiserror::Error)]
pub enum TrajectoryError {
    #[error("no camera observes any point")]
    NothingObserved,
}

struct UnionFind(Vec<usize>);
impl UnionFind {
    fn find(&mut self, i: usize) -> usize {
        let mut r = i;
        while self.0[r] != r {
            r = self.0[r];
        }
        let mut j = i;
        while self.0[j] != r {
            let n = self.0[j];
            self.0[j] = r;
            j = n;
        }
        r
    }
    fn union(&mut self, a: usize, b: usize) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra != rb {
            self.0[ra] = rb;
        }
    }
}

/// Group points into scenes.
fn scene_components(session: &Session) -> (Vec<Option<usize>>, usize) {
    let n = session.points.ids.len();
    let nb = session.points.bodies.len();
    // Nodes: points, then one node per body.
    let mut uf = UnionFind((0..n + nb).collect());
    for (p, kind) in session.points.kinds.iter().enumerate() {
        if let PointKind::Body { body, .. } = kind {
            uf.union(p, n + body);
        }
    }
    let mut seen = vec![false; n];
    for f in &session.frames {
        for obs in &f.observations {
            for w in obs.windows(2) {
                uf.union(w[0].point, w[1].point);
            }
            for o in obs {
                seen[o.point] = true;
            }
        }
    }
    let mut label: HashMap<usize, usize> = HashMap::new();
    let mut out = vec![None; n];
    for p in 0..n {
        if seen[p] {
            let r = uf.find(p);
            let next = label.len();
            out[p] = Some(*label.entry(r).or_insert(next));
        }
    }
    (out, label.len())
}

/// Reconstruct every scene and pose every image in it.
pub fn estimate(session: &Session, opts: &LmOptions) -> Result<Trajectories, TrajectoryError> {
    let (scene_of_point, n_scenes) = scene_components(session);
    if n_scenes == 0 {
        return Err(TrajectoryError::NothingObserved);
    }
    // Reconstruct the scene the reference camera sees most first: its trajectory then
    // arbitrates between ambiguous two-view starts of the other scenes (rigidity: a
    // camera's relative motions have the same rotation angles as the reference's).
    let mut order: Vec<usize> = (0..n_scenes).collect();
    let ref_count = |s: usize| -> usize {
        session
            .frames
            .iter()
            .filter(|f| {
                f.observations[session.reference]
                    .iter()
                    .any(|o| scene_of_point[o.point] == Some(s))
            })
            .count()
    };
    order.sort_by_key(|&s| std::cmp::Reverse(ref_count(s)));
    let mut scene_of_point = scene_of_point;
    let mut scenes: Vec<Option<SceneRecon>> = vec![None; n_scenes];
    let mut failed_scenes = Vec::new();
    let mut reference_poses: BTreeMap<usize, Pose> = BTreeMap::new();
    let mut queue: std::collections::VecDeque<(usize, Option<usize>)> =
        order.into_iter().map(|s| (s, None)).collect();
    let mut splits: HashMap<usize, usize> = HashMap::new();
    // Once the reference poses are known, the other scenes' reconstructions depend on
    // nothing the loop changes (a split relabels only its own scene's points, and a rest
    // keeps its labels until it is reconstructed): those queued then run on all cores at
    // once, and the loop takes their results in its order.
    let mut ahead: Option<HashMap<usize, Result<SceneRecon, String>>> = None;
    while let Some((s, part_of)) = queue.pop_front() {
        let is_rest = part_of.is_some();
        if ahead.is_none() && !reference_poses.is_empty() {
            let rest: Vec<usize> = std::iter::once(s)
                .chain(queue.iter().map(|(q, _)| *q))
                .collect();
            let recons = par_map(&rest, cores(), |&q| {
                reconstruct_scene(session, &scene_of_point, q, opts, &reference_poses, 1)
            });
            ahead = Some(rest.into_iter().zip(recons).collect());
        }
        let recon = match ahead.as_mut().and_then(|a| a.remove(&s)) {
            Some(r) => r,
            None => reconstruct_scene(session, &scene_of_point, s, opts, &reference_poses, cores()),
        };
        match recon {
            Ok(mut r) => {
                r.part_of = part_of;
                if is_rest
                    && r.scale == SceneScale::Unknown
                    && scale_from_shared_motion(&mut r, scenes.iter().flatten())
                {
                    r.scale = SceneScale::SharedMotion;
                }
                if reference_poses.is_empty() {
                    reference_poses = r
                        .poses
                        .iter()
                        .filter(|(k, _)| k.1 == session.reference)
                        .map(|(k, p)| (k.0, *p))
                        .collect();
                }
                // A long chain (a 360° loop) may stop growing where the images that
                // would carry it on share too few points with what is built. The rest
                // becomes a scene of its own; the images that see both tie the two
                // frames together, as after a U-turn.
                // Bounded: a split needs the scene to have reconstructed some points
                // (else its rest is the whole scene again), and a chain splits at most
                // MAX_SPLITS times.
                let origin = part_of.unwrap_or(s);
                let n_splits = splits.entry(origin).or_insert(0usize);
                // Past MAX_SPLITS a rest is still split off when it holds a board: each
                // such split places that board at least, so it ends.
                let built = !r.points.is_empty() || (!r.bodies.is_empty() && !r.poses.is_empty());
                let boards_only = *n_splits >= MAX_SPLITS;
                if built {
                    if let Some(rest) = split_rest(
                        session,
                        &mut scene_of_point,
                        s,
                        &r,
                        scenes.len(),
                        boards_only,
                    ) {
                        *n_splits += 1;
                        scenes.push(None);
                        queue.push_back((rest, Some(origin)));
                    }
                }
                scenes[s] = Some(r);
            }
            // The unreconstructed rest of a scene is data left unused, not a failure.
            Err(_) if is_rest => {}
            Err(e) => failed_scenes.push((s, e)),
        }
    }
    let scenes = scenes
        .into_iter()
        .map(|s| {
            s.unwrap_or(SceneRecon {
                points: BTreeMap::new(),
                bodies: BTreeMap::new(),
                poses: BTreeMap::new(),
                scale: SceneScale::Unknown,
                sigma_px: f64::NAN,
                part_of: None,
            })
        })
        .collect();
    Ok(Trajectories {
        scene_of_point,
        scenes,
        failed_scenes,
    })
}

/// Bring a scene without measured distances to metres through the camera motions it
/// shares with metric scenes: a camera's motion between two frames is the same whatever
/// scene it is measured in, only its length scales with the scene. Median of the length
/// ratios over every (camera, frame pair) posed in both; returns whether any existed.
fn scale_from_shared_motion<'a>(
    r: &mut SceneRecon,
    metric: impl Iterator<Item = &'a SceneRecon>,
) -> bool {
    let mut ratios = Vec::new();
    for m in metric.filter(|m| m.scale.is_metric()) {
        let shared: Vec<&ImageKey> = r.poses.keys().filter(|k| m.poses.contains_key(k)).collect();
        for (i, a) in shared.iter().enumerate() {
            for b in &shared[i + 1..] {
                if a.1 != b.1 {
                    continue;
                }
                let len = |p: &BTreeMap<ImageKey, Pose>| (p[b] * p[a].inverse()).trans.norm();
                let (here, there) = (len(&r.poses), len(&m.poses));
                if here > 1e-9 && there > 1e-3 {
                    ratios.push(there / here);
                }
            }
        }
    }
    let Some(s) = median(ratios) else {
        return false;
    };
    for p in r.poses.values_mut() {
        p.trans *= s;
    }
    for x in r.points.values_mut() {
        *x *= s;
    }
    true
}

/// How many times one scene's chain may be split into a further scene (then only rests
/// holding a board, see [`split_rest`]).
const MAX_SPLITS: usize = 3;
/// A body of at least this many points is a board: its pose is never ambiguous.
const BOARD_POINTS: usize = 16;

/// Points of scene `s` that its reconstruction `r` left out (free points not
/// triangulated, bodies not placed), relabelled as scene `next` if enough images see
/// them to start one: two images of 8 free points (a two-view start), or one image of 4
/// points of an unplaced body. Bodies stay out when only ambiguous poses would link
/// them ([`place_body`]); their own scene then gives their cameras' trajectories. With
/// `boards_only`, only a rest that holds a board (≥ [`BOARD_POINTS`] points) is split off.
fn split_rest(
    session: &Session,
    scene_of_point: &mut [Option<usize>],
    s: usize,
    r: &SceneRecon,
    next: usize,
    boards_only: bool,
) -> Option<usize> {
    let kinds = &session.points.kinds;
    if boards_only {
        let mut size: HashMap<usize, usize> = HashMap::new();
        for (p, k) in kinds.iter().enumerate() {
            if let PointKind::Body { body, .. } = k {
                if scene_of_point[p] == Some(s) && !r.bodies.contains_key(body) {
                    *size.entry(*body).or_default() += 1;
                }
            }
        }
        if !size.values().any(|&n| n >= BOARD_POINTS) {
            return None;
        }
    }
    let left_out = |p: usize| match kinds[p] {
        PointKind::Free => !r.points.contains_key(&p),
        PointKind::Body { body, .. } => !r.bodies.contains_key(&body),
    };
    let rest: Vec<usize> = (0..scene_of_point.len())
        .filter(|&p| scene_of_point[p] == Some(s) && left_out(p))
        .collect();
    let is_rest: std::collections::HashSet<usize> = rest.iter().copied().collect();
    let (mut free_images, mut body_images) = (0, 0);
    for obs in session.frames.iter().flat_map(|f| f.observations.iter()) {
        let seen = obs.iter().filter(|o| is_rest.contains(&o.point));
        let (free, body) = seen.fold((0, 0), |(f, b), o| match kinds[o.point] {
            PointKind::Free => (f + 1, b),
            PointKind::Body { .. } => (f, b + 1),
        });
        free_images += (free >= 8) as usize;
        body_images += (body >= 4) as usize;
    }
    if free_images < 2 && body_images < 1 {
        return None;
    }
    for p in rest {
        scene_of_point[p] = Some(next);
    }
    Some(next)
}

/// Observations of scene `s` per image.
fn scene_images(
    session: &Session,
    scene_of_point: &[Option<usize>],
    s: usize,
) -> BTreeMap<ImageKey, Vec<(usize, Vec2)>> {
    let mut out: BTreeMap<ImageKey, Vec<(usize, Vec2)>> = BTreeMap::new();
    for (fi, f) in session.frames.iter().enumerate() {
        for (ci, obs) in f.observations.iter().enumerate() {
            for o in obs {
                if scene_of_point[o.point] == Some(s) {
                    out.entry((fi, ci)).or_default().push((o.point, o.uv));
                }
            }
        }
    }
    out
}

/// Scene `s` reconstructed: its images posed, its bodies and free points placed. The
/// per-image and per-body work of a scene of bodies spreads over `threads` (the scenes
/// that run side by side on all cores get 1 each).
fn reconstruct_scene(
    session: &Session,
    scene_of_point: &[Option<usize>],
    s: usize,
    opts: &LmOptions,
    reference_poses: &BTreeMap<usize, Pose>,
    threads: usize,
) -> Result<SceneRecon, String> {
    let images = scene_images(session, scene_of_point, s);
    let kinds = &session.points.kinds;
    let cams: Vec<_> = session.cameras.iter().map(|c| c.camera.clone()).collect();
    let has_bodies = images
        .values()
        .flatten()
        .any(|(p, _)| matches!(kinds[*p], PointKind::Body { .. }));
    let mut poses: BTreeMap<ImageKey, Pose> = BTreeMap::new();
    let mut bodies: BTreeMap<usize, Pose> = BTreeMap::new();
    let mut points: BTreeMap<usize, Vec3> = BTreeMap::new();
    let mut metric = has_bodies;

    if has_bodies {
        // Anchor: the body with the most observations defines the scene frame.
        let mut count: HashMap<usize, usize> = HashMap::new();
        for (p, _) in images.values().flatten() {
            if let PointKind::Body { body, .. } = kinds[*p] {
                *count.entry(body).or_default() += 1;
            }
        }
        let anchor = count
            .iter()
            .max_by_key(|(b, c)| (**c, std::cmp::Reverse(**b)))
            .map(|(b, _)| *b)
            .ok_or("no body")?;
        bodies.insert(anchor, Pose::identity());
        loop {
            let mut progress = false;
            // Pose the images from the placed bodies they see that agree with each other
            // (not where what is left is one plane that two poses explain). Each image
            // reads only the placed bodies, each body only the posed images: both run
            // spread over `threads`, with the serial loop's results.
            let unposed: Vec<(&ImageKey, &Vec<(usize, Vec2)>)> = images
                .iter()
                .filter(|(k, _)| !poses.contains_key(k))
                .collect();
            let posed = par_map(&unposed, threads, |(key, obs)| {
                pose_from_bodies(&cams[key.1], obs, kinds, &bodies)
            });
            for ((key, _), pose) in unposed.iter().zip(posed) {
                if let Some(pose) = pose {
                    poses.insert(**key, pose);
                    progress = true;
                }
            }
            // Place the bodies the posed images see, each from all of them at once.
            let unplaced: BTreeSet<usize> = images
                .iter()
                .filter(|(k, _)| poses.contains_key(k))
                .flat_map(|(_, obs)| obs.iter())
                .filter_map(|(p, _)| match kinds[*p] {
                    PointKind::Body { body, .. } if !bodies.contains_key(&body) => Some(body),
                    _ => None,
                })
                .collect();
            let unplaced: Vec<usize> = unplaced.into_iter().collect();
            let placed = par_map(&unplaced, threads, |&body| {
                place_body(body, &images, &poses, kinds, &cams)
            });
            for (body, scene_from_body) in unplaced.into_iter().zip(placed) {
                if let Some(scene_from_body) = scene_from_body {
                    bodies.insert(body, scene_from_body);
                    progress = true;
                }
            }
            if !progress {
                break;
            }
        }
    } else {
        // Under noise the eight-point start of a small scene can be a wrong (twisted)
        // solution that still puts most points in front; growing from it then fails.
        // Try the best-scored pairs and keep the start from which the scene grows most.
        let candidates = best_pairs(&images, &cams, 5);
        if candidates.is_empty() {
            return Err("no two images share 8 points with enough parallax (a scene of unknown geometry needs a two-view start; give its coordinates as a points target or use tags)".to_string());
        }
        // A wrong (flipped) start can grow fully and fit about as well. Rank by coverage,
        // then by disagreement with the reference camera's rotation angles, then by σ.
        let mut tried = Vec::new();
        for (a, b, rel) in candidates {
            let mut p = BTreeMap::from([(a, Pose::identity()), (b, rel)]);
            let mut x = BTreeMap::new();
            let mut no_bodies = BTreeMap::new();
            let mut m = false;
            let sigma = grow_and_refine(
                session,
                &images,
                &mut p,
                &mut x,
                &mut no_bodies,
                false,
                &mut m,
                opts,
            );
            let mismatch = angle_mismatch(&p, reference_poses, session.reference);
            tried.push((
                p.len() + x.len(),
                mismatch,
                if sigma.is_finite() {
                    sigma
                } else {
                    f64::INFINITY
                },
                p,
                x,
                m,
            ));
        }
        // A folded reconstruction of a long chain can cover more than a correct one that
        // stopped short, but it fits worse: among the starts that cover most of the
        // scene, only those fitting about as well as the best one compete.
        let max_cover = tried.iter().map(|t| t.0).max().unwrap_or(0);
        tried.retain(|t| t.0 as f64 >= START_COVER_SHARE * max_cover as f64);
        let best_sigma = tried.iter().map(|t| t.2).fold(f64::INFINITY, f64::min);
        let chosen = tried
            .into_iter()
            .filter(|t| t.2 <= START_SIGMA_RATIO * best_sigma)
            .min_by(|a, b| a.1.total_cmp(&b.1).then(a.2.total_cmp(&b.2)));
        if let Some((_, _, sigma, p, x, m)) = chosen {
            return Ok(SceneRecon {
                points: x,
                bodies,
                poses: p,
                scale: if m {
                    SceneScale::Distances
                } else {
                    SceneScale::Unknown
                },
                sigma_px: sigma,
                part_of: None,
            });
        }
    }

    let sigma_px = grow_and_refine(
        session,
        &images,
        &mut poses,
        &mut points,
        &mut bodies,
        has_bodies,
        &mut metric,
        opts,
    );
    Ok(SceneRecon {
        points,
        bodies,
        poses,
        scale: if has_bodies {
            SceneScale::Bodies
        } else if metric {
            SceneScale::Distances
        } else {
            SceneScale::Unknown
        },
        sigma_px,
        part_of: None,
    })
}

/// Where `body` sits in the scene (`scene_from_body`), from every posed image that sees
/// at least 4 of its points: each image's pose of the body, and for a planar body its
/// mirror too ([`pnp::mirrored`]), is a candidate, judged by its reprojection error over
/// all those images together. `None` while that leaves two poses ([`pnp::ambiguous`]): a
/// small tag seen from one place only. A flipped body would pose every image that sees
/// it alone wrongly, and those poses would become motions that never happened.
fn place_body(
    body: usize,
    images: &BTreeMap<ImageKey, Vec<(usize, Vec2)>>,
    poses: &BTreeMap<ImageKey, Pose>,
    kinds: &[PointKind],
    cams: &[rigcal_core::geometry::Camera],
) -> Option<Pose> {
    type View = (ImageKey, Pose, Vec<Vec3>, Vec<Vec2>);
    let views: Vec<View> = images
        .iter()
        .filter_map(|(key, obs)| {
            let cam_from_scene = *poses.get(key)?;
            let (local, uv): (Vec<Vec3>, Vec<Vec2>) = obs
                .iter()
                .filter_map(|(p, uv)| match kinds[*p] {
                    PointKind::Body { body: b, local } if b == body => Some((local, *uv)),
                    _ => None,
                })
                .unzip();
            (local.len() >= 4).then_some((*key, cam_from_scene, local, uv))
        })
        .collect();
    let mut candidates = Vec::new();
    // Each view's own fit, for the noise level the agreement is judged at.
    let mut own_rms = Vec::new();
    for (key, cam_from_scene, local, uv) in &views {
        let cam = &cams[key.1];
        let Some(fit) = pnp::solve_pose(cam, local, uv) else {
            continue;
        };
        own_rms.push((fit.cost / local.len() as f64).sqrt());
        candidates.push(cam_from_scene.inverse() * fit.pose);
        if is_planar(local) {
            let other = pnp::refine_pose(cam, local, uv, pnp::mirrored(&fit.pose, local));
            candidates.push(cam_from_scene.inverse() * other);
        }
    }
    let cost = |scene_from_body: &Pose| -> f64 {
        views
            .iter()
            .map(|(key, cam_from_scene, local, uv)| {
                pnp::reprojection_cost(
                    &cams[key.1],
                    local,
                    uv,
                    &(*cam_from_scene * *scene_from_body),
                )
            })
            .sum()
    };
    let mut scored: Vec<(f64, Pose)> = candidates.into_iter().map(|c| (cost(&c), c)).collect();
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (best_cost, best) = *scored.first()?;
    let n: usize = views.iter().map(|v| v.2.len()).sum();
    let rival = scored.iter().find(|(_, p)| {
        rigcal_core::geometry::so3::angle_between(&p.rot, &best.rot).to_degrees()
            > pnp::DISTINCT_DEG
    });
    if matches!(rival, Some((c, _)) if pnp::ambiguous(best_cost, *c, n)) {
        return None;
    }
    // Refined against all views at once, then every view must agree with it: one that
    // does not has a wrong pose or a wrong detection, and either would carry the error
    // on through the body. The poses of the views carry their own noise onto the body
    // (a board metres from the one that posed the image), so agreement is judged at a
    // few times the body's own noise in each view, never under a pixel.
    let best = refine_body(&views, cams, best);
    let noise = median(own_rms).unwrap_or(0.0);
    let limit = (AGREE_NOISE_FACTOR * noise).max(AGREE_RMS_PX);
    let agrees = views.iter().all(|(key, cam_from_scene, local, uv)| {
        let c = pnp::reprojection_cost(&cams[key.1], local, uv, &(*cam_from_scene * best));
        (c / local.len() as f64).sqrt() <= limit
    });
    agrees.then_some(best)
}

/// RMS reprojection error (px) below which a body's corners in one image always agree
/// with a placement: detections are good to hundredths of a pixel, a flipped or
/// mislinked body is pixels off.
const AGREE_RMS_PX: f64 = 1.0;
/// ... and the multiple of the body's own single-view noise above that.
const AGREE_NOISE_FACTOR: f64 = 5.0;

/// `scene_from_body` refined to all the views that see the body (their poses held):
/// Gauss–Newton with Levenberg damping on the pixel errors, Jacobian by central
/// differences (6 unknowns, a few hundred residuals).
fn refine_body(
    views: &[(ImageKey, Pose, Vec<Vec3>, Vec<Vec2>)],
    cams: &[rigcal_core::geometry::Camera],
    init: Pose,
) -> Pose {
    let residuals = |p: &Pose| -> Option<Vec<f64>> {
        let mut r = Vec::new();
        for (key, cam_from_scene, local, uv) in views {
            let cam_from_body = *cam_from_scene * *p;
            for (x, m) in local.iter().zip(uv) {
                let q = cams[key.1].project(&cam_from_body.apply(x))?;
                r.push(q.x - m.x);
                r.push(q.y - m.y);
            }
        }
        Some(r)
    };
    let step = |p: &Pose, d: &nalgebra::Vector6<f64>| {
        p.perturbed(&Vec3::new(d[0], d[1], d[2]), &Vec3::new(d[3], d[4], d[5]))
    };
    let normal = |pose: &Pose| {
        let r = residuals(pose)?;
        let h = 1e-6;
        let mut jac = nalgebra::DMatrix::<f64>::zeros(r.len(), 6);
        for k in 0..6 {
            let mut d = nalgebra::Vector6::zeros();
            d[k] = h;
            let (a, b) = (residuals(&step(pose, &d))?, residuals(&step(pose, &-d))?);
            for i in 0..r.len() {
                jac[(i, k)] = (a[i] - b[i]) / (2.0 * h);
            }
        }
        let jt = jac.transpose();
        let g = &jt * nalgebra::DVector::from_column_slice(&r);
        let hess = &jt * &jac;
        Some((
            nalgebra::Matrix6::from_iterator(hess.iter().copied()),
            nalgebra::Vector6::from_iterator(g.iter().copied()),
        ))
    };
    let rules = rigcal_solve::lm::Rules {
        max_iterations: 40,
        damping: rigcal_solve::lm::Damping::Marquardt {
            raise: 4.0,
            lower: 1.0 / 3.0,
            min_lambda: 1e-9,
        },
        tries: 8,
        function_tolerance: 1e-10,
        min_step: 0.0,
        ..Default::default()
    };
    pnp::damped_pose_fit(init, &rules, normal, |p| {
        residuals(p).map(|r| r.iter().map(|x| x * x).sum::<f64>())
    })
}

/// An image's pose from the placed bodies it sees: fitted to all of them, then, while
/// some body's corners disagree with the pose ([`AGREE_RMS_PX`]), refitted without the
/// worst one, so one misplaced tag does not drag the pose of an image that also sees a
/// board. `None` when fewer than 4 points remain or two poses explain them.
fn pose_from_bodies(
    cam: &rigcal_core::geometry::Camera,
    obs: &[(usize, Vec2)],
    kinds: &[PointKind],
    bodies: &BTreeMap<usize, Pose>,
) -> Option<Pose> {
    let mut groups: BTreeMap<usize, (Vec<Vec3>, Vec<Vec2>)> = BTreeMap::new();
    for (p, uv) in obs {
        if let PointKind::Body { body, local } = kinds[*p] {
            if let Some(sb) = bodies.get(&body) {
                let g = groups.entry(body).or_default();
                g.0.push(sb.apply(&local));
                g.1.push(*uv);
            }
        }
    }
    loop {
        let (local, uv): (Vec<Vec3>, Vec<Vec2>) = groups
            .values()
            .flat_map(|(l, u)| l.iter().copied().zip(u.iter().copied()))
            .unzip();
        if local.len() < 4 || !(is_planar(&local) || local.len() >= 6) {
            return None;
        }
        let fit = pnp::solve_pose(cam, &local, &uv)?;
        let worst = groups
            .iter()
            .map(|(b, (l, u))| {
                let rms = (pnp::reprojection_cost(cam, l, u, &fit.pose) / l.len() as f64).sqrt();
                (*b, rms)
            })
            .max_by(|a, b| a.1.total_cmp(&b.1));
        match worst {
            Some((b, rms)) if rms > AGREE_RMS_PX => {
                groups.remove(&b);
            }
            _ => return (!fit.ambiguous).then_some(fit.pose),
        }
    }
}

/// One round of growth: triangulate free points seen by ≥ 2 posed images, then resect
/// images from known points. Returns whether it grew.
fn grow(
    images: &BTreeMap<ImageKey, Vec<(usize, Vec2)>>,
    kinds: &[PointKind],
    cams: &[rigcal_core::geometry::Camera],
    poses: &mut BTreeMap<ImageKey, Pose>,
    points: &mut BTreeMap<usize, Vec3>,
    bodies: &BTreeMap<usize, Pose>,
) -> bool {
    let start = (poses.len(), points.len());
    {
        let before = start;
        let mut rays: BTreeMap<usize, Vec<(Pose, Vec2)>> = BTreeMap::new();
        for (key, obs) in images {
            if let Some(p) = poses.get(key) {
                for (pt, uv) in obs {
                    if kinds[*pt] == PointKind::Free && !points.contains_key(pt) {
                        if let Some(xy) = cams[key.1].unproject(uv) {
                            rays.entry(*pt).or_default().push((*p, xy));
                        }
                    }
                }
            }
        }
        for (pt, views) in rays {
            if views.len() >= 2 {
                if let Some(x) = twoview::triangulate(&views) {
                    let ok = views.iter().all(|(p, _)| p.apply(&x).z > 0.0);
                    // The widest pair of rays decides whether depth is determined.
                    let par = views[1..]
                        .iter()
                        .map(|(p, _)| twoview::parallax(&views[0].0, p, &x))
                        .fold(0.0, f64::max);
                    if ok && par > MIN_TRIANGULATION_PARALLAX {
                        points.insert(pt, x);
                    }
                }
            }
        }
        // Resect only from a good share of what the image sees: a pose from the few
        // points a young reconstruction shares with it is poorly determined, and the
        // points triangulated from it next would fold the scene. When no image
        // qualifies, the single best-covered one goes next (next best view), so growth
        // crosses from one part of a scene to the next one image at a time.
        let mut candidates = Vec::new();
        for (key, obs) in images {
            if poses.contains_key(key) {
                continue;
            }
            let (local, uv) = known_points(obs, kinds, points, bodies);
            if local.len() >= 6 || (local.len() >= 4 && is_planar(&local)) {
                let enough = local.len() * 2 >= obs.len() || local.len() >= RESECT_ENOUGH;
                candidates.push((enough, local.len(), *key, local, uv));
            }
        }
        let any_enough = candidates.iter().any(|c| c.0);
        if !any_enough && points.len() == before.1 {
            // Nothing qualifies and nothing new was triangulated: take the best one.
            if let Some(best) = candidates
                .iter_mut()
                .max_by_key(|c| (c.1, std::cmp::Reverse(c.2)))
            {
                best.0 = true;
            }
        }
        for (enough, _, key, local, uv) in candidates {
            if enough {
                if let Some(fit) = pnp::solve_pose(&cams[key.1], &local, &uv) {
                    if !fit.ambiguous {
                        poses.insert(key, fit.pose);
                    }
                }
            }
        }
    }
    (poses.len(), points.len()) != start
}

/// Incremental reconstruction: grow one round at a time and adjust the scene whenever
/// it grew by 10 % since the last adjustment, so errors do not accumulate along long
/// chains (a 360° loop). Scales to metres as soon as measured points exist. Returns the
/// robust σ of the final adjustment.
#[allow(clippy::too_many_arguments)]
fn grow_and_refine(
    session: &Session,
    images: &BTreeMap<ImageKey, Vec<(usize, Vec2)>>,
    poses: &mut BTreeMap<ImageKey, Pose>,
    points: &mut BTreeMap<usize, Vec3>,
    bodies: &mut BTreeMap<usize, Pose>,
    has_bodies: bool,
    metric: &mut bool,
    opts: &LmOptions,
) -> f64 {
    let kinds = &session.points.kinds;
    let cams: Vec<_> = session.cameras.iter().map(|c| c.camera.clone()).collect();
    let mut last = (0usize, 0usize);
    for _ in 0..100 {
        if !grow(images, kinds, &cams, poses, points, bodies) {
            break;
        }
        let (np, nx) = (poses.len(), points.len());
        if np as f64 > 1.1 * last.0 as f64 || nx as f64 > 1.1 * last.1 as f64 {
            if !*metric {
                *metric = apply_scale(session, poses, points);
            }
            refine_scene(session, images, poses, points, bodies, has_bodies, opts);
            last = (poses.len(), points.len());
        }
    }
    if !*metric {
        *metric = apply_scale(session, poses, points);
    }
    refine_scene(session, images, poses, points, bodies, has_bodies, opts)
}

/// An image's observations of points already placed: (scene coordinates, pixels).
fn known_points(
    obs: &[(usize, Vec2)],
    kinds: &[PointKind],
    points: &BTreeMap<usize, Vec3>,
    bodies: &BTreeMap<usize, Pose>,
) -> (Vec<Vec3>, Vec<Vec2>) {
    obs.iter()
        .filter_map(|(p, uv)| match kinds[*p] {
            PointKind::Free => points.get(p).map(|x| (*x, *uv)),
            PointKind::Body { body, local } => bodies.get(&body).map(|sb| (sb.apply(&local), *uv)),
        })
        .unzip()
}

/// Scale a scene of unknown geometry to metres from the measured distances between its
/// reconstructed points (median ratio). Returns whether the scene is now metric.
fn apply_scale(
    session: &Session,
    poses: &mut BTreeMap<ImageKey, Pose>,
    points: &mut BTreeMap<usize, Vec3>,
) -> bool {
    let ratios: Vec<f64> = session
        .distances
        .iter()
        .filter_map(|d| Some(d.distance / (points.get(&d.a)? - points.get(&d.b)?).norm()))
        .filter(|r| r.is_finite())
        .collect();
    let Some(scale) = median(ratios) else {
        return false;
    };
    for x in points.values_mut() {
        *x *= scale;
    }
    for p in poses.values_mut() {
        p.trans *= scale;
    }
    true
}

/// Median |angle(B) − angle(A)| (rad) between the relative motions of the images of a
/// candidate reconstruction (B, per camera) and of the reference camera over the same
/// frames (A). Zero for a correct reconstruction without noise; 0 if not comparable.
fn angle_mismatch(
    poses: &BTreeMap<ImageKey, Pose>,
    reference: &BTreeMap<usize, Pose>,
    reference_cam: usize,
) -> f64 {
    let mut by_cam: BTreeMap<usize, Vec<(usize, Pose)>> = BTreeMap::new();
    for (k, p) in poses {
        if reference.contains_key(&k.0) && k.1 != reference_cam {
            by_cam.entry(k.1).or_default().push((k.0, *p));
        }
    }
    let mut d = Vec::new();
    for list in by_cam.values() {
        for i in 0..list.len() {
            for j in i + 1..list.len() {
                let (fa, pa) = list[i];
                let (fb, pb) = list[j];
                let b = rigcal_core::geometry::so3::log(&(pb.rot * pa.rot.transpose())).norm();
                let a = rigcal_core::geometry::so3::log(
                    &(reference[&fb].rot * reference[&fa].rot.transpose()),
                )
                .norm();
                d.push((a - b).abs());
            }
        }
    }
    median(d).unwrap_or(0.0)
}

/// Widest ray angle (rad) a free point needs before it is triangulated (COLMAP's 1.5°):
/// depth from narrower rays is mostly noise, and images resected from such points start
/// the fold of a long chain (a 360° loop) that no later adjustment undoes.
const MIN_TRIANGULATION_PARALLAX: f64 = 1.5 * std::f64::consts::PI / 180.0;

/// Share of the best coverage (points + posed images) a start must reach to compete.
const START_COVER_SHARE: f64 = 0.75;
/// Ratio to the best σ beyond which a start's reconstruction counts as folded.
const START_SIGMA_RATIO: f64 = 1.1;

/// Known points from which an image is resected whatever share of its points they are.
const RESECT_ENOUGH: usize = 12;

/// Median parallax (rad) above which a two-view start is not preferred for being wider.
const START_PARALLAX_ENOUGH: f64 = 0.05;

/// Image pairs to start a scene of unknown geometry from: ≥ 8 shared points, ranked by
/// median parallax × √count. Returns up to `n` of `(key a, key b, cam_b_from_cam_a)`.
fn best_pairs(
    images: &BTreeMap<ImageKey, Vec<(usize, Vec2)>>,
    cams: &[rigcal_core::geometry::Camera],
    n: usize,
) -> Vec<(ImageKey, ImageKey, Pose)> {
    let keys: Vec<&ImageKey> = images.keys().collect();
    // Bound the work on long sequences: pair each of the first images with a spread of others.
    let step = (keys.len() / 40).max(1);
    let mut ranked: Vec<(f64, ImageKey, ImageKey, Pose)> = Vec::new();
    for i in (0..keys.len()).step_by(step).take(40) {
        for j in (i + 1..keys.len()).step_by(step) {
            let (a, b) = (&images[keys[i]], &images[keys[j]]);
            let bmap: HashMap<usize, Vec2> = b.iter().copied().collect();
            let mut x1 = Vec::new();
            let mut x2 = Vec::new();
            for (p, uv) in a {
                if let Some(uv2) = bmap.get(p) {
                    if let (Some(p1), Some(p2)) = (
                        cams[keys[i].1].unproject(uv),
                        cams[keys[j].1].unproject(uv2),
                    ) {
                        x1.push(p1);
                        x2.push(p2);
                    }
                }
            }
            if x1.len() < 8 {
                continue;
            }
            let Some(rel) = twoview::relative_pose(&x1, &x2) else {
                continue;
            };
            // Only points in front of both views count; a pose most points disagree with
            // (a wrong chirality under noise) is no start at all.
            let pars: Vec<f64> = x1
                .iter()
                .zip(&x2)
                .filter_map(|(p, q)| twoview::triangulate(&[(Pose::identity(), *p), (rel, *q)]))
                .filter(|x| x.z > 0.0 && rel.apply(x).z > 0.0)
                .map(|x| twoview::parallax(&Pose::identity(), &rel, &x))
                .collect();
            if (pars.len() as f64) < 0.8 * x1.len() as f64 {
                continue;
            }
            // Parallax beyond a few degrees adds little to the start's depth accuracy,
            // while every shared point is one more to resect the next images from: a
            // wide pair sharing 8 points starts a reconstruction nothing else can join.
            let par = median(pars).unwrap_or(0.0).min(START_PARALLAX_ENOUGH);
            let score = par * x1.len() as f64;
            if score > 0.0 {
                ranked.push((score, *keys[i], *keys[j], rel));
            }
        }
    }
    ranked.sort_by(|a, b| b.0.total_cmp(&a.0));
    ranked
        .into_iter()
        .take(n)
        .map(|(_, a, b, r)| (a, b, r))
        .collect()
}

/// Bundle adjustment of one scene; every posed image is its own "rig pose".
fn refine_scene(
    session: &Session,
    images: &BTreeMap<ImageKey, Vec<(usize, Vec2)>>,
    poses: &mut BTreeMap<ImageKey, Pose>,
    points: &mut BTreeMap<usize, Vec3>,
    bodies: &mut BTreeMap<usize, Pose>,
    has_bodies: bool,
    opts: &LmOptions,
) -> f64 {
    let keys: Vec<ImageKey> = poses.keys().copied().collect();
    let pt_ids: Vec<usize> = points.keys().copied().collect();
    let pt_index: HashMap<usize, usize> = pt_ids.iter().enumerate().map(|(i, p)| (*p, i)).collect();
    let body_ids: Vec<usize> = bodies.keys().copied().collect();
    let body_index: HashMap<usize, usize> =
        body_ids.iter().enumerate().map(|(i, b)| (*b, i)).collect();
    let ncam = session.cameras.len();
    let point_ref = |p: usize| super::point_ref(session.points.kinds[p], p, &pt_index, &body_index);
    let mut observations = Vec::new();
    for (r, key) in keys.iter().enumerate() {
        for (p, uv) in &images[key] {
            if let Some(point) = point_ref(*p) {
                observations.push(Obs {
                    rig: r,
                    cam: key.1,
                    point,
                    uv: *uv,
                });
            }
        }
    }
    let distances = super::distance_constraints(session, point_ref);
    let mut problem = BundleProblem {
        cameras: session.cameras.iter().map(|c| c.camera.clone()).collect(),
        rig_from_cam: vec![Pose::identity(); ncam],
        cam_fixed: vec![true; ncam],
        world_from_rig: keys.iter().map(|k| poses[k].inverse()).collect(),
        // Gauge: the anchor body (scene frame) or else the first image is fixed.
        rig_fixed: (0..keys.len()).map(|i| !has_bodies && i == 0).collect(),
        points: pt_ids.iter().map(|p| points[p]).collect(),
        world_from_body: body_ids.iter().map(|b| bodies[b]).collect(),
        body_fixed: body_ids
            .iter()
            .enumerate()
            .map(|(i, _)| has_bodies && i == 0 && bodies[&body_ids[0]] == Pose::identity())
            .collect(),
        observations,
        distances,
        priors: vec![],
        pixel_sigma: 1.0,
    };
    // Drop observations that do not project at the start (a bad pose would poison LM).
    problem.drop_unprojectable();
    let _ = problem.solve_annealed(opts);
    let mut usable = vec![0usize; keys.len()];
    for o in &problem.observations {
        usable[o.rig] += 1;
    }
    for (r, key) in keys.iter().enumerate() {
        if usable[r] >= 4 {
            poses.insert(*key, problem.world_from_rig[r].inverse());
        } else {
            // Every point behind it or unseen: the pose is not supported by the data.
            poses.remove(key);
        }
    }
    for (i, p) in pt_ids.iter().enumerate() {
        points.insert(*p, problem.points[i]);
    }
    for (i, b) in body_ids.iter().enumerate() {
        bodies.insert(*b, problem.world_from_body[i]);
    }
    let norms: Vec<f64> = problem
        .observations
        .iter()
        .filter_map(|o| problem.residual(o))
        .map(|r| r.norm())
        .collect();
    robust_sigma(&norms).unwrap_or(f64::NAN)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(poses: &[(ImageKey, Pose)], scale: SceneScale) -> SceneRecon {
        SceneRecon {
            points: BTreeMap::from([(0, Vec3::new(1.0, 2.0, 3.0))]),
            bodies: BTreeMap::new(),
            poses: poses.iter().copied().collect(),
            scale,
            sigma_px: 1.0,
            part_of: None,
        }
    }

    #[test]
    fn a_split_scene_takes_its_scale_from_the_motions_it_shares() {
        // Camera 1 at frames 3, 4, 5 is posed in both scenes; the rest scene was
        // reconstructed at 1/2.5 of metric scale (and in another frame).
        let cam = |f: usize| {
            Pose::from_rotvec(
                Vec3::new(0.0, 0.3 * f as f64, 0.0),
                Vec3::new(0.4 * f as f64, 0.1, -0.2 * f as f64),
            )
        };
        let other_frame = Pose::from_rotvec(Vec3::new(0.2, -0.1, 0.4), Vec3::new(1.0, 2.0, 3.0));
        let metric = scene(
            &[((3, 1), cam(3)), ((4, 1), cam(4)), ((5, 1), cam(5))],
            SceneScale::Distances,
        );
        let shrink = |p: Pose| {
            let q = p * other_frame;
            Pose::new(q.rot, q.trans / 2.5)
        };
        let mut rest = scene(
            &[
                ((3, 1), shrink(cam(3))),
                ((4, 1), shrink(cam(4))),
                ((5, 1), shrink(cam(5))),
            ],
            SceneScale::Unknown,
        );
        rest.points.insert(0, Vec3::new(0.4, 0.8, 1.2));
        assert!(scale_from_shared_motion(&mut rest, [&metric].into_iter()));
        assert!((rest.points[&0] - Vec3::new(1.0, 2.0, 3.0)).norm() < 1e-12);
        // Nothing shared: no scale, scene untouched.
        let mut alone = scene(&[((7, 2), cam(7)), ((8, 2), cam(8))], SceneScale::Unknown);
        assert!(!scale_from_shared_motion(&mut alone, [&metric].into_iter()));
        assert_eq!(alone.points[&0], Vec3::new(1.0, 2.0, 3.0));
    }

    #[test]
    fn a_scene_of_bodies_is_the_same_on_one_thread_or_several() {
        // The hall's boards and tags: each image posed from the placed bodies and each body
        // placed from the posed images, spread over threads; nothing may depend on the
        // order the threads finish in.
        let (m, _) = rigcal_synth::generate("car-hall", 7, 0.3).expect("preset");
        let session = rigcal_core::session::parse_session(&serde_json::to_vec(&m).expect("json"))
            .expect("session");
        let (scene_of_point, n) = scene_components(&session);
        let opts = LmOptions::default();
        let mut posed = 0;
        for s in 0..n {
            let run = |threads| {
                reconstruct_scene(
                    &session,
                    &scene_of_point,
                    s,
                    &opts,
                    &BTreeMap::new(),
                    threads,
                )
            };
            match (run(1), run(3)) {
                (Ok(a), Ok(b)) => {
                    posed += a.poses.len();
                    assert_eq!(a.poses, b.poses, "scene {s}: image poses");
                    assert_eq!(a.bodies, b.bodies, "scene {s}: bodies");
                    assert_eq!(a.points, b.points, "scene {s}: points");
                    assert_eq!(a.sigma_px.to_bits(), b.sigma_px.to_bits(), "scene {s}: σ");
                }
                (Err(a), Err(b)) => assert_eq!(a, b, "scene {s}"),
                (a, b) => panic!(
                    "scene {s}: {:?} on one thread, {:?} on three",
                    a.err(),
                    b.err()
                ),
            }
        }
        assert!(posed >= 10, "the hall's images are posed ({posed})");
    }
}
