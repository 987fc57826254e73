"""Real-time pacing and timing statistics of the acquisition loop.

Ticks are paced by absolute deadlines ``t0 + k T`` (relative sleeps drift),
reached by a hybrid wait: sleep until shortly before the deadline, then spin
on ``time.perf_counter`` (measured on a 2-core VM: an absolute-deadline sleep alone is
94 us late at the median and 3.2 ms at p99; the hybrid wait with SCHED_FIFO and CPU pinning,
88 us at p99). CPU pinning and SCHED_FIFO are attempted only when
asked for, and their failure is reported rather than raised: the loop works
without them.
"""

from __future__ import annotations

import gc
import math
import os
import sys
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from typing import Callable, Iterator

import numpy as np

__all__ = [
    "DEFAULT_SPIN",
    "STALL_THRESHOLD",
    "DeadlinePacer",
    "TimingStats",
    "TimingRecord",
    "EXACT_TICKS",
    "timing_stats",
    "RealtimeReport",
    "realtime_scheduling",
    "quiet_interpreter",
]

#: Spin this long before each deadline (s): covers the usual sleep overshoot.
DEFAULT_SPIN = 300e-6

#: A tick this late (s) is counted as a stall (VM steal, page fault...), not hidden.
STALL_THRESHOLD = 2e-3

#: A device that keeps the clock (the bridge) with no tick reaching the host for this much more
#: than a period (s) has stalled (:attr:`TimingStats.device_stalls`): five periods, the bridge's
#: watchdog span; a frame or two lost on the link are counted as missed ticks only.
DEVICE_STALL_THRESHOLD = 10e-3


class DeadlinePacer:
    """Wait for tick ``k``'s absolute deadline ``t0 + k period`` with a hybrid sleep-then-spin.

    Parameters
    ----------
    period : float
        Tick period (s).
    spin : float
        How long before the deadline to stop sleeping and start spinning (s).
    clock, sleep : callable
        Time source and sleep function (replaceable in tests).
    """

    def __init__(
        self,
        period: float,
        spin: float = DEFAULT_SPIN,
        clock: Callable[[], float] = time.perf_counter,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if not (math.isfinite(period) and period > 0):
            raise ValueError(f"period must be a positive number of seconds, got {period!r}")
        if not (math.isfinite(spin) and spin >= 0):
            raise ValueError(f"spin must be a non-negative number of seconds, got {spin!r}")
        self.period = float(period)
        self.spin = float(spin)
        self._clock = clock
        self._sleep = sleep
        self.t0 = clock()

    def start(self, t0: float | None = None) -> float:
        """Set time zero (now by default): tick 0's deadline. Returns it."""
        self.t0 = self._clock() if t0 is None else float(t0)
        return self.t0

    def deadline(self, k: int) -> float:
        """Absolute deadline of tick ``k``."""
        return self.t0 + k * self.period

    def wait(self, k: int) -> float:
        """Return at tick ``k``'s deadline (at once if it has passed); the lateness (s)."""
        deadline = self.t0 + k * self.period
        clock = self._clock
        remaining = deadline - clock()
        if remaining > self.spin:
            self._sleep(remaining - self.spin)
        now = clock()
        while now < deadline:
            now = clock()
        return now - deadline


@dataclass(frozen=True)
class TimingStats:
    """Timing of one episode's ticks.

    Attributes
    ----------
    n_ticks : int
        Ticks measured.
    period : float
        Nominal tick period (s).
    paced : bool
        Whether ticks had deadlines (lateness measured); free-running ticks
        have none and their lateness fields are NaN.
    lateness_p50, lateness_p99, lateness_max : float
        How late ticks started against their deadlines (s).
    overruns : int
        Ticks whose command went out after the next tick's deadline
        (lateness + compute time > period).
    stalls : int
        Ticks that started more than :data:`STALL_THRESHOLD` late.
    compute_p50, compute_p99, compute_max : float
        Time from the tick's start to its command being written (s).
    device_stalls : int
        Times a device that keeps the clock (the bridge) went silent for more than one period
        while its clock ran on: the ticks in between are missing from the log, and the host's
        lateness does not show it (it is measured on that clock).
    device_stall_time, device_stall_max : float
        Their total and longest duration (s): the time their missing ticks span.
    device_stall_first : float or None
        Episode time (s) of the sample after the first one (None: none).
    """

    n_ticks: int
    period: float
    paced: bool
    lateness_p50: float = math.nan
    lateness_p99: float = math.nan
    lateness_max: float = math.nan
    overruns: int = 0
    stalls: int = 0
    compute_p50: float = math.nan
    compute_p99: float = math.nan
    compute_max: float = math.nan
    device_stalls: int = 0
    device_stall_time: float = 0.0
    device_stall_max: float = 0.0
    device_stall_first: float | None = None

    def as_dict(self) -> dict:
        """Plain-data form (None where not measured: JSON has no NaN), for logs and summaries."""
        return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in asdict(self).items()}


