#!/usr/bin/env python3
"""Load benchmark of the service (not a timed test; numbers go to docs/performance.md).

1. With a calibration job running on the one worker, `GET /v1/jobs/{id}` under wrk:
   requests/s and latency percentiles.
2. 50 concurrent uploads of distinct 2 MB PNG images: all succeed?, wall time, throughput.

Usage: python3 benches/load.py [--bin target/release/rigcal] [--duration 10]
       python3 benches/load.py --postgres postgres://postgres@127.0.0.1:PORT --s3-bucket B
(the second on PostgreSQL + S3, after `source scripts/backends.sh; start_backends`).
Needs wrk (Debian package `wrk`). Standard library only otherwise.
"""
import argparse, json, os, re, struct, subprocess, sys, tempfile, time, zlib
import urllib.request

from backend import add_args, describe, store_env
from concurrent.futures import ThreadPoolExecutor


def png_gray(w, h, seed):
    """An 8-bit grey PNG of noise (incompressible: the file is ~w*h bytes)."""
    rnd = os.urandom(w * h) if seed is None else (bytes((i * 2654435761 + seed) >> 13 & 255 for i in range(w * h)))
    raw = b"".join(b"\x00" + rnd[y * w:(y + 1) * w] for y in range(h))
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xffffffff)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 1)) + chunk(b"IEND", b""))


def req(method, url, key, body=None, ctype="application/json"):
    r = urllib.request.Request(url, data=body, method=method,
                               headers={"Authorization": f"Bearer {key}", "Content-Type": ctype})
    with urllib.request.urlopen(r, timeout=300) as resp:
        return resp.status, json.loads(resp.read() or b"null")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bin", default="target/release/rigcal")
    ap.add_argument("--duration", type=int, default=10)
    ap.add_argument("--connections", type=int, default=16)
    add_args(ap)
    a = ap.parse_args()
    data = tempfile.mkdtemp(prefix="rigcal-load-")
    env = store_env(a, "load")
    print(describe(a))
    key = subprocess.check_output([a.bin, "apikey", "create", "--tenant", "load", "--data-dir", data],
                                  env=env, stderr=subprocess.DEVNULL).decode().strip()
    srv = subprocess.Popen([a.bin, "serve", "--bind", "127.0.0.1:0", "--data-dir", data, "--workers", "1"],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    try:
        base = srv.stdout.readline().decode().strip().removeprefix("rigcal listening on ")
        # A long job (16-pose loop, ~6 s) several times over, to keep one core busy.
        synth = tempfile.mkdtemp()
        subprocess.check_call([a.bin, "synth", "--preset", "car-planar-loop", "--noise", "0.5", "--out", synth],
                              stderr=subprocess.DEVNULL)
        manifest = open(os.path.join(synth, "session.json"), "rb").read()
        _, sess = req("POST", f"{base}/v1/sessions", key, manifest)
        jobs = [req("POST", f"{base}/v1/jobs", key, json.dumps({"session_id": sess["id"]}).encode())[1]["id"]
                for _ in range(6)]
        while req("GET", f"{base}/v1/jobs/{jobs[0]}", key)[1]["status"] != "running":
            time.sleep(0.05)
        out = subprocess.check_output(["wrk", "-t2", f"-c{a.connections}", f"-d{a.duration}s", "--latency",
                                       "-H", f"Authorization: Bearer {key}", f"{base}/v1/jobs/{jobs[0]}"]).decode()
        busy = [req("GET", f"{base}/v1/jobs/{j}", key)[1]["status"] for j in jobs]
        running = f"{busy.count('running')} running, {busy.count('queued')} queued"
        rps = float(re.search(r"Requests/sec:\s+([\d.]+)", out).group(1))
        pct = dict(re.findall(r"\s+(50|75|90|99)%\s+([\d.]+\w+)", out))
        non2xx = re.search(r"Non-2xx or 3xx responses: (\d+)", out)
        print(f"GET /v1/jobs/{{id}} while a job runs (wrk -t2 -c{a.connections} -d{a.duration}s)")
        print(f"  requests/s {rps:.0f}   p50 {pct.get('50')}   p90 {pct.get('90')}   p99 {pct.get('99')}   "
              f"non-2xx {non2xx.group(1) if non2xx else 0}   (jobs at the end: {running})")

        # 50 concurrent 2 MB uploads.
        w, h, n = 1600, 1300, 50
        frames = [{"index": k, "images": {"cam": f"cam/{k:03}.png"}} for k in range(n)]
        cam = {"id": "cam", "model": "pinhole", "width": w, "height": h,
               "intrinsics": {"fx": 1000.0, "fy": 1000.0, "cx": (w - 1) / 2, "cy": (h - 1) / 2}}
        m2 = {"reference_camera": "cam", "cameras": [cam, dict(cam, id="cam2")], "frames": frames}
        _, s2 = req("POST", f"{base}/v1/sessions", key, json.dumps(m2).encode())
        images = [png_gray(w, h, None) for _ in range(n)]
        size = sum(len(b) for b in images)
        def put(k):
            t = time.perf_counter()
            st, body = req("PUT", f"{base}/v1/sessions/{s2['id']}/images/cam/{k}", key, images[k], "image/png")
            return st, time.perf_counter() - t
        t0 = time.perf_counter()
        with ThreadPoolExecutor(n) as ex:
            res = list(ex.map(put, range(n)))
        wall = time.perf_counter() - t0
        ok = sum(1 for st, _ in res if st == 200)
        lat = sorted(d for _, d in res)
        print(f"{n} concurrent uploads of {size / n / 1e6:.2f} MB PNGs ({w}x{h})")
        print(f"  ok {ok}/{n}   wall {wall:.2f} s   throughput {size / wall / 1e6:.1f} MB/s   "
              f"median {lat[n // 2]:.2f} s   max {lat[-1]:.2f} s")
        _, s2v = req("GET", f"{base}/v1/sessions/{s2['id']}", key)
        print(f"  images_received {s2v['images_received']}")
    finally:
        srv.terminate()
        srv.wait()


if __name__ == "__main__":
    sys.exit(main())
