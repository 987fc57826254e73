"""Where the loop's samples go: sinks fed by a writer thread through a queue.

The loop thread only puts one :class:`Sample` per tick on a queue; a
:class:`SinkWriter` thread hands them to the sinks (episode log, live view,
progress bar), so file I/O and compression never stall a tick. A sink
implements ``open(metadata)``, ``write(sample)`` and ``close(outcome)``; those
run on the writer thread except ``open``, which runs before the first tick.
"""

from __future__ import annotations

import errno
import logging
import shutil
import threading
import time
from collections import deque
from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Any, NamedTuple, NoReturn, Protocol, Sequence, runtime_checkable

import numpy as np

from qube_koopman.daq.episode import Episode, EpisodeMetadata
from qube_koopman.daq.log.names import episode_stem, log_path
from qube_koopman.daq.timing import TimingStats

if TYPE_CHECKING:
    from qube_koopman.daq.log import EpisodeWriter

_log = logging.getLogger(__name__)

__all__ = [
    "Sample",
    "SAMPLE_FIELDS",
    "EpisodeOutcome",
    "Sink",
    "MemorySink",
    "MemoryEpisode",
    "SinkWriter",
    "LogWriteError",
    "BYTES_PER_SAMPLE",
    "McapSink",
    "episode_file_stem",
]


class Sample(NamedTuple):
    """One tick, as the loop hands it to the sinks (units: s, rad, V).

    ``controller_state`` is the state the controller held when it computed
    ``control_output`` (before that tick's update). ``saturation`` is -1, 0
    or +1 when ``plant_input`` was clipped at the lower limit, not clipped,
    or clipped at the upper limit. ``device_time`` is the device's clock
    at the sample (s), NaN when the backend has none. ``controller_record`` is the per-tick
    record of a controller beyond LTI (``ControllerInfo.tick_fields``), empty for an LTI one.
    """

    k: int
    t: float
    theta: float
    alpha: float
    target_theta: float
    target_alpha: float
    feedforward: float
    control_output: float
    plant_input: float
    saturation: int
    lateness: float
    compute_time: float
    controller_state: Sequence[float]
    device_time: float = float("nan")
    controller_record: Sequence[float] = ()


SAMPLE_FIELDS = Sample._fields


@dataclass(frozen=True)
class EpisodeOutcome:
    """How an episode ended.

    Attributes
    ----------
    status : {"complete", "aborted"}
    reason : str
        Why it was aborted; empty when complete.
    n_samples : int
        Ticks recorded.
    timing : TimingStats
    backend_stats : dict
        The backend's counters of the episode (:meth:`~daq.backends.contract.Backend.statistics`).
    """

    status: str
    reason: str
    n_samples: int
    timing: TimingStats
    backend_stats: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        """Plain-data form."""
        return asdict(self)


@runtime_checkable
class Sink(Protocol):
    """A consumer of episodes. ``required = False`` sinks may fail without aborting the episode."""

    required: bool

    def open(self, metadata: EpisodeMetadata) -> None:
        """An episode starts (called on the loop's thread, before tick 0)."""

    def write(self, sample: Sample) -> None:
        """One tick (called on the writer thread, in tick order)."""

    def close(self, outcome: EpisodeOutcome) -> None:
        """The episode ended; every sample has been written (writer thread or caller)."""


