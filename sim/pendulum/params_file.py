"""Plant parameter files: the simulator's physical parameters as TOML, with provenance.

``qube-calibrate`` writes them, ``qube-run --plant FILE`` and
``qube-emulate --plant FILE`` read them. The format (version 2)::

    format = "qube-plant/2"

    [parameters]            # PendulumParameters fields, SI units; missing ones keep their defaults
    Rm = 8.4
    km = 0.0412
    Dr = 0.00031
    Cr = 0.0004
    ...

    [standard_errors]       # optional: one standard error per fitted parameter
    km = 0.0003

    [setups."2023-09-15"]   # optional: what differed on a day the rig was set up (logs of that day)
    Kr = 0.0017             # PendulumParameters fields; the others are [parameters]'s

    [setups."2023-09-15 15:19:11-15:23:27"]   # a session: logs started within 10 min of its span
    delay = 0.0049

    [setup_standard_errors."2023-09-15"]
    Kr = 4e-6

    [load]                  # optional: a random torque on the arm (absent: none)
    diffusion = 0.03        # V/sqrt(s) at the motor: the std of its change over 1 s
    time_constant = 2.5     # s: first-order (Ornstein-Uhlenbeck); inf: a random walk
    floor = 0.0002          # V^2/Hz: a faster part, flat up to floor_corner (optional, default 0)
    floor_corner = 1.0      # Hz (optional, default 1)

    [load_standard_errors]  # optional: the load's standard errors
    diffusion = 0.002
    time_constant = 0.3

    [load_setups."2023-09-15"]   # optional: a recording day's own load (its logs replay with it)
    diffusion = 0.09
    time_constant = 0.55

    [load_setup_standard_errors."2023-09-15"]
    diffusion = 0.02

    [relaxation]            # optional: the cables' relaxation (absent: none)
    fast = 0.26             # V/rad: stiffer than the cable spring against fast motion
    relaxing = 0.38         # V/rad: the part of it that relaxes
    time_constant = 1.0     # s: over which it relaxes

    [relaxation_standard_errors]      # optional: its standard errors (V/rad)
    fast = 0.02
    relaxing = 0.03

    [relaxation_setups."2023-09-15"]   # optional: a recording day's own relaxation
    fast = 0.25
    relaxing = 0.37
    time_constant = 1.0

    [relaxation_setup_standard_errors."2023-09-15"]
    fast = 0.03
    relaxing = 0.04

    [provenance]            # optional, free-form: where the numbers came from
    source = "qube-calibrate"
    logs = ["episodes/ep_001.mcap", ...]
    software_version = "..."
    created = "2026-11-23T11:00:00+00:00"
    residual_rms = 0.0012

Version 1 is version 2 before the cables' pull could level off: a version-1 file without
``cable_softening`` is read with 0 (the linear spring it was fitted with), not with the default.

Unknown keys in ``[parameters]`` and ``[setups.*]`` are an error (a misspelt ``Dr`` must not
silently keep its default), and so are values the model's arithmetic cannot take: a size over 1e6, a
resistance, mass, length or Coulomb speed under 1e-15, a delay over 1 s
(:class:`~qube_koopman.sim.pendulum.physics.PendulumParameters`); a file over 16 MiB, nested more than
64 levels deep, or a named pipe or device is refused unread. A setup is what differed when the logs
were recorded: the cables between the arm's hub and the base are dressed anew each time the rig is
set up (a day: the two recording days' logs want stiffnesses 3.1 times apart), the host's latency
from a command to the motor changes with the session (0.6 to 4.1 ms in four). ``qube-calibrate``
fits those per day and per session with the rest of the physics shared; a replay of a log recorded
then uses them (:meth:`PlantFile.params_for`), and ``[parameters]`` holds the central guess for a
day or session no log shows.
The ``[load]`` table is the arm's random load (:class:`~qube_koopman.sim.pendulum.load.RandomLoad`):
a torque in volts at the motor, past the amplifier's dead zone (``km / Rm`` N m per volt), whose
statistics ``qube-calibrate`` estimates from the arm's equation run backwards on the logs. A file
without it simulates no load, exactly as before the table existed; ``qube-run --no-load`` leaves it
out. Its keys are ``diffusion``, ``time_constant``, ``floor`` and ``floor_corner``, nothing else;
``[load_setups.DAY]`` holds a recording day's own load (the rig's load differed between its
recording days, as its cables did), which a replay of a log of that day uses (:meth:`PlantFile.loads_for_logs`).
The ``[relaxation]`` table is the cables' torque that the arm's own motion drives
(:class:`~qube_koopman.sim.pendulum.relaxation.CableRelaxation`: ``fast``, ``relaxing``,
``time_constant``, all three required); ``[relaxation_setups.DAY]`` a recording day's own
(:meth:`PlantFile.relaxations_for_logs`). A file without it simulates none. Their standard errors
(``[relaxation_standard_errors]``, ``[relaxation_setup_standard_errors.DAY]``: ``fast`` and
``relaxing``; the time constant is chosen from a grid, not fitted) are read and written with them
and change no simulation.
Values are TOML floats or integers; provenance
values are strings, numbers, booleans or lists of those.

Named parameter sets (:func:`named_parameters`): ``"calibrated-two-controllers"``
(``plants/qube_20230828_20230915.toml``: ``qube-calibrate`` on the paper's 28
training episodes and on 10 episodes of the same rig under a softer arm loop,
with the arm's cable spring ``Kr`` fitted per recording day and the command delay per
recording session; its closed-loop validation is in its provenance), ``"default"`` (what
:class:`PendulumParameters` gives: the same values), ``"calibrated-20230828"``
(``plants/qube_20230828.toml``: the paper's 28 training episodes alone, with the arm's hub
inertia and the transport delay fitted and no cable spring: the default before the second
controller's logs), ``"calibrated-with-load"`` (``plants/qube_20230828_20230915_load_tilt.toml``:
the same logs and recipe as the default with ``qube-calibrate --load --tilt``: the arm's random
load, central and per recording day, and each day's tilt of the base; :func:`plant_file` gives
its ``[load]`` tables, which ``qube-run`` simulates), ``"calibrated-with-relaxation"``
(``plants/qube_20230828_20230915_relaxation.toml``: the same with ``--relaxation`` too: each day's
cable relaxation, fitted with the physics, and the random load it leaves),
``"workbook"`` (the Quanser workbook, including its damping) and
``"previous"`` (workbook masses with another public project's hardware-fitted
damping: the default before calibration, the calibration's starting point).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, fields, replace
from pathlib import Path
from typing import Sequence

from qube_koopman.sim.pendulum.load import RandomLoad
from qube_koopman.sim.pendulum.relaxation import CableRelaxation
from qube_koopman.sim.pendulum.physics import PendulumParameters
from qube_koopman.core.files import atomic_path, loads_toml, read_bounded_text

__all__ = [
    "PlantFile",
    "SESSION_GAP",
    "recording_day",
    "recording_sessions",
    "recording_start",
    "setup_labels",
    "load_plant",
    "save_plant",
    "named_parameters",
    "plant_file",
    "plant_parameters",
    "PARAMETER_SETS",
    "PlantFileError",
    "FORMAT",
    "MAX_PLANT_BYTES",
]

FORMAT = "qube-plant/2"
#: The largest plant file read (a few tables of numbers, a table per recording day).
MAX_PLANT_BYTES = 16 * 2**20
#: Earlier formats still read, with what each lacked (the physics it was written with).
_OLDER_FORMATS = {"qube-plant/1": {"cable_softening": 0.0}}

#: The keys of the ``[load]`` table (:class:`RandomLoad`'s fields).
_LOAD_KEYS = ("diffusion", "time_constant", "floor", "floor_corner")
#: The keys of the ``[relaxation]`` table (:class:`CableRelaxation`'s fields).
_RELAXATION_KEYS = ("fast", "relaxing", "time_constant")

#: Seconds between two logs' starts beyond which the second starts a new recording session.
SESSION_GAP = 600.0

_DAY = "%Y-%m-%d"
_TIME = "%Y-%m-%dT%H:%M:%S"
_SESSION_TIME = "%Y-%m-%d %H:%M:%S"  # a session label's first start


def recording_day(start_time: str | None) -> str:
    """The day (``YYYY-MM-DD``) of a log's start time (ISO 8601); "unknown" without a readable one."""
    started = recording_start(start_time)
    return "unknown" if started is None else started.strftime(_DAY)


