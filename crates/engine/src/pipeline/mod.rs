//! The stage runner of the motion method: session → result document.
//! trajectories → linear initialisation → rig bundle adjustment → diagnostics.
//! Never panics on input: every failure becomes a `failed` document with a reason.

use rigcal_calib::diagnostics::{axis_unobservable, lost_dof, observability, residual_report};
use rigcal_calib::handeye::{initialise, InitError};
use rigcal_calib::link::link_cameras_through_tags;
use rigcal_calib::motion::MotionClass;
use rigcal_calib::rig_ba::{refine, RigBaOptions};
use rigcal_calib::trajectory;
use rigcal_calib::verdict::{motion_findings, planar_recommendation};
use rigcal_core::geometry::so3;
use rigcal_core::result::*;
use rigcal_core::session::{undetected_images, Method, Session};
use rigcal_core::verdict::{status_of, ReasonCode};
use rigcal_solve::bundle::LmOptions;
use std::time::Instant;

pub mod detection;
pub use detection::{DirSource, ImageSource, NoImages};

mod vanishing;

/// The rig is inconsistent when its residual σ exceeds this multiple of the scenes' σ
/// plus the floor (px): at matching noise the two agree within a few percent.
pub const INCONSISTENT_SIGMA_RATIO: f64 = 1.5;
pub const INCONSISTENT_SIGMA_FLOOR_PX: f64 = 0.1;
/// More rejected observations than this share means the model, not the data, is wrong.
pub const MAX_OUTLIER_FRACTION: f64 = 0.15;

#[derive(Clone, Debug, Default)]
pub struct CalibOptions {
    pub rig_ba: RigBaOptions,
    /// Least corner noise (px) the reported uncertainty assumes, whatever the residuals
    /// say; at least [`detected_corner_sigma_floor_px`] for corners detected from images.
    pub corner_sigma_floor_px: f64,
    /// Relative scale error of each camera's corners about its principal point that the
    /// reported uncertainty allows for (0: none); [`DETECTED_CORNER_SCALE_SIGMA`] for
    /// corners detected from images.
    pub corner_scale_sigma: f64,
    /// The detection stage's quality (sessions of images).
    pub detection: DetectionQuality,
}

/// Corner noise (px) the uncertainty of a session detected from images assumes at least,
/// by detection quality. The residual σ of the rig adjustment sees each corner's
/// scatter, not an error a tag repeats in every frame (where a board barely moves in the
/// image, frames do not average it out), so a floor stands for that part.
///
/// `accurate`: on the realistic hall and fisheye renders the residual σ alone (~0.006
/// px) gives error/σ of RMS 0.7-1.0 per preset, but one axis in 180 of the hall at 3.4:
/// what the detector repeats by tag is now mostly within its scatter. 0.01 px keeps a
/// margin for that and for what renders do not show (print flatness, a lens model a
/// little off): error/σ RMS 0.5-0.6, at most 2.3, where 0.03 px made the σ 5-6× the
/// errors (docs/accuracy.md, "The corner-noise floor, after the fixes").
///
/// `fast`: tags over 30 px keep their edge-measured corners (0.010-0.012 px RMS on the
/// hall at 1024×576, residual σ 0.007-0.009 px); 0.015 px is the same ~2× margin:
/// error/σ RMS ~0.5, at most ~1.2 on the hall and the planar drive (0.24 / 0.59 and
/// 0.21 / 0.62 at the 0.03 px this floor was while those corners were 0.017-0.026 px).
pub fn detected_corner_sigma_floor_px(quality: DetectionQuality) -> f64 {
    match quality {
        DetectionQuality::Accurate => 0.01,
        DetectionQuality::Fast => 0.015,
    }
}

/// Relative scale error of a camera's detected corners about its principal point that
/// the uncertainty of a session detected from images allows for (see
/// `diagnostics::corner_scale_covariance`). The noise floor above stands for errors
/// that vary from corner to corner; a scale that all of a camera's corners share does
/// not average down over them, and on a hand-held fisheye pair (12 000 corners, σ of
/// 10⁻⁶ along the best determined direction) it was most of what made the reported
/// covariance optimistic (NEES 13-14 where 6 is honest). rigcal's detector reads the
/// corners of its own renders at −0.35 to −1.95 ppm of scale per camera (car-hall,
/// car-hall-planar, fisheye-handheld; docs/accuracy.md); 2 ppm covers what was seen.
pub const DETECTED_CORNER_SCALE_SIGMA: f64 = 2e-6;

