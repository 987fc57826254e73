"""The acquisition loop: one code path for every backend.

Each tick: wait for the tick (the backend's clock, the loop's deadline, or
nothing), read the sample, check safety, run the controller, saturate,
write the command, hand the sample to the writer thread. The controller
state is kept and logged every tick.

An episode whose plan has a swing-up (:mod:`daq.swing_up`) starts with that phase instead of the
start gate: the same backend, tick by tick, under the supervisor's swing-up limits. Its samples
are not the episode's: the episode's sample 0 is the tick after the pendulum has settled, with the
controller from zero state as after the start gate. A swing-up that fails still writes the
episode's log, with no samples and the reason (status ``aborted``). On a backend whose device
keeps the time (the serial bridge, whose watchdog switches the motor off after five ticks
without a command), the log is opened while the settled pendulum stays balanced, and the episode
starts at the tick after it is open: opening it can take longer than the watchdog waits.

Aborts (a safety limit, SIGINT/SIGTERM, a log that cannot be written) put
the motor at 0 V in the tick that sees them, and that tick is logged with
``plant_input = 0`` (what was applied). A backend fault ends the episode
without logging the failed tick. In every case the samples already taken
reach the sinks, which are closed with status ``aborted`` and the reason.
"""

from __future__ import annotations

import importlib
import json
import logging
import math
import threading
import time
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from typing import Any, Callable, NamedTuple

import numpy as np

from qube_koopman.daq.backends.contract import Backend, BackendFault, Pacing
from qube_koopman.daq.controller_step import controller_step
from qube_koopman.daq.excitation import Excitation, ExcitationStream
from qube_koopman.daq.safety import SafetyLimits, StopRequest, stop_on_signals
from qube_koopman.daq.episode import EpisodeMetadata, software_version
from qube_koopman.core.controller_file import ControllerInfo
from qube_koopman.daq.sinks import EpisodeOutcome, Sample, Sink, SinkWriter
from qube_koopman.daq.swing_up import SwingUp, SwingUpReport, run_swing_up
from qube_koopman.daq.timing import (
    DEFAULT_SPIN,
    DEVICE_STALL_THRESHOLD,
    DeadlinePacer,
    TimingRecord,
    TimingStats,
    quiet_interpreter,
)

__all__ = ["ABORT_CAUSES", "EpisodePlan", "EpisodeResult", "run_episode", "REALTIME_SWITCH_INTERVAL"]

_log = logging.getLogger(__name__)

#: Why an episode can end early: a safety limit, a stop request (signal),
#: a backend fault, a sink (log) failure, the start gate, a swing-up that failed, or an error in the loop.
ABORT_CAUSES = ("safety", "stop", "fault", "log", "start", "swing-up", "error")

#: GIL switch interval (s) while a paced episode runs: the loop thread, waking
#: from its sleep, waits at most this long for the writer thread to yield.
REALTIME_SWITCH_INTERVAL = 1e-4

#: While ticks are paced, the writer thread stays idle this long before each
#: deadline (s): the loop's spin before the deadline must not share the GIL.
WRITER_GUARD = 0.8e-3

# A free-running loop (no deadlines) waits, every 1024 ticks, until at most this many samples
# wait for the writer thread: its queue, and so memory, stays bounded whatever the length.
_MAX_BACKLOG = 8192
_BACKLOG_CHECK = 1023
# Ticks of excitation converted to plain floats at a time (a power of two).
_CHUNK = 4096
_CHUNK_MASK = _CHUNK - 1


@dataclass(frozen=True, eq=False)
class EpisodePlan:
    """What one episode runs: the controller and the exogenous signals.

    Parameters
    ----------
    controller : ControllerInfo
        The controller: tracking errors (theta, alpha) in, volts out; its
        ``dt`` must equal the backend's sample period.
    excitation : Excitation or ExcitationStream
        target_theta, target_alpha (rad) and feedforward (V), one value per tick,
        read a chunk at a time (``chunks``).
    excitation_info : dict
        Seeds and settings of the excitation, recorded in the log.
    index : int
        Episode number within the run.
    source : str
        Run identifier recorded in the log.
    extra : dict
        Further provenance recorded in the log.
    plant : PendulumParameters, optional
        On a simulated backend, the pendulum this episode runs (``qube-run --replay``: the replayed
        log's twin, with its recording day's cables and its session's delay); None: the backend's.
    load : RandomLoad, optional
        On a simulated backend, the random load on the arm this episode runs with (``qube-run --replay``:
        the replayed log's recording day's load); None: the backend's.
    relaxation : CableRelaxation, optional
        On a simulated backend, the cables' relaxation this episode runs with (``qube-run --replay``:
        the replayed log's recording day's); None: the backend's.
    swing_up : SwingUp, optional
        Swing the pendulum up from hanging before the episode (instead of waiting for it to be
        raised to the start gate); None: the start gate.
    """

    controller: ControllerInfo
    excitation: Excitation | ExcitationStream
    excitation_info: dict = field(default_factory=dict)
    index: int = 0
    source: str = ""
    extra: dict = field(default_factory=dict)
    plant: Any = None
    swing_up: SwingUp | None = None
    load: Any = None
    relaxation: Any = None

    @property
    def n_samples(self) -> int:
        """Ticks planned."""
        return len(self.excitation)


