"""Episode logs as identification data: finding, reading, checking.

The only module of ``identify`` that reads ``daq``'s episode logs (lazily: mcap and
zstandard load with the first log read).
"""

from __future__ import annotations

import logging
import os
import threading
import time
import warnings
from collections import OrderedDict
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from qube_koopman.core.qube import STATE_NAMES
from qube_koopman.identify.data.trajectory import SIGNALS, EpisodeSequence, EpisodeShape, Trajectory
from qube_koopman.core.lti import DiscreteStateSpace, same_system

__all__ = [
    "LoggedTrajectory",
    "StoredLog",
    "LogTrajectories",
    "load_logs",
    "check_same_controller",
    "check_same_rate",
    "recorded_controllers",
    "IncompleteLogSkipped",
    "UnreadableLogSkipped",
    "find_logs",
    "expand_logs",
    "read_episodes",
]


_log = logging.getLogger(__name__)


class IncompleteLogSkipped(UserWarning):
    """An incomplete (aborted or salvaged) log was left out of the data."""


class UnreadableLogSkipped(IncompleteLogSkipped):
    """A file that cannot be read as an episode log (empty, not MCAP, no metadata) was left out."""


@dataclass(frozen=True, eq=False)
class LoggedTrajectory:
    """One episode log, ready for identification (what :func:`load_logs` returns, one per log).

    Parameters
    ----------
    path : Path
        The log.
    trajectory : Trajectory
        Its signals, after the samples skipped.
    controller : DiscreteStateSpace
        The controller the log records, as the rig ran it (or the loop's as it ran, when
        ``recorded_controller`` is given).
    gains : dict, optional
        The gains that controller was built from (a PD's), if the log records them.
    recorded_controller : DiscreteStateSpace, optional
        The controller the log records, when ``controller`` is the loop's instead (a session's
        command delay after it: :func:`~qube_koopman.identify.estimators.structure.with_command_delay`).
    """

    path: Path
    trajectory: Trajectory
    controller: DiscreteStateSpace
    gains: dict | None = None
    recorded_controller: DiscreteStateSpace | None = None

    @property
    def dt(self) -> float:
        """Sample period (s)."""
        dt = self.trajectory.dt
        assert dt is not None  # _read gives a log's trajectory its sample period
        return dt

    @property
    def n_samples(self) -> int:
        """Samples of the trajectory (after those skipped)."""
        return self.trajectory.n_samples


@dataclass(frozen=True, eq=False)
class StoredLog:
    """One episode log kept on disk: its small metadata in memory, its trajectory read when asked for.

    :attr:`trajectory` reads the log again at every access (about 10 ms for 20 s at 500 Hz), unless
    the process's small cache of decoded logs still holds it (:data:`LOG_CACHE_BYTES`): a fit over
    many episodes holds one at a time beside that cache (0.6 MB each), so memory does not grow with
    the number of episodes.
    Otherwise it stands for a :class:`LoggedTrajectory`.
    """

    path: Path
    controller: DiscreteStateSpace
    gains: dict | None
    dt: float
    n_samples: int
    skip: int = 0
    #: Its trajectory's name, length and signal widths, as first read (checks read these, not the log).
    shape: EpisodeShape | None = None
    #: Applied to the trajectory at every read: how the loop the log ran differs from what it
    #: records (a session's command delay: :func:`~qube_koopman.identify.estimators.structure.with_command_delay`).
    #: A module-level function or a ``functools.partial`` of one, so that the log still pickles.
    adjust: Callable[[Trajectory], Trajectory] | None = None
    #: The controller the log records, when :attr:`controller` is the loop's as it ran (as for
    #: :class:`LoggedTrajectory`).
    recorded_controller: DiscreteStateSpace | None = None

    @property
    def trajectory(self) -> Trajectory:
        """The episode's trajectory, read from the log now (``skip`` samples dropped)."""
        log, _ = _read(self.path, self.skip, strict=True, refusal="changed since it was first read")
        assert log is not None  # strict: _read raises instead
        return log.trajectory if self.adjust is None else self.adjust(log.trajectory)


