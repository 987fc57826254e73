"""Episodes: the unit of data, as the loop records it and identification reads it.

An :class:`Episode` holds time-aligned arrays at a fixed sample rate plus
:class:`EpisodeMetadata` (the controller, excitation, backend, provenance
and the final status). It knows nothing about files: ``daq.log`` writes and
reads it as MCAP, ``daq.legacy_csv`` builds it from the rig's CSV files.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, fields
from datetime import datetime
from types import MappingProxyType
from typing import Any, Mapping, Sequence

import numpy as np

from qube_koopman.core.controller_file import ControllerInfo, plain_json
from qube_koopman.core.lti import DiscreteStateSpace

__all__ = [
    "STATUSES",
    "SIGNALS",
    "STATE_SIGNALS",
    "REFERENCE_SIGNALS",
    "UNITS",
    "EpisodeMetadata",
    "Episode",
    "software_version",
    "stack_signals",
]

#: Final status of an episode: finished normally, stopped early with a
#: reason, or cut short without a status (the writer died; set by the reader).
STATUSES = ("complete", "aborted", "incomplete")

#: One-dimensional float signals of an episode, in storage order.
SIGNALS = (
    "t",
    "theta",
    "alpha",
    "target_theta",
    "target_alpha",
    "feedforward",
    "control_output",
    "plant_input",
    "lateness",
    "compute_time",
    "device_time",
)

#: Units of every per-sample quantity (the controller state has the units of
#: the controller's realization: V per (rad) for the rig's PD filters).
UNITS = MappingProxyType(
    {
        "t": "s",
        "theta": "rad",
        "alpha": "rad",
        "target_theta": "rad",
        "target_alpha": "rad",
        "feedforward": "V",
        "control_output": "V",
        "plant_input": "V",
        "lateness": "s",
        "compute_time": "s",
        "device_time": "s",
        "controller_state": "rad (controller realization)",
        "saturation": "1",
    }
)

#: The measured plant states (the fed-back outputs), in the controller's channel order.
STATE_SIGNALS = ("theta", "alpha")

#: Their references, channel for channel.
REFERENCE_SIGNALS = ("target_theta", "target_alpha")

_TIMING = ("lateness", "compute_time", "device_time")


def stack_signals(source: Any, names: Sequence[str]) -> np.ndarray:
    """Named per-sample signals side by side, one column each (the last axis).

    Parameters
    ----------
    source : mapping or object
        Holds the signals as items (a dict of columns) or attributes (an
        :class:`Episode`, an excitation).
    names : sequence of str
        The signals, in column order (e.g. :data:`STATE_SIGNALS`).

    Returns
    -------
    ndarray of shape ``(*signal_shape, len(names))``
        ``(n_samples, k)`` for 1-D signals; a batch of episodes ``(n_samples, n_episodes)``
        stacks to ``(n_samples, n_episodes, k)``.
    """
    get = source.__getitem__ if isinstance(source, Mapping) else lambda name: getattr(source, name)
    return np.stack([np.asarray(get(name), dtype=float) for name in names], axis=-1)


@functools.cache
def software_version() -> str:
    """Name and version of this software, as recorded in logs."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"qube-koopman {version('qube-koopman')}"
    except PackageNotFoundError:
        return "qube-koopman (not installed)"