def recording_sessions(start_times: Sequence[str | None]) -> list[str]:
    """Each log's recording session: logs whose starts follow each other within :data:`SESSION_GAP`.

    Parameters
    ----------
    start_times : sequence of str
        The logs' start times (ISO 8601, as logged), in any order.

    Returns
    -------
    list of str
        Per log, its session's label ``"YYYY-MM-DD HH:MM:SS-HH:MM:SS"`` (its first and last logs'
        starts), or "unknown" for a log without a readable start time.
    """
    started = [recording_start(t) for t in start_times]
    labels = ["unknown"] * len(started)
    for chain in _chains([(t, t, i) for i, t in enumerate(started) if t is not None]):
        label = f"{chain[0][0]:{_SESSION_TIME}}-{chain[-1][0]:%H:%M:%S}"
        for _, _, i in chain:
            labels[i] = label
    return labels


def _chains(spans: list[tuple]) -> list[list[tuple]]:
    """``(start, end, ...)`` spans in time grouped as sessions: sorted by start, each joining the chain
    before it while it begins within :data:`SESSION_GAP` of that chain's latest end."""
    chains: list[list[tuple]] = []
    end = None
    for span in sorted(spans, key=lambda s: (s[0], s[1])):
        if chains and (span[0] - end).total_seconds() <= SESSION_GAP:
            chains[-1].append(span)
            end = max(end, span[1])
        else:
            chains.append([span])
            end = span[1]
    return chains


