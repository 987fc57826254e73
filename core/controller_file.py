"""Controller files: PD gains or a discrete state-space controller, read into one :class:`ControllerInfo`.

A controller file is TOML, of one of two kinds (core/CONTROLLER_FORMAT.md):

- a PD gains file (no ``kind`` key): ``kp_theta``, ``kd_theta``, ``kp_alpha``, ``kd_alpha``,
  ``tau``, discretized here like the rig's (:func:`core.controller.pd_controller`);
- a state-space file (``format = "qube-controller/1"``, ``kind = "state-space"``): the matrices
  A, B, C, D of a discrete controller at the loop's sample period, inline or in a sibling
  ``.npz``, e.g. written by a controller design from an identified model.

Both give the :class:`~daq.episode.ControllerInfo` the loop runs and the log records. Every
problem is one ``ValueError`` naming the file and what is wrong with it.

Further kinds (a controller beyond LTI, such as ``qube-design --mpc``'s model predictive
controller) are registered by the package that builds them, which this layer does not import:
through a Python entry point of the group :data:`CONTROLLER_KINDS_GROUP` (name: the kind,
value: a builder), or at run time by :func:`register_controller_kind`. A builder takes the
file's table, its path and the loop's sample period and returns the :class:`ControllerInfo`,
whose ``runtime`` the loop then runs (see :class:`ControllerInfo`).
"""

from __future__ import annotations

import json
import math
import zipfile
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
from qube_koopman.core.files import atomic_path, npz_shapes

from qube_koopman.core.controller import (
    MAX_CONTROLLER_BYTES,
    QUBE_SAMPLE_PERIOD,
    controller_file,
    pd_controller,
    pd_gains_from_table,
    read_controller_toml,
)
from qube_koopman.core.lti import DiscreteStateSpace

__all__ = [
    "CONTROLLER_FORMAT",
    "CONTROLLER_KINDS_GROUP",
    "STATE_SPACE_KIND",
    "register_controller_kind",
    "registered_controller_kinds",
    "FEEDFORWARD_INPUTS",
    "STATE_SPACE_METHOD",
    "TRACKING_INPUTS",
    "load_controller",
    "default_controller_path",
    "ControllerInfo",
    "plain_json",
    "toml_value",
    "write_controller_file",
]

#: The ``format`` of a state-space controller file this reader reads.
CONTROLLER_FORMAT = "qube-controller/1"
#: The ``kind`` of a state-space controller file (and of its :class:`ControllerInfo`).
STATE_SPACE_KIND = "state-space"
#: The ``method`` a state-space controller is recorded with: given in discrete time, not discretized.
STATE_SPACE_METHOD = "given"
#: The controller's inputs, in column order of B and D: the tracking errors ``r - y``.
TRACKING_INPUTS = ("e_theta", "e_alpha")
#: The inputs of a controller that also sees the feedforward (which the loop adds to its output
#: all the same): the tracking errors, then the feedforward.
FEEDFORWARD_INPUTS = TRACKING_INPUTS + ("feedforward",)

#: The entry-point group through which a package registers a controller file's kind.
CONTROLLER_KINDS_GROUP = "qube_koopman.controller_kinds"

#: Builders registered at run time (:func:`register_controller_kind`), by kind.
_BUILDERS: dict[str, Callable[[dict, Path, float], "ControllerInfo"]] = {}

_REQUIRED = ("format", "kind", "dt", "inputs")
_MATRICES = ("A", "B", "C", "D")
_KNOWN = frozenset(_REQUIRED + _MATRICES + ("matrices", "provenance"))