@dataclass(eq=False)
class MemoryEpisode:
    """One episode held by :class:`MemorySink`."""

    metadata: EpisodeMetadata
    samples: list = field(default_factory=list)
    outcome: EpisodeOutcome | None = None

    def episode(self) -> Episode:
        """The samples so far as an :class:`~daq.episode.Episode`, with the final status once closed."""
        from dataclasses import replace

        n = len(self.samples)
        n_c = self.metadata.controller.system.n_states
        columns = {
            name: np.array([getattr(s, name) for s in self.samples], dtype=float)
            for name in SAMPLE_FIELDS
            if name not in ("k", "saturation", "controller_state", "controller_record")
        }
        state = np.array([s.controller_state for s in self.samples], dtype=float).reshape(n, n_c)
        saturation = np.array([s.saturation for s in self.samples], dtype=np.int8)
        n_r = len(self.metadata.controller.tick_fields)
        record = np.array([s.controller_record for s in self.samples], dtype=float).reshape(n, n_r)
        meta = self.metadata
        if self.outcome is not None:
            meta = replace(
                meta,
                status=self.outcome.status,
                status_reason=self.outcome.reason,
                timing=self.outcome.timing.as_dict(),
                backend_stats=self.outcome.backend_stats,
            )
        return Episode(
            **columns, controller_state=state, controller_record=record, saturation=saturation, metadata=meta
        )


class MemorySink:
    """Keeps every episode in memory (tests, and quick experiments in a notebook)."""

    required = True

    def __init__(self) -> None:
        self.episodes: list[MemoryEpisode] = []

    def open(self, metadata: EpisodeMetadata) -> None:
        """Start a new episode."""
        self.episodes.append(MemoryEpisode(metadata))

    def write(self, sample: Sample) -> None:
        """Keep one tick."""
        self.episodes[-1].samples.append(sample)

    def close(self, outcome: EpisodeOutcome) -> None:
        """Record how the episode ended."""
        self.episodes[-1].outcome = outcome


# Writer-thread work resumes this long after a tick deadline it waited for (s).
_AFTER_DEADLINE = 50e-6


class SinkWriter:
    """A thread that feeds the loop's samples to the sinks of one episode.

    ``put`` is the only call the loop makes per tick: an append to a deque,
    which wakes nobody. The writer thread polls every ``poll_interval``
    seconds and drains what has accumulated, so it competes with the loop
    for the interpreter a few dozen times a second instead of once per tick.
    A required sink that raises sets :attr:`failed` (the loop then aborts
    the episode); an optional one is dropped with its error recorded in
    :attr:`errors`.

    Parameters
    ----------
    sinks : sequence of Sink
    poll_interval : float
        Seconds between the writer thread's visits to the queue.
    """

    def __init__(self, sinks: Sequence[Sink], poll_interval: float = 0.01) -> None:
        self.sinks = list(sinks)
        self.errors: list[str] = []
        self.failed: str | None = None
        self.poll_interval = poll_interval
        self._queue: deque = deque()
        self._closing = threading.Event()
        self.put = self._queue.append
        self._opened: list[Any] = []
        self._active: list[Any] = []
        self._thread: threading.Thread | None = None
        self._schedule: tuple[float, float, float] | None = None

    def _record(self, sink, what: str, exc: BaseException) -> None:
        message = f"{type(sink).__name__}.{what}: {type(exc).__name__}: {exc}"
        self.errors.append(message)
        if getattr(sink, "required", True) and self.failed is None:
            # The episode's reason: a log's write error says its file and the system's reason
            # already; the sink's and the exception's class names mean nothing to a user.
            self.failed = str(exc) if isinstance(exc, LogWriteError) else message

    def open(self, metadata: EpisodeMetadata) -> bool:
        """Open every sink and start the thread; False when a required sink failed to open."""
        self._opened = []
        for sink in self.sinks:
            try:
                sink.open(metadata)
                self._opened.append(sink)
            except Exception as exc:  # noqa: BLE001 - any sink error is reported, not raised
                self._record(sink, "open", exc)
        self._active = list(self._opened)
        self._thread = threading.Thread(target=self._run, name="episode-writer", daemon=True)
        self._thread.start()
        return self.failed is None

    def wait_below(self, n: int, poll: float = 0.0005) -> None:
        """Block until at most ``n`` samples wait to be written (for free-running loops only).

        A loop without deadlines produces samples faster than a log takes them; without this
        the queue would hold the whole episode (memory growing with its length).
        """
        while len(self._queue) > n and self._thread is not None and self._thread.is_alive():
            time.sleep(poll)

    def keep_clear(self, t0: float, period: float, guard: float) -> None:
        """Do no work in the last ``guard`` seconds before each tick deadline ``t0 + k period``.

        The loop thread wakes shortly before its deadline and then spins;
        Python hands the interpreter lock back and forth every switch
        interval, so a busy writer thread there makes the tick late. Work
        is instead deferred to just after the deadline (``time.perf_counter``
        clock).
        """
        if not (period > 0 and 0 <= guard < period):
            raise ValueError(f"need 0 <= guard < period, got guard {guard}, period {period}")
        self._schedule = (float(t0), float(period), float(guard))

    def _wait_for_window(self) -> None:
        assert self._schedule is not None  # only a scheduled queue waits
        t0, period, guard = self._schedule
        to_deadline = period - (time.perf_counter() - t0) % period
        if to_deadline < guard:
            # Past the deadline plus a little: the loop's tick is then under way.
            time.sleep(to_deadline + _AFTER_DEADLINE)

    def _run(self) -> None:
        pop = self._queue.popleft
        while True:
            # Read the flag before draining: whatever was put before close() is then drained.
            closing = self._closing.is_set()
            while self._queue:
                if self._schedule is not None and not closing:
                    self._wait_for_window()
                item = pop()
                for sink in self._active:
                    try:
                        sink.write(item)
                    except Exception as exc:  # noqa: BLE001
                        self._record(sink, "write", exc)
                        self._active = [s for s in self._active if s is not sink]
            if closing:
                return
            self._closing.wait(self.poll_interval)

    def close(self, outcome: EpisodeOutcome) -> list[str]:
        """Write every queued sample, then close the sinks; returns the errors of the episode."""
        if self._thread is not None:
            self._closing.set()
            self._thread.join()
            self._thread = None
        # A sink that failed mid-episode still gets closed: the log then
        # records the abort and the samples it did take. A required sink that failed while
        # the queue drained after the last tick makes the episode aborted too: never
        # recorded complete with samples missing.
        if self.failed is not None and outcome.status == "complete":
            outcome = replace(outcome, status="aborted", reason=f"log failed: {self.failed}")
        for sink in self._opened:
            if sink in self._active or getattr(sink, "required", True):
                try:
                    sink.close(outcome)
                except Exception as exc:  # noqa: BLE001
                    self._record(sink, "close", exc)
        self._opened = self._active = []
        return list(self.errors)


