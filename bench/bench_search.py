"""Speed of the lifting search (``qube-identify --search``) against a fixed fit, in the same run.

Target: the paper-split search (28 training episodes, with the twin's transfer probes) in at most
60 s on a quiet 2-core machine, and at most 8 times a fixed fit (``--delays 20``) of the same
logs timed in the same run (and, for reference, against a fixed fit of the lifting the search
recommends, with its refit flags). Both run as a user runs them (``qube-identify``'s ``main``, every
core), each timed ``--repeat`` times (the median is quoted: the machine is shared). The
search's report.json says where its time went; printed per stage: the wall time, the time spent
lifting the stage's shared liftings before its candidates ran, and the candidates' summed time
spent on statistics, fits, predictions, offsets, probe fits and probe scoring (summed over the
workers, so the sums can exceed the wall time), and the probes' simulation.

With ``--soft DIR`` (the soft-controller episodes as .mcap logs) it also times the searches over two
controllers' logs against a fixed fit of the same logs, in the same run: the paper's 28 training
episodes with the first five soft episodes (tested on the other five), then with the last five.

Usage: python bench/bench_search.py --data DIR [--soft DIR] [--repeat N] [--no-screen]
(DIR: the paper's 48 episodes as .mcap logs, e.g. qube-import <the dataset's CSV folder> --out DIR)
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import statistics
import tempfile
import time
from pathlib import Path

from qube_koopman.identify.cli.identify import main as identify_main
from qube_koopman.identify.model_selection.ranking import TIMING_KEYS


def timed_run(argv: list[str]) -> tuple[float, dict]:
    """Seconds one ``qube-identify`` run took, and its report.json."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        started = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):  # the command's summary lines: the table says it
            status = identify_main([*argv, "--out", str(out), "-q"])
        seconds = time.perf_counter() - started
        if status != 0:
            raise SystemExit(f"qube-identify {' '.join(argv)} failed with exit status {status}")
        return seconds, json.loads((out / "report.json").read_text())


def mixed_searches(rig_train: list[str], soft: list[str], repeat: int) -> None:
    """The searches over the rig's training logs and half the soft ones, each beside a fixed fit of the
    same logs timed in the same run (the ratio the search must keep with two controllers)."""
    if len(soft) < 4:
        raise SystemExit(f"--soft: expected the soft controller's episodes, found {len(soft)}")
    half = len(soft) // 2
    print(f"\n{'two controllers (rig 28 + soft half)':<40}{'fixed':>8}{'search':>9}{'ratio':>8}  winner, test R^2")
    for label, train, test in (
        ("+ first half, test the second", soft[:half], soft[half:]),
        ("+ second half, test the first", soft[half:], soft[:half]),
    ):
        argv = ["--train", *rig_train, *train, "--test", *test]
        fixed = statistics.median(timed_run([*argv, "--delays", "20"])[0] for _ in range(repeat))
        runs = [timed_run([*argv, "--search"]) for _ in range(repeat)]
        seconds, report = statistics.median(r[0] for r in runs), runs[-1][1]
        print(
            f"{label:<40}{fixed:>6.1f} s{seconds:>7.1f} s{seconds / fixed:>7.1f}x  "
            f"{report['search']['winner']['label']}, {report['test']['r2_mean']:.4f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="folder of the 48 imported .mcap logs")
    parser.add_argument("--repeat", type=int, default=1, help="runs of each, the median quoted (default 1)")
    parser.add_argument(
        "--soft",
        type=Path,
        help="folder of the soft-controller .mcap logs: also time the searches over both controllers' logs",
    )
    parser.add_argument(
        "--no-screen",
        action="store_true",
        help="time the search without screening (every candidate evaluated in full, as before successive halving)",
    )
    args = parser.parse_args()
    logs = [str(p) for p in sorted(args.data.glob("*.mcap"))]
    if len(logs) != 48:
        raise SystemExit(f"{args.data}: expected the paper's 48 logs, found {len(logs)}")
    fixed, search, report = [], [], None
    no_screen = Path(tempfile.mkdtemp()) / "no-screen.toml"  # the default space, every candidate in full
    no_screen.write_text("n_finalists = 0\n")
    for _ in range(args.repeat):
        fixed.append(timed_run([*logs, "--split", "paper", "--delays", "20"])[0])
        seconds, report = timed_run(
            [*logs, "--split", "paper", "--search", *(["--search-space", str(no_screen)] if args.no_screen else [])]
        )
        search.append(seconds)
    fixed_s, search_s = statistics.median(fixed), statistics.median(search)
    print(f"{'measure':<52}{'value':>10}{'target':>12}")
    print(f"{'fixed fit (--delays 20), median of ' + str(len(fixed)):<52}{fixed_s:>8.1f} s")
    print(f"{'search, median of ' + str(len(search)):<52}{search_s:>8.1f} s{'<= 60 s':>12}")
    print(f"{'search / fixed fit':<52}{search_s / fixed_s:>9.1f}x{'<= 8x':>12}")
    # The same ratio against a fixed fit of the lifting the search recommends (its refit flags): what the
    # search adds to fitting the model it ends with.
    flags = report["search"]["winner"]["flags"].split()
    winner = statistics.median(timed_run([*logs, "--split", "paper", *flags])[0] for _ in range(args.repeat))
    print(f"{'fixed fit of the winning lifting, median of ' + str(args.repeat):<52}{winner:>8.1f} s")
    print(f"{'search / fixed fit of the winner':<52}{search_s / winner:>9.1f}x")
    timing = report["search"]["timing"]
    print(
        f"\ntime of the last search (s): probes simulated in {timing['probe_simulation']:.1f}, "
        f"search {timing['search']:.1f}"
    )
    keys = ("shared_statistics", *TIMING_KEYS)
    print("n: candidates evaluated in full; out: screened out (their screens' time is in the sums)")
    print(f"{'stage':<10}{'n':>3}{'out':>4}{'wall':>8}" + "".join(f"{k:>18}" for k in keys))
    for stage, t in timing["stages"].items():
        print(
            f"{stage:<10}{t['candidates']:>3}{t.get('screened_out', 0):>4}{t['wall']:>8.1f}"
            + "".join(f"{t[k]:>18.1f}" for k in keys)
        )
    if args.soft is not None:
        mixed_searches(logs[:28], sorted(str(p) for p in args.soft.glob("*.mcap")), args.repeat)
    search = report["search"]
    winner = search["winner"]
    print(
        f"\nwinner: {winner['label']}, alpha {winner['alpha']:g}, CV R^2 {winner['cv_r2']:.4f}, "
        f"transfer R^2 {winner['transfer_r2']:.4f}; paper test R^2 {report['test']['r2_mean']:.4f}"
    )
    if "screening" in search:
        print(f"screening: {search['screening']['description']}")
        for c in search["screened"]:
            objective = "diverged" if c["objective"] is None else f"{c['objective']:.4f}"
            print(f"  screened out ({c['stage']}): {c['label']}, screen objective {objective}")


if __name__ == "__main__":
    main()
