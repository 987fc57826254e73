"""Time of one stability-constrained CL EDMD fit, beside the same problem posed on the snapshots.

Target: one constrained fit at QUBE size (57 lifted states) in at
most 5 s on 2 cores. Three ways to the constrained plant, all from the same
snapshot statistics (identify.estimators.stability.ClEdmdStable):

* ``method="sqp"`` (the default): least cost increase by sequential QP on
  the closed-loop eigenvalues, in the metric of the Gram factor;
* ``method="lmi"``: the fixed-Lyapunov-matrix LMI (cvxpy + Clarabel) on the
  triangular factor of the snapshot Gram matrix;
* the same LMI with its cost on the raw snapshot matrix
  (``||Theta_2 - U^p S Psi||^2`` over every snapshot), here on the first
  ``--raw-snapshots`` of them so that it finishes.

Times are medians of ``--repeats`` runs (the SDPs once each: tens of
seconds) of the constrained solve alone, and the ratio to the LMI solve in
the same run; the full fit (snapshot statistics included, identical for all
methods) is timed for the default. Each method also reports the closed
loop's spectral radius, the relative least-squares cost increase and the test R^2
on the paper's split.

Usage: python bench/bench_stability.py [--data DIR] [--delays N] [--raw-snapshots N] [--repeats N]
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

    from qube_koopman.identify.estimators.regression import Snapshots
    from qube_koopman.identify.estimators.stability import _lyapunov_certificate

    setup = est.setup_fit(trajs)
    parts = [est.episode_snapshots(setup, t) for t in setup.trajectories]
    d = setup.lifting.n_delays_
    psi = np.vstack(
        [np.hstack([t.xc[d:-1], setup.lifting.transform(t.x)[:-1], t.r[d:-1], t.f[d:-1]]) for t in setup.trajectories]
    )[:n_snapshots]
    target = np.vstack([setup.lifting.transform(t.x)[1:] for t in setup.trajectories])[:n_snapshots]
    est.output_matrix_, est.n_feedforward_ = setup.output_matrix, setup.n_feedforward
    S = setup.plant_input_map
    snapshots = Snapshots.total(parts)
    from qube_koopman.identify.estimators.regression import constrained_plant_solve

    n_c = est.controller.n_states
    U0 = constrained_plant_solve(snapshots, S, est.alpha, slice(n_c, None), "closed_loop")
    P = _lyapunov_certificate(est._closed_loop_state(U0, S), est.max_radius)
    started = time.perf_counter()
    U_p = cp.Variable(U0.shape)
    rows = U_p @ S
    n_theta = n_c + U0.shape[0]
    M = cp.vstack([cp.Constant(est._known_controller_rows()[:, :n_theta]), rows[:, :n_theta]])
    lmi = cp.bmat([[est.max_radius**2 * P, (P @ M).T], [P @ M, P]])
    cost = cp.sum_squares(psi @ rows.T - target) + est.alpha * cp.sum_squares(rows)
    cp.Problem(cp.Minimize(cost / len(psi)), [0.5 * (lmi + lmi.T) >> 0]).solve(solver="CLARABEL")
    return time.perf_counter() - started


def _timed_solve(est, repeats: int):
    """Median seconds of the constrained solve from the fitted statistics, and its (U^f, U^p)."""
    times, out = [], None
    for _ in range(repeats):
        started = time.perf_counter()
        out = est._solve(est.snapshots_, est.plant_input_map_, est.alpha)
        times.append(time.perf_counter() - started)
    return float(np.median(times)), out


def _with_rows(est, rows):
    """A copy of the fitted estimator carrying the matrices ``rows`` = (U^f, U^p)."""
    import copy

    est = copy.copy(est)
    model = est.closed_loop_model_
    est._set_models(*rows, model.lifting, est.n_feedforward_, model.dt)
    return est


def main() -> None:
    from bench_qube_reproduction import import_dataset

    from qube_koopman.identify import ClEdmdKnownRows, Delay, Polynomial
    from qube_koopman.identify.data.logs import check_same_controller, load_logs
    from qube_koopman.identify.model_selection.split import paper_split
    from qube_koopman.identify.metrics import summarize_episodes
    from qube_koopman.identify.estimators.stability import ClEdmdStable, _plant_cost

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path)
    parser.add_argument("--delays", type=int, default=10)
    parser.add_argument("--raw-snapshots", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=5)
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
        return summarize_episodes([t.trajectory.x for t in test], [model.predict(t.trajectory) for t in test])[
            "r2_mean"
        ]

    plain = ClEdmdKnownRows(controller, lifting=lifting, alpha=1e-3).fit(trajs)
    fit_times = []
    for _ in range(args.repeats):
        started = time.perf_counter()
        stable = ClEdmdStable(controller, lifting=lifting, alpha=1e-3, max_radius=1.0).fit(trajs)
        fit_times.append(time.perf_counter() - started)
    base_cost = _plant_cost(
        stable.snapshots_, stable.plant_input_map_, stable.alpha, plain.plant_koopman_matrix_, controller.n_states
    )
    sqp_s, sqp_rows = _timed_solve(stable.set_params(method="sqp"), args.repeats)
    sqp = _with_rows(stable, sqp_rows)
    sqp_cost = stable.objective_
    lmi_s, lmi_rows = _timed_solve(stable.set_params(method="lmi", n_iter=0), 1)
    lmi = _with_rows(stable, lmi_rows)
    lmi_cost = stable.objective_
    raw_s = _raw_posed_fit(
        ClEdmdStable(controller, lifting=lifting, alpha=1e-3, max_radius=1.0), trajs, args.raw_snapshots
    )
    n_lifted = stable.closed_loop_model_.A.shape[0]
    print(f"{'':36} {'radius':>10} {'cost +rel':>10} {'test R^2':>9} {'solve (s)':>9} {'vs LMI':>7}")
    print(
        f"{'closed form (unconstrained)':36} {plain.closed_loop_model_.spectral_radius():10.6f} "
        f"{0.0:10.2e} {r2(plain.closed_loop_model_):9.4f}"
    )
    for name, est, cost, secs in [
        ("sqp on eigenvalues (default)", sqp, sqp_cost, sqp_s),
        ("fixed-P LMI, Gram factor", lmi, lmi_cost, lmi_s),
    ]:
        print(
            f"{name:36} {est.closed_loop_model_.spectral_radius():10.6f} {(cost - base_cost) / base_cost:10.2e} "
            f"{r2(est.closed_loop_model_):9.4f} {secs:9.3f} {secs / lmi_s:7.4f}"
        )
    print(
        f"{f'fixed-P LMI, {args.raw_snapshots} raw snapshots':36} {'':>10} {'':>10} {'':>9} {raw_s:9.1f} "
        f"{raw_s / lmi_s:7.2f}"
    )
    print(
        f"one full constrained fit (default, snapshot statistics included): "
        f"{np.median(fit_times):.2f} s, median of {args.repeats}"
    )
    print(f"{n_lifted} closed-loop states; target: one constrained fit <= 5 s")


if __name__ == "__main__":
    main()
