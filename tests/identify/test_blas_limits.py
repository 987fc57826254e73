"""qube_koopman.core.blas: the BLAS pools are limited inside the block and restored after it."""

from __future__ import annotations

import pytest
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
    from qube_koopman.identify.estimators.base import episode_statistics
    from qube_koopman.identify.lifting import Delay, Polynomial
    from linear_loops import closed_loop_trajectories, mass_spring_damper, pid_position_controller

    A_p, B_p = mass_spring_damper()
    controller = pid_position_controller()
    trajs = closed_loop_trajectories(A_p, B_p, controller, [0], n_episodes=7, n=300, seed=4)
    est = ClEdmd(controller, lifting=[Polynomial(2), Delay(3)], measured=[0])
    setup = est.setup_fit(trajs)
    with limited_blas_threads(1):
        alone = [est.episode_snapshots(setup, t) for t in trajs]
    seen = []
    factor = est.episode_snapshots

    def recorded(setup, t):
        seen.append((threading.current_thread().name, _blas_threads()))
        return factor(setup, t)

    with mock.patch.object(est, "episode_snapshots", recorded), mock.patch.object(blas, "blas_threads", lambda: 2):
        side_by_side = list(episode_statistics(est, setup, range(len(trajs))))
    assert all(np.array_equal(a.R, b.R) for a, b in zip(alone, side_by_side)) and len(side_by_side) == len(trajs)
    assert {name.split("_")[0] for name, _ in seen} == {"episode-statistics"}
    assert all(set(threads) == {1} for _, threads in seen)
    seen.clear()
    with limited_blas_threads(1), mock.patch.object(est, "episode_snapshots", recorded):
        in_order = list(episode_statistics(est, setup, [3, 1]))
    assert [s.R.tobytes() for s in in_order] == [alone[3].R.tobytes(), alone[1].R.tobytes()]
    assert {name for name, _ in seen} == {threading.current_thread().name}


def test_episode_threads_lift_the_limit_for_the_episodes_alone():
    # qube-identify fits inside a one-thread BLAS limit (its many small products) and still factors its
    # training episodes side by side: episode_threads(n) gives them n threads, each with one BLAS thread;
    # outside it (a search's worker processes) the BLAS limit decides, as before.
    import threading

    import pytest

    from qube_koopman.core.blas import episode_thread_count, episode_threads

    with limited_blas_threads(1):
        assert episode_thread_count() == 1
        with episode_threads(3):
            assert episode_thread_count() == 3 and _blas_threads() == [1] * len(_blas_threads())
            seen = []
            thread = threading.Thread(target=lambda: seen.append(episode_thread_count()))
            thread.start()
            thread.join()
            assert seen == [1]  # a context of its own: another thread's fits are not widened
        assert episode_thread_count() == 1
    with pytest.raises(ValueError, match="1 thread or more, got 0"):
        with episode_threads(0):
            pass


@pytest.mark.slow  # about 3 s: four fits of 4 real episodes
def test_a_workflow_fit_factors_its_episodes_on_n_threads_and_the_model_is_the_same(qube_logs):
    import threading

    import numpy as np

    from qube_koopman.daq.log.names import find_logs
    from qube_koopman.identify import ClEdmd
    from qube_koopman.identify.data.logs import load_logs
    from qube_koopman.identify.lifting import Constant, Delay, Polynomial
    from qube_koopman.identify.uncertainty import IntervalOptions
    from qube_koopman.identify.workflow import FitOptions, IdentifyOptions, identify_and_score

    files = find_logs(qube_logs)
    train, test = load_logs(files[:4], skip=500), load_logs(files[28:29], skip=500)
    factor = ClEdmd.episode_snapshots
    runs, threads = {}, {}
    for n, intervals in ((1, None), (2, None), (1, IntervalOptions(0.95, 3)), (2, IntervalOptions(0.95, 3))):
        seen = set()

        def recorded(self, setup, t, seen=seen):  # this pass's set, bound now
            seen.add(threading.current_thread().name.split("_")[0])
            return factor(self, setup, t)

        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(ClEdmd, "episode_snapshots", recorded)
            fit = FitOptions("cl-edmd", [Polynomial(2), Delay(5), Constant()], alpha=1e-3, n_threads=n)
            runs[n, intervals is None] = identify_and_score(
                train, test, train[0].controller, IdentifyOptions(fit, intervals=intervals)
            )
        threads[n, intervals is None] = seen
    main = threading.current_thread().name
    for plain in (True, False):
        assert threads[1, plain] == {main} and threads[2, plain] == {"episode-statistics"}
        one, two = runs[1, plain], runs[2, plain]
        np.testing.assert_array_equal(one.plant.A, two.plant.A)
        np.testing.assert_array_equal(one.plant.B, two.plant.B)
        assert one.report["test"] == two.report["test"]
    assert runs[1, False].report["intervals"]["pooled"] == runs[2, False].report["intervals"]["pooled"]
    with pytest.raises(ValueError, match="n_threads must be -1 \\(every core\\) or at least 1, got 0"):
        identify_and_score(
            train, test, train[0].controller, IdentifyOptions(FitOptions("cl-edmd", [Polynomial(1)], n_threads=0))
        )
