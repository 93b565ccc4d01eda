//! The stage runner of the vanishing method: session → result document.
//! camera–target poses and pair transforms → chain and ring-closure optimisation →
//! extrinsics with their σ, chainwise beside global.

use super::{enter, failed, reason, CalibOptions, Cancelled, Progress};
use rigcal_calib::vanishing::{self, pose::Init, VanishingOptions};
use rigcal_core::result::*;
use rigcal_core::session::Session;
use rigcal_core::verdict::{status_of, ReasonCode};
use std::time::Instant;

fn init_name(i: Init) -> String {
    match i {
        Init::VanishingPoints => "vanishing_points",
        Init::Homography => "homography",
    }
    .into()
}

/// Per-axis 1-σ (translation m, rotation deg) of a `[dt, dφ]` covariance.
fn sigmas(cov: &nalgebra::DMatrix<f64>) -> ([f64; 3], [f64; 3]) {
    (
        [0, 1, 2].map(|a| cov[(a, a)].max(0.0).sqrt()),
        [3, 4, 5].map(|a| cov[(a, a)].max(0.0).sqrt().to_degrees()),
    )
}

pub(super) fn calibrate(
    session: &Session,
    opts: &CalibOptions,
    progress: &dyn Progress,
) -> Result<ResultDocument, Cancelled> {
    let mut stages = Vec::new();
    let ids: Vec<&str> = session.cameras.iter().map(|c| c.id.as_str()).collect();
    let Some(input) = &session.vanishing else {
        return Ok(failed(
            session,
            vec![reason(
                ReasonCode::MethodNotSupported,
                "not a vanishing-method session",
                None,
            )],
            stages,
        ));
    };
    enter(progress, "camera_target_poses")?;
    let t = Instant::now();
    let vopts = VanishingOptions {
        loss: opts.rig_ba.loss,
        max_iterations: opts.rig_ba.max_iterations,
    };
    let (solution, findings) = vanishing::solve(session, &vopts);
    stages.push(Stage {
        name: "camera_target_poses_and_ring_optimisation".into(),
        seconds: t.elapsed().as_secs_f64(),
    });
    let mut reasons: Vec<Reason> = findings
        .iter()
        .map(|f| reason(f.code, f.message.clone(), f.camera.as_deref()))
        .collect();
    // The method returns no solution exactly when a finding stopped it.
    let Some(sol) = solution else {
        if reasons.is_empty() {
            reasons.push(reason(
                ReasonCode::CameraNotObserved,
                format!(
                    "the reference camera {} has no usable line observations",
                    ids[session.reference]
                ),
                Some(ids[session.reference]),
            ));
        }
        return Ok(failed(session, reasons, stages));
    };
    enter(progress, "extrinsics")?;
    let t = Instant::now();
    let tname = |t: usize| input.targets[t].id.clone();
    let mut extrinsics = Vec::new();
    let mut initialisation = Vec::new();
    let mut cams = Vec::new();
    let mut all = Vec::new();
    let mut per_camera = Vec::new();
    for c in &sol.cameras {
        let id = ids[c.camera];
        let (st, sr) = sigmas(&c.global.cov);
        let (cst, csr) = sigmas(&c.chainwise.cov);
        let (vst, vsr) = sigmas(&c.view.covariance);
        let is_ref = c.camera == session.reference;
        extrinsics.push(Extrinsic {
            value: ExtrinsicValue::of(id, &c.global.pose),
            sigma_translation_m: st.map(Some),
            sigma_rotation_deg: sr.map(Some),
            observable_dof: ObservableDof {
                rotation: 3,
                translation: 3,
            },
            covariance: (!is_ref)
                .then(|| std::array::from_fn(|a| std::array::from_fn(|b| c.global.cov[(a, b)]))),
        });
        initialisation.push(ExtrinsicValue::of(id, &c.chainwise.pose));
        let res: Vec<f64> = c.view.residuals.iter().map(|r| r.abs()).collect();
        all.extend(&res);
        per_camera.push(CameraStats {
            camera: id.to_string(),
            stats: Stats::of(&res),
        });
        cams.push(VanishingCamera {
            camera: id.to_string(),
            target: tname(c.target),
            chain: c.path.iter().map(|t| tname(*t)).collect(),
            chain_transforms: c.path.len().saturating_sub(1),
            chainwise: ExtrinsicValue::of(id, &c.chainwise.pose),
            chainwise_sigma_translation_m: cst,
            chainwise_sigma_rotation_deg: csr,
            target_pose_sigma_translation_m: vst,
            target_pose_sigma_rotation_deg: vsr,
            initialised_from: init_name(c.view.init),
            line_elevation_deg: c.view.elevation_deg,
            residuals: Stats::of(&res),
        });
    }
    let mut aux_all = Vec::new();
    let mut per_frame = Vec::new();
    let mut ring_views = Vec::new();
    for v in &sol.ring_views {
        let r = &input.ring[v.ring];
        let res: Vec<f64> = v.residuals.iter().map(|x| x.abs()).collect();
        aux_all.extend(&res);
        per_frame.push(FrameStats {
            frame: r.index,
            stats: Stats::of(&res),
        });
        ring_views.push(RingViewReport {
            index: r.index,
            targets: r.targets.map(tname),
            initialised_from: [init_name(v.poses[0].init), init_name(v.poses[1].init)],
            residuals: Stats::of(&res),
        });
    }
    all.extend(&aux_all);
    per_camera.push(CameraStats {
        camera: input.auxiliary.id.clone(),
        stats: Stats::of(&aux_all),
    });
    // Consistency: the ring must explain the auxiliary views about as well as each view
    // explained its own targets. A much larger σ means a pair transform or a view's pose
    // is wrong (a mislabelled target, a moved target), however converged the solver is.
    let view_sigmas: Vec<f64> = sol
        .ring_views
        .iter()
        .flat_map(|v| v.poses.iter().map(|p| p.sigma_px))
        .collect();
    let unprojected = sol
        .ring_views
        .iter()
        .flat_map(|v| &v.residuals)
        .filter(|r| !r.is_finite())
        .count();
    if let Some(vs) = rigcal_solve::loss::median(view_sigmas) {
        let bound = super::INCONSISTENT_SIGMA_RATIO * vs + super::INCONSISTENT_SIGMA_FLOOR_PX;
        if sol.sigma_px.is_nan() || sol.sigma_px > bound || unprojected > 0 {
            reasons.push(reason(
                ReasonCode::InconsistentRing,
                format!("the ring of targets explains the auxiliary views with σ {:.2} px against {vs:.2} px for the views alone{}: a pair transform or a target pose is wrong (a target moved between images, or a view names the wrong targets)", sol.sigma_px, if unprojected > 0 { format!(", and {unprojected} line points fall behind a camera") } else { String::new() }),
                None,
            ));
        }
    }
    let closed = sol.closure.is_some();
    if !closed {
        reasons.push(reason(ReasonCode::RingOpen, "no auxiliary view closes the ring: the chainwise result is final and its error grows along the chain; photograph the last pair too to close it", None));
    }
    let residuals = Residuals {
        all: Stats::of(&all),
        inliers: all.len(),
        outliers: 0,
        sigma_px: sol.sigma_px,
        per_camera,
        per_frame,
        histogram: Histogram::of(&all, 20),
        outlier_list: vec![],
    };
    // An open ring is accepted (the contract) but says so (a note); an
    // inconsistent ring fails; any other finding degrades.
    let status = status_of(&reasons, false);
    stages.push(Stage {
        name: "extrinsics".into(),
        seconds: t.elapsed().as_secs_f64(),
    });
    Ok(ResultDocument {
        rigcal_version: env!("CARGO_PKG_VERSION").into(),
        method: "vanishing".into(),
        status,
        reasons,
        reference_camera: ids[session.reference].to_string(),
        extrinsics,
        residuals: Some(residuals),
        singularity: None,
        vanishing: Some(VanishingReport {
            reference_target: tname(sol.reference_target),
            ring_closed: closed,
            closure_error: sol.closure.map(|((i, j), t, r)| ClosureError {
                pair: [tname(i), tname(j)],
                translation_m: t,
                rotation_deg: r.to_degrees(),
            }),
            pairs: sol
                .pairs
                .iter()
                .map(|((i, j), n)| PairReport {
                    targets: [tname(*i), tname(*j)],
                    views: *n,
                })
                .collect(),
            cameras: cams,
            ring_views,
            labelling: sol
                .labelling
                .iter()
                .map(|(ri, c)| LabellingReport {
                    ring_index: session.manifest.ring[*ri].index,
                    target: tname(c.target),
                    rotation_deg: c.degrees,
                    criterion: c.criterion.name().into(),
                    margin: c.margin.is_finite().then_some(c.margin),
                    clear: c.clear,
                })
                .collect(),
        }),
        initialisation,
        solver: Some(SolverReport {
            iterations: sol.summary.iterations,
            initial_cost: sol.summary.initial_cost,
            final_cost: sol.summary.final_cost,
            converged: sol.summary.converged,
            termination: sol.summary.termination.clone(),
        }),
        stages,
        trajectory: vec![],
        detection: None,
    })
}
