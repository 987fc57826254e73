"""What the rig's encoders report: quantized angles, the pendulum's wrapped.

The rig read two encoders of 2048 counts per revolution (24-bit two's complement counters):
``theta = count0 * 2 pi / 2048`` and ``alpha = wrap(count1 * 2 pi / 2048 - pi)``
to ``[-pi, pi)``, the pendulum's counter being zeroed hanging down, so that
``alpha = 0`` is upright. :func:`counts_to_angles` is that conversion (the
serial backend uses it on the bridge's counts) and :func:`angles_to_counts`
its inverse up to quantization (the emulated QUBE uses it); the simulator's
measurements go through the same counts, so every path lands on the same grid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["SensorModel", "ZeroOffsetDistribution", "measure", "counts_to_angles", "angles_to_counts", "COUNTS_PER_REV"]

TWO_PI = 2.0 * math.pi

#: Encoder counts per revolution of the QUBE-Servo 2's encoders.
COUNTS_PER_REV = 2048


@dataclass(frozen=True)
class SensorModel:
    """Encoder resolution and optional angle noise.

    Parameters
    ----------
    counts_per_rev : int or None
        Encoder counts per revolution (2048 on the QUBE-Servo 2); None for
        exact angles.
    noise_std : float
        Standard deviation (rad) of Gaussian noise added to each true angle
        before quantization, so measurements stay on the encoder's grid as
        the real ones do (a dithered count rather than an off-grid value).
    alpha_offset : float
        Encoder zero offset of the pendulum (rad): the measured alpha is the
        true one plus this, before quantization. The rig's counter is zeroed
        wherever the pendulum hung when it was reset, so the measured upright
        is a few counts off the true one, differently each episode (about
        +0.0025 rad, spread 0.001, in the paper's dataset).
    """

    counts_per_rev: int | None = 2048
    noise_std: float = 0.0
    alpha_offset: float = 0.0

    def __post_init__(self) -> None:
        cpr = self.counts_per_rev
        if cpr is not None and (isinstance(cpr, bool) or not isinstance(cpr, (int, np.integer)) or cpr < 2 or cpr % 2):
            raise ValueError(f"counts_per_rev must be an even integer >= 2 or None, got {cpr!r}")
        if not (math.isfinite(self.noise_std) and self.noise_std >= 0):
            raise ValueError(f"noise_std must be a non-negative number of radians, got {self.noise_std!r}")
        if not (math.isfinite(self.alpha_offset) and abs(self.alpha_offset) < math.pi):
            raise ValueError(f"alpha_offset must be an angle in (-pi, pi) rad, got {self.alpha_offset!r}")

    @property
    def resolution(self) -> float:
        """Radians per count (0.0 for exact angles)."""
        return 0.0 if self.counts_per_rev is None else TWO_PI / self.counts_per_rev


@dataclass(frozen=True)
class ZeroOffsetDistribution:
    """Where the pendulum encoder's zero falls, episode by episode.

    Each episode's :attr:`SensorModel.alpha_offset` is drawn from a normal
    distribution; the defaults are the paper's dataset (the mean alpha over an
    episode after its first second: +0.0025 rad, spread about 0.001 rad).

    Parameters
    ----------
    mean, std : float
        Of the offset (rad).
    """

    mean: float = 0.0025
    std: float = 0.001

    def __post_init__(self) -> None:
        if not (math.isfinite(self.mean) and abs(self.mean) < 0.5):
            raise ValueError(f"mean must be a small angle (|mean| < 0.5 rad), got {self.mean!r}")
        if not (math.isfinite(self.std) and 0 <= self.std < 0.5):
            raise ValueError(f"std must be in [0, 0.5) rad, got {self.std!r}")

    def draw(self, rng: np.random.Generator) -> float:
        """One episode's offset (rad)."""
        return float(self.mean + self.std * rng.standard_normal())