@dataclass(frozen=True, eq=False)
class EpisodeResult(EpisodeOutcome):
    """How an episode went: its :class:`~daq.sinks.EpisodeOutcome` and more.

    Parameters
    ----------
    status, reason, n_samples, timing, backend_stats
        As for :class:`~daq.sinks.EpisodeOutcome`.
    metadata : EpisodeMetadata or None
        What the sinks were told, with the final status; None when the episode never started
        (backend failed to start, start gate not passed, stopped before).
    sink_errors : tuple of str
        Errors raised by sinks.
    signal : int or None
        The signal that stopped the episode, if one did.
    cause : str
        What ended an aborted episode: one of :data:`ABORT_CAUSES`; empty
        when complete.
    """

    metadata: EpisodeMetadata | None = None
    sink_errors: tuple[str, ...] = ()
    signal: int | None = None
    cause: str = ""

    @property
    def complete(self) -> bool:
        """True when the episode ran to its end."""
        return self.status == "complete"

    @property
    def started(self) -> bool:
        """True when the episode got past the start gate (so sinks hold it)."""
        return self.metadata is not None


def _zero_motor(backend: Backend) -> None:
    # Best effort: after a fault the write may fail too, and stop() must still run.
    try:
        backend.write(0.0)
    except BackendFault:
        pass
    finally:
        backend.stop()


def _statistics(backend: Backend) -> dict:
    # The counters are informative: a backend failing to give them, or giving
    # something JSON cannot hold, must not cost the log its final status.
    try:
        return json.loads(json.dumps(dict(backend.statistics()), allow_nan=False))
    except Exception as exc:  # noqa: BLE001
        return {"error": f"statistics unavailable: {type(exc).__name__}: {exc}"}


def _wait_upright(
    backend: Backend, limits: SafetyLimits, stop: StopRequest, pacer: DeadlinePacer | None
) -> tuple[str, str]:
    """Hold 0 V until |alpha| < start_alpha; ('', '') once there, else (why not, cause)."""
    max_ticks = (
        math.inf if limits.start_timeout is None else max(1, round(limits.start_timeout / backend.sample_period))
    )
    k = 0
    if pacer is not None:
        pacer.start()
    while True:
        if stop.requested:
            return f"{stop.reason} before the start", "stop"
        _, alpha = backend.read()
        if abs(alpha) < limits.start_alpha:
            return "", ""
        backend.write(0.0)
        k += 1
        if k >= max_ticks:
            return (
                f"not started: |alpha| stayed above {math.degrees(limits.start_alpha):.1f} deg "
                f"for {limits.start_timeout} s",
                "start",
            )
        if pacer is not None:
            pacer.wait(k)


def _check_controller(ctrl, period: float) -> None:
    """Refuse a controller the loop cannot run: two tracking errors (and optionally the feedforward) in, one
    voltage out, at the backend's rate."""
    if ctrl.n_inputs not in (2, 3) or ctrl.n_outputs != 1:
        raise ValueError(
            "the controller must map the two tracking errors (theta, alpha), and optionally the "
            "feedforward, to one voltage; "
            f"got {ctrl.n_inputs} inputs and {ctrl.n_outputs} outputs"
        )
    if abs(ctrl.dt - period) > 1e-9 * period:
        raise ValueError(f"controller dt {ctrl.dt} s differs from the backend's sample period {period} s")


