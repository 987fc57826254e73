"""The arm cables' relaxation: the part of the slow load on the arm that the arm's own motion drives.

Run backwards on the soft controller's logs, the arm's equation leaves a slow torque (the random
load, :mod:`~qube_koopman.sim.pendulum.load`) of which more than half follows the arm's reference:
it is not a disturbance from outside the loop but a torque the arm's motion makes, lagging it by
about a second, as a cable bundle that creeps would. :class:`CableRelaxation` is that torque, beyond
the twin's cable spring (``Kr``, its softening), as a spring with a relaxing (Maxwell) element:

    d = -fast theta + relaxing x,        x' = (theta - x) / time_constant

``x`` is the arm's angle as the relaxing element remembers it (its first-order lag). Against motion
faster than ``time_constant`` the cables are ``fast`` stiffer than the twin's spring (V/rad); held
still, ``fast - relaxing`` stiffer (negative: softer), the difference relaxing over
``time_constant`` seconds. Units as the load's: volts at the motor past the dead zone, the torque
``km d / Rm`` on the arm. The simulations hold ``theta`` over each sample (the element relaxes over a
second, the sample is 2 ms) and update ``x`` exactly for that: ``x <- theta + (x - theta) exp(-dt /
time_constant)``, starting relaxed (``x = theta``).

``qube-calibrate --load --relaxation`` estimates it per recording day from the logs' reconstructed loads
(:func:`~qube_koopman.identify.calibrate.load_fit.fit_relaxation`), and the random load from what
it leaves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["CableRelaxation", "lagged", "relaxation_torque", "relaxed"]


@dataclass(frozen=True)
class CableRelaxation:
    """The cables' torque beyond the twin's spring, with a relaxing part (V at the motor).

    Parameters
    ----------
    fast : float
        Stiffness beyond the twin's cable spring against fast motion (V/rad; negative: softer).
    relaxing : float
        The part of ``fast`` that relaxes (V/rad, at least 0: a relaxing element only gives way).
    time_constant : float
        Seconds over which it relaxes (positive, finite).
    """

    fast: float
    relaxing: float
    time_constant: float

    def __post_init__(self) -> None:
        for name in ("fast", "relaxing", "time_constant"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"relaxation {name} must be a finite number, got {value!r}")
        if self.relaxing < 0:
            raise ValueError(f"relaxation relaxing must be at least 0 (it only gives way), got {self.relaxing!r}")
        if not self.time_constant > 0:
            raise ValueError(f"relaxation time_constant must be positive, got {self.time_constant!r}")

    def decay(self, dt: float) -> float:
        """How much of ``x``'s lag behind the arm is left after a sample of ``dt`` seconds."""
        return math.exp(-dt / self.time_constant)

    def torque(self, theta, x):
        """The torque (V at the motor) at arm angle ``theta`` with the element at ``x`` (floats or arrays)."""
        return relaxation_torque(self.fast, self.relaxing, theta, x)

    def remembered(self, theta: np.ndarray, dt: float) -> np.ndarray:
        """``x`` at each sample of arm angles (along the first axis) held over each sample, starting relaxed:
        the state the simulations use at that sample (before its update)."""
        return lagged(theta, self.time_constant, dt)

    def torque_of(self, theta: np.ndarray, dt: float) -> np.ndarray:
        """The torque (V at the motor) over each sample of a logged arm angle, the element starting relaxed:
        what the twin's relaxation applies along that motion. ``qube-calibrate --relaxation``'s shooting
        fit simulates its 0.25 s segments with it as a known load (over a segment the arm the twin
        predicts stays within a few milliradians of the logged one)."""
        theta = np.asarray(theta, dtype=float)
        return self.torque(theta, self.remembered(theta, dt))

    def then(self, x, theta, dt: float):
        """``x`` after a sample of ``dt`` seconds with the arm held at ``theta``."""
        return relaxed(x, theta, self.decay(dt))


def relaxation_torque(fast, relaxing, theta, x):
    """:class:`CableRelaxation`'s torque from its stiffnesses (floats, or arrays of one per episode)."""
    return relaxing * x - fast * theta


def relaxed(x, theta, decay):
    """The element's ``x`` after a sample with the arm held at ``theta``, ``decay`` of its lag left (floats, arrays)."""
    return theta + (x - theta) * decay


def lagged(values: np.ndarray, time_constant: float, dt: float) -> np.ndarray:
    """A first-order lag of ``values`` (along the first axis), each held over its sample, starting at the first:
    the relaxing element's ``x`` at each sample (:meth:`CableRelaxation.remembered`), and any such low pass."""
    values = np.asarray(values, dtype=float)
    x = np.empty_like(values)
    if len(values) == 0:
        return x
    from scipy.signal import lfilter

    # x[k+1] = r x[k] + (1 - r) v[k], x[0] = v[0]: one recursion, as the simulations step it.
    r = math.exp(-dt / time_constant)
    x[0] = values[0]
    if len(values) > 1:
        x[1:] = lfilter([1.0 - r], [1.0, -r], values[:-1], axis=0, zi=r * values[:1])[0]
    return x
