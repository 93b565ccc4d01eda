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
//!   decimetres: the consistent one is chosen by that discrepancy.
//! - **One rigid rig.** When a view reaches a new target, the labellings place its
//!   camera at different positions: a wrong half-turn throws the camera to the far side
//!   of its target, a quarter-turn sideways by the target distance. The rig cameras are
//!   one body, so the labelling that puts the new camera nearest the cameras already
//!   placed is chosen.
//!
//! A decision is *clear* when the runner-up is worse by [`CLEAR_RATIO`]; otherwise the
//! given labelling is kept and the choice is reported as ambiguous (the result is then
//! `degraded`, never confidently wrong). The rig images fix each frame and need no rule:
//! a rig labelling rotated by a symmetry only renames the target's frame, which cancels
//! in the extrinsic once the auxiliary views agree with it.

use rigcal_core::geometry::{Pose, Vec3};
use rigcal_core::target::line_layout::{LineLayout, Symmetry};

/// Runner-up score over best score above which a labelling decision is clear.
pub const CLEAR_RATIO: f64 = 1.5;

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
    /// Runner-up score over best (∞ when there is no runner-up).
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

/// Choose, per view and target, the symmetry that makes the views agree with the rig
/// labellings. `target_from_cam[t]`: the rig camera's position for target `t` (if a rig
/// camera sees it). Returns per view the symmetry index for each of its two targets
/// (0 = as labelled) and the decisions for the report (symmetric targets only).
pub fn resolve(
    layouts: &[LineLayout],
    reference_target: usize,
    target_from_cam: &[Option<Pose>],
    views: &[View],
) -> (Vec<[usize; 2]>, Vec<Choice>) {
    let syms: Vec<Vec<Symmetry>> = layouts.iter().map(LineLayout::symmetries).collect();
    let mut chosen = vec![[0usize; 2]; views.len()];
    let mut report = Vec::new();
    if views
        .iter()
        .all(|v| v.targets.iter().all(|&t| syms[t].len() <= 1))
    {
        return (chosen, report);
    }
    let size = |t: usize| {
        let c = layouts[t].centre();
        layouts[t]
            .segments
            .iter()
            .map(|s| (s.from - c).norm().max((s.to - c).norm()))
            .fold(0.0, f64::max)
    };
    let mut ref_from_target: Vec<Option<Pose>> = vec![None; layouts.len()];
    ref_from_target[reference_target] = Some(Pose::identity());
    let camera_at = |placed: &[Option<Pose>], t: usize| -> Option<Vec3> {
        Some((placed[t]? * target_from_cam[t]?).trans)
    };
    let mut done = vec![false; views.len()];
    loop {
        // Views with both targets placed first (closure is the stronger test), then the
        // first view that reaches a new target.
        let next = (0..views.len())
            .filter(|&v| !done[v])
            .map(|v| {
                let placed = views[v].targets.map(|t| ref_from_target[t].is_some());
                (v, placed)
            })
            .filter(|(_, p)| p[0] || p[1])
            .min_by_key(|(v, p)| (!(p[0] && p[1]), *v));
        let Some((v, placed)) = next else { break };
        done[v] = true;
        let view = &views[v];
        let [a, b] = view.targets;
        // Candidates: every pair of symmetries, each giving ta_from_tb.
        let mut candidates = Vec::new();
        for (ga, sa) in syms[a].iter().enumerate() {
            for (gb, sb) in syms[b].iter().enumerate() {
                let pa = relabel(&view.poses[0], sa);
                let pb = relabel(&view.poses[1], sb);
                candidates.push(([ga, gb], pa.inverse() * pb));
            }
        }
        let (scores, criterion): (Vec<Option<f64>>, Criterion) = if placed[0] && placed[1] {
            let (Some(ra), Some(rb)) = (ref_from_target[a], ref_from_target[b]) else {
                continue;
            };
            let known = ra.inverse() * rb;
            let s = size(a).max(size(b));
            (
                candidates
                    .iter()
                    .map(|(_, rel)| Some(discrepancy(rel, &known, s)))
                    .collect(),
                Criterion::Closure,
            )
        } else {
            // Place the new target (from the placed one) and score its camera.
            let (from, to) = if placed[0] { (a, b) } else { (b, a) };
            let Some(rf) = ref_from_target[from] else {
                continue;
            };
            let placed_cams: Vec<Vec3> = (0..layouts.len())
                .filter_map(|t| camera_at(&ref_from_target, t))
                .collect();
            let centroid = placed_cams.iter().sum::<Vec3>() / placed_cams.len().max(1) as f64;
            let scores: Vec<Option<f64>> = candidates
                .iter()
                .map(|(_, rel)| {
                    let rel = if from == a { *rel } else { rel.inverse() };
                    let cam = (rf * rel * target_from_cam[to]?).trans;
                    Some((cam - centroid).norm())
                })
                .collect();
            let criterion = if scores.iter().all(Option::is_some) && !placed_cams.is_empty() {
                Criterion::RigCompactness
            } else {
                Criterion::Undetermined
            };
            (scores, criterion)
        };
        // Best and runner-up among candidates that differ in outcome.
        let given = 0; // [0, 0]: as labelled
        let (best, margin) = match criterion {
            Criterion::Undetermined => (given, 1.0),
            _ => {
                let s: Vec<f64> = scores.iter().map(|x| x.unwrap_or(f64::INFINITY)).collect();
                let best = (0..s.len())
                    .min_by(|&i, &j| s[i].total_cmp(&s[j]))
                    .unwrap_or(given);
                let runner = (0..s.len())
                    .filter(|&i| i != best)
                    .map(|i| s[i])
                    .fold(f64::INFINITY, f64::min);
                let margin = if s[best] > 0.0 {
                    runner / s[best]
                } else if runner > 0.0 {
                    f64::INFINITY
                } else {
                    1.0
                };
                (best, margin)
            }
        };
        let clear = margin >= CLEAR_RATIO;
        let pick = if clear { best } else { given };
        let (g, rel) = candidates[pick];
        chosen[v] = g;
        if !(placed[0] && placed[1]) {
            if placed[0] {
                ref_from_target[b] = ref_from_target[a].map(|r| r * rel);
            } else {
                ref_from_target[a] = ref_from_target[b].map(|r| r * rel.inverse());
            }
        }
        for (k, &t) in view.targets.iter().enumerate() {
            if syms[t].len() > 1 {
                report.push(Choice {
                    view: v,
                    target: t,
                    degrees: syms[t][g[k]].degrees,
                    criterion,
                    margin,
                    clear: clear && criterion != Criterion::Undetermined,
                });
            }
        }
    }
    (chosen, report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rigcal_core::geometry::so3;

    /// Four targets around a compact rig; each camera 0.6 m inside its target.
    fn scene() -> (Vec<Pose>, Vec<Pose>) {
        let mut ref_from_target = Vec::new();
        let mut target_from_cam = Vec::new();
        for k in 0..4 {
            let yaw = k as f64 * std::f64::consts::FRAC_PI_2;
            let r = so3::exp(&Vec3::new(0.0, yaw, 0.0));
            ref_from_target.push(Pose::new(r, r * Vec3::new(0.0, 0.15, 1.0)));
            // The camera 0.6 m back towards the rig centre and 0.15 m above the target.
            target_from_cam.push(Pose::new(
                so3::exp(&Vec3::new(0.7, 0.0, 0.0)),
                Vec3::new(0.0, -0.15, -0.6),
            ));
        }
        (ref_from_target, target_from_cam)
    }

    #[test]
    fn misrotated_labellings_are_found_by_the_rig_and_by_closure() {
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
        assert!(report.iter().any(|c| c.criterion == Criterion::Closure));
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