def load_controller(
    path: str | Path | None = None, method: str = "backward-euler", dt: float = QUBE_SAMPLE_PERIOD
) -> ControllerInfo:
    """The controller of a controller file of either kind, as the loop runs it.

    Parameters
    ----------
    path : str or Path, optional
        A controller file, or a shipped name (``"rig"``, ``"soft-theta"``; see
        :func:`core.controller.controller_file`); the rig's PD gains when None.
    method : {"backward-euler", "zoh", "tustin"}
        Discretization of a PD gains file's derivative filters; a state-space file is
        already discrete (recorded with method ``"given"``).
    dt : float
        The loop's sample period (s): a PD controller is discretized at it, a state-space
        file must be written at it.

    Returns
    -------
    ControllerInfo
        kind ``"pd"`` with its gains, or ``"state-space"`` with the file's provenance.

    Raises
    ------
    ValueError
        Naming the file and the problem: unreadable, not TOML, a missing or unknown key, an
        unknown kind or format, a matrix of the wrong shape or with non-finite entries, a
        sample period other than ``dt``.
    """
    path = controller_file("rig" if path is None else path)
    data = read_controller_toml(path)
    if "kind" not in data and "format" not in data:
        gains = pd_gains_from_table(data, path)
        return ControllerInfo(pd_controller(gains, dt, method), method, gains.as_dict(), "pd")
    kind = data.get("kind")
    if kind != STATE_SPACE_KIND:
        if kind is None:
            raise ValueError(f'{path}: missing key kind (a state-space file has kind = "{STATE_SPACE_KIND}")')
        builder = _builder(kind) if isinstance(kind, str) else None
        if builder is None:
            others = "".join(f', "{k}"' for k in registered_controller_kinds())
            raise ValueError(
                f'{path}: unknown controller kind {kind!r}; expected "{STATE_SPACE_KIND}"{others} (a PD '
                "gains file has no kind, only kp_theta, kd_theta, kp_alpha, kd_alpha, tau)"
            )
        if data.get("format") != CONTROLLER_FORMAT:
            raise ValueError(
                f'{path}: format {data.get("format")!r} is not supported (this reader reads "{CONTROLLER_FORMAT}")'
            )
        _check_period(data.get("dt"), path, dt)
        return builder(data, path, dt)
    return _state_space(data, path, dt)


def register_controller_kind(kind: str, builder: Callable[[dict, Path, float], "ControllerInfo"]) -> None:
    """Register the builder of a controller file's ``kind`` (beside the entry points of :data:`CONTROLLER_KINDS_GROUP`).

    Parameters
    ----------
    kind : str
        The file's ``kind``.
    builder : callable
        ``builder(table, path, dt) -> ControllerInfo``; every problem a ``ValueError`` naming ``path``.
    """
    if kind == STATE_SPACE_KIND or kind == "pd":
        raise ValueError(f"controller kind {kind!r} is built in")
    _BUILDERS[kind] = builder


def registered_controller_kinds() -> tuple[str, ...]:
    """The kinds registered beyond the built-in ones (entry points and :func:`register_controller_kind`), sorted."""
    return tuple(sorted(set(_BUILDERS) | {ep.name for ep in entry_points(group=CONTROLLER_KINDS_GROUP)}))


def _builder(kind: str):
    if kind in _BUILDERS:
        return _BUILDERS[kind]
    for ep in entry_points(group=CONTROLLER_KINDS_GROUP):
        if ep.name == kind:
            return ep.load()
    return None


def _state_space(data: dict, path: Path, dt: float) -> ControllerInfo:
    """A state-space file's controller, every key checked."""
    missing = [k for k in _REQUIRED if k not in data]
    if "matrices" not in data:
        missing += [m for m in _MATRICES if m not in data]
    if missing:
        raise ValueError(f"{path}: missing key{'s' if len(missing) > 1 else ''} {', '.join(missing)}")
    unknown = sorted(set(data) - _KNOWN)
    if unknown:
        raise ValueError(
            f"{path}: unknown keys {', '.join(unknown)} (a state-space file has {', '.join(sorted(_KNOWN))})"
        )
    if data["format"] != CONTROLLER_FORMAT:
        raise ValueError(
            f'{path}: format {data["format"]!r} is not supported (this reader reads "{CONTROLLER_FORMAT}")'
        )
    _check_period(data["dt"], path, dt)
    inputs = _check_inputs(data["inputs"], path)
    A, B, C, D = _matrices(data, path)
    _check_shapes(A, B, C, D, inputs, path)
    provenance = data.get("provenance", {})
    if not isinstance(provenance, dict):
        raise ValueError(f"{path}: provenance must be a table ([provenance]), got {type(provenance).__name__}")
    try:
        return ControllerInfo(
            DiscreteStateSpace(A, B, C, D, float(data["dt"])),
            STATE_SPACE_METHOD,
            {},
            STATE_SPACE_KIND,
            json.loads(json.dumps(provenance, default=str)),
        )
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def _check_period(value: Any, path: Path, dt: float) -> None:
    if not _is_number(value) or not (math.isfinite(value) and value > 0):
        raise ValueError(f"{path}: dt must be a positive number of seconds, got {value!r}")
    if abs(value - dt) > 1e-9 * dt:
        raise ValueError(
            f"{path}: dt {value!r} s differs from the sample period {dt!r} s of the loop and its logs (a "
            "discrete controller runs only at the period it was designed for)"
        )