class _LogOpening:
    """An episode's log opened in a thread while its settled swing-up keeps the pendulum balanced.

    ``prepare`` of :func:`~qube_koopman.daq.swing_up.run_swing_up`: called with the settled report, it
    starts the thread (the metadata, then :meth:`SinkWriter.open`) and returns the poll that says it
    has finished.
    """

    def __init__(self, plan: EpisodePlan, backend: Backend, limits: SafetyLimits, sinks: list[Sink]) -> None:
        # What a process's first log opening does once, done before the swing-up: 60 ms of Python (the
        # package's version from its metadata, mcap's record classes) in the thread beside the loop.
        software_version()
        importlib.import_module("mcap.records")
        self._args = plan, backend, limits
        self.writer = SinkWriter(sinks)
        self.metadata: EpisodeMetadata | None = None
        self.opened = False
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None

    @property
    def started(self) -> bool:
        """Whether the log is being (or has been) opened."""
        return self._thread is not None

    def __call__(self, report: SwingUpReport) -> Callable[[], bool]:
        thread = threading.Thread(target=self._open, args=(report,), name="episode-log-open", daemon=True)
        self._thread = thread
        thread.start()
        return lambda: not thread.is_alive()

    def _open(self, report: SwingUpReport) -> None:
        try:
            self.metadata = _episode_metadata(*self._args, report)
            self.opened = self.writer.open(self.metadata)
        except BaseException as exc:  # noqa: BLE001 - raised again in the loop's thread (result)
            self._error = exc

    def result(self) -> tuple[EpisodeMetadata, SinkWriter, bool]:
        """(metadata, writer, opened) once the thread has finished; its error raised here."""
        assert self._thread is not None  # only once started
        self._thread.join()
        if self._error is not None:
            raise self._error
        assert self.metadata is not None  # set unless it raised
        return self.metadata, self.writer, self.opened


def _start(
    backend: Backend,
    plan: EpisodePlan,
    limits: SafetyLimits,
    stop: StopRequest,
    pacer: DeadlinePacer | None,
    opening: _LogOpening | None = None,
) -> tuple[str, str, SwingUpReport | None]:
    """Start the backend and pass the start gate, or swing the pendulum up; ('', '', report) then,
    else (why not, cause, report) with the motor at 0 V. The report is the swing-up's (None without)."""
    report = None
    try:
        backend.start()
        if plan.swing_up is None:
            reason, cause = _wait_upright(backend, limits, stop, pacer)
        else:
            report = run_swing_up(backend, plan.controller.system, plan.swing_up, limits, stop, pacer, opening)
            reason = report.reason
            cause = "" if report.settled else "stop" if report.outcome == "stopped" else "swing-up"
    except BackendFault as exc:
        reason, cause = f"backend fault before the start: {exc}", "fault"
    if reason:
        _zero_motor(backend)
    return reason, cause, report


def _episode_metadata(
    plan: EpisodePlan, backend: Backend, limits: SafetyLimits, swing: SwingUpReport | None = None
) -> EpisodeMetadata:
    """What the sinks are told when the episode starts."""
    swing_up = {}
    if plan.swing_up is not None and swing is not None:
        swing_up = {"swing_up": {**swing.as_dict(), "settings": plan.swing_up.as_dict()}}
    return EpisodeMetadata(
        controller=plan.controller,
        sample_rate_hz=1.0 / backend.sample_period,
        backend=backend.name,
        source=plan.source,
        start_time=datetime.now(timezone.utc).isoformat(),
        excitation=plan.excitation_info,
        extra={
            "episode_index": plan.index,
            "n_planned": plan.n_samples,
            "backend": backend.describe(),
            "safety": limits.as_dict(),
            **swing_up,
            **plan.extra,
        },
    )


class _TickTimes:
    """Per-tick lateness and compute time, buffered a chunk of ticks at a time into timing records.

    Memory stays the same for any episode length: the loop writes tick ``k`` at ``k % _CHUNK``,
    and :meth:`fold` hands the buffered ticks to the records before the buffer is reused.
    """

    def __init__(self, period: float, also: TimingRecord | None = None) -> None:
        self.lateness = np.full(_CHUNK, np.nan)
        self.compute = np.full(_CHUNK, np.nan)
        self.record = TimingRecord(period)
        self._records = [self.record] + ([also] if also is not None else [])
        self._n = 0

    def device_stall(self, t: float, held: float) -> None:
        """The device held its ticks ``held`` seconds before the sample at ``t`` (see :class:`TimingStats`)."""
        for record in self._records:
            record.device_stall(t, held)

    def fold(self, n_ticks: int) -> None:
        """Add the ticks buffered since the last fold, up to ``n_ticks`` ticks in all."""
        rest = n_ticks - self._n
        if rest > 0:
            for record in self._records:
                record.add(self.lateness[:rest], self.compute[:rest])
            self._n = n_ticks


