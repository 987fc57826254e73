"""identify/model_selection/distributed.py's parts without a cluster of processes: statistics computed elsewhere by
episode index, logs read from a path or from bytes, the checks that name a worker, ordered results.

The real cluster (``dask scheduler`` and ``dask worker`` processes) is tests/identify/test_dask_cluster.py's.
"""

from __future__ import annotations

import copy
import time

import numpy as np
import pytest

from linear_loops import closed_loop_trajectories, mass_spring_damper, pid_position_controller
from qube_koopman.identify import ClEdmd, Delay, Edmd, Polynomial, ThinPlateRbf
from qube_koopman.identify.model_selection.split import group_shuffle_splits
from qube_koopman.identify.model_selection.distributed import (
    ClusterStatistics,
    LogSource,
    _check_versions,
    _unseen,
    ordered_results,
)
from qube_koopman.identify.model_selection.sweep import SweepOptions, regularization_sweep

ALPHAS = [1e-6, 1e-3, 1.0]


@pytest.fixture(scope="module")
def loop():
    A, B = mass_spring_damper()
    controller = pid_position_controller()
    return closed_loop_trajectories(A, B, controller, [0], n_episodes=6, n=300, seed=3), controller


class _Elsewhere:
    """Statistics computed from another copy of the episodes, by index (as a worker reads log ``i``)."""

    def __init__(self, trajectories):
        self.trajectories, self.asked = copy.deepcopy(trajectories), []

    def __call__(self, estimator, setup, indices):
        indices = [int(i) for i in indices]
        self.asked.append(indices)
        assert not setup.trajectories or len(setup.trajectories) == len(indices)
        return (estimator.episode_snapshots(setup, self.trajectories[i]) for i in indices)


@pytest.mark.parametrize(
    "lifting",
    [[Polynomial(2), Delay(3)], [ThinPlateRbf(6, seed=1), Delay(2)]],
    ids=["shared statistics", "lifting fitted per fold"],
)
def test_a_sweep_with_statistics_computed_elsewhere_equals_the_local_sweep(loop, lifting):
    trajs, controller = loop
    splits = group_shuffle_splits(len(trajs), n_splits=3, test_size=0.34, seed=2)
    template = ClEdmd(controller, lifting=lifting, measured=[0])
    here = regularization_sweep(template, trajs, ALPHAS, splits, scorings=("cl",))
    elsewhere = _Elsewhere(trajs)
    there = regularization_sweep(
        template, trajs, ALPHAS, splits, scorings=("cl",), options=SweepOptions(episode_statistics=elsewhere)
    )
    np.testing.assert_array_equal(there.cv_r2["cl"], here.cv_r2["cl"])
    for a, b in zip(here.closed_loop_models, there.closed_loop_models):
        np.testing.assert_array_equal(a.A, b.A)
    everything = list(range(len(trajs)))
    if isinstance(lifting[0], ThinPlateRbf):  # each fold fits its lifting, and asks for its own episodes
        assert elsewhere.asked == [list(train) for train, _ in splits] + [everything]
    else:
        assert elsewhere.asked == [everything]


@pytest.mark.parametrize("closed_loop", [True, False], ids=["CL EDMD", "EDMD"])
def test_a_fit_from_statistics_computed_elsewhere_equals_the_fit(loop, closed_loop):
    from qube_koopman.identify.workflow import _fit

    trajs, controller = loop
    lifting = [Polynomial(2), Delay(3)]
    estimator = (
        ClEdmd(controller, lifting=lifting, alpha=1e-3, measured=[0])
        if closed_loop
        else Edmd(lifting=lifting, alpha=1e-3)
    )
    controllers = [controller] * len(trajs) if closed_loop else None
    here = copy.deepcopy(estimator).fit(trajs, controllers) if closed_loop else copy.deepcopy(estimator).fit(trajs)
    elsewhere = _Elsewhere(trajs)
    there = _fit(copy.deepcopy(estimator), trajs, controllers, elsewhere)
    np.testing.assert_array_equal(there.koopman_matrix_, here.koopman_matrix_)
    assert elsewhere.asked == [list(range(len(trajs)))]


@pytest.fixture
def log_file(tmp_path):
    from _episodes import make_episode
    from qube_koopman.daq.log import write_episode
    from qube_koopman.daq.log.names import log_path

    path = log_path(tmp_path, "episode")
    write_episode(path, make_episode(400, seed=5))
    return path


def test_a_log_read_from_its_path_or_from_its_bytes_is_the_same_trajectory(log_file):
    a, b = LogSource(str(log_file)).read(10), LogSource(str(log_file), log_file.read_bytes()).read(10)
    assert a.name == b.name == log_file.name and a.n_samples == b.n_samples == 390
    for signal in ("x", "u", "r", "f", "xc"):
        np.testing.assert_array_equal(getattr(a, signal), getattr(b, signal))