def _check_inputs(value: Any, path: Path) -> tuple[str, ...]:
    inputs = tuple(value) if isinstance(value, list) else value
    if inputs in (TRACKING_INPUTS, FEEDFORWARD_INPUTS):
        return inputs
    raise ValueError(
        f"{path}: inputs must be {json.dumps(list(TRACKING_INPUTS))} (the tracking errors r - y "
        f"of theta and alpha, the columns of B and D) or {json.dumps(list(FEEDFORWARD_INPUTS))} "
        f"(the feedforward too), got {value!r}"
    )


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _matrices(data: dict, path: Path) -> list[np.ndarray]:
    """A, B, C, D: inline lists of rows, or the arrays of the ``matrices`` .npz beside the file."""
    if "matrices" not in data:
        return [_inline_matrix(data[m], m, path) for m in _MATRICES]
    inline = [m for m in _MATRICES if m in data]
    if inline:
        raise ValueError(
            f"{path}: {', '.join(inline)} given both inline and in matrices = "
            f"{data['matrices']!r}: give each matrix once"
        )
    if not isinstance(data["matrices"], str):
        raise ValueError(f"{path}: matrices must be the name of an .npz file, got {data['matrices']!r}")
    npz = path.parent / data["matrices"]
    try:  # the file and the size of each array it declares, before loading any
        npz_shapes(npz, MAX_CONTROLLER_BYTES, "controller's matrices file")
    except OSError as exc:
        raise ValueError(f"{path}: cannot read {npz} ({exc.strerror or exc}) (matrices)") from None
    except ValueError as exc:
        raise ValueError(f"{path}: {exc} (matrices)") from None
    try:
        with np.load(npz, allow_pickle=False) as arrays:
            loaded = {m: arrays[m] for m in _MATRICES if m in arrays.files}
    except OSError as exc:
        raise ValueError(f"{path}: cannot read {npz} ({exc.strerror or exc}) (matrices)") from None
    except (ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{path}: {npz} is not a numpy .npz of numbers ({exc}) (matrices)") from None
    absent = [m for m in _MATRICES if m not in loaded]
    if absent:
        raise ValueError(f"{path}: {npz} holds no array {', '.join(absent)} (matrices)")
    return [_numeric(loaded[m], m, path) for m in _MATRICES]


def _inline_matrix(value: Any, name: str, path: Path) -> np.ndarray:
    """A TOML list of rows of numbers as a float matrix."""
    if (
        not isinstance(value, list)
        or not value
        or not all(isinstance(row, list) for row in value)
        or not all(_is_number(v) for row in value for v in row)
    ):
        raise ValueError(
            f"{path}: {name} must be a matrix: a non-empty list of rows of numbers, "
            f"e.g. {name} = [[1.0, 0.0], [0.0, 1.0]]"
        )
    lengths = sorted({len(row) for row in value})
    if len(lengths) > 1:
        raise ValueError(f"{path}: {name} has rows of different lengths ({', '.join(map(str, lengths))})")
    return _numeric(np.array(value, dtype=float).reshape(len(value), lengths[0]), name, path)


def _numeric(value: np.ndarray, name: str, path: Path) -> np.ndarray:
    """A finite 2-D float matrix, or a ValueError naming the first bad entry."""
    if value.ndim != 2 or value.dtype.kind not in "fiu":
        raise ValueError(f"{path}: {name} must be a 2-D matrix of numbers, got {value.ndim}-D {value.dtype}")
    value = value.astype(float)
    bad = np.argwhere(~np.isfinite(value))
    if len(bad):
        i, j = bad[0]
        raise ValueError(
            f"{path}: {name} has {len(bad)} non-finite entr{'y' if len(bad) == 1 else 'ies'} "
            f"(first: row {i}, column {j}: {value[i, j]})"
        )
    return value


def _check_shapes(
    A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray, inputs: tuple[str, ...], path: Path
) -> None:
    """A n x n, B n x p, C 1 x n, D 1 x p, with n = the rows of A and p = the inputs."""
    n, p = A.shape[0], len(inputs)
    expected = {"A": (n, n), "B": (n, p), "C": (1, n), "D": (1, p)}
    for name, value in zip(_MATRICES, (A, B, C, D)):
        if value.shape != expected[name]:
            rows, cols = expected[name]
            raise ValueError(
                f"{path}: {name} has shape {value.shape[0]} x {value.shape[1]}, expected "
                f"{rows} x {cols} (A has {n} rows: {n} states; {p} inputs "
                f"{', '.join(inputs)}; 1 output, the voltage)"
            )


def write_controller_file(
    path: str | Path, system: DiscreteStateSpace, provenance: Mapping[str, Any] | None = None, *, npz: bool = False
) -> Path:
    """Write a state-space controller file that :func:`load_controller` reads back exactly.

    Parameters
    ----------
    path : str or Path
        The TOML file to write.
    system : DiscreteStateSpace
        The controller: two tracking errors in (and the feedforward as a third input, if it
        takes it), one voltage out.
    provenance : mapping, optional
        Free-form ``[provenance]`` table (strings, numbers, booleans, lists, tables).
    npz : bool, default False
        Put the matrices in ``<path stem>.npz`` beside the file (``matrices = ...``) instead of
        inline: a 200-state file then loads in milliseconds instead of about 0.3 s.

    Returns
    -------
    Path
        The TOML file written.
    """
    path = Path(path)
    if system.n_inputs not in (len(TRACKING_INPUTS), len(FEEDFORWARD_INPUTS)) or system.n_outputs != 1:
        raise ValueError(
            f"a controller file holds 2 inputs (3 with the feedforward) and 1 output, got "
            f"{system.n_inputs} and {system.n_outputs}"
        )
    inputs = TRACKING_INPUTS if system.n_inputs == len(TRACKING_INPUTS) else FEEDFORWARD_INPUTS
    lines = [
        f"# A discrete state-space controller of qube-koopman (core/CONTROLLER_FORMAT.md): {system.n_states} states",
        f'format = "{CONTROLLER_FORMAT}"',
        f'kind = "{STATE_SPACE_KIND}"',
        f"dt = {system.dt!r}",
        f"inputs = {json.dumps(list(inputs))}",
    ]
    if npz:
        target = path.with_suffix(".npz")
        with atomic_path(target) as tmp:
            np.savez(tmp, **{m: getattr(system, m) for m in _MATRICES})
        lines.append(f"matrices = {json.dumps(target.name)}")
    else:
        for m in _MATRICES:
            rows = ",\n".join("  [" + ", ".join(repr(v) for v in row) + "]" for row in getattr(system, m).tolist())
            lines.append(f"{m} = [\n{rows},\n]")
    if provenance:
        lines += ["", "[provenance]"] + [f"{_toml_key(k)} = {toml_value(v)}" for k, v in provenance.items()]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return path


def _toml_key(key: str) -> str:
    key = str(key)
    return key if key and all(c.isascii() and (c.isalnum() or c in "_-") for c in key) else json.dumps(key)


def toml_value(value: Any) -> str:
    """A TOML value for plain data (JSON's string escapes are TOML's basic-string escapes).

    Floats are written with ``repr``, so they read back bit for bit.

    Parameters
    ----------
    value : str, int, float, bool, mapping or sequence of them

    Returns
    -------
    str
    """
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, Mapping):
        return "{" + ", ".join(f"{_toml_key(k)} = {toml_value(v)}" for k, v in value.items()) + "}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    raise ValueError(f"provenance value {value!r} is not plain data (str, number, bool, list, table)")


