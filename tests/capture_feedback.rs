//! Capture feedback on upload (issue 18): a session's images are detected as they
//! arrive, the capture check follows the detections (partial, then complete moments
//! after the last image), the session's event stream pushes both, and the job reuses
//! the detections instead of decoding the images again. Real server, real HTTP, a
//! rendered car-hall capture (JPEG, vignetting, noise, mixed boards).

mod common;

use common::*;
use rigcal_calib::check::capture_check;
use rigcal_core::result::DetectionQuality;
use rigcal_core::session::parse_session;
use rigcal_engine::pipeline::detection::{detect_session, MemorySource};
use rigcal_engine::pipeline::Silent;
use rigcal_synth::hall::{hall, Hall, Nuisance};
use serde_json::{json, Value};
use std::collections::{BTreeSet, HashMap};
use std::time::{Duration, Instant};

const MIN: Duration = Duration::from_secs(60);

/// An event stream read as it comes: `(event, data)` pairs.
struct Events {
    resp: reqwest::Response,
    buf: String,
    ended: bool,
}

impl Events {
    async fn open(c: &reqwest::Client, s: &Server, session: &str) -> Events {
        let resp = c
            .get(s.url(&format!("/v1/sessions/{session}/events")))
            .send()
            .await
            .unwrap();
        assert_eq!(resp.status(), 200);
        assert_eq!(
            resp.headers()["content-type"].to_str().unwrap(),
            "text/event-stream"
        );
        Events {
            resp,
            buf: String::new(),
            ended: false,
        }
    }

    /// The next event, `None` when the stream ended. Panics after `timeout`.
    async fn next(&mut self, timeout: Duration) -> Option<(String, Value)> {
        let end = Instant::now() + timeout;
        loop {
            if let Some(cut) = self.buf.find("\n\n") {
                let raw: String = self.buf.drain(..cut + 2).collect();
                let (mut kind, mut data) = (String::new(), String::new());
                for line in raw.lines() {
                    if let Some(v) = line.strip_prefix("event:") {
                        kind = v.trim().to_string();
                    } else if let Some(v) = line.strip_prefix("data:") {
                        data.push_str(v.trim_start());
                    }
                }
                if kind.is_empty() {
                    continue; // a keep-alive comment
                }
                return Some((kind, serde_json::from_str(&data).unwrap()));
            }
            if self.ended {
                return None;
            }
            let left = end.saturating_duration_since(Instant::now());
            match tokio::time::timeout(left, self.resp.chunk()).await {
                Ok(Ok(Some(b))) => self.buf.push_str(&String::from_utf8_lossy(&b)),
                Ok(Ok(None)) => self.ended = true,
                Ok(Err(e)) => panic!("stream error: {e}"),
                Err(_) => panic!("no event within {timeout:?}"),
            }
        }
    }
}

async fn put_image(c: &reqwest::Client, s: &Server, sid: &str, cam: &str, frame: usize, b: &[u8]) {
    let r = c
        .put(s.url(&format!("/v1/sessions/{sid}/images/{cam}/{frame}")))
        .header("content-type", "image/jpeg")
        .body(b.to_vec())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200, "{}", r.text().await.unwrap());
}

/// `GET /check` is 409 `check-not-ready`, its detail starting with `detail`.
async fn check_not_ready(c: &reqwest::Client, s: &Server, sid: &str, detail: &str) {
    let r = c
        .get(s.url(&format!("/v1/sessions/{sid}/check")))
        .send()
        .await
        .unwrap();
    let p = expect_problem(r, 409, "check-not-ready").await;
    assert!(p["detail"].as_str().unwrap().starts_with(detail), "{p}");
}

/// What the check must say: the capture check of the session as the detection stage
/// detects it from the same bytes.
fn expected_check(manifest: &Value, images: &HashMap<String, Vec<u8>>) -> Value {
    let session = parse_session(&serde_json::to_vec(manifest).unwrap()).unwrap();
    let (detected, _) = detect_session(
        &session,
        &MemorySource(images.clone()),
        DetectionQuality::Accurate,
        &Silent,
    )
    .unwrap();
    serde_json::to_value(capture_check(&detected)).unwrap()
}

