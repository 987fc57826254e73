"""The lifting search on two controllers' logs: does more data of a second controller help the model it
recommends, against the one recommended from the rig's logs alone?

    python bench/bench_mixed_search.py --rig DIR --soft DIR [--tie-standard-errors K] [--out DIR]

``--rig``: the paper's 48 episodes, ``--soft``: the ten episodes of the same rig under the softer
controller (CSV files as published, or MCAP logs). The rig-only search (the paper's 28 training
episodes) recommends one lifting; four mixed searches train on those 28 and six or five soft
episodes (soft 1-5, 6-10, and from both recording sessions 1-3 with 6-8, 3-5 with 8-10) and each
is scored on the soft episodes it did not see and the paper's 20 test episodes. Beside each, the
rig-only recommendation (its lifting and alpha, fitted on the 28) is scored on the same test logs,
so each test loop's command delay is estimated from the same logs for both. Printed per set:
the winner, mean / worst R^2 on the held-out soft episodes (with per-episode offsets, after the
1 s window) for both, and the paper test's mean.

``--tie-standard-errors K`` ranks the mixed searches with ``tie_standard_errors = K`` (a
``--search-space`` file): 0 is the largest objective alone, the default 1 the one-standard-error
rule (docs/lifting-search.md).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import shlex
import tempfile
import time
from pathlib import Path

import numpy as np

from bench_two_controllers import data_arguments, identify_report, read_datasets


#: The mixed training sets: soft episodes (0-based, sorted by name) trained on with the rig's 28.
SETS = {
    "soft 1-5": (0, 1, 2, 3, 4),
    "soft 6-10": (5, 6, 7, 8, 9),
    "soft 1-3, 6-8": (0, 1, 2, 5, 6, 7),
    "soft 3-5, 8-10": (2, 3, 4, 7, 8, 9),
}


def run(argv: list[str], out: Path) -> dict:
    """report.json of one ``qube-identify`` run without intervals (its console lines swallowed)."""
    with contextlib.redirect_stderr(io.StringIO()):
        return identify_report([*argv, "--interval", "0"], out)


def split_scores(report: dict, soft_names: set[str]) -> tuple[np.ndarray, np.ndarray]:
    """R^2 per held-out soft episode and per paper test episode."""
    scores = dict(zip(report["scored_logs"], report["test"]["r2_per_episode"]))
    soft = np.array([v for k, v in scores.items() if k in soft_names])
    return soft, np.array([v for k, v in scores.items() if k not in soft_names])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    data_arguments(p, lifting=False)
    p.add_argument("--tie-standard-errors", type=float, default=None, help="the mixed searches' tie (default: 1)")
    p.add_argument("--out", type=Path, default=None, help="keep the runs' reports here")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        root = args.out or Path(tmp)
        rig, soft = read_datasets(args, root, 10, 10)
        train, paper_test = [str(x) for x in rig[:28]], [str(x) for x in rig[28:]]
        space = []
        if args.tie_standard_errors is not None:
            (root / "space.toml").write_text(f"tie_standard_errors = {args.tie_standard_errors}\n")
            space = ["--search-space", str(root / "space.toml")]
        started = time.perf_counter()
        rig_only = run(["--train", *train, "--test", *paper_test, "--search"], root / "rig_only")
        flags = shlex.split(rig_only["search"]["winner"]["flags"])
        print(f"rig-only winner: {rig_only['search']['winner']['label']}, {shlex.join(flags)}")
        print("| training | winner | soft held-out | rig-only on them | paper test, mean | rig-only |")
        print("|---|---|---|---|---|---|")
        for label, chosen in SETS.items():
            held = [str(soft[i]) for i in range(len(soft)) if i not in chosen]
            names = {Path(h).name for h in held}
            test = ["--test", *paper_test, *held]
            tag = label.replace(" ", "").replace(",", "_")
            mixed = run(["--train", *train, *(str(soft[i]) for i in chosen), *test, "--search", *space], root / tag)
            fixed = run(["--train", *train, *test, *flags], root / f"{tag}_rig_only")
            (ms, mp), (fs, fp) = split_scores(mixed, names), split_scores(fixed, names)
            w = mixed["search"]["winner"]
            print(
                f"| rig 28 + {label} | {w['label']}, alpha {w['alpha']:g} | {ms.mean():.4f} / {ms.min():.4f} "
                f"| {fs.mean():.4f} / {fs.min():.4f} | {mp.mean():.4f} | {fp.mean():.4f} |",
                flush=True,
            )
        print(f"({time.perf_counter() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