class LogTrajectories(EpisodeSequence):
    """The trajectories of logs as a lazy sequence: a stored log's is read when asked for, one at a time.

    Picklable (paths and metadata): a worker reading the same files rebuilds the episodes itself.
    """

    def __init__(self, logs: Sequence[LoggedTrajectory | StoredLog]) -> None:
        self.logs = tuple(logs)

    def __len__(self) -> int:
        return len(self.logs)

    def _make(self, i: int) -> Trajectory:
        return self.logs[i].trajectory

    def shapes(self) -> list[EpisodeShape] | None:
        shapes = [log.shape if isinstance(log, StoredLog) else log.trajectory.shape() for log in self.logs]
        return None if any(shape is None for shape in shapes) else shapes  # type: ignore[return-value]


#: Bytes of decoded logs a process keeps for their next read (``$QUBE_KOOPMAN_LOG_CACHE_MB``
#: megabytes when set; 0 turns the cache off). A fit reads each training log several times (the
#: lifting's fit, the statistics, the intervals' refits) and a search once per stage: decoding
#: is most of a read's 10-30 ms, and the paper's 48 logs take 29 MB decoded. The budget is a
#: constant, so memory still does not grow with the number of logs. An entry holds for the file
#: as it was: a file changed since (its size, modification time or inode) is read again, and
#: checked again.
LOG_CACHE_BYTES = 64 * 2**20

#: A full cache makes room only by dropping logs not read for this long (s); otherwise it keeps
#: what it holds and the new log is not kept. Written by hand rather than functools' LRU cache
#: for this: passes over more logs than the budget holds would have each log pushed out before
#: its next read, decoding them all every pass, where keeping the first ones saves their share.
#: Logs a finished fit left behind (a notebook's earlier dataset) go after this long.
LOG_CACHE_IDLE_S = 30.0

# Least recently read first: key -> (log, samples, bytes, last read on _clock). Written read-only, as
# every caller gets the same arrays. Threads fold episodes' statistics in parallel, hence the lock.
_CACHE: OrderedDict[tuple, tuple[LoggedTrajectory, int, int, float]] = OrderedDict()
_CACHE_LOCK = threading.Lock()
_clock = time.monotonic


def _cache_budget() -> int:
    value = os.environ.get("QUBE_KOOPMAN_LOG_CACHE_MB")
    if value is None:
        return LOG_CACHE_BYTES
    try:
        return max(0, int(float(value) * 2**20))
    except ValueError:
        return LOG_CACHE_BYTES  # a malformed value: the default, rather than failing a fit over it


def clear_log_cache() -> None:
    """Forget every decoded log this process keeps (:data:`LOG_CACHE_BYTES`)."""
    with _CACHE_LOCK:
        _CACHE.clear()


def _cache_key(path: Path, skip: int) -> tuple | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return (os.path.abspath(path), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, skip)


def _read(path: Path, skip: int, strict: bool, refusal: str) -> tuple[LoggedTrajectory | None, int]:
    """One log as a :class:`LoggedTrajectory` and its samples (None when skipped, with a warning),
    from the cache of decoded logs when it holds the file as it is now."""
    if not path.is_file():
        raise ValueError(f"{path}: no such log file")
    key = _cache_key(path, skip)
    hit = None
    if key is not None:
        with _CACHE_LOCK:
            hit = _CACHE.get(key)
            if hit is not None:
                _CACHE[key] = (*hit[:3], _clock())
                _CACHE.move_to_end(key)
    if hit is not None:
        cached, n = hit[:2]  # the caller's own path (messages name the file as given) and gains
        return replace(cached, path=path, gains=None if cached.gains is None else dict(cached.gains)), n
    log, n = _decode(path, skip, strict, refusal)
    if log is not None:
        _read_only(log.trajectory)  # kept or not, alike: a reader that writes to them fails every time
        if key is not None and _cache_key(path, skip) == key:
            _keep(key, log, n)
    return log, n


