"""A controller file checked on the twin before it runs: ``qube-run --controller FILE``.

The controller is closed around the twin's linearization at upright
(:func:`~qube_koopman.sim.pendulum.closed_loop.linear_loop_radius`); a spectral radius above 1 means the loop
diverges from upright. On the rig (the serial backend) such a controller is refused unless forced, since the
safety supervisor stops a diverging episode only after the pendulum has left; on the simulator it is a
warning (the simulator is where one tries such a controller).
"""

from __future__ import annotations

from qube_koopman.core.command import CliError
from qube_koopman.core.lti import DiscreteStateSpace
from qube_koopman.sim.pendulum.closed_loop import linear_loop_radius
from qube_koopman.sim.pendulum.model import PendulumParameters

__all__ = ["check_controller_on_twin"]


def check_controller_on_twin(
    controller: DiscreteStateSpace,
    name: str,
    backend: str,
    force: bool = False,
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
    force : bool
        Run it on the rig anyway (``--force``): a warning instead of the refusal.
    params : PendulumParameters, optional
        The twin (the calibrated one by default; on the simulator, the plant it runs).

    Returns
    -------
    str or None
        The warning to print, None when the loop is stable.

    Raises
    ------
    CliError
        On the rig without ``force`` when the loop diverges (exit 2).
    """
    radius = linear_loop_radius(controller, params)
    if radius <= 1.0:
        return None
    problem = (
        f"{name}: the controller destabilises the twin's loop linearized at upright (spectral radius {radius:.4f} > 1)"
    )
    if backend == "serial" and not force:
        raise CliError(f"{problem}: refused on the rig; --force runs it anyway")
    return problem + ("; run on the rig as --force asks" if backend == "serial" else "")
