"""Speed of the QUBE-Servo reproduction against the naive per-fit, per-step approach.

Target: the whole reproduction, import excluded, in at most 10 s on
a 2-core machine. The sweeps run in one worker
process per core; the same code in one process is timed beside it. The reference
implementation solved an SDP per fit and
predicted about 1 ms per step (36 CPU-hours for the protocol). Here the naive
approach is: for every (fold, alpha) build the lifted snapshots and fit from
scratch, then predict each validation episode step by step with the full
lifting recomputed from the history (tests/naive_reference.py). It is timed
on a subset in the same run and extrapolated to the protocol's 2 methods x 3
folds x 180 alphas x 2 scorings.

Usage: python bench/bench_qube_reproduction.py [--data DIR_WITH_MCAP_LOGS]
(without --data the dataset is imported into a temporary folder first).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def import_dataset(out: Path) -> None:
    from conftest import dataset_dir
    from qube_koopman.daq.legacy_csv import legacy_episode, load_legacy_controller
    from qube_koopman.daq.log import write_episode
    from qube_koopman.daq.log.names import log_path

    src = dataset_dir()
    if src is None:
        sys.exit("dataset not found: set QUBE_DATASET_DIR or pass --data")
    controller = load_legacy_controller(src / "controller.toml")
    for path in sorted(src.glob("*.csv")):
        write_episode(log_path(out, path.stem), legacy_episode(path, controller))


def naive_cost(data: Path, n_alphas: int = 2, n_validation: int = 2) -> float:
    """Seconds per (fold, alpha, scoring) evaluation of the naive approach."""
    from qube_koopman.identify import ClEdmd, Delay, Polynomial
    from qube_koopman.identify.data.logs import check_same_controller, load_logs
    from qube_koopman.identify.model_selection.split import group_shuffle_splits, paper_split
    from naive_reference import naive_predict

    train_paths, _ = paper_split(sorted(data.glob("*.mcap")))
    logs = load_logs(train_paths, skip=500)
    controller = check_same_controller(logs, "training")
    trajs = [log.trajectory for log in logs]
    train_idx, val_idx = group_shuffle_splits(len(trajs))[0]
    started = time.perf_counter()
    for alpha in np.logspace(-3, 3, n_alphas):
        model = ClEdmd(controller, lifting=[Polynomial(2), Delay(10)], alpha=alpha, known_controller_rows=False).fit(
            [trajs[i] for i in train_idx]
        )
        cl = model.closed_loop_model_
        for i in val_idx[:n_validation]:
            t = trajs[i]
            naive_predict(cl, t.x[:11], cl.inputs_of(t), t.xc[10])
    elapsed = time.perf_counter() - started
    # scale the validation part to the 6 held-out episodes of a fold
    per_eval = elapsed / n_alphas
    return per_eval * len(val_idx) / n_validation


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, help="folder of imported .mcap logs")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            data = Path(tmp)
            t0 = time.perf_counter()
            import_dataset(data)
            print(f"imported the dataset in {time.perf_counter() - t0:.1f} s (not counted)")
        from qube_koopman.reproduce.qube_study import reproduce_qube

        runs, serial = [], []
        for _ in range(3):
            t0 = time.perf_counter()
            results = reproduce_qube(data)
            runs.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        reproduce_qube(data, n_jobs=1)
        serial.append(time.perf_counter() - t0)
        fast = float(np.median(runs))
        per_eval = naive_cost(data)
    evaluations = 2 * 3 * 180 * 2
    naive_total = per_eval * evaluations
    print()
    print(f"{'measure':<52}{'value':>14}{'target':>12}")
    print(f"{'whole reproduction (median of 3 runs)':<52}{fast:>12.1f} s{'<= 10 s':>12}")
    print(f"{'  the same in one process (n_jobs=1)':<52}{serial[0]:>12.1f} s{'':>12}")
    print(f"{'naive: one fit + 6 validation predictions':<52}{per_eval:>12.2f} s{'':>12}")
    print(f"{'naive: the protocol extrapolated (2160 evaluations)':<52}{naive_total / 60:>10.1f} min{'':>12}")
    print(f"{'speed-up of the whole reproduction':<52}{naive_total / fast:>13.0f}x{'':>12}")
    print(f"checks: {', '.join(k for k, ok in results['checks'].items() if ok)}")


if __name__ == "__main__":
    main()
