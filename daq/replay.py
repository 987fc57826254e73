"""Replaying logged experiments: the same excitations (seeds, settings) as the given logs.

``qube-run --replay LOGS...`` runs, for each log, the rig's excitation
regenerated from the log's seeds and settings (bit-exact: the generator is
deterministic), for the log's duration, under the log's own controller or
the one given. Logs imported from the paper's CSV files carry no settings;
the rig's (``ExcitationSettings()``: 10 000 samples, active 2000..8000) are
used for them, which is what the rig ran.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Callable, Sequence

from qube_koopman.core.controller_file import ControllerInfo
from qube_koopman.daq.excitation import ExcitationSettings
from qube_koopman.daq.log.names import SEED_SIGNALS
from qube_koopman.daq.loop import EpisodePlan
from qube_koopman.daq.session import plan_episodes

__all__ = ["replay_plans"]


def _settings(meta, path: Path) -> ExcitationSettings:
    recorded = meta.excitation.get("settings")
    try:
        return ExcitationSettings() if recorded is None else ExcitationSettings.from_dict(recorded)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: its excitation settings cannot be used ({exc})") from None


def replay_plans(
    paths: Sequence[str | Path],
    controller: ControllerInfo | None = None,
    source: str = "qube-run --replay",
    twins: Callable[[list], list] | None = None,
    loads: Callable[[list], list] | None = None,
    relaxations: Callable[[list], list] | None = None,
) -> list[EpisodePlan]:
    """One plan per log: its excitation regenerated, under ``controller`` or the log's own.

    ``twins`` maps the logs' start times to the pendulum each replays on (a plant file's
    :meth:`~qube_koopman.sim.pendulum.params_file.PlantFile.params_for_logs`: each log's
    recording day's cables and its session's delay), set as the plans' ``plant``; None leaves the
    backend's. ``loads`` likewise maps them to each replay's random load on the arm (a plant file's
    :meth:`~qube_koopman.sim.pendulum.params_file.PlantFile.loads_for_logs`: each log's recording
    day's load), set as the plans' ``load``, and ``relaxations`` to each replay's cables' relaxation
    (:meth:`~qube_koopman.sim.pendulum.params_file.PlantFile.relaxations_for_logs`), the plans' ``relaxation``.

    Raises
    ------
    ValueError
        Naming the file: unreadable, without excitation seeds, with unusable settings, or recorded
        under a controller beyond LTI (an MPC) when no ``controller`` is given.
    """
    from qube_koopman.daq.log import read_episode_metadata

    plans, starts = [], []
    for i, raw in enumerate(paths):
        path = Path(raw)
        try:
            meta = read_episode_metadata(path)
        except OSError as exc:
            raise ValueError(f"{path}: cannot read the episode log ({exc.strerror or exc})") from None
        except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's to fix
            # the reader's messages start with the path: named once
            raise ValueError(f"{path}: cannot read the episode log ({str(exc).removeprefix(f'{path}: ')})") from None
        seeds = meta.excitation.get("seeds", {})
        if not all(isinstance(seeds.get(k), int) for k in SEED_SIGNALS):
            raise ValueError(f"{path}: the log records no excitation seeds; it cannot be replayed")
        if not all(-(2**63) <= seeds[k] < 2**63 for k in SEED_SIGNALS):
            raise ValueError(
                f"{path}: excitation seeds {[seeds[k] for k in SEED_SIGNALS]} are not 64-bit integers "
                "(qube-run records such seeds only); it cannot be replayed"
            )
        if controller is None and meta.controller.tick_fields:
            # a log keeps a controller beyond LTI's settings, not all it runs on (its model's matrices)
            raise ValueError(
                f"{path}: recorded under a controller of kind {meta.controller.kind!r}, which a log does not hold "
                "whole; give its controller file with --controller"
            )
        (plan,) = plan_episodes(
            controller or meta.controller,
            [tuple(seeds[k] for k in SEED_SIGNALS)],
            _settings(meta, path),
            source=source,
            extra={"command": "qube-run --replay", "replay_of": path.name},
        )
        plans.append(replace(plan, index=i))
        starts.append(meta.start_time)
    if twins is not None:
        plans = [replace(plan, plant=twin) for plan, twin in zip(plans, twins(starts))]
    if loads is not None:
        plans = [replace(plan, load=load) for plan, load in zip(plans, loads(starts))]
    if relaxations is not None:
        plans = [replace(plan, relaxation=r) for plan, r in zip(plans, relaxations(starts))]
    return plans
