//! Fleet statistics of one vehicle model: the distribution of its vehicles' accepted
//! calibrations, the vehicles whose latest calibration is an outlier, and drift over time.
//!
//! Every number is a camera's deviation from the model's nominal rig (translation mm,
//! rotation vector deg, reference axes: `rigcal_core::vehicle::Deviation`), not the raw
//! extrinsic: deviations are small and wrap-free, and their median is the fleet's
//! systematic offset from CAD. The spread is the MAD × 1.4826 (the standard deviation of a
//! normal sample, unmoved by the outliers it must find) and a vehicle's robust z-score on
//! an axis is its distance from the fleet median in spreads. A vehicle is an outlier when
//! any axis of any camera exceeds the model's `fleet_outlier_z` (default 5: with 6 axes
//! for each of 3 cameras, a normal fleet exceeds 3.5 somewhere on ~0.8 % of vehicles by
//! chance, 5 on one in 10⁵).

use crate::store::vehicle_models::FleetJob;
use rigcal_core::result::ExtrinsicValue;
use rigcal_core::vehicle::VehicleModel;
use serde::Serialize;
use std::collections::BTreeMap;

/// The six axes of a deviation, with their units.
pub const AXES: [(&str, &str); 6] = [
    ("tx", "mm"),
    ("ty", "mm"),
    ("tz", "mm"),
    ("rx", "deg"),
    ("ry", "deg"),
    ("rz", "deg"),
];

/// The smallest spread a z-score divides by (mm for translations, deg for rotations):
/// below any calibration's precision, so a fleet of identical calibrations does not turn
/// rounding into outliers.
const SPREAD_FLOOR: [f64; 2] = [1e-3, 1e-5];

/// Robust location and spread of one axis over the fleet's latest calibrations.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct AxisStats {
    pub axis: &'static str,
    pub unit: &'static str,
    pub median: f64,
    /// 1.4826 × the median absolute deviation.
    pub spread: f64,
    pub count: usize,
}

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct CameraStats {
    pub camera: String,
    pub axes: Vec<AxisStats>,
}

/// One axis of an outlier vehicle beyond the threshold.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct OutlierAxis {
    pub camera: String,
    pub axis: &'static str,
    pub unit: &'static str,
    pub value: f64,
    pub z: f64,
}

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Outlier {
    pub vehicle_id: String,
    pub job_id: String,
    pub finished_at: i64,
    /// The largest |z| over its cameras and axes.
    pub max_abs_z: f64,
    pub axes: Vec<OutlierAxis>,
}

/// The median of one axis over the accepted calibrations finished in one period.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct DriftPoint {
    pub from: i64,
    pub median: f64,
    pub count: usize,
}

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct DriftSeries {
    pub camera: String,
    pub axis: &'static str,
    pub unit: &'static str,
    pub points: Vec<DriftPoint>,
}

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct FleetStats {
    /// Vehicles with an accepted calibration (their latest is what the statistics use).
    pub vehicles: usize,
    /// Accepted calibrations, all of them (drift uses every one).
    pub calibrations: usize,
    pub outlier_z: f64,
    pub cameras: Vec<CameraStats>,
    /// Worst first.
    pub outliers: Vec<Outlier>,
    /// Length of a drift period (ms).
    pub bucket_ms: i64,
    pub drift: Vec<DriftSeries>,
    /// Per camera (model order) and axis, every vehicle's latest value with whether it
    /// is an outlier there: what the fleet figure draws (not in the JSON answer).
    #[serde(skip)]
    pub latest: Vec<[Vec<(f64, bool)>; 6]>,
}

fn median(xs: &mut [f64]) -> f64 {
    if xs.is_empty() {
        return f64::NAN;
    }
    xs.sort_by(f64::total_cmp);
    let n = xs.len();
    if n % 2 == 1 {
        xs[n / 2]
    } else {
        0.5 * (xs[n / 2 - 1] + xs[n / 2])
    }
}