class _Logged(NamedTuple):
    """How the logged part of an episode went (see :func:`_run_logged`)."""

    n_done: int
    reason: str
    cause: str
    outcome: EpisodeOutcome
    errors: list


def _run_logged(
    backend: Backend,
    plan: EpisodePlan,
    metadata: EpisodeMetadata,
    sinks: list[Sink],
    limits: SafetyLimits,
    stop: StopRequest,
    pacer: DeadlinePacer | None,
    times: _TickTimes,
    refused: tuple[str, str] = ("", ""),
    opened: tuple[SinkWriter, bool] | None = None,
) -> _Logged:
    """Open the sinks, run the ticks, and whatever happens zero the motor and close the sinks.

    ``refused``: (reason, cause) of an episode that cannot start (a failed swing-up): its log is
    opened and closed aborted with that reason, without a tick. ``opened``: the writer already
    opened with ``metadata`` (while a swing-up balanced the pendulum) and whether it opened.
    """
    writer = SinkWriter(sinks) if opened is None else opened[0]
    n_done = 0
    reason = cause = ""
    try:
        if not (writer.open(metadata) if opened is None else opened[1]):
            reason, cause = f"log failed: {writer.failed}", "log"
        elif refused[0]:
            reason, cause = refused
        else:
            n_done, reason, cause = _ticks(backend, plan, limits, stop, writer, pacer, times)
    except BaseException as exc:
        if not reason:
            reason, cause = f"loop error: {type(exc).__name__}: {exc}", "error"
        raise
    finally:
        _zero_motor(backend)
        times.fold(n_done)
        timing = times.record.stats() if n_done else TimingRecord(backend.sample_period).stats()
        if timing.device_stalls:
            _log.warning(
                "episode %d: the %s backend's device stalled %d time(s), %.0f ms at most (the first before "
                "t = %.3f s): the ticks it held back are missing from the log",
                plan.index,
                backend.name,
                timing.device_stalls,
                timing.device_stall_max * 1e3,
                timing.device_stall_first,
            )
        outcome = EpisodeOutcome("aborted" if reason else "complete", reason, n_done, timing, _statistics(backend))
        errors = writer.close(outcome)
        if writer.failed is not None and not reason:
            # The log failed after the last tick, while its queue drained: the episode is
            # lost all the same (SinkWriter.close recorded it aborted).
            reason, cause = f"log failed: {writer.failed}", "log"
            outcome = replace(outcome, status="aborted", reason=reason)
    return _Logged(n_done, reason, cause, outcome, errors)