def _keep(key: tuple, log: LoggedTrajectory, n: int) -> None:
    """Keep a decoded log if the budget has room, or if logs idle for :data:`LOG_CACHE_IDLE_S` can make it."""
    budget = _cache_budget()
    size = sum(a.nbytes for a in _arrays(log.trajectory))
    if size > budget:
        return
    with _CACHE_LOCK:
        now, total = _clock(), sum(entry[2] for entry in _CACHE.values())
        while _CACHE and total + size > budget:
            oldest = next(iter(_CACHE))
            if now - _CACHE[oldest][3] < LOG_CACHE_IDLE_S:
                return  # least recently read first: every other one was read more recently
            total -= _CACHE.pop(oldest)[2]
        _CACHE[key] = (log, n, size, now)


def _arrays(traj: Trajectory) -> list[np.ndarray]:
    """A trajectory's signals that it has (the states and :data:`~qube_koopman.identify.data.trajectory.SIGNALS`)."""
    return [a for a in (getattr(traj, name) for name in ("x", *SIGNALS)) if a is not None]


def _read_only(traj: Trajectory) -> None:
    """Mark a read log's arrays read-only (a cached log's reach every reader of the file)."""
    for a in _arrays(traj):
        a.flags.writeable = False


def _decode(path: Path, skip: int, strict: bool, refusal: str) -> tuple[LoggedTrajectory | None, int]:
    """One log read from its file (see :func:`_read`)."""
    from qube_koopman.daq.log import read_episode  # lazily: mcap and zstandard

    try:
        episode = read_episode(path, warn=False)
    except (ValueError, OSError) as exc:
        problem = str(exc).removeprefix(f"{path}: ") if isinstance(exc, ValueError) else exc.strerror or exc
        if strict:
            raise ValueError(f"{path}: {problem}; {refusal}") from None
        warnings.warn(f"{path}: {problem}; skipped", UnreadableLogSkipped, stacklevel=3)
        return None, 0
    if not episode.is_complete:
        reason = episode.metadata.status_reason or episode.metadata.salvage_note or episode.metadata.status
        if strict:
            raise ValueError(f"{path}: incomplete episode ({reason}); {refusal}")
        warnings.warn(f"{path}: incomplete episode ({reason}); skipped", IncompleteLogSkipped, stacklevel=3)
        return None, 0
    if len(episode) <= skip + 2:
        raise ValueError(f"{path}: {len(episode)} samples, too few to drop {skip} and identify")
    traj = Trajectory(
        x=episode.states,
        u=np.asarray(episode.plant_input)[:, None],
        r=episode.references,
        f=np.asarray(episode.feedforward)[:, None],
        xc=episode.controller_state,
        name=path.name,
        state_names=STATE_NAMES,
        input_names=("u",),
        dt=episode.dt,
    )
    return LoggedTrajectory(
        path, traj.skip(skip), episode.controller, dict(episode.metadata.controller.gains) or None
    ), len(episode)