#: Up to this many values a series keeps them all and its percentiles are exact (131 s at
#: 500 Hz); past it, it keeps a fixed histogram instead (:class:`TimingRecord`).
EXACT_TICKS = 1 << 16

# The histogram: magnitudes from 1e-7 s to 10 s in 200 log-spaced bins a decade (a bin is
# 1.2 % wide), mirrored for negative values, one bin for |v| < 1e-7 s; ends clamp.
_HIST_FLOOR = 1e-7
_HIST_PER_DECADE = 200
_HIST_HALF = 8 * _HIST_PER_DECADE


def _bin_index(values: np.ndarray) -> np.ndarray:
    magnitude = np.abs(values)
    i = np.floor(np.log10(np.maximum(magnitude, _HIST_FLOOR) / _HIST_FLOOR) * _HIST_PER_DECADE)
    i = np.clip(i, 0, _HIST_HALF - 1).astype(np.intp)
    return np.where(magnitude < _HIST_FLOOR, _HIST_HALF, np.where(values > 0, _HIST_HALF + 1 + i, _HIST_HALF - 1 - i))


def _bin_value(index: int) -> float:
    if index == _HIST_HALF:
        return 0.0
    i = index - _HIST_HALF - 1 if index > _HIST_HALF else _HIST_HALF - 1 - index
    middle = _HIST_FLOOR * 10.0 ** ((i + 0.5) / _HIST_PER_DECADE)
    return middle if index > _HIST_HALF else -middle


class _Series:
    """One timing quantity in bounded memory: exact values up to :data:`EXACT_TICKS`, then a histogram."""

    def __init__(self) -> None:
        self.n = 0
        self.low, self.high = math.inf, -math.inf
        self._parts: list[np.ndarray] = []
        self._hist: np.ndarray | None = None

    def add(self, values: np.ndarray) -> None:
        if values.size == 0:
            return
        self.n += values.size
        self.low, self.high = min(self.low, float(values.min())), max(self.high, float(values.max()))
        if self._hist is None and self.n <= EXACT_TICKS:
            self._parts.append(np.array(values, dtype=float))
            return
        hist = self._histogram()
        hist += np.bincount(_bin_index(values), minlength=hist.size)

    def _histogram(self) -> np.ndarray:
        """Keep the histogram from now on, the exact values kept so far counted in it; returns it."""
        if self._hist is None:
            self._hist = np.zeros(2 * _HIST_HALF + 1, dtype=np.int64)
            if self._parts:
                self._hist += np.bincount(_bin_index(np.concatenate(self._parts)), minlength=self._hist.size)
            self._parts = []
        return self._hist

    def merge(self, other: "_Series") -> None:
        """Add the values ``other`` holds (exact values, or its histogram)."""
        if other.n == 0:
            return
        if other._hist is None:
            self.add(np.concatenate(other._parts))
            return
        hist = self._histogram()
        hist += other._hist
        self.n += other.n
        self.low, self.high = min(self.low, other.low), max(self.high, other.high)

    def summary(self) -> tuple[float, float, float]:
        """(p50, p99, max); NaN when empty. Exact up to :data:`EXACT_TICKS` values, else within a bin."""
        if self.n == 0:
            return math.nan, math.nan, math.nan
        if self._hist is None:
            p50, p99 = np.percentile(np.concatenate(self._parts), [50, 99])
            return float(p50), float(p99), self.high
        cumulative = np.cumsum(self._hist)
        out = []
        for q in (50, 99):
            rank = math.floor(q / 100 * (self.n - 1))  # the order statistic below the percentile
            index = int(np.searchsorted(cumulative, rank + 1))
            out.append(min(max(_bin_value(index), self.low), self.high))
        return out[0], out[1], self.high


