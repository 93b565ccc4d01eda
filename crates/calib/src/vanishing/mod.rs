//! The vanishing method (Wu et al. 2016) for static rings of cameras whose views do not
//! overlap: each rig camera sees its own planar line target; an auxiliary camera
//! photographs neighbouring targets in pairs.
//!
//! camera–target poses (vanishing points + L1, point-to-line LM) → pair transforms from
//! the auxiliary views (eq. 22) → chain from the reference target (eq. 23) → ring-closure
//! optimisation of all targets and auxiliary views (eq. 25) → camera extrinsics (eq. 26).

pub mod bundle;
pub mod labelling;
pub mod pose;
pub mod ring;

use bundle::{LineBundle, LinePoints, LineSummary};
use pose::{estimate_view_pose, ideal_camera, undistort, ViewPose};
use rigcal_core::geometry::{Camera, Pose, Vec2};
use rigcal_core::result::Reason;
use rigcal_core::session::{LineObs, Session, VanishingInput};
use rigcal_core::target::line_layout::LineLayout;
use rigcal_core::verdict::{ReasonCode, Severity};
use rigcal_solve::Loss;
use ring::{chain, fuse, propagate, Edges, Uncertain};

#[derive(Clone, Debug)]
pub struct VanishingOptions {
    pub loss: Loss,
    pub max_iterations: usize,
}

/// A problem found on the way, with its stable code (see `docs/formats.md`). A fatal
/// one ([`ReasonCode::severity`]) found before the extrinsics stops the method.
#[derive(Clone, Debug)]
pub struct Finding {
    pub code: ReasonCode,
    pub message: String,
    pub camera: Option<String>,
}

impl Finding {
    pub fn reason(&self) -> Reason {
        Reason::new(self.code, self.message.clone(), self.camera.as_deref())
    }
}

#[derive(Clone, Debug)]
pub struct CameraSolution {
    pub camera: usize,
    pub target: usize,
    pub view: ViewPose,
    /// Targets from the reference target to this camera's, inclusive.
    pub path: Vec<usize>,
    pub chainwise: Uncertain,
    pub global: Uncertain,
}

#[derive(Clone, Debug)]
pub struct RingViewSolution {
    /// Index into `session.manifest.ring`.
    pub ring: usize,
    pub poses: [ViewPose; 2],
    /// Point-to-line residuals (px) after the global optimisation.
    pub residuals: Vec<f64>,
}

#[derive(Clone, Debug)]
pub struct Solution {
    pub reference_target: usize,
    pub cameras: Vec<CameraSolution>,
    pub ring_views: Vec<RingViewSolution>,
    /// Pairs `(i, j)` with the number of usable auxiliary views of each.
    pub pairs: Vec<((usize, usize), usize)>,
    /// Largest chain closure error over the closing pairs: (pair, translation m, rotation rad).
    pub closure: Option<((usize, usize), f64, f64)>,
    pub summary: LineSummary,
    pub sigma_px: f64,
    /// Labelling decisions for symmetric targets in the auxiliary views (`view` indexes
    /// `ring_views`' order before unusable views were dropped: see `ring`).
    pub labelling: Vec<(usize, labelling::Choice)>,
}

type Pair = (usize, usize);
type ComposeFn = fn(&[Pose]) -> Pose;

/// Undistorted points of each line of `target` (a layout of `lines` lines) among `obs`.
fn points_by_line(camera: &Camera, obs: &[LineObs], target: usize, lines: usize) -> Vec<Vec<Vec2>> {
    let mut out = vec![Vec::new(); lines];
    for o in obs.iter().filter(|o| o.target == target && o.line < lines) {
        out[o.line] = undistort(camera, &o.points);
    }
    out
}

fn geometry(input: &VanishingInput) -> Vec<LineLayout> {
    input.targets.iter().map(|t| t.layout.clone()).collect()
}

fn finding(code: ReasonCode, message: String, camera: Option<&str>) -> Finding {
    Finding {
        code,
        message,
        camera: camera.map(str::to_string),
    }
}

