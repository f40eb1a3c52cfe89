"""Dask references: speed-up of ``mitsuba-plugins reference`` with W workers against 1, and
a scaling estimate for larger clusters.

Renders the same reference (same seeds, same total spp) with:

* an embedded ``LocalCluster`` of 1 worker with all cores' Dr.Jit threads (the
  default), 1 worker with 1 thread, and W workers with cores / W threads each;
* a cluster started with the ``dask`` command line (``dask scheduler`` and W
  ``dask worker`` processes of one thread each), reached with ``--scheduler``, each
  worker rendering with cores / W Dr.Jit threads (``--threads``).

Reports wall time, speed-ups, the scheduling overhead per task (wall time minus the
passes' own render time, spread over the passes a worker ran), bytes returned per pass,
and from these an estimate of passes per second for 8, 64 and 512 workers. Writes
``benchmarks/results/reference_scaling.{md,json}``.

Needs the ``distributed`` extra. Run from the repository root:
``python3 -m benchmarks.reference_scaling``.
"""
from __future__ import annotations

import argparse
import datetime
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before drjit loads
import mitsuba as mi

from benchmarks.harness import device_model
from mitsuba_plugins.registry import default_variant  # noqa: E402

VARIANT = default_variant()
ROOT = Path(__file__).resolve().parents[1]
TARGET = 1.7
#: passes of the reference the cluster estimate is for
ESTIMATE_PASSES = 256


def run_reference(out: Path, args, **where) -> dict:
    from mitsuba_plugins.tools.reference import reference
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    info = reference(str(ROOT / "scenes" / f"{args.scene}.xml"), {"type": args.integrator},
                     args.spp, args.passes, out, res=args.res, variant=VARIANT,
                     progress=False, **where)
    info["wall_with_startup"] = time.perf_counter() - t0
    return info


def _summary(info: dict, workers: int) -> dict:
    per_pass = info["per_pass"]
    render = sum(p["seconds"] for p in per_pass)
    by_worker = {}
    for p in per_pass:
        by_worker.setdefault(p["worker"], []).append(p["seconds"])
    # overhead per task: what the busiest worker's wall time holds beyond its renders
    busiest = max(by_worker.values(), key=sum)
    overhead = max(0.0, info["wall_seconds"] - sum(busiest)) / len(busiest)
    steady = [s for w in by_worker.values() for s in sorted(w)[:-1] or w]  # drop compile pass
    return {"workers": workers, "wall": info["wall_seconds"],
            "wall_with_startup": info["wall_with_startup"],
            "render_seconds_sum": render, "workers_used": len(by_worker),
            "median_pass_seconds": statistics.median(steady),
            "first_pass_seconds_max": max(max(w) for w in by_worker.values()),
            "overhead_per_task": overhead}