def run_episode(
    backend: Backend,
    plan: EpisodePlan,
    sinks: list[Sink],
    *,
    limits: SafetyLimits = SafetyLimits(),
    stop: StopRequest | None = None,
    handle_signals: bool = True,
    spin: float = DEFAULT_SPIN,
    timing: TimingRecord | None = None,
) -> EpisodeResult:
    """Run one episode on a backend, under the safety supervisor, into sinks.

    Parameters
    ----------
    backend : Backend
        Started by this function and stopped (motor at 0 V) before it returns.
    plan : EpisodePlan
        Controller and excitation; the episode lasts ``plan.n_samples`` ticks.
    sinks : list of Sink
        Receive the episode on a writer thread.
    limits : SafetyLimits
        Voltage clamp, angle limits and start gate.
    stop : StopRequest, optional
        Set it (from another thread, or a signal handler) to end the episode
        early; one is made when not given.
    handle_signals : bool
        Turn SIGINT and SIGTERM into a stop while the episode runs (main
        thread only); the previous handlers are restored afterwards.
    spin : float
        For a loop-paced backend: spin this long before each deadline (s); the whole period when
        the backend asks to spin (:attr:`Backend.spin`).
    timing : TimingRecord, optional
        Also add the episode's tick timing to it (a run's statistics over its episodes).

    Returns
    -------
    EpisodeResult
    """
    period = backend.sample_period
    _check_controller(plan.controller.system, period)
    stop = stop if stop is not None else StopRequest()
    paced = backend.pacing is not Pacing.NONE

    signals = stop_on_signals(stop) if handle_signals else nullcontext(False)
    # The collector is frozen before the start gate: once the pendulum is upright,
    # control must begin within a tick, not after a collection of the whole heap.
    quiet = quiet_interpreter(REALTIME_SWITCH_INTERVAL if paced else None)
    with signals, quiet:
        pacer = DeadlinePacer(period, period if backend.spin else spin) if backend.pacing is Pacing.LOOP else None
        times = _TickTimes(period, timing)
        if plan.plant is not None and hasattr(backend, "use_plant"):
            backend.use_plant(plan.plant)
        if plan.load is not None and hasattr(backend, "use_load"):
            backend.use_load(plan.load)
        if plan.relaxation is not None and hasattr(backend, "use_relaxation"):
            backend.use_relaxation(plan.relaxation)
        # A device that keeps the time trips its watchdog while a log opens between the swing-up's
        # last tick and the episode's first: it is opened while the swing-up keeps balancing.
        opening = (
            _LogOpening(plan, backend, limits, sinks)
            if plan.swing_up is not None and backend.pacing is Pacing.DEVICE
            else None
        )
        reason, cause, swing = _start(backend, plan, limits, stop, pacer, opening)
        if reason and cause != "swing-up" and not (opening is not None and opening.started):
            return EpisodeResult(
                "aborted",
                reason,
                0,
                TimingStats(0, period, paced),
                _statistics(backend),
                signal=stop.signal,
                cause=cause,
            )
        if opening is not None and opening.started:
            metadata, writer, ok = opening.result()
            run = _run_logged(backend, plan, metadata, sinks, limits, stop, pacer, times, (reason, cause), (writer, ok))
        else:
            metadata = _episode_metadata(plan, backend, limits, swing)
            run = _run_logged(backend, plan, metadata, sinks, limits, stop, pacer, times, (reason, cause))
    outcome, stats = run.outcome, run.outcome.timing
    metadata = replace(
        metadata,
        status=outcome.status,
        status_reason=run.reason,
        timing=stats.as_dict(),
        backend_stats=outcome.backend_stats,
    )
    return EpisodeResult(
        outcome.status,
        run.reason,
        run.n_done,
        stats,
        outcome.backend_stats,
        metadata=metadata,
        sink_errors=tuple(run.errors),
        signal=stop.signal,
        cause=run.cause,
    )


class _DeviceLateness:
    """Lateness of a device-paced tick: its arrival against the device's clock, anchored on tick 0.

    Keeps the writer thread clear of the expected arrivals, and moves the anchor when a tick
    comes sooner after tick 0 than the device's clock says (tick 0 was read late).
    """

    def __init__(self, writer: SinkWriter, period: float) -> None:
        self.writer = writer
        self.period = period
        self.guard = min(WRITER_GUARD, 0.5 * period)
        self.t0 = 0.0
        self.when0: float | None = None

    def __call__(self, k: int, t_tick: float, when: float | None) -> float:
        """The lateness (s) of tick ``k`` read at ``t_tick`` (host clock), device time ``when``."""
        if k == 0:
            self.t0, self.when0 = t_tick, when
            self.writer.keep_clear(self.t0, self.period, self.guard)
        if when is None:
            return t_tick - (self.t0 + k * self.period)
        assert self.when0 is not None  # a device with a clock gave tick 0 its time too
        late = t_tick - (self.t0 + (when - self.when0))
        if late < 0:
            # Came sooner after tick 0 than the device's clock says: tick 0 was
            # read late (it had been waiting). Anchor on the earliest arrival.
            self.t0 += late
            late = 0.0
            self.writer.keep_clear(self.t0, self.period, self.guard)
        return late


def _excitation_chunks(ex: Excitation | ExcitationStream):
    """The excitation as plain floats, a chunk at a time: a whole long episode's worth would
    take 100 bytes a tick."""
    for chunk in ex.chunks(_CHUNK):
        yield tuple(signal.tolist() for signal in chunk)


def _abort(theta: float, alpha: float, limits: SafetyLimits, stop: StopRequest, writer: SinkWriter) -> tuple[str, str]:
    """Why this tick must put the motor at 0 V and end the episode: (reason, cause), or ('', '')."""
    if not (abs(theta) <= limits.theta_limit and abs(alpha) <= limits.alpha_limit):
        violation = limits.violation(theta, alpha)
        assert violation is not None  # the same check
        return violation, "safety"
    if stop.requested:
        return stop.reason, "stop"
    if writer.failed is not None:
        return f"log failed: {writer.failed}", "log"
    return "", ""


