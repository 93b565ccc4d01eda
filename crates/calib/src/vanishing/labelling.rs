//! Which way round each target was labelled in each auxiliary view.
//!
//! A symmetric layout (a 3×2 grid under a half-turn, a 3×3 grid under quarter-turns) looks
//! the same after a rotation about its centre, so the lines found in one image can be
//! labelled in several ways that fit equally well ([`LineLayout::symmetries`]). What the
//! method needs is not the "true" labelling but a *consistent* one: target `t`'s frame
//! is whatever its rig camera's labelling made it, and every auxiliary view must label
//! `t` the same way, or the extrinsic of `t`'s camera comes out rotated about `t`'s
//! centre. Two facts decide it, both geometric:
//!
//! - **Closure.** When a view links two targets whose frames are already fixed (a pair
//!   photographed twice, the view closing the ring), one labelling reproduces their
//!   relative pose and the others are off by a rotation about a target centre, i.e. by
//!   decimetres.
//! - **One rigid rig.** When a view reaches a new target, the labellings place its
//!   camera at different positions: a wrong half-turn throws the camera to the far side
//!   of its target, a quarter-turn sideways by the target distance. The rig cameras are
//!   one body, so the labelling that keeps all cameras closest together is chosen.
//!
//! Both are one cost ([`resolve`]); a decision is *clear* when its runner-up costs
//! distinctly more, and otherwise it is reported as ambiguous (the result is then
//! `degraded`, never silently confident). The rig images fix each frame and need no rule:
//! a rig labelling rotated by a symmetry only renames the target's frame, which cancels
//! in the extrinsic once the auxiliary views agree with it.

use rigcal_core::geometry::{Pose, Vec3};
use rigcal_core::target::line_layout::{LineLayout, Symmetry};

/// How a labelling was decided.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Criterion {
    Closure,
    RigCompactness,
    /// Nothing tells the labellings apart (no camera on the new target, no loop).
    Undetermined,
}

impl Criterion {
    pub fn name(self) -> &'static str {
        match self {
            Criterion::Closure => "closure",
            Criterion::RigCompactness => "rig_compactness",
            Criterion::Undetermined => "undetermined",
        }
    }
}

/// The labelling chosen for one target in one auxiliary view.
#[derive(Clone, Debug)]
pub struct Choice {
    /// Index into the views given to [`resolve`].
    pub view: usize,
    pub target: usize,
    /// Rotation (deg) of the chosen labelling relative to the detected one.
    pub degrees: u32,
    pub criterion: Criterion,
    /// How clearly it won: how much worse the runner-up is, as a distance (m), over half
    /// the median camera–target distance (≥ 1 is clear; ∞ when there is no runner-up).
    pub margin: f64,
    pub clear: bool,
}

/// One auxiliary view: its two targets and their labelled poses `aux_from_target`.
pub struct View {
    pub targets: [usize; 2],
    pub poses: [Pose; 2],
}

/// The symmetry `g` of `layout` applied to a labelled pose: the pose of the layout's own
/// frame (`cam_from_target = cam_from_labelled · (target_from_labelled)⁻¹`).
pub fn relabel(pose: &Pose, g: &Symmetry) -> Pose {
    *pose * g.target_from_labelled.inverse()
}

/// Discrepancy between two relative target poses: translation (m) plus the rotation
/// angle times the layout's size (m), so both count in metres.
fn discrepancy(a: &Pose, b: &Pose, size: f64) -> f64 {
    let (dr, dt) = a.distance(b);
    dt + dr * size
}

/// The ring as a labelling makes it: the discrepancy (m) of every view that links two
/// targets already placed (a closing view, a repeated pair).
struct Placement {
    /// Per view: `Some(discrepancy)` if it closed a loop.
    closing: Vec<Option<f64>>,
}

/// `ta_from_tb` of view `v` under the labels `labels[v]`.
fn relative(syms: &[Vec<Symmetry>], view: &View, labels: [usize; 2]) -> Pose {
    let [a, b] = view.targets;
    relabel(&view.poses[0], &syms[a][labels[0]]).inverse()
        * relabel(&view.poses[1], &syms[b][labels[1]])
}

