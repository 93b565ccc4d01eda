"""Round-trip of rigcal's exports through the parsers of the tools that read them.

Format checks, not peers: PyYAML with the type rules of Kalibr's ConfigReader (camchain),
cv2.FileStorage and cv2.stereoRectify (OpenCV), xml.etree with the URDF joint chain and the
ROS 2 static transforms recomposed, PyYAML with camera_calibration_parsers' field names
(camera_info), pycolmap.read_rig_config (COLMAP >= 3.12). Every transform read back is
composed and compared with the result document's ref_from_cam.

usage: check_exports.py RIGCAL_BINARY WORKDIR
"""
import json
import math
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import yaml

PRESETS = ["lebraly-5.1", "car-planar-uturn", "car-planar", "car-planar-loop", "car-bump", "pure-translation", "single-axis", "wu-table2", "car-hall", "car-hall-planar", "car-hall-isolated", "fisheye-handheld"]
TOL = 1e-9


def run(binary, *args):
    return subprocess.run([binary, *args], capture_output=True, text=True)


def fail(where, why):
    raise SystemExit(f"FAIL {where}: {why}")


def truth_of(result):
    return {e["camera"]: np.array(e["ref_from_cam"]) for e in result["extrinsics"]}


def close(where, got, want):
    err = np.abs(np.asarray(got, float) - np.asarray(want, float)).max()
    if not err <= TOL:
        fail(where, f"transform differs from the result by {err:.3g}")


def check_kalibr(where, text, cams, truth, session):
    data = yaml.safe_load(text)  # PyYAML: YAML 1.1, what Kalibr reads with
    if sorted(data) != sorted(f"cam{i}" for i in range(len(cams))):
        fail(where, f"top-level keys {sorted(data)}")
    ref_from = None
    for i, cam_id in enumerate(cams):
        c = data[f"cam{i}"]
        if not isinstance(c["rostopic"], str):
            fail(where, "rostopic has to be a string")
        if c["camera_model"] != "pinhole":
            fail(where, f"camera_model {c['camera_model']!r}")
        k = c["intrinsics"]
        if len(k) != 4 or not all(isinstance(x, float) for x in k) or k[0] < 0 or k[1] < 0:
            fail(where, f"invalid focalLength (2 floats): {k!r}")
        if k[2] < 0 or k[3] < 0:
            fail(where, f"invalid principalPoint: {k!r}")
        n = {"radtan": 4, "equidistant": 4, "fov": 1, "none": 0}.get(c["distortion_model"])
        d = c["distortion_coeffs"]
        if n is None or len(d) != n or not all(isinstance(x, float) for x in d):
            fail(where, f"distortion {c['distortion_model']!r} {d!r}")
        r = c["resolution"]
        if len(r) != 2 or not all(type(x) is int for x in r):
            fail(where, f"invalid resolution {r!r}")
        if not all(type(j) is int and 0 <= j < len(cams) and j != i for j in c["cam_overlaps"]):
            fail(where, f"cam_overlaps {c['cam_overlaps']!r}")
        spec = session["cameras"][i]
        if r != [spec["width"], spec["height"]]:
            fail(where, f"resolution {r} vs {spec['width']}x{spec['height']}")
        if i == 0:
            ref_from = truth[cam_id]
        else:
            t = np.array(c["T_cn_cnm1"], dtype=float)
            if t.shape != (4, 4) or not all(isinstance(x, float) for row in c["T_cn_cnm1"] for x in row):
                fail(where, "T_cn_cnm1 is not a 4x4 float matrix")
            ref_from = ref_from @ np.linalg.inv(t)
        close(f"{where} cam{i} chain", ref_from, truth[cam_id])
        close(f"{where} cam{i} T_ref_cam", c["T_ref_cam"], truth[cam_id])


def check_opencv(where, path, cams, truth):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        fail(where, "cv2.FileStorage cannot open it")
    read = {}
    for cam_id in cams:
        m = {k: fs.getNode(f"{cam_id}_{k}").mat() for k in ["K", "D", "size", "R", "T"]}
        m["model"] = fs.getNode(f"{cam_id}_model").string()
        if any(v is None for v in m.values()) or m["K"].shape != (3, 3) or m["R"].shape != (3, 3):
            fail(where, f"{cam_id}: K, D, size, R, T, model not all read: {m}")
        cam_from_ref = np.eye(4)
        cam_from_ref[:3, :3], cam_from_ref[:3, 3] = m["R"], m["T"].ravel()
        close(f"{where} {cam_id}", np.linalg.inv(cam_from_ref), truth[cam_id])
        read[cam_id] = m
    a, b = read[cams[0]], read[cams[1]]
    r = b["R"] @ a["R"].T
    t = b["T"] - r @ a["T"]
    size = tuple(int(x) for x in a["size"].ravel())
    if a["model"] == b["model"] == "pinhole":
        out = cv2.stereoRectify(a["K"], a["D"], b["K"], b["D"], size, r, t)
    elif a["model"] == b["model"] == "fisheye":
        out = cv2.fisheye.stereoRectify(a["K"], a["D"], b["K"], b["D"], size, r, t, flags=0)
    else:
        return
    if not all(np.isfinite(x).all() for x in out[:5]):
        fail(where, "stereoRectify gave non-finite matrices")


