"""Benchmark: peak memory (RSS) of a run against the number of planned episodes and their length.

Target: peak RSS flat within 10 % for 1 vs 10,000 planned
episodes, and for 20 s vs 1 h episodes (sim backend, free-running, MCAP log).
Each row runs in a fresh process (``ru_maxrss`` is a high-water mark):

- planned episodes: ``N`` episodes of 20 s are planned as ``qube-run`` plans
  them, and the first two run into an MCAP log (the run is then stopped: the
  memory the plan costs shows by then);
- episode length: one episode of the given length runs into an MCAP log.

The reference row is the baseline process (imports only), so the table shows
what a run adds to it.

Usage::

    python bench/bench_memory.py [--long SECONDS]    # the python of the environment the package is installed in
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, resource, sys, tempfile
from qube_koopman.daq.backends import SimBackend
from qube_koopman.daq.session import excitation_settings, load_controller, plan_episodes, run_episodes, run_seeds
from qube_koopman.daq.safety import StopRequest
from qube_koopman.daq.sinks import McapSink

episodes, seconds, run = int(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
if run:
    seeds, backend_seed = run_seeds(1, episodes)
    plans = plan_episodes(load_controller(), seeds, excitation_settings(seconds), source="bench")
    stop = StopRequest()
    done = []

    def on_result(plan, result):
        done.append(result.status)
        if len(done) == 2:
            stop.request("bench: two episodes are enough")

    with tempfile.TemporaryDirectory() as out:
        run_episodes(SimBackend(seed=backend_seed), plans, [McapSink(out)], stop=stop, on_result=on_result)
print(json.dumps({"peak_kib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
                  "episodes_run": len(done) if run else 0}))
"""


def _peak(episodes: int, seconds: float, run: bool = True) -> dict:
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(episodes), str(seconds), str(int(run))],
        capture_output=True,
        text=True,
        cwd=REPO,
        env={"PYTHONPATH": str(REPO), "PATH": ""},
        check=True,
    )
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    """Run the benchmark and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--long", type=float, default=3600.0, help="the long episode's length (s)")
    args = parser.parse_args(argv)

    base = _peak(1, 20.0, run=False)["peak_kib"]
    rows = [("baseline (imports only)", None, base)]
    pairs = []
    for label, a, b in (("planned episodes", (1, 20.0), (10_000, 20.0)), ("episode length", (1, 20.0), (1, args.long))):
        pa, pb = _peak(*a)["peak_kib"], _peak(*b)["peak_kib"]
        rows += [(f"{label}: {a[0]} x {a[1]:g} s", a, pa), (f"{label}: {b[0]} x {b[1]:g} s", b, pb)]
        pairs.append((label, pa, pb))
    print(f"{'row':<40} {'peak RSS MiB':>12} {'over baseline MiB':>18}")
    for name, _, kib in rows:
        print(f"{name:<40} {kib / 1024:>12.1f} {(kib - base) / 1024:>18.1f}")
    print()
    ok = True
    for label, pa, pb in pairs:
        ratio = pb / pa
        flat = ratio <= 1.10
        ok &= flat
        print(f"{label}: peak RSS ratio {ratio:.3f} (target <= 1.10): {'met' if flat else 'NOT met'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
