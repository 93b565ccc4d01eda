#!/usr/bin/env python3
"""OpenCV calibrateHandEye side by side with rigcal, on the same per-camera trajectories.

Usage (from the repository root, after `cargo build --release`):
    pip install numpy "opencv-contrib-python-headless<5"   # the 5.0 wheel has no calibrateHandEye
    python3 benches/peers/handeye.py --preset lebraly-5.1 --trials 50 --noise 0.1,0.3,0.5,1.0

Mapping (hand-eye AX = XB with X = gripper_from_cam = ref_from_cam):
  gripper = the reference camera, base = the reference camera's scene:
      gripper2base = scene_from_ref = inverse(ref_from_scene)
  cam = camera i, target = camera i's scene:
      target2cam = cam_from_scene
The script first checks, on noise-free data, that every method recovers the truth.
Not part of the test suite: a peer for measurements only.
"""
import argparse
import json
import subprocess

import cv2
import numpy as np

METHODS = {
    "Tsai": cv2.CALIB_HAND_EYE_TSAI,
    "Park": cv2.CALIB_HAND_EYE_PARK,
    "Horaud": cv2.CALIB_HAND_EYE_HORAUD,
    "Andreff": cv2.CALIB_HAND_EYE_ANDREFF,
    "Daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}


def export(preset, trials, noise, seed, binary):
    out = subprocess.run(
        [binary, "bench", "handeye-export", "--preset", preset, "--trials", str(trials), "--noise", str(noise), "--seed", str(seed)],
        check=True, capture_output=True, text=True,
    ).stdout
    return json.loads(out)


def errors(est, truth):
    est, truth = np.asarray(est), np.asarray(truth)
    dt = np.linalg.norm(est[:3, 3] - truth[:3, 3])
    c = (np.trace(est[:3, :3].T @ truth[:3, :3]) - 1) / 2
    return dt, np.degrees(np.arccos(np.clip(c, -1, 1)))


def opencv(trial, method):
    r_g2b, t_g2b, r_t2c, t_t2c = [], [], [], []
    for a, b in zip(trial["ref_from_scene"], trial["cam_from_scene"]):
        # OpenCV needs contiguous float64 3x3 rotations and 3x1 translations.
        g2b = np.linalg.inv(np.asarray(a, dtype=np.float64))
        r_g2b.append(np.ascontiguousarray(g2b[:3, :3])); t_g2b.append(np.ascontiguousarray(g2b[:3, 3:4]))
        b = np.asarray(b, dtype=np.float64)
        r_t2c.append(np.ascontiguousarray(b[:3, :3])); t_t2c.append(np.ascontiguousarray(b[:3, 3:4]))
    r, t = cv2.calibrateHandEye(r_g2b, t_g2b, r_t2c, t_t2c, method=method)
    m = np.eye(4); m[:3, :3] = r; m[:3, 3] = t.ravel()
    return m


def rms(values):
    return float(np.sqrt(np.mean(np.square(values)))) if values else float("nan")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="lebraly-5.1")
    ap.add_argument("--trials", type=int, default=50)
    ap.add_argument("--noise", default="0.1,0.3,0.5,1.0")
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--binary", default="target/release/rigcal")
    args = ap.parse_args()

    # Sanity: noise-free, a method must recover the truth; one that does not (OpenCV
    # 4.x Tsai rejects these motions as "not enough informative motions" and returns an
    # arbitrary matrix) is reported as unusable instead of compared.
    usable = dict(METHODS)
    for trial in export(args.preset, 3, 0.0, args.seed, args.binary):
        for name, m in METHODS.items():
            dt, dr = errors(opencv(trial, m), trial["truth_ref_from_cam"])
            if not (dt < 1e-5 and dr < 1e-4) and name in usable:
                print(f"noise-free check: {name} fails ({dt:.3f} m, {dr:.2f} deg): left out")
                del usable[name]
    print(f"noise-free check: {', '.join(usable)} recover the truth")
    METHODS.clear()
    METHODS.update(usable)

    names = ["rigcal BA", "rigcal init"] + list(METHODS)
    print(f"preset {args.preset}, {args.trials} trials per noise level: RMS translation mm / rotation deg")
    print(f"{'σ px':>6} " + " ".join(f"{n:>20}" for n in names))
    for noise in [float(x) for x in args.noise.split(",")]:
        trials = export(args.preset, args.trials, noise, args.seed, args.binary)
        acc = {n: ([], []) for n in names}
        for trial in trials:
            truth = trial["truth_ref_from_cam"]
            for n, est in [("rigcal BA", trial["rigcal_refined"]), ("rigcal init", trial["rigcal_init"])]:
                dt, dr = errors(est, truth); acc[n][0].append(dt * 1e3); acc[n][1].append(dr)
            for n, m in METHODS.items():
                dt, dr = errors(opencv(trial, m), truth); acc[n][0].append(dt * 1e3); acc[n][1].append(dr)
        print(f"{noise:>6.2f} " + " ".join(f"{rms(acc[n][0]):>10.2f}/{rms(acc[n][1]):<9.4f}" for n in names))


if __name__ == "__main__":
    main()