/// Run the vanishing method. Returns the solution (if any) and what was found on the way.
pub fn solve(session: &Session, opts: &VanishingOptions) -> (Option<Solution>, Vec<Finding>) {
    let mut findings = Vec::new();
    let Some(input) = &session.vanishing else {
        findings.push(finding(
            ReasonCode::MethodNotSupported,
            "not a vanishing-method session".into(),
            None,
        ));
        return (None, findings);
    };
    let geo = geometry(input);
    let names: Vec<&str> = session.cameras.iter().map(|c| c.id.as_str()).collect();
    let tname = |t: usize| input.targets[t].id.as_str();

    // 1. Camera–target poses of the rig cameras.
    let mut rig: Vec<Option<(usize, ViewPose)>> = vec![None; names.len()];
    for (c, obs) in input.rig.iter().enumerate() {
        let Some(first) = obs.first() else {
            findings.push(finding(
                ReasonCode::CameraNotObserved,
                format!("camera {} has no line observations of a target", names[c]),
                Some(names[c]),
            ));
            continue;
        };
        let cam = &session.cameras[c].camera;
        let pts = points_by_line(cam, obs, first.target, geo[first.target].len());
        match estimate_view_pose(
            &ideal_camera(cam),
            &geo[first.target],
            &pts,
            &opts.loss,
            opts.max_iterations,
        ) {
            Ok(v) => {
                if v.init == pose::Init::Homography {
                    findings.push(finding(ReasonCode::VanishingPointAtInfinity, format!("camera {} sees target {} almost fronto-parallel (line directions {:.1}° and {:.1}° from the image plane): the vanishing points are ill-conditioned, so its pose was initialised from the corner homography; tilt the target (about 40°) for the vanishing method", names[c], tname(first.target), v.elevation_deg[0], v.elevation_deg[1]), Some(names[c])));
                }
                rig[c] = Some((first.target, v));
            }
            Err(why) => findings.push(finding(
                ReasonCode::LinesUnusable,
                format!("camera {}, target {}: {why}", names[c], tname(first.target)),
                Some(names[c]),
            )),
        }
    }

    // 2. Auxiliary views: both targets' poses, then the pair transform (eq. 22).
    let aux = ideal_camera(&input.auxiliary.camera);
    let mut views: Vec<(usize, [ViewPose; 2])> = Vec::new();
    for (ri, r) in input.ring.iter().enumerate() {
        let mut poses = Vec::new();
        for &t in &r.targets {
            let pts = points_by_line(&input.auxiliary.camera, &r.lines, t, geo[t].len());
            match estimate_view_pose(&aux, &geo[t], &pts, &opts.loss, opts.max_iterations) {
                Ok(v) => {
                    if v.init == pose::Init::Homography {
                        findings.push(finding(ReasonCode::VanishingPointAtInfinity, format!("ring[{ri}] sees target {} almost fronto-parallel (line directions {:.1}° and {:.1}° from the image plane): pose initialised from the corner homography; photograph pairs from about 40° above the target plane", tname(t), v.elevation_deg[0], v.elevation_deg[1]), None));
                    }
                    poses.push(v)
                }
                Err(why) => {
                    findings.push(finding(
                        ReasonCode::RingViewUnusable,
                        format!(
                            "ring[{ri}] (index {}), target {}: {why}; the view is left out",
                            r.index,
                            tname(t)
                        ),
                        None,
                    ));
                    break;
                }
            }
        }
        let Ok(poses) = <[ViewPose; 2]>::try_from(poses) else {
            continue;
        };
        views.push((ri, poses));
    }

    // 2b. Symmetric layouts: label every target in every auxiliary view as its rig view did.
    let Some((reference_target, _)) = rig[session.reference].clone() else {
        return (None, findings);
    };
    let mut target_from_cam = vec![None; geo.len()];
    for (t, v) in rig.iter().flatten() {
        target_from_cam[*t] = Some(v.cam_from_target.inverse());
    }
    let label_views: Vec<labelling::View> = views
        .iter()
        .map(|(ri, p)| labelling::View {
            targets: input.ring[*ri].targets,
            poses: [p[0].cam_from_target, p[1].cam_from_target],
        })
        .collect();
    let (chosen, labelling) =
        labelling::resolve(&geo, reference_target, &target_from_cam, &label_views);
    let mut ring_lines: Vec<Vec<LineObs>> = input.ring.iter().map(|r| r.lines.clone()).collect();
    for ((ri, poses), g) in views.iter_mut().zip(&chosen) {
        for k in 0..2 {
            let t = input.ring[*ri].targets[k];
            let Some(sym) = geo[t]
                .symmetries()
                .into_iter()
                .nth(g[k])
                .filter(|_| g[k] > 0)
            else {
                continue;
            };
            poses[k].cam_from_target = labelling::relabel(&poses[k].cam_from_target, &sym);
            poses[k].initial = labelling::relabel(&poses[k].initial, &sym);
            for o in ring_lines[*ri].iter_mut().filter(|o| o.target == t) {
                o.line = sym.line_of[o.line];
            }
        }
    }
    for c in labelling.iter().filter(|c| !c.clear) {
        let ri = views[c.view].0;
        findings.push(finding(
            ReasonCode::LineLabellingAmbiguous,
            format!(
                "ring[{ri}] (index {}), target {}: the grid is symmetric and which way round it was photographed is not clearly decided ({}: margin {:.2}, clear from 1); the most consistent labelling is used. Photograph each pair twice, or print an orientation mark",
                input.ring[ri].index,
                tname(c.target),
                c.criterion.name(),
                c.margin
            ),
            None,
        ));
    }
    let mut per_pair: std::collections::BTreeMap<(usize, usize), Vec<Uncertain>> =
        Default::default();
    for (ri, poses) in &views {
        let r = &input.ring[*ri];
        let (i, j) = (r.targets[0], r.targets[1]);
        let factors = [
            Uncertain {
                pose: poses[0].cam_from_target,
                cov: poses[0].covariance.clone(),
            },
            Uncertain {
                pose: poses[1].cam_from_target,
                cov: poses[1].covariance.clone(),
            },
        ];
        // ti_from_tj = (aux_from_ti)⁻¹ · aux_from_tj, keyed with i < j.
        let (key, f): (Pair, ComposeFn) = if i < j {
            ((i, j), |p| p[0].inverse() * p[1])
        } else {
            ((j, i), |p| p[1].inverse() * p[0])
        };
        let poses_now: Vec<Pose> = factors.iter().map(|u| u.pose).collect();
        per_pair.entry(key).or_default().push(Uncertain {
            pose: f(&poses_now),
            cov: propagate(&factors, f),
        });
    }
    let mut edges = Edges::new();
    let mut pairs = Vec::new();
    for (key, est) in &per_pair {
        if let Some(u) = fuse(est) {
            edges.insert(*key, u);
            pairs.push((*key, est.len()));
        }
    }

    // 3. Chain from the reference camera's target (eq. 23).
    let ch = chain(input.targets.len(), reference_target, &edges);
    for (c, r) in rig.iter().enumerate() {
        let Some((t, _)) = r else { continue };
        if ch.path[*t].is_empty() {
            let in_ring = input.ring.iter().any(|v| v.targets.contains(t));
            let (code, why) = if in_ring {
                (ReasonCode::RingBroken, format!("target {} of camera {} is not connected to the reference target {} through the auxiliary views: the ring is broken; photograph the missing neighbouring pair(s)", tname(*t), names[c], tname(reference_target)))
            } else {
                (ReasonCode::TargetNotLinked, format!("target {} of camera {} appears in no usable auxiliary view: photograph it together with a neighbouring target", tname(*t), names[c]))
            };
            findings.push(finding(code, why, Some(names[c])));
        }
    }
    if findings
        .iter()
        .any(|f| f.code.severity() == Severity::Fatal)
    {
        return (None, findings);
    }
    let closure = ch
        .closing
        .iter()
        .filter_map(|e| ch.closure_error(&edges, *e).map(|(t, r)| (*e, t, r)))
        .max_by(|a, b| a.1.total_cmp(&b.1));

    // 4. Ring-closure optimisation (eq. 25): all targets linked to the reference and
    //    every usable auxiliary view, from the chain.
    let linked: Vec<bool> = ch.path.iter().map(|p| !p.is_empty()).collect();
    let views_ring: Vec<usize> = views.iter().map(|(ri, _)| *ri).collect();
    views.retain(|(ri, _)| input.ring[*ri].targets.iter().all(|t| linked[*t]));
    let mut problem = LineBundle {
        geometry: geo.clone(),
        ref_from_target: ch
            .ref_from_target
            .iter()
            .map(|u| u.as_ref().map_or(Pose::identity(), |u| u.pose))
            .collect(),
        target_free: (0..geo.len())
            .map(|t| linked[t] && t != reference_target)
            .collect(),
        cameras: vec![aux.clone(); views.len()],
        cam_from_ref: views
            .iter()
            .map(|(ri, poses)| {
                let t = input.ring[*ri].targets[0];
                poses[0].cam_from_target * target_from_ref(&ch.ref_from_target[t])
            })
            .collect(),
        view_free: vec![true; views.len()],
        obs: views
            .iter()
            .enumerate()
            .flat_map(|(v, (ri, _))| {
                ring_lines[*ri].iter().map(move |o| LinePoints {
                    view: v,
                    target: o.target,
                    line: o.line,
                    points: undistort(&input.auxiliary.camera, &o.points),
                    weight: 1.0,
                })
            })
            .collect(),
    };
    let summary = problem.solve_weighing_lines(&opts.loss, opts.max_iterations);
    let Some((cov, sigma_px)) = problem.covariance(&opts.loss) else {
        findings.push(finding(
            ReasonCode::NoConvergence,
            "the ring-closure optimisation is singular: the auxiliary views do not determine the targets".into(),
            None,
        ));
        return (None, findings);
    };
    if !summary.converged {
        findings.push(finding(
            ReasonCode::NoConvergence,
            format!(
                "the ring-closure optimisation stopped: {}",
                summary.termination
            ),
            None,
        ));
    }
    let target_cov = |t: usize| match problem.target_column(t) {
        Some(c) => cov.view((c, c), (6, 6)).into_owned(),
        None => nalgebra::DMatrix::zeros(6, 6),
    };
    let residuals = problem.residuals();
    let ring_views = views
        .iter()
        .enumerate()
        .map(|(v, (ri, poses))| RingViewSolution {
            ring: *ri,
            poses: poses.clone(),
            residuals: problem
                .obs
                .iter()
                .zip(&residuals)
                .filter(|(o, _)| o.view == v)
                .flat_map(|(_, r)| r.iter().copied())
                .collect(),
        })
        .collect();

    // 5. Camera extrinsics (eq. 26): refcam_from_cam = refcam_from_reftarget ·
    //    reftarget_from_target · target_from_cam.
    let Some((_, ref_view)) = rig[session.reference].clone() else {
        return (None, findings);
    };
    let ref_factor = Uncertain {
        pose: ref_view.cam_from_target,
        cov: ref_view.covariance.clone(),
    };
    let compose = |p: &[Pose]| p[0] * p[1] * p[2].inverse();
    let mut cameras = Vec::new();
    for (c, r) in rig.iter().enumerate() {
        let Some((t, view)) = r else { continue };
        let own = Uncertain {
            pose: view.cam_from_target,
            cov: view.covariance.clone(),
        };
        let extrinsic = |target: Uncertain| {
            if c == session.reference {
                return Uncertain {
                    pose: Pose::identity(),
                    cov: nalgebra::DMatrix::zeros(6, 6),
                };
            }
            let f = [ref_factor.clone(), target, own.clone()];
            let poses: Vec<Pose> = f.iter().map(|u| u.pose).collect();
            Uncertain {
                pose: compose(&poses),
                cov: propagate(&f, compose),
            }
        };
        // Unlinked targets were reported as fatal above; skip rather than panic.
        let Some(chain_t) = ch.ref_from_target[*t].clone() else {
            continue;
        };
        let global_t = Uncertain {
            pose: problem.ref_from_target[*t],
            cov: target_cov(*t),
        };
        cameras.push(CameraSolution {
            camera: c,
            target: *t,
            view: view.clone(),
            path: ch.path[*t].clone(),
            chainwise: extrinsic(chain_t),
            global: extrinsic(global_t),
        });
    }
    (
        Some(Solution {
            reference_target,
            cameras,
            ring_views,
            pairs,
            closure,
            summary,
            sigma_px,
            labelling: labelling
                .into_iter()
                .map(|c| (views_ring[c.view], c))
                .collect(),
        }),
        findings,
    )
}

/// `target_from_ref` from the chain's `ref_from_target` (identity where unlinked).
fn target_from_ref(u: &Option<Uncertain>) -> Pose {
    u.as_ref().map_or(Pose::identity(), |u| u.pose.inverse())
}