def plain_json(value: Mapping[str, Any], name: str) -> dict[str, Any]:
    """``value`` as plain JSON data (a dict), or a ValueError naming ``name``."""
    # Round-trip through JSON now so a value the log cannot store fails here,
    # where the caller can see which field, not later in the writer thread.
    # (A plain dict, not a read-only proxy, so that episodes can be pickled.)
    try:
        return json.loads(json.dumps(dict(value), allow_nan=False))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be JSON-serializable plain data: {exc}") from None


@dataclass(frozen=True)
class ControllerInfo:
    """The controller that ran the episode.

    Parameters
    ----------
    system : DiscreteStateSpace
        Discrete controller (A^c, B^c, C^c, D^c, dt); inputs are the tracking
        errors ``target_theta - theta`` and ``target_alpha - alpha``.
    method : str
        Discretization it was built with (e.g. ``"backward-euler"``).
    gains : mapping of str to float
        The gains it was built from (e.g. :meth:`core.controller.PdGains.as_dict`).
    kind : str
        Controller family: ``"pd"`` (built from gains) or ``"state-space"`` (matrices given
        in discrete time, core/CONTROLLER_FORMAT.md).
    provenance : mapping
        Free-form JSON-serializable record of where the controller comes from (for a
        state-space file: its ``[provenance]`` table, e.g. what designed it); empty for gains.
    settings : mapping
        A registered kind's run-time settings (plain data, recorded in the log); empty for the
        built-in kinds.
    tick_fields : tuple of str
        Names of the per-tick record the controller gives (``runtime.tick_record``), which the
        log keeps as sample fields; empty for an LTI controller.
    runtime : object, optional
        A controller beyond LTI: ``runtime.step()`` gives a fresh ``(output, update)`` pair per
        episode, ``output(e_theta, e_alpha, feedforward, target_theta) -> (u, state)`` and
        ``update(e_theta, e_alpha, feedforward)``, and after each ``output``
        ``runtime.tick_record`` holds that tick's values of ``tick_fields``. Its ``state`` has
        ``system``'s size: ``system`` is then the LTI controller that gives the same state (and,
        for the MPC, the output without active constraints). None: the loop runs ``system``.
    """

    system: DiscreteStateSpace
    method: str
    gains: Mapping[str, float] = field(default_factory=dict)
    kind: str = "pd"
    provenance: Mapping[str, Any] = field(default_factory=dict)
    settings: Mapping[str, Any] = field(default_factory=dict)
    tick_fields: tuple[str, ...] = ()
    runtime: Any = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.system, DiscreteStateSpace):
            raise TypeError(f"system must be a DiscreteStateSpace, got {type(self.system).__name__}")
        gains = {str(k): float(v) for k, v in dict(self.gains).items()}
        object.__setattr__(self, "gains", plain_json(gains, "controller gains"))
        object.__setattr__(self, "provenance", plain_json(self.provenance, "controller provenance"))
        object.__setattr__(self, "settings", plain_json(self.settings, "controller settings"))
        object.__setattr__(self, "tick_fields", tuple(str(name) for name in self.tick_fields))

    def as_dict(self) -> dict:
        """Plain-data form: kind, method, gains, provenance, the state-space matrices (and settings, tick fields)."""
        extra: dict[str, Any] = {}  # only a registered kind has them: the built-in kinds' dicts stay as they were
        if self.settings:
            extra["settings"] = dict(self.settings)
        if self.tick_fields:
            extra["tick_fields"] = list(self.tick_fields)
        return {
            "kind": self.kind,
            "method": self.method,
            "gains": dict(self.gains),
            "provenance": dict(self.provenance),
            **extra,
            **self.system.as_dict(),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "ControllerInfo":
        """Inverse of :meth:`as_dict` (``provenance``, ``settings``, ``tick_fields`` optional; no runtime)."""
        missing = {"kind", "method", "gains"} - set(data)
        if missing:
            raise ValueError(f"controller data misses {sorted(missing)}")
        return cls(
            DiscreteStateSpace.from_dict(data),
            data["method"],
            data["gains"],
            data["kind"],
            data.get("provenance", {}),
            data.get("settings", {}),
            tuple(data.get("tick_fields", ())),
        )


def default_controller_path() -> Path:
    """The controller.toml shipped with the package: the gains that recorded the paper's dataset."""
    return controller_file("rig")
