"""Episodes of a simulated run spread over local worker processes (``qube-run --n-jobs``).

Simulated episodes are independent once each knows where the run's random streams stand at
its start, so worker processes can run them side by side. Each writes its episode's log into
the run's folder, and every log is the one a serial run (:func:`daq.session.run_episodes` into
an :class:`~daq.sinks.McapSink`) writes, sample for sample and field for field, timing apart:

- **randomness**: the excitation comes from the plan's seeds; the simulator's draws of episode
  ``k`` (its start perturbation and pendulum encoder zero) come from a copy of the run's
  backend skipped past episodes ``0 .. k-1`` (:meth:`SimBackend.skip_episode`): the numbers a
  serial run draws. (A noisy sensor, whose noise stream runs on across episodes, is refused.)
- **names**: a log is named after its start time (:mod:`daq.log.names`), and the names must
  sort in episode order; episodes start in their order, each in a later millisecond than the
  one before, so they do.
- **the first episode** runs in this process while the workers start; the others start once
  it has ended, unless it ended the run: a setup that cannot work (a full disk, a log folder
  refusing writes) fails once, as in a serial run.
- **stops**: a signal (SIGINT, SIGTERM) stops every running episode, its log closed "aborted",
  and starts no more, as in a serial run. An episode that ends a serial run (a backend fault,
  a log failure: :data:`daq.session.FATAL_CAUSES`) starts no more; those already running finish.

joblib's loky processes run the episodes (the lifting search's approach; joblib also limits
each worker's BLAS threads to its share of the cores). What the processes share (which
episodes have started, and when; the run's stop) are small files in a private folder. Results
come back in episode order.
"""

from __future__ import annotations

import copy
import json
import os
import shutil
import signal
import tempfile
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, replace
from datetime import datetime, timedelta, timezone
from itertools import count
from pathlib import Path
from typing import Callable, Iterator, Sequence

from qube_koopman.core.workers import resolve_n_jobs
from qube_koopman.daq.excitation import ExcitationStream
from qube_koopman.daq.loop import EpisodePlan, EpisodeResult, run_episode
from qube_koopman.daq.safety import SafetyLimits, StopRequest, stop_on_signals
from qube_koopman.daq.session import FATAL_CAUSES, RunResult, log_outcome
from qube_koopman.daq.sinks import LogWriteError, McapSink, Sink
from qube_koopman.daq.timing import DEFAULT_SPIN, TimingRecord

__all__ = ["LoggedEpisode", "resolve_n_jobs", "run_episodes_parallel"]

# Seconds between a waiting worker's looks at whether its turn to start has come.
_TURN_POLL = 0.002
# Seconds between two looks of a stop relay (this process -> the flags -> the workers).
_RELAY_POLL = 0.05
# Seconds between a worker's looks at whether the run's process is still its parent.
_PARENT_POLL = 0.1
# Longest excitation (samples) sent to a worker made (24 bytes a sample: 25 MB); longer ones
# are made by the worker, a chunk at a time.
_MADE_HERE = 1 << 20


@dataclass(frozen=True)
class LoggedEpisode:
    """An episode of a parallel run, as this process gets it.

    Attributes
    ----------
    result : EpisodeResult
    path : Path or None
        Its log; None when it never started.
    log_error : LogWriteError or None
        Why its log could not be written (the file and the error).
    timing : TimingRecord
        Its ticks' timing, for the run's statistics.
    """

    result: EpisodeResult
    path: Path | None
    log_error: LogWriteError | None
    timing: TimingRecord