def _clocking(backend: Backend, writer: SinkWriter, pacer: DeadlinePacer | None):
    """How ticks are timed: (the pacer's wait or None, a :class:`_DeviceLateness` or None).

    A loop-paced episode's time zero is set here, and the writer kept clear of its deadlines.
    """
    period = backend.sample_period
    if pacer is not None:
        writer.keep_clear(pacer.start(), period, min(WRITER_GUARD, 0.5 * period))
        return pacer.wait, None
    return None, (_DeviceLateness(writer, period) if backend.pacing is Pacing.DEVICE else None)


def _ticks(
    backend: Backend,
    plan: EpisodePlan,
    limits: SafetyLimits,
    stop: StopRequest,
    writer: SinkWriter,
    pacer: DeadlinePacer | None,
    times: _TickTimes,
) -> tuple[int, str, str]:
    """The ticks of one episode; returns (ticks recorded, abort reason, cause), '' when complete."""
    runtime = plan.controller.runtime
    if runtime is None:
        output, update = controller_step(plan.controller.system)
        tick_output = None
    else:  # a controller beyond LTI (core/controller_file.py): it also sees the arm's reference
        tick_output, update = runtime.step()
    record = ()
    n_ticks = plan.n_samples
    chunks = _excitation_chunks(plan.excitation)
    ref_theta = ref_alpha = ff = []
    vmax = limits.max_voltage
    th_lim, al_lim = limits.theta_limit, limits.alpha_limit
    rate = 1.0 / backend.sample_period  # t = k / rate, the log's nominal time (FORMAT.md)
    read, write, put = backend.read, backend.write, writer.put
    clock = time.perf_counter
    late = nan = math.nan
    wait, device_lateness = _clocking(backend, writer, pacer)
    throttle = backend.pacing is Pacing.NONE
    device_time = backend.device_time
    lateness, compute = times.lateness, times.compute
    last_when, stalled = math.inf, backend.sample_period + DEVICE_STALL_THRESHOLD

    for k in range(n_ticks):
        j = k & _CHUNK_MASK
        if not j:
            times.fold(k)
            ref_theta, ref_alpha, ff = next(chunks)
        if wait is not None:
            late = wait(k)
            t_tick = clock()
        try:
            theta, alpha = read()
        except BackendFault as exc:
            return k, f"backend fault: {exc}", "fault"
        when = device_time()  # logged per sample (format 1.3): the device's gaps stay visible
        if when is not None:
            if when - last_when > stalled:
                times.device_stall(k / rate, when - last_when - backend.sample_period)
            last_when = when
        if wait is None:
            t_tick = clock()
            if device_lateness is not None:
                late = device_lateness(k, t_tick, when)
        r_theta, r_alpha = ref_theta[j], ref_alpha[j]
        e0 = r_theta - theta
        e1 = r_alpha - alpha
        f = ff[j]
        if tick_output is None:
            u, xc = output(e0, e1, f)
        else:
            u, xc = tick_output(e0, e1, f, r_theta)
            record = runtime.tick_record
        reason = ""
        if not (abs(theta) <= th_lim and abs(alpha) <= al_lim) or stop.requested or writer.failed is not None:
            reason, cause = _abort(theta, alpha, limits, stop, writer)
        if reason:
            v, sat = 0.0, 0
        else:
            v = u + f
            if v - v != 0.0:  # nan or +-inf (a call per tick saved)
                # Every backend the same: 0 V this tick, logged as applied, and the episode ends on a
                # fault (the bridge would otherwise switch its amplifier off and carry on silently).
                reason, cause = f"controller fault: its output is {float(u)!r}, not a voltage; 0 V applied", "fault"
                v, sat = 0.0, 0
            else:
                sat = 1 if v > vmax else -1 if v < -vmax else 0
                if sat:
                    v = sat * vmax
        try:
            write(v)
        except BackendFault as exc:
            return k, f"backend fault: {exc}", "fault"
        spent = clock() - t_tick
        lateness[j] = late
        compute[j] = spent
        put(
            Sample(
                k,
                k / rate,
                theta,
                alpha,
                r_theta,
                r_alpha,
                f,
                u,
                v,
                sat,
                late,
                spent,
                xc,
                nan if when is None else when,
                record,
            )
        )
        if throttle and not k & _BACKLOG_CHECK:
            writer.wait_below(_MAX_BACKLOG)  # free-running: memory must not grow with the episode
        if reason:
            return k + 1, reason, cause
        update(e0, e1, f)
    return n_ticks, "", ""
