#!/usr/bin/env python3
"""rigcal's rig bundle adjustment side by side with COLMAP's (Ceres) on the same problem.

For each K, `rigcal bench speed --poses K --export DIR` builds the issue-2 benchmark rig
(6 cameras on a ring, K rig poses, 100 points per camera scene, 0.5 px noise, perturbed
start), solves it and writes the problem, the start and rigcal's end state to
DIR/ba_K.json. This script then gives COLMAP the identical problem as a native rig
(pycolmap >= 3.12: one Rig whose reference sensor is camera 0, one Frame per rig pose,
`sensor_from_rig` refined), from the identical start, with the same gauge (frame 0 and
camera 0 held), intrinsics held, no robust loss and the same stopping tolerances, and
times `BundleAdjuster.solve()` alone (problem construction excluded for both).

Both end states are scored by one function here (0.5 * sum of squared pixel residuals,
Ceres' definition and rigcal's), so "same final cost" is checked independently of what
either solver reports.

    pip install pycolmap numpy
    cargo build --release
    python3 benches/peers/colmap_ba.py --poses 50,200,1000

Needs nothing beyond PyPI; not part of the test suite (.ci/run).
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
import pycolmap


def pose(a):
    """12 numbers (row-major R, t) -> (R, t) of the map x -> R x + t."""
    a = np.asarray(a, dtype=float)
    return a[:9].reshape(3, 3), a[9:12]


def inverse(R, t):
    return R.T, -R.T @ t


def cost(doc, state):
    """0.5 * sum of squared reprojection errors of `state` (rigcal's parameterisation:
    ref_from_cam, world_from_ref, points) over the exported observations."""
    fx, fy, cx, cy = doc["intrinsics"]
    obs = np.asarray(doc["observations"], dtype=float)
    k = obs[:, 0].astype(int)
    c = obs[:, 1].astype(int)
    i = obs[:, 2].astype(int)
    X = np.asarray(state["points"], dtype=float)
    rigs = [pose(p) for p in state["world_from_ref"]]
    cams = [pose(p) for p in state["ref_from_cam"]]
    total = 0.0
    for kk in range(len(rigs)):
        sel_k = k == kk
        Rw, tw = rigs[kk]
        for cc in range(len(cams)):
            sel = sel_k & (c == cc)
            if not sel.any():
                continue
            Rc, tc = cams[cc]
            # world_from_cam = world_from_ref * ref_from_cam; invert to cam_from_world.
            R, t = inverse(Rw @ Rc, Rw @ tc + tw)
            q = X[i[sel]] @ R.T + t
            u = fx * q[:, 0] / q[:, 2] + cx
            v = fy * q[:, 1] / q[:, 2] + cy
            total += np.sum((u - obs[sel, 3]) ** 2 + (v - obs[sel, 4]) ** 2)
    return 0.5 * total


def rigid(R, t):
    return pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(R)), np.asarray(t))


def build(doc):
    """The exported problem as a COLMAP reconstruction with one rig, at the start state."""
    fx, fy, cx, cy = doc["intrinsics"]
    start = doc["start"]
    cams = [pose(p) for p in start["ref_from_cam"]]
    rigs = [pose(p) for p in start["world_from_ref"]]
    n_cam, n_rig = len(cams), len(rigs)
    rec = pycolmap.Reconstruction()
    for c in range(n_cam):
        rec.add_camera(
            pycolmap.Camera(
                camera_id=c + 1,
                model="PINHOLE",
                width=doc["width"],
                height=doc["height"],
                params=[fx, fy, cx, cy],
            )
        )
    sensor = lambda c: pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=c + 1)
    rig = pycolmap.Rig(rig_id=1)
    rig.add_ref_sensor(sensor(0))
    for c in range(1, n_cam):
        # sensor_from_rig = cam_from_ref = inverse(ref_from_cam)
        rig.add_sensor(sensor(c), rigid(*inverse(*cams[c])))
    rec.add_rig(rig)

    obs = np.asarray(doc["observations"], dtype=float)
    image_id = lambda k, c: k * n_cam + c + 1
    per_image = {}
    for row, (k, c) in enumerate(obs[:, :2].astype(int)):
        per_image.setdefault((k, c), []).append(row)
    for k in range(n_rig):
        frame = pycolmap.Frame(frame_id=k + 1, rig_id=1)
        frame.rig_from_world = rigid(*inverse(*rigs[k]))  # ref_from_world
        for c in range(n_cam):
            frame.add_data_id(pycolmap.data_t(sensor_id=sensor(c), id=image_id(k, c)))
        rec.add_frame(frame)
        for c in range(n_cam):
            rows = per_image.get((k, c), [])
            kp = obs[rows, 3:5] if rows else np.zeros((0, 2))
            im = pycolmap.Image(
                name=f"{k}_{c}", keypoints=kp, camera_id=c + 1, image_id=image_id(k, c)
            )
            im.frame_id = k + 1
            rec.add_image(im)
        rec.register_frame(k + 1)
    tracks = {}
    for (k, c), rows in per_image.items():
        for idx, row in enumerate(rows):
            tracks.setdefault(int(obs[row, 2]), []).append((image_id(k, c), idx))
    point_id = {}
    for i, xyz in enumerate(start["points"]):
        track = pycolmap.Track()
        for im, idx in tracks.get(i, []):
            track.add_element(im, idx)
        point_id[i] = rec.add_point3D(np.asarray(xyz, dtype=float), track)
    return rec, point_id


def state_of(rec, point_id, n_cam, n_rig):
    """COLMAP's end state back in rigcal's parameterisation."""
    rig = rec.rig(1)
    ref_from_cam = []
    for c in range(n_cam):
        if c == 0:
            R, t = np.eye(3), np.zeros(3)
        else:
            s = rig.sensor_from_rig(pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=c + 1))
            R, t = inverse(s.rotation.matrix(), s.translation)
        ref_from_cam.append(list(R.ravel()) + list(t))
    world_from_ref = []
    for k in range(n_rig):
        f = rec.frame(k + 1).rig_from_world
        R, t = inverse(f.rotation.matrix(), f.translation)
        world_from_ref.append(list(R.ravel()) + list(t))
    points = [list(rec.point3D(point_id[i]).xyz) for i in range(len(point_id))]
    return {"ref_from_cam": ref_from_cam, "world_from_ref": world_from_ref, "points": points}


def solve_colmap(doc, threads):
    rec, point_id = build(doc)
    tol = doc["tolerances"]
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = False
    opts.refine_principal_point = False
    opts.refine_extra_params = False
    opts.refine_rig_from_world = True
    opts.refine_sensor_from_rig = True
    opts.print_summary = False
    so = opts.ceres.solver_options
    so.max_num_iterations = tol["max_iterations"]
    so.function_tolerance = tol["function"]
    so.parameter_tolerance = tol["parameter"]
    so.gradient_tolerance = tol["gradient"]
    so.num_threads = threads
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    for c in rec.cameras:
        config.set_constant_cam_intrinsics(c)
    config.set_constant_rig_from_world_pose(1)  # frame 0: rigcal's held rig pose
    adjuster = pycolmap.create_default_bundle_adjuster(opts, config, rec)
    t0 = time.perf_counter()
    summary = adjuster.solve()
    seconds = time.perf_counter() - t0
    ceres = summary.ceres_summary
    n_cam, n_rig = len(doc["start"]["ref_from_cam"]), len(doc["start"]["world_from_ref"])
    return {
        "seconds": seconds,
        "iterations": ceres.num_successful_steps + ceres.num_unsuccessful_steps,
        "reported_cost": ceres.final_cost,
        "linear_solver": str(ceres.linear_solver_type_used).split(".")[-1],
        "termination": str(ceres.termination_type).split(".")[-1],
        "state": state_of(rec, point_id, n_cam, n_rig),
    }


def extrinsic_gap_mm(a, b):
    """Largest translation difference between two solutions' extrinsics, after bringing
    b to a's scale (scale is a free gauge direction of this problem for both solvers)."""
    ta = [pose(p)[1] for p in a["ref_from_cam"]]
    tb = [pose(p)[1] for p in b["ref_from_cam"]]
    s = np.linalg.norm(ta[1]) / np.linalg.norm(tb[1])
    return 1e3 * max(np.linalg.norm(x - s * y) for x, y in zip(ta, tb))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", default="50,200,1000")
    ap.add_argument("--rigcal", default="target/release/rigcal")
    ap.add_argument("--threads", default="1,2", help="Ceres thread counts to run")
    ap.add_argument("--repeat", type=int, default=1, help="runs per solver; the median time is shown")
    args = ap.parse_args()
    ks = [int(k) for k in args.poses.split(",")]
    threads = [int(t) for t in args.threads.split(",")]
    print(
        f"pycolmap {pycolmap.__version__}; rigcal {args.rigcal}; "
        f"seconds = median of {args.repeat} run(s) of the solve alone",
        flush=True,
    )
    header = f"{'K':>5} {'solver':<28} {'seconds':>8} {'iters':>6} {'final cost':>14} {'rescored':>14} {'vs rigcal':>10} {'Δext mm':>8}"
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in ks:
            times = []
            for _ in range(args.repeat):
                subprocess.run(
                    [args.rigcal, "bench", "speed", "--poses", str(k), "--export", tmp],
                    check=True,
                    stdout=subprocess.DEVNULL,
                )
                path = os.path.join(tmp, f"ba_{k}.json")
                with open(path) as f:
                    doc = json.load(f)
                os.remove(path)
                times.append(doc["rigcal"]["seconds"])
            r = doc["rigcal"]
            r["seconds"] = float(np.median(times))
            ours = cost(doc, r["final"])
            start = cost(doc, doc["start"])
            rows.append(
                f"{k:>5} {f'rigcal ({os.cpu_count()} cores)':<28} {r['seconds']:>8.3f} {r['iterations']:>6} "
                f"{r['final_cost']:>14.6e} {ours:>14.6e} {1.0:>10.4f} {0.0:>8.3f}"
            )
            for t in threads:
                runs = [solve_colmap(doc, t) for _ in range(args.repeat)]
                c = runs[-1]
                c["seconds"] = float(np.median([x["seconds"] for x in runs]))
                theirs = cost(doc, c["state"])
                rows.append(
                    f"{k:>5} {'COLMAP ' + c['linear_solver'] + f' ({t}t)':<28} {c['seconds']:>8.3f} "
                    f"{c['iterations']:>6} {c['reported_cost']:>14.6e} {theirs:>14.6e} "
                    f"{theirs / ours:>10.4f} {extrinsic_gap_mm(r['final'], c['state']):>8.3f}"
                )
                print(f"K={k}: start cost {start:.6e}; {c['termination']}", file=sys.stderr, flush=True)
    print(header)
    for row in rows:
        print(row)


if __name__ == "__main__":
    main()
