"""``qube-identify --scheduler`` on a real cluster started as a user starts one: ``dask scheduler`` and two
``dask worker`` processes on the loopback address, each with its own command line.

The search, a fit and an alpha sweep on the cluster equal the local run's; a worker killed mid-search
changes nothing (dask reschedules its tasks on the other).
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from _cluster_logs import N_TRAIN

pytest.importorskip("dask.distributed", reason="the dask extra is optional")

pytestmark = pytest.mark.dataset

STARTUP = 120.0  # s: generous, for a loaded 2-core machine
RUN = 300.0


@dataclass
class Cluster:
    """A running scheduler and its workers (subprocesses of this test), and a client of them."""

    address: str
    scheduler: subprocess.Popen
    workers: list[subprocess.Popen]
    client: object
    folder: Path

    def worker_pids(self) -> dict[str, int]:
        """Each connected worker's address and process id."""
        return self.client.run(os.getpid)

    def executed(self) -> int:
        """Tasks the connected workers have run."""
        return sum(self.client.run(lambda dask_worker: dask_worker.state.executed_count).values())

    def logs(self) -> str:
        """The processes' output, for a failure's message."""
        return "\n".join(f"--- {p.name}\n{p.read_text()[-3000:]}" for p in sorted(self.folder.glob("*.log")))


def _stop(*processes: subprocess.Popen) -> None:
    """Stop processes this test started, by their ids: politely, then for good (all at once, then waited for)."""
    running = [p for p in processes if p.poll() is None]
    for process in running:
        process.terminate()
    for process in running:
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=30)


def _free_port() -> int:
    """A loopback port nobody listens on now (the operating system's choice)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start_cluster(folder: Path, addfinalizer) -> Cluster:
    """``dask scheduler`` on a free loopback port and two single-threaded ``dask worker`` processes.

    ``addfinalizer`` gets what stops them before anything starts: it runs however the test ends.
    """
    from dask.distributed import Client

    folder.mkdir()
    started: list[subprocess.Popen] = []
    clients: list = []

    def finish():
        for client in clients:
            client.close()
        _stop(*started[1:])  # the workers, then the scheduler (stopped together, a worker can hang on it)
        _stop(*started[:1])

    addfinalizer(finish)

    def start(name: str, *argv: str) -> subprocess.Popen:
        with open(folder / f"{name}.log", "wb") as out:
            process = subprocess.Popen(
                [sys.executable, "-m", "dask", *argv], stdout=out, stderr=subprocess.STDOUT, cwd=folder
            )
        started.append(process)
        return process

    address = f"tcp://127.0.0.1:{_free_port()}"
    # All at once: the workers keep trying to reach the scheduler until it listens.
    scheduler = start(
        "scheduler", "scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1], "--no-dashboard"
    )
    workers = [
        start(
            f"worker{i}",
            "worker",
            address,
            "--host",
            "127.0.0.1",
            "--nthreads",
            "1",
            "--no-nanny",
            "--no-dashboard",
            "--local-directory",
            str(folder / f"worker{i}"),
            "--name",
            f"worker{i}",
        )
        for i in range(2)
    ]
    running = Cluster(address, scheduler, workers, None, folder)
    try:
        client = Client(address, timeout=STARTUP, set_as_default=False)
        clients.append(client)
        client.wait_for_workers(2, timeout=STARTUP)
    except (OSError, TimeoutError) as exc:
        raise AssertionError(f"the cluster did not start ({exc})\n{running.logs()}") from None
    running.client = client
    assert sorted(running.worker_pids().values()) == sorted(w.pid for w in workers)
    return running


@pytest.fixture(scope="module")
def cluster(tmp_path_factory, request) -> Cluster:
    """A cluster the tests that leave it whole share."""
    return _start_cluster(tmp_path_factory.mktemp("shared") / "cluster", request.addfinalizer)


@pytest.fixture
def own_cluster(tmp_path, request) -> Cluster:
    """A cluster for one test (that kills a worker)."""
    return _start_cluster(tmp_path / "cluster", request.addfinalizer)


def _argv(logs: Path, out: Path, *extra) -> list[str]:
    return [str(a) for a in ("--train", logs / "train", "--test", logs / "test", "--out", out, "-q", *extra)]


def _search_argv(logs: Path, out: Path, *extra) -> list[str]:
    return _argv(logs, out, "--search", "--search-space", logs / "space.toml", "--transfer", "none", *extra)


def _identify(argv: list[str]) -> None:
    from qube_koopman.identify.cli.identify import main

    assert main(argv) == 0


def _numbers(value) -> list[float]:
    """Every number of a JSON document, in a fixed order (keys sorted)."""
    if isinstance(value, dict):
        return [x for key in sorted(value) for x in _numbers(value[key])]
    if isinstance(value, list):
        return [x for item in value for x in _numbers(item)]
    return [float(value)] if isinstance(value, (int, float)) and not isinstance(value, bool) else []


def _assert_same_numbers(a, b, what: str) -> None:
    x, y = np.array(_numbers(a)), np.array(_numbers(b))
    assert x.shape == y.shape and x.size > 0, what
    np.testing.assert_allclose(y, x, rtol=1e-10, atol=0, err_msg=what)


def _results(out: Path) -> tuple[dict, dict]:
    report = json.loads((out / "report.json").read_text())
    return report, json.loads((out / "model.json").read_text())


def _without_timings(value):
    """A search report's scores and choices: without wall times and how it ran (they differ between runs)."""
    if isinstance(value, dict):
        return {
            k: _without_timings(v) for k, v in value.items() if k not in ("seconds", "timing", "scheduler", "n_jobs")
        }
    return [_without_timings(v) for v in value] if isinstance(value, list) else value


