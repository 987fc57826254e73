"""Rerun recordings (``.rrd`` files) that appear only whole and never hang a command (rerun-sdk imported lazily).

Two writers, both into a temporary file beside the final one, renamed into place when complete
(:func:`core.files.atomic_path`):

- :class:`RrdFile`, for a recording made at once (``qube-identify``, ``qube-design``,
  ``qube-calibrate``): encoded in memory (rerun-sdk's binary stream) and written with Python's own
  file I/O, whose errors are ordinary ``OSError`` naming the file.
- :class:`RrdProcess`, for a recording that grows as a run goes (``qube-run --rerun-save``): a
  child process takes the data through a pipe and writes it with rerun-sdk's file sink, so the
  memory it takes stays bounded however long the run.

Why never the file sink in the command's own process: it writes on a thread of its own, and when
a write fails (a full disk, a file-size limit) that thread ends while a flush may still be queued
behind the failed write. That flush is never answered: ``flush()`` without a timeout,
``disconnect()`` and the recording's destruction at exit then wait for ever, every thread
parked, deaf to Ctrl-C and SIGTERM (rerun-sdk 0.41), and the SDK has no call that bounds the
last two. In a child process the wait is bounded by this module: the child is killed after a
timeout, and the error it printed (``os error N``) names the cause.
"""

from __future__ import annotations

import errno
import importlib
import os
import pickle
import queue
import re
import subprocess
import sys
import threading
import time
from contextlib import ExitStack
from pathlib import Path

from qube_koopman.core.files import atomic_path

__all__ = ["FLUSH_TIMEOUT_S", "RrdFile", "RrdProcess", "apply_op", "flush_recording", "import_rerun", "read_stream"]

#: The longest a recording's encoding may take to finish (it is in memory: seconds at most).
FLUSH_TIMEOUT_S = 60.0


def import_rerun():
    """rerun-sdk, imported with its own log lines off unless ``RUST_LOG`` asks for them.

    A failure is reported by the command, once, in its own words; the SDK would add warnings of
    its own on stderr (a viewer it cannot reach, a recording it drops).

    Raises
    ------
    ImportError
        rerun-sdk (the optional ``viz`` extra) is not installed.
    """
    os.environ.setdefault("RUST_LOG", "off")  # read by the SDK's first import
    return importlib.import_module("rerun")


def flush_recording(recording, timeout: float) -> None:
    """``recording.flush`` within ``timeout`` seconds where the SDK can bound it (``timeout_sec``, in recent
    releases); the oldest release this toolkit allows (0.24) flushes without a bound."""
    try:
        recording.flush(timeout_sec=timeout)
    except TypeError:  # no timeout_sec: an older rerun-sdk
        recording.flush(blocking=True)


def read_stream(stream, timeout: float) -> bytes | None:
    """A binary stream's bytes, flushed first (within ``timeout`` where the SDK can bound it, as
    :func:`flush_recording`)."""
    try:
        return stream.read(flush=True, flush_timeout_sec=timeout)
    except TypeError:  # no flush_timeout_sec: an older rerun-sdk
        return stream.read(flush=True)


class RrdFile:
    """A rerun recording held in memory and written to ``path`` whole by :meth:`save`.

    Log to :attr:`recording` (a ``rerun.RecordingStream``); nothing reaches the disk before
    :meth:`save`. A process stopped before (even by SIGKILL) leaves no file under ``path``; one
    stopped while saving leaves at most a locked temporary file, removed by the next write of
    ``path``. The recording stays in memory until saved: for one made at once; one that grows
    with a run takes :class:`RrdProcess`.

    Parameters
    ----------
    path : str or Path
        The ``.rrd`` file (replaced when it exists).
    application_id : str
        The recording's application (the viewer groups recordings by it).
    blueprint : rerun blueprint, optional
        The recording's default layout.
    recording_id : str, optional
        The recording's id (a new one when not given).

    Raises
    ------
    ImportError
        rerun-sdk is not installed.
    """

    def __init__(self, path: str | Path, application_id: str, *, blueprint=None, recording_id: str | None = None):
        rr = import_rerun()
        self.path = Path(path)
        self.recording = rr.RecordingStream(application_id, recording_id=recording_id)
        self._stream = self.recording.binary_stream()
        if blueprint is not None:  # as save(default_blueprint=...) sends it: the default, not forced active
            self.recording.send_blueprint(blueprint, make_active=False, make_default=True)

    def save(self, timeout: float = FLUSH_TIMEOUT_S) -> Path:
        """Finish the recording and write it to :attr:`path` whole; the recording takes no more data.

        Parameters
        ----------
        timeout : float
            The longest to wait for the SDK to finish encoding (s).

        Returns
        -------
        Path
            :attr:`path`.

        Raises
        ------
        OSError
            The file cannot be written (a full disk, a file-size limit, a missing folder) or the
            recording could not be finished in time; ``filename`` is :attr:`path`, and nothing is
            left under that name or beside it.
        """
        try:
            data = read_stream(self._stream, timeout)
        except RuntimeError as exc:  # the SDK's timeout
            raise OSError(
                errno.ETIMEDOUT, f"the rerun recording could not be finished: {exc}", str(self.path)
            ) from None
        self.recording.disconnect()  # flushed, and a memory sink: nothing to wait for
        try:
            with atomic_path(self.path) as tmp:
                tmp.write_bytes(data or b"")
        except OSError as exc:  # named by the final file, not the temporary one
            raise OSError(exc.errno, exc.strerror or str(exc), str(self.path)) from None
        return self.path


