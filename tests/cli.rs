//! The `rigcal` binary as a user runs it: synth → calibrate → exit codes and output.

use std::process::Command;

fn rigcal() -> Command {
    Command::new(env!("CARGO_BIN_EXE_rigcal"))
}

/// The JSON a successful run printed (exit 0, else its stderr is the failure).
fn printed_json(out: &std::process::Output) -> serde_json::Value {
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn synth_then_calibrate_prints_the_result_document() {
    let dir = tempfile::tempdir().unwrap();
    let st = rigcal()
        .args([
            "synth",
            "--preset",
            "lebraly-5.1",
            "--seed",
            "3",
            "--noise",
            "0.3",
            "--out",
        ])
        .arg(dir.path())
        .status()
        .unwrap();
    assert!(st.success());
    let out = rigcal()
        .arg("calibrate")
        .arg(dir.path().join("session.json"))
        .output()
        .unwrap();
    let doc = printed_json(&out);
    assert_eq!(doc["status"], "succeeded");
    assert_eq!(doc["extrinsics"].as_array().unwrap().len(), 2);
    let out = rigcal()
        .arg("calibrate")
        .arg(dir.path().join("session.json"))
        .args(["--format", "kalibr"])
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&out.stdout).contains("cam1:"));
}

#[test]
fn degraded_exit_code_and_bad_input_errors() {
    let dir = tempfile::tempdir().unwrap();
    rigcal()
        .args(["synth", "--preset", "car-planar", "--out"])
        .arg(dir.path())
        .status()
        .unwrap();
    let out = rigcal()
        .arg("calibrate")
        .arg(dir.path().join("session.json"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(3));
    let bad = dir.path().join("bad.json");
    std::fs::write(&bad, r#"{"reference_camera":"a","cameras":[{"id":"a","model":"fisheye","width":10,"height":10,"intrinsics":{"fx":5,"fy":5,"cx":5,"cy":5}}]}"#).unwrap();
    let out = rigcal().arg("calibrate").arg(&bad).output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("cameras[0].model"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = rigcal()
        .args(["synth", "--preset", "nope"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
}

/// `rigcal detect` reads its target (and camera) from a file or inline, and a wrong
/// path is named as the option it came from.
#[test]
fn detect_reads_its_target_from_a_file_or_inline() {
    use rigcal_synth::tagscene::{scene, Lens, SceneParams};
    let s = scene(&SceneParams {
        grid: false,
        tag_px: 80.0,
        obliquity_deg: 20.0,
        lens: Lens::Pinhole,
        width: 640,
        height: 480,
        render: Default::default(),
        seed: 1,
    });
    let dir = tempfile::tempdir().unwrap();
    let image = dir.path().join("tag.png");
    s.image.save(&image).unwrap();
    let target = serde_json::to_string(&s.targets).unwrap();
    let file = dir.path().join("target.json");
    std::fs::write(&file, &target).unwrap();
    let detect = |target: &std::ffi::OsStr| {
        rigcal()
            .args(["detect", "--threads", "1", "--target"])
            .arg(target)
            .arg(&image)
            .output()
            .unwrap()
    };
    let ids = |out: &std::process::Output| -> Vec<u64> {
        printed_json(out)["tags"]
            .as_array()
            .unwrap()
            .iter()
            .map(|t| t["id"].as_u64().unwrap())
            .collect()
    };
    let want: Vec<u64> = s.truth.keys().map(|&id| id as u64).collect();
    assert!(!want.is_empty());
    assert_eq!(ids(&detect(file.as_os_str())), want);
    assert_eq!(ids(&detect(std::ffi::OsStr::new(&target))), want);
    let missing = detect(dir.path().join("nowhere.json").as_os_str());
    assert_eq!(missing.status.code(), Some(1));
    let err = String::from_utf8_lossy(&missing.stderr);
    assert!(
        err.contains("--target") && err.contains("nowhere.json"),
        "{err}"
    );
}
