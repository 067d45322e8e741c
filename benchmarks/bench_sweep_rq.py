"""Wall time of one sweep fanned out to 1 and 2 RQ workers, and on the embedded backend.

Each run gets a fresh Redis, data directory and `polydda serve` (RQ backend) with K
`polydda worker`s, started and registered before the clock starts; the sweep goes out as K
shares: one parent job of K children (`service.cli.client.sweep_parent`, what `polydda sweep
--server URL --jobs K` runs), and the clock stops when the merged document is written. The
embedded backend (2 job processes) runs the same sweep in 2 shares. Every run must give
the same numbers (all but each realisation's own wall time).
Run: `python -m benchmarks.bench_sweep_rq [--mode analytic|dda] [--n N]` (needs
redis-server; the helpers that start the processes are the service tests' own).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

from service.cli.client import sweep_parent
from tests.service_helpers import RedisServer, Server, wait_until, worker_command

ROOT = Path(__file__).resolve().parents[1]


def sweep_scene(n: int, mode: str) -> dict[str, Any]:
    """The paper's wedge with φ ~ Normal(25°, 5°), seed 2026 (as tests/test_sweep.py)."""
    scene = json.loads((ROOT / "examples" / "wedge.json").read_text())
    scene["sweep"] = {"n": n, "seed": 2026, "friction_angle": {"mean": 25, "sd": 5},
                      "mode": mode}
    return scene


def on_rq(scene: dict[str, Any], k: int, tmp: Path) -> tuple[float, dict[str, Any]]:
    """Wall time (s) and merged document of the sweep on `k` RQ workers."""
    import subprocess

    data = tmp / f"rq{k}" / "data"
    data.mkdir(parents=True)
    with RedisServer(data.parent) as redis:
        env = {**os.environ, "POLYDDA_DATA_DIR": str(data), "POLYDDA_REDIS_URL": redis.url}
        logs = [open(data.parent / f"w{i}.log", "ab") for i in range(k)]  # noqa: SIM115
        workers = [subprocess.Popen(worker_command("--name", f"bench{i}-{os.getpid()}"),
                                    env=env, stdout=f, stderr=subprocess.STDOUT) for i, f in
                   enumerate(logs)]
        try:
            with Server(data, POLYDDA_BACKEND="rq", POLYDDA_REDIS_URL=redis.url) as srv, \
                    httpx.Client(base_url=srv.url, timeout=60) as c:
                wait_until(lambda: c.get("/health").json()["workers"] == k, 60, "workers")
                t0 = time.perf_counter()
                doc = sweep_parent(c, scene, k, data.parent / "out", poll=0.2)
                return time.perf_counter() - t0, doc
        finally:
            for w in workers:
                w.terminate()
            for w in workers:
                w.wait(30)
            for f in logs:
                f.close()


def on_embedded(scene: dict[str, Any], k: int, tmp: Path) -> tuple[float, dict[str, Any]]:
    """Wall time (s) and merged document of the sweep in `k` shares on `polydda serve`
    with `k` embedded job processes."""
    data = tmp / f"embedded{k}" / "data"
    data.mkdir(parents=True)
    with Server(data, POLYDDA_MAX_WORKERS=str(k)) as srv, \
            httpx.Client(base_url=srv.url, timeout=60) as c:
        t0 = time.perf_counter()
        doc = sweep_parent(c, scene, k, data.parent / "out", poll=0.2)
        return time.perf_counter() - t0, doc


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mode", choices=("analytic", "dda"), default="analytic")
    p.add_argument("--n", type=int, default=10000, help="realisations (default 10000)")
    args = p.parse_args()
    scene = sweep_scene(args.n, args.mode)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        runs = {"rq, 1 worker": on_rq(scene, 1, tmp), "rq, 2 workers": on_rq(scene, 2, tmp),
                "embedded, 2 processes": on_embedded(scene, 2, tmp)}
    print(f"sweep of {args.n} realisations ({args.mode}), load average "
          f"{os.getloadavg()[0]:.1f} at the end")
    one = runs["rq, 1 worker"][0]
    for name, (wall, doc) in runs.items():
        each = [r["wall_time"] for r in doc["realisations"] if "wall_time" in r]
        per = f"   {sum(each) / len(each):6.1f} s per realisation" if each else ""
        print(f"  {name:24s} {wall:8.1f} s   ×{one / wall:.2f} of 1 worker   "
              f"PoF {doc[args.mode]['probability_of_failure']:.6f}{per}")
    # every number but the realisations' own wall times
    docs = [{"aggregate": doc[args.mode], "analytic": doc.get("analytic"),
             "realisations": [{k: v for k, v in r.items() if k != "wall_time"}
                              for r in doc["realisations"]]} for _, doc in runs.values()]
    same = all(d == docs[0] for d in docs)
    print(f"  identical numbers (aggregates and every realisation's FS, trials, status): "
          f"{same}")

if __name__ == "__main__":
    main()