class TimingRecord:
    """Timing statistics of ticks fed a chunk at a time, in memory that does not grow with their number.

    Counts (ticks, overruns, stalls) and maxima are exact; the percentiles are exact up to
    :data:`EXACT_TICKS` measured ticks, then read from a fixed histogram (within 1.2 %).

    Parameters
    ----------
    period : float
        Nominal tick period (s).
    """

    def __init__(self, period: float) -> None:
        self.period = float(period)
        self.n_ticks = 0
        self.overruns = 0
        self.stalls = 0
        self.device_stalls = 0
        self.device_stall_time = 0.0
        self.device_stall_max = 0.0
        self.device_stall_first: float | None = None
        self._lateness = _Series()
        self._compute = _Series()

    def add(self, lateness, compute_time) -> None:
        """Add ticks: their lateness (NaN when not paced) and compute time (s), 1-D arrays of one length."""
        lateness = np.asarray(lateness, dtype=float)
        compute = np.asarray(compute_time, dtype=float)
        if lateness.shape != compute.shape or lateness.ndim != 1:
            raise ValueError(
                f"lateness {lateness.shape} and compute_time {compute.shape} must be 1-D arrays of the same length"
            )
        self.n_ticks += lateness.size
        self._compute.add(compute[np.isfinite(compute)])
        measured = np.isfinite(lateness)
        late = lateness[measured]
        self._lateness.add(late)
        self.overruns += int(np.count_nonzero(late + np.nan_to_num(compute[measured]) > self.period))
        self.stalls += int(np.count_nonzero(late > STALL_THRESHOLD))

    def device_stall(self, t: float, held: float) -> None:
        """The device's clock ran ``held`` seconds past a period without a tick reaching the host, before time ``t``."""
        self.device_stalls += 1
        self.device_stall_time += held
        self.device_stall_max = max(self.device_stall_max, held)
        if self.device_stall_first is None:
            self.device_stall_first = t

    def merge(self, other: "TimingRecord") -> None:
        """Add the ticks ``other`` recorded (another process's episodes, say), as if added here.

        Parameters
        ----------
        other : TimingRecord
            Of the same period; left unchanged.
        """
        if other.period != self.period:
            raise ValueError(f"cannot merge ticks of period {other.period} s into a record of {self.period} s")
        self.n_ticks += other.n_ticks
        self.overruns += other.overruns
        self.stalls += other.stalls
        self.device_stalls += other.device_stalls
        self.device_stall_time += other.device_stall_time
        self.device_stall_max = max(self.device_stall_max, other.device_stall_max)
        if self.device_stall_first is None:
            self.device_stall_first = other.device_stall_first
        self._lateness.merge(other._lateness)
        self._compute.merge(other._compute)

    def stats(self) -> TimingStats:
        """The statistics so far."""
        c50, c99, cmax = self._compute.summary()
        if self._lateness.n == 0:
            stats = TimingStats(self.n_ticks, self.period, False, compute_p50=c50, compute_p99=c99, compute_max=cmax)
        else:
            l50, l99, lmax = self._lateness.summary()
            stats = TimingStats(
                self.n_ticks, self.period, True, l50, l99, lmax, self.overruns, self.stalls, c50, c99, cmax
            )
        return replace(
            stats,
            device_stalls=self.device_stalls,
            device_stall_time=self.device_stall_time,
            device_stall_max=self.device_stall_max,
            device_stall_first=self.device_stall_first,
        )