@dataclass(frozen=True)
class EpisodeMetadata:
    """Everything about an episode that is not a per-sample array.

    Parameters
    ----------
    controller : ControllerInfo
        The controller in the loop.
    sample_rate_hz : float
        Fixed sample rate of all arrays.
    backend : str
        What produced the samples (``"sim"``, ``"serial"``, ``"legacy-rig"``...).
    source : str
        Where the data comes from (a run id, or the imported file's name).
    start_time : str
        ISO 8601 start time of sample 0; without a UTC offset when the
        source did not record one (then it is the rig's local time).
    excitation : mapping
        Excitation seeds and settings (JSON-serializable).
    software_version : str
        Software that wrote the episode.
    status : {"complete", "aborted", "incomplete"}
        Final status; ``"incomplete"`` means the log had no final status.
    status_reason : str
        Why the episode was aborted (or is incomplete); empty when complete.
    salvaged : bool
        Set by the reader: the file was cut short or damaged, and the
        episode holds the readable prefix.
    salvage_note : str
        Set by the reader: what was wrong with the file and what was kept.
    log_format_version : str
        Set by the reader: the format version of the file it came from.
    extra : mapping
        Further JSON-serializable provenance (e.g. a source file's hash).
    backend_stats : mapping
        The backend's counters of the episode (e.g. the serial link's lost
        frames), recorded with the final status; empty when it has none.
    timing : mapping
        The loop's timing statistics of the episode (lateness percentiles,
        overruns...), recorded with the final status; empty when the
        episode has none (imported data, no status record).
    """

    controller: ControllerInfo
    sample_rate_hz: float
    backend: str
    source: str
    start_time: str
    excitation: Mapping[str, Any] = field(default_factory=dict)
    software_version: str = field(default_factory=software_version)
    status: str = "complete"
    status_reason: str = ""
    salvaged: bool = False
    salvage_note: str = ""
    log_format_version: str = ""
    extra: Mapping[str, Any] = field(default_factory=dict)
    timing: Mapping[str, Any] = field(default_factory=dict)
    backend_stats: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.controller, ControllerInfo):
            raise TypeError(f"controller must be a ControllerInfo, got {type(self.controller).__name__}")
        rate = float(self.sample_rate_hz)
        if not (np.isfinite(rate) and rate > 0):
            raise ValueError(f"sample_rate_hz must be a positive number, got {self.sample_rate_hz!r}")
        object.__setattr__(self, "sample_rate_hz", rate)
        if self.status not in STATUSES:
            raise ValueError(f"status must be one of {', '.join(STATUSES)}, got {self.status!r}")
        try:
            datetime.fromisoformat(self.start_time)
        except (TypeError, ValueError):
            raise ValueError(f"start_time must be an ISO 8601 date and time, got {self.start_time!r}") from None
        if abs(self.controller.system.dt * rate - 1.0) > 1e-9:
            raise ValueError(f"controller dt {self.controller.system.dt} s does not match the sample rate {rate} Hz")
        object.__setattr__(self, "excitation", plain_json(self.excitation, "excitation"))
        object.__setattr__(self, "extra", plain_json(self.extra, "extra"))
        object.__setattr__(self, "timing", plain_json(self.timing, "timing"))
        object.__setattr__(self, "backend_stats", plain_json(self.backend_stats, "backend_stats"))

    @property
    def dt(self) -> float:
        """Sample period in seconds."""
        return 1.0 / self.sample_rate_hz

    @property
    def start_datetime(self) -> datetime:
        """:attr:`start_time` as a datetime (naive when no UTC offset was recorded)."""
        return datetime.fromisoformat(self.start_time)


