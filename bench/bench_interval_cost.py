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

Measured (2 quiet cores of an AMD EPYC, median of 3, ``--members 5``; without, with, added; the
calibrations' time; then the same with 5 bootstrap refits instead of 20; the default twin with a delay
per recording session, so the soft episodes' bands also take their own gains' probes):

| case | without | with | added | calibrations | 5 refits: with, added |
|---|---|---|---|---|---|
| default lifting, paper test | 0.5 s | 1.2 s | 159 % | held-out 0.2 s | 0.9 s, 102 % |
| search's lifting, paper test | 5.5 s | 12.1 s | 120 % | held-out 2.9 s | 9.4 s, 71 % |
| default lifting, soft episodes | 0.4 s | 1.9 s | 332 % | held-out 0.2 s, probes 1.0 s | 1.4 s, 207 % |
| search's lifting, soft episodes | 7.0 s | 22.1 s | 214 % | held-out 3.6 s, probes 9.3 s | 18.8 s, 168 % |
| search, paper split (``--search``) | 46.6 s | 51.1 s | 10 % | held-out 2.6 s | |

The search meets the target; a single fit does not. Fewer refits barely move the bands (paper test,
search's lifting: pooled coverage 0.968 / 0.956 with 20, 0.959 / 0.953 with 5, 0.966 / 0.953 with 2,
at 8.5 s), but the held-out calibration alone, a prediction of the training episodes held out in
turn, costs about half of a fit without intervals.

With ``--members B [B ...]`` each fit is also timed with B bootstrap refits instead of the default 20,
a row each with its pooled coverage: what trimming that source of the band saves and costs.

Usage: python bench/bench_interval_cost.py --data DIR [--soft DIR] [--repeat N] [--search] [--members B ...]
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
SEARCH_LIFTING = "--poly 1 --trig --delays 35 --rbf thin-plate --rbf-centers 25 --friction --alpha 1e-5 --offsets alpha"


def bench_logs(data: Path, soft_folder: Path | None, repeat: int) -> tuple[list[str], list[str], list[str], list[str]]:
    """The paper's 48 logs, its 28 training and 20 test logs, and the soft controller's logs (a SystemExit naming
    what is wrong: another count of logs, an empty soft folder, fewer than one repeat)."""
    logs = [str(p) for p in sorted(data.glob("*.mcap"))]
    if len(logs) != 48:
        raise SystemExit(f"{data}: expected the paper's 48 logs, found {len(logs)}")
    if repeat < 1:
        raise SystemExit("--repeat must be at least 1")
    soft = [] if soft_folder is None else [str(p) for p in sorted(soft_folder.glob("*.mcap"))]
    if soft_folder is not None and not soft:
        raise SystemExit(f"{soft_folder}: no .mcap logs")
    return logs, logs[:28], logs[28:], soft


def measure(label: str, argv: list[str], repeat: int, members: list[int] | None = None) -> None:
    """Time ``argv`` without and with intervals, alternating; print the medians and what was added.

    ``members``: also with these numbers of bootstrap refits (``--interval-members``), a row each.
    """
    timed_run([*argv, "--interval", "0"])  # warm-up: imports and the probe cache, not counted
    variants = [(label, [])] + [(f"  {m} members", ["--interval-members", str(m)]) for m in members or []]
    without: list[float] = []
    with_: dict[str, list[float]] = {name: [] for name, _ in variants}
    reports: dict[str, dict] = {}
    for _ in range(repeat):
        without.append(timed_run([*argv, "--interval", "0"])[0])
        for name, flags in variants:
            seconds, reports[name] = timed_run([*argv, *flags])
            with_[name].append(seconds)
    plain = statistics.median(without)
    for name, _ in variants:
        banded = statistics.median(with_[name])
        intervals = reports[name].get("intervals", {})
        parts = ", ".join(f"{k} {v:.1f} s" for k, v in intervals.get("seconds", {}).items())
        pooled = intervals.get("pooled", {})
        coverage = " / ".join(f"{v:.3f}" for v in pooled.get("coverage", {}).values())
        worst = " / ".join(f"{v:.3f}" for v in pooled.get("worst_episode_coverage", {}).values())
        print(
            f"{name:<44}{plain:>8.1f} s{banded:>8.1f} s{100 * (banded / plain - 1):>8.0f} %   {parts}; "
            f"coverage {coverage} (worst {worst})",
            flush=True,
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="folder of the 48 imported .mcap logs")
    parser.add_argument(
        "--soft",
        type=Path,
        help="folder of the soft-controller .mcap logs: also time fits "
        "tested on them (their bands calibrated on the twin's probes)",
    )
    parser.add_argument("--repeat", type=int, default=3, help="runs of each, the median quoted (default 3)")
    parser.add_argument("--search", action="store_true", help="also time the search (minutes per run)")
    parser.add_argument(
        "--members",
        type=int,
        nargs="+",
        metavar="B",
        help="also time each fit's intervals with "
        "B bootstrap refits (--interval-members) instead of the default, a row each",
    )
    args = parser.parse_args()
    logs, train, test, soft = bench_logs(args.data, args.soft, args.repeat)
    print(f"median of {args.repeat}; target: intervals add at most 20 %")
    print(
        f"{'case':<44}{'without':>10}{'with':>10}{'added':>10}   the intervals' calibrations; pooled coverage "
        "theta / alpha (worst episode)"
    )
    cases = [("default lifting, paper test", []), ("search's lifting, paper test", SEARCH_LIFTING.split())]
    for label, flags in cases:
        measure(label, ["--train", *train, "--test", *test, *flags], args.repeat, args.members)
    for label, flags in cases if soft else []:
        measure(
            label.replace("paper test", "soft episodes"),
            ["--train", *train, "--test", *soft, *flags],
            args.repeat,
            args.members,
        )
    if args.search:
        measure("search, paper split", [*logs, "--split", "paper", "--search"], args.repeat)


if __name__ == "__main__":
    main()
