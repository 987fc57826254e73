"""qube_koopman.core.blas: the BLAS pools are limited inside the block and restored after it."""

from __future__ import annotations

from threadpoolctl import threadpool_info

from qube_koopman.core.blas import limited_blas_threads


def _blas_threads() -> list[int]:
    return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]


def test_blas_threads_are_limited_then_restored():
    import scipy.linalg  # noqa: F401  (load scipy's BLAS too)

    before = _blas_threads()
    assert before, "numpy loads a BLAS"
    with limited_blas_threads(1):
        assert _blas_threads() == [1] * len(before)
    assert _blas_threads() == before


def test_episode_statistics_run_side_by_side_in_order_and_as_one_at_a_time():
    # A fit's episodes are factored side by side, on as many threads as the BLAS may use, each with one BLAS
    # thread: the same factors bit for bit as one at a time with one BLAS thread, in the episodes' order.
    # Inside a limit (a search's workers) they are factored one at a time, in the caller's thread.
    import threading
    from unittest import mock

    import numpy as np

    import qube_koopman.core.blas as blas
    from qube_koopman.identify import ClEdmd
    from qube_koopman.identify.estimators._base import episode_statistics
    from qube_koopman.identify.lifting import Delay, Polynomial
    from linear_loops import closed_loop_trajectories, mass_spring_damper, pid_position_controller

    A_p, B_p = mass_spring_damper()
    controller = pid_position_controller()
    trajs = closed_loop_trajectories(A_p, B_p, controller, [0], n_episodes=7, n=300, seed=4)
    est = ClEdmd(controller, lifting=[Polynomial(2), Delay(3)], measured=[0])
    setup = est._setup(trajs)
    with limited_blas_threads(1):
        alone = [est._episode_snapshots(setup, t) for t in trajs]
    seen = []
    factor = est._episode_snapshots

    def recorded(setup, t):
        seen.append((threading.current_thread().name, _blas_threads()))
        return factor(setup, t)

    with mock.patch.object(est, "_episode_snapshots", recorded), mock.patch.object(blas, "blas_threads", lambda: 2):
        side_by_side = list(episode_statistics(est, setup, range(len(trajs))))
    assert all(np.array_equal(a.R, b.R) for a, b in zip(alone, side_by_side)) and len(side_by_side) == len(trajs)
    assert {name.split("_")[0] for name, _ in seen} == {"episode-statistics"}
    assert all(set(threads) == {1} for _, threads in seen)
    seen.clear()
    with limited_blas_threads(1), mock.patch.object(est, "_episode_snapshots", recorded):
        in_order = list(episode_statistics(est, setup, [3, 1]))
    assert [s.R.tobytes() for s in in_order] == [alone[3].R.tobytes(), alone[1].R.tobytes()]
    assert {name for name, _ in seen} == {threading.current_thread().name}