class _Flags:
    """What the run's processes share, as files in a private folder: the episodes started (when) and the stop.

    Files, not a server process: nothing to outlive the run, and a worker whose parent died
    (killed) sees it and stops instead of waiting for a turn that will not come.
    """

    def __init__(self, folder: Path, parent: int) -> None:
        self.folder = folder
        self.parent = parent

    def _write(self, name: str, text: str, replace: bool = True) -> None:
        path = self.folder / name
        if replace or not path.exists():
            temporary = self.folder / f".{name}.{os.getpid()}.{threading.get_ident()}"
            temporary.write_text(text)
            os.replace(temporary, path)  # readers see the whole file or none

    def _orphaned(self) -> bool:
        return os.getpid() != self.parent and os.getppid() != self.parent

    def halt(self, reason: str = "", signum: int | None = None) -> None:
        """Start no more episodes; with a reason, stop the running ones too."""
        self._write("halt", json.dumps({"reason": reason, "signal": signum}), replace=bool(reason))

    def stop_request(self) -> tuple[str, int | None] | None:
        """The stop running episodes must make (reason, signal), or None."""
        if self._orphaned():
            return "the run's process ended", None
        try:
            found = json.loads((self.folder / "halt").read_text())
        except FileNotFoundError:
            return None
        return (found["reason"], found["signal"]) if found["reason"] else None

    def halted(self) -> bool:
        """Whether no more episodes may start."""
        return (self.folder / "halt").exists() or self._orphaned()

    def pass_turn(self, index: int, start_time: str | None) -> None:
        """Episode ``index`` started at ``start_time`` (or will not start: the time before): the next one's turn."""
        self._write(f"started-{index}", start_time or "", replace=False)

    def wait_turn(self, index: int) -> str | None:
        """Wait until episode ``index - 1`` has started (or will not) or the run halts; its start time."""
        if index == 0:
            return None
        path = self.folder / f"started-{index - 1}"
        while not path.exists():
            if self.halted():
                return None
            time.sleep(_TURN_POLL)
        return path.read_text() or None


class _PassTurn:
    """A sink passing the start turn on once the episode's log is open (its start time known)."""

    required = False

    def __init__(self, flags: _Flags, index: int) -> None:
        self.flags = flags
        self.index = index

    def open(self, metadata) -> None:
        self.flags.pass_turn(self.index, metadata.start_time)

    def write(self, sample) -> None:
        pass

    def close(self, outcome) -> None:
        pass