def apply_op(rr, recording, op: tuple) -> None:
    """Apply one call of :class:`RrdProcess`'s vocabulary to a ``rerun.RecordingStream``.

    ``op`` is ``("log", entity, archetype, kwargs, static)`` (``rr.<archetype>(**kwargs)``),
    ``("set_time", timeline, kwargs)`` or ``("scalars", entity, indexes, values)``, where
    ``indexes`` holds ``(timeline, kind, array)`` (``kind``: ``"duration"``, ``"sequence"``...)
    and ``values`` the scalars, one row per index value.
    """
    kind = op[0]
    if kind == "log":
        _, entity, archetype, kwargs, static = op
        recording.log(entity, getattr(rr, archetype)(**kwargs), static=static)
    elif kind == "set_time":
        recording.set_time(op[1], **op[2])
    elif kind == "scalars":
        _, entity, indexes, values = op
        columns = [rr.TimeColumn(timeline, **{unit: array}) for timeline, unit, array in indexes]
        recording.send_columns(entity, indexes=columns, columns=rr.Scalars.columns(scalars=values))
    else:
        raise ValueError(f"unknown recording call {kind!r}")


class RrdProcess:
    """A rerun recording a child process writes as the data comes; renamed to ``path`` whole by :meth:`close`.

    The calls (:meth:`log`, :meth:`set_time`, :meth:`send_scalars`) never block: they queue the
    data for a thread that pipes it to the child. The child, in a session of its own (Ctrl-C at
    the terminal is the command's to handle), writes a temporary file beside ``path`` with
    rerun-sdk's file sink; :meth:`close` waits for it, at most ``timeout`` seconds, then renames
    the file into place, or removes it and says why. A command killed outright leaves no file
    under ``path``: the child, seeing its input end, finishes the temporary file, which the next
    write of ``path`` removes.

    Parameters
    ----------
    path : str or Path
        The ``.rrd`` file (replaced when it exists).
    application_id : str
        The recording's application.
    blueprint : str, optional
        ``"module:function"`` returning the recording's default layout (built in the child).
    recording_id : str, optional
        The recording's id (a new one when not given).
    max_queued : int
        Calls that may wait for the child; more (a child that fell behind or stopped reading)
        and the recording is given up, reported by :meth:`close`.
    """

    def __init__(
        self,
        path: str | Path,
        application_id: str,
        *,
        blueprint: str | None = None,
        recording_id: str | None = None,
        max_queued: int = 10_000,
    ) -> None:
        self.path = Path(path)
        self._problem: str | None = None
        self._queue: queue.Queue = queue.Queue(max_queued)
        self._stack = ExitStack()
        tmp = self._stack.enter_context(atomic_path(self.path))
        env = dict(os.environ, RUST_LOG="error")  # the child's errors say what failed; they are read, not shown
        try:
            self._child = subprocess.Popen(
                [sys.executable, "-c", "from qube_koopman.core.rrd import _child_main; _child_main()"],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                bufsize=0,
                env=env,
                start_new_session=True,
            )
        except BaseException:
            self._stack.__exit__(OSError, None, None)  # no child: no temporary file either
            raise
        stdin, stdout, stderr = self._child.stdin, self._child.stdout, self._child.stderr
        assert stdin is not None and stdout is not None and stderr is not None  # each asked for as a pipe
        self._stdin, self._stdout, self._stderr = stdin, stdout, stderr
        self._queue.put(("open", str(tmp), application_id, recording_id, blueprint))
        self._pump = threading.Thread(target=self._send_all, name="rrd-pipe", daemon=True)
        self._pump.start()
        self._errors: list[str] = []
        self._failed = threading.Event()  # the child's writer reported an error: do not wait for it
        self._listener = threading.Thread(target=self._listen, name="rrd-errors", daemon=True)
        self._listener.start()

    def _send(self, op: tuple) -> None:
        if self._problem is not None:
            return
        try:
            self._queue.put_nowait(op)
        except queue.Full:
            self._problem = "the recording fell behind the run"

    def _send_all(self) -> None:
        stdin = self._stdin
        try:
            while (op := self._queue.get()) is not None:
                if self._problem is not None:
                    continue
                try:
                    pickle.dump(op, stdin, protocol=pickle.HIGHEST_PROTOCOL)
                except OSError:  # the child is gone: close() says why
                    self._problem = self._problem or "the recording's writer stopped"
        finally:
            try:
                stdin.close()  # the child's end of the data: it completes the file
            except OSError:
                pass

    def _listen(self) -> None:
        for line in self._stderr:
            text = line.decode(errors="replace")
            self._errors.append(text)
            if "ERROR" in text or "os error" in text:
                self._failed.set()

    def log(self, entity: str, archetype: str, *, static: bool = False, **kwargs) -> None:
        """``rerun.RecordingStream.log(entity, rerun.<archetype>(**kwargs), static=static)`` in the child."""
        self._send(("log", entity, archetype, kwargs, static))

    def set_time(self, timeline: str, **kwargs) -> None:
        """``rerun.RecordingStream.set_time(timeline, **kwargs)`` in the child."""
        self._send(("set_time", timeline, kwargs))

    def send_scalars(self, entity: str, indexes: list[tuple], values) -> None:
        """Scalars against time columns in the child (:func:`apply_op`'s ``"scalars"``)."""
        self._send(("scalars", entity, indexes, values))

    def close(self, timeout: float = FLUSH_TIMEOUT_S) -> Path:
        """End the recording: wait for the child (at most about ``timeout`` s), rename its file into place.

        Returns
        -------
        Path
            :attr:`path`.

        Raises
        ------
        OSError
            The file could not be written (``errno`` and ``strerror`` from the child's error when
            it names one: a full disk, a file-size limit), the child stopped, or it did not finish
            in time; ``filename`` is :attr:`path`, and nothing is left under that name or beside it.
        """
        deadline = time.monotonic() + timeout
        try:
            self._queue.put(None, timeout=timeout)
        except queue.Full:
            self._child.kill()  # not reading: the pump's write fails, it drains, the put goes through
            self._queue.put(None)
        self._pump.join(max(0.0, deadline - time.monotonic()))
        # The child completes the file and exits, or has reported its writer's error: then its flush
        # may never return, and there is nothing to wait for.
        while self._child.poll() is None and not self._failed.is_set() and time.monotonic() < deadline:
            self._failed.wait(0.05)
        if self._child.poll() is None:
            if not self._failed.is_set():
                self._problem = self._problem or f"the recording was not finished within {timeout:g} s"
            self._child.kill()
        self._child.wait()
        self._pump.join()
        self._listener.join()
        out = self._stdout.read()
        self._stdout.close()
        self._stderr.close()
        error = _child_error(out, "".join(self._errors), self._child.returncode)
        if self._problem is None and error is None:
            self._stack.close()  # renames the temporary file into place
            return self.path
        self._stack.__exit__(OSError, None, None)  # removes it
        code, text = error or (errno.EIO, self._problem)
        raise OSError(code, text, str(self.path))


