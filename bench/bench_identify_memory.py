"""Benchmark: peak memory and time of ``qube-identify`` against the number of training episodes.

The paper's 28 training episodes (imported from the dataset) are repeated, as hard links under new
names (``qube-identify`` reads a file named twice once), to 28, 112 and 448 episodes; each size is
identified in a fresh process with the issue's lifting::

    qube-identify --train ... --test <the 20 test episodes> --poly 2 --delays 40 \\
        --rbf thin-plate --rbf-centers 50 --alpha 1e-4

Printed per size: wall and CPU time (the child's user + system time: the machine is shared, and
other processes' load changes the wall time by several times between runs), the CPU time per
added training episode from the previous size (the run's fixed cost, imports and the 20 test
episodes' predictions, left out) and its ratio to the first such step (target: within 1.3, time
linear in the data), peak RSS (``ru_maxrss`` of the child) and its ratio to the smallest size's
(target: 448 within 1.3 of 28: memory flat in the number of episodes).

Usage::

    python bench/bench_identify_memory.py [--sizes 28 112 448] [--dataset DIR] [--work DIR] [--lifting OPTIONS]
        [-- EXTRA qube-identify OPTIONS]
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

DEFAULT_DATASET = Path(
    os.environ.get(
        "QUBE_DATASET_DIR", Path(__file__).resolve().parents[2] / "shared" / "datasets" / "qube_servo_20230828"
    )
)
LIFTING = ["--poly", "2", "--delays", "40", "--rbf", "thin-plate", "--rbf-centers", "50", "--alpha", "1e-4"]

CHILD = r"""
import json, resource, sys, time
from qube_koopman.identify.cli.identify import main
argv = json.loads(sys.argv[1])
start = time.perf_counter()
status = main(argv)
usage = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"status": status, "seconds": time.perf_counter() - start,
                  "cpu_seconds": usage.ru_utime + usage.ru_stime, "peak_rss_mb": usage.ru_maxrss / 1024}))
"""


def logs(dataset: Path, work: Path) -> tuple[list[Path], list[Path]]:
    """The paper's split of the imported dataset (imported once into ``work/logs``)."""
    folder = work / "logs"
    if not folder.is_dir():
        subprocess.run(
            ["qube-import", *map(str, sorted(dataset.glob("*.csv"))), "--out", str(folder), "-q"], check=True
        )
    files = sorted(folder.glob("*.mcap"))
    return files[:28], files[28:]


def repeated(train: list[Path], n: int, work: Path) -> list[Path]:
    """``n`` training files: the 28 repeated as hard links under new names."""
    folder = work / f"train_{n}"
    folder.mkdir(exist_ok=True)
    out = []
    for i in range(n):
        source = train[i % len(train)]
        link = folder / f"r{i // len(train):03d}_{source.name}"
        if not link.exists():
            os.link(source, link)
        out.append(link)
    return out


def measure(train: list[Path], test: list[Path], out: Path, options: list[str]) -> dict:
    argv = ["--train", *map(str, train), "--test", *map(str, test), *options, "--out", str(out), "-q"]
    done = subprocess.run([sys.executable, "-c", CHILD, json.dumps(argv)], capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    """Run each size in a fresh process and print the table."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[28, 112, 448])
    p.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    p.add_argument(
        "--work", type=Path, default=None, help="folder for the links and outputs (default: a temporary one)"
    )
    p.add_argument(
        "--lifting",
        default=" ".join(LIFTING),
        help="the lifting and alpha options, in one string (default: %(default)s); e.g. the folds' "
        "memory: '--poly 2 --delays 20 --alpha-sweep 1e-6 1e-2 4'",
    )
    p.add_argument("extra", nargs="*", help="more qube-identify options, after --")
    args = p.parse_args()
    if not args.dataset.is_dir():
        sys.exit(f"dataset not found: {args.dataset} (set QUBE_DATASET_DIR or pass --dataset)")
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_identify_memory_"))
    work.mkdir(parents=True, exist_ok=True)
    train, test = logs(args.dataset, work)
    rows = []
    for n in args.sizes:
        started = time.perf_counter()
        result = measure(repeated(train, n, work), test, work / f"out_{n}", shlex.split(args.lifting) + args.extra)
        rows.append((n, result, time.perf_counter() - started))
        print(f"{n} episodes: {result}", flush=True)
    base = rows[0][1]
    # CPU seconds per episode added since the previous size: the fixed cost cancels.
    steps = [None] + [(r["cpu_seconds"] - q["cpu_seconds"]) / (n - m) for (m, q, _), (n, r, _) in zip(rows, rows[1:])]
    print(
        f"\n{'training episodes':>18} {'wall s':>8} {'CPU s':>8} {'CPU s/added episode':>20} {'x first step':>13} "
        f"{'peak RSS MB':>12} {'x smallest':>11}"
    )
    for (n, r, _), step in zip(rows, steps):
        per, ratio = ("", "") if step is None else (f"{step:.3f}", f"{step / steps[1]:.2f}")
        print(
            f"{n:>18} {r['seconds']:>8.1f} {r['cpu_seconds']:>8.1f} {per:>20} {ratio:>13} "
            f"{r['peak_rss_mb']:>12.0f} {r['peak_rss_mb'] / base['peak_rss_mb']:>11.2f}"
        )
    print(
        f"targets: peak RSS at the largest within 1.3 x the smallest; CPU s per added episode within 1.3 x "
        f"the first step's. Files in {work}"
    )


if __name__ == "__main__":
    sys.exit(main())
