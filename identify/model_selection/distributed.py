"""Identification's independent pieces on a dask.distributed cluster (``qube-identify --scheduler``).

Two kinds of work go to the workers, and come back in the order they were sent, so that a
cluster run folds exactly what a local run folds:

* the lifting search's candidates (:func:`candidate_runner`; they share the loaded episodes,
  sent to the cluster once);
* the per-episode snapshot statistics of a fit or a regularization sweep
  (:class:`ClusterStatistics`): a worker reads one training log, lifts it and returns its
  :class:`~qube_koopman.identify.estimators.regression.Snapshots` factor (at most p x p, p the
  regressors and targets); the client folds the factors as they come back. A worker reads the
  log at its path when the workers see the client's files (``shared``), or from the bytes the
  client sends with the task.

dask reschedules the tasks of a worker that dies on the others; the results are the same.
When the cluster has had no worker at all for ``worker_timeout`` seconds (default
:data:`DEFAULT_WORKER_TIMEOUT`) while results are awaited, the client gives up
(:class:`NoWorkersError`) rather than wait for workers that may never come back.
The scheduler and the workers need this package installed, at the client's version (checked on
connecting): dask unpickles the tasks on both.
"""

from __future__ import annotations

import tempfile
import time
from collections import deque
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

__all__ = [
    "connect",
    "ordered_results",
    "candidate_runner",
    "release_workers",
    "LogSource",
    "ClusterStatistics",
    "NoWorkersError",
    "DEFAULT_WORKER_TIMEOUT",
]

PACKAGE = "qube-koopman"

#: Seconds without any worker on the cluster, results still awaited, before the client gives up.
#: Long enough for a nanny to restart a worker or a cluster manager to replace lost ones.
DEFAULT_WORKER_TIMEOUT = 120.0

# Seconds between two looks at the cluster's workers while a result is awaited.
_WORKER_POLL = 1.0


class NoWorkersError(TimeoutError):
    """The cluster has had no worker for the worker timeout while results were awaited."""


def connect(address: str, timeout: float = 30.0, security=None):
    """A dask client of the scheduler at ``address``; it and its workers checked to run this package.

    Parameters
    ----------
    address : str
        The scheduler, e.g. ``tls://host:8786``.
    timeout : float
        Seconds to keep trying to reach it.
    security : distributed.security.Security, optional
        The client's TLS certificates, for a ``tls://`` scheduler (default: dask's configuration,
        ``distributed.comm.tls.*``).

    Returns
    -------
    distributed.Client

    Raises
    ------
    ValueError
        dask.distributed missing, the scheduler unreachable or refusing this client's
        certificate, or the scheduler or a worker without this package (or with another
        version of it).
    """
    try:
        from dask.distributed import Client
    except ImportError:
        raise ValueError(
            'a dask scheduler needs dask.distributed, which is optional: pip install "qube-koopman[dask]"'
        ) from None
    try:
        client = Client(address, timeout=timeout, set_as_default=False, security=security)
    except (OSError, TimeoutError) as exc:
        raise ValueError(f"{address}: cannot reach the dask scheduler ({exc})") from None
    try:
        _check_versions(client, address)
    except BaseException:
        client.close()
        raise
    return client


def _check_versions(client, address: str) -> None:
    """The scheduler and every worker now connected have this package at the client's version.

    Both unpickle the tasks (dask sends the task graph to the scheduler pickled).
    """
    from importlib.metadata import version

    mine = version(PACKAGE)
    # A function of the standard library: it unpickles where this package is missing.
    theirs = {"the scheduler": _answer(client.run_on_scheduler, version, PACKAGE)}
    theirs.update((f"worker {w}", v) for w, v in sorted(client.run(version, PACKAGE, on_error="return").items()))
    for who, found in theirs.items():
        if isinstance(found, BaseException):
            raise ValueError(
                f"{address}: {who} cannot find {PACKAGE} ({found!r}); install it on the scheduler and every worker"
            )
        if found != mine:
            raise ValueError(
                f"{address}: {who} runs {PACKAGE} {found}, this client {mine}; install the same "
                "version on the scheduler and every worker"
            )


def _answer(call, *args):
    """``call(*args)``, or the exception it raised (an answer from afar)."""
    try:
        return call(*args)
    except Exception as exc:  # noqa: BLE001 (whatever the remote side raised is the answer)
        return exc