/// The robust loss of the outlier pass by its user-facing name (CLI `--loss`, job
/// option `loss`); its scale is given beside it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LossKind {
    #[default]
    Huber,
    Cauchy,
    Squared,
}

impl std::str::FromStr for LossKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "huber" => Ok(Self::Huber),
            "cauchy" => Ok(Self::Cauchy),
            "squared" => Ok(Self::Squared),
            other => Err(format!("one of huber, cauchy, squared, got {other:?}")),
        }
    }
}

impl CalibOptions {
    /// Options from the robust loss and its scale in pixels (CLI flags, job options).
    /// Errors name the field.
    pub fn from_loss(
        loss: LossKind,
        loss_scale: f64,
    ) -> Result<Self, rigcal_core::session::InputError> {
        use rigcal_core::session::InputError;
        use rigcal_solve::Loss;
        if !(loss_scale.is_finite() && loss_scale > 0.0 && loss_scale <= 1000.0) {
            return Err(InputError::new(
                "loss_scale",
                format!("a positive number of pixels up to 1000, got {loss_scale}"),
            ));
        }
        let loss = match loss {
            LossKind::Huber => Loss::Huber { scale: loss_scale },
            LossKind::Cauchy => Loss::Cauchy { scale: loss_scale },
            LossKind::Squared => Loss::Squared,
        };
        let mut opts = Self::default();
        opts.rig_ba.loss = loss;
        Ok(opts)
    }
}

/// The rig poses of the bundle adjustment relative to the first one (frame ids, not
/// positions in the session).
fn rig_trajectory(session: &Session, ba: &rigcal_calib::rig_ba::RigBaOutput) -> Vec<RigPose> {
    let poses = &ba.problem.world_from_rig;
    let Some(first) = poses.first() else {
        return vec![];
    };
    let first_inv = first.inverse();
    ba.rig_frames
        .iter()
        .zip(poses)
        .map(|(f, p)| {
            let rel = first_inv * *p;
            RigPose {
                frame: session.frames[*f].index,
                translation: [rel.trans.x, rel.trans.y, rel.trans.z],
                quaternion_wxyz: so3::to_quaternion(&rel.rot),
            }
        })
        .collect()
}

pub(crate) fn reason(code: ReasonCode, message: impl Into<String>, camera: Option<&str>) -> Reason {
    Reason::new(code, message, camera)
}

pub(crate) fn failed(
    session: &Session,
    reasons: Vec<Reason>,
    stages: Vec<Stage>,
) -> ResultDocument {
    ResultDocument {
        rigcal_version: env!("CARGO_PKG_VERSION").into(),
        method: match session.manifest.method {
            Method::Motion => "motion",
            Method::Vanishing => "vanishing",
        }
        .into(),
        status: Status::Failed,
        reasons,
        reference_camera: session.cameras[session.reference].id.clone(),
        extrinsics: vec![],
        residuals: None,
        singularity: None,
        vanishing: None,
        initialisation: vec![],
        solver: None,
        stages,
        trajectory: vec![],
        detection: None,
    }
}

/// Where the stage runner reports progress and learns that it should stop. The service
/// records stages as job events and honours cancellation between stages; the CLI ignores both.
pub trait Progress {
    /// Called as `stage` starts, `fraction` of the whole job done. Returning `false`
    /// stops the run before that stage (cancellation).
    fn stage(&self, stage: &str, fraction: f64) -> bool;
}

/// Progress that is never looked at and never cancels.
pub struct Silent;

impl Progress for Silent {
    fn stage(&self, _: &str, _: f64) -> bool {
        true
    }
}

/// The run was cancelled between stages, at the named stage.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Cancelled(pub String);