def setup_labels(start_times: Sequence[str | None]) -> dict[str, list[str]]:
    """The setups of logs started at ``start_times``, as ``qube-calibrate --setups cables-and-delay`` fits them.

    Returns
    -------
    dict
        ``{"Kr": each log's recording day, "delay": each log's recording session}``: the cables are
        dressed anew when the rig is set up, the host's latency changes with the session.
    """
    return {"Kr": [recording_day(t) for t in start_times], "delay": recording_sessions(start_times)}


def recording_start(start_time: str | None):
    """A log's start time (ISO 8601, as logged) as a ``datetime`` to the second; None without a readable one
    (the logs :func:`recording_sessions` puts in no session)."""
    from datetime import datetime

    try:
        return datetime.strptime(str(start_time or "")[:19], _TIME)
    except ValueError:
        return None


def _session_span(label: str):
    """The first and last starts of a session label, or None for a label that is not one (a day)."""
    from datetime import datetime

    try:
        first = datetime.strptime(label[:19], _SESSION_TIME)
        last = datetime.strptime(label[:10] + " " + label[20:], _SESSION_TIME)
    except ValueError:
        return None
    return (first, last) if len(label) == 28 and label[19] == "-" else None


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
    setups : dict of str to dict of str to float, optional
        Per setup (a recording day, ``YYYY-MM-DD``, or a recording session,
        ``YYYY-MM-DD HH:MM:SS-HH:MM:SS``), the parameters that differed then.
    setup_standard_errors : dict of str to dict of str to float, optional
        Their standard errors.
    load : RandomLoad, optional
        The random torque on the arm (the ``[load]`` table); None: no load.
    load_standard_errors : dict of str to float, optional
        Its parameters' standard errors.
    load_setups : dict of str to RandomLoad, optional
        A recording day's (``YYYY-MM-DD``) own load.
    load_setup_standard_errors : dict of str to dict of str to float, optional
        Their standard errors.
    relaxation : CableRelaxation, optional
        The cables' relaxation (the ``[relaxation]`` table); None: none.
    relaxation_setups : dict of str to CableRelaxation, optional
        A recording day's (``YYYY-MM-DD``) own relaxation.
    relaxation_standard_errors : dict of str to float, optional
        The central relaxation's standard errors (``fast``, ``relaxing``).
    relaxation_setup_standard_errors : dict of str to dict of str to float, optional
        A recording day's relaxation's standard errors.
    """

    def relaxations_for_logs(self, start_times: Sequence[str | None]) -> list[CableRelaxation | None]:
        """The cables' relaxation of each log's replay: its recording day's (``relaxation_setups``) or the central
        one (None where the file has none)."""
        return [self.relaxation_setups.get(recording_day(t), self.relaxation) for t in start_times]

    def loads_for_logs(self, start_times: Sequence[str | None]) -> list[RandomLoad | None]:
        """The random load of each log's replay: its recording day's (``load_setups``) or the central one.

        Parameters
        ----------
        start_times : sequence of str or None
            The logs' starts (ISO 8601, as logged).

        Returns
        -------
        list of RandomLoad or None
            None where the file has no load.
        """
        return [self.load_setups.get(recording_day(t), self.load) for t in start_times]

    def __init__(
        self,
        params: PendulumParameters,
        standard_errors: dict | None = None,
        provenance: dict | None = None,
        setups: dict | None = None,
        setup_standard_errors: dict | None = None,
        load: RandomLoad | None = None,
        load_standard_errors: dict | None = None,
        load_setups: dict | None = None,
        load_setup_standard_errors: dict | None = None,
        relaxation: CableRelaxation | None = None,
        relaxation_setups: dict | None = None,
        relaxation_standard_errors: dict | None = None,
        relaxation_setup_standard_errors: dict | None = None,
    ) -> None:
        self.params = params
        self.relaxation = relaxation
        self.relaxation_setups = {str(k): v for k, v in (relaxation_setups or {}).items()}
        self.relaxation_standard_errors = dict(relaxation_standard_errors or {})
        self.relaxation_setup_standard_errors = {
            str(k): dict(v) for k, v in (relaxation_setup_standard_errors or {}).items()
        }
        if self.relaxation_setups and relaxation is None:
            raise ValueError("a recording day's relaxation (relaxation_setups) needs the central one beside it")
        self.load = load
        self.load_standard_errors = dict(load_standard_errors or {})
        self.load_setups = {str(k): v for k, v in (load_setups or {}).items()}
        self.load_setup_standard_errors = {str(k): dict(v) for k, v in (load_setup_standard_errors or {}).items()}
        if self.load_setups and load is None:
            raise ValueError("a recording day's load (load_setups) needs the central load beside it")
        self.standard_errors = dict(standard_errors or {})
        self.provenance = dict(provenance or {})
        self.setups = {str(k): dict(v) for k, v in (setups or {}).items()}
        self.setup_standard_errors = {str(k): dict(v) for k, v in (setup_standard_errors or {}).items()}

    def params_for(self, start_time: str | None) -> PendulumParameters:
        """The twin of a log that started at ``start_time``: :attr:`params` with the values of its setups.

        Its day's (a setup labelled ``YYYY-MM-DD``) and its session's (a setup labelled
        ``"YYYY-MM-DD HH:MM:SS-HH:MM:SS"`` whose span the start falls in, give or take
        :data:`SESSION_GAP`), where the file has them; :meth:`params_for_logs` for several logs.

        Parameters
        ----------
        start_time : str or None
            The log's start (ISO 8601, as logged); None or a time no setup covers gives :attr:`params`.

        Returns
        -------
        PendulumParameters
        """
        return self.params_for_logs([start_time])[0]

    def params_for_logs(self, start_times: Sequence[str | None]) -> list[PendulumParameters]:
        """The twin of each of several logs: :meth:`params_for`, their sessions found together.

        Logs that follow each other within :data:`SESSION_GAP` are one session, as
        :func:`recording_sessions` finds them, and so are they with a session of the file
        they reach: a log recorded 15 minutes after the fitted ones, with others between, is of
        their session (nearest in time if its chain reaches two).

        Parameters
        ----------
        start_times : sequence of str or None
            The logs' starts (ISO 8601, as logged).

        Returns
        -------
        list of PendulumParameters
        """
        started = [recording_start(t) for t in start_times]
        sessions = {label: span for label in self.setups if (span := _session_span(label)) is not None}
        # The logs (a span each: its start) and the file's sessions, chained as recording_sessions chains logs.
        spans = [(t, t, i, "") for i, t in enumerate(started) if t is not None]
        spans += [(first, last, -1, label) for label, (first, last) in sessions.items()]
        session_of: dict[int, str] = {}
        for chain in _chains(spans):
            known = [c for c in chain if c[3]]
            for t, _, i, label in chain:
                if not label and known:
                    nearest = min(known, key=lambda k: max((k[0] - t).total_seconds(), (t - k[1]).total_seconds()))
                    session_of[i] = nearest[3]
        out = []
        for i, t in enumerate(started):
            if t is None:
                out.append(self.params)
                continue
            values = {k: float(v) for k, v in self.setups.get(t.strftime(_DAY), {}).items()}
            values.update({k: float(v) for k, v in self.setups.get(session_of.get(i, ""), {}).items()})
            out.append(replace(self.params, **values) if values else self.params)
        return out


#: The named parameter sets (:func:`named_parameters`).
PARAMETER_SETS = (
    "default",
    "calibrated-two-controllers",
    "calibrated-with-load",
    "calibrated-with-relaxation",
    "calibrated-20230828",
    "workbook",
    "previous",
)
#: The named sets that are shipped plant files with setups (:func:`plant_file` reads them whole).
_SHIPPED_FILES = {
    "default": "qube_20230828_20230915.toml",
    "calibrated-two-controllers": "qube_20230828_20230915.toml",
    "calibrated-with-load": "qube_20230828_20230915_load_tilt.toml",
    "calibrated-with-relaxation": "qube_20230828_20230915_relaxation.toml",
}


def named_parameters(name: str) -> PendulumParameters:
    """A named parameter set: one of :data:`PARAMETER_SETS`."""
    sets = {
        "default": PendulumParameters,
        "workbook": PendulumParameters.workbook,
        "previous": PendulumParameters.previous,
        "calibrated-two-controllers": lambda: load_plant(PLANTS / _SHIPPED_FILES["calibrated-two-controllers"]).params,
        "calibrated-with-load": lambda: load_plant(PLANTS / _SHIPPED_FILES["calibrated-with-load"]).params,
        "calibrated-with-relaxation": lambda: load_plant(PLANTS / _SHIPPED_FILES["calibrated-with-relaxation"]).params,
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
    if name_or_path is None:  # the shipped twin's values, without reading its file
        return PendulumParameters()
    return plant_file(name_or_path).params


def plant_file(name_or_path: str | Path | None) -> PlantFile:
    """What ``--plant`` names, with its setups: :func:`plant_parameters` as a :class:`PlantFile`.

    None and ``"default"`` give the shipped twin's file (its recording days' cables and sessions'
    delays), a named set without a file its parameters alone (no setups).

    Raises
    ------
    PlantFileError
        The file cannot be read (the message names it).
    """
    named = name_or_path is not None and str(name_or_path) in PARAMETER_SETS and not Path(name_or_path).exists()
    if name_or_path is None or (named and str(name_or_path) in _SHIPPED_FILES):
        return load_plant(PLANTS / _SHIPPED_FILES[str(name_or_path or "default")])
    if named:
        return PlantFile(named_parameters(str(name_or_path)))
    return load_plant(name_or_path)


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
        data = loads_toml(read_bounded_text(path, MAX_PLANT_BYTES, "plant file"), path)
    except OSError as exc:
        raise PlantFileError(f"{path}: cannot read plant file ({exc.strerror or exc})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise PlantFileError(f"{path}: not a TOML file ({exc})") from None
    except ValueError as exc:  # a FIFO, a device, too large or nested too deep: the message names the file
        raise PlantFileError(str(exc)) from None
    version = data.get("format")
    if version != FORMAT and version not in _OLDER_FORMATS:
        raise PlantFileError(
            f"{path}: format must be {FORMAT!r} (or {', '.join(map(repr, _OLDER_FORMATS))}), got {version!r}"
        )
    values = _OLDER_FORMATS.get(version, {}) | _numbers(path, data.get("parameters", {}), "")
    try:
        params = PendulumParameters(**values)
    except ValueError as exc:
        raise PlantFileError(f"{path}: {exc}") from None
    setups = {str(day): _numbers(path, table, f"setup {day}: ") for day, table in data.get("setups", {}).items()}
    load, load_errors = _load_table(path, data, "load", "load_standard_errors")
    load_setups, load_setup_errors = {}, {}
    per_day_load_errors = _per_day(path, data, "load_setup_standard_errors")
    for day, table in _per_day(path, data, "load_setups").items():
        errors = per_day_load_errors.get(day, {})
        load_setups[day], errors = _load_table(
            path, {"load": table, "errors": errors}, "load", "errors", f"load_setups.{day}"
        )
        if errors:
            load_setup_errors[day] = errors
    if load_setups and load is None:
        raise PlantFileError(f"{path}: [load_setups] needs a [load] table beside it (the central load)")
    relaxation = _relaxation_table(path, data.get("relaxation"), "relaxation")
    relaxation_setups = {
        str(day): _relaxation_table(path, table, f"relaxation_setups.{day}")
        for day, table in _per_day(path, data, "relaxation_setups").items()
    }
    if relaxation_setups and relaxation is None:
        raise PlantFileError(f"{path}: [relaxation_setups] needs a [relaxation] table beside it (the central one)")
    relaxation_errors = _relaxation_errors(path, data.get("relaxation_standard_errors"), "relaxation_standard_errors")
    relaxation_setup_errors = {
        str(day): _relaxation_errors(path, table, f"relaxation_setup_standard_errors.{day}")
        for day, table in _per_day(path, data, "relaxation_setup_standard_errors").items()
    }
    unmatched = sorted(set(relaxation_setup_errors) - set(relaxation_setups))
    if (relaxation_errors and relaxation is None) or unmatched:
        what = "[relaxation_standard_errors]" if not unmatched else f"[relaxation_setup_standard_errors.{unmatched[0]}]"
        raise PlantFileError(f"{path}: {what} has no relaxation beside it to be the errors of")
    plant = PlantFile(
        params,
        data.get("standard_errors", {}),
        data.get("provenance", {}),
        setups,
        data.get("setup_standard_errors"),
        load,
        load_errors,
        load_setups,
        load_setup_errors,
        relaxation,
        relaxation_setups,
        relaxation_errors,
        relaxation_setup_errors,
    )
    for day, table in setups.items():
        try:
            replace(params, **table)
        except ValueError as exc:
            raise PlantFileError(f"{path}: setup {day}: {exc}") from None
    return plant


def _load_table(
    path: Path, data: dict, key: str, errors_key: str, title: str = "load"
) -> tuple[RandomLoad | None, dict]:
    """The ``data[key]`` table as a :class:`RandomLoad` (None without one) and ``data[errors_key]``, its
    standard errors, checked; messages name the table ``[title]``."""
    errors = data.get(errors_key, {})
    if key not in data:
        return None, {}
    out = [
        _number_table(path, table, name, _LOAD_KEYS, "diffusion, time_constant")
        for name, table in ((title, data[key]), (f"{title} standard errors", errors))
    ]
    if "diffusion" not in out[0]:
        raise PlantFileError(f"{path}: [{title}]: diffusion (V/sqrt(s)) is missing")
    try:
        return RandomLoad(**out[0]), out[1]
    except ValueError as exc:
        raise PlantFileError(f"{path}: [{title}]: {exc}") from None


def _relaxation_table(path: Path, table, title: str) -> CableRelaxation | None:
    """The ``[title]`` table as a :class:`CableRelaxation` (None without one), checked."""
    if table is None:
        return None
    if not isinstance(table, dict):
        raise PlantFileError(f"{path}: [{title}] must be a table ({', '.join(_RELAXATION_KEYS)}), got {table!r}")
    unknown, missing = sorted(set(table) - set(_RELAXATION_KEYS)), [k for k in _RELAXATION_KEYS if k not in table]
    if unknown or missing:
        what = f"unknown key(s) {', '.join(unknown)}" if unknown else f"missing {', '.join(missing)}"
        raise PlantFileError(f"{path}: [{title}]: {what}; it takes {', '.join(_RELAXATION_KEYS)}")
    try:
        CableRelaxation(**table)  # the checks, on the values as written (a boolean is not a number)
    except ValueError as exc:
        raise PlantFileError(f"{path}: [{title}]: {exc}") from None
    return CableRelaxation(*(float(table[k]) for k in _RELAXATION_KEYS))


#: The keys a relaxation's standard errors may have: the fitted stiffnesses (its time is chosen from a grid).
_RELAXATION_ERROR_KEYS = ("fast", "relaxing")


def _number_table(path: Path, table, title: str, keys: Sequence[str], hint: str, lower: float | None = None) -> dict:
    """The ``[title]`` table of numbers under ``keys`` (``hint``: what the message says it holds), checked; each
    value at least ``lower`` when given (NaN passes: an error that could not be estimated)."""
    if not isinstance(table, dict):
        raise PlantFileError(f"{path}: [{title}] must be a table ({hint}), got {table!r}")
    unknown = sorted(set(table) - set(keys))
    if unknown:
        raise PlantFileError(f"{path}: [{title}]: unknown key(s) {', '.join(unknown)}; known: {', '.join(keys)}")
    bound = "" if lower is None else f", {lower:g} or more (or nan)"
    for key, value in table.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (lower is not None and value < lower):
            raise PlantFileError(f"{path}: [{title}]: {key} must be a number{bound}, got {value!r}")
    return {k: float(v) for k, v in table.items()}


def _relaxation_errors(path: Path, table, title: str) -> dict[str, float]:
    """The ``[title]`` table of a relaxation's standard errors (empty without one), checked."""
    if table is None:
        return {}
    return _number_table(path, table, title, _RELAXATION_ERROR_KEYS, "fast, relaxing", lower=0.0)