def ordered_results(
    client,
    calls: Iterable[tuple[Callable, tuple, dict]],
    ahead: int | None = None,
    worker_timeout: float = DEFAULT_WORKER_TIMEOUT,
) -> Iterator:
    """Run ``(function, args, kwargs)`` calls on the cluster; yield their results in the calls' order.

    At most ``ahead`` calls are in flight (default: twice the cluster's threads), so a long
    stream of calls holds a bounded number of results. A call's exception is raised here.

    Raises
    ------
    NoWorkersError
        The cluster had no worker for ``worker_timeout`` seconds while a result was awaited
        (every worker died, none came back).
    """
    ahead = ahead or max(2, 2 * sum(client.nthreads().values()))
    pending: deque = deque()
    for fn, args, kwargs in calls:
        pending.append(client.submit(fn, *args, pure=False, **kwargs))
        if len(pending) >= ahead:
            yield _result(client, pending.popleft(), len(pending) + 1, worker_timeout)
    while pending:
        yield _result(client, pending.popleft(), len(pending) + 1, worker_timeout)


def _result(client, future, waiting: int, worker_timeout: float):
    """``future``'s result; :class:`NoWorkersError` once the cluster has had no worker for ``worker_timeout`` s.

    dask keeps a task whose workers all died waiting for a new one, for ever: the client
    looks at the workers every second meanwhile.
    """
    since = None  # when the cluster was first seen without a worker
    while True:
        try:
            return future.result(timeout=_WORKER_POLL)
        except TimeoutError:
            if future.done():
                # The call's own error, or a result that came just after the wait gave up (a loaded
                # machine): asked again, the future answers at once either way.
                return future.result()
            now = time.monotonic()
            if client.nthreads():
                since = None
            elif since is None:
                since = now
            elif now - since >= worker_timeout:
                raise NoWorkersError(
                    f"{client.scheduler.address}: no dask worker for {worker_timeout:g} s with {waiting} "
                    "task(s) waiting (did every worker stop?); gave up (--worker-timeout)"
                ) from None


def _value(value):
    """On a worker: the value itself (a task whose result the workers share)."""
    return value


def _shared_arguments(
    client, calls: list[tuple[Callable, tuple, dict]], sent: dict[int, tuple]
) -> list[tuple[Callable, tuple, dict]]:
    """The calls with each argument common to several of them sent once, as a task's result.

    Not scattered, as joblib's dask backend does: scattered data has no lineage, and a worker that
    dies with the only copy fails every call that needs it. A task's result the scheduler computes
    again on another worker; the other workers fetch it from one that holds it. ``sent`` keeps
    what earlier calls sent (by the argument's id: ``(argument, future)``), for later ones to reuse.
    """
    seen: dict[int, int] = {}
    for _, args, kwargs in calls:
        for value in (*args, *kwargs.values()):
            seen[id(value)] = seen.get(id(value), 0) + 1
    for _, args, kwargs in calls:
        for value in (*args, *kwargs.values()):
            common = (seen[id(value)] > 1 or id(value) in sent) and value is not None
            if common and not isinstance(value, (str, int, float)) and id(value) not in sent:
                sent[id(value)] = (value, client.submit(_value, value, pure=False))  # the value keeps its id
    swap = lambda value: sent[id(value)][1] if id(value) in sent else value  # noqa: E731
    return [(fn, tuple(swap(v) for v in args), {k: swap(v) for k, v in kwargs.items()}) for fn, args, kwargs in calls]


def candidate_runner(
    n_jobs: int, client=None, worker_timeout: float = DEFAULT_WORKER_TIMEOUT
) -> Callable[[list], Iterator]:
    """A function mapping ``joblib.delayed`` calls to their results, in order.

    On ``client``'s cluster when given (giving up after ``worker_timeout`` s without a
    worker, see :func:`ordered_results`); else through joblib (a well-kept library) on
    ``n_jobs`` local processes (1: in this process).
    """
    sent: dict[int, tuple] = {}  # the search's episodes, sent once for all its stages

    def run(calls):
        calls = list(calls)
        if client is not None:
            yield from ordered_results(
                client, _shared_arguments(client, calls, sent), ahead=len(calls) or 1, worker_timeout=worker_timeout
            )
        elif n_jobs == 1:
            for fn, args, kwargs in calls:
                yield fn(*args, **kwargs)
        else:
            import joblib

            # max_nbytes=None: arguments pickled, not memory-mapped (no shared folders to track)
            yield from joblib.Parallel(n_jobs=n_jobs, return_as="generator", max_nbytes=None)(calls)

    return run