@pytest.fixture(scope="module")
def local_search(cluster_logs, tmp_path_factory) -> dict:
    """The narrowed search run locally, in this process: the cluster runs' reference."""
    out = tmp_path_factory.mktemp("local_search")
    _identify(_search_argv(cluster_logs, out, "--n-jobs", "1"))
    return _results(out)


@pytest.mark.slow
def test_a_search_on_the_cluster_equals_the_local_search(cluster, cluster_logs, local_search, tmp_path):
    before = cluster.executed()
    _identify(_search_argv(cluster_logs, tmp_path / "out", "--scheduler", cluster.address))
    report, model = _results(tmp_path / "out")
    reference, reference_model = local_search
    assert report["search"]["winner"]["label"] == reference["search"]["winner"]["label"]
    assert [c["label"] for c in report["search"]["candidates"]] == [
        c["label"] for c in reference["search"]["candidates"]
    ]
    _assert_same_numbers(_without_timings(reference["search"]), _without_timings(report["search"]), "search")
    _assert_same_numbers(reference_model, model, "the winner's model")
    _assert_same_numbers(reference["test"], report["test"], "test scores")
    # The candidates ran on the workers (a screen each in the screened stages, then a full evaluation of
    # the finalists), and so did the winner's statistics (one task a training log), and one task handed the
    # episodes to them; each family's largest lifting was lifted there too (one task: too few episodes to
    # split), its statistics handed to the family's candidates (one more).
    stages = report["search"]["timing"]["stages"]
    families = sum(t["shared_statistics"] > 0 for t in stages.values())
    assert families == 2  # the delays stage's (the longest delays) and the form stage's
    candidates = report["search"]["candidates"]
    screens = sum(
        sum(c["stage"] == stage for c in candidates) + stages[stage]["screened_out"]
        for stage in report["search"]["screening"]["stages"]
    )
    assert screens == 7  # 4 delays, 3 forms (poly 1 and 2, with and without the constant, but the one tried)
    assert cluster.executed() - before == len(candidates) + screens + N_TRAIN + 1 + 2 * families


@pytest.mark.slow
def test_a_fit_and_an_alpha_sweep_on_the_cluster_equal_the_local_ones(cluster, cluster_logs, tmp_path):
    before = cluster.executed()
    fit = ("--poly", "2", "--delays", "10", "--alpha", "1e-3", "--worker-logs", "shared")
    sweep = ("--poly", "2", "--delays", "5", "--trig", "--alpha-sweep", "1e-4", "1", "3")  # logs shipped
    for name, options in (("fit", fit), ("sweep", sweep)):
        local = [o for o in options if o not in ("--worker-logs", "shared")]
        _identify(_argv(cluster_logs, tmp_path / f"{name}_local", *local))
        reference, reference_model = _results(tmp_path / f"{name}_local")
        _identify(_argv(cluster_logs, tmp_path / name, *options, "--scheduler", cluster.address))
        report, model = _results(tmp_path / name)
        _assert_same_numbers(reference_model, model, f"{name}: model")
        _assert_same_numbers(reference["test"], report["test"], f"{name}: test scores")
        assert ("sweep" in report) == (name == "sweep")
    _assert_same_numbers(reference["sweep"], report["sweep"], "the sweep")
    # Every training log's statistics were computed on the workers, once a fit: the fit, the
    # sweep (its folds share them) and the sweep's final fit.
    assert cluster.executed() - before == 3 * N_TRAIN, cluster.logs()


@pytest.mark.slow
def test_a_worker_killed_mid_search_leaves_the_same_winner(own_cluster, cluster_logs, local_search, tmp_path):
    cluster, out = own_cluster, tmp_path / "out"
    with open(tmp_path / "search.log", "wb") as log:
        search = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "qube_koopman.identify.cli.identify",
                *_search_argv(cluster_logs, out, "--scheduler", cluster.address),
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
        )
    try:
        victim, interrupted = _kill_a_busy_worker(cluster, search)
        assert search.wait(timeout=RUN) == 0, (tmp_path / "search.log").read_text() + cluster.logs()
    finally:
        _stop(search)
    assert victim.wait(timeout=30) == -signal.SIGKILL
    assert len(cluster.worker_pids()) == 1  # the search finished on the other worker
    # What the killed worker was computing ran again on the other, to the end (then the client let it go).
    stories = cluster.client.run_on_scheduler(lambda dask_scheduler: [dask_scheduler.story(k) for k in interrupted])
    assert [_runs(story) for story in stories] == [(2, "forgotten")] * len(interrupted)
    report, model = _results(out)
    reference, reference_model = local_search
    assert report["search"]["winner"]["label"] == reference["search"]["winner"]["label"]
    assert report["search"]["winner"]["alpha"] == reference["search"]["winner"]["alpha"]
    _assert_same_numbers(_without_timings(reference["search"]), _without_timings(report["search"]), "search")
    _assert_same_numbers(reference_model, model, "the winner's model")