def test_a_damaged_shipped_log_is_an_error_naming_its_path(log_file):
    with pytest.raises(ValueError) as caught:
        LogSource(str(log_file), log_file.read_bytes()[:200]).read(10)
    assert str(caught.value).startswith(f"{log_file}: ") and "qube-log-" not in str(caught.value)


class _FakeClient:
    """What the checks ask of a client: ``run`` on every worker, here answered as given."""

    def __init__(self, answers: dict):
        self.answers = answers

    def run(self, fn, *args, **kwargs):
        return self.answers

    def run_on_scheduler(self, fn, *args):
        return self.answers.get("scheduler", fn(*args))


def test_shared_logs_a_worker_cannot_see_are_an_error_naming_the_file_and_the_worker(log_file, tmp_path):
    missing = tmp_path / "elsewhere.mcap"
    assert _unseen([str(log_file), str(missing)]) == [(str(log_file), log_file.stat().st_size), (str(missing), None)]
    size = log_file.stat().st_size
    client = _FakeClient(
        {"tcp://10.0.0.2:4000": [(str(log_file), size)], "tcp://10.0.0.3:4000": [(str(log_file), None)]}
    )
    with pytest.raises(
        ValueError,
        match=f"{log_file}: not readable as the same file on dask worker tcp://10.0.0.3:4000 \\(no such file\\)",
    ):
        ClusterStatistics(client, [log_file], skip=0, shared=True)
    client.answers["tcp://10.0.0.3:4000"] = [(str(log_file), size - 1)]
    with pytest.raises(ValueError, match=f"{size - 1} bytes, here {size}"):
        ClusterStatistics(client, [log_file], skip=0, shared=True)
    shipped = ClusterStatistics(client, [log_file], skip=0)  # nothing to check: the bytes travel
    assert shipped.source(0) == LogSource(str(log_file.resolve()), log_file.read_bytes())


def test_a_worker_without_the_package_or_at_another_version_is_named():
    from importlib.metadata import version

    mine = version("qube-koopman")
    _check_versions(_FakeClient({"tcp://a:1": mine}), "tcp://s:8786")
    with pytest.raises(ValueError, match="x: worker tcp://b:1 cannot find qube-koopman"):
        _check_versions(_FakeClient({"tcp://a:1": mine, "tcp://b:1": ModuleNotFoundError("qube_koopman")}), "x")
    with pytest.raises(ValueError, match=f"worker tcp://a:1 runs qube-koopman 0.0.1, this client {mine}"):
        _check_versions(_FakeClient({"tcp://a:1": "0.0.1"}), "x")

    def missing(*args):
        raise ModuleNotFoundError("qube_koopman")

    client = _FakeClient({"tcp://a:1": mine})
    client.run_on_scheduler = missing
    with pytest.raises(ValueError, match="x: the scheduler cannot find qube-koopman"):
        _check_versions(client, "x")


def _sleep_then(seconds: float, value: int) -> int:
    time.sleep(seconds)
    if value < 0:
        raise ValueError(f"call {value} failed")
    return value


def test_results_come_back_in_the_calls_order_and_a_calls_error_is_raised_here():
    distributed = pytest.importorskip("dask.distributed", reason="the dask extra is optional")
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=3, dashboard_address=":0") as client:
        # The first call ends last; at most two in flight.
        calls = [(_sleep_then, (0.3 - 0.05 * i, i), {}) for i in range(5)]
        assert list(ordered_results(client, calls, ahead=2)) == [0, 1, 2, 3, 4]
        with pytest.raises(ValueError, match="call -1 failed"):
            list(ordered_results(client, [(_sleep_then, (0.0, 1), {}), (_sleep_then, (0.0, -1), {})]))


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--worker-logs", "shared"], "--worker-logs says how dask workers read the logs: it needs --scheduler"),
        (
            ["--scheduler", "tcp://h:8786", "--method", "arx", "--score", "plant"],
            "--scheduler computes the Koopman methods' per-episode statistics; --method arx fits here",
        ),
        (["--scheduler", ""], "--scheduler takes a dask scheduler's address, for example tls://host:8786, got ''"),
        (["--scheduler", "tcp://h"], "got 'tcp://h'"),
        (["--scheduler", "h:99999"], "got 'h:99999'"),
    ],
)
def test_cluster_option_refusals(tmp_path, capsys, argv, message):
    from qube_koopman.identify.cli.identify import main

    code = main(["--train", "a.mcap", "--test", "b.mcap", "--out", str(tmp_path), *argv])
    err = capsys.readouterr().err
    assert code == 2 and message in err and "Traceback" not in err, err