@dataclass(frozen=True, eq=False)
class Episode:
    """One episode: time-aligned arrays at a fixed sample rate plus metadata.

    Row ``k`` of every array belongs to tick ``k``. ``controller_state[k]``
    is the state the controller held when it computed ``control_output[k]``
    (before that tick's update), so
    ``control_output = C x + D (target - measured)`` row by row.

    Parameters
    ----------
    t : array_like of shape (n,)
        Time since the episode start, s.
    theta, alpha : array_like of shape (n,)
        Measured motor and pendulum angles, rad (alpha = 0 upright).
    target_theta, target_alpha : array_like of shape (n,)
        References, rad.
    feedforward : array_like of shape (n,)
        Feedforward voltage added to the controller output, V.
    controller_state : array_like of shape (n, n_controller_states)
        Controller state, in the realization of ``metadata.controller``.
    control_output : array_like of shape (n,)
        Controller output before saturation, V.
    plant_input : array_like of shape (n,)
        Voltage applied: clip(control_output + feedforward), V.
    saturation : array_like of shape (n,)
        -1, 0 or +1: plant_input was clipped at the lower/upper limit.
    metadata : EpisodeMetadata
        Controller, sample rate, excitation, provenance, status.
    lateness, compute_time : array_like of shape (n,), optional
        Per-tick timing, s; NaN where not measured (imported data).
    device_time : array_like of shape (n,), optional
        The device's own clock at each sample, s since its first telemetry of
        the session; NaN where the backend has no device clock (the simulator,
        imported data, logs older than format 1.3). A gap between consecutive
        values larger than ``dt`` shows periods the device lost.
    controller_record : array_like of shape (n, len(metadata.controller.tick_fields)), optional
        The controller's per-tick record (a controller beyond LTI: the MPC's solver status,
        iterations, solve time, ...), one column per ``metadata.controller.tick_fields``;
        empty (n x 0) for an LTI controller.

    Raises
    ------
    ValueError
        If the arrays disagree in length, the controller state has the wrong
        number of columns, or saturation holds a value other than -1, 0, 1.
    """

    t: np.ndarray
    theta: np.ndarray
    alpha: np.ndarray
    target_theta: np.ndarray
    target_alpha: np.ndarray
    feedforward: np.ndarray
    controller_state: np.ndarray
    control_output: np.ndarray
    plant_input: np.ndarray
    saturation: np.ndarray
    metadata: EpisodeMetadata
    lateness: np.ndarray | None = None
    compute_time: np.ndarray | None = None
    device_time: np.ndarray | None = None
    controller_record: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = np.shape(self.t)[0] if np.ndim(self.t) == 1 else None
        if n is None:
            raise ValueError(f"t must be 1-D, got shape {np.shape(self.t)}")
        for name in SIGNALS:
            value = getattr(self, name)
            value = np.full(n, np.nan) if value is None and name in _TIMING else value
            self._store(name, np.asarray(value, dtype=np.float64), (n,))
        k = self.metadata.controller.system.n_states
        state = np.asarray(self.controller_state, dtype=np.float64)
        self._store("controller_state", state.reshape(0, k) if n == 0 and state.size == 0 else state, (n, k))
        n_tick = len(self.metadata.controller.tick_fields)
        record = np.empty((n, 0)) if self.controller_record is None else np.asarray(self.controller_record, float)
        self._store(
            "controller_record", record.reshape(0, n_tick) if n == 0 and record.size == 0 else record, (n, n_tick)
        )
        sat = np.asarray(self.saturation)
        if sat.shape == (n,) and not np.isin(sat, (-1, 0, 1)).all():
            raise ValueError("saturation must hold only -1, 0 and +1")
        self._store("saturation", sat.astype(np.int8), (n,))

    def _store(self, name: str, value: np.ndarray, shape: tuple[int, ...]) -> None:
        if value.shape != shape:
            raise ValueError(f"{name} must have shape {shape}, got {value.shape}")
        # Own a read-only copy: the episode must not change under us, nor
        # may it freeze the caller's arrays.
        value = value.copy()
        value.setflags(write=False)
        object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return self.t.shape[0]

    @property
    def n_samples(self) -> int:
        """Number of samples."""
        return len(self)

    @property
    def dt(self) -> float:
        """Sample period in seconds."""
        return self.metadata.dt

    @property
    def controller(self) -> DiscreteStateSpace:
        """The controller as a discrete state-space system (A^c, B^c, C^c, D^c, dt)."""
        return self.metadata.controller.system

    @property
    def states(self) -> np.ndarray:
        """Measured plant states, shape (n, 2): columns theta, alpha."""
        return stack_signals(self, STATE_SIGNALS)

    @property
    def references(self) -> np.ndarray:
        """References, shape (n, 2): columns target_theta, target_alpha."""
        return stack_signals(self, REFERENCE_SIGNALS)

    @property
    def tracking_error(self) -> np.ndarray:
        """Controller input ``references - states``, shape (n, 2)."""
        return self.references - self.states

    @property
    def is_complete(self) -> bool:
        """True when the episode finished normally and was read whole."""
        return self.metadata.status == "complete" and not self.metadata.salvaged

    def arrays(self) -> dict[str, np.ndarray]:
        """All per-sample arrays by name (read-only views)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "metadata"}
