"""Speed of the lifting search (qube-identify --search) against the naive per-fit approach.

Target: the default search on the paper's 28 training episodes in at most
5 minutes on 2 cores. The search shares each lifting's statistics across folds and
alphas and predicts every alpha's model on every validation episode in one batched
simulation. The naive approach fits every (candidate, fold, alpha) from scratch and
predicts each validation episode alone; it is timed on one representative candidate
(monomials of order 2, 20 delays) for two alphas in the same run and extrapolated to
the search's candidates x folds x alphas.

Usage: python bench/bench_search.py --data DIR_WITH_MCAP_LOGS [--n-jobs 2]
(import the dataset first: qube-import ../shared/datasets/qube_servo_20230828/*.csv --out DIR)
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def naive_cost(trajs, controller, splits, window: int, n_alphas: int = 2) -> float:
    """Seconds per (fold, alpha) evaluation of one candidate, fitted and predicted naively."""
    from qube_koopman.identify import ClEdmd
    from qube_koopman.identify.scores import r2_scores
    from qube_koopman.identify.search import LiftingSpec

    train, validation = splits[0]
    started = time.perf_counter()
    for alpha in np.logspace(-4, -2, n_alphas):
        model = ClEdmd(controller, lifting=LiftingSpec(delays=20).steps(), alpha=alpha).fit(
            [trajs[i] for i in train]).closed_loop_model_
        for i in validation:
            r2_scores(trajs[i].x[window:], model.predict(trajs[i])[window:])
    return (time.perf_counter() - started) / n_alphas


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="folder of the 48 imported .mcap logs")
    parser.add_argument("--n-jobs", type=int, default=2)
    args = parser.parse_args()
    from qube_koopman.identify.data import check_same_controller, group_shuffle_splits, load_logs, paper_split
    from qube_koopman.identify.search import SearchSpace, evaluate_candidate, search_liftings, SearchData, LiftingSpec

    train_paths, _ = paper_split(sorted(args.data.glob("*.mcap")))
    logs = load_logs(train_paths, skip=500)
    controller = check_same_controller(logs, "training")
    trajs = [log.trajectory for log in logs]
    splits = group_shuffle_splits(len(trajs), n_splits=3, test_size=0.2, seed=1234)
    space, window = SearchSpace(), 500
    t0 = time.perf_counter()
    result = search_liftings(trajs, controller, splits=splits, window=window, space=space, n_jobs=args.n_jobs)
    search_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    evaluate_candidate(LiftingSpec(delays=20), SearchData(trajs, splits, controller, np.array(space.alphas), window))
    one_fast = time.perf_counter() - t0
    per_eval = naive_cost(trajs, controller, splits, window)
    evaluations = len(result.candidates) * len(splits) * len(space.alphas)
    one_naive = per_eval * len(splits) * len(space.alphas)
    print(f"{'measure':<60}{'value':>12}{'target':>10}")
    print(f"{'default search, ' + str(len(result.candidates)) + ' candidates, n_jobs ' + str(args.n_jobs):<60}"
          f"{search_s:>10.0f} s{'<= 300 s':>10}")
    print(f"{'one candidate (poly 2, 20 delays, 17 alphas x 3 folds)':<60}{one_fast:>10.1f} s")
    print(f"{'  naive, same candidate (51 fits + predictions)':<60}{one_naive:>10.1f} s"
          f"{one_naive / one_fast:>9.1f}x")
    print(f"{'naive search extrapolated (' + str(evaluations) + ' evaluations at that cost)':<60}"
          f"{per_eval * evaluations / 60:>8.1f} min")
    w = result.winner
    print(f"winner: {w.spec.label()}, alpha {w.best_alpha:g}, CV R^2 {w.score:.4f}")


if __name__ == "__main__":
    main()
