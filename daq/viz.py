"""Live and recorded views of a run in rerun (rerun-sdk, imported only when used).

:class:`RerunSink` is a sink like the episode log: it runs on the writer
thread, off the loop, and sends samples in batches (``send_columns``, one
chunk per plot every 0.25 s of data: the view still follows live, four
updates a second) rather than one ``log`` call per sample. A 20 s episode
records as about 330 chunks and 1.4 MB (with 0.1 s batches: 820 chunks,
2.0 MB). Episodes follow
one another on the ``time`` timeline (seconds since the first episode
started, episodes back to back); the ``episode`` timeline numbers them.

The default blueprint shows theta and alpha against their references, the
voltages (controller output, applied input, feedforward) and the loop's
timing (lateness and compute time per tick), plus a log of episode events.

A saved recording is written by a child process as the run goes and renamed
into place, whole, when the run ends (:class:`core.rrd.RrdProcess`, which says
why); a viewer is streamed to live. Neither can stop or hang the run: a
failure is reported when it ends.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

import numpy as np

from qube_koopman.core.rrd import RrdProcess, apply_op, flush_recording, import_rerun
from qube_koopman.daq.episode import EpisodeMetadata
from qube_koopman.daq.sinks import EpisodeOutcome, Sample

__all__ = [
    "DEFAULT_VIEWER_PORT",
    "RecordingFailed",
    "RerunUnavailable",
    "RunRecording",
    "blueprint",
    "open_recording",
    "RerunSink",
]

DEFAULT_VIEWER_PORT = 9876
#: The longest the end of a run waits for a viewer to take what was sent (s); the SDK then gives
#: up a connection that never came within a few seconds more.
LIVE_FLUSH_TIMEOUT_S = 10.0

# entity path -> series on it: (Sample field, scale, legend name). One send_columns
# call per entity and batch: every call holds the interpreter for a while.
_SERIES = {
    "theta": (("theta", 1.0, "theta (rad)"), ("target_theta", 1.0, "target_theta (rad)")),
    "alpha": (("alpha", 1.0, "alpha (rad)"), ("target_alpha", 1.0, "target_alpha (rad)")),
    "voltage": (
        ("control_output", 1.0, "controller output (V)"),
        ("plant_input", 1.0, "applied, clamped (V)"),
        ("feedforward", 1.0, "feedforward (V)"),
    ),
    "timing": (("lateness", 1e3, "lateness (ms)"), ("compute_time", 1e3, "compute time (ms)")),
}
_FIELDS = [(name, scale) for series in _SERIES.values() for name, scale, _ in series]  # Sample's float fields
EVENTS = "events"


class RerunUnavailable(RuntimeError):
    """No rerun viewer to stream to (the message says what to do instead)."""


class RecordingFailed(RuntimeError):
    """The run's recording could not be written, or its viewer did not take it (one line naming which)."""