/// The chain from the reference target, breadth first over the views in order:
/// `ref_from_target` per target it reaches, and which views it used (the others close
/// loops or repeat a pair).
fn chain(
    syms: &[Vec<Symmetry>],
    reference_target: usize,
    views: &[View],
    labels: &[[usize; 2]],
) -> (Vec<Option<Pose>>, Vec<bool>) {
    let mut ref_from: Vec<Option<Pose>> = vec![None; syms.len()];
    ref_from[reference_target] = Some(Pose::identity());
    let mut used = vec![false; views.len()];
    loop {
        let mut grew = false;
        for (v, view) in views.iter().enumerate() {
            if used[v] {
                continue;
            }
            let [a, b] = view.targets;
            match (ref_from[a], ref_from[b]) {
                (Some(ra), None) => ref_from[b] = Some(ra * relative(syms, view, labels[v])),
                (None, Some(rb)) => {
                    ref_from[a] = Some(rb * relative(syms, view, labels[v]).inverse())
                }
                _ => continue,
            }
            used[v] = true;
            grew = true;
        }
        if !grew {
            break;
        }
    }
    (ref_from, used)
}

fn place(
    syms: &[Vec<Symmetry>],
    sizes: &[f64],
    reference_target: usize,
    views: &[View],
    chosen: &[[usize; 2]],
) -> Placement {
    let (ref_from, used) = chain(syms, reference_target, views, chosen);
    let closing = (0..views.len())
        .map(|v| {
            if used[v] {
                return None;
            }
            let [a, b] = views[v].targets;
            let (ra, rb) = (ref_from[a]?, ref_from[b]?);
            Some(discrepancy(
                &relative(syms, &views[v], chosen[v]),
                &(ra.inverse() * rb),
                sizes[a].max(sizes[b]),
            ))
        })
        .collect();
    Placement { closing }
}

/// Relative labellings searched exhaustively by closure (`|G|^n` with `n` the targets
/// seen in more than one pair); above it the ring's labels stay as detected.
const MAX_CLOSURE_SEARCH: usize = 1 << 18;