def _kill_a_busy_worker(cluster: Cluster, search: subprocess.Popen) -> tuple[subprocess.Popen, list[str]]:
    """Once the search has finished some tasks, SIGKILL a worker computing one: (the worker, its tasks).

    The worker is frozen first (SIGSTOP) until the scheduler has seen the same tasks on it twice:
    it can neither finish them nor say so, so each of them must run again elsewhere.
    """
    processes = {w.pid: w for w in cluster.workers}
    pids = cluster.worker_pids()  # this test's processes, by their ids
    deadline = time.monotonic() + RUN
    while time.monotonic() < deadline:
        assert search.poll() is None, "the search ended before a worker could be killed"
        busy = [worker for worker, keys in cluster.client.processing().items() if keys]
        if busy and cluster.executed() >= 2:
            victim = processes[pids[busy[0]]]
            victim.send_signal(signal.SIGSTOP)
            seen = None
            while (keys := sorted(cluster.client.processing().get(busy[0], ()))) != seen:
                seen = keys
                time.sleep(0.5)  # any word it sent before it froze reaches the scheduler meanwhile
            if keys:
                victim.send_signal(signal.SIGKILL)
                return victim, keys
            victim.send_signal(signal.SIGCONT)
        time.sleep(0.05)
    raise AssertionError("the search never had a task running after two finished")


def _runs(story: list) -> tuple[int, str]:
    """How many times the scheduler sent a task to a worker, and its last state (from its story)."""
    # A story's transitions are (key, start, finish, ...) tuples.
    return sum(t[2] == "processing" for t in story), story[-1][2] if story else ""


def _kill_workers(cluster: Cluster) -> None:
    """SIGKILL every worker of ``cluster`` (this test's processes, by their ids) and wait until the scheduler knows."""
    for worker in cluster.workers:
        worker.send_signal(signal.SIGKILL)
    for worker in cluster.workers:
        assert worker.wait(timeout=30) == -signal.SIGKILL
    deadline = time.monotonic() + STARTUP
    while cluster.client.nthreads():
        assert time.monotonic() < deadline, "the scheduler still counts the killed workers"
        time.sleep(0.1)


def test_results_give_up_once_every_worker_died_mid_task(own_cluster):
    from qube_koopman.identify.model_selection.distributed import NoWorkersError, ordered_results

    cluster = own_cluster
    results = ordered_results(cluster.client, [(time.sleep, (600.0,), {}) for _ in range(4)], worker_timeout=2.0)
    failure: list = []

    def consume():
        try:
            next(results)
        except NoWorkersError as exc:
            failure.append((time.monotonic(), exc))

    import threading

    waiting = threading.Thread(target=consume, daemon=True)
    waiting.start()
    deadline = time.monotonic() + STARTUP
    while sum(map(len, cluster.client.processing().values())) < 2:  # both workers busy with a 600 s task
        assert time.monotonic() < deadline, "the tasks never started"
        time.sleep(0.05)
    _kill_workers(cluster)
    gone = time.monotonic()
    waiting.join(RUN)
    assert failure, "still waiting for workers that will not come"
    when, exc = failure[0]
    assert when - gone >= 2.0 - 1e-3, "gave up before the timeout (the scheduler saw no worker from `gone` on)"
    assert str(exc) == (
        f"{cluster.address}: no dask worker for 2 s with 4 task(s) waiting (did every worker "
        "stop?); gave up (--worker-timeout)"
    )


def test_qube_identify_gives_up_in_one_line_when_the_cluster_has_no_worker(own_cluster, cluster_logs, tmp_path):
    cluster = own_cluster
    _kill_workers(cluster)
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "qube_koopman.identify.cli.identify",
            *_argv(cluster_logs, tmp_path / "out", "--scheduler", cluster.address, "--worker-timeout", "2"),
        ],
        capture_output=True,
        text=True,
        timeout=RUN,
    )
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith(f"qube-identify: error: {cluster.address}: no dask worker for 2 s with ")
    assert "(--worker-timeout)" in proc.stderr


def test_worker_timeout_is_in_the_help(capsys):
    from qube_koopman.identify.cli.identify import main

    with pytest.raises(SystemExit):
        main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--worker-timeout S" in text and "no worker for this long" in text and "default 120" in text
