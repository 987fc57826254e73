"""A controller file checked on the twin before it runs: ``qube-run --controller FILE``.

The controller is closed around the twin's linearization at upright
(:func:`~qube_koopman.sim.pendulum.closed_loop.linear_loop_radius`); a spectral radius above 1 means the loop
diverges from upright. On the rig (the serial backend) such a controller is refused unless forced, since the
safety supervisor stops a diverging episode only after the pendulum has left (``--run-unstable`` runs it
anyway); on the simulator it is a warning (the simulator is where one tries such a controller). Only linear
controllers are judged: PD gains and state-space files (a feedforward input left out: it is exogenous, and the
loop's stability does not depend on it); a registered kind beyond LTI (the MPC) is not.
"""

from __future__ import annotations

from qube_koopman.core.command import CliError
from qube_koopman.core.controller_file import STATE_SPACE_KIND, ControllerInfo
from qube_koopman.core.lti import DiscreteStateSpace
from qube_koopman.sim.pendulum.closed_loop import linear_loop_radius
from qube_koopman.sim.pendulum.physics import PendulumParameters

__all__ = ["RUN_UNSTABLE_OPTION", "check_controller_on_twin", "check_controller_file_on_twin", "judged_system"]

#: The qube-run option that runs on the rig a controller the twin's check refuses (``--force`` replaces files).
RUN_UNSTABLE_OPTION = "--run-unstable"


def check_controller_on_twin(
    controller: DiscreteStateSpace,
    name: str,
    backend: str,
    run_unstable: bool = False,
    params: PendulumParameters | None = None,
) -> str | None:
    """Check ``controller`` on the twin's linearized loop before it runs.

    Parameters
    ----------
    controller : DiscreteStateSpace
        The controller the episodes will run.
    name : str
        Its file, first in the message.
    backend : str
        ``"serial"`` (the rig: refused) or ``"sim"`` (a warning).
    run_unstable : bool
        Run it on the rig anyway (``--run-unstable``): a warning instead of the refusal.
    params : PendulumParameters, optional
        The twin (the calibrated one by default; on the simulator, the plant it runs).

    Returns
    -------
    str or None
        The warning to print, None when the loop is stable.

    Raises
    ------
    CliError
        On the rig without ``run_unstable`` when the loop diverges (exit 2).
    """
    radius = linear_loop_radius(controller, params)
    if radius <= 1.0:
        return None
    problem = (
        f"{name}: the controller destabilises the twin's loop linearized at upright (spectral radius {radius:.4f} > 1)"
    )
    if backend == "serial" and not run_unstable:
        raise CliError(f"{problem}: refused on the rig; {RUN_UNSTABLE_OPTION} runs it anyway")
    return problem + (f"; run on the rig as {RUN_UNSTABLE_OPTION} asks" if backend == "serial" else "")


def judged_system(controller: ControllerInfo) -> DiscreteStateSpace | None:
    """The linear controller of the tracking errors the check judges, or None for a kind it cannot judge.

    Parameters
    ----------
    controller : ControllerInfo
        As :func:`~qube_koopman.core.controller_file.load_controller` gives it.

    Returns
    -------
    DiscreteStateSpace or None
        PD gains' system, or a state-space file's with its feedforward column (if any) left out; None for a
        registered kind beyond LTI (``runtime`` set, such as the MPC), whose loop is not its ``system``'s.
    """
    if controller.runtime is not None or controller.kind not in ("pd", STATE_SPACE_KIND):
        return None
    system = controller.system
    if system.n_inputs == 3:  # e_theta, e_alpha, feedforward: the feedforward is outside the loop
        system = DiscreteStateSpace(system.A, system.B[:, :2], system.C, system.D[:, :2], system.dt)
    return system


def check_controller_file_on_twin(
    controller: ControllerInfo,
    name: str,
    backend: str,
    run_unstable: bool = False,
    params: PendulumParameters | None = None,
) -> str | None:
    """:func:`check_controller_on_twin` for a loaded controller file; None, silently, for a kind it cannot judge.

    Parameters
    ----------
    controller : ControllerInfo
        The loaded controller file.
    name, backend, run_unstable, params
        As for :func:`check_controller_on_twin`.

    Returns
    -------
    str or None
        The warning to print, None when the loop is stable or the kind is not judged.

    Raises
    ------
    CliError
        As :func:`check_controller_on_twin`.
    """
    system = judged_system(controller)
    if system is None:
        return None
    return check_controller_on_twin(system, name, backend, run_unstable, params)
