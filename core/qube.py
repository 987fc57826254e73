"""Facts of the QUBE-Servo rig that several packages rely on, stated once.

The acquisition (``daq``), the twin's probes and the calibration's replays (``identify``) and the
controller design (``design``) must agree on them: a safety limit that differed between the rig
and the probes, or a skip that differed between the fit and the scores, would compare unlike
things without a word.
"""

from __future__ import annotations

import math

__all__ = ["ALPHA_LIMIT", "MEASURED", "SKIP_SAMPLES", "STATE_NAMES", "THETA_LIMIT"]

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


#: Longest episode (s): one day. An episode's plan and timing arrays take 40 bytes a tick
#: (about 1.7 GB at 500 Hz for a day); see bench/bench_memory.py.
MAX_DURATION = 86_400.0