def timing_stats(lateness, compute_time, period: float) -> TimingStats:
    """Summarize per-tick lateness and compute time (see :class:`TimingRecord` for long runs).

    Parameters
    ----------
    lateness : array_like of shape (n,)
        Lateness of each tick (s); all NaN for free-running ticks.
    compute_time : array_like of shape (n,)
        Compute time of each tick (s).
    period : float
        Nominal tick period (s).
    """
    record = TimingRecord(period)
    record.add(lateness, compute_time)
    return record.stats()


@dataclass
class RealtimeReport:
    """What :func:`realtime_scheduling` managed to set up.

    Attributes
    ----------
    cpu : int or None
        CPU the process is pinned to, None when not pinned.
    priority : int or None
        SCHED_FIFO priority in effect, None when not real-time.
    notes : list of str
        Why a request was not granted (e.g. missing permission).
    """

    cpu: int | None = None
    priority: int | None = None
    notes: list[str] = field(default_factory=list)

    def describe(self) -> str:
        """One line for the user."""
        parts = [
            f"pinned to CPU {self.cpu}" if self.cpu is not None else "not pinned",
            f"SCHED_FIFO {self.priority}" if self.priority is not None else "normal scheduling",
        ]
        return ", ".join(parts) + ("" if not self.notes else " (" + "; ".join(self.notes) + ")")


@contextmanager
def realtime_scheduling(cpu: int | None = None, priority: int | None = None) -> Iterator[RealtimeReport]:
    """Pin the process to a CPU and/or run it SCHED_FIFO, where permitted; undo on exit.

    Parameters
    ----------
    cpu : int, optional
        CPU to pin to; None leaves the affinity alone.
    priority : int, optional
        SCHED_FIFO priority (1..99); None leaves the scheduling policy alone.

    Yields
    ------
    RealtimeReport
        What was granted; refused requests are noted, never raised.
    """
    report = RealtimeReport()
    saved_affinity = saved_policy = None
    if cpu is not None:
        try:
            saved_affinity = os.sched_getaffinity(0)
            os.sched_setaffinity(0, {int(cpu)})
            report.cpu = int(cpu)
        except (AttributeError, OSError, ValueError) as exc:
            saved_affinity = None
            report.notes.append(f"CPU pinning refused: {exc}")
    if priority is not None:
        try:
            saved_policy = (os.sched_getscheduler(0), os.sched_getparam(0))
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(priority)))
            report.priority = int(priority)
        except (AttributeError, OSError, ValueError) as exc:
            saved_policy = None
            report.notes.append(f"SCHED_FIFO refused: {exc}")
    try:
        yield report
    finally:
        if saved_policy is not None:
            try:
                os.sched_setscheduler(0, *saved_policy)
            except OSError:
                pass
        if saved_affinity is not None:
            try:
                os.sched_setaffinity(0, saved_affinity)
            except OSError:
                pass


@contextmanager
def quiet_interpreter(switch_interval: float | None = None) -> Iterator[None]:
    """Keep the interpreter from interrupting the loop; restore everything on exit.

    The garbage collector is frozen and disabled (a collection pauses every
    thread for milliseconds). With ``switch_interval`` the GIL is handed
    over more often, so the loop thread waiting for it after a sleep is not
    held up for the default 5 ms by the writer thread.
    """
    was_enabled = gc.isenabled()
    saved_interval = sys.getswitchinterval()
    gc.collect()
    gc.freeze()
    gc.disable()
    if switch_interval is not None:
        sys.setswitchinterval(switch_interval)
    try:
        yield
    finally:
        sys.setswitchinterval(saved_interval)
        gc.unfreeze()
        if was_enabled:
            gc.enable()