/// The parts of a check that depend on the detections (not its timing).
fn essence(check: &Value) -> Value {
    let mut v = check.clone();
    v.as_object_mut().unwrap().remove("seconds");
    v
}

/// Equal, numbers to 1e-9 relative (kept detections went through JSON text).
fn same(a: &Value, b: &Value) -> bool {
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            (x - y).abs() <= 1e-9 * x.abs().max(y.abs()).max(1.0)
        }
        (Value::Array(x), Value::Array(y)) => {
            x.len() == y.len() && x.iter().zip(y).all(|(x, y)| same(x, y))
        }
        (Value::Object(x), Value::Object(y)) => {
            x.len() == y.len() && x.iter().all(|(k, v)| y.get(k).is_some_and(|w| same(v, w)))
        }
        _ => a == b,
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn images_are_detected_as_they_arrive_and_the_check_and_the_job_follow() {
    // A rendered car-hall capture: 4 cameras (2 radtan, 2 fisheye), 18 frames, 72 JPEGs.
    let h = hall("car-hall", 5, Some((1024, 576))).unwrap();
    let nuisance = Nuisance::default();
    let capture = h.image_capture(true);
    let manifest = serde_json::to_value(&capture.manifest).unwrap();
    let mut order: Vec<(String, usize, String)> = Vec::new();
    for (frame, spec) in capture.manifest.frames.iter().enumerate() {
        for (cam, path) in &spec.images {
            order.push((cam.clone(), frame, path.clone()));
        }
    }
    let n = order.len();
    assert_eq!(n, 72);
    // Rendered over the cores.
    let images: HashMap<String, Vec<u8>> = std::thread::scope(|sc| {
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        let chunks: Vec<_> = order
            .chunks(n.div_ceil(threads))
            .map(|part| {
                let (h, nuisance) = (&h, &nuisance);
                sc.spawn(move || {
                    part.iter()
                        .map(|(cam, frame, path)| {
                            let ci = h.cameras.iter().position(|c| &c.0 == cam).unwrap();
                            let img = h.render(*frame, ci, nuisance, (frame * 8 + ci) as u64);
                            (path.clone(), Hall::encode(&img, nuisance).unwrap())
                        })
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        chunks.into_iter().flat_map(|c| c.join().unwrap()).collect()
    });
    let expected = essence(&expected_check(&manifest, &images));

    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "line-7");
    let s = Server::start(dir.path(), &["--workers", "1"]);
    let c = client(&key);
    let sess = create_session(&c, &s, &manifest).await;
    let sid = sess["id"].as_str().unwrap().to_string();
    assert_eq!(sess["images_to_detect"], 72, "{sess}");
    assert_eq!(sess["images_detected"], 0, "{sess}");
    assert_eq!(sess["capture_check"], Value::Null);
    check_not_ready(&c, &s, &sid, "0 of 72 images detected").await;
    // A cursor this server never sent is refused, naming the header.
    let r = c
        .get(s.url(&format!("/v1/sessions/{sid}/events")))
        .header("last-event-id", "99999999")
        .send()
        .await
        .unwrap();
    let p = expect_problem(r, 400, "invalid-field").await;
    assert_eq!(p["field"], "Last-Event-ID");

    let mut events = Events::open(&c, &s, &sid).await;
    let mut seen: BTreeSet<(String, i64)> = BTreeSet::new();

    // Half the capture: a partial check covering exactly those images, said to be partial.
    let half = n / 2;
    for (cam, frame, path) in &order[..half] {
        put_image(&c, &s, &sid, cam, *frame, &images[path]).await;
    }
    loop {
        let (kind, e) = events.next(MIN).await.expect("the stream ended early");
        match kind.as_str() {
            "image" => {
                let d = &e["data"];
                assert!(d["error"].is_null(), "{e}");
                assert!(d["points"].as_u64().unwrap() > 0, "{e}");
                let key = (
                    d["camera"].as_str().unwrap().into(),
                    d["frame"].as_i64().unwrap(),
                );
                assert!(seen.insert(key), "one image event per image: {e}");
            }
            "check" => {
                let d = &e["data"];
                assert_eq!(d["images_expected"], 72);
                assert_eq!(d["complete"], false, "{e}");
                if d["images_detected"] == half {
                    let reasons: Vec<&str> = d["check"]["reasons"]
                        .as_array()
                        .unwrap()
                        .iter()
                        .map(|r| r["code"].as_str().unwrap())
                        .collect();
                    assert!(reasons.contains(&"detections_pending"), "{reasons:?}");
                    break;
                }
            }
            other => panic!("unexpected event {other}"),
        }
    }
    assert_eq!(seen.len(), half);
    check_not_ready(&c, &s, &sid, "36 of 72 images detected (36 of 72 received)").await;
    let v = get_json(&c, &s, &format!("/v1/sessions/{sid}")).await;
    assert_eq!(v["images_detected"], 36, "{v}");
    assert_eq!(v["capture_check_complete"], false, "{v}");
    assert!(v["capture_check"]["verdict"].is_string(), "{v}");

    // The rest, one by one as a capture rig sends them; the stream ends with the
    // complete check.
    for (cam, frame, path) in &order[half..] {
        put_image(&c, &s, &sid, cam, *frame, &images[path]).await;
    }
    let last_put = Instant::now();
    let mut last_check = Value::Null;
    while let Some((kind, e)) = events.next(MIN).await {
        if kind == "image" {
            let d = &e["data"];
            let key = (
                d["camera"].as_str().unwrap().into(),
                d["frame"].as_i64().unwrap(),
            );
            assert!(seen.insert(key), "one image event per image: {e}");
        } else {
            assert_eq!(kind, "check");
            last_check = e["data"].clone();
        }
    }
    let to_check = last_put.elapsed();
    assert_eq!(seen.len(), 72);
    assert_eq!(last_check["complete"], true, "{last_check}");
    assert_eq!(last_check["images_detected"], 72);

    // The complete check is the one the detection stage's detections give.
    let check = get_json(&c, &s, &format!("/v1/sessions/{sid}/check")).await;
    assert_eq!(essence(&check), essence(&last_check["check"]));
    assert!(same(&essence(&check), &expected), "{check}\n{expected}");
    assert_ne!(check["verdict"], "insufficient", "{check}");
    let v = get_json(&c, &s, &format!("/v1/sessions/{sid}")).await;
    assert_eq!(v["capture_check_complete"], true, "{v}");
    assert_eq!(v["images_detected"], 72, "{v}");
    // A stream opened now has nothing more to say: it replays and ends.
    let mut again = Events::open(&c, &s, &sid).await;
    let mut replayed = 0;
    while again.next(MIN).await.is_some() {
        replayed += 1;
    }
    assert!(replayed >= 73, "{replayed}");

    // The job uses the detections made at upload: none detected again.
    let to_check = to_check.as_secs_f64();
    let t = Instant::now();
    let job = run_job(&c, &s, &sid, Duration::from_secs(300)).await;
    let job_seconds = t.elapsed().as_secs_f64();
    assert_eq!(job["status"], "succeeded", "{job}");
    let doc = get_json(
        &c,
        &s,
        &format!("/v1/jobs/{}/result", job["id"].as_str().unwrap()),
    )
    .await;
    let det = &doc["detection"];
    assert_eq!(det["images_total"], 72, "{det}");
    assert_eq!(det["images_reused"], 72, "{det}");
    eprintln!(
        "72 images PUT one by one: last PUT -> complete check {to_check:.2} s; job submitted then -> result {job_seconds:.2} s (its detection stage {:.3} s)",
        det["seconds"].as_f64().unwrap()
    );
}

/// A session of detections has its check at creation: complete at once, and its event
/// stream ends at once (nothing to detect).
#[tokio::test]
async fn a_session_of_detections_is_checked_at_creation() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let c = client(&key);
    let sess = create_session(&c, &s, &synth_session("lebraly-5.1", 3, 0.3, "VIN-1")).await;
    let sid = sess["id"].as_str().unwrap();
    assert_eq!(sess["capture_check_complete"], true, "{sess}");
    assert_eq!(sess["images_to_detect"], 0);
    let check = get_json(&c, &s, &format!("/v1/sessions/{sid}/check")).await;
    assert_eq!(check["verdict"], "ok", "{check}");
    let mut events = Events::open(&c, &s, sid).await;
    assert!(events.next(MIN).await.is_none());
}

/// A job submitted while a large upload is still being detected runs after a turn of
/// images (`jobs::detection::IMAGES_PER_TURN`), not after the whole upload: a fleet
/// keeps uploading, and a factory's job must not wait for every image of it. One
/// worker: before, it detected all 80 pending 1080p images first.
#[tokio::test]
async fn a_job_does_not_wait_for_every_pending_upload() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &["--workers", "1"]);
    let c = client(&key);
    let (frames, w, h) = (40, 1920, 1080);
    let manifest = image_session(frames, w, h);
    let mut files = vec![(
        "capture/session.json".to_string(),
        serde_json::to_vec(&manifest).unwrap(),
    )];
    for k in 0..frames {
        for (i, cam) in ["front", "rear"].into_iter().enumerate() {
            let seed = (2 * k + i) as u8;
            files.push((format!("capture/{cam}/{k:04}.png"), png(w, h, seed)));
        }
    }
    let upload = create_archive_session(&c, &s, &files).await;
    let upload_id = upload["id"].as_str().unwrap();
    let other = create_session(&c, &s, &synth_session("lebraly-5.1", 3, 0.3, "VIN-2")).await;
    let job = submit(&c, &s, other["id"].as_str().unwrap()).await;
    let done = wait_job(&c, &s, job["id"].as_str().unwrap(), MIN).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let view = get_json(&c, &s, &format!("/v1/sessions/{upload_id}")).await;
    let (queued, detected) = (
        view["images_to_detect"].as_i64(),
        view["images_detected"].as_i64(),
    );
    assert_eq!(queued, Some(2 * frames as i64), "{view}");
    assert!(
        detected.is_some_and(|n| n < 2 * frames as i64),
        "the job waited for the whole upload: {view}"
    );
    eprintln!("job done with {detected:?} of {queued:?} uploaded images detected");
}