def dask_cli_cluster(workers: int):
    """``dask scheduler`` and ``workers`` one-thread ``dask worker`` processes."""
    exe = Path(sys.executable).parent / "dask"
    scheduler = subprocess.Popen([str(exe), "scheduler", "--host", "127.0.0.1", "--port", "0",
                                  "--no-dashboard", "--scheduler-file", SCHEDULER_FILE],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 60
    while not os.path.exists(SCHEDULER_FILE) and time.time() < deadline:
        time.sleep(0.1)
    procs = [scheduler]
    for _ in range(workers):
        procs.append(subprocess.Popen(
            [str(exe), "worker", "--scheduler-file", SCHEDULER_FILE, "--nthreads", "1",
             "--nworkers", "1", "--no-dashboard"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    return procs


SCHEDULER_FILE = os.path.join(tempfile.gettempdir(), f"mitsuba-plugins-bench-{os.getpid()}.json")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="smoke")
    ap.add_argument("--integrator", default="volpath_delta")
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", type=int, default=8192)
    ap.add_argument("--passes", type=int, default=32)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 2)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "reference_scaling"))
    args = ap.parse_args()
    mi.set_variant(VARIANT)
    from distributed import Client
    from mitsuba_plugins import output
    from mitsuba_plugins.tools.reference import close, connect
    cores = os.cpu_count() or 1
    W = args.workers
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for name, workers, threads in (("1 worker, all cores (default)", 1, cores),
                                       ("1 worker, 1 thread", 1, 1),
                                       (f"{W} workers, cores / {W} threads each", W,
                                        max(1, cores // W))):
            t0 = time.perf_counter()
            client, _ = connect(workers=workers)
            start = time.perf_counter() - t0
            try:
                info = run_reference(tmp / "r", args, client=client, threads=threads)
            finally:
                close(client)
            rows[name] = _summary(info, workers)
            rows[name]["cluster_start_seconds"] = start
            print(name, f"{rows[name]['wall']:.1f} s", flush=True)
        procs = dask_cli_cluster(W)
        try:
            client = Client(scheduler_file=SCHEDULER_FILE, timeout="60s")
            client.wait_for_workers(W, timeout=120)
            address = client.scheduler.address
            info = run_reference(tmp / "r", args, client=client, threads=max(1, cores // W))
            client.close()
            rows[f"dask CLI: scheduler + {W} workers"] = _summary(info, W)
            rows[f"dask CLI: scheduler + {W} workers"]["address"] = address
            print("dask CLI", f"{info['wall_seconds']:.1f} s", flush=True)
        finally:
            for p in procs[::-1]:
                p.terminate()
            for p in procs:
                p.wait(30)
            if os.path.exists(SCHEDULER_FILE):
                os.unlink(SCHEDULER_FILE)
    bytes_per_pass = args.res * args.res * 3 * 8
    base = rows["1 worker, all cores (default)"]["wall"]
    base1 = rows["1 worker, 1 thread"]["wall"]
    overhead = statistics.median(r["overhead_per_task"] for r in rows.values())
    result = {"date": datetime.date.today().isoformat(), "cpu": device_model(VARIANT),
              "variant": VARIANT, "cores": cores, "config": vars(args), "rows": rows,
              "bytes_per_pass": bytes_per_pass, "speedup_vs_1_worker_all_cores": {
                  k: base / r["wall"] for k, r in rows.items()},
              "speedup_vs_1_worker_1_thread": {k: base1 / r["wall"] for k, r in rows.items()},
              "overhead_per_task": overhead}
    out = Path(args.out)
    output.write_json(out.with_suffix(".json"), result, indent=1)
    output.write_text(out.with_suffix(".md"), markdown(result))
    print(markdown(result))


def markdown(r: dict) -> str:
    c = r["config"]
    lines = ["# Dask references: speed-up and scaling", "",
             f"Measured {r['date']} on {r['cpu']} ({r['cores']} cores, {r['variant']}) by "
             f"`python3 -m benchmarks.reference_scaling`: `{c['scene']}` with "
             f"`{c['integrator']}` at {c['res']}x{c['res']}, {c['spp']} spp in {c['passes']} "
             "passes (one Dask task each), same seeds in every row. Wall: from submitting the "
             "first pass to the last result (cluster start-up excluded). Target: >= "
             f"{TARGET}x with 2 workers.", "",
             "| cluster | wall (s) | speed-up vs 1 worker, all cores | vs 1 worker, 1 thread | "
             "median pass (s) | first pass incl. compile (s) | overhead per task (s) |",
             "|---|---|---|---|---|---|---|"]
    for name, row in r["rows"].items():
        lines.append(f"| {name} | {row['wall']:.2f} | "
                     f"{r['speedup_vs_1_worker_all_cores'][name]:.2f}x | "
                     f"{r['speedup_vs_1_worker_1_thread'][name]:.2f}x | "
                     f"{row['median_pass_seconds']:.3f} | {row['first_pass_seconds_max']:.2f} | "
                     f"{row['overhead_per_task']:.4f} |")
    lines += ["", f"Bytes returned per pass: {r['bytes_per_pass']} (float64 RGB image); "
              f"median scheduling overhead per task: {r['overhead_per_task']:.4f} s.", "",
              "## Estimate for larger clusters (on paper)", "",
              f"A reference of {ESTIMATE_PASSES} passes of the measured size ({r['config']['spp'] // r['config']['passes']} "
              "spp each, e.g. 65536 spp at 64x64): each worker loads the scene and compiles the "
              "kernel once (its first pass, measured with compilation), then renders passes back "
              "to back at the median pass time of the one-thread workers plus the overhead per task. "
              "Wall = first pass + (rounds - 1) x (pass + overhead), rounds = ceil(passes / "
              "workers). Results cross the network once per pass (bytes above); the scheduler "
              "handles one task per pass.", "",
              "| workers | rounds | passes/s (all workers) | results into the client (MB/s) | "
              "estimated wall (s) | bound by |", "|---|---|---|---|---|---|"]
    default = next(row for name, row in r["rows"].items() if "threads each" in name)
    step = default["median_pass_seconds"] + r["overhead_per_task"]
    for n in (8, 64, 512):
        rounds = -(-ESTIMATE_PASSES // n)
        busy = min(n, ESTIMATE_PASSES)
        wall = default["first_pass_seconds_max"] + (rounds - 1) * step
        bound = ("rendering" if rounds > 2 else
                 "scene loading + kernel compilation per worker (first pass)" if n < ESTIMATE_PASSES
                 else f"too few passes: {n - ESTIMATE_PASSES} workers idle")
        lines.append(f"| {n} | {rounds} | {busy / step:.1f} | "
                     f"{busy / step * r['bytes_per_pass'] / 1e6:.1f} | {wall:.1f} | {bound} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
