"""Facts of the QUBE-Servo rig that several packages rely on, stated once.

The acquisition (``daq``), the twin's probes and the calibration's replays (``identify``) and the
controller design (``design``) must agree on them: a safety limit that differed between the rig
and the probes, or a skip that differed between the fit and the scores, would compare unlike
things without a word.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["ALPHA_LIMIT", "MEASURED", "SKIP_SAMPLES", "STATE_NAMES", "THETA_LIMIT", "loop_cost"]

#: The measured states, in the order of every log, trajectory and model: the arm angle theta and
#: the pendulum angle alpha (rad; alpha 0 upright).
STATE_NAMES = ("theta", "alpha")

#: The states the rig's controllers feed back, as indices into :data:`STATE_NAMES`: both angles
#: (a list, for numpy's fancy indexing of a state array: ``x[:, MEASURED]``).
MEASURED = [0, 1]

#: The arm's safety limit (rad, 90 deg): the C program that ran the rig stopped an episode, with
#: 0 V in the same tick, once ``|theta|`` exceeded it; ``qube-run`` does (``daq.safety``), and a
#: twin probe or replayed episode beyond it counts as fallen.
THETA_LIMIT = math.pi / 2

#: The pendulum's safety limit (rad, 45 deg): beyond it the pendulum is falling, and the episode
#: stops as for :data:`THETA_LIMIT`.
ALPHA_LIMIT = math.pi / 4

#: Samples left out at the start of every episode, fitted or scored: the first second at 500 Hz,
#: while the pendulum is raised by hand to the start gate and the controller's derivative kicks
#: (the paper drops it too).
SKIP_SAMPLES = 500


def loop_cost(theta, target_theta, alpha, skip: int = SKIP_SAMPLES) -> np.ndarray:
    """The loop's cost J of each episode after ``skip`` samples: ``mean((theta - target_theta)^2) + mean(alpha^2)``.

    The one definition of J (rad^2): what ``qube-design`` predicts of a design and its interval, and
    what the identification's held-out episodes measure and predict for that interval.

    Parameters
    ----------
    theta, target_theta, alpha : array_like
        The arm's angle, its reference and the pendulum's angle (rad), time along the last axis;
        any leading axes (episodes, plants) broadcast.
    skip : int
        Samples left out at each episode's start.

    Returns
    -------
    ndarray
        Of the broadcast leading shape (a 0-d array for one episode); non-finite where the angles are.
    """
    tracking = np.asarray(theta, dtype=float)[..., skip:] - np.asarray(target_theta, dtype=float)[..., skip:]
    return np.mean(tracking**2, axis=-1) + np.mean(np.asarray(alpha, dtype=float)[..., skip:] ** 2, axis=-1)


#: Longest episode (s): one day. An episode's plan and timing arrays take 40 bytes a tick
#: (about 1.7 GB at 500 Hz for a day); see bench/bench_memory.py.
MAX_DURATION = 86_400.0
