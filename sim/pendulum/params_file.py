"""Plant parameter files: the simulator's physical parameters as TOML, with provenance.

``qube-calibrate`` writes them, ``qube-run --plant FILE`` and
``qube-emulate --plant FILE`` read them. The format (version 1)::

    format = "qube-plant/1"

    [parameters]            # PendulumParameters fields, SI units; missing ones keep their defaults
    Rm = 8.4
    km = 0.0412
    Dr = 0.00031
    Cr = 0.0004
    ...

    [standard_errors]       # optional: one standard error per fitted parameter
    km = 0.0003

    [provenance]            # optional, free-form: where the numbers came from
    source = "qube-calibrate"
    logs = ["episodes/ep_001.mcap", ...]
    software_version = "..."
    created = "2026-11-23T11:00:00+00:00"
    residual_rms = 0.0012

Unknown keys in ``[parameters]`` are an error (a misspelt ``Dr`` must not
silently keep its default). Values are TOML floats or integers; provenance
values are strings, numbers, booleans or lists of those.

Named parameter sets (:func:`named_parameters`): ``"calibrated-two-controllers"``
(``plants/qube_20230828_20230915.toml``: ``qube-calibrate`` on the paper's 28
training episodes and on 10 episodes of the same rig under a softer arm loop,
with the arm's cable spring ``Kr`` fitted; its closed-loop validation is in its
provenance), ``"default"`` (what :class:`PendulumParameters` gives: the same
values), ``"calibrated-20230828"`` (``plants/qube_20230828.toml``: the paper's
28 training episodes alone, with the arm's hub inertia and the transport delay
fitted and no cable spring: the default before the second controller's logs),
``"workbook"`` (the Quanser workbook, including its damping) and
``"previous"`` (workbook masses with another public project's hardware-fitted
damping: the default before calibration, the calibration's starting point).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, fields
from pathlib import Path

from qube_koopman.sim.pendulum.model import PendulumParameters
from qube_koopman.core.files import atomic_path

__all__ = [
    "PlantFile",
    "load_plant",
    "save_plant",
    "named_parameters",
    "plant_parameters",
    "PARAMETER_SETS",
    "PlantFileError",
    "FORMAT",
]

FORMAT = "qube-plant/1"

#: Shipped plant files.
PLANTS = Path(__file__).resolve().parent / "plants"


class PlantFileError(ValueError):
    """A plant file that cannot be read: the message names the file and the problem."""


class PlantFile:
    """A plant file's contents.

    Parameters
    ----------
    params : PendulumParameters
    standard_errors : dict of str to float
    provenance : dict
    """

    def __init__(
        self, params: PendulumParameters, standard_errors: dict | None = None, provenance: dict | None = None
    ) -> None:
        self.params = params
        self.standard_errors = dict(standard_errors or {})
        self.provenance = dict(provenance or {})


#: The named parameter sets (:func:`named_parameters`).
PARAMETER_SETS = ("default", "calibrated-two-controllers", "calibrated-20230828", "workbook", "previous")


def named_parameters(name: str) -> PendulumParameters:
    """A named parameter set: one of :data:`PARAMETER_SETS`."""
    sets = {
        "default": PendulumParameters,
        "workbook": PendulumParameters.workbook,
        "previous": PendulumParameters.previous,
        "calibrated-two-controllers": lambda: load_plant(PLANTS / "qube_20230828_20230915.toml").params,
        "calibrated-20230828": lambda: load_plant(PLANTS / "qube_20230828.toml").params,
    }
    if name not in sets:
        raise ValueError(f"no parameter set named {name!r}; known: {', '.join(sets)}")
    return sets[name]()


def plant_parameters(name_or_path: str | Path | None) -> PendulumParameters:
    """What ``--plant`` names: a plant file, a set of :data:`PARAMETER_SETS`, or None for the defaults.

    A set's name that is also a file in the working folder is the file.

    Raises
    ------
    PlantFileError
        The file cannot be read (the message names it).
    """
    if name_or_path is None:
        return PendulumParameters()
    if str(name_or_path) in PARAMETER_SETS and not Path(name_or_path).exists():
        return named_parameters(str(name_or_path))
    return load_plant(name_or_path).params


def load_plant(path: str | Path) -> PlantFile:
    """Read a plant file.

    Parameters
    ----------
    path : str or Path
        A plant file (``qube-calibrate``'s output, :func:`save_plant`).

    Returns
    -------
    PlantFile

    Raises
    ------
    PlantFileError
        The file is missing, not TOML, of another format, or has unknown or invalid parameters.
    """
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except OSError as exc:
        raise PlantFileError(f"{path}: cannot read plant file ({exc.strerror or exc})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise PlantFileError(f"{path}: not a TOML file ({exc})") from None
    if data.get("format") != FORMAT:
        raise PlantFileError(f"{path}: format must be {FORMAT!r}, got {data.get('format')!r}")
    values = data.get("parameters", {})
    known = {f.name for f in fields(PendulumParameters)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise PlantFileError(f"{path}: unknown parameter(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    for name, value in values.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise PlantFileError(f"{path}: parameter {name} must be a number, got {value!r}")
    try:
        params = PendulumParameters(**{k: float(v) for k, v in values.items()})
    except ValueError as exc:
        raise PlantFileError(f"{path}: {exc}") from None
    return PlantFile(params, data.get("standard_errors", {}), data.get("provenance", {}))


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
        return repr(value)
    if isinstance(value, str):
        escaped = value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
        return f'"{escaped}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to a plant file")


def save_plant(path: str | Path, plant: PlantFile) -> None:
    """Write a plant file (format above); floats round-trip exactly.

    Parameters
    ----------
    path : str or Path
        The file (written atomically, replaced if it exists).
    plant : PlantFile
        The parameters, their standard errors and provenance.
    """
    lines = [f'format = "{FORMAT}"', "", "[parameters]"]
    lines += [f"{k} = {_toml_value(float(v))}" for k, v in asdict(plant.params).items()]
    if plant.standard_errors:
        lines += ["", "[standard_errors]"]
        lines += [f"{k} = {_toml_value(float(v))}" for k, v in plant.standard_errors.items()]
    if plant.provenance:
        lines += ["", "[provenance]"]
        lines += [f"{k} = {_toml_value(v)}" for k, v in plant.provenance.items()]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