/// Stage names and the fraction of a typical run done when each starts (motion method,
/// then the vanishing method's own stages).
pub const STAGES: [(&str, f64); 7] = [
    ("detection", 0.0),
    ("trajectories", 0.05),
    ("initialisation", 0.4),
    ("rig_bundle_adjustment", 0.5),
    ("diagnostics", 0.9),
    ("camera_target_poses", 0.05),
    ("extrinsics", 0.9),
];

pub(crate) fn enter(progress: &dyn Progress, stage: &str) -> Result<(), Cancelled> {
    let fraction = STAGES
        .iter()
        .find(|(s, _)| *s == stage)
        .map_or(0.0, |(_, f)| *f);
    if progress.stage(stage, fraction) {
        Ok(())
    } else {
        Err(Cancelled(stage.to_string()))
    }
}

/// Run a session end to end: detection on the images that need it (read from
/// `images`), then the calibration of its method. The result carries the detection
/// report.
pub fn run(
    session: &Session,
    images: &dyn ImageSource,
    opts: &CalibOptions,
    progress: &dyn Progress,
) -> Result<ResultDocument, Cancelled> {
    let (detected, report) = match detection::detect_session(
        session,
        images,
        opts.detection,
        progress,
    ) {
        Ok(d) => d,
        Err(detection::DetectionFailure::Cancelled(c)) => return Err(c),
        Err(detection::DetectionFailure::Inconsistent {
            field,
            expected,
            report,
        }) => {
            let mut doc = failed(
                session,
                vec![reason(
                    ReasonCode::InternalError,
                    format!(
                        "internal error in the detection stage: its detections do not make a valid session ({field}: expected {expected}); this is a bug of rigcal, not of the capture"
                    ),
                    None,
                )],
                vec![Stage {
                    name: "detection".into(),
                    seconds: report.seconds,
                }],
            );
            doc.detection = Some(report);
            return Ok(doc);
        }
        Err(detection::DetectionFailure::InputMissing { images, report }) => {
            let n = images.len();
            let (field, why) = &images[0];
            let mut doc = failed(
                session,
                vec![reason(
                    ReasonCode::InputMissing,
                    format!(
                        "{n} image(s) of the session could not be read ({field}: {why}{}); the capture was not judged",
                        if n > 1 { "; ..." } else { "" }
                    ),
                    None,
                )],
                vec![Stage {
                    name: "detection".into(),
                    seconds: report.seconds,
                }],
            );
            doc.detection = Some(report);
            return Ok(doc);
        }
    };
    calibrate_detected(&detected, report, opts, progress)
}

/// The calibration of a session the detection stage has filled in (`report`: what it
/// found, `None` when nothing needed detecting): [`calibrate_with`] with the corner-noise
/// floor of detected corners, and the report in the document.
pub fn calibrate_detected(
    detected: &Session,
    report: Option<DetectionReport>,
    opts: &CalibOptions,
    progress: &dyn Progress,
) -> Result<ResultDocument, Cancelled> {
    let detected_corners = report.as_ref().is_some_and(|r| r.points_total > 0);
    let opts = &CalibOptions {
        corner_sigma_floor_px: if detected_corners {
            opts.corner_sigma_floor_px
                .max(detected_corner_sigma_floor_px(opts.detection))
        } else {
            opts.corner_sigma_floor_px
        },
        corner_scale_sigma: if detected_corners {
            opts.corner_scale_sigma.max(DETECTED_CORNER_SCALE_SIGMA)
        } else {
            opts.corner_scale_sigma
        },
        ..opts.clone()
    };
    let mut doc = calibrate_with(detected, opts, progress)?;
    if let Some(r) = &report {
        name_skipped_images(&mut doc.reasons, r);
        doc.stages.insert(
            0,
            Stage {
                name: "detection".into(),
                seconds: r.seconds,
            },
        );
    }
    doc.detection = report;
    Ok(doc)
}

