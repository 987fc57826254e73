"""Rerun recordings (``.rrd`` files) that appear only whole and never hang a command (rerun-sdk imported lazily).

Every command's ``--rerun-save`` goes through :class:`RrdFile`: the recording is encoded in memory
(rerun-sdk's binary stream) and written by this module, with Python's own file I/O, to a temporary
file beside the final one, renamed into place when complete (:func:`core.files.atomic_path`).

Why not rerun-sdk's file sink: it writes on a thread of its own, and when a write fails (a full
disk, a file-size limit) that thread ends while a flush may still be queued behind the failed
write. That flush is never answered: ``flush()`` without a timeout, ``disconnect()`` and the
recording's destruction at exit then wait for ever, every thread parked, deaf to Ctrl-C and
SIGTERM (rerun-sdk 0.41). The in-memory stream never touches the disk, its flush is bounded by a
timeout, and a write that fails here is an ordinary ``OSError`` naming the file: one error line.
"""

from __future__ import annotations

import errno
import importlib
import os
from pathlib import Path

from qube_koopman.core.files import atomic_path

__all__ = ["FLUSH_TIMEOUT_S", "RrdFile", "import_rerun"]

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


class RrdFile:
    """A rerun recording held in memory and written to ``path`` whole by :meth:`save`.

    Log to :attr:`recording` (a ``rerun.RecordingStream``); nothing reaches the disk before
    :meth:`save`. A process stopped before (even by SIGKILL) leaves no file under ``path``; one
    stopped while saving leaves at most a locked temporary file, removed by the next write of
    ``path``. The encoded recording stays in memory until saved (about 70 kB per second of a
    ``qube-run`` episode).

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
            data = self._stream.read(flush=True, flush_timeout_sec=timeout)
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