/// Uploads detected at `--upload-detect-quality fast` serve a `fast` job, which reuses
/// them, but not an `accurate` one, which detects every image again; each result says
/// the quality its job asked for.
#[tokio::test]
async fn a_job_reuses_only_upload_detections_as_accurate_as_it_asked() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(
        dir.path(),
        &["--workers", "1", "--upload-detect-quality", "fast"],
    );
    let c = client(&key);
    let manifest = image_session(2, 32, 24);
    let files: Vec<(String, Vec<u8>)> = std::iter::once((
        "session.json".to_string(),
        serde_json::to_vec(&manifest).unwrap(),
    ))
    .chain((0..2).flat_map(|k| {
        [("front", 1), ("rear", 2)]
            .map(|(cam, seed)| (format!("{cam}/{k:04}.png"), png(32, 24, seed + k as u8)))
    }))
    .collect();
    let v = create_archive_session(&c, &s, &files).await;
    let sid = v["id"].as_str().unwrap().to_string();
    let t = Instant::now();
    while get_json(&c, &s, &format!("/v1/sessions/{sid}")).await["images_detected"] != 4 {
        assert!(t.elapsed() < MIN, "uploads not detected");

        tokio::time::sleep(Duration::from_millis(100)).await;
    }

    let detection_of = |quality: Option<&'static str>| {
        let (c, s, sid) = (&c, &s, &sid);
        async move {
            let mut body = json!({"session_id": sid});
            if let Some(q) = quality {
                body["options"] = json!({"detection": {"quality": q}});
            }
            let r = c.post(s.url("/v1/jobs")).json(&body).send().await.unwrap();
            assert_eq!(r.status(), 202);
            let job: Value = r.json().await.unwrap();
            let id = job["id"].as_str().unwrap();
            let done = wait_job(c, s, id, MIN).await;
            // Gradients with no tag: the job fails, but its document reports detection.
            assert_eq!(done["error"]["code"], "camera_not_observed", "{done}");
            get_json(c, s, &format!("/v1/jobs/{id}/result")).await["detection"].clone()
        }
    };
    let fast = detection_of(Some("fast")).await;

    assert_eq!(
        (fast["quality"].as_str(), fast["images_reused"].as_u64()),
        (Some("fast"), Some(4)),
        "{fast}"
    );
    let accurate = detection_of(None).await;
    assert_eq!(
        (
            accurate["quality"].as_str(),
            accurate["images_reused"].as_u64(),
            accurate["images_total"].as_u64()
        ),
        (Some("accurate"), Some(0), Some(4)),
        "{accurate}"
    );
}
