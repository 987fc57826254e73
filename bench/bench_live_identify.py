"""Identification while recording (``qube-run --identify``): the cost of adding an episode, and the loop's lateness.

Targets: adding one 20 s episode to the model (read its log, predict and score it with the model of the
episodes before it, fold its statistics in and refit) takes at most 0.1 s of CPU with the default lifting
and at most 1 s with the search's lifting; the loop's lateness p99 while refits run is no worse than
without them.

1. ``--episodes`` episodes of ``--duration`` s are collected on the twin (free-running) into a temporary folder.
2. Each lifting's :class:`~qube_koopman.identify.live.IncrementalIdentifier` adds them one at a time, as the
   live sink does; the CPU time of the thread doing it (``time.thread_time``) is taken per episode. The
   reference approach, refitting from every log so far (``qube-identify``'s fit, ``fit`` on the episodes read
   again), is timed for the last episode in the same run: their ratio is printed.
3. ``qube-run --realtime`` runs ``--rt-episodes`` episodes without and with ``--identify`` (the search's
   lifting: the costlier refit, running on its worker thread during the next episode); the lateness p99 and
   the overruns of each run are printed. The machine is shared: compare the two rows of the same run.

Usage: python bench/bench_live_identify.py [--episodes N] [--duration S] [--rt-episodes N] [--rt-duration S]
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from qube_koopman.identify.cli.identify import live_fit_options
from qube_koopman.identify.data.logs import load_logs
from qube_koopman.core.blas import limited_blas_threads
from qube_koopman.identify.live import IncrementalIdentifier, score_and_add

DEFAULT_FLAGS = ""
SEARCH_FLAGS = "--poly 1 --trig --delays 35 --rbf thin-plate --rbf-centers 25 --friction --alpha 1e-5"
TARGETS = {"default": 0.1, "search": 1.0}


def collect(out: Path, n: int, duration: float, seed: int = 7) -> list[Path]:
    """``n`` free-running episodes on the twin."""
    argv = ["qube-run", "--episodes", str(n), "--duration", f"{duration:g}", "--seed", str(seed), "--out", str(out)]
    subprocess.run([*argv, "-q", "--n-jobs", "1"], check=True, capture_output=True)
    return sorted(out.glob("*.mcap"))


def cpu_per_episode(paths: list[Path], flags: str) -> tuple[list[float], float, float]:
    """CPU seconds of each add (read, score, add) after the first; the last add's and a full refit's CPU."""
    fit = live_fit_options(flags)
    ident = IncrementalIdentifier(fit.lifting, fit.method, fit.alpha)
    with limited_blas_threads(1):  # as the live sink runs: one core
        per = [score_and_add(ident, path, fit.skip).cpu_seconds for path in paths]
        start = time.thread_time()  # the reference: the model refitted from every log so far
        batch = IncrementalIdentifier(fit.lifting, fit.method, fit.alpha)
        for log in load_logs(paths, skip=fit.skip):
            batch.add(log)
        batch.refit_exact(skip=fit.skip)
        return per[1:], per[-1], time.thread_time() - start


LATE = re.compile(r"lateness p50 [\d.]+ us, p99 ([\d.]+) us, max ([\d.]+) us(?:; (\d+) overruns)?")


def lateness(out: Path, n: int, duration: float, identify: str | None) -> tuple[float, float, int]:
    """Lateness p99 and max (us) and overruns of a --realtime run, with or without --identify."""
    argv = ["qube-run", "--realtime", "--episodes", str(n), "--duration", f"{duration:g}", "--seed", "5"]
    argv += ["--out", str(out), "-q"] + ([f"--identify={identify}"] if identify is not None else [])
    done = subprocess.run(argv, capture_output=True, text=True)
    found = LATE.search(done.stdout)
    if done.returncode != 0 or found is None:
        sys.exit(f"qube-run failed ({done.returncode}): {done.stderr.strip()[-500:]}")
    return float(found.group(1)), float(found.group(2)), int(found.group(3) or 0)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--episodes", type=int, default=8)
    p.add_argument("--duration", type=float, default=20.0)
    p.add_argument("--rt-episodes", type=int, default=3)
    p.add_argument("--rt-duration", type=float, default=10.0)
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        paths = collect(Path(tmp) / "logs", args.episodes, args.duration)
        print(f"{len(paths)} episodes of {args.duration:g} s on the twin")
        head = f"{'lifting':<10}{'CPU per add: median':>22}{'max':>9}{'target':>9}"
        print(f"{head}{'last add':>10}{'full refit':>12}{'ratio':>8}")
        for name, flags in (("default", DEFAULT_FLAGS), ("search", SEARCH_FLAGS)):
            per, last, full = cpu_per_episode(paths, flags)
            verdict = "PASS" if statistics.median(per) <= TARGETS[name] else "FAIL"
            print(
                f"{name:<10}{statistics.median(per):>20.3f} s{max(per):>7.3f} s{TARGETS[name]:>7.1f} s"
                f"{last:>8.3f} s{full:>10.3f} s{full / last:>7.1f}x  {verdict}"
            )
        rows = []
        for label, identify in (("without --identify", None), ("with --identify (search lifting)", SEARCH_FLAGS)):
            rows.append((label, *lateness(Path(tmp) / label.split()[0], args.rt_episodes, args.rt_duration, identify)))
        print(f"\n--realtime, {args.rt_episodes} x {args.rt_duration:g} s: lateness p99, max, overruns")
        for label, p99, worst, overruns in rows:
            print(f"{label:<36}{p99:>10.1f} us{worst:>10.1f} us{overruns:>6}")
        ok = rows[1][1] <= max(rows[0][1] * 1.1, rows[0][1] + 50.0)
        print(f"p99 with refits no worse than without (within 10 % or 50 us of it): {'PASS' if ok else 'FAIL'}")


if __name__ == "__main__":
    main()