@contextmanager
def _relay(
    source: Callable[[], tuple[str, int | None] | None], target: Callable[[str, int | None], None]
) -> Iterator[None]:
    """While the block runs, a thread looks at ``source`` every 50 ms and hands a stop it finds to ``target``."""
    done = threading.Event()

    def watch() -> None:
        while not done.wait(_RELAY_POLL):
            found = source()
            if found:
                target(*found)
                return

    thread = threading.Thread(target=watch, name="stop-relay", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()


def _start_after(start_time: str | None) -> None:
    """Wait until the clock is past the millisecond of ``start_time`` (ISO 8601): the next name sorts after."""
    if start_time is None:
        return
    previous = datetime.fromisoformat(start_time)
    after = previous.replace(microsecond=previous.microsecond // 1000 * 1000) + timedelta(milliseconds=1)
    while (wait := (after - datetime.now(timezone.utc)).total_seconds()) > 0:
        time.sleep(wait)


def _run_logged(
    backend, plan: EpisodePlan, out_dir: Path, sinks: list, limits: SafetyLimits, stop: StopRequest, spin: float
) -> LoggedEpisode:
    """One episode into its own log in ``out_dir`` (and ``sinks``)."""
    mcap, timing = McapSink(out_dir), TimingRecord(backend.sample_period)
    result = run_episode(
        backend, plan, [mcap, *sinks], limits=limits, stop=stop, handle_signals=False, spin=spin, timing=timing
    )
    return LoggedEpisode(result, mcap.paths[-1] if result.started and mcap.paths else None, mcap.error, timing)


@contextmanager
def _sigint_ignored() -> Iterator[None]:
    """Ignore SIGINT while the block runs: processes started in it keep ignoring it (a disposition
    a process inherits through exec, which Python leaves in place).

    A Ctrl-C reaches every process of the terminal's group; a worker still importing would
    die of it with a traceback. This process's stop handler comes back after the block (a few
    milliseconds: the workers' fork and exec).
    """
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


_prepared = False
# Held while a worker runs an episode: a worker whose parent died ends once its episode has.
_episode_lock = threading.Lock()


def _exit_with_parent(parent: int) -> None:
    """In a worker: end the process once ``parent`` (the run's process) is no longer its parent.

    A run killed outright (SIGKILL) cannot stop its workers, and loky's workers wait for work on
    pipes that they themselves hold open, so they would wait forever. Polled rather than asked
    of the kernel (Linux's PR_SET_PDEATHSIG): that signal comes when the *thread* that started
    the worker ends, and loky starts its workers from threads of its own that come and go, and
    it does not exist elsewhere. A running episode is let end first: it sees the orphaning
    through the run's flags within 50 ms and closes its log as aborted.
    """

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(_PARENT_POLL)
        with _episode_lock:
            os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def _prepare_worker(parent: int, setup: Callable[[], None] | None) -> None:
    """Once in a worker process: ignore SIGINT between episodes (the run's stop comes through the
    flags; a Ctrl-C reaches every process of the terminal), end with the run's process, and run
    the caller's ``setup``."""
    global _prepared
    if _prepared or os.getpid() == parent:  # joblib runs n_jobs=1 in this very process
        return
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _exit_with_parent(parent)
    if setup is not None:
        setup()
    _prepared = True


def _in_worker(
    backend, plan: EpisodePlan, out_dir: Path, flags: _Flags, limits: SafetyLimits, spin: float, setup
) -> LoggedEpisode | Exception | None:
    """A worker's episode: at its turn, into its own log; None when the run halted before it."""
    _prepare_worker(flags.parent, setup)
    stop, last_start = StopRequest(), None
    try:
        with _episode_lock, stop_on_signals(stop), _relay(flags.stop_request, stop.request):
            last_start = flags.wait_turn(plan.index)
            if flags.halted():
                return None
            _start_after(last_start)
            return _run_logged(backend, plan, out_dir, [_PassTurn(flags, plan.index)], limits, stop, spin)
    except Exception as exc:  # noqa: BLE001 - raised in the parent, once the others have finished
        return exc
    finally:
        flags.pass_turn(plan.index, last_start)


def _release_workers() -> None:
    """Stop joblib's reusable local workers: a run leaves no process behind it."""
    from joblib.externals.loky import get_reusable_executor

    get_reusable_executor(reuse=True).shutdown(wait=True)  # the one joblib ran (reuse: not a new one)


def _for_worker(plan: EpisodePlan) -> EpisodePlan:
    """The plan with its excitation made here when it is short (the same values, bit for bit): a
    worker then does not make it again."""
    if isinstance(plan.excitation, ExcitationStream) and len(plan.excitation) <= _MADE_HERE:
        return replace(plan, excitation=plan.excitation.whole())
    return plan


def _calls(backend, plans: Sequence[EpisodePlan], halted: threading.Event, args: tuple) -> Iterator:
    """The workers' calls, episode 1 on, each with a copy of ``backend`` as that episode starts it."""
    import joblib

    call = joblib.delayed(_in_worker)
    for index in range(1, len(plans)):
        if halted.is_set():
            return
        here = copy.deepcopy(backend)
        backend.skip_episode()
        yield call(here, _for_worker(plans[index]), *args)


def run_episodes_parallel(
    backend,
    plans: Sequence[EpisodePlan],
    out_dir: str | Path,
    *,
    n_jobs: int,
    sinks: Sequence[Sink] = (),
    limits: SafetyLimits = SafetyLimits(),
    stop: StopRequest | None = None,
    spin: float = DEFAULT_SPIN,
    on_result: Callable[[EpisodePlan, LoggedEpisode], None] | None = None,
    timing: TimingRecord | None = None,
    worker_setup: Callable[[], None] | None = None,
) -> RunResult:
    """Run ``plans``, each episode into its own MCAP log in ``out_dir``: the first here, the others in workers.

    The logs are those :func:`daq.session.run_episodes` writes with an
    :class:`~daq.sinks.McapSink` on ``out_dir``, and the run ends as that one would (see the
    module docstring).

    Parameters
    ----------
    backend : SimBackend
        As the first episode is to start it; it runs the first episode.
    plans : sequence of EpisodePlan
    out_dir : str or Path
        The logs' folder (must exist).
    n_jobs : int
        Worker processes (:func:`resolve_n_jobs`), for the episodes after the first.
    sinks : sequence of Sink
        Also receive the first episode (a progress bar, say).
    limits : SafetyLimits
    stop : StopRequest, optional
        Set it to end the run (SIGINT and SIGTERM set it while the run lasts).
    spin : float
        Spin before each deadline when the loop paces (s).
    on_result : callable(plan, LoggedEpisode), optional
        Called in this process for each episode attempted, in episode order.
    timing : TimingRecord, optional
        Gathers every episode's tick timing.
    worker_setup : callable, optional
        Run once in each worker process before its first episode (picklable; e.g. logging).

    Returns
    -------
    RunResult
        The episodes attempted, in order (those the run halted before are left out).

    Raises
    ------
    ValueError
        When the backend's episodes cannot be skipped (:meth:`SimBackend.skip_episode`).
    Exception
        An error a loop raised, once the episodes already running have finished.
    """
    import joblib
    from joblib.externals.loky.process_executor import BrokenProcessPool

    source = copy.deepcopy(backend)
    source.skip_episode()  # refused here, not in a worker; the copy starts the second episode
    stop = stop if stop is not None else StopRequest()
    folder = Path(tempfile.mkdtemp(prefix="qube-run-"))
    state = _RunState(plans, _Flags(folder, os.getpid()), stop, on_result, timing)
    parallel = joblib.Parallel(n_jobs=n_jobs, return_as="generator", max_nbytes=None, batch_size=1)
    # Absolute: joblib may reuse workers another part of this process started in another directory.
    args = (Path(out_dir).absolute(), state.flags, limits, spin, worker_setup)
    try:
        with (
            stop_on_signals(stop),
            _relay(lambda: (stop.reason, stop.signal) if stop.requested else None, state.flags.halt),
        ):
            with _sigint_ignored():  # the workers start now, deaf to a Ctrl-C: it reaches them as the flags
                results = parallel(_calls(source, plans, state.halted, args))
            first = _first(backend, plans[0], Path(out_dir), sinks, limits, stop, spin)
            state.take(0, first)
            state.after_first(first)
            for index, logged in zip(count(1), results):
                state.take(index, logged)
    except BrokenProcessPool as exc:
        state.run.stopped = stop.reason or f"a worker process ended unexpectedly ({exc})"
    finally:
        state.halt()  # workers still waiting for their turn (an error here) start nothing
        _release_workers()
        shutil.rmtree(folder, ignore_errors=True)
    return state.finish()


class _RunState:
    """A parallel run as this process sees it: the episodes back so far, whether it halted, an error."""

    def __init__(self, plans: Sequence[EpisodePlan], flags: _Flags, stop: StopRequest, on_result, timing) -> None:
        self.plans, self.flags, self.stop = plans, flags, stop
        self.on_result, self.timing = on_result, timing
        self.run = RunResult()
        self.halted = threading.Event()
        self.failure: Exception | None = None

    def halt(self) -> None:
        """Start no more episodes (those running go on)."""
        if not self.halted.is_set():
            self.halted.set()
            self.flags.halt()

    def take(self, index: int, logged: LoggedEpisode | Exception | None) -> None:
        """Count episode ``index`` as :func:`daq.session.run_episodes` counts one; halt when it ends the run."""
        if isinstance(logged, Exception):
            self.failure = self.failure or logged
        elif logged is not None:
            result = logged.result
            self.run.results.append(result)
            if self.timing is not None:
                self.timing.merge(logged.timing)
            log_outcome(self.plans[index], result)
            if self.on_result is not None:
                self.on_result(self.plans[index], logged)
            if result.signal is not None:  # a signal only a worker saw: the run stops as if this process had
                self.stop.request(result.reason, result.signal)
            if result.cause in FATAL_CAUSES and not self.run.stopped:
                self.run.stopped = result.reason
        if self.failure is not None or self.run.stopped:
            self.halt()

    def after_first(self, first: LoggedEpisode | Exception | None) -> None:
        """The workers' turn once the first episode has ended, unless the run is over."""
        if self.stop.requested:
            self.flags.halt(self.stop.reason, self.stop.signal)
        elif not self.halted.is_set():  # the others wait for the first's end, not its start
            # None only when the run was stopped, an exception halted it (take): here it is an episode
            assert isinstance(first, LoggedEpisode)
            metadata = first.result.metadata  # None: it never started
            started = metadata.start_time if metadata is not None else None
            self.flags.pass_turn(0, started)

    def finish(self) -> RunResult:
        """The run's result; the first error a loop raised, raised."""
        if self.failure is not None:
            raise self.failure
        run, stop = self.run, self.stop
        run.signal = stop.signal
        if stop.requested and not run.stopped:
            run.stopped = stop.reason
        return run


def _first(
    backend, plan: EpisodePlan, out_dir: Path, sinks, limits: SafetyLimits, stop: StopRequest, spin: float
) -> LoggedEpisode | Exception | None:
    """The first episode, in this process (None when the run was stopped before it)."""
    if stop.requested:
        return None
    try:
        return _run_logged(backend, plan, out_dir, list(sinks), limits, stop, spin)
    except Exception as exc:  # noqa: BLE001 - raised once the workers are stopped
        return exc
