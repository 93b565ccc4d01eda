//! Vehicle models over real HTTP: the nominal rig and tolerances as a factory sets them,
//! sessions that name a model, every job judged against it (a camera mounted 2° off its
//! bracket fails the line although its calibration is right), exports in the vehicle
//! frame, and the fleet statistics of 205 calibrated vehicles with 5 planted outliers.

mod common;

use common::*;
use rigcal_core::geometry::{so3, Pose};
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::time::Duration;

const PRESET: &str = "lebraly-5.1";

/// The preset's design rig as a vehicle model: cam2 within 10 mm / 0.5° of its nominal.
fn model() -> Value {
    design_rig_model(PRESET, [1.5, 0.0, 1.2])
}

/// A session of vehicle `vin` of model `rig` whose cam2 is mounted `delta` off design.
fn session(seed: u64, noise: f64, vin: &str, delta: Option<Pose>) -> Value {
    let mounting: BTreeMap<String, Pose> =
        delta.map(|d| ("cam2".to_string(), d)).into_iter().collect();
    let (m, _) = rigcal_synth::generate_mounted(PRESET, seed, noise, &mounting).unwrap();
    let mut v = serde_json::to_value(&m).unwrap();
    v["vehicle_id"] = json!(vin);
    v["vehicle_model"] = json!("rig");
    v
}

async fn put_model(c: &reqwest::Client, s: &Server, name: &str, body: &Value) -> reqwest::Response {
    c.put(s.url(&format!("/v1/vehicle-models/{name}")))
        .json(body)
        .send()
        .await
        .unwrap()
}