def rpy_matrix(r, p, y):
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def check_urdf(where, text, cams, ref, truth):
    root = ET.fromstring(text)
    links = {l.get("name") for l in root.iter("link")}
    if links != {f"{c}_optical_frame" for c in cams}:
        fail(where, f"links {sorted(links)}")
    for j in root.iter("joint"):
        if j.find("parent").get("link") != f"{ref}_optical_frame":
            fail(where, "a joint whose parent is not the reference camera")
        child = j.find("child").get("link").removesuffix("_optical_frame")
        o = j.find("origin")
        m = np.eye(4)
        m[:3, :3] = rpy_matrix(*map(float, o.get("rpy").split()))
        m[:3, 3] = list(map(float, o.get("xyz").split()))
        # rpy round-trips to ~1e-12 only; the translation is exact.
        err = np.abs(m - truth[child]).max()
        if not err <= 1e-9:
            fail(where, f"{child}: joint differs from the result by {err:.3g}")


def check_colmap(where, path, cams, ref, truth):
    rigs = pycolmap.read_rig_config(str(path))
    if len(rigs) != 1 or len(rigs[0].cameras) != len(cams):
        fail(where, f"{len(rigs)} rigs")
    for cam_id, rc in zip(cams, rigs[0].cameras):
        if rc.image_prefix != f"{cam_id}/":
            fail(where, f"image_prefix {rc.image_prefix!r}")
        if rc.ref_sensor != (cam_id == ref):
            fail(where, f"{cam_id}: ref_sensor {rc.ref_sensor}")
        if cam_id != ref:
            m = np.eye(4)
            m[:3, :] = rc.cam_from_rig.matrix()
            close(f"{where} {cam_id}", np.linalg.inv(m), truth[cam_id])
        if rc.camera is None:
            fail(where, f"{cam_id}: camera model not read")


def quat_matrix(x, y, z, w):
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def check_ros2(where, text, cams, ref, truth):
    root = ET.fromstring(text)
    nodes = list(root.iter("node"))
    if len(nodes) != len(cams) - 1:
        fail(where, f"{len(nodes)} static_transform_publisher nodes for {len(cams)} cameras")
    for n in nodes:
        if (n.get("pkg"), n.get("exec")) != ("tf2_ros", "static_transform_publisher"):
            fail(where, f"node {n.attrib}")
        a = n.get("args").split()
        kv = dict(zip(a[::2], a[1::2]))
        if kv["--frame-id"] != f"{ref}_optical_frame":
            fail(where, f"parent {kv['--frame-id']}")
        child = kv["--child-frame-id"].removesuffix("_optical_frame")
        m = np.eye(4)
        q = [float(kv[k]) for k in ["--qx", "--qy", "--qz", "--qw"]]
        if abs(np.linalg.norm(q) - 1) > 1e-12:
            fail(where, f"quaternion norm {np.linalg.norm(q)}")
        m[:3, :3] = quat_matrix(*q)
        m[:3, 3] = [float(kv[k]) for k in ["--x", "--y", "--z"]]
        close(f"{where} {child}", m, truth[child])


def check_camera_info(where, text, spec):
    info = yaml.safe_load(text)
    need = ["image_width", "image_height", "camera_name", "camera_matrix", "distortion_model",
            "distortion_coefficients", "rectification_matrix", "projection_matrix"]
    if sorted(info) != sorted(need):
        fail(where, f"fields {sorted(info)}")
    if (info["image_width"], info["image_height"]) != (spec["width"], spec["height"]):
        fail(where, "image size")
    if info["camera_name"] != spec["id"]:
        fail(where, f"camera_name {info['camera_name']!r}")
    for name, (r, c) in [("camera_matrix", (3, 3)), ("rectification_matrix", (3, 3)), ("projection_matrix", (3, 4))]:
        m = info[name]
        if (m["rows"], m["cols"]) != (r, c) or len(m["data"]) != r * c or not all(isinstance(x, float) for x in m["data"]):
            fail(where, f"{name} {m}")
    k = spec["intrinsics"]
    # (to an ulp: the session's pixel convention is converted on the way in and out)
    want = [k["fx"], 0.0, k["cx"], 0.0, k["fy"], k["cy"], 0.0, 0.0, 1.0]
    if not np.allclose(info["camera_matrix"]["data"], want, rtol=1e-12, atol=0):
        fail(where, "camera_matrix is not the session's intrinsics")
    n = {"plumb_bob": 5, "equidistant": 4}.get(info["distortion_model"])
    d = info["distortion_coefficients"]
    if n is None or d["cols"] != n or len(d["data"]) != n:
        fail(where, f"distortion {info['distortion_model']} {d}")