/// Choose, per view and target, the symmetry that makes the views agree with the rig
/// labellings. `target_from_cam[t]`: the rig camera's position for target `t` (if a rig
/// camera sees it). Returns per view the symmetry index for each of its two targets
/// (0 = as labelled) and the decisions for the report (symmetric targets only).
///
/// Three steps, each a clean discrete choice:
/// 1. Views of the same pair agree with the pair's first view (their `ta_from_tb`).
/// 2. Closure: each target's label in its other pairs relative to its first, all at
///    once, exhaustively: only the consistent choice closes every loop.
/// 3. The rig: a target relabelled the same way in all its views still closes, and
///    moves only its own camera about its centre (the reference target's turns the rest
///    of the rig), so each target's turn is the one that puts its camera nearest the
///    other cameras.
///
/// A choice is clear when its runner-up is worse by `d/2` (m), `d` the median
/// distance of a rig camera to its target: a wrong labelling moves a camera by `√2·d`.
pub fn resolve(
    layouts: &[LineLayout],
    reference_target: usize,
    target_from_cam: &[Option<Pose>],
    views: &[View],
) -> (Vec<[usize; 2]>, Vec<Choice>) {
    let syms: Vec<Vec<Symmetry>> = layouts.iter().map(LineLayout::symmetries).collect();
    let mut chosen = vec![[0usize; 2]; views.len()];
    let mut report = Vec::new();
    let symmetric = |v: &View| v.targets.iter().any(|&t| syms[t].len() > 1);
    if !views.iter().any(symmetric) {
        return (chosen, report);
    }
    let sizes: Vec<f64> = layouts
        .iter()
        .map(|l| {
            let c = l.centre();
            l.segments
                .iter()
                .map(|s| (s.from - c).norm().max((s.to - c).norm()))
                .fold(0.0, f64::max)
        })
        .collect();
    let mut dist: Vec<f64> = target_from_cam
        .iter()
        .flatten()
        .map(|p| p.inverse().trans.norm())
        .collect();
    dist.sort_by(f64::total_cmp);
    let scale = dist.get(dist.len() / 2).copied().unwrap_or(1.0);
    let order = |t: usize| syms[t].len();
    let rel = |v: usize, g: [usize; 2]| relative(&syms, &views[v], g);
    let mut margin_of = vec![f64::INFINITY; views.len()];

    // 1. Repeated views of a pair: agree with the pair's first view.
    let key = |v: usize| {
        let [a, b] = views[v].targets;
        (a.min(b), a.max(b))
    };
    let mut first_of: std::collections::BTreeMap<(usize, usize), usize> = Default::default();
    for v in 0..views.len() {
        let first = *first_of.entry(key(v)).or_insert(v);
        if first == v {
            continue;
        }
        let [a, b] = views[v].targets;
        // The first view's ta_from_tb in this view's target order.
        let known = if views[first].targets == views[v].targets {
            rel(first, [0, 0])
        } else {
            rel(first, [0, 0]).inverse()
        };
        let s = sizes[a].max(sizes[b]);
        let mut scored: Vec<(f64, [usize; 2])> = (0..order(a))
            .flat_map(|ga| (0..order(b)).map(move |gb| [ga, gb]))
            .map(|g| (discrepancy(&rel(v, g), &known, s), g))
            .collect();
        scored.sort_by(|x, y| x.0.total_cmp(&y.0));
        chosen[v] = scored[0].1;
        margin_of[v] = scored
            .get(1)
            .map_or(f64::INFINITY, |r| (r.0 - scored[0].0) / (0.5 * scale));
    }
    // 2. Closure over the distinct pairs: per target, its label in each pair after the
    //    first it appears in, relative to that first.
    let firsts: Vec<usize> = first_of.values().copied().collect();
    let first_views: Vec<View> = firsts
        .iter()
        .map(|&v| View {
            targets: views[v].targets,
            poses: views[v].poses,
        })
        .collect();
    let mut first_pair_of_target: Vec<Option<usize>> = vec![None; layouts.len()];
    let mut unknowns: Vec<(usize, usize)> = Vec::new(); // (view, slot)
    for &v in &firsts {
        for k in 0..2 {
            let t = views[v].targets[k];
            if first_pair_of_target[t].is_none() {
                first_pair_of_target[t] = Some(v);
            } else if order(t) > 1 {
                unknowns.push((v, k));
            }
        }
    }
    let combos = unknowns
        .iter()
        .map(|&(v, k)| order(views[v].targets[k]))
        .try_fold(1usize, |acc, n| {
            acc.checked_mul(n).filter(|x| *x <= MAX_CLOSURE_SEARCH)
        });
    let closure_cost = |labels: &[[usize; 2]]| {
        let l: Vec<[usize; 2]> = firsts.iter().map(|&v| labels[v]).collect();
        place(&syms, &sizes, reference_target, &first_views, &l)
            .closing
            .iter()
            .flatten()
            .map(|d| d * d)
            .sum::<f64>()
            .sqrt()
    };
    let loops = {
        let l = vec![[0usize; 2]; first_views.len()];
        place(&syms, &sizes, reference_target, &first_views, &l)
            .closing
            .iter()
            .flatten()
            .count()
    };
    let decode = |code: usize| {
        let mut labels = chosen.clone();
        let mut c = code;
        for &(v, k) in &unknowns {
            let m = order(views[v].targets[k]);
            labels[v][k] = c % m;
            c /= m;
        }
        labels
    };
    // Closure alone can leave near-ties when many labels are unknown (65 536 labellings
    // of a ring of eight "#" grids put some within millimetres of closing): the best
    // decides, and a near-tie is reported (a sum with the rig's spread was tried and
    // let folded rigs win).
    let searched = combos.is_some() && loops > 0 && !unknowns.is_empty();
    let mut candidates: Vec<(f64, usize)> = Vec::new();
    if let (Some(n), true) = (combos, searched) {
        for code in 0..n {
            candidates.push((closure_cost(&decode(code)), code));
        }
        candidates.sort_by(|x, y| x.0.total_cmp(&y.0));
    } else {
        candidates.push((0.0, 0));
    }
    // Repeated views follow their pair's first view's change.
    let repeats = |labels: &mut Vec<[usize; 2]>| {
        for v in 0..views.len() {
            let first = first_of[&key(v)];
            if first != v {
                let f = labels[first];
                let same = views[first].targets == views[v].targets;
                let (fa, fb) = if same { (f[0], f[1]) } else { (f[1], f[0]) };
                let [a, b] = views[v].targets;
                labels[v] = [
                    (labels[v][0] + fa) % order(a),
                    (labels[v][1] + fb) % order(b),
                ];
            }
        }
    };
    // 3. The rig: each target's turn in all its views, its camera nearest the others.
    let turn_all = |labels: &mut Vec<[usize; 2]>, t: usize, h: usize| {
        for (v, view) in views.iter().enumerate() {
            for k in 0..2 {
                if view.targets[k] == t {
                    labels[v][k] = (labels[v][k] + h) % order(t);
                }
            }
        }
    };
    let cameras = |labels: &[[usize; 2]]| -> Vec<Option<Vec3>> {
        let l: Vec<[usize; 2]> = firsts.iter().map(|&v| labels[v]).collect();
        place_cameras(&syms, reference_target, target_from_cam, &first_views, &l)
    };
    let rig = |labels: &mut Vec<[usize; 2]>| -> (Vec<f64>, Vec<bool>, f64) {
        let mut rig_margin = vec![f64::INFINITY; layouts.len()];
        let mut rig_known = vec![false; layouts.len()];
        for _sweep in 0..2 {
            for t in (0..layouts.len()).filter(|&t| order(t) > 1 && target_from_cam[t].is_some()) {
                let mut scored = Vec::new();
                for h in 0..order(t) {
                    let mut l = labels.clone();
                    turn_all(&mut l, t, h);
                    let cams = cameras(&l);
                    let others: Vec<Vec3> = cams
                        .iter()
                        .enumerate()
                        .filter(|(u, _)| *u != t)
                        .filter_map(|(_, c)| *c)
                        .collect();
                    if others.is_empty() {
                        break;
                    }
                    let centroid = others.iter().sum::<Vec3>() / others.len() as f64;
                    // The reference target's turn swings every other camera about its
                    // centre: judge it by their mean distance to the reference camera;
                    // another target's, by its own camera's distance to the others'.
                    let score = if t == reference_target {
                        let me = cams[t].unwrap_or(centroid);
                        others.iter().map(|c| (c - me).norm()).sum::<f64>() / others.len() as f64
                    } else {
                        cams[t].map_or(f64::INFINITY, |c| (c - centroid).norm())
                    };
                    scored.push((score, h));
                }
                if scored.len() < order(t) {
                    continue;
                }
                scored.sort_by(|x, y| x.0.total_cmp(&y.0));
                turn_all(labels, t, scored[0].1);
                rig_margin[t] = (scored[1].0 - scored[0].0) / (0.5 * scale);
                rig_known[t] = true;
            }
        }
        let cams: Vec<Vec3> = cameras(labels).into_iter().flatten().collect();
        let c = cams.iter().sum::<Vec3>() / cams.len().max(1) as f64;
        let spread = cams.iter().map(|x| (x - c).norm()).sum::<f64>() / cams.len().max(1) as f64;
        (rig_margin, rig_known, spread)
    };
    let closure_done = searched || unknowns.is_empty();
    let closure_margin = match (candidates.first(), candidates.get(1)) {
        (Some(b), Some(r)) => (r.0 - b.0) / (0.5 * scale),
        _ => f64::INFINITY,
    };
    let Some(&(_, code)) = candidates.first() else {
        return (chosen, report);
    };
    let mut labels = decode(code);
    repeats(&mut labels);
    let (rig_margin, rig_known, _) = rig(&mut labels);
    chosen = labels;
    for v in (0..views.len()).filter(|&v| symmetric(&views[v])) {
        for (k, &t) in views[v].targets.iter().enumerate() {
            if order(t) <= 1 {
                continue;
            }
            let repeated = first_of[&key(v)] != v;
            let in_closure = unknowns.contains(&(v, k));
            let (criterion, margin) = if !rig_known[t] {
                (Criterion::Undetermined, 0.0)
            } else {
                let mut m = rig_margin[t];
                let mut c = Criterion::RigCompactness;
                if in_closure {
                    if !closure_done {
                        m = 0.0;
                    } else if closure_margin < m {
                        m = closure_margin;
                        c = Criterion::Closure;
                    }
                }
                if repeated && margin_of[v] < m {
                    m = margin_of[v];
                    c = Criterion::Closure;
                }
                (c, m)
            };
            report.push(Choice {
                view: v,
                target: t,
                degrees: syms[t][chosen[v][k]].degrees,
                criterion,
                margin,
                clear: margin >= 1.0 && criterion != Criterion::Undetermined,
            });
        }
    }
    (chosen, report)
}