def _counts(theta, alpha, counts_per_rev: int, floor: Callable):
    # Nearest count: unbiased around the true angle. The pendulum's counter
    # reads half a turn when upright, as it was zeroed hanging down.
    step = TWO_PI / counts_per_rev
    return floor(theta / step + 0.5), floor(alpha / step + 0.5) + counts_per_rev // 2


def _angles(count0, count1, counts_per_rev: int):
    # Wrapping the integer count keeps alpha exactly on the grid, in [-pi, pi)
    # like the rig's: wrap(c * step - pi) = (c mod N - N/2) * step.
    step = TWO_PI / counts_per_rev
    return count0 * step, (count1 % counts_per_rev - counts_per_rev // 2) * step


def encoder_angles(theta, alpha, counts_per_rev: int | None, floor: Callable):
    """The angles the encoders read for true angles: quantized to ``counts_per_rev`` counts a turn
    (None: not quantized) and alpha wrapped into [-pi, pi); plain arithmetic so floats
    (``floor=math.floor``) and arrays (``np.floor``) share it."""
    if counts_per_rev is None:
        return theta, (alpha + math.pi) % TWO_PI - math.pi
    count0, count1 = _counts(theta, alpha, counts_per_rev, floor)
    return _angles(count0, count1, counts_per_rev)


def angles_to_counts(theta: float, alpha: float, counts_per_rev: int = COUNTS_PER_REV) -> tuple[int, int]:
    """Raw encoder counters for true angles: what a QUBE's counters read.

    Parameters
    ----------
    theta, alpha : float
        True motor and pendulum angles (rad, alpha = 0 upright, not wrapped).
    counts_per_rev : int
        Encoder resolution.

    Returns
    -------
    (int, int)
        Nearest counts; the pendulum's counter is zero hanging down (so it
        reads ``counts_per_rev / 2`` upright). Not wrapped: the hardware's
        24-bit counters keep counting over turns.
    """
    return _counts(theta, alpha, counts_per_rev, math.floor)


def counts_to_angles(count0: int, count1: int, counts_per_rev: int = COUNTS_PER_REV) -> tuple[float, float]:
    """The rig's angles from its raw encoder counters, as the C program that ran it computed them.

    ``theta = count0 * 2 pi / N`` and ``alpha = wrap(count1 * 2 pi / N - pi)``
    in ``[-pi, pi)``: the pendulum's counter was zeroed hanging down, so
    ``alpha = 0`` is upright. For the counts of :func:`angles_to_counts` the
    result equals what :class:`SensorModel` reports for the same angles.

    Examples
    --------
    >>> counts_to_angles(0, 1024)
    (0.0, 0.0)
    >>> counts_to_angles(512, 0)[1] == -math.pi
    True
    """
    return _angles(count0, count1, counts_per_rev)


def measure(state, sensor: SensorModel = SensorModel(), rng: np.random.Generator | None = None) -> np.ndarray:
    """Encoder readings for states.

    Parameters
    ----------
    state : array_like of shape (..., 4) or (..., 2)
        States (only theta and alpha are used).
    sensor : SensorModel
    rng : numpy.random.Generator, optional
        Needed when ``sensor.noise_std > 0``.

    Returns
    -------
    ndarray of shape (..., 2)
        Measured theta and alpha (rad), alpha in ``[-pi, pi)``.
    """
    x = np.asarray(state, dtype=float)
    if x.ndim == 0 or x.shape[-1] not in (2, 4):
        raise ValueError(f"state must have shape (..., 4) or (..., 2), got {x.shape}")
    theta, alpha = x[..., 0], x[..., 1] + sensor.alpha_offset
    if sensor.noise_std > 0:
        if rng is None:
            raise ValueError("a noisy sensor needs rng (a numpy Generator) for reproducible noise")
        theta = theta + rng.normal(0.0, sensor.noise_std, theta.shape)
        alpha = alpha + rng.normal(0.0, sensor.noise_std, alpha.shape)
    return np.stack(encoder_angles(theta, alpha, sensor.counts_per_rev, np.floor), axis=-1)
