#!/usr/bin/env python3
"""Queue throughput with separate worker processes (not a timed test; numbers go to
docs/performance.md).

One API-only `rigcal serve` and N `rigcal worker --workers 1` processes on one store; a
fixed mix of synthetic jobs (16 x lebraly-5.1, ~0.04 s each, and 4 x car-planar-loop,
~4 s each) submitted at once; jobs per minute from the first submit to the last finish.

Usage:
  python3 benches/fleet.py [--bin target/release/rigcal] [--workers 1,2,4]
  python3 benches/fleet.py --postgres postgres://postgres@127.0.0.1:PORT --s3-bucket B
(the second form after `source scripts/backends.sh; start_backends`, which also exports
the AWS_* settings; a fresh database is created per row with psql).
"""
import argparse, json, os, subprocess, sys, tempfile, time
import urllib.request

from backend import add_args, describe, store_env


def req(method, url, key, body=None):
    r = urllib.request.Request(url, data=body, method=method,
                               headers={"Authorization": f"Bearer {key}", "Content-Type": "application/json"})
    with urllib.request.urlopen(r, timeout=300) as resp:
        return json.loads(resp.read() or b"null")


def synth(bin_, preset):
    out = tempfile.mkdtemp()
    subprocess.check_call([bin_, "synth", "--preset", preset, "--noise", "0.3", "--out", out],
                          stderr=subprocess.DEVNULL)
    return open(os.path.join(out, "session.json"), "rb").read()


def run(a, workers, manifests):
    data = tempfile.mkdtemp(prefix="rigcal-fleet-")
    env = store_env(a, "fleet")
    key = subprocess.check_output([a.bin, "apikey", "create", "--tenant", "fleet", "--data-dir", data],
                                  env=env, stderr=subprocess.DEVNULL).decode().strip()
    srv = subprocess.Popen([a.bin, "serve", "--bind", "127.0.0.1:0", "--data-dir", data, "--workers", "0"],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    procs = [subprocess.Popen([a.bin, "worker", "--workers", "1", "--data-dir", data], env=env,
                              stderr=subprocess.DEVNULL) for _ in range(workers)]
    try:
        base = srv.stdout.readline().decode().strip().removeprefix("rigcal listening on ")
        sessions = [req("POST", f"{base}/v1/sessions", key, m)["id"] for m in manifests]
        t0 = time.perf_counter()
        jobs = [req("POST", f"{base}/v1/jobs", key, json.dumps({"session_id": s}).encode())["id"]
                for s in sessions]
        pending = set(jobs)
        while pending:
            for j in list(pending):
                if req("GET", f"{base}/v1/jobs/{j}", key)["status"] not in ("queued", "running"):
                    pending.discard(j)
            time.sleep(0.05)
        wall = time.perf_counter() - t0
        statuses = [req("GET", f"{base}/v1/jobs/{j}", key)["status"] for j in jobs]
        return wall, statuses
    finally:
        for p in procs + [srv]:
            p.terminate()
        for p in procs + [srv]:
            p.wait()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bin", default="target/release/rigcal")
    ap.add_argument("--workers", default="1,2,4")
    add_args(ap)
    a = ap.parse_args()
    quick, slow = synth(a.bin, "lebraly-5.1"), synth(a.bin, "car-planar-loop")
    mix = [slow if k % 5 == 0 else quick for k in range(20)]
    print(f"{describe(a)}: 20 jobs (16 lebraly-5.1, 4 car-planar-loop) submitted at once")
    for n in [int(x) for x in a.workers.split(",")]:
        wall, statuses = run(a, n, mix)
        ok = statuses.count("succeeded")
        print(f"  {n} worker process(es): {wall:.1f} s, {len(mix) / wall * 60:.0f} jobs/min, {ok}/{len(mix)} succeeded")


if __name__ == "__main__":
    sys.exit(main())