#[tokio::test(flavor = "multi_thread")]
async fn nominal_rig_tolerances_and_the_vehicle_frame() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "factory");
    let s = Server::start(dir.path(), &[]);
    let c = client(&key);

    // Bad models: each error names its field; nothing is stored.
    let mut no_tol = model();
    no_tol["cameras"][1]
        .as_object_mut()
        .unwrap()
        .remove("tolerance");
    let p = expect_problem(
        put_model(&c, &s, "rig", &no_tol).await,
        422,
        "invalid-field",
    )
    .await;
    assert_eq!(p["field"], "cameras[1].tolerance", "{p}");
    let mut wrong_type = model();
    wrong_type["cameras"][1]["translation"] = json!("0.1, 0.1, -2");
    let p = expect_problem(
        put_model(&c, &s, "rig", &wrong_type).await,
        422,
        "invalid-field",
    )
    .await;
    assert_eq!(p["field"], "cameras[1].translation", "{p}");
    let mut unit = model();
    unit["cameras"][1]["quaternion_wxyz"] = json!([1.0, 1.0, 0.0, 0.0]);
    let p = expect_problem(put_model(&c, &s, "rig", &unit).await, 422, "invalid-field").await;
    assert_eq!(p["field"], "cameras[1].quaternion_wxyz", "{p}");
    let r = c
        .put(s.url("/v1/vehicle-models/rig"))
        .header("content-type", "application/json")
        .body("{\"reference_camera\": ")
        .send()
        .await
        .unwrap();
    expect_problem(r, 400, "malformed-json").await;
    let p = expect_problem(
        put_model(&c, &s, "no%20spaces", &model()).await,
        422,
        "invalid-field",
    )
    .await;
    assert_eq!(p["field"], "model", "{p}");
    expect_problem(
        c.get(s.url("/v1/vehicle-models/rig")).send().await.unwrap(),
        404,
        "not-found",
    )
    .await;

    // Created, then replaced; listed.
    let r = put_model(&c, &s, "rig", &model()).await;
    assert_eq!(r.status().as_u16(), 201);
    assert_eq!(r.headers()["location"], "/v1/vehicle-models/rig");
    // Replacements back to back (within a millisecond of each other, some of them)
    // are replacements.
    for _ in 0..10 {
        let r = put_model(&c, &s, "rig", &model()).await;
        assert_eq!(r.status().as_u16(), 200);
    }
    let mut strict = model();
    strict["fleet_outlier_z"] = json!(6.0);
    let r = put_model(&c, &s, "rig", &strict).await;
    assert_eq!(r.status().as_u16(), 200);
    let got = get_json(&c, &s, "/v1/vehicle-models/rig").await;
    assert_eq!(got["model"], "rig");
    assert_eq!(got["fleet_outlier_z"], 6.0);
    assert_eq!(got["cameras"][1]["tolerance"]["rotation_deg"], 0.5);
    let list = get_json(&c, &s, "/v1/vehicle-models").await;
    assert_eq!(list["vehicle_models"].as_array().unwrap().len(), 1);

    // Sessions must name a defined model and fit it.
    let mut unknown = session(1, 0.05, "VIN-1", None);
    unknown["vehicle_model"] = json!("other");
    let r = c
        .post(s.url("/v1/sessions"))
        .json(&unknown)
        .send()
        .await
        .unwrap();
    let p = expect_problem(r, 422, "invalid-field").await;
    assert_eq!(p["field"], "vehicle_model", "{p}");
    let mut car = synth_session("car-bump", 1, 0.3, "VIN-CAR");
    car["vehicle_model"] = json!("rig");
    let r = c
        .post(s.url("/v1/sessions"))
        .json(&car)
        .send()
        .await
        .unwrap();
    let p = expect_problem(r, 422, "invalid-field").await;
    assert_eq!(p["field"], "reference_camera", "{p}");

    // A vehicle built to nominal passes; one whose cam2 bracket is turned 2° calibrates
    // fine (succeeded) and fails the line, with the camera and the bound named.
    let good = create_session(&c, &s, &session(1, 0.05, "VIN-GOOD", None)).await;
    let turned = Pose::new(
        so3::exp(&nalgebra::Vector3::new(0.0, 2f64.to_radians(), 0.0)),
        nalgebra::Vector3::zeros(),
    );
    let bad = create_session(&c, &s, &session(2, 0.05, "VIN-BENT", Some(turned))).await;
    let good = run_job(
        &c,
        &s,
        good["id"].as_str().unwrap(),
        Duration::from_secs(60),
    )
    .await;
    let bad = run_job(&c, &s, bad["id"].as_str().unwrap(), Duration::from_secs(60)).await;
    for j in [&good, &bad] {
        assert_eq!(j["status"], "succeeded", "{j}");
        assert_eq!(j["vehicle_model"], "rig");
        assert_eq!(j["acceptance"]["nominal"]["vehicle_model"], "rig");
    }
    assert_eq!(good["acceptance"]["pass"], true, "{good}");
    assert_eq!(good["acceptance"]["nominal"]["within_tolerance"], true);
    let d = &good["acceptance"]["nominal"]["cameras"][0];
    assert_eq!(d["camera"], "cam2");
    assert!(d["rotation_angle_deg"].as_f64().unwrap() < 0.1, "{d}");
    assert!(d["translation_norm_mm"].as_f64().unwrap() < 5.0, "{d}");
    assert_eq!(bad["acceptance"]["pass"], false, "{bad}");
    let d = &bad["acceptance"]["nominal"]["cameras"][0];
    assert!(
        (d["rotation_angle_deg"].as_f64().unwrap() - 2.0).abs() < 0.1,
        "{d}"
    );
    assert_eq!(d["within_tolerance"], false);
    let reasons = bad["acceptance"]["reasons"].to_string();
    assert!(
        reasons.contains("camera cam2 rotation") && reasons.contains("exceeds 0.5 deg"),
        "{reasons}"
    );
    // The list judges the same way; the result document carries the verdict too.
    let listed = get_json(&c, &s, "/v1/jobs?vehicle_id=VIN-BENT").await;
    assert_eq!(listed["jobs"][0]["acceptance"]["pass"], false);
    let bad_id = bad["id"].as_str().unwrap();
    let doc = get_json(&c, &s, &format!("/v1/jobs/{bad_id}/result")).await;
    assert_eq!(
        doc["nominal"]["within_tolerance"], false,
        "{}",
        doc["nominal"]
    );
    // Widen the tolerance: the old job is judged again on read and passes.
    let mut loose = model();
    loose["cameras"][1]["tolerance"]["rotation_deg"] = json!(3.0);
    assert_eq!(
        put_model(&c, &s, "rig", &loose).await.status().as_u16(),
        200
    );
    let again = get_json(&c, &s, &format!("/v1/jobs/{bad_id}")).await;
    assert_eq!(again["acceptance"]["pass"], true, "{}", again["acceptance"]);
    // The model's own thresholds take over from the tenant's.
    let mut tight = loose.clone();
    tight["acceptance_thresholds"] = json!({"max_rms_px": 0.001, "max_sigma_translation_m": 1.0, "max_sigma_rotation_deg": 10.0});
    assert_eq!(
        put_model(&c, &s, "rig", &tight).await.status().as_u16(),
        200
    );
    let again = get_json(&c, &s, &format!("/v1/jobs/{bad_id}")).await;
    assert_eq!(again["acceptance"]["thresholds_from"], "vehicle_model");
    assert_eq!(again["acceptance"]["pass"], false);
    assert!(again["acceptance"]["reasons"]
        .to_string()
        .contains("residual RMS"));

    // Exports in the vehicle frame: base_link parents the reference camera.
    let good_id = good["id"].as_str().unwrap();
    let text = |q: &str| {
        let c = c.clone();
        let url = s.url(&format!("/v1/jobs/{good_id}/result?{q}"));
        async move {
            let r = c.get(url).send().await.unwrap();
            (r.status().as_u16(), r.text().await.unwrap())
        }
    };
    let (st, urdf) = text("format=urdf&frame=vehicle").await;
    assert_eq!(st, 200, "{urdf}");
    assert!(
        urdf.contains("<parent link=\"base_link\"/>")
            && urdf.contains("<child link=\"cam1_optical_frame\"/>"),
        "{urdf}"
    );
    let (st, ros) = text("format=ros2&frame=vehicle").await;
    assert_eq!(st, 200);
    assert!(
        ros.contains("--frame-id base_link --child-frame-id cam1_optical_frame"),
        "{ros}"
    );
    let (st, kalibr) = text("format=kalibr&frame=vehicle").await;
    assert_eq!(st, 200);
    let y: Value = serde_norway::from_str(&kalibr).unwrap();
    let v = Pose::new(
        so3::from_rpy(-90f64.to_radians(), 0.0, -90f64.to_radians()),
        nalgebra::Vector3::new(1.5, 0.0, 1.2),
    );
    let m = v.matrix();
    for (i, row) in y["cam0"]["T_vehicle_cam"]
        .as_array()
        .unwrap()
        .iter()
        .enumerate()
    {
        for (j, x) in row.as_array().unwrap().iter().enumerate() {
            assert!((x.as_f64().unwrap() - m[i][j]).abs() < 1e-12, "{kalibr}");
        }
    }
    let (st, reference) = text("format=kalibr").await;
    assert_eq!(st, 200);
    assert!(!reference.contains("T_vehicle_cam"));
    let (st, body) = text("format=colmap&frame=vehicle").await;
    assert_eq!(st, 422, "{body}");
    assert!(body.contains("ref_sensor"), "{body}");
    let (st, body) = text("format=urdf&frame=world").await;
    assert_eq!(st, 422);
    assert!(body.contains("\"field\":\"frame\""), "{body}");
    // A job without a vehicle model has no vehicle frame.
    let plain = create_session(&c, &s, &synth_session(PRESET, 3, 0.05, "VIN-PLAIN")).await;
    let plain = run_job(
        &c,
        &s,
        plain["id"].as_str().unwrap(),
        Duration::from_secs(60),
    )
    .await;
    assert!(plain["acceptance"].get("nominal").is_none());
    let r = c
        .get(s.url(&format!(
            "/v1/jobs/{}/result?format=urdf&frame=vehicle",
            plain["id"].as_str().unwrap()
        )))
        .send()
        .await
        .unwrap();
    let p = expect_problem(r, 422, "invalid-field").await;
    assert_eq!(p["field"], "frame");
}

