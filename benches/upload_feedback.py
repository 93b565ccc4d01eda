#!/usr/bin/env python3
"""Capture feedback on upload (issue 18; not a timed test, numbers go to
docs/performance.md): a rendered car-hall capture (4 cameras, 18 frames, 72 JPEGs) is
uploaded image by image to a real `rigcal serve` (one embedded worker, as the default),
and the script measures

  - upload: first PUT -> last PUT,
  - check:  last PUT -> GET /v1/sessions/{id}/check answers 200 (complete),
  - result: last PUT -> the job (submitted once the check is complete) has its result,
            and the job's own time from claim to result,

at full speed (every PUT as soon as the previous answered) and at a capture-like pace
(`--pace`: seconds between frames, 4 images per frame). For comparison it times
`rigcal calibrate` on the same capture directory (every image detected by the job).

Usage: python3 benches/upload_feedback.py [--bin target/release/rigcal] [--size 1920x1080]
       [--seed 5] [--pace 0.5] [--capture DIR] [--quality accurate|fast]
       [--postgres URL --s3-bucket B]
Standard library only.
"""
import argparse, json, os, subprocess, tempfile, time
import urllib.error, urllib.request

from backend import add_args, describe, store_env


def req(method, url, key, body=None, ctype="application/json"):
    r = urllib.request.Request(url, data=body, method=method,
                               headers={"Authorization": f"Bearer {key}", "Content-Type": ctype})
    try:
        with urllib.request.urlopen(r, timeout=300) as resp:
            return resp.status, json.loads(resp.read() or b"null")
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"null")


def run(a, capture, pace):
    data = tempfile.mkdtemp(prefix="rigcal-feedback-")
    env = store_env(a, "feedback")
    key = subprocess.check_output([a.bin, "apikey", "create", "--tenant", "line", "--data-dir", data],
                                  env=env, stderr=subprocess.DEVNULL).decode().strip()
    srv = subprocess.Popen([a.bin, "serve", "--bind", "127.0.0.1:0", "--data-dir", data,
                            "--upload-detect-quality", a.quality],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    try:
        base = srv.stdout.readline().decode().strip().removeprefix("rigcal listening on ")
        manifest = json.load(open(os.path.join(capture, "session.json")))
        st, sess = req("POST", f"{base}/v1/sessions", key, json.dumps(manifest).encode())
        assert st == 201, sess
        sid = sess["id"]
        t0 = time.monotonic()
        for fi, frame in enumerate(manifest["frames"]):
            if pace and fi:
                time.sleep(max(0.0, t0 + fi * pace - time.monotonic()))
            for cam, path in frame["images"].items():
                body = open(os.path.join(capture, path), "rb").read()
                st, r = req("PUT", f"{base}/v1/sessions/{sid}/images/{cam}/{fi}", key, body, "image/jpeg")
                assert st == 200, r
        last = time.monotonic()
        while True:
            st, check = req("GET", f"{base}/v1/sessions/{sid}/check", key)
            if st == 200:
                break
            assert st == 409, check
            time.sleep(0.02)
        t_check = time.monotonic() - last
        body = {"session_id": sid, "options": {"detection": {"quality": a.quality}}}
        st, job = req("POST", f"{base}/v1/jobs", key, json.dumps(body).encode())
        assert st == 202, job
        while True:
            st, j = req("GET", f"{base}/v1/jobs/{job['id']}", key)
            if j["status"] in ("succeeded", "degraded", "failed", "cancelled"):
                break
            time.sleep(0.02)
        t_result = time.monotonic() - last
        st, doc = req("GET", f"{base}/v1/jobs/{job['id']}/result", key)
        det = doc.get("detection") or {}
        return {
            "upload_s": last - t0, "check_s": t_check, "result_s": t_result,
            "job_s": j.get("running_seconds"), "status": j["status"], "verdict": check["verdict"],
            "reused": det.get("images_reused"), "images": det.get("images_total"),
        }
    finally:
        srv.terminate()
        srv.wait()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bin", default="target/release/rigcal")
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--pace", type=float, default=0.5, help="seconds between frames of the paced run")
    ap.add_argument("--capture", help="a capture directory rendered before (skips the ~3 min render)")
    ap.add_argument("--quality", default="accurate", choices=["accurate", "fast"],
                    help="detection quality of the uploads, the job and `rigcal calibrate`")
    add_args(ap)
    a = ap.parse_args()
    capture = a.capture
    if not capture:
        capture = tempfile.mkdtemp(prefix="rigcal-capture-")
        subprocess.check_call([a.bin, "synth", "--preset", "car-hall", "--images", "--size", a.size,
                               "--seed", str(a.seed), "--out", capture], stderr=subprocess.DEVNULL)
    print(f"car-hall {a.size}, seed {a.seed}, 72 JPEGs; {describe(a)}; 1 embedded worker, "
          f"{os.cpu_count()} cores; detection {a.quality}")
    t = time.monotonic()
    out = subprocess.run([a.bin, "calibrate", os.path.join(capture, "session.json"),
                          "--detect-quality", a.quality],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    print(f"rigcal calibrate (detects every image itself): {time.monotonic() - t:.2f} s (exit {out.returncode})")
    for name, pace in (("full speed", 0.0), (f"paced, {a.pace} s per frame", a.pace)):
        r = run(a, capture, pace)
        print(f"{name:>26}: upload {r['upload_s']:.2f} s; last PUT -> complete check {r['check_s']:.2f} s "
              f"({r['verdict']}); -> result {r['result_s']:.2f} s ({r['status']}, job {r['job_s']:.2f} s, "
              f"{r['reused']}/{r['images']} detections reused)")


if __name__ == "__main__":
    main()