def check_session(binary, where, session_path, refused=()):
    result = json.loads(run(binary, "calibrate", str(session_path)).stdout)
    if result["status"] == "failed":
        # A failed calibration never leaves as a file another tool loads as one.
        for fmt in ["kalibr", "opencv", "urdf", "colmap", "ros2"]:
            p = run(binary, "calibrate", str(session_path), "--format", fmt)
            if "nothing to export" not in p.stderr or json.loads(p.stdout)["status"] != "failed":
                fail(f"{where} {fmt}", f"a failed calibration was exported: {p.stdout[:200]!r}")
        print(f"ok {where}: failed, exported as JSON only")
        return
    session = json.loads(Path(session_path).read_text())
    cams = [c["id"] for c in session["cameras"]]
    ref = result["reference_camera"]
    truth = truth_of(result)
    out = Path(session_path).parent
    for fmt in ["kalibr", "opencv", "urdf", "colmap", "ros2"]:
        p = run(binary, "calibrate", str(session_path), "--format", fmt)
        if fmt in refused:
            if p.returncode == 0 or "--format" not in p.stderr:
                fail(f"{where} {fmt}", f"expected a refusal naming --format, got {p.returncode} {p.stderr!r}")
            continue
        if p.returncode not in (0, 3):
            fail(f"{where} {fmt}", p.stderr)
        path = out / f"export.{fmt}"
        path.write_text(p.stdout)
        if fmt == "kalibr":
            check_kalibr(f"{where} kalibr", p.stdout, cams, truth, session)
        elif fmt == "opencv":
            check_opencv(f"{where} opencv", path, cams, truth)
        elif fmt == "urdf":
            check_urdf(f"{where} urdf", p.stdout, cams, ref, truth)
        elif fmt == "ros2":
            check_ros2(f"{where} ros2", p.stdout, cams, ref, truth)
        else:
            check_colmap(f"{where} colmap", path, cams, ref, truth)
    for spec in session["cameras"]:
        p = run(binary, "calibrate", str(session_path), "--format", "camera_info", "--camera", spec["id"])
        if p.returncode not in (0, 3):
            fail(f"{where} camera_info {spec['id']}", p.stderr)
        check_camera_info(f"{where} camera_info {spec['id']}", p.stdout, spec)
    p = run(binary, "calibrate", str(session_path), "--format", "camera_info")
    if p.returncode == 0 or "--camera" not in p.stderr:
        fail(f"{where} camera_info", f"without --camera: expected a refusal naming --camera, got {p.stderr!r}")
    print(f"ok {where}: {len(cams)} cameras")


def tf_tree(edges, root):
    """Every frame's pose in `root`, composed along parent -> child edges {child: (parent, m)}."""
    out = {root: np.eye(4)}
    while len(out) <= len(edges):
        grew = False
        for child, (parent, m) in edges.items():
            if child not in out and parent in out:
                out[child] = out[parent] @ m
                grew = True
        if not grew:
            fail("tf tree", f"frames not connected to {root}: {sorted(set(edges) - set(out))}")
    return out


