"""The legacy rig's CSV episodes (the paper's dataset): parsing, validation, conversion.

A legacy file is named ``qube_<YYYYMMDD>T<HHMMSS>_<theta seed>_<alpha seed>_<ff seed>.csv``
and holds a header line and one row per 500 Hz tick with the columns of
:data:`LEGACY_COLUMNS`. It does not hold the controller state; the import
recomputes it by running the controller of the ``controller.toml`` beside
the files on the tracking error from zero state at t = 0 (as the rig did),
and refuses the file unless that controller reproduces the logged
``control_output`` (:func:`controller_state_from_log`). Every problem is
raised as :class:`LegacyCsvError`, whose message starts with the file.

The rig ended every line, the last one too, with a newline: a file whose last
line has none was cut short (a copy or a write that stopped). That line is
dropped (a number cut short still parses, to a wrong value), the rest is read,
and the episode is marked incomplete, its reason saying so.

The layout has no place for an episode's status: ``qube-export`` writes the
status of an episode that did not complete beside its CSV, in
``<name>.status.json`` (:data:`STATUS_SIDECAR_SUFFIX`), and the import gives
the episode that status back.
"""

from __future__ import annotations

import hashlib
import io
import warnings
from datetime import datetime, timedelta
from pathlib import Path
from typing import TypedDict

import numpy as np

from qube_koopman.daq.episode import REFERENCE_SIGNALS, STATE_SIGNALS, Episode, EpisodeMetadata, stack_signals
from qube_koopman.core.controller_file import ControllerInfo
from qube_koopman.core.files import loads_json, read_bounded_bytes, read_bounded_text
from qube_koopman.daq.log.names import parse_episode_name
from qube_koopman.core.lti import replay_controller

__all__ = [
    "LEGACY_COLUMNS",
    "LEGACY_SAMPLE_RATE_HZ",
    "CONTROL_TOLERANCE_V",
    "CONTROL_CHECK_AFTER_S",
    "LegacyCsvError",
    "parse_legacy_name",
    "read_legacy_csv",
    "controller_state_from_log",
    "legacy_excitation",
    "load_legacy_controller",
    "legacy_episode",
    "STATUS_SIDECAR_SUFFIX",
    "status_sidecar",
]

LEGACY_COLUMNS = (
    "t",
    "target_theta",
    "target_alpha",
    "theta",
    "alpha",
    "control_output",
    "feedforward",
    "plant_input",
    "saturation",
)
LEGACY_SAMPLE_RATE_HZ = 500.0
#: The largest CSV log (or status file beside it) read whole: an hour at 500 Hz is about 300 MB.
_MAX_CSV_BYTES = 2**31
#: The recomputed controller output must match the logged one this closely...
CONTROL_TOLERANCE_V = 1e-9
#: ...from this time on (the first second is the hand-raising transient).
CONTROL_CHECK_AFTER_S = 1.0

_TIME_TOLERANCE_S = 1e-9

#: Beside ``<name>.csv``, ``<name>.status.json``: the status of an episode that did not complete
#: (keys ``status``, ``reason``, ``salvaged``, ``salvage_note``, ``samples``), which the CSV cannot hold.
STATUS_SIDECAR_SUFFIX = ".status.json"


def status_sidecar(csv_path: str | Path) -> Path:
    """The status file beside a legacy CSV file (:data:`STATUS_SIDECAR_SUFFIX`)."""
    return Path(csv_path).with_suffix(STATUS_SIDECAR_SUFFIX)


class _Status(TypedDict, total=False):
    """EpisodeMetadata's status fields (none: a complete episode)."""

    status: str
    status_reason: str


