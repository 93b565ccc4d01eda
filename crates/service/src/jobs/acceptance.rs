//! Pass/fail of a finished job against its tenant's acceptance thresholds — the mark the
//! dashboard shows beside every job. Computed when read, not when the job ends, so a
//! tenant that tightens its thresholds sees old jobs judged by the new ones.

use super::queue::{JobRow, JobStatus};
use crate::store::Tenant;
use rigcal_core::result::{ExtrinsicValue, ResultDocument};
use rigcal_core::vehicle::{AcceptanceThresholds, Deviation, VehicleModel};
use serde::Serialize;

/// What the jobs table keeps of a result document to judge it without reading it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ResultSummary {
    pub residual_rms_px: Option<f64>,
    /// Largest 1-σ over every camera's observable translation components (m).
    pub worst_sigma_translation_m: Option<f64>,
    /// Largest 1-σ over every camera's observable rotation components (deg).
    pub worst_sigma_rotation_deg: Option<f64>,
    /// The extrinsics, for the nominal-rig verdict and the fleet statistics.
    pub extrinsics: Vec<ExtrinsicValue>,
}

impl ResultSummary {
    /// The `extrinsics` column: `None` when the result has none.
    pub fn extrinsics_json(&self) -> Option<String> {
        (!self.extrinsics.is_empty())
            .then(|| serde_json::to_string(&self.extrinsics).ok())
            .flatten()
    }

    pub fn of(doc: &ResultDocument) -> Self {
        let worst = |f: &dyn Fn(&rigcal_core::result::Extrinsic) -> [Option<f64>; 3]| {
            doc.extrinsics
                .iter()
                .flat_map(|e| f(e).into_iter().flatten())
                .fold(None, |m: Option<f64>, s| Some(m.map_or(s, |m| m.max(s))))
        };
        ResultSummary {
            residual_rms_px: doc.residuals.as_ref().map(|r| r.all.rms),
            worst_sigma_translation_m: worst(&|e| e.sigma_translation_m),
            worst_sigma_rotation_deg: worst(&|e| e.sigma_rotation_deg),
            extrinsics: doc.extrinsics.iter().map(|e| e.value.clone()).collect(),
        }
    }
}

/// The verdict: `pass` is `None` while the job has not ended.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Acceptance {
    pub pass: Option<bool>,
    /// Why it failed, one sentence per broken threshold or tolerance (empty when it
    /// passed).
    pub reasons: Vec<String>,
    /// Whose thresholds judged it: `tenant` or `vehicle_model`.
    pub thresholds_from: &'static str,
    /// With a vehicle model: every camera's deviation from the nominal rig.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub nominal: Option<NominalReport>,
}

/// The job's cameras against its vehicle model's nominal rig.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct NominalReport {
    pub vehicle_model: String,
    /// `None` while there are no extrinsics to compare (unfinished, or no result).
    pub within_tolerance: Option<bool>,
    pub cameras: Vec<Deviation>,
}

/// The job's extrinsics from its `extrinsics` column (empty when it has none). The
/// column is written from a result document by this build; text that does not parse is
/// a corrupt store and is judged as no extrinsics, with the reason saying so.
fn extrinsics_of(job: &JobRow) -> Result<Vec<ExtrinsicValue>, String> {
    match &job.extrinsics {
        None => Ok(vec![]),
        Some(t) => serde_json::from_str(t)
            .map_err(|e| format!("internal: the stored extrinsics of the job do not parse ({e})")),
    }
}