def load_logs(
    paths: Sequence[str | Path],
    skip: int = 0,
    strict: bool = False,
    *,
    refusal: str = "refused because of --strict",
    stored: bool = False,
) -> list[LoggedTrajectory | StoredLog]:
    """Read MCAP episode logs into trajectories, dropping ``skip`` samples at each start.

    Incomplete logs (aborted, or cut short and salvaged) are skipped with an
    :class:`IncompleteLogSkipped` warning, unreadable ones (empty, not MCAP,
    damaged before the episode's metadata) with an :class:`UnreadableLogSkipped`
    warning, one per file naming it and the reason; both are refused when ``strict``.

    Parameters
    ----------
    paths : sequence of str or Path
        The log files.
    skip : int, default 0
        Samples dropped at the start of each episode.
    strict : bool, default False
        Refuse an unreadable or incomplete log instead of skipping it.
    refusal : str, default "refused because of --strict"
        What the error of a refused log ends with: why it is refused (a command that always
        refuses, without a ``--strict`` option, says so in its own words).

    stored : bool, default False
        Keep each log on disk (a :class:`StoredLog`, its trajectory read again when asked for)
        instead of in memory: every log is read and checked now, one at a time, and memory
        does not grow with the number of logs.

    Raises
    ------
    ValueError
        Naming the file: unreadable, not an episode log, incomplete with
        ``strict``, or too short for ``skip``.
    """
    if skip < 0:
        raise ValueError(f"skip must be >= 0, got {skip}")
    out: list[LoggedTrajectory | StoredLog] = []
    for raw in paths:
        path = Path(raw)
        log, n = _read(path, skip, strict, refusal)
        if log is None:
            continue
        out.append(
            StoredLog(path, log.controller, log.gains, log.dt, log.n_samples, skip, log.trajectory.shape())
            if stored
            else log
        )
        _log.debug("%s: %d samples at %g Hz", path, n, 1.0 / log.dt)
    _log.info("read %d of %d episode logs", len(out), len(paths))
    return out


def recorded_controllers(logs: Sequence[LoggedTrajectory | StoredLog]) -> list[DiscreteStateSpace] | None:
    """The controller each log records, when some log's loop is not its controller alone (its
    :attr:`~LoggedTrajectory.recorded_controller` is given); None when every log's is."""
    if all(log.recorded_controller is None for log in logs):
        return None
    return [log.controller if log.recorded_controller is None else log.recorded_controller for log in logs]


def check_same_rate(logs: Sequence[LoggedTrajectory | StoredLog], what: str) -> float:
    """The common sample period of the logs; a ValueError naming the odd file otherwise."""
    dt = logs[0].dt
    for log in logs[1:]:
        if not np.isclose(log.dt, dt, rtol=1e-9, atol=0):
            raise ValueError(
                f"{log.path}: sample rate {1 / log.dt:g} Hz differs from "
                f"{1 / dt:g} Hz of {logs[0].path.name} ({what} logs must share one rate)"
            )
    return dt


def check_same_controller(logs: Sequence[LoggedTrajectory | StoredLog], what: str) -> DiscreteStateSpace:
    """The common controller of the logs; a ValueError naming the odd file otherwise."""
    controller = logs[0].controller
    for log in logs[1:]:
        if not same_system(log.controller, controller):
            raise ValueError(
                f"{log.path}: its controller differs from that of {logs[0].path.name} "
                f"({what} logs must share one controller)"
            )
    return controller


def find_logs(folder: str | Path) -> list[Path]:
    """The episode logs in ``folder``, sorted by name (so in the order they ran).

    Parameters
    ----------
    folder : str or Path

    Returns
    -------
    list of Path
    """
    from qube_koopman.daq.log.names import find_logs as logs_in

    return logs_in(folder)


def expand_logs(items) -> list[Path]:
    """Log paths from a command line: files as given, folders as the logs in them (by name).

    Raises
    ------
    CliError
        An item that does not exist, or a folder without logs (the message names it).
    """
    from qube_koopman.daq.log.names import expand_logs as expand

    return expand(items)


def read_episodes(logs: Sequence[LoggedTrajectory | StoredLog]) -> list:
    """The whole recorded episodes of ``logs`` (every signal and the metadata, as
    :func:`qube_koopman.daq.read_episode` gives them), for work that needs more than the trajectory.

    Parameters
    ----------
    logs : sequence of LoggedTrajectory or StoredLog
        Logs :func:`load_logs` accepted.

    Returns
    -------
    list of Episode
    """
    from qube_koopman.daq.log import read_episode

    return [read_episode(log.path, warn=False) for log in logs]
