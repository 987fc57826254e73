"""The MPC's controller file (kind ``"mpc"``): write it, and build the controller the loop runs from it.

The file holds everything the controller needs at run time: the plant's one-step rows on its
history (the rest of the history system is a shift), the LQ weights, the terminal cost ``P``,
the horizon, limits and solver settings (:class:`design.mpc.MpcSettings`) and the provenance.
:func:`build_mpc_controller` is registered with ``core``'s controller files through the entry
point ``mpc`` of the group ``qube_koopman.controller_kinds`` (pyproject.toml), so
``qube-run --controller FILE`` loads it without ``daq`` importing ``design``; it condenses the
problem again (a few milliseconds) and returns a :class:`~core.controller_file.ControllerInfo`
whose ``system`` is the LQ realization of the same weights (the controller's state, which the
log records, and its output when no constraint binds) and whose ``runtime`` is the MPC.

With a disturbance model (:class:`design.mpc.MpcDisturbance`) the file also holds its
``disturbance`` table (``entries``, ``pole``, the Kalman filter's ``gain``, one row per entry; a
file written with one disturbance, ``entry`` and a gain of one row, reads as that);
``settings.offset_free`` says whether the MPC uses the estimates or only records them. A file
without the table is the MPC without a disturbance model, exactly.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from qube_koopman.core.controller_file import (
    CONTROLLER_FORMAT,
    TRACKING_INPUTS,
    ControllerInfo,
    toml_value,
)
from qube_koopman.core.files import atomic_path
from qube_koopman.design.lq import Weights, augment, realize
from qube_koopman.design.mpc import MpcDisturbance, MpcRuntime, MpcSettings, condense
from qube_koopman.design.plant import DesignError, LinearPlant

__all__ = ["MPC_KIND", "write_mpc_file", "build_mpc_controller", "mpc_controller"]

#: The ``kind`` of an MPC controller file.
MPC_KIND = "mpc"

_KEYS = frozenset(
    {"format", "kind", "dt", "inputs", "n_delays", "plant_rows", "plant_input", "terminal_cost", "weights", "settings"}
    | {"provenance"}
)
#: Keys a file has only with a disturbance model.
_DISTURBANCE_KEYS = frozenset({"disturbance"})
_OPTIONAL = frozenset({"provenance"}) | _DISTURBANCE_KEYS


def _plant(rows: np.ndarray, b: np.ndarray, n_delays: int, dt: float) -> LinearPlant:
    """The history system from its one-step rows ``[F_x, G_x]``."""
    m = rows.shape[0]
    n = m * (n_delays + 1)
    F = np.zeros((n, n))
    F[:m] = rows
    F[m:, :-m] = np.eye(n - m)
    G = np.zeros((n, 1))
    G[:m, 0] = b
    return LinearPlant(F, G, np.zeros(n), m, n_delays, dt, True, "the MPC file's plant")


def mpc_controller(
    plant: LinearPlant,
    weights: Weights,
    P: np.ndarray,
    settings: MpcSettings,
    provenance: Mapping[str, Any] = {},
    disturbance: MpcDisturbance | None = None,
) -> ControllerInfo:
    """The controller the loop runs: the LQ realization as its state and its output without constraints, the MPC.

    Parameters
    ----------
    plant : LinearPlant
    weights : Weights
    P : ndarray
        The terminal cost (the infinite-horizon LQ's Riccati solution on :func:`design.lq.augment`'s system).
    settings : MpcSettings
    provenance : mapping
    disturbance : MpcDisturbance, optional
        The disturbance the MPC estimates each tick (and, with ``settings.offset_free``, rejects).

    Returns
    -------
    ControllerInfo
        kind ``"mpc"``.
    """
    F, G, Q, R = augment(plant, weights)
    K = np.linalg.solve(R + G.T @ P @ G, G.T @ P @ F)
    problem = condense(F, G, Q, R, P, K, settings)
    runtime = MpcRuntime(problem, plant.n_delays, weights.integral, plant.dt, disturbance=disturbance)
    extra = {} if disturbance is None else {"disturbance": disturbance.as_dict()}
    return ControllerInfo(
        realize(K, plant, weights.integral),
        "given",
        {},
        MPC_KIND,
        dict(provenance),
        {"weights": weights.as_dict(), **settings.as_dict(), **extra},
        runtime.tick_fields,
        runtime,
    )


def write_mpc_file(
    path: str | Path,
    plant: LinearPlant,
    weights: Weights,
    P: np.ndarray,
    settings: MpcSettings,
    provenance=None,
    disturbance: MpcDisturbance | None = None,
) -> Path:
    """Write the MPC's controller file, which :func:`core.controller_file.load_controller` reads back exactly.

    Parameters
    ----------
    path : str or Path
    plant : LinearPlant
        The plant designed on (its one-step rows are written).
    weights : Weights
    P : ndarray
        The terminal cost.
    settings : MpcSettings
    provenance : mapping, optional
    disturbance : MpcDisturbance, optional
        Written as the ``disturbance`` table (its plant is ``plant``'s).

    Returns
    -------
    Path
    """
    path = Path(path)
    m = plant.n_measured

    def matrix(a) -> str:
        return json.dumps(np.asarray(a, dtype=float).tolist())

    lines = [
        f"# A model predictive controller of qube-koopman (core/CONTROLLER_FORMAT.md): horizon {settings.horizon}",
        f'format = "{CONTROLLER_FORMAT}"',
        f'kind = "{MPC_KIND}"',
        f"dt = {plant.dt!r}",
        f"inputs = {json.dumps(list(TRACKING_INPUTS))}",
        f"n_delays = {plant.n_delays}",
        f"plant_rows = {matrix(plant.F[:m])}",
        f"plant_input = {matrix(plant.G[:m, 0])}",
        f"terminal_cost = {matrix(P)}",
        f"weights = {toml_value(weights.as_dict())}",
        f"settings = {toml_value(settings.as_dict())}",
    ]
    if disturbance is not None:
        lines.append(f"disturbance = {toml_value(disturbance.as_dict())}")
    if provenance:
        lines += ["", "[provenance]"] + [f"{json.dumps(str(k))} = {toml_value(v)}" for k, v in provenance.items()]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return path


def build_mpc_controller(data: dict, path: Path, dt: float) -> ControllerInfo:
    """The builder of kind ``"mpc"`` (``load_controller`` calls it with the file's table, its path, the loop's period).

    Raises
    ------
    ValueError
        Naming the file: a missing or unknown key, a matrix of the wrong shape or not finite, bad
        weights or settings.
    """
    missing = sorted(_KEYS - _OPTIONAL - set(data))
    if missing:
        raise ValueError(f"{path}: missing key{'s' if len(missing) > 1 else ''} {', '.join(missing)}")
    unknown = sorted(set(data) - _KEYS - _DISTURBANCE_KEYS)
    if unknown:
        known = ", ".join(sorted(_KEYS | _DISTURBANCE_KEYS))
        raise ValueError(f"{path}: unknown keys {', '.join(unknown)} (an mpc file has {known})")
    if tuple(data["inputs"]) != TRACKING_INPUTS:
        raise ValueError(f"{path}: inputs must be {json.dumps(list(TRACKING_INPUTS))}, got {data['inputs']!r}")
    d = data["n_delays"]
    if not (isinstance(d, int) and not isinstance(d, bool) and 0 <= d <= 1000):
        raise ValueError(f"{path}: n_delays must be a whole number >= 0, got {d!r}")
    weights_data, settings_data = data["weights"], data["settings"]
    if not isinstance(weights_data, dict) or not isinstance(settings_data, dict):
        raise ValueError(f"{path}: weights and settings must be tables")
    try:
        weights = Weights(**weights_data)
        settings = MpcSettings(**settings_data)
    except (TypeError, DesignError) as exc:
        raise ValueError(f"{path}: {exc}") from None
    n = 2 * (d + 1)
    n_z = n + int(weights.integral)
    rows = _array(data["plant_rows"], "plant_rows", (2, n), path)
    b = _array(data["plant_input"], "plant_input", (2,), path)
    P = _array(data["terminal_cost"], "terminal_cost", (n_z, n_z), path)
    provenance = data.get("provenance", {})
    if not isinstance(provenance, dict):
        raise ValueError(f"{path}: provenance must be a table ([provenance])")
    plant = _plant(rows, b, d, float(data["dt"]))
    disturbance = None
    if "disturbance" in data:
        table = data["disturbance"]
        if not isinstance(table, dict) or set(table) not in ({"entries", "pole", "gain"}, {"entry", "pole", "gain"}):
            raise ValueError(f"{path}: disturbance must be a table of entries, pole and gain")
        entries = table["entries"] if "entries" in table else [table["entry"]]
        if not isinstance(entries, list) or not entries:
            raise ValueError(f"{path}: disturbance.entries must be a list of where each disturbance enters")
        shape = (2,) if "entry" in table else (len(entries), 2)
        try:
            disturbance = MpcDisturbance(
                tuple(map(str, entries)),
                float(table["pole"]),
                _array(table["gain"], "disturbance.gain", shape, path),
                rows,
                b,
            )
        except (TypeError, DesignError) as exc:
            raise ValueError(f"{path}: {exc}") from None
    try:
        return mpc_controller(plant, weights, P, settings, provenance, disturbance)
    except DesignError as exc:
        raise ValueError(f"{path}: {exc}") from None


def _array(value: Any, name: str, shape: tuple[int, ...], path: Path) -> np.ndarray:
    try:
        a = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: {name} must be an array of numbers") from None
    if a.shape != shape:
        raise ValueError(
            f"{path}: {name} has shape {' x '.join(map(str, a.shape))}, expected {' x '.join(map(str, shape))}"
        )
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{path}: {name} has non-finite entries")
    return a