/// Judge `job` by `model`'s thresholds when it has them, else the tenant's, and by the
/// model's tolerances. `job.vehicle_model` names the model; `model` is it as stored now
/// (`None`: not defined).
pub fn judge(job: &JobRow, tenant: &Tenant, model: Option<&VehicleModel>) -> Acceptance {
    let own = model.and_then(|m| m.acceptance_thresholds);
    let thresholds_from = if own.is_some() {
        "vehicle_model"
    } else {
        "tenant"
    };
    let t = own.unwrap_or(AcceptanceThresholds {
        max_rms_px: tenant.max_rms_px,
        max_sigma_translation_m: tenant.max_sigma_translation_m,
        max_sigma_rotation_deg: tenant.max_sigma_rotation_deg,
    });
    let mut reasons = Vec::new();
    let nominal = job.vehicle_model.as_ref().map(|name| {
        let mut report = NominalReport {
            vehicle_model: name.clone(),
            within_tolerance: None,
            cameras: vec![],
        };
        match (model, extrinsics_of(job)) {
            (None, _) => reasons.push(format!("vehicle model {name} is not defined")),
            (Some(_), Err(why)) => reasons.push(why),
            (Some(_), Ok(ex)) if ex.is_empty() => {}
            (Some(m), Ok(ex)) => match m.deviations(&ex) {
                Err(why) => reasons.push(why),
                Ok(cameras) => {
                    report.cameras = cameras;
                    report.within_tolerance =
                        Some(report.cameras.iter().all(|d| d.within_tolerance));
                    reasons.extend(
                        report
                            .cameras
                            .iter()
                            .flat_map(|d| d.exceeded.iter().cloned()),
                    );
                }
            },
        }
        report
    });
    if !job.is_terminal() {
        return Acceptance {
            pass: None,
            reasons: vec![],
            thresholds_from,
            nominal,
        };
    }
    if job.status != JobStatus::Succeeded {
        reasons.insert(0, format!("the job ended {}", job.status));
    }
    let mut check = |name: &str, value: Option<f64>, max: f64, unit: &str| match value {
        Some(v) if v <= max => {}
        Some(v) => reasons.push(format!("{name} {v:.4} {unit} exceeds {max} {unit}")),
        None if job.status == JobStatus::Succeeded => {
            reasons.push(format!("no {name} was computed"))
        }
        None => {}
    };
    check("residual RMS", job.residual_rms_px, t.max_rms_px, "px");
    check(
        "translation 1-σ",
        job.worst_sigma_translation_m,
        t.max_sigma_translation_m,
        "m",
    );
    check(
        "rotation 1-σ",
        job.worst_sigma_rotation_deg,
        t.max_sigma_rotation_deg,
        "deg",
    );
    Acceptance {
        pass: Some(reasons.is_empty()),
        reasons,
        thresholds_from,
        nominal,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job(status: &str, rms: Option<f64>, st: Option<f64>, sr: Option<f64>) -> JobRow {
        JobRow {
            id: "j".into(),
            tenant_id: "t".into(),
            session_id: "s".into(),
            vehicle_id: None,
            vehicle_model: None,
            method: "motion".into(),
            options: "{}".into(),
            status: JobStatus::parse(status).unwrap(),
            stage: None,
            progress: 1.0,
            attempts: 1,
            max_attempts: 3,
            error: None,
            lease_owner: None,
            residual_rms_px: rms,
            worst_sigma_translation_m: st,
            worst_sigma_rotation_deg: sr,
            extrinsics: None,
            created_at: 0,
            started_at: Some(0),
            finished_at: Some(1),
        }
    }

    fn tenant() -> Tenant {
        Tenant {
            id: "t".into(),
            name: "t".into(),
            max_rms_px: 1.0,
            max_sigma_translation_m: 0.005,
            max_sigma_rotation_deg: 0.1,
        }
    }

    #[test]
    fn within_every_threshold_passes() {
        let a = judge(
            &job("succeeded", Some(0.4), Some(0.001), Some(0.02)),
            &tenant(),
            None,
        );
        assert_eq!(a.pass, Some(true));
        assert!(a.reasons.is_empty());
    }

    #[test]
    fn each_broken_threshold_is_named() {
        let a = judge(
            &job("succeeded", Some(1.5), Some(0.01), Some(0.02)),
            &tenant(),
            None,
        );
        assert_eq!(a.pass, Some(false));
        assert_eq!(a.reasons.len(), 2, "{:?}", a.reasons);
        assert!(a.reasons[0].contains("residual RMS"));
        assert!(a.reasons[1].contains("translation"));
    }

    #[test]
    fn unfinished_has_no_verdict_and_degraded_fails() {
        let mut j = job("running", None, None, None);
        j.finished_at = None;
        assert_eq!(judge(&j, &tenant(), None).pass, None);
        let a = judge(
            &job("degraded", Some(0.3), Some(0.001), None),
            &tenant(),
            None,
        );
        assert_eq!(a.pass, Some(false));
        assert_eq!(a.reasons, vec!["the job ended degraded".to_string()]);
    }
}