def _sidecar_status(path: Path) -> _Status:
    """The status an export recorded beside ``path`` as EpisodeMetadata fields; {} when there is none."""
    sidecar = status_sidecar(path)
    if not sidecar.is_file():
        return {}
    try:
        info = loads_json(read_bounded_text(sidecar, _MAX_CSV_BYTES, "status file"), sidecar)
        status = info["status"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise LegacyCsvError(f"{path}: its status file {sidecar.name} is unreadable ({exc})") from None
    reason = "; ".join(str(text) for text in (info.get("reason"), info.get("salvage_note")) if text)
    if status == "complete" and not info.get("salvaged"):
        return {}
    return {
        "status": status if status == "aborted" else "incomplete",
        "status_reason": reason or f"exported from a log whose status was {status}",
    }


class LegacyCsvError(ValueError):
    """A legacy CSV file that cannot be imported; the message names the file and the problem."""


def parse_legacy_name(path: str | Path) -> tuple[str, dict[str, int]]:
    """Start time and excitation seeds from a legacy file name.

    Returns
    -------
    start_time : str
        ISO 8601, without UTC offset (the rig recorded its local time).
    seeds : dict
        PRBS seeds of ``target_theta``, ``target_alpha`` and ``feedforward``.

    Raises
    ------
    LegacyCsvError
        If the name does not follow the pattern or holds an invalid date.
    """
    path = Path(path)
    name = parse_episode_name(path, ".csv")
    if name is None:
        raise LegacyCsvError(
            f"{path}: file name does not follow qube_<YYYYMMDD>T<HHMMSS>_<theta seed>_"
            f"<alpha seed>_<feedforward seed>.csv (it gives the start time and seeds)"
        )
    try:
        start = datetime.strptime(name.stamp, "%Y%m%dT%H%M%S")
    except ValueError:
        raise LegacyCsvError(f"{path}: file name holds an invalid date and time {name.stamp!r}") from None
    if name.milliseconds is not None:
        start += timedelta(milliseconds=name.milliseconds)
    return start.isoformat(), name.seeds


def _diagnose(path: Path, text: str, names: list[str]) -> str:
    """The first malformed row, for a file numpy's fast parser refused."""
    for lineno, line in enumerate(text.splitlines()[1:], start=2):
        if not line.strip():
            continue
        fields = line.split(",")
        if len(fields) != len(names):
            kind = "short" if len(fields) < len(names) else "long"
            return f"line {lineno}: {kind} row: {len(fields)} fields, the header has {len(names)}"
        for name, field in zip(names, fields):
            try:
                float(field)
            except ValueError:
                return f"line {lineno}: column {name}: {field.strip()!r} is not a number"
    return "cannot be parsed as comma-separated numbers"


def _line_of(text: str, row: int) -> int:
    """File line number (1-based) of data row ``row`` (0-based); blank lines do not count as rows."""
    seen = -1
    for lineno, line in enumerate(text.splitlines()[1:], start=2):
        if line.strip():
            seen += 1
            if seen == row:
                return lineno
    return -1


def _shorten(text: str, limit: int = 120) -> str:
    """``text`` cut to ``limit`` characters, marked when cut (for one-line messages)."""
    return text if len(text) <= limit else text[:limit] + "..."


def read_legacy_csv(path: str | Path) -> tuple[dict[str, np.ndarray], bytes]:
    """Parse and validate a legacy CSV file.

    A last line cut short (no newline after it) is dropped with a :class:`UserWarning`
    naming the file (see the module's docstring).

    Parameters
    ----------
    path : str or Path
        A CSV file of the dataset.

    Returns
    -------
    columns : dict of str to ndarray
        One float array per column of :data:`LEGACY_COLUMNS`.
    raw : bytes
        The file's bytes (for a provenance hash).

    Raises
    ------
    LegacyCsvError
        Naming the file and the problem: unreadable, missing or duplicated
        columns, a short or long row, a non-number or non-finite value, no
        rows, time not evenly spaced at 500 Hz from 0, saturation other
        than -1, 0, +1.
    """
    columns, raw, cut = _read(Path(path))
    if cut:
        warnings.warn(f"{path}: {cut}", UserWarning, stacklevel=2)
    return columns, raw


def _drop_cut_line(raw: bytes) -> tuple[bytes, str]:
    """The file's whole lines, and what was dropped ("" for a file ending in a newline, as the rig's did)."""
    if raw.endswith(b"\n") or b"\n" not in raw:  # no newline at all: a header alone, refused later
        return raw, ""
    whole = raw[: raw.rindex(b"\n") + 1]
    line = whole.count(b"\n") + 1
    return whole, f"cut short: its last line (line {line}) ends without a newline and was dropped"


def _read(path: Path) -> tuple[dict[str, np.ndarray], bytes, str]:
    """:func:`read_legacy_csv`, and what was dropped from a file cut short ("" when nothing)."""
    try:
        raw = read_bounded_bytes(path, _MAX_CSV_BYTES, "CSV log")
    except OSError as exc:
        raise LegacyCsvError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except ValueError as exc:  # a FIFO, a device or too large: the message names the file
        raise LegacyCsvError(str(exc)) from None
    if b"\0" in raw[:4096]:
        raise LegacyCsvError(f"{path}: not a CSV file (binary content: NUL bytes near its start)")
    text = raw.decode("utf-8", errors="replace")
    header = text.split("\n", 1)[0].strip()
    if not header:
        raise LegacyCsvError(f"{path}: empty file (no header line)")
    names = [name.strip() for name in header.split(",")]
    missing = [c for c in LEGACY_COLUMNS if c not in names]
    if missing:
        raise LegacyCsvError(
            f"{path}: missing column{'s' if len(missing) > 1 else ''} "
            f"{', '.join(missing)} (header: {_shorten(header)!r})"
        )
    duplicated = sorted({n for n in names if names.count(n) > 1})
    if duplicated:
        raise LegacyCsvError(f"{path}: duplicated column {', '.join(duplicated)}")
    whole, cut = _drop_cut_line(raw)
    text = whole.decode("utf-8", errors="replace")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "input contained no data": handled below
            data = np.loadtxt(io.BytesIO(whole), delimiter=",", skiprows=1, ndmin=2, dtype=np.float64)
    except ValueError:
        raise LegacyCsvError(f"{path}: {_diagnose(path, text, names)}") from None
    if data.shape[0] == 0:
        raise LegacyCsvError(f"{path}: no data rows")
    if data.shape[1] != len(names):
        raise LegacyCsvError(f"{path}: {_diagnose(path, text, names)}")
    bad = ~np.isfinite(data)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise LegacyCsvError(
            f"{path}: line {_line_of(text, row)}: column {names[col]}: non-finite value {float(data[row, col])}"
        )
    columns = {name: data[:, names.index(name)].copy() for name in LEGACY_COLUMNS}
    t = columns["t"]
    expected = np.arange(len(t)) / LEGACY_SAMPLE_RATE_HZ
    off = np.abs(t - expected)
    if off.max() > _TIME_TOLERANCE_S:
        k = int(np.argmax(off > _TIME_TOLERANCE_S))
        raise LegacyCsvError(
            f"{path}: t is not evenly spaced at {LEGACY_SAMPLE_RATE_HZ:g} Hz from 0 "
            f"(line {_line_of(text, k)}: t = {float(t[k])!r}, expected {float(expected[k])!r})"
        )
    if not np.isin(columns["saturation"], (-1.0, 0.0, 1.0)).all():
        k = int(np.argmax(~np.isin(columns["saturation"], (-1.0, 0.0, 1.0))))
        raise LegacyCsvError(
            f"{path}: line {_line_of(text, k)}: saturation {float(columns['saturation'][k])!r} is not -1, 0 or +1"
        )
    return columns, raw, cut


def controller_state_from_log(
    columns: dict[str, np.ndarray],
    controller: ControllerInfo,
    where: str,
    *,
    tolerance: float = CONTROL_TOLERANCE_V,
    after_s: float = CONTROL_CHECK_AFTER_S,
) -> np.ndarray:
    """Recompute the controller state and check it reproduces the logged output.

    The controller runs from zero state at t = 0 on the tracking error
    ``target - measured``, as on the rig.

    Returns
    -------
    ndarray of shape (n, n_controller_states)
        State before each tick's update.

    Raises
    ------
    LegacyCsvError
        If the recomputed output differs from ``control_output`` by more
        than ``tolerance`` volts at some t >= ``after_s``, or the file ends
        before ``after_s``.
    """
    state, output = replay_controller(
        controller.system, stack_signals(columns, REFERENCE_SIGNALS), stack_signals(columns, STATE_SIGNALS)
    )
    checked = columns["t"] >= after_s - _TIME_TOLERANCE_S
    if not checked.any():
        raise LegacyCsvError(f"{where}: ends before t = {after_s:g} s, too short to check the controller")
    mismatch = np.abs(output[:, 0] - columns["control_output"]) * checked
    worst = int(np.argmax(mismatch))
    if mismatch[worst] > tolerance:
        raise LegacyCsvError(
            f"{where}: the {controller.method} {controller.kind} controller (gains "
            f"{', '.join(f'{k} {v:g}' for k, v in controller.gains.items())}) does not reproduce "
            f"control_output: off by {mismatch[worst]:.3g} V at t = {columns['t'][worst]:.3f} s "
            f"(tolerance {tolerance:g} V after {after_s:g} s); wrong controller.toml?"
        )
    return state


def legacy_excitation(seeds: dict[str, int]) -> dict:
    """Excitation seeds and settings of the legacy rig: the generator of the C program that ran it
    (:mod:`qube_koopman.daq.excitation` reproduces it), seeded with the numbers in the file name."""
    return {
        "generator": "PRBS, 16-bit Fibonacci LFSR, taps 16 14 13 11, bits held for the bit period",
        "seeds": dict(seeds),
        "target_theta": {
            "signal": "rate PRBS integrated by forward Euler",
            "amplitude_rad_s": 0.25,
            "bit_period_s": 0.25,
        },
        "target_alpha": {"signal": "PRBS", "amplitude_rad": 0.01, "bit_period_s": 0.1},
        "feedforward": {"signal": "PRBS", "amplitude_V": 0.5, "bit_period_s": 0.1},
        "active_samples": [2000, 8000],
        "smoothing": {"filter": "backward-Euler low-pass c / (s + c)", "c_rad_s": 200.0},
        "settings_source": "the rig's C program (decargroup/quanser_qube); the CSV holds only the seeds, "
        "in its file name",
    }


def load_legacy_controller(path: str | Path, method: str = "backward-euler") -> ControllerInfo:
    """The rig's PD controller from a controller.toml (backward Euler, as the rig ran it).

    Parameters
    ----------
    path : str or Path
        The dataset's controller.toml.
    method : str
        The discretization (``"backward-euler"``, ``"zoh"``, ``"tustin"``).

    Returns
    -------
    ControllerInfo

    Raises
    ------
    ValueError
        Naming the file, if it cannot be read or misses a gain.
    """
    from qube_koopman.core.controller import load_pd_gains, pd_controller  # python-control: imported lazily

    gains = load_pd_gains(path)
    system = pd_controller(gains, 1.0 / LEGACY_SAMPLE_RATE_HZ, method)
    return ControllerInfo(system, method, gains.as_dict(), kind="pd")


def legacy_episode(path: str | Path, controller: ControllerInfo) -> Episode:
    """Read, validate and convert one legacy CSV file into an :class:`Episode`.

    Parameters
    ----------
    path : str or Path
        The CSV file.
    controller : ControllerInfo
        The controller that ran it (:func:`load_legacy_controller`).

    Returns
    -------
    Episode
        Complete, or, for a file cut short, ``"incomplete"`` with the reason (the rows
        before the cut line; see the module's docstring).

    Raises
    ------
    LegacyCsvError
        Naming the file and the problem (see :func:`read_legacy_csv`,
        :func:`controller_state_from_log`, :func:`parse_legacy_name`).
    """
    path = Path(path)
    start_time, seeds = parse_legacy_name(path)
    columns, raw, cut = _read(path)
    state = controller_state_from_log(columns, controller, str(path))
    status: _Status = {"status": "incomplete", "status_reason": f"legacy CSV {cut}"} if cut else _sidecar_status(path)
    metadata = EpisodeMetadata(
        controller=controller,
        sample_rate_hz=LEGACY_SAMPLE_RATE_HZ,
        backend="legacy-rig",
        source=f"legacy CSV {path.name}",
        start_time=start_time,
        excitation=legacy_excitation(seeds),
        extra={
            "source_sha256": hashlib.sha256(raw).hexdigest(),
            "importer": "qube_koopman.daq.legacy_csv",
            "plant_input_limit_V": 10.0,
        },
        **status,
    )
    return Episode(
        t=columns["t"],
        theta=columns["theta"],
        alpha=columns["alpha"],
        target_theta=columns["target_theta"],
        target_alpha=columns["target_alpha"],
        feedforward=columns["feedforward"],
        controller_state=state,
        control_output=columns["control_output"],
        plant_input=columns["plant_input"],
        saturation=columns["saturation"],
        metadata=metadata,
    )