def _per_day(path: Path, data: dict, name: str) -> dict:
    """``data[name]``, a table per recording day (empty without one), checked to be one."""
    tables = data.get(name, {})
    if not isinstance(tables, dict):
        raise PlantFileError(f"{path}: [{name}] must hold a table per recording day, got {tables!r}")
    return tables


def _numbers(path: Path, values, where: str) -> dict[str, float]:
    """A table of PendulumParameters fields and numbers, checked (the message names the file and the key)."""
    if not isinstance(values, dict):
        raise PlantFileError(f"{path}: {where}must be a table of parameters, got {values!r}")
    known = {f.name for f in fields(PendulumParameters)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise PlantFileError(
            f"{path}: {where}unknown parameter(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}"
        )
    for name, value in values.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise PlantFileError(f"{path}: {where}parameter {name} must be a number, got {value!r}")
    return {k: float(v) for k, v in values.items()}


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
        The parameters, their standard errors, the setups' and provenance.
    """
    lines = [f'format = "{FORMAT}"', "", "[parameters]"]
    lines += [f"{k} = {_toml_value(float(v))}" for k, v in asdict(plant.params).items()]
    if plant.standard_errors:
        lines += ["", "[standard_errors]"]
        lines += [f"{k} = {_toml_value(float(v))}" for k, v in plant.standard_errors.items()]
    for name, tables in (("setups", plant.setups), ("setup_standard_errors", plant.setup_standard_errors)):
        for day, table in tables.items():
            lines += ["", f"[{name}.{_toml_value(str(day))}]"]
            lines += [f"{k} = {_toml_value(float(v))}" for k, v in table.items()]
    if plant.load is not None:
        lines += ["", "[load]"]
        lines += [f"{k} = {_toml_value(float(getattr(plant.load, k)))}" for k in _LOAD_KEYS]
        if plant.load_standard_errors:
            lines += ["", "[load_standard_errors]"]
            lines += [f"{k} = {_toml_value(float(v))}" for k, v in plant.load_standard_errors.items()]
        for day, load in plant.load_setups.items():
            lines += ["", f"[load_setups.{_toml_value(str(day))}]"]
            lines += [f"{k} = {_toml_value(float(getattr(load, k)))}" for k in _LOAD_KEYS]
        for day, table in plant.load_setup_standard_errors.items():
            if table:
                lines += ["", f"[load_setup_standard_errors.{_toml_value(str(day))}]"]
                lines += [f"{k} = {_toml_value(float(v))}" for k, v in table.items()]
    if plant.relaxation is not None:
        relaxation_tables = [
            ("relaxation", "relaxation_standard_errors", plant.relaxation, plant.relaxation_standard_errors)
        ]
        for day, relaxation in plant.relaxation_setups.items():
            errors = plant.relaxation_setup_standard_errors.get(day, {})
            key = _toml_value(str(day))
            relaxation_tables.append(
                (f"relaxation_setups.{key}", f"relaxation_setup_standard_errors.{key}", relaxation, errors)
            )
        for title, errors_title, relaxation, errors in relaxation_tables:
            lines += ["", f"[{title}]"]
            lines += [f"{k} = {_toml_value(float(getattr(relaxation, k)))}" for k in _RELAXATION_KEYS]
            if errors:
                lines += ["", f"[{errors_title}]"]
                lines += [f"{k} = {_toml_value(float(v))}" for k, v in errors.items()]
    if plant.provenance:
        lines += ["", "[provenance]"]
        lines += [f"{k} = {_toml_value(v)}" for k, v in plant.provenance.items()]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
