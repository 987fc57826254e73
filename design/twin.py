"""The first episodes of ``qube-run --seed S`` on the twin, held in memory: what ``qube-design --rerun-save`` shows.

:func:`run_on_twin` runs a controller file (or the rig's PD) on the default simulated pendulum
with the excitations, start perturbations, encoder zeros and sensor noise that ``qube-run
--seed S --controller FILE`` gives its first episodes, and returns them as
:class:`~daq.episode.Episode` objects without writing logs.
"""

from __future__ import annotations

from pathlib import Path

from qube_koopman.daq.backends import SimBackend
from qube_koopman.daq.episode import Episode
from qube_koopman.core.controller_file import ControllerInfo
from qube_koopman.daq.session import excitation_settings, plan_episodes, run_episodes, run_seeds
from qube_koopman.core.controller_file import load_controller
from qube_koopman.daq.sinks import MemorySink

__all__ = ["run_on_twin"]


def run_on_twin(
    controller: ControllerInfo | str | Path | None,
    seed: int,
    n_episodes: int,
    of: int | None = None,
    duration: float = 20.0,
) -> list[Episode]:
    """Run the first ``n_episodes`` of ``qube-run --seed seed --episodes of --duration duration`` on the twin.

    Parameters
    ----------
    controller : ControllerInfo, str, Path or None
        A controller, or a controller file (core/CONTROLLER_FORMAT.md); None for the rig's PD.
    seed : int
        The run's seed.
    n_episodes : int
        Episodes run.
    of : int, optional
        Episodes in the run they are the first of (``n_episodes`` when not given): the run's seed
        gives the twin's noise, start perturbations and encoder zeros after all its excitations.
    duration : float
        Seconds per episode.

    Returns
    -------
    list of Episode
        One per episode run, in order (an episode the safety supervisor stopped is shorter,
        its status says why).
    """
    seeds, backend_seed = run_seeds(seed, max(n_episodes, of or 0))
    if not isinstance(controller, ControllerInfo):
        controller = load_controller(controller)
    plans = plan_episodes(
        controller,
        seeds[:n_episodes],
        excitation_settings(duration),
        source=f"qube-design --rerun-save, as qube-run seed {seed}",
    )
    sink = MemorySink()
    backend = SimBackend(seed=backend_seed)
    try:
        run_episodes(backend, plans, [sink])
    finally:
        backend.close()
    return [kept.episode() for kept in sink.episodes]
