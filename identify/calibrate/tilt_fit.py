"""The base's tilt, from the pendulum's balance angle in the logs (:func:`fit_tilt`).

A base tilted by a few mrad moves the angle at which the pendulum balances with the arm's angle,
``alpha_b = tilt_x sin(theta) + tilt_y cos(theta)`` (:class:`~qube_koopman.sim.pendulum.PendulumParameters`).
The pendulum's equation run backwards on a log gives that angle sample by sample
(:func:`~qube_koopman.identify.calibrate.load_fit.reconstruct_balance`: the measured alpha less the angle
at which gravity balances the measured accelerations). Its slow part, below :data:`TILT_BAND` Hz,
regressed on ``sin`` of the arm's slow angle, gives ``tilt_x``: by least squares, each episode with
its own constant (the pendulum encoder's zero, set by hand each episode), with standard errors
clustered by episode (the slow residuals are correlated over seconds, the episodes are not).

``tilt_y`` is not fitted (the fit's ``tilt_y`` is 0): it multiplies ``cos(theta)``, whose constant part
is the encoder's zero and whose change over an excursion of a few tenths of a radian is of second
order, as even in the arm's angle as the loop's own errors at the excursions' ends. Regressed with
it, twin episodes of a known tilt gave ``tilt_y`` off by ten times its size. On twin episodes of
square-wave arm references the fitted ``tilt_x`` is within about 1 mrad of the truth (a level base:
-0.7 to +0.6 mrad under the rig's gains, +0.8 under a soft arm loop), the loop's own slow motion
under that excitation; the twin's level-base replays of the real logs (their excitations,
controllers and quantized encoders) give -0.01 +- 0.03 mrad (the rig's day) and -0.03 +- 0.12 (the
soft day): on those logs the estimate is the base's, not the loop's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.signal import butter, sosfiltfilt

from qube_koopman.core.qube import SKIP_SAMPLES
from qube_koopman.identify.calibrate.load_fit import reconstruct_balance
from qube_koopman.sim.pendulum import PendulumParameters

__all__ = ["TILT_BAND", "TiltFit", "fit_tilt"]

#: The band (Hz) of the balance angle and the arm's angle that the fit regresses: the arm's slow
#: excursions (its references' steps, its wander) are there; the pendulum's balancing motion, which
#: the reconstruction follows less exactly, is above it.
TILT_BAND = 0.3
#: Samples left out at each end of the slow signals (1 s at 500 Hz): the zero-phase filter's edges.
_EDGE = 500


@dataclass(frozen=True)
class TiltFit:
    """A fitted tilt of the base.

    Attributes
    ----------
    tilt_x, tilt_y : float
        The tilt (rad), :class:`~qube_koopman.sim.pendulum.PendulumParameters`' fields (``tilt_y`` 0: not fitted).
    standard_errors : dict of str to float
        ``tilt_x``'s standard error (rad), clustered by episode.
    r2 : float
        The share of the slow balance angle's variance (each episode's constant removed) the tilt explains.
    n_episodes : int
    """

    tilt_x: float
    tilt_y: float
    standard_errors: dict
    r2: float
    n_episodes: int


def _slow(x: np.ndarray, dt: float) -> np.ndarray:
    sos = butter(2, TILT_BAND, fs=1.0 / dt, output="sos")
    return sosfiltfilt(sos, x)[_EDGE:-_EDGE]


def fit_tilt(
    states: Sequence[np.ndarray], params: PendulumParameters | Sequence[PendulumParameters], dt: float
) -> TiltFit:
    """The base's tilt that the logs' balance angles give (the module's text).

    Parameters
    ----------
    states : sequence of ndarray (n, 2 or more)
        Each episode's measured theta and alpha (rad), from its first sample.
    params : PendulumParameters, or one per episode
        The pendulum whose equation reconstructs the balance angle (its masses, lengths and damping;
        the arm's terms do not enter).
    dt : float
        Sample period (s).

    Returns
    -------
    TiltFit

    Raises
    ------
    ValueError
        Fewer than two episodes, or an episode too short for the band (under 3 s after the first second).
    """
    states = list(states)
    per_episode = [params] * len(states) if isinstance(params, PendulumParameters) else list(params)
    if len(states) < 2 or len(per_episode) != len(states):
        raise ValueError(f"fit_tilt needs two or more episodes, each with its pendulum; got {len(states)}")
    columns, targets = [], []
    for y, p in zip(states, per_episode):
        y = np.asarray(y, float)
        if len(y) - SKIP_SAMPLES < 2 * _EDGE + int(1.0 / dt):
            raise ValueError(f"an episode of {len(y)} samples is too short for the tilt's fit")
        balance = _slow(reconstruct_balance(y, p, dt), dt)
        theta = _slow(y[SKIP_SAMPLES:, 0], dt)
        x = np.sin(theta)[:, None]
        columns.append(x - x.mean(axis=0))  # each episode's own constant: its encoder's zero
        targets.append(balance - balance.mean())
    X, b = np.vstack(columns), np.concatenate(targets)
    gram_inv = np.linalg.inv(X.T @ X)
    tilt = gram_inv @ (X.T @ b)
    # Clustered by episode (the sandwich with each episode's score summed), with the small-sample factor.
    scores = np.array([x.T @ (t - x @ tilt) for x, t in zip(columns, targets)])
    g = len(scores)
    covariance = gram_inv @ (scores.T @ scores) @ gram_inv * g / (g - 1)
    errors = np.sqrt(np.diag(covariance))
    residual = b - X @ tilt
    return TiltFit(
        tilt_x=float(tilt[0]),
        tilt_y=0.0,
        standard_errors={"tilt_x": float(errors[0])},
        r2=float(1.0 - residual @ residual / (b @ b)),
        n_episodes=g,
    )