class McapSink:
    """Writes each episode to its own MCAP episode log in a folder (format: daq/log/FORMAT.md).

    Files are named ``qube_<UTC date>T<time>.<ms>_<s1>_<s2>_<s3>.mcap`` after
    the start time and the excitation seeds, like the dataset's CSV files
    plus milliseconds: free-running episodes start several per second, and
    the names must sort in the order the episodes ran (the paper's split
    takes the first files by name). A name already taken gets a ``_<n>``
    suffix rather than overwriting.

    Parameters
    ----------
    out_dir : str or Path
        Folder for the logs (must exist).
    flush_interval_s : float
        Make the samples durable every this many seconds of data, so a
        killed process loses at most that much.

    Attributes
    ----------
    paths : list of Path
        The files written, in episode order.
    """

    required = True

    def __init__(self, out_dir, flush_interval_s: float = 0.5) -> None:
        from pathlib import Path

        self.out_dir = Path(out_dir)
        self.flush_interval_s = flush_interval_s
        self.paths: list = []
        self.error: LogWriteError | None = None
        self._writer: EpisodeWriter | None = None

    def open(self, metadata: EpisodeMetadata) -> None:
        """Check the free space, create the episode's file and write its metadata (durable at once).

        Raises
        ------
        LogWriteError
            Too little free space for the planned episode, or the file cannot be written.
        """
        from qube_koopman.daq.log import EpisodeWriter

        self.error = None
        base = episode_file_stem(metadata)
        path = log_path(self.out_dir, base)
        n = 1
        while path.exists():
            path = log_path(self.out_dir, f"{base}_{n}")
            n += 1
        need = log_size_needed(int(metadata.extra.get("n_planned", 0)))
        free = shutil.disk_usage(self.out_dir).free
        if free < need:
            self._fail(
                path, OSError(errno.ENOSPC, f"{free / 1e6:.1f} MB free, the episode needs about {need / 1e6:.1f} MB")
            )
        try:
            self._writer = EpisodeWriter(path, metadata, flush_interval_s=self.flush_interval_s)
        except OSError as exc:
            self._fail(path, exc)
        self.paths.append(path)
        _log.debug("writing %s (%.1f MB free, the episode needs about %.1f MB)", path, free / 1e6, need / 1e6)

    def write(self, sample: Sample) -> None:
        """Append one tick (flushed every ``flush_interval_s`` of data)."""
        writer = self._writer
        assert writer is not None, "open() first"
        try:
            writer.write_sample(
                t=sample.t,
                theta=sample.theta,
                alpha=sample.alpha,
                target_theta=sample.target_theta,
                target_alpha=sample.target_alpha,
                feedforward=sample.feedforward,
                controller_state=sample.controller_state,
                control_output=sample.control_output,
                plant_input=sample.plant_input,
                saturation=sample.saturation,
                lateness=sample.lateness,
                compute_time=sample.compute_time,
                device_time=sample.device_time,
                controller_record=sample.controller_record,
            )
        except OSError as exc:
            self._fail(writer.path, exc)

    def close(self, outcome: EpisodeOutcome) -> None:
        """Record the final status, timing statistics and backend counters, and close the file.

        After a write error the file is closed without a status record instead: it then
        reads as incomplete, up to its last flushed chunk.
        """
        writer, self._writer = self._writer, None
        if writer is None or writer.finished:
            return
        if self.error is not None:
            writer.abandon()
            return
        try:
            writer.finish(outcome.status, outcome.reason, outcome.timing.as_dict(), outcome.backend_stats)
        except OSError as exc:
            self._fail(writer.path, exc)

    def _fail(self, path, exc: OSError) -> NoReturn:
        """Record and raise the error as a :class:`LogWriteError` naming ``path``."""
        self.error = exc if isinstance(exc, LogWriteError) else LogWriteError(path, exc)
        raise self.error from None


