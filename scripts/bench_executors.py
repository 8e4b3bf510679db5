"""Evaluation throughput with the local process pool and with Ray on the same cores, side by side in one run, and
the throughput projected for a cluster from the measured costs (docs/scale.md, "Measured").

    .venv/bin/python scripts/bench_executors.py [--system gsmn] [--episodes 8] [--repeats 3] [--workers 2]

Starts a Ray head of its own on 127.0.0.1 with --workers CPUs (no dashboard, its workers at the local pool's
priority: --worker-niceness) unless --ray-address is given, and stops it at the end. Per repeat (the two backends
in alternating order, so drifting load on a shared machine falls on both alike): `evaluate` of the same episodes
on each backend, checked to give the same records; episodes per second end to end (worker start-up included)
and steady (from the first round of results on). Then the costs a projection needs: a no-op job's round trip on
each backend (the driver's cost per episode), and a weight broadcast on Ray (ray.put of a checkpoint's files
once, and each actor's first fetch). Medians of the repeats; the load average is printed beside them.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")  # a one-node cluster on 127.0.0.1, not the host IP

from gsmn.config import preset  # noqa: E402
from gsmn.evaluation import checkpoint_path, evaluate  # noqa: E402
from gsmn.executor import ExecutorOptions, LocalExecutor, echo, no_setup  # noqa: E402


def start_head(cpus: int, niceness: int) -> tuple[subprocess.Popen, str, str]:
    temp = tempfile.mkdtemp(prefix="gsb")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ray = Path(sys.executable).with_name("ray")
    head = subprocess.Popen([str(ray), "start", "--head", "--block", "--port", str(port), "--node-ip-address",
                             "127.0.0.1", "--num-cpus", str(cpus), "--object-store-memory", str(300 * 2**20),
                             "--include-dashboard=false", "--disable-usage-stats", "--temp-dir", temp],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            env={**os.environ, "RAY_worker_niceness": str(niceness)})
    address = f"127.0.0.1:{port}"
    for _ in range(180):
        probe = subprocess.run([sys.executable, "-c", f"import ray; ray.init(address={address!r})"],
                               capture_output=True)
        if probe.returncode == 0:
            return head, address, temp
        if head.poll() is not None:
            break
        time.sleep(1)
    head.send_signal(signal.SIGTERM)
    raise SystemExit("the Ray head did not come up")


def timed_eval(system: str, ids: list[int], config, workers: int, options: ExecutorOptions) -> dict:
    stamps = []
    t0 = time.perf_counter()
    records = evaluate(system, ids, config, workers=workers, executor_options=options,
                       on_episode=lambda r: stamps.append(time.perf_counter()))
    total = time.perf_counter() - t0
    first_round = stamps[workers - 1] if len(stamps) > workers else stamps[0]
    steady = (len(stamps) - workers) / max(stamps[-1] - first_round, 1e-9) if len(stamps) > workers else math.nan
    return {"records": records, "end_to_end": len(ids) / total, "steady": steady, "seconds": total}


def round_trip(executor, jobs: int) -> float:
    list(executor.map(echo, range(4)))  # started
    t0 = time.perf_counter()
    list(executor.map(echo, range(jobs)))
    return (time.perf_counter() - t0) / jobs


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--system", default="gsmn")
    parser.add_argument("--checkpoint", default=None)
    parser.add_argument("--preset", default="paper")
    parser.add_argument("--episodes", type=int, default=8, help="test environments per backend and repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--ray-address", default=None, help="an existing cluster (default: start one here)")
    parser.add_argument("--worker-niceness", type=int, default=0,
                        help="the niceness Ray adds to its workers on the head started here (Ray's own default is "
                             "15: on a machine busy with other work its actors then get the CPU last; 0 = the "
                             "local pool's priority, for a like-for-like comparison)")
    parser.add_argument("--json", default=None, help="write the measurements here")
    args = parser.parse_args()

    import ray

    from gsmn.executor_ray import RayExecutor, fetch_seconds

    config = preset(args.preset)
    ids = list(range(70, 70 + args.episodes))
    head, temp = None, None
    address = args.ray_address
    if address is None:
        head, address, temp = start_head(args.workers, args.worker_niceness)
    try:
        ray.init(address=address, log_to_driver=False)
        backends = {"local": ExecutorOptions("local"), "ray": ExecutorOptions("ray", address)}
        runs: dict[str, list[dict]] = {"local": [], "ray": []}
        loads = [os.getloadavg()[0]]
        for rep in range(args.repeats):
            for name in (("local", "ray") if rep % 2 == 0 else ("ray", "local")):
                runs[name].append(timed_eval(args.system, ids, config, args.workers, backends[name]))
                print(f"repeat {rep + 1} {name}: {runs[name][-1]['end_to_end']:.3f} episodes/s end to end, "
                      f"{runs[name][-1]['steady']:.3f} steady", file=sys.stderr)
                loads.append(os.getloadavg()[0])
            assert runs["local"][-1]["records"] == runs["ray"][-1]["records"], "the backends flew differently"

        ckpt = checkpoint_path(args.system, args.checkpoint)
        ckpt_bytes = sum(p.stat().st_size for p in ckpt.iterdir() if p.is_file()) if ckpt and ckpt.is_dir() else 0
        with LocalExecutor(args.workers, no_setup, ()) as local:
            rt_local = statistics.median(round_trip(local, 200) for _ in range(args.repeats))
        with RayExecutor(args.workers, no_setup, (), address=address) as remote:
            rt_ray = statistics.median(round_trip(remote, 200) for _ in range(args.repeats))
            puts, fetches = [], []
            if ckpt_bytes:
                for _ in range(args.repeats):
                    t0 = time.perf_counter()
                    shared = remote.share(ckpt)
                    puts.append(time.perf_counter() - t0)
                    fetches.append(max(remote.map(fetch_seconds, [None] * args.workers, shared)))
    finally:
        if ray.is_initialized():
            ray.shutdown()
        if head is not None:
            head.send_signal(signal.SIGTERM)
            head.wait(timeout=60)
            shutil.rmtree(temp, ignore_errors=True)

    med = {name: {k: statistics.median(r[k] for r in rs) for k in ("end_to_end", "steady")}
           for name, rs in runs.items()}
    put = statistics.median(puts) if puts else 0.0
    fetch = statistics.median(fetches) if fetches else 0.0
    episode_seconds = args.workers / med["ray"]["steady"]  # one worker's seconds per episode, on Ray
    result = {
        "system": args.system, "preset": args.preset, "episodes": args.episodes, "repeats": args.repeats,
        "workers": args.workers, "cpus": os.cpu_count(), "worker_niceness": args.worker_niceness,
        "load_average": {"min": min(loads), "max": max(loads)},
        "episodes_per_second": med, "ray_overhead_ratio": {k: med["local"][k] / med["ray"][k] for k in med["local"]},
        "round_trip_seconds": {"local": rt_local, "ray": rt_ray}, "checkpoint_bytes": ckpt_bytes,
        "broadcast_seconds": {"put": put, "first_fetch": fetch}, "episode_seconds_per_worker": episode_seconds,
    }
    n_d = preset("paper").dagger.rollouts_per_iteration
    projected = {}
    for machines in (1, 8, 64):
        workers = machines * args.workers
        eval_rate = min(workers / episode_seconds, 1 / rt_ray)  # the driver handles one result at a time
        waves = math.ceil(n_d / workers)
        iteration = put + fetch + waves * episode_seconds  # DAggerFM's rollouts: broadcast, then N_D episodes
        projected[machines] = {"eval_episodes_per_second": eval_rate, "dagger_rollout_seconds": iteration}
    result["projected"] = projected
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")

    print(f"{args.system} ({args.preset} preset), {args.episodes} episodes x {args.repeats} repeats on "
          f"{args.workers} workers, {os.cpu_count()} CPUs, load average {min(loads):.1f}-{max(loads):.1f}")
    print("| backend | episodes/s end to end | episodes/s steady | no-op job round trip (ms) |")
    print("|---|---|---|---|")
    for name in ("local", "ray"):
        print(f"| {name} | {med[name]['end_to_end']:.3f} | {med[name]['steady']:.3f} | "
              f"{1000 * result['round_trip_seconds'][name]:.2f} |")
    ratio = result["ray_overhead_ratio"]
    print(f"Ray's overhead (local / ray episodes per second): {ratio['end_to_end']:.3f} end to end, "
          f"{ratio['steady']:.3f} steady")
    print(f"weight broadcast: {ckpt_bytes / 2**20:.1f} MiB, ray.put {1000 * put:.1f} ms, an actor's first fetch "
          f"{1000 * fetch:.1f} ms; one episode {episode_seconds:.2f} s per worker")
    print(f"| machines ({args.workers} workers each) | eval episodes/s | DAggerFM rollouts of an iteration "
          f"(N_D = {n_d}), s |")
    print("|---|---|---|")
    for machines, p in projected.items():
        print(f"| {machines} | {p['eval_episodes_per_second']:.2f} | {p['dagger_rollout_seconds']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