/// A camera short of observations because images of it were skipped says which and
/// why: the images' own error (a size other than the camera's, bytes that are no image)
/// is what the operator must fix, where the reason alone reads as a capture that missed
/// the targets.
fn name_skipped_images(reasons: &mut [Reason], report: &DetectionReport) {
    const COVERAGE: [ReasonCode; 3] = [
        ReasonCode::CameraNotObserved,
        ReasonCode::TooFewMotions,
        ReasonCode::LinesUnusable,
    ];
    for r in reasons {
        let Some(camera) = r.camera.as_deref() else {
            continue;
        };
        if !COVERAGE.iter().any(|c| c.as_str() == r.code) {
            continue;
        }
        let images: Vec<&ImageReport> = report
            .images
            .iter()
            .filter(|i| i.camera == camera)
            .collect();
        let skipped: Vec<&ImageReport> = images
            .iter()
            .copied()
            .filter(|i| i.error.is_some())
            .collect();
        if let Some(first) = skipped.first() {
            r.message.push_str(&format!(
                "; {} of its {} images were skipped ({}: {}{})",
                skipped.len(),
                images.len(),
                first.field,
                first.error.as_deref().unwrap_or_default(),
                if skipped.len() > 1 { "; ..." } else { "" }
            ));
        }
    }
}

/// Run the motion method on a validated session.
pub fn calibrate(session: &Session, opts: &CalibOptions) -> ResultDocument {
    match calibrate_with(session, opts, &Silent) {
        Ok(doc) => doc,
        Err(Cancelled(stage)) => failed(
            session,
            vec![reason(
                ReasonCode::Cancelled,
                format!("cancelled before {stage}"),
                None,
            )],
            vec![],
        ),
    }
}