#: Bytes an episode log takes per sample at most: the payload (about 120 bytes) and its MCAP
#: message record and index entries (about 60 bytes), as if compression saved nothing.
BYTES_PER_SAMPLE = 200


def log_size_needed(n_samples: int) -> int:
    """Free space (bytes) an episode of ``n_samples`` must find before it starts: twice the
    uncompressed size (:data:`BYTES_PER_SAMPLE`) plus 1 MB for the metadata and the summary."""
    return 2 * BYTES_PER_SAMPLE * max(n_samples, 0) + 1_000_000


class LogWriteError(OSError):
    """An episode log could not be written: the file and the operating system's reason.

    ``str()`` reads ``<file>: <reason> (<ERRNO>)``.
    """

    def __init__(self, path, cause: OSError) -> None:
        super().__init__(cause.errno, cause.strerror or str(cause))
        self.path = path
        self.cause = cause

    def __str__(self) -> str:
        name = errno.errorcode.get(self.errno, "") if self.errno else ""
        return f"{self.path}: {self.strerror}" + (f" ({name})" if name else "")

    def __reduce__(self):
        # OSError pickles as (errno, strerror): the path would be lost on the way back from a
        # worker process (daq.parallel).
        return type(self), (self.path, self.cause)


def episode_file_stem(metadata: EpisodeMetadata) -> str:
    """``qube_<date>T<time>.<ms>_<s1>_<s2>_<s3>``: start time (UTC, ISO 8601 basic) and excitation seeds
    (:func:`daq.log.names.episode_stem` of the metadata)."""
    return episode_stem(metadata.start_datetime, metadata.excitation.get("seeds", {}))
