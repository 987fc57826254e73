"""Benchmark: ``qube-run --n-jobs``, the paper-sized twin run on one core against several.

Target: ``qube-run --episodes 48 --seed 1`` on the simulator (the calibrated
twin, free-running, 20 s episodes) gets faster in proportion to the cores, with the same logs.
Each row is the median wall time of ``--repeats`` whole runs as a user starts them (a fresh
process: start-up, the first episode alone while the workers start, the workers' imports,
logging), the job counts taking turns so that a load on the machine falls on each alike. The
ratio is measured in the same run against ``--n-jobs 1``; the load average is printed beside
it, since other work on the machine takes cores from the parallel run.

Usage::

    python bench/bench_run_parallel.py [--jobs 1 2] [--repeats 3] [--episodes 48]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _run(jobs: int, episodes: int, duration: float, out: Path) -> float:
    """Wall seconds of one ``qube-run`` with ``--n-jobs jobs``."""
    command = [
        sys.executable,
        "-m",
        "qube_koopman.daq.cli.run",
        "--episodes",
        str(episodes),
        "--duration",
        f"{duration:g}",
        "--seed",
        "1",
        "--n-jobs",
        str(jobs),
        "--out",
        str(out),
        "-q",
    ]
    start = time.perf_counter()
    proc = subprocess.run(command, capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"qube-run --n-jobs {jobs} failed ({proc.returncode}): {proc.stderr}")
    return elapsed


def _seeds(folder: Path) -> list[str]:
    """The logs' names without their start times, in name order (the order the episodes ran)."""
    return [p.name.split("_", 2)[2] for p in sorted(folder.glob("*.mcap"))]


def main(argv=None) -> int:
    """Run the benchmark and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--jobs", type=int, nargs="+", default=[1, 2], help="job counts to time (default 1 2)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per job count (median)")
    parser.add_argument("--episodes", type=int, default=48, help="episodes per run (default 48)")
    parser.add_argument("--duration", type=float, default=20.0, help="seconds per episode (default 20)")
    args = parser.parse_args(argv)
    jobs = sorted(set(args.jobs) | {1})

    times: dict[int, list[float]] = {n: [] for n in jobs}
    names: dict[int, list[str]] = {}
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        for repeat in range(args.repeats):
            for n in jobs if repeat % 2 == 0 else reversed(jobs):
                out = Path(tmp) / f"jobs{n}_{repeat}"
                times[n].append(_run(n, args.episodes, args.duration, out))
                names.setdefault(n, _seeds(out))
    load = max(load, os.getloadavg()[0])

    base = statistics.median(times[1])
    print(
        f"qube-run --episodes {args.episodes} --duration {args.duration:g} --seed 1 on the twin, "
        f"{os.cpu_count()} cores, median of {args.repeats} (load average up to {load:.1f})"
    )
    print(f"{'':14s}{'wall s':>10s}{'runs (s)':>26s}{'speed-up':>10s}{'per core':>10s}")
    for n in jobs:
        median = statistics.median(times[n])
        runs = " ".join(f"{t:.1f}" for t in times[n])
        print(f"{'--n-jobs ' + str(n):14s}{median:10.1f}{runs:>26s}{base / median:9.2f}x{base / median / n:10.2f}")
    same = all(names[n] == names[1] for n in jobs)
    print(f"the same logs (seeds, in name order) with every job count: {'yes' if same else 'NO'}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
