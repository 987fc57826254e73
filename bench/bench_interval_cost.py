"""What the prediction intervals add to a fit's time, and to the search's, measured in the same run.

Target: the intervals (``qube-identify``'s default ``--interval 0.95``: bootstrap refits, the held-out
calibration, every test episode's band) add at most 20 % to a fit and to the search. Each case runs
``qube-identify``'s ``main`` in this process (imports paid once, by a warm-up run that is not
counted) with ``--interval 0`` and with the default, alternating, ``--repeat`` times; the medians,
their ratio and the time the intervals' report says went into their calibrations are printed. The
machine is shared: only the medians and their ratio mean something.

Cases: the default lifting and the search's lifting on the paper's split (28 training episodes, 20
test); with ``--soft DIR`` also both trained on the paper's 28 and tested on the soft controller's
episodes (a loop the training never ran: its band is calibrated on the twin's probe episodes, read
from the probe cache after the first run); with ``--search`` the search itself on the paper's split.

Measured (2 quiet cores of an AMD EPYC, median of 3; without, with, added; the calibrations' time;
the default twin with a delay per recording session, so the soft episodes' bands also take their
own gains' probes):

| case | without | with | added | calibrations |
|---|---|---|---|---|
| default lifting, paper test | 0.8 s | 1.5 s | 87 % | held-out 0.2 s |
| search's lifting, paper test | 5.8 s | 11.9 s | 104 % | held-out 2.7 s |
| default lifting, soft episodes | 0.5 s | 1.7 s | 209 % | held-out 0.2 s, probes 0.7 s |
| search's lifting, soft episodes | 7.0 s | 21.8 s | 210 % | held-out 2.8 s, probes 7.9 s |
| search, paper split (``--search``) | 38.7 s | 45.3 s | 17 % | held-out 2.5 s |

The search meets the target; a single fit does not: its bootstrap refits' predictions of every test
episode and the held-out calibration cost about as much as the fit itself.

Usage: python bench/bench_interval_cost.py --data DIR [--soft DIR] [--repeat N] [--search]
(DIR: the paper's 48 episodes as .mcap logs, e.g. qube-import <the dataset's CSV folder> --out DIR)
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_search import timed_run  # noqa: E402  (one qube-identify run in this process: seconds, report.json)

#: The search's lifting on the paper's split (docs/lifting-search.md).
SEARCH_LIFTING = ("--poly 1 --trig --delays 35 --rbf thin-plate --rbf-centers 25 --friction --alpha 1e-5 "
                  "--offsets alpha")


def measure(label: str, argv: list[str], repeat: int) -> None:
    """Time ``argv`` without and with intervals, alternating; print the medians and what was added."""
    timed_run([*argv, "--interval", "0"])  # warm-up: imports and the probe cache, not counted
    without, with_, report = [], [], {}
    for _ in range(repeat):
        without.append(timed_run([*argv, "--interval", "0"])[0])
        seconds, report = timed_run(argv)
        with_.append(seconds)
    plain, banded = statistics.median(without), statistics.median(with_)
    spent = report.get("intervals", {}).get("seconds", {})
    parts = ", ".join(f"{k} {v:.1f} s" for k, v in spent.items())
    print(f"{label:<44}{plain:>8.1f} s{banded:>8.1f} s{100 * (banded / plain - 1):>8.0f} %   {parts}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="folder of the 48 imported .mcap logs")
    parser.add_argument("--soft", type=Path, help="folder of the soft-controller .mcap logs: also time fits "
                        "tested on them (their bands calibrated on the twin's probes)")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each, the median quoted (default 3)")
    parser.add_argument("--search", action="store_true", help="also time the search (minutes per run)")
    args = parser.parse_args()
    logs = [str(p) for p in sorted(args.data.glob("*.mcap"))]
    if len(logs) != 48:
        raise SystemExit(f"{args.data}: expected the paper's 48 logs, found {len(logs)}")
    if args.repeat < 1:
        raise SystemExit("--repeat must be at least 1")
    train, test = logs[:28], logs[28:]
    soft = [] if args.soft is None else [str(p) for p in sorted(args.soft.glob("*.mcap"))]
    if args.soft is not None and not soft:
        raise SystemExit(f"{args.soft}: no .mcap logs")
    print(f"median of {args.repeat}; target: intervals add at most 20 %")
    print(f"{'case':<44}{'without':>10}{'with':>10}{'added':>10}   the intervals' calibrations")
    cases = [("default lifting, paper test", []), ("search's lifting, paper test", SEARCH_LIFTING.split())]
    for label, flags in cases:
        measure(label, ["--train", *train, "--test", *test, *flags], args.repeat)
    for label, flags in cases if soft else []:
        measure(label.replace("paper test", "soft episodes"), ["--train", *train, "--test", *soft, *flags],
                args.repeat)
    if args.search:
        measure("search, paper split", [*logs, "--split", "paper", "--search"], args.repeat)


if __name__ == "__main__":
    main()
