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
    floor : float
        A faster part beside it (V^2/Hz, one-sided): its power spectral density, flat up to
        ``floor_corner``, falling as ``1 / f^2`` above (a second first-order process, of time
        constant ``1 / (2 pi floor_corner)``). Run backwards on the rig's logs, the arm's equation
        leaves such a flat torque below 1 Hz, 50 times what it leaves on the twin's replays of the
        same logs; above 1 Hz the logs cannot tell it from the twin's own small errors. 0: none.
    floor_corner : float
        Where the faster part's spectrum bends down (Hz).
    """

    diffusion: float
    time_constant: float = math.inf
    floor: float = 0.0
    floor_corner: float = 1.0

    def __post_init__(self) -> None:
        for name in ("diffusion", "time_constant", "floor", "floor_corner"):
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
        if not (0 <= self.floor <= _MAX_DIFFUSION):
            raise ValueError(f"load floor must be between 0 and {_MAX_DIFFUSION:g} V^2/Hz, got {self.floor}")
        if not (0 < self.floor_corner <= _MAX_DIFFUSION):
            raise ValueError(
                f"load floor_corner must be positive Hz (at most {_MAX_DIFFUSION:g}), got {self.floor_corner}"
            )

    @property
    def kind(self) -> str:
        """``"random-walk"`` or ``"first-order"``."""
        return "random-walk" if math.isinf(self.time_constant) else "first-order"

    @property
    def std(self) -> float:
        """Stationary standard deviation (V) of a first-order load, ``q sqrt(tau / 2)``; inf for a random walk."""
        return self.diffusion * math.sqrt(self.time_constant / 2.0)

    @property
    def floor_time_constant(self) -> float:
        """The faster part's time constant (s), ``1 / (2 pi floor_corner)``."""
        return 1.0 / (2.0 * math.pi * self.floor_corner)

    def coefficients(self, dt: float) -> tuple[float, float, float]:
        """``(a, b, s0)``: ``d[k+1] = a d[k] + b w[k]`` with ``w`` standard normal, sampled exactly at ``dt``;
        ``s0`` the standard deviation of ``d[0]`` (stationary; 0 for a random walk). The slow part's."""
        return _first_order(self.diffusion, self.time_constant, dt)

    def floor_coefficients(self, dt: float) -> tuple[float, float, float]:
        """:meth:`coefficients` of the faster part (``floor``): its spectrum's level ``2 q^2 tau^2`` is the floor."""
        tau = self.floor_time_constant
        return _first_order(math.sqrt(self.floor / 2.0) / tau, tau, dt)

    def sample(self, n_steps: int, dt: float, rng: np.random.Generator, batch: tuple[int, ...] = ()) -> np.ndarray:
        """``n_steps`` samples of independent loads, one per element of ``batch``: shape ``(n_steps, *batch)``.

        The same generator state gives the same loads (:class:`LoadStream` draws the same numbers
        one sample at a time).
        """
        out = np.empty((n_steps, *batch))
        if n_steps == 0:
            return out
        parts = [self.coefficients(dt)] + ([self.floor_coefficients(dt)] if self.floor else [])
        a = np.array([c[0] for c in parts])
        d = np.stack([c[2] * rng.standard_normal(batch) for c in parts], axis=-1)
        w = rng.standard_normal((n_steps - 1, *batch, len(parts))) * np.array([c[1] for c in parts])
        out[0] = d.sum(axis=-1)
        for k in range(n_steps - 1):
            d = a * d + w[k]
            out[k + 1] = d.sum(axis=-1)
        return out

    def to_dict(self) -> dict:
        """The load's settings as a log's metadata records them."""
        return {
            "kind": self.kind,
            "diffusion": self.diffusion,
            "time_constant": self.time_constant,
            "floor": self.floor,
            "floor_corner": self.floor_corner,
        }


def _first_order(q: float, tau: float, dt: float) -> tuple[float, float, float]:
    """``(a, b, s0)`` of ``dd = -d / tau dt + q dW`` sampled exactly at ``dt`` (a random walk for infinite ``tau``)."""
    if math.isinf(tau):
        return 1.0, q * math.sqrt(dt), 0.0
    std = q * math.sqrt(tau / 2.0)
    return math.exp(-dt / tau), std * math.sqrt(-math.expm1(-2.0 * dt / tau)), std


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
        self._fast = bool(load.floor)
        self._a, self._b, s0 = load.coefficients(dt)
        self._slow = float(s0 * self._rng.standard_normal())
        self._af, self._bf, sf = load.floor_coefficients(dt) if self._fast else (0.0, 0.0, 0.0)
        self._quick = float(sf * self._rng.standard_normal()) if self._fast else 0.0
        self._value = self._slow + self._quick if self._fast else self._slow
        self._noise: list = []
        self._at = 0

    def set_period(self, dt: float) -> None:
        """Sample at ``dt`` from the next sample on, keeping the current value."""
        self._a, self._b, _ = self.load.coefficients(dt)
        if self._fast:
            self._af, self._bf, _ = self.load.floor_coefficients(dt)
        self._noise, self._at = [], 0

    @property
    def value(self) -> float:
        """The load (V) over the current sample."""
        return self._value

    def advance(self) -> float:
        """Move on to the next sample; returns its load."""
        if self._at == len(self._noise):
            shape = (_BLOCK, 2) if self._fast else (_BLOCK, 1)
            self._noise = self._rng.standard_normal(shape).tolist()
            self._at = 0
        w = self._noise[self._at]
        self._at += 1
        self._slow = self._a * self._slow + self._b * w[0]
        if not self._fast:
            self._value = self._slow
            return self._value
        self._quick = self._af * self._quick + self._bf * w[1]
        self._value = self._slow + self._quick
        return self._value