/// Camera positions (reference frame) per target through the chain of `views`.
fn place_cameras(
    syms: &[Vec<Symmetry>],
    reference_target: usize,
    target_from_cam: &[Option<Pose>],
    views: &[View],
    labels: &[[usize; 2]],
) -> Vec<Option<Vec3>> {
    let (ref_from, _) = chain(syms, reference_target, views, labels);
    (0..syms.len())
        .map(|t| Some((ref_from[t]? * target_from_cam[t]?).trans))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rigcal_core::geometry::so3;

    /// Four targets around a compact rig; each camera 0.6 m inside its target.
    fn scene() -> (Vec<Pose>, Vec<Pose>) {
        let mut ref_from_target = Vec::new();
        let mut target_from_cam = Vec::new();
        // Irregular yaws and distances: no symmetry of the scene hides a labelling.
        for (yaw, dist) in [(0.0f64, 1.0), (80.0, 1.2), (170.0, 0.9), (275.0, 1.1)] {
            let r = so3::exp(&Vec3::new(0.0, yaw.to_radians(), 0.0));
            ref_from_target.push(Pose::new(r, r * Vec3::new(0.0, 0.15, dist)));
            // The camera 0.6 m back towards the rig centre and 0.15 m above the target.
            target_from_cam.push(Pose::new(
                so3::exp(&Vec3::new(0.7, 0.0, 0.0)),
                Vec3::new(0.0, -0.15, -0.6),
            ));
        }
        (ref_from_target, target_from_cam)
    }

    #[test]
    fn misrotated_labellings_are_found_by_the_rig() {
        let layout = LineLayout::grid(0.5, 0.2, 3, 2, 0.012);
        let layouts = vec![layout.clone(); 4];
        let half = &layout.symmetries()[1];
        let (rft, tfc) = scene();
        // The first camera at the origin: express everything relative to it.
        let ref_cam = rft[0] * tfc[0];
        let rft: Vec<Pose> = rft.iter().map(|p| ref_cam.inverse() * *p).collect();
        let aux = Pose::new(
            so3::exp(&Vec3::new(1.2, 0.0, 0.0)),
            Vec3::new(0.0, -1.0, 0.0),
        );
        // View k sees targets (k, k+1); some labelled with the half-turn.
        let flips = [[false, true], [true, false], [false, false], [true, true]];
        let views: Vec<View> = (0..4)
            .map(|k| {
                let pair = [k, (k + 1) % 4];
                let poses = [0, 1].map(|i| {
                    let truth = aux.inverse() * rft[pair[i]];
                    // A label rotated by g gives cam_from_labelled = truth · g.
                    if flips[k][i] {
                        truth * half.target_from_labelled
                    } else {
                        truth
                    }
                });
                View {
                    targets: pair,
                    poses,
                }
            })
            .collect();
        let tfc: Vec<Option<Pose>> = tfc.into_iter().map(Some).collect();
        let (chosen, report) = resolve(&layouts, 0, &tfc, &views);
        for k in 0..4 {
            assert_eq!(chosen[k], flips[k].map(usize::from), "view {k}");
        }
        assert!(report.iter().all(|c| c.clear), "{report:?}");
        assert!(report
            .iter()
            .any(|c| c.criterion == Criterion::RigCompactness));
    }

    #[test]
    fn asymmetric_layouts_need_no_decision() {
        let layouts = vec![LineLayout::l_target(0.5, 0.2); 2];
        let views = vec![View {
            targets: [0, 1],
            poses: [Pose::identity(), Pose::identity()],
        }];
        let (chosen, report) = resolve(&layouts, 0, &[None, None], &views);
        assert_eq!(chosen, vec![[0, 0]]);
        assert!(report.is_empty());
    }
}