def blueprint():
    """The run's default layout: angles against references, voltages, timing, events."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Vertical(
            rrb.TimeSeriesView(origin="/theta", name="theta vs reference (rad)"),
            rrb.TimeSeriesView(origin="/alpha", name="alpha vs reference (rad)"),
            rrb.TimeSeriesView(origin="/voltage", name="voltages (V)"),
            rrb.TimeSeriesView(origin="/timing", name="loop timing (ms)"),
            rrb.TextLogView(origin=f"/{EVENTS}", name="episodes"),
            row_shares=[3, 3, 3, 2, 1],
        ),
        collapse_panels=True,
    )


def _port_open(host: str, port: int, timeout: float = 0.3) -> bool:
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def _viewer_url(port: int) -> str:
    return f"rerun+http://127.0.0.1:{port}/proxy"


def _live_sink(url: str | None, port: int):
    """A gRPC sink to a viewer: the given URL, a viewer already listening, or one spawned."""
    import rerun as rr

    if url:
        return rr.GrpcSink(url)
    if _port_open("127.0.0.1", port):
        return rr.GrpcSink(_viewer_url(port))
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise RerunUnavailable(
            f"no rerun viewer is listening on 127.0.0.1:{port} and there is no display to open one; "
            "start a viewer elsewhere and pass its address, or record with --rerun-save FILE.rrd"
        )
    try:
        rr.spawn(port=port, connect=False)
    except Exception as exc:  # noqa: BLE001 - any spawn failure becomes one clear message
        raise RerunUnavailable(f"could not start the rerun viewer: {exc}") from None
    if not _port_open("127.0.0.1", port, timeout=5.0):
        raise RerunUnavailable(f"the rerun viewer did not start listening on 127.0.0.1:{port}")
    return rr.GrpcSink(_viewer_url(port))


def open_recording(
    *,
    live: bool = False,
    url: str | None = None,
    save: str | Path | None = None,
    port: int = DEFAULT_VIEWER_PORT,
    application_id: str = "qube-run",
    recording_id: str | None = None,
):
    """A rerun recording streaming to a viewer and/or saving to an .rrd file, with the default blueprint.

    Parameters
    ----------
    live : bool
        Stream to a viewer: ``url`` if given, else one listening on ``port``,
        else a newly spawned one (needs a display).
    url : str, optional
        Viewer address, e.g. ``rerun+http://host:9876/proxy``.
    save : path, optional
        Also write the recording to this .rrd file (headless), whole, when
        :meth:`RunRecording.finish` is called.
    port : int
        Local viewer port.

    Returns
    -------
    RunRecording

    Raises
    ------
    RerunUnavailable
        When rerun-sdk is not installed, or ``live`` and no viewer can be
        reached or started.
    """
    try:
        rr = import_rerun()
    except ImportError:
        raise RerunUnavailable(
            'rerun-sdk is not installed (the viewer is optional): pip install "qube-koopman[viz]"'
        ) from None
    if not live and save is None:
        raise ValueError("open_recording needs live=True or a save path")
    stream, unreachable = None, None
    address = _address(url) if live and url else None
    if address is not None and not _port_open(*address, timeout=1.0):
        # Told of a viewer that is not there, the SDK waits 5 s to open the stream and 5 s more to close it: the
        # run goes on without it and says so at its end, as for a viewer that goes away.
        unreachable = f"nothing listens on {address[0]}:{address[1]}"
    elif live:
        stream = rr.RecordingStream(application_id, recording_id=recording_id)
        stream.set_sinks(_live_sink(url, port), default_blueprint=blueprint())
    rrd = None
    if save is not None:
        same_id = recording_id if stream is None else stream.get_recording_id()  # one recording in the viewer
        rrd = RrdProcess(save, application_id, blueprint=f"{__name__}:blueprint", recording_id=same_id)
    return RunRecording(stream, rrd, unreachable)


def _address(url: str) -> tuple[str, int] | None:
    """A viewer URL's host and port (``rerun+http://HOST:PORT/proxy``), None when it names none."""
    from urllib.parse import urlsplit

    try:
        where = urlsplit(url.removeprefix("rerun+"))
        return (where.hostname, where.port) if where.hostname and where.port else None
    except ValueError:
        return None


class RunRecording:
    """A run's rerun recording: a live stream to a viewer, a file written as the run goes, or both.

    Takes :class:`core.rrd.RrdProcess`'s calls (``log``, ``set_time``, ``send_scalars``) and
    sends each to both.

    Parameters
    ----------
    live : rerun.RecordingStream or None
        The stream to a viewer.
    rrd : core.rrd.RrdProcess or None
        The file.
    unreachable : str, optional
        Why a viewer asked for was not streamed to (nothing listened at its address): reported by
        :meth:`finish` as a viewer that did not take the recording.
    """

    def __init__(self, live=None, rrd: RrdProcess | None = None, unreachable: str | None = None) -> None:
        self.live = live
        self.rrd = rrd
        self.unreachable = unreachable

    def _apply(self, op: tuple) -> None:
        if self.live is not None:
            apply_op(import_rerun(), self.live, op)

    def log(self, entity: str, archetype: str, *, static: bool = False, **kwargs) -> None:
        """Log ``rerun.<archetype>(**kwargs)`` at ``entity``."""
        self._apply(("log", entity, archetype, kwargs, static))
        if self.rrd is not None:
            self.rrd.log(entity, archetype, static=static, **kwargs)

    def set_time(self, timeline: str, **kwargs) -> None:
        """Set the time of what is logged next on ``timeline``."""
        self._apply(("set_time", timeline, kwargs))
        if self.rrd is not None:
            self.rrd.set_time(timeline, **kwargs)

    def send_scalars(self, entity: str, indexes: list[tuple], values) -> None:
        """Scalars at ``entity`` against ``(timeline, kind, array)`` time columns."""
        self._apply(("scalars", entity, indexes, values))
        if self.rrd is not None:
            self.rrd.send_scalars(entity, indexes, values)

    def finish(self, timeout: float = LIVE_FLUSH_TIMEOUT_S) -> None:
        """Hand the viewer what is left (waiting at most ``timeout`` s) and complete the file.

        Raises
        ------
        RecordingFailed
            The viewer did not take the recording, or the file could not be written (then no
            file is left under its name); both are tried whatever the other did.
        """
        problems = []
        if self.unreachable is not None:
            problems.append(f"--rerun: the viewer did not take the recording: {self.unreachable}")
        if self.live is not None:
            try:
                flush_recording(self.live, timeout)
            except RuntimeError as exc:  # no viewer (any more), or a timeout
                problems.append(f"--rerun: the viewer did not take the recording: {exc}")
            self.live.disconnect()  # gives up an unreachable viewer within seconds
        if self.rrd is not None:
            try:
                self.rrd.close()
            except OSError as exc:
                problems.append(f"{exc.filename}: {exc.strerror}; the rerun recording was not written")
        if problems:
            raise RecordingFailed("; ".join(problems))


