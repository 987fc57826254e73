"""Each log's recording session, and the command delay a plant file calibrated per session gives it.

``qube-calibrate --setups cables-and-delay`` fits the host's command delay once per recording
session (logs started less than 10 minutes apart). :func:`session_delays` reads such a plant
file and gives each log the delay of the session it was recorded in (logs reach a session as
the twin's replay finds them: :meth:`~qube_koopman.sim.pendulum.params_file.PlantFile.params_for_logs`),
so that a plant identified from several sessions' logs sees each loop as it ran
(:func:`~qube_koopman.identify.estimators.structure.with_command_delay`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["order_neighbours", "session_delays", "session_neighbours"]


def session_delays(logs: Sequence[str | Path], plant: str | Path) -> np.ndarray:
    """Each log's command delay (seconds) in a plant file with a delay per recording session.

    Parameters
    ----------
    logs : sequence of str or Path
        Episode logs (their start times place them in sessions).
    plant : str or Path
        A plant file written by ``qube-calibrate --setups cables-and-delay``. A log of no session
        the file knows gets the file's shared delay.

    Returns
    -------
    ndarray of shape (len(logs),)

    Raises
    ------
    ValueError
        Naming the file: not a plant file, or one without a delay per session.
    """
    from qube_koopman.sim.pendulum.params_file import load_plant

    plant_file = load_plant(plant)
    if not any("delay" in values for values in plant_file.setups.values()):
        raise ValueError(
            f"{plant}: no command delay per recording session (write one with qube-calibrate --setups cables-and-delay)"
        )
    return np.array([params.delay for params in plant_file.params_for_logs(_start_times(logs))])


def _start_times(logs: Sequence[str | Path]) -> list[str | None]:
    """The logs' start times as logged (their metadata only)."""
    from qube_koopman.daq.log import read_episode_metadata  # lazily: mcap

    return [read_episode_metadata(Path(log)).start_time for log in logs]


def session_neighbours(logs: Sequence[str | Path], k: int) -> list[list[int]]:
    """Per log, up to ``k`` other logs of its recording session, the nearest in recording order first.

    Sessions are logs started within ten minutes of each other, as the twin's calibration per
    session finds them (:func:`~qube_koopman.sim.pendulum.params_file.recording_sessions`). A log
    without a readable start time has no session and no neighbours. See :func:`order_neighbours`.

    Parameters
    ----------
    logs : sequence of str or Path
        Episode logs.
    k : int
        Neighbours at most.

    Returns
    -------
    list of list of int
        Indices into ``logs``.
    """
    return order_neighbours(_start_times(logs), [Path(log).name for log in logs], k)


def order_neighbours(starts: Sequence[str | None], names: Sequence[str], k: int) -> list[list[int]]:
    """Per log, up to ``k`` other logs of its session, the nearest in recording order first.

    The logs of a session are ordered by their start times (ties by the start time as logged,
    then by name) and each log's neighbours are the ones recorded just before and after it: at
    equal distance in that order the earlier first, so ``k = 4`` takes two on each side where the
    session has them. The order, not the seconds between starts, decides: the twin's episodes run
    in parallel start within seconds of each other in an order ``qube-run`` keeps, and a choice by
    seconds changed with the machine's load from one recording of the same episodes to the next.

    Parameters
    ----------
    starts : sequence of str or None
        The logs' start times as logged (ISO 8601).
    names : sequence of str
        The logs' names (the last tie-break).
    k : int
        Neighbours at most.

    Returns
    -------
    list of list of int
        Indices into ``starts``.
    """
    from qube_koopman.sim.pendulum.params_file import recording_sessions, recording_start

    labels = recording_sessions(starts)
    started = [recording_start(t) for t in starts]  # None exactly where the label is "unknown"
    known = [j for j in range(len(starts)) if started[j] is not None]
    rank = {j: r for r, j in enumerate(sorted(known, key=lambda j: (started[j], str(starts[j]), names[j], j)))}
    return [
        sorted(
            (j for j in known if j != i and labels[j] == label),
            key=lambda j: (abs(rank[j] - rank[i]), rank[j]),
        )[:k]
        if started[i] is not None
        else []
        for i, label in enumerate(labels)
    ]