def check_vehicle_frame(binary, where, work, session_path, result):
    """Exports in a vehicle model's frame (--frame vehicle): every camera's pose in the
    vehicle frame read back from each format equals vehicle_from_ref @ ref_from_cam."""
    session = json.loads(Path(session_path).read_text())
    cams = [c["id"] for c in session["cameras"]]
    ref = result["reference_camera"]
    v = np.eye(4)
    v[:3, :3] = rpy_matrix(math.radians(-90.0), math.radians(1.5), math.radians(-90.0))
    v[:3, 3] = [1.8, -0.02, 1.35]
    model = {
        "reference_camera": ref,
        "cameras": [
            {"id": e["camera"], "translation": e["translation"], "quaternion_wxyz": e["quaternion_wxyz"],
             **({} if e["camera"] == ref else {"tolerance": {"translation_mm": 50.0, "rotation_deg": 2.0}})}
            for e in result["extrinsics"]
        ],
        "vehicle_from_ref": {"translation": list(v[:3, 3]), "rpy_deg": [-90.0, 1.5, -90.0]},
    }
    model["cameras"][0]["translation"] = [0.0, 0.0, 0.0]
    model["cameras"][0]["quaternion_wxyz"] = [1.0, 0.0, 0.0, 0.0]
    model_path = work / f"{where}-model.json"
    model_path.write_text(json.dumps(model))
    want = {c: v @ m for c, m in truth_of(result).items()}
    args = ["--frame", "vehicle", "--vehicle-model", str(model_path)]
    for fmt in ["kalibr", "opencv", "urdf", "ros2", "colmap"]:
        p = run(binary, "calibrate", str(session_path), "--format", fmt, *args)
        if fmt == "colmap":
            if p.returncode == 0 or "ref_sensor" not in p.stderr:
                fail(f"{where} colmap vehicle", f"expected a refusal, got {p.returncode} {p.stderr!r}")
            continue
        if p.returncode not in (0, 3):
            fail(f"{where} {fmt} vehicle", p.stderr)
        if "from nominal" not in p.stderr:
            fail(f"{where} {fmt} vehicle", f"no deviation from nominal printed: {p.stderr!r}")
        if fmt == "kalibr":
            data = yaml.safe_load(p.stdout)
            for i, cam_id in enumerate(cams):
                t = data[f"cam{i}"]["T_vehicle_cam"]
                if not all(isinstance(x, float) for row in t for x in row):
                    fail(f"{where} kalibr vehicle", "T_vehicle_cam is not a 4x4 float matrix")
                close(f"{where} kalibr vehicle cam{i}", t, want[cam_id])
            check_kalibr(f"{where} kalibr vehicle", p.stdout, cams, truth_of(result), session)
        elif fmt == "opencv":
            path = work / f"{where}-vehicle.yaml"
            path.write_text(p.stdout)
            check_opencv(f"{where} opencv vehicle", path, cams, want)
        else:
            root = ET.fromstring(p.stdout)
            edges = {}
            if fmt == "urdf":
                for j in root.iter("joint"):
                    o = j.find("origin")
                    m = np.eye(4)
                    m[:3, :3] = rpy_matrix(*map(float, o.get("rpy").split()))
                    m[:3, 3] = list(map(float, o.get("xyz").split()))
                    edges[j.find("child").get("link")] = (j.find("parent").get("link"), m)
            else:
                for n in root.iter("node"):
                    a = n.get("args").split()
                    kv = dict(zip(a[::2], a[1::2]))
                    m = np.eye(4)
                    m[:3, :3] = quat_matrix(*[float(kv[k]) for k in ["--qx", "--qy", "--qz", "--qw"]])
                    m[:3, 3] = [float(kv[k]) for k in ["--x", "--y", "--z"]]
                    edges[kv["--child-frame-id"]] = (kv["--frame-id"], m)
            poses = tf_tree(edges, "base_link")
            for cam_id in cams:
                err = np.abs(poses[f"{cam_id}_optical_frame"] - want[cam_id]).max()
                if not err <= 1e-9:
                    fail(f"{where} {fmt} vehicle {cam_id}", f"base_link chain differs by {err:.3g}")
    p = run(binary, "calibrate", str(session_path), "--format", "urdf", "--frame", "vehicle")
    if p.returncode == 0 or "--vehicle-model" not in p.stderr:
        fail(f"{where} vehicle", f"--frame vehicle without a model: {p.stderr!r}")
    print(f"ok {where}: vehicle frame")


def main():
    binary, work = sys.argv[1], Path(sys.argv[2])
    for preset in PRESETS:
        d = work / preset
        subprocess.run([binary, "synth", "--preset", preset, "--seed", "5", "--noise", "0.3", "--out", str(d)], check=True, capture_output=True)
        check_session(binary, preset, d / "session.json")
        if preset in ("lebraly-5.1", "car-bump", "fisheye-handheld"):
            result = json.loads(run(binary, "calibrate", str(d / "session.json")).stdout)
            check_vehicle_frame(binary, preset, work, d / "session.json", result)
    # Awkward but valid ids: YAML keywords and numbers, XML comment breakers, dots.
    base = json.loads((work / "lebraly-5.1" / "session.json").read_text())
    ids = [c["id"] for c in base["cameras"]]
    for names, refused in [(["yes", "null"], ()), (["a--b", "No"], ()), (["1e5", "a.b_c-d"], ("opencv",))]:
        text = json.dumps(base)
        for old, new in zip(ids, names):
            text = text.replace(f'"{old}"', f'"{new}"')
        d = work / ("ids-" + "-".join(names))
        d.mkdir(parents=True, exist_ok=True)
        (d / "session.json").write_text(text)
        check_session(binary, f"ids {names}", d / "session.json", refused)
    print("format checks passed")


if __name__ == "__main__":
    main()
