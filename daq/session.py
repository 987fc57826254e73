"""A run of episodes: per-episode seeds and excitation, the controller, and the loop over them.

The library behind ``qube-run``: :func:`plan_episodes` makes the plans
(three excitation seeds per episode drawn from one run seed, the rig's
excitation scaled to the episode length) and :func:`run_episodes` runs them
one after the other on a backend, stopping the run on a signal, a backend
fault or a log failure, and going on after a safety stop.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable, Sequence, overload

import numpy as np

from qube_koopman.daq.backends.contract import Backend
from qube_koopman.core.controller_file import ControllerInfo
from qube_koopman.daq.excitation import ExcitationSettings, ExcitationStream
from qube_koopman.daq.log.names import SEED_SIGNALS
from qube_koopman.daq.loop import EpisodePlan, EpisodeResult, run_episode
from qube_koopman.daq.safety import SafetyLimits, StopRequest, stop_on_signals
from qube_koopman.daq.sinks import Sink
from qube_koopman.daq.swing_up import SwingUp
from qube_koopman.daq.timing import DEFAULT_SPIN, TimingRecord

__all__ = [
    "SEED_RANGE",
    "run_seeds",
    "excitation_settings",
    "excitation_record",
    "plan_episodes",
    "EpisodePlans",
    "MAX_EPISODES",
    "RunResult",
    "FATAL_CAUSES",
    "log_outcome",
    "run_episodes",
]

#: Excitation seeds are drawn from this range, as the rig's were (1..999).
SEED_RANGE = (1, 999)

#: Most episodes one run plans (their seeds take 6 bytes each: 6 MB).
MAX_EPISODES = 1_000_000

# The rig's excitation was laid out for 20 s episodes: zero for the first 2000 samples,
# active for samples 2000..7999 (quiet until 4 s, active until 16 s). Other lengths keep these proportions.
_RIG_SECONDS = 20.0

_log = logging.getLogger(__name__)


def run_seeds(seed: int, n_episodes: int) -> tuple[np.ndarray, int]:
    """Three excitation seeds per episode (an ``(n_episodes, 3)`` int16 array) and a seed for
    the backend, all drawn from ``seed``.

    Parameters
    ----------
    seed : int
        The run's seed (``qube-run --seed``).
    n_episodes : int
        Episodes of the run.

    Returns
    -------
    seeds : ndarray of shape (n_episodes, 3)
    backend_seed : int
    """
    if not 0 <= n_episodes <= MAX_EPISODES:
        raise ValueError(f"n_episodes must be in [0, {MAX_EPISODES}], got {n_episodes}")
    rng = np.random.default_rng(seed)
    draws = rng.integers(SEED_RANGE[0], SEED_RANGE[1] + 1, size=(n_episodes, 3)).astype(np.int16)
    return draws, int(rng.integers(2**32))


def excitation_settings(duration: float, sample_rate: float = 500.0) -> ExcitationSettings:
    """The rig's excitation for an episode of ``duration`` seconds.

    At 20 s this is exactly the rig's (active samples 2000..7999 of 10,000);
    for other lengths the active window keeps its place, 20 % to 80 % of
    the episode.

    Parameters
    ----------
    duration : float
        The episode's length (s).
    sample_rate : float
        The loop's rate (Hz).

    Returns
    -------
    ExcitationSettings
    """
    n = round(duration * sample_rate)
    if n < 1 or abs(n - duration * sample_rate) > 1e-6:
        raise ValueError(f"duration {duration} s is not a whole, positive number of samples at {sample_rate} Hz")
    start = round(n * 4.0 / _RIG_SECONDS)
    stop = round(n * 16.0 / _RIG_SECONDS)
    return ExcitationSettings(sample_rate=sample_rate, n_samples=n, window_start=start, window_stop=stop)


def excitation_record(seeds: Sequence[int], settings: ExcitationSettings) -> dict:
    """What the log records of an episode's excitation: enough to regenerate it exactly."""
    return {
        "generator": "daq.excitation.generate_excitation (the rig's PRBS: 16-bit Fibonacci LFSR, taps 16 14 13 11)",
        "seeds": dict(zip(SEED_SIGNALS, (int(s) for s in seeds))),
        "settings": settings.as_dict(),
    }


def plan_episodes(
    controller: ControllerInfo,
    seeds: Sequence[tuple[int, int, int]] | np.ndarray,
    settings: ExcitationSettings,
    source: str = "",
    extra: dict | None = None,
    swing_up: SwingUp | None = None,
) -> "EpisodePlans":
    """One plan per seed triple: the rig's excitation with those seeds, under ``controller``.

    The plans are made one at a time, when asked for (:class:`EpisodePlans`).

    Parameters
    ----------
    controller : ControllerInfo
        The controller every episode runs.
    seeds : sequence of (int, int, int), or ndarray of shape (n_episodes, 3)
        Each episode's excitation seeds (:func:`run_seeds`).
    settings : ExcitationSettings
        The excitation (:func:`excitation_settings`).
    source : str
        What planned the run, recorded in each log.
    extra : dict, optional
        More metadata recorded in each log.
    swing_up : SwingUp, optional
        Start every episode by swinging the pendulum up from hanging (:mod:`daq.swing_up`).

    Returns
    -------
    EpisodePlans
        A sequence of :class:`~qube_koopman.daq.loop.EpisodePlan`.
    """
    return EpisodePlans(controller, seeds, settings, source, extra, swing_up)