/// Run the motion method, reporting each stage to `progress` (which may cancel).
pub fn calibrate_with(
    session: &Session,
    opts: &CalibOptions,
    progress: &dyn Progress,
) -> Result<ResultDocument, Cancelled> {
    let mut stages = Vec::new();
    enter(progress, "detection")?;
    let undetected = undetected_images(session);
    if !undetected.is_empty() {
        let n = undetected.len();
        return Ok(failed(
            session,
            vec![reason(
                ReasonCode::DetectionUnavailable,
                format!(
                    "{n} image(s) have no detections ({}{}); this build detects AprilTag and AprilGrid targets only (line targets and `points` targets need detections in the session)",
                    undetected[0],
                    if n > 1 { ", ..." } else { "" }
                ),
                None,
            )],
            stages,
        ));
    }
    let ids: Vec<&str> = session.cameras.iter().map(|c| c.id.as_str()).collect();
    if session.cameras.len() < 2 {
        return Ok(failed(
            session,
            vec![reason(
                ReasonCode::TooFewCameras,
                "a rig calibration needs at least 2 cameras",
                None,
            )],
            stages,
        ));
    }
    if session.manifest.method == Method::Vanishing {
        return vanishing::calibrate(session, opts, progress);
    }
    // Input sufficiency per camera, named.
    let mut reasons = Vec::new();
    for (c, id) in ids.iter().enumerate() {
        let frames = session
            .frames
            .iter()
            .filter(|f| f.observations[c].len() >= 4)
            .count();
        if frames == 0 {
            reasons.push(reason(
                ReasonCode::CameraNotObserved,
                format!("camera {id} observes no target or point in any frame"),
                Some(id),
            ));
        } else if frames < 3 {
            reasons.push(reason(
                ReasonCode::TooFewMotions,
                format!("camera {id} observes points in {frames} frame(s); at least 3 are needed"),
                Some(id),
            ));
        }
    }
    if !reasons.is_empty() {
        return Ok(failed(session, reasons, stages));
    }

    enter(progress, "trajectories")?;
    let t = Instant::now();
    let lm = LmOptions {
        loss: opts.rig_ba.loss,
        max_iterations: opts.rig_ba.max_iterations,
        ..LmOptions::default()
    };
    let traj = match trajectory::estimate(session, &lm) {
        Ok(t) => t,
        Err(e) => {
            return Ok(failed(
                session,
                vec![reason(ReasonCode::DetectionFailed, e.to_string(), None)],
                stages,
            ))
        }
    };
    stages.push(Stage {
        name: "trajectories".into(),
        seconds: t.elapsed().as_secs_f64(),
    });
    for (_, why) in &traj.failed_scenes {
        reasons.push(reason(ReasonCode::SceneNotReconstructed, why.clone(), None));
    }
    for scene in &traj.scenes {
        // The split-off rest of a measured scene takes its scale from the rig (solved
        // in the initialisation with the rest); only a scene no distance was ever
        // measured in lacks one.
        if !scene.poses.is_empty() && !scene.scale.is_metric() && scene.part_of.is_none() {
            reasons.push(reason(ReasonCode::ScaleMissing, "a scene of unknown geometry has no measured distance (scale[]): its scale comes from the rig motion only", None));
            break;
        }
    }

    enter(progress, "initialisation")?;
    let t = Instant::now();
    let mut init = match initialise(session, &traj) {
        Ok(i) => i,
        Err(e) => {
            let cam = match &e {
                InitError::CameraNotObserved(c) | InitError::ReferenceNotObserved(c) => c.clone(),
            };
            reasons.push(reason(
                ReasonCode::CameraNotObserved,
                e.to_string(),
                Some(&cam),
            ));
            return Ok(failed(session, reasons, stages));
        }
    };
    // Under planar motion, cameras that share no scene have unobservable relative
    // heights; tags both see but no scene could place (two planar poses fit) may link
    // them once the rig's rotations are known. Under general motion the motions
    // determine every extrinsic, and such a link would add little and risk much.
    let mut traj = traj;
    if init.motion.class == MotionClass::Planar {
        if let Some(linked) = link_cameras_through_tags(session, &traj, &init) {
            // The same cameras and frames are posed as before, only linked further: an
            // initialisation that succeeded cannot fail on them.
            match initialise(session, &linked) {
                Ok(i) => init = i,
                Err(e) => {
                    reasons.push(reason(
                        ReasonCode::InternalError,
                        format!("internal error in the initialisation: it failed once tags linked the cameras ({e}), although it succeeded before; this is a bug of rigcal, not of the capture"),
                        None,
                    ));
                    return Ok(failed(session, reasons, stages));
                }
            }
            traj = linked;
        }
    }
    stages.push(Stage {
        name: "initialisation".into(),
        seconds: t.elapsed().as_secs_f64(),
    });
    let initialisation: Vec<ExtrinsicValue> = ids
        .iter()
        .zip(&init.ref_from_cam)
        .map(|(id, p)| ExtrinsicValue::of(id, p))
        .collect();

    enter(progress, "rig_bundle_adjustment")?;
    let t = Instant::now();
    let ba = refine(session, &traj, &init, &opts.rig_ba);
    stages.push(Stage {
        name: "rig_bundle_adjustment".into(),
        seconds: t.elapsed().as_secs_f64(),
    });

    enter(progress, "diagnostics")?;
    let t = Instant::now();
    let obs = observability(&ba, opts.corner_sigma_floor_px, opts.corner_scale_sigma);
    let residuals = residual_report(session, &ba);
    let mut extrinsics = Vec::new();
    let mut per_camera = Vec::new();
    for (c, id) in ids.iter().enumerate() {
        let value = ExtrinsicValue::of(id, &ba.problem.rig_from_cam[c]);
        let slot = obs
            .as_ref()
            .and_then(|o| o.cams.iter().position(|x| *x == c));
        let covariance = match (&obs, slot) {
            (Some(o), Some(i)) => Some(std::array::from_fn(|a| {
                std::array::from_fn(|b| o.cov[i].1[(a, b)])
            })),
            _ => None,
        };
        let (sig_t, sig_r, dof, eig) = match (&obs, slot) {
            (Some(o), Some(i)) => {
                let cov = &o.cov[i].1;
                let st = [0, 1, 2].map(|a| {
                    (!axis_unobservable(&o.null, 6 * i, a)).then(|| cov[(a, a)].max(0.0).sqrt())
                });
                let sr = [0, 1, 2].map(|a| {
                    (!axis_unobservable(&o.null, 6 * i + 3, a))
                        .then(|| cov[(a + 3, a + 3)].max(0.0).sqrt().to_degrees())
                });
                let dof = ObservableDof {
                    translation: 3 - lost_dof(&o.null, 6 * i),
                    rotation: 3 - lost_dof(&o.null, 6 * i + 3),
                };
                (st, sr, dof, o.per_camera_eigen[i].clone())
            }
            // The reference camera defines the frame: exact by definition.
            _ if c == session.reference => (
                [Some(0.0); 3],
                [Some(0.0); 3],
                ObservableDof {
                    rotation: 3,
                    translation: 3,
                },
                vec![],
            ),
            _ => (
                [None; 3],
                [None; 3],
                ObservableDof {
                    rotation: 0,
                    translation: 0,
                },
                vec![],
            ),
        };
        per_camera.push(CameraObservability {
            camera: id.to_string(),
            observable_dof: dof.clone(),
            information_eigenvalues: eig,
        });
        extrinsics.push(Extrinsic {
            value,
            sigma_translation_m: sig_t,
            sigma_rotation_deg: sig_r,
            observable_dof: dof,
            covariance,
        });
    }

    let mut unobservable_directions = Vec::new();
    if let Some(o) = &obs {
        for (k, (v, s)) in o.null.iter().enumerate() {
            let components: Vec<DirectionComponent> = o
                .cams
                .iter()
                .enumerate()
                .filter(|(i, _)| (0..6).any(|k| v[6 * i + k].abs() > 1e-3))
                .map(|(i, c)| DirectionComponent {
                    camera: ids[*c].to_string(),
                    translation: [v[6 * i], v[6 * i + 1], v[6 * i + 2]],
                    rotation: [v[6 * i + 3], v[6 * i + 4], v[6 * i + 5]],
                })
                .collect();
            let names: Vec<&str> = components
                .iter()
                .filter(|c| {
                    c.translation
                        .iter()
                        .chain(&c.rotation)
                        .any(|x| x.abs() > 0.1)
                })
                .map(|c| c.camera.as_str())
                .collect();
            let trans = components
                .iter()
                .map(|c| c.translation.iter().map(|x| x * x).sum::<f64>())
                .sum::<f64>();
            let kind = if trans > 0.5 {
                "translation"
            } else {
                "rotation"
            };
            let description = if k < o.held {
                let plural = names.len() > 1;
                format!(
                    "the {}height of {} {} relative to {} along the motion-plane normal: planar motion without a shared scene leaves it unobservable, so it is held at the prior or 0",
                    if plural { "common " } else { "" },
                    if plural { "cameras" } else { "camera" },
                    names.join(", "),
                    ids[session.reference]
                )
            } else if names.len() > 1 {
                format!("a {kind} shared by cameras {} relative to {}: they can move together without changing any observation", names.join(", "), ids[session.reference])
            } else {
                format!(
                    "a {kind} of camera {} relative to {} that no observation constrains",
                    names.join(", "),
                    ids[session.reference]
                )
            };
            // A slide the adjustment left wherever its steps ended, set back to the
            // value the held heights take: say so, it is a convention, not a measurement.
            let recentred = ba.recentred_directions.iter().any(|r| r.dot(v).abs() > 0.9);
            let description = if recentred {
                format!("{description}; it is set to the prior or 0, as the held heights are")
            } else {
                description
            };
            unobservable_directions.push(UnobservableDirection {
                components,
                sigma: *s,
                description,
            });
        }
    }

    // Verdict and recommendations.
    let class = init.motion.class;
    let any_null = !unobservable_directions.is_empty();
    let mut recommendations = Vec::new();
    let mut resolved_by = Vec::new();
    if init.permutation {
        resolved_by.push("scene_permutation".to_string());
    }
    let found = motion_findings(&init.motion);
    reasons.extend(found.reasons);
    recommendations.extend(found.recommendations);
    if any_null {
        let cams: Vec<String> = unobservable_directions
            .iter()
            .flat_map(|d| d.components.iter().map(|c| c.camera.clone()))
            .collect::<std::collections::BTreeSet<_>>()
            .into_iter()
            .collect();
        if class == MotionClass::Planar {
            reasons.push(reason(ReasonCode::PlanarMotion, format!("planar motion: the height of {} relative to {} along the plane normal is not observable", cams.join(", "), ids[session.reference]), None));
            let src = init.height_source.unwrap_or("zero");
            let has_prior = cams.iter().any(|c| {
                session
                    .camera_index(c)
                    .is_some_and(|i| session.height_priors[i].is_some())
            });
            resolved_by.push(if has_prior || src == "prior" {
                "prior".into()
            } else {
                "none".into()
            });
            recommendations.push(planar_recommendation(&cams.join(", ")));
            if !has_prior {
                recommendations.push(format!("Or give priors.height_offsets for {} (measured on the vehicle); until then the height is held at the linear initialisation (0).", cams.join(", ")));
            }
        } else if !matches!(
            class,
            MotionClass::PureTranslation | MotionClass::SingleAxis | MotionClass::None
        ) {
            reasons.push(reason(
                ReasonCode::PoorlyDetermined,
                format!(
                    "some extrinsic directions of {} are not determined by the data",
                    cams.join(", ")
                ),
                None,
            ));
            recommendations
                .push("Capture more varied motion: larger rotations about different axes.".into());
        }
    }
    if !ba.summary.converged {
        reasons.push(reason(
            ReasonCode::NoConvergence,
            format!(
                "the rig bundle adjustment stopped: {}",
                ba.summary.termination
            ),
            None,
        ));
    }
    // Consistency: the rigid rig must explain the observations about as well as the
    // independent scene reconstructions did. A much larger residual, or a large share of
    // rejected observations, means a scene or an extrinsic is wrong (a folded
    // reconstruction), however converged the solver is.
    if let Some(ss) = traj.median_scene_sigma() {
        if ba.sigma_px > INCONSISTENT_SIGMA_RATIO * ss + INCONSISTENT_SIGMA_FLOOR_PX {
            reasons.push(reason(
                ReasonCode::InconsistentRig,
                format!("the rigid rig explains the observations with σ {:.2} px against {:.2} px for the scenes alone: a scene reconstruction or an extrinsic is wrong", ba.sigma_px, ss),
                None,
            ));
        }
    }
    let total_obs = ba.keys.len() + ba.outliers.len();
    if total_obs > 0 && ba.outliers.len() as f64 > MAX_OUTLIER_FRACTION * total_obs as f64 {
        reasons.push(reason(
            ReasonCode::TooManyOutliers,
            format!(
                "{} of {} observations ({:.0} %) were rejected as outliers",
                ba.outliers.len(),
                total_obs,
                100.0 * ba.outliers.len() as f64 / total_obs as f64
            ),
            None,
        ));
    }
    if !ba.outliers.is_empty() {
        reasons.push(reason(
            ReasonCode::OutliersRemoved,
            format!("{} observations rejected as outliers", ba.outliers.len()),
            None,
        ));
    }
    let status = status_of(&reasons, any_null);
    stages.push(Stage {
        name: "diagnostics".into(),
        seconds: t.elapsed().as_secs_f64(),
    });

    let m = &init.motion;
    Ok(ResultDocument {
        rigcal_version: env!("CARGO_PKG_VERSION").into(),
        method: "motion".into(),
        status,
        reasons,
        reference_camera: ids[session.reference].to_string(),
        extrinsics,
        residuals: Some(residuals),
        singularity: Some(Singularity {
            motion_class: class.as_str().into(),
            axis: m.axis,
            motions: m.motions,
            informative_motions: m.informative_motions,
            max_rotation_deg: m.max_rotation_deg,
            max_out_of_axis_deg: m.max_out_of_axis_deg,
            scene_permutation: init.permutation,
            motion_pairs_used: init.pairs_used,
            motion_pairs_dropped_small_rotation: init.pairs_dropped_small,
            motion_pairs_dropped_near_180: init.pairs_dropped_near_180,
            per_camera,
            unobservable_directions,
            resolved_by,
            recommendations,
        }),
        vanishing: None,
        initialisation,
        solver: Some(SolverReport {
            iterations: ba.summary.iterations,
            initial_cost: ba.summary.initial_cost,
            final_cost: ba.summary.final_cost,
            converged: ba.summary.converged,
            termination: ba.summary.termination.clone(),
        }),
        stages,
        trajectory: rig_trajectory(session, &ba),
        detection: None,
    })
}
