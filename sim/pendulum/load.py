"""A random load on the arm: a slow torque at the motor that no logged signal explains.

Run backwards on the rig's logs, the arm's equation leaves, besides the cables' pull, a slow
torque that wanders from episode to episode and within each (the cables' bending and slipping,
the dry friction's drift): the real loop's voltage below 0.3 Hz carries it, and a twin without
it replays that band at about half the real standard deviation. :class:`RandomLoad` is that
torque as a random process with the statistics ``qube-calibrate`` estimates from the logs (the
plant file's ``[load]`` table, :mod:`~qube_koopman.sim.pendulum.params_file`):

- a first-order (Ornstein-Uhlenbeck) process, ``dd = -d / tau dt + q dW``: stationary standard
  deviation ``q sqrt(tau / 2)``, its spectrum flat below ``1 / (2 pi tau)`` Hz and falling as
  ``1 / f^2`` above;
- a random walk (integrated white noise, ``tau`` infinite), ``dd = q dW``, starting at zero.

Units: the load ``d`` is in volts at the motor, past the amplifier's dead zone: the torque
``km d / Rm`` (N m) on the arm, what ``d`` volts more at the motor would give. The simulations
add it in the arm's equation, where the cables' pull and the friction act, and hold each
sample's value over the sample (the process is sampled exactly at the sample period).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["RandomLoad", "LoadStream"]

#: The largest load parameters taken (V/sqrt(s), s): past them the load is not a load any more.
_MAX_DIFFUSION = 1e3
_MAX_TIME_CONSTANT = 1e9
_BLOCK = 4096


@dataclass(frozen=True)
class RandomLoad:
    """A random torque on the arm, in volts at the motor (the torque ``km / Rm`` times it).

    Parameters
    ----------
    diffusion : float
        ``q`` (V / sqrt(s)): the standard deviation of the load's change over one second, were it
        not pulled back (its increments' variance grows by ``q^2`` per second). 0: no load.
    time_constant : float
        ``tau`` (s) over which the load forgets itself (first-order process); ``math.inf`` for a
        random walk.
    """

    diffusion: float
    time_constant: float = math.inf

    def __post_init__(self) -> None:
        for name in ("diffusion", "time_constant"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
                raise ValueError(f"load {name} must be a number, got {value!r}")
        if not (0 <= self.diffusion <= _MAX_DIFFUSION):
            raise ValueError(f"load diffusion must be between 0 and {_MAX_DIFFUSION:g} V/sqrt(s), got {self.diffusion}")
        if not (
            self.time_constant > 0 and (self.time_constant <= _MAX_TIME_CONSTANT or self.time_constant == math.inf)
        ):
            raise ValueError(
                f"load time_constant must be positive seconds (at most {_MAX_TIME_CONSTANT:g}, or inf for a "
                f"random walk), got {self.time_constant}"
            )

    @property
    def kind(self) -> str:
        """``"random-walk"`` or ``"first-order"``."""
        return "random-walk" if math.isinf(self.time_constant) else "first-order"

    @property
    def std(self) -> float:
        """Stationary standard deviation (V) of a first-order load, ``q sqrt(tau / 2)``; inf for a random walk."""
        return self.diffusion * math.sqrt(self.time_constant / 2.0)

    def coefficients(self, dt: float) -> tuple[float, float, float]:
        """``(a, b, s0)``: ``d[k+1] = a d[k] + b w[k]`` with ``w`` standard normal, sampled exactly at ``dt``;
        ``s0`` the standard deviation of ``d[0]`` (stationary; 0 for a random walk)."""
        if math.isinf(self.time_constant):
            return 1.0, self.diffusion * math.sqrt(dt), 0.0
        a = math.exp(-dt / self.time_constant)
        return a, self.std * math.sqrt(-math.expm1(-2.0 * dt / self.time_constant)), self.std

    def sample(self, n_steps: int, dt: float, rng: np.random.Generator, batch: tuple[int, ...] = ()) -> np.ndarray:
        """``n_steps`` samples of independent loads, one per element of ``batch``: shape (n_steps, *batch).

        The same generator state gives the same loads (:class:`LoadStream` draws the same numbers
        one sample at a time).
        """
        a, b, s0 = self.coefficients(dt)
        out = np.empty((n_steps, *batch))
        if n_steps == 0:
            return out
        d = s0 * rng.standard_normal(batch)
        w = rng.standard_normal((n_steps - 1, *batch)) * b
        out[0] = d
        for k in range(n_steps - 1):
            d = a * d + w[k]
            out[k + 1] = d
        return out

    def to_dict(self) -> dict:
        """The load's settings as a log's metadata records them."""
        return {"kind": self.kind, "diffusion": self.diffusion, "time_constant": self.time_constant}


class LoadStream:
    """One load's samples, one at a time (a per-tick simulator): :meth:`RandomLoad.sample`'s numbers.

    Parameters
    ----------
    load : RandomLoad
    dt : float
        Sample period (s).
    seed : int
        The load's seed (a log records it): the same seed gives the same load.
    """

    def __init__(self, load: RandomLoad, dt: float, seed: int) -> None:
        self.load = load
        self.seed = int(seed)
        self._rng = np.random.default_rng(self.seed)
        self._a, self._b, s0 = load.coefficients(dt)
        self._value = float(s0 * self._rng.standard_normal())
        self._noise: list[float] = []
        self._at = 0

    def set_period(self, dt: float) -> None:
        """Sample at ``dt`` from the next sample on, keeping the current value."""
        self._a, self._b, _ = self.load.coefficients(dt)
        self._noise, self._at = [], 0

    @property
    def value(self) -> float:
        """The load (V) over the current sample."""
        return self._value

    def advance(self) -> float:
        """Move on to the next sample; returns its load."""
        if self._at == len(self._noise):
            self._noise = (self._rng.standard_normal(_BLOCK) * self._b).tolist()
            self._at = 0
        self._value = self._a * self._value + self._noise[self._at]
        self._at += 1
        return self._value