class EpisodePlans(Sequence):
    """The plans of a run, each made when it is asked for.

    Only the seeds are kept (6 bytes an episode), so planning a million episodes costs what
    planning one does, plus 6 MB; each plan's excitation is made a chunk at a time as its episode runs.
    """

    def __init__(
        self,
        controller: ControllerInfo,
        seeds: Sequence[tuple[int, int, int]] | np.ndarray,
        settings: ExcitationSettings,
        source: str = "",
        extra: dict | None = None,
        swing_up: SwingUp | None = None,
    ) -> None:
        self.controller = controller
        self.swing_up = swing_up
        self.seeds = np.asarray(seeds, dtype=np.int64).reshape(-1, 3)
        self.settings = settings
        self.source = source
        self.extra = dict(extra or {})

    def __len__(self) -> int:
        return len(self.seeds)

    @overload
    def __getitem__(self, index: int) -> EpisodePlan: ...

    @overload
    def __getitem__(self, index: slice) -> list[EpisodePlan]: ...

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        i = range(len(self))[index]  # IndexError and negative indices as a list's
        s = tuple(int(v) for v in self.seeds[i])
        return EpisodePlan(
            self.controller,
            ExcitationStream(s, self.settings),
            excitation_record(s, self.settings),
            index=i,
            source=self.source,
            extra=dict(self.extra),
            swing_up=self.swing_up,
        )


@dataclass
class RunResult:
    """The episodes of a run, and whether it ended early.

    Parameters
    ----------
    results : list of EpisodeResult
        One per episode attempted.
    stopped : str
        Why the run ended before its last episode; empty when it ran them all.
    signal : int or None
        The signal that ended it, if one did.
    """

    results: list[EpisodeResult] = field(default_factory=list)
    stopped: str = ""
    signal: int | None = None

    @property
    def n_complete(self) -> int:
        """Episodes that ran to their end."""
        return sum(r.complete for r in self.results)

    @property
    def n_aborted(self) -> int:
        """Episodes that ended early (including those that never started)."""
        return len(self.results) - self.n_complete


#: An abort for these causes ends the run: the next episode would fail the same way. (A safety stop
#: or a failed swing-up does not: the next episode's swing-up starts from where the pendulum fell.)
FATAL_CAUSES = ("stop", "fault", "log", "error")


def log_outcome(plan: EpisodePlan, result: EpisodeResult) -> None:
    """Say how an episode ended (an info line of the ``qube_koopman`` log: ``qube-run -v``)."""
    _log.info(
        "episode %d: %s after %d of %d ticks%s",
        plan.index,
        result.status,
        result.n_samples,
        plan.n_samples,
        f" ({result.reason})" if result.reason else "",
    )


def run_episodes(
    backend: Backend,
    plans: Sequence[EpisodePlan],
    sinks: list[Sink],
    *,
    limits: SafetyLimits = SafetyLimits(),
    stop: StopRequest | None = None,
    spin: float = DEFAULT_SPIN,
    on_start: Callable[[EpisodePlan], None] | None = None,
    on_result: Callable[[EpisodePlan, EpisodeResult], None] | None = None,
    timing: TimingRecord | None = None,
) -> RunResult:
    """Run episodes one after the other; SIGINT/SIGTERM end the run cleanly.

    Signal handlers are installed for the duration of the run (restored
    after), so a signal between two episodes also ends the run without
    leaving a log half-written.

    Parameters
    ----------
    backend : Backend
    plans : sequence of EpisodePlan
    sinks : list of Sink
        Receive every episode.
    limits : SafetyLimits
    stop : StopRequest, optional
        Set it to end the run (a signal sets it too).
    spin : float
        Spin before each deadline when the loop paces (s).
    on_start, on_result : callable, optional
        Called before and after each episode (progress, summaries).
    timing : TimingRecord, optional
        Gathers the tick timing of every episode (the run's statistics, in bounded memory).
    """
    stop = stop if stop is not None else StopRequest()
    run = RunResult()
    with stop_on_signals(stop):
        for plan in plans:
            if stop.requested:
                run.stopped = stop.reason
                break
            if on_start is not None:
                on_start(plan)
            result = run_episode(
                backend, plan, sinks, limits=limits, stop=stop, handle_signals=False, spin=spin, timing=timing
            )
            run.results.append(result)
            log_outcome(plan, result)
            if on_result is not None:
                on_result(plan, result)
            if result.cause in FATAL_CAUSES:
                run.stopped = result.reason
                break
    run.signal = stop.signal
    if stop.requested and not run.stopped:
        run.stopped = stop.reason
    return run
