#!/usr/bin/env python3
"""rigcal's tag detector side by side with pupil-apriltags and OpenCV cv2.aruco
(tag36h11, CORNER_REFINE_SUBPIX) on the same rendered images with known corners.

    pip install pupil-apriltags opencv-contrib-python-headless numpy
    cargo build --release
    python3 benches/peers/detect.py --views 20            # 6 cells × 20 views, 1600×1200

Renders the views with `rigcal bench detect --out DIR` (which also prints rigcal's own
table), then runs every detector on every PNG, single-threaded, and prints detection
rate, wrong ids, corner RMS error and median time per image per cell. Corner
conventions: pixel centres at integer coordinates (rigcal, OpenCV); the AprilTag C
library (pupil-apriltags) puts them at +0.5, which is subtracted. Corners are matched to
the nearest true corner of the same id, so no detector is penalised for its corner order.
Times are the detection call only (image already decoded), median per image.

    python3 benches/peers/detect.py --capture DIR   # a rendered hall capture

runs the same detectors on every image of a capture written by `rigcal synth --preset
car-hall --images --out DIR` (dense 1080p JPEG scenes: AprilGrids and wall tags on
textured walls), rigcal with `--threads 1` and with all cores at `--detect-quality
accurate` and with one thread at `fast`, against the capture's
corners.json: share of fully visible tags found, corners more than 1 px off (wrong),
corner RMS of the others, median ms per image.
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import cv2
import numpy as np
from pupil_apriltags import Detector


def release(detector):
    """Free a pupil-apriltags detector before its own `__del__` can: that one destroys the
    tag families first and the detector after, which reads them while it frees itself (a
    use after free, pupil-labs/apriltags#46), and at interpreter shutdown it crashed this
    script now and then after the table was printed. The AprilTag library's own examples
    free the detector, then the families."""
    if detector.tag_detector_ptr is None:
        return
    detector.libc.apriltag_detector_destroy.restype = None
    detector.libc.apriltag_detector_destroy(detector.tag_detector_ptr)
    detector.tag_detector_ptr = None
    for family, tf in detector.tag_families.items():
        destroy = getattr(detector.libc, f"{family}_destroy")
        destroy.restype = None
        destroy(tf)


def match_error(corners, truth):
    """Per-corner distance to the nearest true corner."""
    return [min(np.hypot(*(np.array(c) - np.array(t))) for t in truth) for c in corners]


def in_print(entry, tid):
    if not entry["grid"]:
        return False
    t = entry["targets"][0]
    return t["first_id"] <= tid < t["first_id"] + t["rows"] * t["cols"]


def capture_main(a):
    """Every detector on every image of a rendered hall capture (see the docstring)."""
    d = a.capture
    session = json.load(open(os.path.join(d, "session.json")))
    truth = json.load(open(os.path.join(d, "corners.json")))
    tf = os.path.join(d, "targets.peer.json")
    json.dump(session["targets"], open(tf, "w"))
    cams = {c["id"]: c for c in session["cameras"]}
    pupil = Detector(families="tag36h11", nthreads=1, quad_decimate=2.0, refine_edges=1)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    aruco = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), params)
    results = {}
    cores = str(os.cpu_count() or 1)
    for threads, quality in [("1", "accurate"), (cores, "accurate"), ("1", "fast")]:
        name = f"rigcal {quality} ({threads} thread{'s' if threads != '1' else ''})"
        for cam in cams:
            entries = [e for e in truth if e["camera"] == cam]
            cf = os.path.join(d, f"camera.{cam}.peer.json")
            json.dump(cams[cam], open(cf, "w"))
            cmd = [a.rigcal, "detect", "--target", tf, "--camera", cf, "--threads", threads,
                   "--detect-quality", quality]
            cmd += [os.path.join(d, e["path"]) for e in entries]
            out = json.loads(subprocess.run(cmd, capture_output=True, check=False).stdout)
            out = out if isinstance(out, list) else [out]
            for e, o in zip(entries, out):
                pts = {p["point"]: (p["u"], p["v"]) for p in o.get("points", [])}
                results[(e["path"], name)] = (pts, o.get("elapsed_ms", 0.0))
    for e in truth:
        img = cv2.imread(os.path.join(d, e["path"]), cv2.IMREAD_GRAYSCALE)
        for name, det in [("pupil-apriltags", None), ("cv2.aruco subpix", None)]:
            t = time.perf_counter()
            if name == "pupil-apriltags":
                found = [(r.tag_id, (r.corners - 0.5).tolist()) for r in pupil.detect(img)]
            else:
                corners, ids, _ = aruco.detectMarkers(img)
                found = [] if ids is None else [
                    (int(i), c.reshape(4, 2).tolist()) for i, c in zip(ids.flatten(), corners)]
            ms = (time.perf_counter() - t) * 1e3
            pts = {}
            for tid, corners in found:
                truths = [e["corners"].get(f"tag:{tid}:{k}") for k in range(4)]
                if any(t is None for t in truths):
                    continue
                # Nearest true corner of the same tag: no detector is penalised for its
                # corner order.
                for c in corners:
                    k = min(range(4), key=lambda k: np.hypot(*(np.array(c) - truths[k])))
                    pts[f"tag:{tid}:{k}"] = tuple(c)
            results[(e["path"], name)] = (pts, ms)
    names = sorted({k[1] for k in results}, key=lambda n: (not n.startswith("rigcal"), n))
    print(f"\n{'detector':<28} {'images':>6} {'tags':>6} {'found %':>8} {'wrong':>6} "
          f"{'rms px':>8} {'med ms':>8}")
    for name in names:
        total = found = wrong = 0
        err, ms = [], []
        for e in truth:
            pts, t = results[(e["path"], name)]
            ms.append(t)
            tags = {}
            for k in e["corners"]:
                tags.setdefault(k.rsplit(":", 1)[0], []).append(k)
            for ks in tags.values():
                if len(ks) == 4:
                    total += 1
                    found += all(k in pts for k in ks)
            for k, (u, v) in e["corners"].items():
                if k in pts:
                    x = float(np.hypot(pts[k][0] - u, pts[k][1] - v))
                    if x > 1.0:
                        wrong += 1
                    else:
                        err.append(x)
        rms = float(np.sqrt(np.mean(np.square(err)))) if err else float("nan")
        print(f"{name:<28} {len(truth):>6} {total:>6} {100 * found / max(1, total):>8.2f} "
              f"{wrong:>6} {rms:>8.4f} {statistics.median(ms):>8.1f}")
    release(pupil)
    return 0


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--views", type=int, default=20)
    ap.add_argument("--width", type=int, default=1600)
    ap.add_argument("--height", type=int, default=1200)
    ap.add_argument("--rigcal", default="target/release/rigcal")
    ap.add_argument("--dir", default=None, help="reuse/keep rendered views here")
    ap.add_argument("--only", default=None,
                    help="comma-separated detectors to run (default: all four)")
    ap.add_argument("--capture", default=None,
                    help="a hall capture written by `rigcal synth --images` (see above)")
    a = ap.parse_args()
    cv2.setNumThreads(1)
    if a.capture:
        return capture_main(a)
    d = a.dir or tempfile.mkdtemp(prefix="rigcal-detect-")
    if not os.path.exists(os.path.join(d, "truth.json")):
        subprocess.run([a.rigcal, "bench", "detect", "--views", str(a.views), "--width",
                        str(a.width), "--height", str(a.height), "--out", d], check=True)
    truth = json.load(open(os.path.join(d, "truth.json")))

    pupil = Detector(families="tag36h11", nthreads=1, quad_decimate=2.0, refine_edges=1)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    aruco = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), params)

    def run_rigcal_batch(entries, with_camera):
        """One `rigcal detect` over images that share target and camera; `elapsed_ms`
        times detection only (image decoded, decoder table built beforehand, as a
        worker keeps it)."""
        e0 = entries[0]
        tf = os.path.join(d, "target.json")
        json.dump(e0["targets"][0], open(tf, "w"))
        cmd = [a.rigcal, "detect"] + [os.path.join(d, e["image"]) for e in entries]
        cmd += ["--target", tf]
        if with_camera:
            cf = os.path.join(d, "camera.json")
            json.dump(e0["camera"], open(cf, "w"))
            cmd += ["--camera", cf]
        out = json.loads(subprocess.run(cmd, capture_output=True, check=False).stdout)
        out = out if isinstance(out, list) else [out]
        return [([(t["id"], t["corners"]) for t in o.get("tags", [])], o.get("elapsed_ms", 0.0))
                for o in out]

    def run_pupil(img):
        t = time.perf_counter()
        dets = pupil.detect(img)
        ms = (time.perf_counter() - t) * 1e3
        return [(r.tag_id, (r.corners - 0.5).tolist()) for r in dets], ms

    def run_aruco(img):
        t = time.perf_counter()
        corners, ids, _ = aruco.detectMarkers(img)
        ms = (time.perf_counter() - t) * 1e3
        if ids is None:
            return [], ms
        return [(int(i), c.reshape(4, 2).tolist()) for i, c in zip(ids.flatten(), corners)], ms

    names = [n for n in ["rigcal", "rigcal (no camera)", "pupil-apriltags", "cv2.aruco subpix"]
             if a.only is None or n in a.only.split(",")]
    stats = {}
    # One rigcal process per (target, camera): grids get a new id range per view.
    by_cell = {}
    for entry in truth:
        key = json.dumps([entry["targets"][0], entry["camera"]], sort_keys=True)
        by_cell.setdefault(key, []).append(entry)
    rigcal_out = {}
    for cell, entries in by_cell.items():
        for name, cam in [("rigcal", True), ("rigcal (no camera)", False)]:
            if name in names:
                for entry, r in zip(entries, run_rigcal_batch(entries, cam)):
                    rigcal_out[(entry["image"], name)] = r
    for entry in truth:
        path = os.path.join(d, entry["image"])
        img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        truths = {t["id"]: t["corners"] for t in entry["tags"]}
        results = {}
        for name in names:
            if name.startswith("rigcal"):
                results[name] = rigcal_out[(entry["image"], name)]
            elif name == "pupil-apriltags":
                results[name] = run_pupil(img)
            else:
                results[name] = run_aruco(img)
        label = ("grid " if entry["grid"] else "tag ") + entry["lens"]
        for name, (dets, ms) in results.items():
            s = stats.setdefault((label, name), {"visible": 0, "found": 0, "wrong": 0,
                                                 "err": [], "ms": []})
            s["visible"] += len(truths)
            s["ms"].append(ms)
            seen = set()
            for tid, corners in dets:
                if tid in truths and tid not in seen:
                    seen.add(tid)
                    s["found"] += 1
                    s["err"] += match_error(corners, truths[tid])
                elif tid not in truths and not in_print(entry, tid):
                    s["wrong"] += 1

    print(f"\n{'cell':<18} {'detector':<20} {'visible':>7} {'found':>6} {'rate %':>7} "
          f"{'wrong':>5} {'rms px':>8} {'p95 px':>7} {'med ms':>7}")
    for label in sorted({k[0] for k in stats}):
        for name in names:
            s = stats[(label, name)]
            e = np.array(s["err"]) if s["err"] else np.array([np.nan])
            print(f"{label:<18} {name:<20} {s['visible']:>7} {s['found']:>6} "
                  f"{100 * s['found'] / max(1, s['visible']):>7.2f} {s['wrong']:>5} "
                  f"{np.sqrt(np.mean(e ** 2)):>8.4f} {np.percentile(e, 95):>7.3f} "
                  f"{statistics.median(s['ms']):>7.1f}")
    release(pupil)
    return 0


if __name__ == "__main__":
    sys.exit(main())
