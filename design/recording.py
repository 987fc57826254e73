"""A rerun recording of a design: predicted vs twin trajectories, closed-loop eigenvalues
(``qube-design --rerun-save``).

Entities, against the timeline ``time`` (seconds from the episode's start):
``episodes/<name>/<channel>/<kind>`` for the channels ``theta``, ``alpha`` (rad) and ``voltage``
(V) and the kinds ``predicted`` (the plant model under the design, from upright, as the design's
cost is predicted), ``twin`` (the twin under the design) and ``twin_training`` (the twin under the
model's training controller, when the model file holds one the loop can run);
``episodes/<name>/theta/target``
the arm's reference. Static: ``eigenvalues/design`` and ``eigenvalues/training`` (the design
plant in closed loop with each controller, as points of the complex plane) beside
``eigenvalues/unit_circle``.

The recording carries a blueprint (:func:`blueprint`): a tab with one column per episode (theta,
alpha, voltage), and a tab of the eigenvalues.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from qube_koopman.core.rrd import RrdFile, import_rerun
from qube_koopman.daq.episode import Episode
from qube_koopman.design.predict import LoopTrajectories

__all__ = ["CHANNELS", "blueprint", "write_recording"]

#: The plotted channels of every episode.
CHANNELS = ("theta", "alpha", "voltage")
#: Series colours: predicted blue, the twin under the design orange, under the training controller grey.
_COLORS = {"predicted": (31, 119, 180), "twin": (255, 140, 0), "twin_training": (170, 170, 170), "target": (0, 0, 0)}


def blueprint(names: list[str]):
    """The layout: a tab of episodes (theta, alpha, voltage of each, one column per episode), a tab of eigenvalues."""
    import rerun.blueprint as rrb

    columns = [
        rrb.Vertical(
            *(
                rrb.TimeSeriesView(origin=f"episodes/{name}/{channel}", name=f"{name}: {channel}")
                for channel in CHANNELS
            ),
            name=name,
        )
        for name in names
    ]
    tabs = rrb.Tabs(
        rrb.Horizontal(*columns, name="predicted vs twin (x: time)"),
        rrb.Spatial2DView(origin="eigenvalues", name="closed-loop eigenvalues and the unit circle"),
    )
    return rrb.Blueprint(tabs, collapse_panels=True)


def _series(rec, path: str, time, values: np.ndarray, kind: str) -> None:
    import rerun as rr

    rec.log(path, rr.SeriesLines(colors=[_COLORS[kind]], names=[kind]), static=True)
    values = np.asarray(values, dtype=float)
    rec.send_columns(
        path,
        indexes=[rr.TimeColumn("time", duration=time[: len(values)])],
        columns=rr.Scalars.columns(scalars=np.where(np.isfinite(values), values, np.nan)),
    )


def _episode_channels(episode: Episode) -> dict[str, np.ndarray]:
    return {"theta": episode.theta, "alpha": episode.alpha, "voltage": episode.plant_input}


def write_recording(
    path: str | Path, predicted: LoopTrajectories, twin: dict[str, list[Episode]], eigenvalues: dict[str, np.ndarray]
) -> Path:
    """Write the first episodes' predicted and twin trajectories, and the eigenvalues, to an .rrd file.

    Parameters
    ----------
    path : str or Path
        The .rrd file to write (replaced when it exists).
    predicted : LoopTrajectories
        The model's prediction of at least as many episodes as ``twin``'s lists hold.
    twin : dict
        Kind (``"twin"``, ``"twin_training"``) to the episodes the twin ran, in the excitation's order.
    eigenvalues : dict
        Kind (``"design"``, ``"training"``) to closed-loop eigenvalues.

    Returns
    -------
    Path
        ``path``.
    """
    n = max((len(episodes) for episodes in twin.values()), default=0)
    names = [f"episode_{i:02d}" for i in range(n)]
    path = Path(path)
    rr = import_rerun()
    rrd = RrdFile(path, "qube-design", blueprint=blueprint(names))  # whole or not at all
    rec = rrd.recording
    time = np.arange(predicted.theta.shape[1]) * predicted.dt
    for i, name in enumerate(names):
        _series(rec, f"episodes/{name}/theta/target", time, predicted.target_theta[i], "target")
        for channel, values in zip(CHANNELS, (predicted.theta, predicted.alpha, predicted.voltage)):
            _series(rec, f"episodes/{name}/{channel}/predicted", time, values[i], "predicted")
        for kind, episodes in twin.items():
            if i < len(episodes):
                for channel, values in _episode_channels(episodes[i]).items():
                    _series(rec, f"episodes/{name}/{channel}/{kind}", time, values, kind)
    circle = np.exp(1j * np.linspace(0, 2 * np.pi, 181))
    rec.log("eigenvalues/unit_circle", rr.LineStrips2D([np.column_stack([circle.real, circle.imag])]), static=True)
    for kind, values in eigenvalues.items():
        rec.log(
            f"eigenvalues/{kind}",
            rr.Points2D(
                np.column_stack([values.real, values.imag]),
                radii=0.005,
                colors=[_COLORS["twin" if kind == "design" else "twin_training"]],
            ),
            static=True,
        )
    rrd.save()
    return path
