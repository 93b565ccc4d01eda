//! The CLI client against a real server: `rigcal submit` uploads a capture (a
//! directory of images, or a session.json of detections), waits, writes the result and
//! the exports and exits with the verdict; a retried submit gets the first job back;
//! `rigcal jobs list|show|cancel`.

mod common;

use common::*;
use serde_json::Value;
use std::path::Path;
use std::process::Output;

fn client_cmd(s: &Server, key: &str, args: &[&str]) -> Output {
    std::process::Command::new(BIN)
        .args(args)
        .args(["--server", &s.base, "--key", key])
        .output()
        .unwrap()
}

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).to_string()
}

fn job_id(o: &Output) -> String {
    stdout(o)
        .lines()
        .find_map(|l| {
            l.strip_prefix("job ")
                .map(|r| r.split(':').next().unwrap().trim().to_string())
        })
        .unwrap_or_else(|| panic!("no job line in {:?}", stdout(o)))
}

fn write_json(path: &Path, v: &Value) {
    std::fs::write(path, serde_json::to_vec(v).unwrap()).unwrap();
}

#[tokio::test(flavor = "multi_thread")]
async fn submit_waits_writes_the_result_and_exports_and_a_retry_gets_the_same_job() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "line-7");
    let s = Server::start(dir.path(), &["--workers", "1"]);
    let c = client(&key);

    let manifest = dir.path().join("session.json");
    write_json(&manifest, &synth_session("lebraly-5.1", 3, 0.3, "car-42"));
    let out = dir.path().join("out");
    let m = manifest.to_str().unwrap();
    let o = out.to_str().unwrap();
    let first = client_cmd(&s, &key, &["submit", m, "--wait", "--out", o]);
    assert_eq!(
        first.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&first.stderr)
    );
    assert!(
        stdout(&first).contains("residuals: RMS"),
        "{}",
        stdout(&first)
    );
    let id = job_id(&first);
    let stored = get_json(&c, &s, &format!("/v1/jobs/{id}/result")).await;
    let written: Value =
        serde_json::from_slice(&std::fs::read(out.join("result.json")).unwrap()).unwrap();
    assert_eq!(written, stored);
    for f in [
        "kalibr.yaml",
        "opencv.yaml",
        "urdf.urdf",
        "colmap.json",
        "ros2.launch.xml",
    ] {
        let bytes = std::fs::read(out.join(f)).unwrap_or_else(|e| panic!("{f}: {e}"));
        assert!(!bytes.is_empty(), "{f}");
    }

    // A script that retries gets the first job, not a second one.
    let again = client_cmd(&s, &key, &["submit", m]);
    assert_eq!(again.status.code(), Some(0));
    assert_eq!(job_id(&again), id);
    let jobs = get_json(&c, &s, "/v1/jobs").await;
    assert_eq!(jobs["total"], 1, "{jobs}");

    // A failed calibration: exit 1 like `calibrate`, result.json and no exports.
    let failed = dir.path().join("failed.json");
    write_json(
        &failed,
        &synth_session("pure-translation", 1, 0.3, "car-43"),
    );
    let out2 = dir.path().join("out2");
    let f = client_cmd(
        &s,
        &key,
        &[
            "submit",
            failed.to_str().unwrap(),
            "--wait",
            "--out",
            out2.to_str().unwrap(),
        ],
    );
    assert_eq!(
        f.status.code(),
        Some(1),
        "{}",
        String::from_utf8_lossy(&f.stderr)
    );
    assert!(out2.join("result.json").is_file());
    assert!(!out2.join("kalibr.yaml").exists());

    // jobs list / show / cancel.
    let list = client_cmd(&s, &key, &["jobs", "list"]);
    assert!(list.status.success());
    assert!(stdout(&list).contains(&id), "{}", stdout(&list));
    let show = client_cmd(&s, &key, &["jobs", "show", &id]);
    let shown: Value = serde_json::from_slice(&show.stdout).unwrap();
    assert_eq!(shown["status"], "succeeded");
    let cancel = client_cmd(&s, &key, &["jobs", "cancel", &id]);
    assert_eq!(cancel.status.code(), Some(1));
    let err = String::from_utf8_lossy(&cancel.stderr);
    assert!(err.contains("already ended"), "{err}");
}

#[tokio::test(flavor = "multi_thread")]
async fn submit_uploads_a_capture_directory_and_refuses_what_is_not_one() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "line-7");
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let c = client(&key);
    let capture = dir.path().join("capture");
    for cam in ["front", "rear"] {
        std::fs::create_dir_all(capture.join(cam)).unwrap();
    }
    write_json(&capture.join("session.json"), &image_session(2, 40, 30));
    for k in 0..2u8 {
        std::fs::write(capture.join(format!("front/{k:04}.png")), png(40, 30, k)).unwrap();
        std::fs::write(
            capture.join(format!("rear/{k:04}.png")),
            png(40, 30, 10 + k),
        )
        .unwrap();
    }
    let o = client_cmd(&s, &key, &["submit", capture.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let job = get_json(&c, &s, &format!("/v1/jobs/{}", job_id(&o))).await;
    let sess = get_json(&c, &s, job["links"]["session"].as_str().unwrap()).await;
    assert_eq!(sess["images_received"], 4, "{sess}");

    for (input, expected) in [
        (dir.path().join("nowhere.tar"), "reading"),
        (dir.path().to_path_buf(), "session.json at its top"),
    ] {
        let o = client_cmd(&s, &key, &["submit", input.to_str().unwrap()]);
        assert_eq!(o.status.code(), Some(1));
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(expected), "{err}");
    }
    let wrong_key = client_cmd(&s, "rk_wrong", &["jobs", "list"]);
    assert_eq!(wrong_key.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&wrong_key.stderr).contains("401"));
}
