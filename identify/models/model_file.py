"""Model files: a fitted Koopman model, its lifting and its controller, as JSON.

The format is documented in MODEL_FORMAT.md. A loaded model predicts exactly
as the fitted one did.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from qube_koopman.identify.lifting import (
    Constant,
    CoulombFriction,
    Delay,
    GaussianRbf,
    Lifting,
    LiftingFunction,
    Polynomial,
    ThinPlateRbf,
    Trigonometric,
)
from qube_koopman.identify.models.identified import FitUncertainty, HeldOutFigures, IdentifiedModel
from qube_koopman.identify.models.model import KoopmanModel
from qube_koopman.core.lti import DiscreteStateSpace
from qube_koopman.core.files import atomic_path, loads_json, read_bounded_text

__all__ = [
    "FORMAT",
    "VERSION",
    "ARX_FORMAT",
    "MAX_DELAYS",
    "MAX_MODEL_BYTES",
    "MAX_POLYNOMIAL_ORDER",
    "lifting_to_dict",
    "lifting_from_dict",
    "save_model",
    "load_model",
    "save_arx_model",
    "uncertainty_to_dict",
]

FORMAT = "qube-koopman-model"
VERSION = 1
#: The most delays a model file's lifting may ask for (20 s of samples at 500 Hz).
MAX_DELAYS = 10_000
#: The highest polynomial order a model file's lifting may ask for.
MAX_POLYNOMIAL_ORDER = 10
#: The largest model file read (a 300-state plant with 100 bootstrap refits is about 300 MB).
MAX_MODEL_BYTES = 2**30
#: The columns of the held-out figures (``uncertainty.held_out.figures``).
HELD_OUT_FIGURES = ("J", "voltage_rms", "voltage_peak")


#: An innermost JSON list of numbers, as ``json.dumps(..., indent=1)`` spreads it over one line per number (real
#: line breaks: a string's are escaped, so text that looks like a list is never touched).
_NUMBER_LIST = re.compile(r"\[\n\s*(-?[0-9][-+0-9.eE]*(?:,\n\s*-?[0-9][-+0-9.eE]*)*)\n\s*\]")


def _dumps(data: dict) -> str:
    """``data`` as indented JSON with each innermost list of numbers on one line (a matrix by rows): a file
    that reads as the matrices it holds, and smaller (340 instead of 406 kB for a plant of 35 delays with
    its bootstrap refits)."""
    text = json.dumps(data, indent=1)
    return _NUMBER_LIST.sub(lambda m: "[" + ", ".join(v.strip() for v in m.group(1).split(",")) + "]", text) + "\n"


def lifting_to_dict(lifting: Lifting) -> dict:
    """The fitted lifting as plain data (RBF centres included)."""
    steps = []
    for step in lifting.steps_:
        entry: dict[str, Any] = {"type": type(step).__name__}
        # The hyperparameters as stored (an np.int64 is legal) become plain JSON numbers.
        if isinstance(step, Polynomial):
            entry["order"] = int(step.order)
        elif isinstance(step, Delay):
            entry["n_delays"] = int(step.n_delays)
        elif isinstance(step, Constant):
            pass
        elif isinstance(step, Trigonometric):
            entry["features"] = list(step.features_)
        elif isinstance(step, CoulombFriction):
            entry.update(feature=int(step.feature), lag=int(step.lag), width=float(step.width))
        elif isinstance(step, (ThinPlateRbf, GaussianRbf)):
            entry.update(shape=float(step.shape), centers=step.centers_.tolist())
            if isinstance(step, ThinPlateRbf):
                entry["offset"] = float(step.offset)
        else:
            raise ValueError(f"lifting step {type(step).__name__} cannot be saved")
        steps.append(entry)
    return {"state_names": list(lifting.feature_names_in_), "steps": steps}


def lifting_from_dict(data: dict) -> Lifting:
    """Rebuild a fitted lifting from :func:`lifting_to_dict` output.

    The sizes a file may ask for are bounded before anything is allocated: at most
    :data:`MAX_DELAYS` delays and polynomial order :data:`MAX_POLYNOMIAL_ORDER`.
    """
    steps: list[LiftingFunction] = []
    for entry in data["steps"]:
        kind = entry.get("type")
        if kind == "Polynomial":
            steps.append(Polynomial(_bounded(entry["order"], "polynomial order", MAX_POLYNOMIAL_ORDER)))
        elif kind == "Delay":
            steps.append(Delay(_bounded(entry["n_delays"], "number of delays", MAX_DELAYS)))
        elif kind == "Constant":
            steps.append(Constant())
        elif kind == "Trigonometric":
            steps.append(Trigonometric(entry["features"]))
        elif kind == "CoulombFriction":
            steps.append(CoulombFriction(entry["feature"], entry["lag"], entry["width"]))
        elif kind == "ThinPlateRbf":
            steps.append(ThinPlateRbf(len(entry["centers"]), entry["shape"], entry["offset"], centers=entry["centers"]))
        elif kind == "GaussianRbf":
            steps.append(GaussianRbf(len(entry["centers"]), entry["shape"], centers=entry["centers"]))
        else:
            raise ValueError(f"unknown lifting step {kind!r}")
    lifting = Lifting(steps)
    names = data["state_names"]
    # Every step is now determined by its parameters; fitting only records the names.
    return lifting.fit([np.zeros((lifting.n_delays + 2, len(names)))], names)


def _bounded(value, name: str, largest: int):
    """``value`` unchanged when it is not an integer larger than ``largest`` (its own checks come later)."""
    if isinstance(value, int) and value > largest:
        raise ValueError(f"{name} {value} is more than this reader takes ({largest})")
    return value


def _model_to_dict(model: KoopmanModel | None) -> dict | None:
    if model is None:
        return None
    return {
        "A": model.A.tolist(),
        "B": model.B.tolist(),
        "input_signals": list(model.input_signals),
        "n_passthrough": model.n_passthrough,
        "passthrough_names": list(model.passthrough_names),
    }


def save_model(
    path: str | Path,
    *,
    method: str | None,
    alpha: float | None,
    plant: KoopmanModel,
    closed_loop: KoopmanModel | None,
    controller: DiscreteStateSpace | None,
    measured: list[int],
    training: dict | None,
    uncertainty: dict | None = None,
    disturbance=None,
) -> None:
    """Write a model file (see MODEL_FORMAT.md), atomically.

    Parameters
    ----------
    path : str or Path
        The file to write (replaced if it exists).
    method : str or None
        The identification method (``qube-identify --method``: ``"cl-edmd"``, ``"edmd"``, ...).
    alpha : float or None
        The Tikhonov coefficient of the fit (None for a method without one).
    plant : KoopmanModel
        The plant model (input ``u``); its lifting is saved with it.
    closed_loop : KoopmanModel or None
        The closed-loop model (inputs ``r``, ``f``), if the method identified one.
    controller : DiscreteStateSpace or None
        The controller of the closed loop.
    measured : list of int
        The fed-back plant states.
    training : dict or None
        What the model was fitted on, stored as given (JSON values).
    uncertainty : dict, optional
        The fit's uncertainty for a design (:func:`uncertainty_to_dict`); left out when None.
    disturbance : DisturbanceModel, optional
        The disturbance model and its Kalman filter's gain
        (:class:`~qube_koopman.identify.models.disturbance.DisturbanceModel`); left out when None.
    """
    data = {
        "format": FORMAT,
        "version": VERSION,
        "method": method,
        "alpha": alpha,
        "dt": plant.dt,
        "lifting": lifting_to_dict(plant.lifting),
        "measured": list(measured),
        "controller": None if controller is None else controller.as_dict(),
        "plant": _model_to_dict(plant),
        "closed_loop": _model_to_dict(closed_loop),
        "training": training,
    }
    if uncertainty is not None:
        data["uncertainty"] = uncertainty
    if disturbance is not None:
        data["disturbance"] = disturbance.as_dict()
    with atomic_path(path) as tmp:
        tmp.write_text(_dumps(data))


def uncertainty_to_dict(
    plant: KoopmanModel,
    members: list[KoopmanModel],
    held_out: np.ndarray | None,
    *,
    seed: int | None,
    skip: int | None,
    logs: list[str] | None = None,
    spectra: dict | None = None,
    method: str = "episode bootstrap",
) -> dict:
    """The ``uncertainty`` entry of a model file: bootstrap plants and held-out figures (MODEL_FORMAT.md).

    Parameters
    ----------
    plant : KoopmanModel
        The plant model (the point fit).
    members : list of KoopmanModel
        Its bootstrap refits; only the rows of the measured states are kept (the rows a re-lifted
        prediction uses: the others are the point fit's).
    held_out : ndarray of shape (n, 2, 3) or None
        Measured and predicted ``[J, voltage RMS, voltage peak]`` of the held-out training episodes
        (:func:`identify.uncertainty.held_out_figures`); None leaves ``held_out`` out.
    seed : int or None
        The resampling's seed.
    skip : int or None
        Samples left out at each held-out episode's start.
    logs : list of str, optional
        The held-out episodes' names.
    spectra : dict, optional
        Their prediction error's band spectra
        (:meth:`identify.uncertainty.spectra.ErrorSpectra.as_dict`).
    method : str
        How the members were drawn.

    Returns
    -------
    dict
    """
    m = plant.n_states
    out: dict[str, Any] = {
        "method": method,
        "seed": None if seed is None else int(seed),
        "plant_members": [{"A": member.A[:m].tolist(), "B": member.B[:m].tolist()} for member in members],
    }
    if held_out is None:
        return out
    out["held_out"] = {
        "skip_samples": None if skip is None else int(skip),
        "figures": list(HELD_OUT_FIGURES),
        "measured": np.asarray(held_out)[:, 0].tolist(),
        "predicted": np.asarray(held_out)[:, 1].tolist(),
    }
    if logs is not None:
        out["held_out"]["logs"] = list(logs)
    if spectra is not None:
        out["held_out"]["error_spectra"] = spectra
    return out


#: The ``format`` key of an ARX model file (MODEL_FORMAT.md).
ARX_FORMAT = "qube-arx-model"


def save_arx_model(path: str | Path, *, method: str, lags: int, model) -> None:
    """Write an ARX model file (see MODEL_FORMAT.md), atomically.

    Parameters
    ----------
    path : str or Path
        The file to write (replaced if it exists).
    method : {"arx", "cl-arx"}
        The identification method.
    lags : int
        The output and input lags of the fit.
    model : Arx
        The fitted ARX model: the plant's for ``"arx"``, the closed loop's for ``"cl-arx"``.
    """
    data = {
        "format": ARX_FORMAT,
        "version": 1,
        "method": method,
        "output_lags": lags,
        "input_lags": lags,
        "inputs": list(model.inputs),
        "coef": model.coef_.tolist(),
        "dt": model.dt_,
    }
    with atomic_path(path) as tmp:
        tmp.write_text(_dumps(data))


def load_model(path: str | Path) -> IdentifiedModel:
    """Read a model file.

    Parameters
    ----------
    path : str or Path
        A file :func:`save_model` wrote (``qube-identify --model``).

    Returns
    -------
    IdentifiedModel
        Its models ready to predict: ``plant`` and ``closed_loop`` (:class:`KoopmanModel`; the
        closed loop None when the method identified none),
        ``controller`` (:class:`DiscreteStateSpace` or None), ``uncertainty`` (the bootstrap refits
        of the plant as :class:`KoopmanModel`, their rows past the measured states the plant's, and
        the held-out figures; None when the file holds none), ``disturbance`` (its
        :class:`~qube_koopman.identify.models.disturbance.DisturbanceModel`, or None).

    Raises
    ------
    ValueError
        Naming the file when it is not a model file, has another version, holds no plant, or a model in it
        cannot be used (a non-finite entry in A or B, shapes that do not fit, damaged held-out
        figures or error spectra).
    """
    path = Path(path)
    try:  # a FIFO, a device, a file over MAX_MODEL_BYTES or nested too deep: a ValueError naming it
        data = loads_json(read_bounded_text(path, MAX_MODEL_BYTES, "model file"), path)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:  # an OSError's text would name the path again
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise ValueError(f"{path}: not a readable model file ({reason})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ValueError(f"{path}: not a {FORMAT} file")
    if data.get("version") != VERSION:
        raise ValueError(f"{path}: model format version {data.get('version')}, this software reads {VERSION}")
    dt = data.get("dt")
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"{path}: dt must be a positive number of seconds (the sample period), got {dt!r}")
    try:
        lifting = lifting_from_dict(data["lifting"])
    except (ValueError, TypeError, KeyError, AttributeError) as exc:
        raise ValueError(f"{path}: lifting: {exc}") from None

    def matrix(entry, name: str, key: str) -> np.ndarray:
        try:
            values = np.array(entry[key], dtype=float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: {name}.{key} is not a matrix of numbers ({exc})") from None
        bad = np.argwhere(~np.isfinite(values))
        if bad.size:
            where = ", ".join(str(i) for i in bad[0])
            raise ValueError(
                f"{path}: {name}.{key} has a non-finite entry ({values[tuple(bad[0])]}) at "
                f"[{where}]{f' and {len(bad) - 1} more' if len(bad) > 1 else ''}"
            )
        return values

    def model(entry, name: str):
        if entry is None:
            return None
        try:
            return KoopmanModel(
                matrix(entry, name, "A"),
                matrix(entry, name, "B"),
                lifting,
                tuple(entry["input_signals"]),
                n_passthrough=entry["n_passthrough"],
                dt=data["dt"],
                passthrough_names=tuple(entry["passthrough_names"]),
                feedback=tuple(data["measured"]) if "r" in entry["input_signals"] else (),
            )
        except ValueError as exc:
            message = str(exc)
            raise ValueError(message if message.startswith(f"{path}:") else f"{path}: {name}: {message}") from None

    plant = model(data["plant"], "plant")
    if plant is None:
        raise ValueError(f"{path}: the model file holds no plant model")
    return IdentifiedModel(
        method=data.get("method"),
        alpha=data.get("alpha"),
        dt=dt,
        lifting=lifting,
        measured=tuple(data.get("measured") or ()),
        plant=plant,
        closed_loop=model(data["closed_loop"], "closed_loop"),
        controller=None if data["controller"] is None else DiscreteStateSpace.from_dict(data["controller"]),
        training=data.get("training"),
        uncertainty=_uncertainty(data.get("uncertainty"), plant, matrix, path),
        disturbance=_disturbance(data.get("disturbance"), path),
    )


def _disturbance(entry, path: Path):
    """The model file's ``disturbance`` (None when it holds none)."""
    if entry is None:
        return None
    from qube_koopman.identify.models.disturbance import DisturbanceModel

    try:
        return DisturbanceModel.from_dict(entry)
    except (ValueError, TypeError, AttributeError) as exc:
        raise ValueError(f"{path}: disturbance: {exc}") from None


def _uncertainty(entry, plant: KoopmanModel, matrix, path: Path) -> FitUncertainty | None:
    """The model file's ``uncertainty`` (None when it holds none)."""
    if not isinstance(entry, dict):
        return None
    return FitUncertainty(
        plant_members=_members(entry.get("plant_members") or [], plant, matrix, path),
        held_out=_held_out(entry.get("held_out"), path),
        seed=entry.get("seed"),
        method=entry.get("method", "episode bootstrap"),
    )


def _members(entries: list, plant: KoopmanModel, matrix, path: Path) -> tuple[KoopmanModel, ...]:
    """The bootstrap plants of a model file's ``uncertainty.plant_members``."""
    m = plant.n_states
    members = []
    for i, entry in enumerate(entries):
        name = f"uncertainty.plant_members[{i}]"
        A_x, B_x = matrix(entry, name, "A"), matrix(entry, name, "B")
        if A_x.shape != (m, plant.A.shape[1]) or B_x.shape != (m, plant.B.shape[1]):
            raise ValueError(
                f"{path}: uncertainty.plant_members[{i}] has A {A_x.shape} and B {B_x.shape}, the plant's "
                f"measured rows are {(m, plant.A.shape[1])} and {(m, plant.B.shape[1])}"
            )
        A, B = plant.A.copy(), plant.B.copy()
        A[:m], B[:m] = A_x, B_x
        members.append(KoopmanModel(A, B, plant.lifting, tuple(plant.input_signals), dt=plant.dt))
    return tuple(members)


def _held_out(entry, path: Path) -> HeldOutFigures | None:
    """The model file's ``uncertainty.held_out`` (None when it holds none)."""
    if not entry:
        return None
    name = "uncertainty.held_out"
    k = len(HELD_OUT_FIGURES)

    def rows(key: str) -> np.ndarray:
        try:
            values = np.asarray(entry.get(key) or np.empty((0, k)), dtype=float)
        except (TypeError, ValueError):
            values = np.empty(0)
        if values.ndim != 2 or values.shape[1] != k:
            raise ValueError(f"{path}: {name}.{key} must be rows of {k} numbers ({', '.join(HELD_OUT_FIGURES)})")
        return values

    measured, predicted = rows("measured"), rows("predicted")
    if measured.shape != predicted.shape:
        raise ValueError(f"{path}: {name}: {len(measured)} measured rows, {len(predicted)} predicted")
    spectra = None
    if entry.get("error_spectra"):
        from qube_koopman.identify.uncertainty.spectra import ErrorSpectra

        try:
            spectra = ErrorSpectra.from_dict(entry["error_spectra"])
        except ValueError as exc:
            raise ValueError(f"{path}: {name}.error_spectra: {exc}") from None
        if measured.size and spectra.n_episodes != len(measured):
            raise ValueError(
                f"{path}: {name}.error_spectra holds {spectra.n_episodes} episodes, its figures {len(measured)}"
            )
    logs = entry.get("logs")
    return HeldOutFigures(
        measured=measured,
        predicted=predicted,
        skip_samples=entry.get("skip_samples"),
        logs=None if logs is None else tuple(logs),
        error_spectra=spectra,
    )