class RerunSink:
    """Sends every episode of a run to a rerun recording, in batches, from the writer thread.

    Optional (``required = False``): a failing viewer never stops data
    collection.

    Parameters
    ----------
    recording : RunRecording
        From :func:`open_recording`.
    batch_seconds : float
        Send the buffered samples every this many seconds of data.
    """

    required = False

    def __init__(self, recording, batch_seconds: float = 0.25) -> None:
        self.recording = recording
        self.batch_seconds = batch_seconds
        self._offset = 0.0
        self._index = 0
        self._buffer: list[Sample] = []
        self._jobs: list = []
        self._batch = 1
        self._dt = 0.002
        self._styled = False

    def _style(self) -> None:
        for path, series in _SERIES.items():
            self.recording.log(path, "SeriesLines", static=True, names=[label for _, _, label in series])
        self._styled = True

    def open(self, metadata: EpisodeMetadata) -> None:
        """Mark the episode's start on the event log."""
        if not self._styled:
            self._style()
        self._dt = metadata.dt
        self._batch = max(1, round(self.batch_seconds / self._dt))
        self._index = int(metadata.extra.get("episode_index", self._index))
        self._buffer = []
        seeds = metadata.excitation.get("seeds", {})
        self.recording.set_time("time", duration=self._offset)
        self.recording.set_time("episode", sequence=self._index)
        text = f"episode {self._index} started, seeds {seeds}, backend {metadata.backend}"
        self.recording.log(EVENTS, "TextLog", text=text, level="INFO")

    def write(self, sample: Sample) -> None:
        """Buffer one tick; a full batch becomes one job per plot, sent one job per later tick.

        Spreading the sends keeps each call of this method short, so the
        writer thread can stay clear of the loop's deadlines between them.
        """
        self._buffer.append(sample)
        if len(self._buffer) >= self._batch:
            self._queue_batch()
        elif self._jobs:
            self._send(self._jobs.pop())

    def _queue_batch(self) -> None:
        if not self._buffer:
            return
        rows = np.array([[getattr(s, name) * scale for name, scale in _FIELDS] for s in self._buffer], dtype=float)
        t = self._offset + np.array([s.t for s in self._buffer])
        first = 0
        for path, series in _SERIES.items():
            self._jobs.insert(0, (path, t, rows[:, first : first + len(series)]))
            first += len(series)
        self._buffer = []

    def _send(self, job) -> None:
        path, t, block = job
        indexes = [("time", "duration", t), ("episode", "sequence", np.full(t.size, self._index))]
        self.recording.send_scalars(path, indexes, block)

    def close(self, outcome: EpisodeOutcome) -> None:
        """Send what is buffered and log how the episode ended, with its timing."""
        self._queue_batch()
        while self._jobs:
            self._send(self._jobs.pop())
        timing = outcome.timing
        end = self._offset + outcome.n_samples * self._dt
        text = f"episode {self._index} {outcome.status}" + (f": {outcome.reason}" if outcome.reason else "")
        if timing.paced:
            text += (
                f"; lateness p50 {timing.lateness_p50 * 1e3:.3f} ms, p99 {timing.lateness_p99 * 1e3:.3f} ms, "
                f"max {timing.lateness_max * 1e3:.3f} ms, {timing.overruns} overruns"
            )
        self.recording.set_time("time", duration=end)
        self.recording.set_time("episode", sequence=self._index)
        self.recording.log(EVENTS, "TextLog", text=text, level="INFO" if outcome.status == "complete" else "WARN")
        self._offset = end
        self._index += 1

    def finish(self) -> None:
        """End the recording: the viewer has been sent everything and the .rrd file is complete.

        Raises
        ------
        RecordingFailed
            The file could not be written, or the viewer did not take the run.
        """
        self.recording.finish()
