"""What the rig's encoders report: quantized angles, the pendulum's wrapped.

The rig read two 2048-count encoders (FACTS sections 3 and 5):
``theta = count0 * 2 pi / 2048`` and ``alpha = wrap(count1 * 2 pi / 2048)``
to ``[-pi, pi)``, with the pendulum's zero count set upright.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["SensorModel", "measure"]

TWO_PI = 2.0 * math.pi


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
    """

    counts_per_rev: int | None = 2048
    noise_std: float = 0.0

    def __post_init__(self) -> None:
        cpr = self.counts_per_rev
        if cpr is not None and (isinstance(cpr, bool) or not isinstance(cpr, (int, np.integer))
                                or cpr < 2 or cpr % 2):
            raise ValueError(f"counts_per_rev must be an even integer >= 2 or None, got {cpr!r}")
        if not (math.isfinite(self.noise_std) and self.noise_std >= 0):
            raise ValueError(f"noise_std must be a non-negative number of radians, got {self.noise_std!r}")

    @property
    def resolution(self) -> float:
        """Radians per count (0.0 for exact angles)."""
        return 0.0 if self.counts_per_rev is None else TWO_PI / self.counts_per_rev


def _encode(theta, alpha, counts_per_rev: int | None, floor: Callable):
    """Quantize and wrap; plain arithmetic so floats and arrays share it."""
    if counts_per_rev is None:
        return theta, (alpha + math.pi) % TWO_PI - math.pi
    step = TWO_PI / counts_per_rev
    half = counts_per_rev // 2
    # Nearest count: unbiased around the true angle. Wrapping the integer
    # count keeps alpha exactly on the grid, in [-pi, pi) like the rig's.
    count_theta = floor(theta / step + 0.5)
    count_alpha = (floor(alpha / step + 0.5) + half) % counts_per_rev - half
    return count_theta * step, count_alpha * step


def measure(state, sensor: SensorModel = SensorModel(),
            rng: np.random.Generator | None = None) -> np.ndarray:
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
    theta, alpha = x[..., 0], x[..., 1]
    if sensor.noise_std > 0:
        if rng is None:
            raise ValueError("a noisy sensor needs rng (a numpy Generator) for reproducible noise")
        theta = theta + rng.normal(0.0, sensor.noise_std, theta.shape)
        alpha = alpha + rng.normal(0.0, sensor.noise_std, alpha.shape)
    return np.stack(_encode(theta, alpha, sensor.counts_per_rev, np.floor), axis=-1)