#[tokio::test(flavor = "multi_thread")]
async fn fleet_of_205_vehicles_with_five_planted_outliers() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "fleet");
    let s = Server::start(dir.path(), &["--workers", "2"]);
    let c = client(&key);
    assert_eq!(
        put_model(&c, &s, "rig", &model()).await.status().as_u16(),
        201
    );

    // Mounting variation of the line: 2 mm and 0.1° per axis (normal, in the camera's
    // frame, clipped at 3σ: a bracket beyond that is rejected at assembly); five vehicles whose latest calibration has cam2 knocked far beyond it, and
    // one knocked earlier and repaired since (its latest is normal: not an outlier).
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let mm = Normal::new(0.0, 2e-3).unwrap();
    let deg = Normal::new(0.0, 0.1f64.to_radians()).unwrap();
    let knock = |k: usize| -> Option<(nalgebra::Vector3<f64>, nalgebra::Vector3<f64>)> {
        let z = nalgebra::Vector3::zeros;
        match k {
            17 => Some((z(), nalgebra::Vector3::new(1.5f64.to_radians(), 0.0, 0.0))),
            44 => Some((nalgebra::Vector3::new(0.0, 0.05, 0.0), z())),
            90 => Some((z(), nalgebra::Vector3::new(0.0, 0.0, -2f64.to_radians()))),
            133 => Some((nalgebra::Vector3::new(0.04, 0.0, 0.03), z())),
            188 => Some((z(), nalgebra::Vector3::new(0.0, 1.2f64.to_radians(), 0.0))),
            _ => None,
        }
    };
    let mut jobs = Vec::new();
    let mut sessions = Vec::new();
    for k in 0..206usize {
        // Vehicle 0 twice: knocked first, repaired second.
        let vin = if k == 205 {
            "VIN-0000".to_string()
        } else {
            format!("VIN-{k:04}")
        };
        let mut draw = |d: &Normal<f64>| {
            let x: f64 = d.sample(&mut rng);
            x.clamp(-3.0 * d.std_dev(), 3.0 * d.std_dev())
        };
        let mut t = nalgebra::Vector3::new(draw(&mm), draw(&mm), draw(&mm));
        let mut r = nalgebra::Vector3::new(draw(&deg), draw(&deg), draw(&deg));
        let planted = if k == 0 {
            Some((
                nalgebra::Vector3::new(0.06, 0.0, 0.0),
                nalgebra::Vector3::zeros(),
            ))
        } else {
            knock(k)
        };
        if let Some((dt, dr)) = planted {
            t += dt;
            r += dr;
        }
        sessions.push(session(
            100 + k as u64,
            0.03,
            &vin,
            Some(Pose::from_rotvec(r, t)),
        ));
    }
    // The repaired visit of vehicle 0 must finish after the knocked one: posted last,
    // after the others have finished.
    let last = sessions.pop().unwrap();
    for m in &sessions {
        let sid = create_session(&c, &s, m).await["id"]
            .as_str()
            .unwrap()
            .to_string();
        jobs.push(
            submit(&c, &s, &sid).await["id"]
                .as_str()
                .unwrap()
                .to_string(),
        );
    }
    for id in &jobs {
        let j = wait_job(&c, &s, id, Duration::from_secs(300)).await;
        assert_eq!(j["status"], "succeeded", "{j}");
    }
    let sid = create_session(&c, &s, &last).await["id"]
        .as_str()
        .unwrap()
        .to_string();
    let j = run_job(&c, &s, &sid, Duration::from_secs(60)).await;
    assert_eq!(j["status"], "succeeded", "{j}");

    let f = get_json(&c, &s, "/v1/vehicle-models/rig/fleet").await;
    assert_eq!(f["vehicles"], 205, "{}", f["vehicles"]);
    assert_eq!(f["calibrations"], 206);
    assert_eq!(f["outlier_z"], 5.0);
    let mut flagged: Vec<&str> = f["outliers"]
        .as_array()
        .unwrap()
        .iter()
        .map(|o| o["vehicle_id"].as_str().unwrap())
        .collect();
    flagged.sort_unstable();
    assert_eq!(
        flagged,
        ["VIN-0017", "VIN-0044", "VIN-0090", "VIN-0133", "VIN-0188"],
        "{}",
        serde_json::to_string_pretty(&f["outliers"]).unwrap()
    );
    // The spread is the line's mounting variation plus the calibration's own error.
    let cam2 = &f["cameras"][0];
    assert_eq!(cam2["camera"], "cam2");
    for a in cam2["axes"].as_array().unwrap() {
        let spread = a["spread"].as_f64().unwrap();
        let (lo, hi) = if a["unit"] == "mm" {
            (1.5, 4.0)
        } else {
            (0.07, 0.15)
        };
        assert!(spread > lo && spread < hi, "{a}");
        assert_eq!(a["count"], 205);
    }
    // Drift: one weekly period holds every calibration.
    let series = f["drift"]["series"].as_array().unwrap();
    assert_eq!(series.len(), 6);
    let counted: u64 = series[0]["points"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["count"].as_u64().unwrap())
        .sum();
    assert_eq!(counted, 206);
    // A lower threshold flags more, never fewer; bad queries name the parameter.
    let loose = get_json(&c, &s, "/v1/vehicle-models/rig/fleet?z=2&bucket=day").await;
    assert!(loose["outliers"].as_array().unwrap().len() > 5);
    assert_eq!(loose["drift"]["bucket"], "day");
    for (q, field) in [("z=0.5", "z"), ("z=abc", "z"), ("bucket=year", "bucket")] {
        let r = c
            .get(s.url(&format!("/v1/vehicle-models/rig/fleet?{q}")))
            .send()
            .await
            .unwrap();
        let p = expect_problem(r, 422, "invalid-field").await;
        assert_eq!(p["field"], field, "{p}");
    }
    let r = c
        .get(s.url("/v1/vehicle-models/rig/fleet?colour=red"))
        .send()
        .await
        .unwrap();
    expect_problem(r, 400, "invalid-query").await;
    let r = c
        .get(s.url("/v1/vehicle-models/none/fleet"))
        .send()
        .await
        .unwrap();
    expect_problem(r, 404, "not-found").await;
}