def _child_error(out: bytes, text: str, status: int | None) -> tuple[int, str] | None:
    """``(errno, strerror)`` of a child that did not end with its file complete, else None."""
    if status == 0 and out.strip() == b"ok":
        return None
    found = re.search(r"\(os error (\d+)\)", text)
    if found:
        code = int(found.group(1))
        return code, os.strerror(code)
    lines = out.decode(errors="replace").strip().splitlines() or [f"the recording's writer ended with status {status}"]
    return errno.EIO, lines[-1]


def _child_main() -> None:
    """The child of :class:`RrdProcess`: the calls from stdin into a file sink; ``ok`` on stdout when complete.

    Ends with ``os._exit``: rerun-sdk's own handler at exit could wait for ever on a sink that failed.
    """
    status, message = 0, b"ok\n"
    try:
        stdin = sys.stdin.buffer
        _, part, application_id, recording_id, blueprint = pickle.load(stdin)
        rr = importlib.import_module("rerun")
        recording = rr.RecordingStream(application_id, recording_id=recording_id)
        layout = None
        if blueprint:
            module, _, function = blueprint.partition(":")
            layout = getattr(importlib.import_module(module), function)()
        recording.save(part, default_blueprint=layout)
        while True:
            try:
                op = pickle.load(stdin)
            except EOFError:
                break
            apply_op(rr, recording, op)
        flush_recording(recording, FLUSH_TIMEOUT_S)
        recording.disconnect()
    except BaseException as exc:  # noqa: BLE001 - any failure is the parent's to report
        status, message = 1, f"{exc}\n".encode()
    finally:
        try:
            os.write(1, message)
        except OSError:  # the parent is gone (killed): nobody to tell
            pass
        os._exit(status)  # never the interpreter's exit, where rerun-sdk's handler could wait for ever
