"""Writing episode logs: incrementally, sample by sample, or a whole episode at once."""

from __future__ import annotations

import math
import os
import secrets
import stat
import struct
from datetime import datetime, timezone
from pathlib import Path
from typing import IO, Mapping

import numpy as np

try:
    import fcntl
except ImportError:  # not a POSIX system: temporary files are not locked
    fcntl = None  # type: ignore[assignment]  # mypy: a module or, here, None

from qube_koopman.daq.episode import SIGNALS, Episode, EpisodeMetadata
from qube_koopman.daq.log.mcap_writer import COMPRESSIONS, BlockWriter
from qube_koopman.daq.log.metadata import STATUS_RECORD, episode_records, status_record
from qube_koopman.daq.log.schema import (
    CDR_LE_HEADER,
    FORMAT_VERSION,
    SAMPLE_SCHEMA_NAME,
    SAMPLE_TOPIC,
    payload_dtype,
    sample_fields,
    schema_text,
    state_field,
)

__all__ = ["EpisodeWriter", "write_episode", "remove_stale_temp_files"]

#: Samples held before they go to the MCAP writer when no flush comes sooner (``flush_interval_s=None``).
_BLOCK = 1024


def _epoch_ns(start_time: str) -> int:
    # MCAP log times are absolute nanoseconds; a start time without a UTC
    # offset (the legacy rig's local time) is placed on the axis as if UTC.
    start = datetime.fromisoformat(start_time)
    if start.tzinfo is None:
        start = start.replace(tzinfo=timezone.utc)
    delta = start - datetime(1970, 1, 1, tzinfo=timezone.utc)
    return (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1000


class EpisodeWriter:
    """Write one episode to an MCAP file, sample by sample.

    The file is created at once with the episode's metadata, and samples go
    into compressed chunks that are flushed every ``flush_interval_s`` of
    data: a process killed mid-episode leaves a file that
    :func:`daq.log.read_episode` reads up to the last flush, marked
    incomplete. :meth:`finish` records the final status.

    Not thread-safe, and not for the real-time loop's thread: compressing a
    chunk takes milliseconds (MCAP ``add_message`` spikes of 5-33 ms). The
    loop hands samples to a writer thread (e.g. through a queue), and only
    that thread calls this object.

    Parameters
    ----------
    path : str or Path
        Output file (conventionally ``*.mcap``).
    metadata : EpisodeMetadata
        Controller, sample rate, excitation and provenance; its status
        fields are ignored (the status is given to :meth:`finish`).
    flush_interval_s : float or None
        Make the data durable (against a killed process, not a power cut
        unless ``fsync``) every this many seconds of samples; None flushes
        only when a chunk is full and at the end.
    compression : {"zstd", "lz4", "none"}
        Chunk compression.
    overwrite : bool
        Replace an existing file; by default an existing file is an error.
    fsync : bool
        Also ``os.fsync`` at every flush.

    Raises
    ------
    FileExistsError
        If ``path`` exists and ``overwrite`` is false.

    Examples
    --------
    >>> with EpisodeWriter("run.mcap", meta) as log:          # doctest: +SKIP
    ...     for sample in samples:                              # writer thread
    ...         log.write_sample(**sample)
    ...     log.finish("aborted", "pendulum fell: |alpha| > pi/4")
    """

    def __init__(
        self,
        path: str | os.PathLike,
        metadata: EpisodeMetadata,
        *,
        flush_interval_s: float | None = 0.5,
        compression: str = "zstd",
        overwrite: bool = False,
        fsync: bool = False,
    ) -> None:
        if compression not in COMPRESSIONS:
            raise ValueError(f"compression must be one of {', '.join(COMPRESSIONS)}, got {compression!r}")
        if flush_interval_s is not None and not flush_interval_s > 0:
            raise ValueError(f"flush_interval_s must be positive or None, got {flush_interval_s!r}")
        self.path = Path(path)
        self.metadata = metadata
        self._n_states = metadata.controller.system.n_states
        self._tick_fields = tuple(metadata.controller.tick_fields)
        self._flush_every = (
            None if flush_interval_s is None else max(1, round(flush_interval_s * metadata.sample_rate_hz))
        )
        self._fsync = fsync
        self._epoch_ns = _epoch_ns(metadata.start_time)
        fields = sample_fields(self._n_states, self._tick_fields)
        self._dtype = payload_dtype(fields)
        # "<" packs without padding; valid because payload_dtype has none for
        # this field order (float64s first, the int8 last).
        self._struct = struct.Struct("<4s" + "d" * (len(fields) - 1) + "b")
        assert self._struct.size == self._dtype.itemsize
        self._file: IO[bytes] = open(self.path, "wb" if overwrite else "xb")
        try:
            self._start(metadata, compression)
        except BaseException:
            # A file whose header never reached the disk (a full disk, a size limit) is no log:
            # nothing is left behind that a reader would have to reject.
            try:
                self._file.close()
            except OSError:
                pass
            self.path.unlink(missing_ok=True)
            raise

    def _start(self, metadata: EpisodeMetadata, compression: str) -> None:
        # mcap's Writer's file, with the messages packed in blocks (daq/log/mcap_writer.py says why).
        self._mcap = BlockWriter(self._file, compression)
        self._pending_payloads = bytearray()
        self._pending_times: list[int] = []
        self._mcap.start(profile="", library=f"qube-koopman daq.log {FORMAT_VERSION}")
        schema_id = self._mcap.register_schema(
            SAMPLE_SCHEMA_NAME, "ros2msg", schema_text(self._n_states, self._tick_fields).encode()
        )
        self._channel = self._mcap.register_channel(SAMPLE_TOPIC, "cdr", schema_id)
        for name, record in episode_records(metadata).items():
            self._mcap.add_metadata(name, record)
        self._n = 0
        self._since_flush = 0
        self._finished = False
        self.flush()

    @property
    def n_samples(self) -> int:
        """Samples written so far."""
        return self._n

    @property
    def finished(self) -> bool:
        """True once :meth:`finish` has run."""
        return self._finished

    def _check_open(self) -> None:
        if self._finished:
            raise RuntimeError(f"{self.path}: episode log already finished")

    def _add(self, payload: bytes, log_time: int) -> None:
        # Held until the next flush (or a block's worth): the MCAP writer packs them together.
        self._pending_payloads += payload
        self._pending_times.append(log_time)
        self._n += 1
        self._since_flush += 1
        if self._flush_every is not None and self._since_flush >= self._flush_every:
            self.flush()
        elif len(self._pending_times) >= _BLOCK:
            self._hand_over()

    def _hand_over(self) -> None:
        """The held samples to the MCAP writer (which closes a chunk at its size, as mcap's does)."""
        n = len(self._pending_times)
        if n:
            payloads = np.frombuffer(bytes(self._pending_payloads), np.uint8).reshape(n, -1)
            self._mcap.add_messages(self._channel, self._n - n, self._pending_times, payloads)
            self._pending_payloads.clear()
            self._pending_times.clear()

    def write_sample(
        self,
        *,
        t: float,
        theta: float,
        alpha: float,
        target_theta: float,
        target_alpha: float,
        feedforward: float,
        controller_state,
        control_output: float,
        plant_input: float,
        saturation: int,
        lateness: float = float("nan"),
        compute_time: float = float("nan"),
        device_time: float = float("nan"),
        controller_record=(),
    ) -> None:
        """Append one tick (units as in :class:`daq.episode.Episode`; ``controller_record``: the controller's
        per-tick record, one value per ``metadata.controller.tick_fields``).

        Raises
        ------
        ValueError
            If ``t`` is not finite, the controller state has the wrong length
            or saturation is not -1, 0 or +1.
        """
        self._check_open()
        # The loop's controllers give a tuple or a list of floats (struct takes them as they are).
        state = controller_state if type(controller_state) in (tuple, list) else np.ravel(controller_state).tolist()
        if len(state) != self._n_states:
            raise ValueError(f"controller_state must have {self._n_states} values, got {len(state)}")
        if len(controller_record) != len(self._tick_fields):
            raise ValueError(
                f"controller_record must have {len(self._tick_fields)} values, got {len(controller_record)}"
            )
        if saturation not in (-1, 0, 1):
            raise ValueError(f"saturation must be -1, 0 or +1, got {saturation!r}")
        if not math.isfinite(t):
            raise ValueError(f"t must be finite, got {t!r}")
        try:
            payload = self._struct.pack(
                CDR_LE_HEADER,
                t,
                theta,
                alpha,
                target_theta,
                target_alpha,
                feedforward,
                control_output,
                plant_input,
                lateness,
                compute_time,
                device_time,
                *state,
                *controller_record,
                int(saturation),
            )
        except struct.error as exc:  # a value that is not a number
            raise ValueError(f"a sample's values must be numbers: {exc}") from None
        self._add(payload, self._epoch_ns + round(t * 1e9))

    def write_samples(self, episode: Episode) -> None:
        """Append all samples of an episode (its metadata is not written)."""
        self._check_open()
        if episode.controller_state.shape[1] != self._n_states:
            raise ValueError(
                f"episode has {episode.controller_state.shape[1]} controller states, the log {self._n_states}"
            )
        if not np.isfinite(episode.t).all():
            raise ValueError("t must be finite")
        # Pack every payload at once; only the per-message MCAP call stays in Python.
        block = np.zeros(len(episode), self._dtype)
        block["cdr_header"] = np.frombuffer(CDR_LE_HEADER, "<u4")[0]
        for name in SIGNALS:
            block[name] = getattr(episode, name)
        for i in range(self._n_states):
            block[state_field(i)] = episode.controller_state[:, i]
        record = np.asarray(episode.controller_record)  # an episode always holds one (n x 0 for LTI)
        for i, name in enumerate(self._tick_fields):
            block[name] = record[:, i]
        block["saturation"] = episode.saturation
        payloads = block.view(np.uint8).reshape(len(block), self._dtype.itemsize)
        log_times = self._epoch_ns + np.round(episode.t * 1e9).astype(np.int64)
        self._hand_over()
        k = 0
        while k < len(block):  # chunks closed where sample-by-sample writing closes them
            take = len(block) - k
            if self._flush_every is not None:
                take = min(take, self._flush_every - self._since_flush)
            self._mcap.add_messages(self._channel, self._n, log_times[k : k + take], payloads[k : k + take])
            self._n += take
            self._since_flush += take
            k += take
            if self._flush_every is not None and self._since_flush >= self._flush_every:
                self.flush()

    def flush(self) -> None:
        """Close the chunk in progress and push everything written so far to the OS."""
        self._check_open()
        self._hand_over()
        self._mcap.flush()
        self._since_flush = 0
        if self._fsync:
            os.fsync(self._file.fileno())

    def finish(
        self,
        status: str = "complete",
        reason: str = "",
        timing: Mapping | None = None,
        backend_stats: Mapping | None = None,
    ) -> None:
        """Record the final status and close the file.

        Parameters
        ----------
        status : {"complete", "aborted"}
            How the episode ended.
        reason : str
            Why it was aborted (required then).
        timing : mapping, optional
            The loop's timing statistics of the episode (plain numbers;
            NaN is stored as null), recorded with the status.
        backend_stats : mapping, optional
            The backend's counters of the episode (plain data), recorded with the status.
        """
        self._check_open()
        if status not in ("complete", "aborted"):
            raise ValueError(f"status must be 'complete' or 'aborted', got {status!r}")
        if status == "aborted" and not reason:
            raise ValueError("an aborted episode needs a reason")
        try:
            # Flush first so the status record follows the last chunk in the file.
            self.flush()
            self._mcap.add_metadata(STATUS_RECORD, status_record(status, reason, self._n, timing, backend_stats))
            self._mcap.finish()
            self._file.flush()
            if self._fsync:
                os.fsync(self._file.fileno())
        except BaseException:
            self.abandon()
            raise
        self._file.close()
        self._finished = True

    def abandon(self) -> None:
        """Close the file without a status record (after a write error): it reads as incomplete.

        What was flushed before stays readable (the salvage path of :func:`daq.log.read_episode`);
        whatever the OS refuses now is dropped. Never raises.
        """
        self._finished = True
        try:
            self._file.close()
        except OSError:
            pass

    def __enter__(self) -> "EpisodeWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self._finished:
            return
        if exc_type is None:
            self.finish("complete")
        else:
            self.finish("aborted", f"{exc_type.__name__}: {exc}")


def write_episode(
    path: str | os.PathLike, episode: Episode, *, overwrite: bool = False, compression: str = "zstd"
) -> Path:
    """Write a whole episode to ``path`` at once.

    The file appears only when complete (written beside it, then linked or
    renamed into place), so an interrupted call leaves no partial log.
    An episode whose status is ``"incomplete"`` is recorded as aborted,
    with the reason saying so.

    Parameters
    ----------
    path : str or Path
        Output file.
    episode : Episode
        What to write.
    overwrite : bool
        Replace an existing file; by default it is an error.
    compression : {"zstd", "lz4", "none"}
        Chunk compression.

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    FileExistsError
        If ``path`` exists and ``overwrite`` is false.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: file exists")
    meta = episode.metadata
    status, reason = meta.status, meta.status_reason
    if status == "incomplete":
        status, reason = "aborted", f"incomplete log: {reason or 'no final status'}"
    fd, tmp = _temp_file(path)
    try:
        # The live writer's chunks (0.5 s of samples): a damaged byte costs one chunk, never the episode.
        writer = EpisodeWriter(tmp, meta, compression=compression, overwrite=True)
        writer.write_samples(episode)
        writer.finish(status, reason)
        if overwrite:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)  # fails if path appeared meanwhile: never clobber
            except FileExistsError:
                raise FileExistsError(f"{path}: file exists") from None
            except OSError:  # a file system without hard links
                os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
        os.close(fd)  # releases the lock
    return path


def _temp_name(path: Path, tag: str = "*") -> str:
    return f".{path.name}.{tag}.tmp"


def _temp_file(path: Path) -> tuple[int, str]:
    """A new hidden file beside ``path``, locked while its writer lives, as ``(fd, name)``.

    Created like :func:`open` creates a file (mode 0666 less the umask; ``tempfile.mkstemp``
    makes 0600 whatever the umask), exclusively, and held under an advisory lock (``flock``)
    until ``fd`` is closed, so :func:`remove_stale_temp_files` never takes a live one. A
    cleaner that took it in the instant between its creation and its lock is seen (the name
    no longer leads to it): another name is tried.
    """
    for _ in range(100):
        tmp = path.with_name(_temp_name(path, secrets.token_hex(4)))
        try:
            fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
        except FileExistsError:
            continue
        if fcntl is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:  # a file system without locks: then never taken for stale either
                pass
        if _same_file(tmp, fd):
            return fd, str(tmp)
        os.close(fd)
    raise FileExistsError(f"{path}: no free temporary name beside it")


def _same_file(path: Path, fd: int) -> bool:
    """Whether ``path`` still names the file open as ``fd``."""
    try:
        named, held = os.stat(path), os.fstat(fd)
    except FileNotFoundError:
        return False
    return (named.st_dev, named.st_ino) == (held.st_dev, held.st_ino)


def remove_stale_temp_files(folder: str | os.PathLike, suffix: str = ".mcap") -> list[Path]:
    """Remove what interrupted :func:`write_episode` calls left in ``folder``; return the files removed.

    Only hidden ``.<name><suffix>.<tag>.tmp`` regular files (the names :func:`write_episode`
    gives its temporary files) are candidates, and of those only the ones no live writer
    holds locked (a writer locks its file as it creates it, see :func:`_temp_file`). Without
    ``fcntl`` (not a POSIX system) nothing is removed.

    Parameters
    ----------
    folder : str or PathLike
        The folder logs are written to.
    suffix : str, default ".mcap"
        The suffix of the logs whose temporary files are looked for.

    Returns
    -------
    list of Path
        The files removed.
    """
    removed: list[Path] = []
    if fcntl is None or not Path(folder).is_dir():
        return removed
    for tmp in sorted(Path(folder).glob(_temp_name(Path(f"*{suffix}")))):  # the names _temp_file gives
        try:
            fd = os.open(tmp, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0))
        except OSError:  # gone, a link, unreadable: not ours to judge
            continue
        try:
            info = os.fstat(fd)
            if not stat.S_ISREG(info.st_mode):
                continue
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # OSError: a writer holds it
            os.unlink(tmp)
            removed.append(tmp)
        except OSError:
            continue
        finally:
            os.close(fd)
    return removed