def release_workers(n_jobs: int, client=None) -> None:
    """Stop joblib's reusable local workers (a search leaves no process behind it); close ``client``."""
    if client is not None:
        client.close()
    elif n_jobs != 1:
        from joblib.externals.loky import get_reusable_executor

        get_reusable_executor().shutdown(wait=True)


@dataclass(frozen=True)
class LogSource:
    """One training log as a worker gets it: its path, and its bytes when the worker cannot see it.

    Attributes
    ----------
    path : str
        The log's absolute path on the client.
    data : bytes, optional
        The file's content (None: the worker reads ``path`` itself).
    """

    path: str
    data: bytes | None = None

    def read(self, skip: int):
        """The log's :class:`~qube_koopman.identify.data.trajectory.Trajectory`, as ``load_logs`` gives it."""
        from qube_koopman.identify.data.logs import load_logs

        refusal = "the client read it complete: is it the same file on this worker?"
        if self.data is None:
            return load_logs([self.path], skip=skip, strict=True, refusal=refusal)[0].trajectory
        with tempfile.TemporaryDirectory(prefix="qube-log-") as folder:
            copy = Path(folder) / Path(self.path).name  # the same name: the trajectory's
            copy.write_bytes(self.data)
            try:
                return load_logs([copy], skip=skip, strict=True, refusal=refusal)[0].trajectory
            except ValueError as exc:
                raise ValueError(str(exc).replace(str(copy), self.path)) from None


def _episode_part(estimator, setup, source: LogSource, skip: int):
    """On a worker: one log's snapshot statistics (what the estimator's own fit computes for it)."""
    from qube_koopman.core.blas import limited_blas_threads

    with limited_blas_threads(1):
        return estimator.episode_snapshots(setup, source.read(skip))


def _unseen(paths: Sequence[str]) -> list[tuple[str, int | None]]:
    """On a worker: the paths it cannot read as files, with their sizes there (None: missing)."""
    out: list[tuple[str, int | None]] = []
    for path in paths:
        try:
            out.append((path, Path(path).stat().st_size))
        except OSError:
            out.append((path, None))
    return out


class ClusterStatistics:
    """Per-episode snapshot statistics of training logs, computed on a dask cluster.

    Called as ``statistics(estimator, setup, indices)`` (the ``episode_statistics`` of
    :func:`~qube_koopman.identify.model_selection.sweep.regularization_sweep` and
    :func:`~qube_koopman.identify.workflow.identify_and_score`), it yields the statistics of
    the logs at ``indices`` in that order, each computed by a worker from its log, as the
    estimator computes them from ``setup.trajectories`` here.

    Parameters
    ----------
    client : distributed.Client
    paths : sequence of str or Path
        The training logs, in the order of the trajectories.
    skip : int
        Samples dropped at the start of each episode (as when they were loaded here).
    shared : bool
        The workers read the logs at these (absolute) paths; checked on every worker now
        connected. Otherwise each task carries its log's bytes.
    worker_timeout : float
        Seconds without any worker, results awaited, before giving up (:class:`NoWorkersError`).
    """

    def __init__(
        self,
        client,
        paths: Sequence[str | Path],
        skip: int,
        shared: bool = False,
        worker_timeout: float = DEFAULT_WORKER_TIMEOUT,
    ) -> None:
        self.client, self.skip, self.shared = client, int(skip), shared
        self.worker_timeout = float(worker_timeout)
        self.paths = [str(Path(p).resolve()) for p in paths]
        if shared:
            self._check_shared()

    def _check_shared(self) -> None:
        sizes = [Path(p).stat().st_size for p in self.paths]
        for worker, seen in sorted(self.client.run(_unseen, self.paths).items()):
            for (path, size), mine in zip(seen, sizes):
                if size != mine:
                    found = "no such file" if size is None else f"{size} bytes, here {mine}"
                    raise ValueError(
                        f"{path}: not readable as the same file on dask worker {worker} ({found}); "
                        "the workers must see the logs at the same paths, or let the logs be "
                        "shipped to them"
                    )

    def source(self, index: int) -> LogSource:
        """What a worker gets of log ``index``."""
        path = self.paths[index]
        return LogSource(path, None if self.shared else Path(path).read_bytes())

    def __call__(self, estimator, setup, indices: Iterable[int]) -> Iterator:
        light = replace(setup, trajectories=[])  # the worker reads its own episode
        calls: Iterator[tuple[Callable, tuple, dict]] = (
            (_episode_part, (estimator, light, self.source(int(i)), self.skip), {}) for i in indices
        )
        yield from ordered_results(self.client, calls, worker_timeout=self.worker_timeout)
