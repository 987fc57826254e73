"""Time of one stability-constrained CL EDMD fit, beside the same problem posed on the snapshots.

Target (issue 10): one constrained fit at QUBE size (57 lifted states) in at
most 5 s on 2 cores. The fit (identify.stability.ClEdmdStable) poses the
least squares on the triangular factor of the snapshot Gram matrix; the
reference poses the same cost, with the same LMI, on the raw snapshot
matrix (``||Theta_2 - U^p S Psi||^2`` over every snapshot), here on the
first ``--raw-snapshots`` of them so that it finishes. Both also report
the closed loop's spectral radius and the test R^2 on the paper's split.

Usage: python bench/bench_stability.py [--data DIR] [--delays N] [--raw-snapshots N]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))


def _raw_posed_fit(est, trajs, n_snapshots: int) -> float:
    """The same fixed-P constrained problem with the cost on raw snapshots; returns seconds."""
    import cvxpy as cp

    from qube_koopman.identify.regression import Snapshots
    from qube_koopman.identify.stability import _lyapunov_certificate

    setup = est._setup(trajs)
    parts = [est._episode_snapshots(setup, t) for t in setup.trajectories]
    d = setup.lifting.n_delays_
    psi = np.vstack([np.hstack([t.xc[d:-1], setup.lifting.transform(t.x)[:-1], t.r[d:-1], t.f[d:-1]])
                     for t in setup.trajectories])[:n_snapshots]
    target = np.vstack([setup.lifting.transform(t.x)[1:] for t in setup.trajectories])[:n_snapshots]
    est.output_matrix_, est.n_feedforward_ = setup.output_matrix, setup.n_feedforward
    S = setup.plant_input_map
    snapshots = Snapshots.total(parts)
    from qube_koopman.identify.regression import constrained_plant_solve

    n_c = est.controller.n_states
    U0 = constrained_plant_solve(snapshots, S, est.alpha, slice(n_c, None), "closed_loop")
    P = _lyapunov_certificate(est._closed_loop_state(U0, S), est.max_radius)
    started = time.perf_counter()
    U_p = cp.Variable(U0.shape)
    rows = U_p @ S
    n_theta = n_c + U0.shape[0]
    M = cp.vstack([cp.Constant(est._known_controller_rows()[:, :n_theta]), rows[:, :n_theta]])
    lmi = cp.bmat([[est.max_radius ** 2 * P, (P @ M).T], [P @ M, P]])
    cost = cp.sum_squares(psi @ rows.T - target) + est.alpha * cp.sum_squares(rows)
    cp.Problem(cp.Minimize(cost / len(psi)), [0.5 * (lmi + lmi.T) >> 0]).solve(solver="CLARABEL")
    return time.perf_counter() - started


def main() -> None:
    from bench_qube_reproduction import import_dataset

    from qube_koopman.identify import ClEdmdKnownRows, Delay, Polynomial
    from qube_koopman.identify.data import check_same_controller, load_logs, paper_split
    from qube_koopman.identify.scores import summarize_episodes
    from qube_koopman.identify.stability import ClEdmdStable

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path)
    parser.add_argument("--delays", type=int, default=10)
    parser.add_argument("--raw-snapshots", type=int, default=2000)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            data = Path(tmp)
            import_dataset(data)
        train_paths, test_paths = paper_split(sorted(data.glob("*.mcap")))
        train, test = load_logs(train_paths, skip=500), load_logs(test_paths, skip=500)
    controller = check_same_controller(train, "training")
    trajs = [log.trajectory for log in train]
    lifting = [Polynomial(2), Delay(args.delays)]

    def r2(model):
        return summarize_episodes([t.trajectory.x for t in test], [model.predict(t.trajectory) for t in test])["r2_mean"]

    plain = ClEdmdKnownRows(controller, lifting=lifting, alpha=1e-3).fit(trajs)
    started = time.perf_counter()
    stable = ClEdmdStable(controller, lifting=lifting, alpha=1e-3, max_radius=1.0, n_iter=0).fit(trajs)
    fit_s = time.perf_counter() - started
    raw_s = _raw_posed_fit(ClEdmdStable(controller, lifting=lifting, alpha=1e-3, max_radius=1.0), trajs,
                           args.raw_snapshots)
    n_lifted = stable.closed_loop_model_.A.shape[0]
    print(f"{'':34} {'radius':>10} {'test R^2':>9} {'time (s)':>9}")
    print(f"{'closed form (unconstrained)':34} {plain.closed_loop_model_.spectral_radius():10.6f} "
          f"{r2(plain.closed_loop_model_):9.4f} {'':>9}")
    print(f"{'constrained, Gram factor':34} {stable.closed_loop_model_.spectral_radius():10.6f} "
          f"{r2(stable.closed_loop_model_):9.4f} {fit_s:9.1f}")
    print(f"{f'same, {args.raw_snapshots} raw snapshots':34} {'':>10} {'':>9} {raw_s:9.1f}")
    print(f"{n_lifted} closed-loop states; target: one constrained fit <= 5 s")


if __name__ == "__main__":
    main()
