"""K-step predictions: what they add to a fit's time, and their scores against the horizon, in the same run.

Target: K-step scores at two horizons (``qube-identify --horizon 0.1,1``: the disturbance model fitted
on the training episodes, every test episode predicted at both horizons from its measurements) add at
most 50 % to a ``qube-identify`` command. Each case runs ``qube-identify``'s ``main`` in this process
(imports paid once, by a warm-up run that is not counted) without and with ``--horizon``, alternating,
``--repeat`` times, both with ``--interval 0`` (the intervals' own cost is ``bench_interval_cost.py``'s);
the medians, their ratio, the disturbance the fit chose and the K-step R^2 per horizon and channel are
printed beside the free run's. Then the default and linear cases again as commands, each run in a
fresh process: what a user waits for, the imports the K-step path adds included. The machine is
shared: only the medians and their ratio mean something.

Cases: the default lifting, the design page's linear one and the search's lifting on the paper's split
(28 training episodes, 20 test); with ``--soft DIR`` also both trained on the paper's 28 and tested on the
soft controller's episodes, and with ``--entry E`` the disturbance's entry point set by hand (``--disturbance E``)
instead of chosen on the training episodes.

Usage: python bench/bench_kstep.py --data DIR [--soft DIR] [--repeat N] [--entry E]
(DIR: the paper's 48 episodes as .mcap logs, e.g. qube-import <the dataset's CSV folder> --out DIR)
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_search import timed_run  # noqa: E402  (one qube-identify run in this process: seconds, report.json)
from bench_interval_cost import SEARCH_LIFTING, bench_logs  # noqa: E402

HORIZONS = "0.1,1"
#: The design page's plant: an affine lifting, whose K-step predictions are a filter (no window simulated per start).
LINEAR_LIFTING = "--poly 1 --delays 35 --const"


def _free_run_r2(report: dict) -> str:
    """The free run's mean R^2 per channel (theta / alpha), from its per-episode scores if the report has them."""
    test = report.get("test") or {}
    return f"{test.get('r2_mean', float('nan')):.4f}"


def measure(label: str, argv: list[str], repeat: int, entry: str | None) -> None:
    """Time ``argv`` without and with K-step scores, alternating; print the medians, the ratio and the scores."""
    ahead = ["--horizon", HORIZONS] + ([] if entry is None else ["--disturbance", entry])
    base = [*argv, "--interval", "0"]
    timed_run(base)  # warm-up: imports, not counted
    without, with_ = [], []
    report: dict = {}
    for _ in range(repeat):
        without.append(timed_run(base)[0])
        seconds, report = timed_run([*base, *ahead])
        with_.append(seconds)
    plain, scored = statistics.median(without), statistics.median(with_)
    disturbance = report.get("disturbance", {})
    model = disturbance.get("model") or {}
    horizons = report.get("ahead", {}).get("horizons", {})
    scores = "; ".join(
        f"{h} s {' / '.join(f'{v:.4f}' for v in s['r2_mean'])} (worst {' / '.join(f'{v:.4f}' for v in s['r2_worst'])})"
        for h, s in horizons.items()
    )
    print(
        f"{label:<40}{plain:>8.1f} s{scored:>8.1f} s{100 * (scored / plain - 1):>7.0f} %   disturbance "
        f"{disturbance.get('entry')} (q {model.get('q', 0):.3g}); K-step R^2 theta / alpha: {scores}; "
        f"free run {_free_run_r2(report)}",
        flush=True,
    )


def command_seconds(argv: list[str]) -> float:
    """Seconds one ``qube-identify`` command takes in a fresh process, its imports included."""
    with tempfile.TemporaryDirectory() as tmp:
        started = time.perf_counter()
        subprocess.run(
            [sys.executable, "-m", "qube_koopman.identify.cli.identify", *argv, "--out", str(Path(tmp) / "o"), "-q"],
            check=True,
            stdout=subprocess.DEVNULL,
        )
        return time.perf_counter() - started


def measure_commands(label: str, argv: list[str], repeat: int) -> None:
    """The same as :func:`measure` with each run a command of its own (what a user waits for, imports included)."""
    base = [*argv, "--interval", "0"]
    without, with_ = [], []
    for _ in range(repeat):
        without.append(command_seconds(base))
        with_.append(command_seconds([*base, "--horizon", HORIZONS]))
    plain, scored = statistics.median(without), statistics.median(with_)
    print(f"{label:<40}{plain:>8.2f} s{scored:>8.2f} s{100 * (scored / plain - 1):>7.0f} %", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="folder of the 48 imported .mcap logs")
    parser.add_argument("--soft", type=Path, help="folder of the soft-controller .mcap logs: also fits tested on them")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each, the median quoted (default 3)")
    parser.add_argument(
        "--entry",
        choices=["input", "theta", "alpha", "none"],
        help="the disturbance's entry point (--disturbance); default: chosen on the training episodes",
    )
    args = parser.parse_args()
    _, train, test, soft = bench_logs(args.data, args.soft, args.repeat)
    print(f"median of {args.repeat}; target: --horizon {HORIZONS} adds at most 50 %")
    print(f"{'case':<40}{'without':>10}{'with':>10}{'added':>9}")
    cases = [
        ("default lifting, paper test", []),
        ("linear lifting, paper test", LINEAR_LIFTING.split()),
        ("search's lifting, paper test", SEARCH_LIFTING.split()),
    ]
    for label, flags in cases:
        measure(label, ["--train", *train, "--test", *test, *flags], args.repeat, args.entry)
    print(f"\nas commands, each in a fresh process (imports included), median of {args.repeat}")
    for label, flags in cases[:2]:
        measure_commands(label, ["--train", *train, "--test", *test, *flags], args.repeat)
    for label, flags in cases if soft else []:
        measure(
            label.replace("paper test", "soft episodes"),
            ["--train", *train, "--test", *soft, *flags],
            args.repeat,
            args.entry,
        )


if __name__ == "__main__":
    main()