/// One calibration as six numbers per camera (in the model's camera order, reference
/// excluded); `None` where the camera has no extrinsic.
type Row = Vec<Option<[f64; 6]>>;

fn row(model: &VehicleModel, extrinsics: &[ExtrinsicValue]) -> Result<Row, String> {
    Ok(model
        .deviations(extrinsics)?
        .iter()
        .map(|d| match (d.translation_mm, d.rotation_deg) {
            (Some(t), Some(r)) => Some([t[0], t[1], t[2], r[0], r[1], r[2]]),
            _ => None,
        })
        .collect())
}

/// The statistics of `jobs` (accepted calibrations of `model`'s vehicles, oldest first).
/// A job whose extrinsics column does not parse is a corrupt store: `Err` names it.
pub fn stats(
    model: &VehicleModel,
    jobs: &[FleetJob],
    outlier_z: f64,
    bucket_ms: i64,
) -> Result<FleetStats, String> {
    let cameras: Vec<String> = model
        .cameras
        .iter()
        .filter(|c| c.id != model.reference_camera)
        .map(|c| c.id.clone())
        .collect();
    let mut rows = Vec::with_capacity(jobs.len());
    for j in jobs {
        let ex: Vec<ExtrinsicValue> = serde_json::from_str(&j.extrinsics).map_err(|e| {
            format!(
                "the stored extrinsics of job {} do not parse: {e}",
                j.job_id
            )
        })?;
        rows.push(row(model, &ex)?);
    }
    // Latest per vehicle (jobs are oldest first, so the last one wins).
    let mut latest: BTreeMap<&str, usize> = BTreeMap::new();
    for (k, j) in jobs.iter().enumerate() {
        latest.insert(&j.vehicle_id, k);
    }
    let column = |idx: &mut dyn Iterator<Item = usize>, c: usize, a: usize| -> Vec<f64> {
        idx.filter_map(|k| rows[k].get(c).copied().flatten().map(|v| v[a]))
            .collect()
    };
    let mut camera_stats = Vec::new();
    let mut centre = vec![[(0.0, 1.0); 6]; cameras.len()];
    for (c, id) in cameras.iter().enumerate() {
        let mut axes = Vec::new();
        for (a, (axis, unit)) in AXES.iter().enumerate() {
            let mut xs = column(&mut latest.values().copied(), c, a);
            let m = median(&mut xs);
            let mut dev: Vec<f64> = xs.iter().map(|x| (x - m).abs()).collect();
            let spread = 1.4826 * median(&mut dev);
            let floor = SPREAD_FLOOR[a / 3];
            centre[c][a] = (
                m,
                if spread.is_finite() {
                    spread.max(floor)
                } else {
                    floor
                },
            );
            axes.push(AxisStats {
                axis,
                unit,
                median: m,
                spread,
                count: xs.len(),
            });
        }
        camera_stats.push(CameraStats {
            camera: id.clone(),
            axes,
        });
    }
    let mut values: Vec<[Vec<(f64, bool)>; 6]> = vec![Default::default(); cameras.len()];
    let mut outliers = Vec::new();
    for &k in latest.values() {
        let mut axes = Vec::new();
        let mut max_abs_z: f64 = 0.0;
        for (c, id) in cameras.iter().enumerate() {
            let Some(v) = rows[k].get(c).copied().flatten() else {
                continue;
            };
            for (a, (axis, unit)) in AXES.iter().enumerate() {
                let (m, s) = centre[c][a];
                let z = (v[a] - m) / s;
                max_abs_z = max_abs_z.max(z.abs());
                values[c][a].push((v[a], z.abs() > outlier_z));
                if z.abs() > outlier_z {
                    axes.push(OutlierAxis {
                        camera: id.clone(),
                        axis,
                        unit,
                        value: v[a],
                        z,
                    });
                }
            }
        }
        if !axes.is_empty() {
            outliers.push(Outlier {
                vehicle_id: jobs[k].vehicle_id.clone(),
                job_id: jobs[k].job_id.clone(),
                finished_at: jobs[k].finished_at,
                max_abs_z,
                axes,
            });
        }
    }
    outliers.sort_by(|a, b| b.max_abs_z.total_cmp(&a.max_abs_z));
    // Drift: every accepted calibration in the period it finished in.
    let mut periods: BTreeMap<i64, Vec<usize>> = BTreeMap::new();
    for (k, j) in jobs.iter().enumerate() {
        periods
            .entry(j.finished_at.div_euclid(bucket_ms) * bucket_ms)
            .or_default()
            .push(k);
    }
    let mut drift = Vec::new();
    for (c, id) in cameras.iter().enumerate() {
        for (a, (axis, unit)) in AXES.iter().enumerate() {
            let points = periods
                .iter()
                .filter_map(|(&from, ks)| {
                    let mut xs = column(&mut ks.iter().copied(), c, a);
                    (!xs.is_empty()).then(|| DriftPoint {
                        from,
                        count: xs.len(),
                        median: median(&mut xs),
                    })
                })
                .collect();
            drift.push(DriftSeries {
                camera: id.clone(),
                axis,
                unit,
                points,
            });
        }
    }
    Ok(FleetStats {
        vehicles: latest.len(),
        calibrations: jobs.len(),
        outlier_z,
        cameras: camera_stats,
        outliers,
        bucket_ms,
        drift,
        latest: values,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    use rigcal_core::geometry::{so3, Pose};

    fn model() -> VehicleModel {
        VehicleModel::parse(
            serde_json::json!({
                "reference_camera": "front",
                "cameras": [
                    {"id": "front", "translation": [0.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 0.0]},
                    {"id": "rear", "translation": [0.0, 0.1, -4.0], "rpy_deg": [0.0, 180.0, 0.0],
                     "tolerance": {"translation_mm": 10.0, "rotation_deg": 1.0}},
                    {"id": "left", "translation": [-1.0, 0.0, -2.0], "rpy_deg": [0.0, -90.0, 0.0],
                     "tolerance": {"translation_mm": 10.0, "rotation_deg": 1.0}}
                ]
            })
            .to_string()
            .as_bytes(),
        )
        .unwrap()
    }

    /// 210 vehicles mounted with 1.5 mm / 0.05° of normal variation per axis, five of
    /// them with one camera planted 2-4 % of a degree or a few mm beyond that (≥ 8
    /// spreads), 40 calibrated twice: exactly the five are flagged.
    #[test]
    fn a_fleet_of_210_with_five_planted_outliers_flags_the_five() {
        let m = model();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mm = Normal::new(0.0, 1.5e-3).unwrap();
        let deg = Normal::new(0.0, 0.05f64.to_radians()).unwrap();
        let planted: BTreeMap<usize, (&str, Vector3<f64>, Vector3<f64>)> = [
            (
                13,
                (
                    "rear",
                    Vector3::new(0.0, 0.0, 0.0),
                    Vector3::new(0.0, 0.6f64.to_radians(), 0.0),
                ),
            ),
            (
                57,
                ("left", Vector3::new(0.015, 0.0, 0.0), Vector3::zeros()),
            ),
            (
                101,
                (
                    "left",
                    Vector3::zeros(),
                    Vector3::new(0.0, 0.0, -0.5f64.to_radians()),
                ),
            ),
            (
                150,
                ("rear", Vector3::new(0.0, -0.02, 0.0), Vector3::zeros()),
            ),
            (
                199,
                (
                    "rear",
                    Vector3::new(0.0, 0.0, 0.012),
                    Vector3::new(0.4f64.to_radians(), 0.0, 0.0),
                ),
            ),
        ]
        .into();
        let mut jobs = Vec::new();
        for v in 0..210usize {
            for visit in 0..(1 + usize::from(v % 5 == 0)) {
                let mut ex = vec![ExtrinsicValue::of("front", &Pose::identity())];
                for cam in ["rear", "left"] {
                    let nom = m.nominal(cam).unwrap();
                    let mut dt = Vector3::new(
                        mm.sample(&mut rng),
                        mm.sample(&mut rng),
                        mm.sample(&mut rng),
                    );
                    let mut dr = Vector3::new(
                        deg.sample(&mut rng),
                        deg.sample(&mut rng),
                        deg.sample(&mut rng),
                    );
                    if let Some((c, t, r)) = planted.get(&v) {
                        // Only the latest visit is planted: a vehicle knocked since.
                        if *c == cam && visit == usize::from(v % 5 == 0) {
                            dt += t;
                            dr += r;
                        }
                    }
                    ex.push(ExtrinsicValue::of(
                        cam,
                        &Pose::new(so3::exp(&dr) * nom.rot, nom.trans + dt),
                    ));
                }
                jobs.push(FleetJob {
                    job_id: format!("job-{v}-{visit}"),
                    vehicle_id: format!("VIN-{v:04}"),
                    finished_at: (visit as i64 * 30 + (v as i64 % 30)) * 86_400_000,
                    extrinsics: serde_json::to_string(&ex).unwrap(),
                });
            }
        }
        jobs.sort_by_key(|j| j.finished_at);
        let s = stats(&m, &jobs, m.fleet_outlier_z, 7 * 86_400_000).unwrap();
        assert_eq!(s.vehicles, 210);
        assert_eq!(s.calibrations, 210 + 42);
        let mut flagged: Vec<&str> = s.outliers.iter().map(|o| o.vehicle_id.as_str()).collect();
        flagged.sort_unstable();
        let want: Vec<String> = planted.keys().map(|v| format!("VIN-{v:04}")).collect();
        assert_eq!(flagged, want.iter().map(String::as_str).collect::<Vec<_>>());
        // The spread estimates the mounting variation (1.5 mm, 0.05°) within 20 %.
        for c in &s.cameras {
            for a in &c.axes {
                let truth = if a.unit == "mm" { 1.5 } else { 0.05 };
                assert!(
                    (a.spread / truth - 1.0).abs() < 0.2,
                    "{} {}: {}",
                    c.camera,
                    a.axis,
                    a.spread
                );
                assert!(
                    a.median.abs() < 0.3 * truth,
                    "{} {}: {}",
                    c.camera,
                    a.axis,
                    a.median
                );
                assert_eq!(a.count, 210);
            }
        }
        // The planted axis is the one named.
        let o = s
            .outliers
            .iter()
            .find(|o| o.vehicle_id == "VIN-0057")
            .unwrap();
        assert_eq!((o.axes[0].camera.as_str(), o.axes[0].axis), ("left", "tx"));
        assert!(o.axes[0].value > 10.0);
        // Drift: two months of weekly periods, every calibration counted once per axis.
        let rear_tx = &s.drift[0];
        assert_eq!((rear_tx.camera.as_str(), rear_tx.axis), ("rear", "tx"));
        assert_eq!(rear_tx.points.iter().map(|p| p.count).sum::<usize>(), 252);
    }

    #[test]
    fn an_identical_fleet_flags_no_one_and_corrupt_rows_are_named() {
        let m = model();
        let ex: Vec<_> = ["front", "rear", "left"]
            .iter()
            .map(|c| ExtrinsicValue::of(c, &m.nominal(c).unwrap()))
            .collect();
        let jobs: Vec<FleetJob> = (0..20)
            .map(|v| FleetJob {
                job_id: format!("j{v}"),
                vehicle_id: format!("v{v}"),
                finished_at: v,
                extrinsics: serde_json::to_string(&ex).unwrap(),
            })
            .collect();
        let s = stats(&m, &jobs, 5.0, 1000).unwrap();
        assert!(s.outliers.is_empty());
        let mut bad = jobs.clone();
        bad[3].extrinsics = "{".into();
        assert!(stats(&m, &bad, 5.0, 1000).unwrap_err().contains("job j3"));
    }
}
