"""Identification while recording: a model kept up to date as episodes complete.

:class:`IncrementalIdentifier` adds one episode's statistics at a time to a running total and
refits (the estimators' public statistics protocol: ``setup_fit``, ``episode_snapshots``,
``statistics_fold``, ``finish_fit``), so an added episode costs one episode's lifting and factor
and one solve, whatever the number of episodes before it. :class:`LiveIdentification` is an episode
sink (``open``, ``write``, ``close``, as ``qube-run``'s sinks are; nothing of ``daq`` is imported):
each complete episode's log is handed to a worker thread that first scores the episode with the model
of the episodes before it (a held-out score no fit saw), then adds it, and tells the stop rule.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from qube_koopman.core.blas import limited_blas_threads
from qube_koopman.core.qube import MEASURED, SKIP_SAMPLES
from qube_koopman.identify.data.logs import LoggedTrajectory, LogTrajectories, load_logs
from qube_koopman.identify.estimators.cl_edmd import ClEdmd, ClEdmdKnownRows
from qube_koopman.identify.estimators.edmd import Edmd
from qube_koopman.identify.estimators.structure import close_loop
from qube_koopman.identify.lifting import GaussianRbf, ThinPlateRbf
from qube_koopman.identify.metrics import EpisodeScore, episode_score
from qube_koopman.identify.uncertainty import Loop, predict_episodes

__all__ = ["IncrementalIdentifier", "LiveIdentification", "LiveScore", "StopRule", "LIVE_METHODS", "score_and_add"]

#: The methods an incremental fit supports (``qube-identify --method``).
LIVE_METHODS = {"cl-edmd": ClEdmd, "cl-edmd-known-rows": ClEdmdKnownRows, "edmd": Edmd}


def _fits_lifting(lifting: Sequence) -> bool:
    """Whether the lifting has parameters fitted on the data (RBF centres drawn in the data's box)."""
    return any(isinstance(step, (ThinPlateRbf, GaussianRbf)) and step.centers is None for step in lifting)


class IncrementalIdentifier:
    """A Koopman model refitted as episodes are added, equal to the batch fit on the same episodes.

    Each :meth:`add` folds one episode's statistics into a running total and solves again:
    ``qube-identify --train <the episodes added> ... --interval 0`` with the same lifting, method
    and alpha gives the same matrices (to rounding). A lifting without parameters fitted on the
    data (monomials, sin/cos, delays, friction, constant) is fitted once on the first episode and
    never changes, so every running model is that batch fit. RBF centres are drawn in the box the
    training data span: while adding, they stay those of the first episode's box (each add then
    costs one episode); :meth:`refit_exact` draws them in the box of every episode added and
    refits once, reading the logs again (the final model of a live run).

    Parameters
    ----------
    lifting : sequence of LiftingFunction
        The lifting of the plant states (``qube-identify``'s lifting options).
    method : {"cl-edmd", "cl-edmd-known-rows", "edmd"}
        The estimator (``qube-identify --method``).
    alpha : float
        The Tikhonov coefficient.

    Attributes
    ----------
    model_ : KoopmanModel
        The closed loop of the first episode's controller, fitted on every episode added.
    plant_model_ : KoopmanModel
        The plant.
    controller_ : DiscreteStateSpace
        The controller the episodes ran.
    logs_ : list of Path
        The episodes added, in order.
    """

    def __init__(self, lifting: Sequence, method: str = "cl-edmd", alpha: float = 1e-3) -> None:
        if method not in LIVE_METHODS:
            raise ValueError(f"an incremental fit supports {', '.join(LIVE_METHODS)}, not {method!r}")
        self.lifting = list(lifting)
        self.method = method
        self.alpha = alpha
        self.logs_: list[Path] = []
        self._estimator: Any = None
        self._setup: Any = None
        self._fold: Any = None

    def _make(self, controller):
        cls = LIVE_METHODS[self.method]
        if cls is Edmd:
            return cls(lifting=self.lifting, alpha=self.alpha)
        return cls(controller, lifting=self.lifting, alpha=self.alpha)

    def _setup_on(self, estimator, trajectories, controller):
        if isinstance(estimator, Edmd):
            return estimator.setup_fit(trajectories)
        return estimator.setup_fit(trajectories, [controller] * len(trajectories))

    @property
    def n_episodes_(self) -> int:
        """Episodes added so far."""
        return len(self.logs_)

    def add(self, log: LoggedTrajectory) -> "IncrementalIdentifier":
        """Fold one episode in and refit.

        Parameters
        ----------
        log : LoggedTrajectory
            A complete episode (:func:`~qube_koopman.identify.data.logs.load_logs`), recorded under the
            first episode's controller.

        Returns
        -------
        self
        """
        from qube_koopman.core.lti import same_system

        if self._estimator is None:
            self.controller_ = log.controller
            self._estimator = self._make(log.controller)
            self._setup = self._setup_on(self._estimator, [log.trajectory], log.controller)
            self._fold = self._estimator.statistics_fold(self._setup)
        elif not same_system(log.controller, self.controller_):
            raise ValueError(f"{log.path}: another controller than the first episode's: an incremental fit needs one")
        self._fold.add(0, self._estimator.episode_snapshots(self._setup, log.trajectory))
        self._estimator.finish_fit(self._setup, self._fold.total())
        self.logs_.append(log.path)
        self._models(self._estimator)
        return self

    def _models(self, estimator) -> None:
        if isinstance(estimator, Edmd):
            self.plant_model_ = estimator.model_
            self.model_ = close_loop(estimator.model_, self.controller_, MEASURED)
        else:
            self.plant_model_, self.model_ = estimator.plant_model_, estimator.closed_loop_model_

    def refit_exact(self, skip: int = SKIP_SAMPLES) -> "IncrementalIdentifier":
        """With RBF centres fitted on the data: draw them in the box of every episode added and refit once.

        The logs are read again (``skip`` samples dropped from each, as when they were added). Without
        such centres the running model is already the batch fit and nothing is done.
        """
        if self._estimator is None or not _fits_lifting(self.lifting):
            return self
        logs = load_logs(self.logs_, skip=skip, stored=True)
        estimator = self._make(self.controller_)
        trajectories = LogTrajectories(logs)
        setup = self._setup_on(estimator, trajectories, self.controller_)
        estimator.fit_setup(setup)
        self._estimator, self._setup = estimator, setup
        self._fold = None  # no more adds after an exact refit: its fold would have to be rebuilt
        self._models(estimator)
        return self

    def predict(self, log: LoggedTrajectory) -> np.ndarray:
        """The closed-loop prediction of an episode's measured states from its references and feedforward.

        Parameters
        ----------
        log : LoggedTrajectory
            An episode under the model's controller (its initial states start the prediction).

        Returns
        -------
        ndarray of shape (n_samples, 2)
        """
        if self._estimator is None:
            raise ValueError("no episode added yet: nothing predicts")
        loop = Loop.of(log.controller, self.controller_, "cl")
        model = loop.model(self.model_, self.plant_model_, MEASURED)
        return predict_episodes([model], [log.trajectory])[0].prediction

    def score(self, log: LoggedTrajectory, start: int = 1) -> EpisodeScore:
        """R^2 and NRMSE of :meth:`predict` on the episode from sample ``start`` on (``qube-identify``'s scores)."""
        return episode_score(log.trajectory.x[:, MEASURED], self.predict(log), start)


@dataclass(frozen=True)
class LiveScore:
    """One episode of a live run: its held-out score (None for the first) and the cost of adding it.

    Attributes
    ----------
    log : Path
    index : int
        Its place among the complete episodes (0: the first).
    score : EpisodeScore or None
        The prediction by the model of the episodes before it; None for the first episode.
    cpu_seconds : float
        The worker thread's CPU time to read, score and add it.
    prediction : ndarray or None
        The predicted measured states (for a view of predicted against measured).
    measured : ndarray or None
    dt : float or None
        The sample period (s).
    first_sample : int
        The log's sample the arrays start at (the samples skipped).
    """

    log: Path
    index: int
    score: EpisodeScore | None
    cpu_seconds: float
    prediction: np.ndarray | None = None
    measured: np.ndarray | None = None
    dt: float | None = None
    first_sample: int = 0

    def as_dict(self) -> dict:
        """report.json's entry."""
        s = self.score
        return {
            "log": self.log.name,
            "n_training_episodes": self.index,
            "r2": None if s is None else float(s.r2),
            "nrmse": None if s is None else float(s.nrmse),
            "diverged_at": None if s is None else s.diverged_at,
            "cpu_seconds": self.cpu_seconds,
        }


@dataclass
class StopRule:
    """When a live run has identified the model.

    With ``until``: stop once the held-out R^2 of the last ``patience`` episodes are all at least
    ``until``. With ``plateau``: stop once at least ``min_scored`` episodes are scored and the best R^2 of
    the last ``window`` episodes beats the best before them by less than ``tolerance``. Neither: never.
    """

    until: float | None = None
    plateau: bool = False
    patience: int = 3
    window: int = 5
    tolerance: float = 1e-3
    min_scored: int = 10
    scores: list = field(default_factory=list)

    def add(self, r2: float) -> str | None:
        """One held-out R^2; why to stop now, or None."""
        self.scores.append(float(r2))
        s = self.scores
        if self.until is not None and len(s) >= self.patience and min(s[-self.patience :]) >= self.until:
            return f"held-out R^2 at least {self.until:g} on the last {self.patience} episodes"
        if self.plateau and len(s) >= max(self.min_scored, self.window + 1):
            gain = max(s[-self.window :]) - max(s[: -self.window])
            if gain < self.tolerance:
                return (
                    f"held-out R^2 plateaued: the last {self.window} episodes' best beats the earlier best "
                    f"by {gain:.2g} < {self.tolerance:g}"
                )
        return None


class LiveIdentification:
    """An episode sink that scores each complete episode with the model of the episodes before it, then adds it.

    ``close`` (on the recording side) only puts the new log's path on a queue; a worker thread reads
    the log, scores and adds it (:class:`IncrementalIdentifier`), so a refit never runs on the loop's
    thread. When the stop rule is met, the next ``close`` sets ``stop`` (the run then ends before its
    next episode, never inside one).

    Parameters
    ----------
    identifier : IncrementalIdentifier
    paths : object with a ``paths`` list
        The episode log sink (its last path is the episode just closed); closed before this sink.
    rule : StopRule
    stop : object with ``requested`` and ``reason``, optional
        The run's stop request.
    skip : int
        Samples dropped at the start of each episode (``qube-identify --skip``).
    on_score : callable, optional
        ``on_score(LiveScore)`` on the worker thread after each episode (console lines, a view).
    keep_predictions : bool
        Keep each score's predicted and measured states.
    max_behind : int, optional
        ``close`` waits until at most this many episodes wait to be scored and added (0: the episode just
        closed is scored before ``close`` returns, and the stop rule is met on the episode that meets it);
        None: never waits (a loop paced by a clock, which must not be held up).
    worker : {"thread", "process"}
        Where episodes are read, scored and added: on this sink's thread, or in one worker process (started
        with ``spawn``) that holds the identifier, so the refits never compete with the loop for this
        process's interpreter; the thread then only waits for its answers.
    """

    required = False

    def __init__(
        self,
        identifier: IncrementalIdentifier,
        paths,
        rule: StopRule | None = None,
        stop=None,
        skip: int = SKIP_SAMPLES,
        on_score: Callable[[LiveScore], None] | None = None,
        keep_predictions: bool = False,
        max_behind: int | None = None,
        worker: str = "thread",
    ) -> None:
        self.identifier = identifier
        self.paths = paths
        self.rule = rule if rule is not None else StopRule()
        self.stop = stop
        self.skip = skip
        self.on_score = on_score
        self.keep_predictions = keep_predictions
        self.max_behind = max_behind
        self._pending = 0
        self._done = threading.Condition()
        self.scores: list[LiveScore] = []
        self.errors: list[str] = []
        self.stop_reason: str | None = None
        if worker not in ("thread", "process"):
            raise ValueError(f"worker must be 'thread' or 'process', got {worker!r}")
        self._pool: Any = None
        if worker == "process":
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            self._pool = ProcessPoolExecutor(
                1, mp_context=multiprocessing.get_context("spawn"), initializer=_start_worker, initargs=(identifier,)
            )
            # Started now, not at the first episode's end: it inherits this process's scheduling as it is before
            # the run (a real-time policy or a pinned CPU set for the loop afterwards is the loop's alone).
            self._pool.submit(_ready).result()
        self._queue: queue.Queue = queue.Queue()
        self._thread = threading.Thread(target=self._work, name="live-identification", daemon=True)
        self._thread.start()

    def open(self, metadata) -> None:
        """An episode starts: nothing to do."""

    def write(self, sample) -> None:
        """A tick: nothing to do (the episode is read from its log once complete)."""

    def close(self, outcome) -> None:
        """Queue a complete episode's log; ask the run to stop when the rule has been met."""
        if outcome.status == "complete" and self.paths.paths:
            with self._done:
                self._pending += 1
            self._queue.put(Path(self.paths.paths[-1]))
            behind = self.max_behind
            if behind is not None:
                with self._done:
                    self._done.wait_for(lambda: self._pending <= behind or not self._thread.is_alive())
        self._ask_stop()

    def _ask_stop(self) -> None:
        if self.stop_reason is not None and self.stop is not None and not self.stop.requested:
            self.stop.reason = f"identified: {self.stop_reason}"
            self.stop.requested = True

    def _work(self) -> None:
        # One BLAS thread: a refit takes one core, never the loop's.
        with limited_blas_threads(1):
            while True:
                path = self._queue.get()
                if path is None:
                    return
                try:
                    self._one(path)
                except Exception as exc:  # noqa: BLE001 - reported with the run's summary, the recording goes on
                    self.errors.append(f"{path}: {exc}")
                finally:
                    with self._done:
                        self._pending -= 1
                        self._done.notify_all()

    def _one(self, path: Path) -> None:
        if self._pool is None:
            live = score_and_add(self.identifier, path, self.skip, self.keep_predictions)
        else:
            live = self._pool.submit(_score_and_add_in_worker, path, self.skip, self.keep_predictions).result()
        if live is None:
            return
        self.scores.append(live)
        if live.score is not None and self.stop_reason is None:
            self.stop_reason = self.rule.add(live.score.r2)
        if self.on_score is not None:
            self.on_score(live)

    def finish(self) -> list[LiveScore]:
        """Wait for the queued episodes to be scored and added; the scores, in episode order.

        With a worker process, :attr:`identifier` is then the worker's (every episode added), and the process ends.
        """
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        if self._pool is not None:
            try:
                self.identifier = self._pool.submit(_identifier_in_worker).result()
            finally:
                self._pool.shutdown()
                self._pool = None
        return list(self.scores)


def score_and_add(ident: IncrementalIdentifier, path: Path, skip: int, keep: bool = False) -> LiveScore | None:
    """Read one log, score it with ``ident``'s model (none for the first episode), then add it to ``ident``.

    None when the log is not a complete episode. The CPU time is that of the calling thread.
    """
    start = time.thread_time()
    logs = load_logs([path], skip=skip)
    if not logs:
        return None
    log = logs[0]
    assert isinstance(log, LoggedTrajectory)  # read now (not stored)
    score = prediction = None
    if ident.n_episodes_:
        prediction = ident.predict(log)
        score = episode_score(log.trajectory.x[:, MEASURED], prediction, 1)
    ident.add(log)
    keep = keep and prediction is not None
    return LiveScore(
        path,
        ident.n_episodes_ - 1,
        score,
        time.thread_time() - start,
        prediction if keep else None,
        log.trajectory.x[:, MEASURED] if keep else None,
        log.dt,
        skip,
    )


# The worker process's identifier (worker="process"): one process, one identifier.
_WORKER: dict = {}


def _start_worker(identifier: IncrementalIdentifier) -> None:
    _WORKER["identifier"] = identifier


def _ready() -> bool:
    return True


def _score_and_add_in_worker(path: Path, skip: int, keep: bool) -> LiveScore | None:
    with limited_blas_threads(1):  # one core: the other is the loop's
        return score_and_add(_WORKER["identifier"], path, skip, keep)


def _identifier_in_worker() -> IncrementalIdentifier:
    return _WORKER["identifier"]
