"""Synthetic episodes for the tests: the rig's controller, metadata and deterministic samples."""

from __future__ import annotations

import numpy as np

from daq.episode import SIGNALS, ControllerInfo, Episode, EpisodeMetadata
from sim.lti import DiscreteStateSpace

RATE = 500.0

# The rig's backward-Euler PD controller (FACTS section 2), written out so the
# tests do not depend on python-control.
_A = 1 / 1.1
QUBE_PD = DiscreteStateSpace(np.eye(2) * _A, np.eye(2),
                             [[-1.8 * 50 * (_A - 1) * _A, -2.5 * 50 * (_A - 1) * _A]],
                             [[-6 - 1.8 * 50 * _A, -30 - 2.5 * 50 * _A]], 1 / RATE)


def make_metadata(**changes) -> EpisodeMetadata:
    base = dict(
        controller=ControllerInfo(QUBE_PD, "backward-euler",
                                  {"kp_theta": 6.0, "kd_theta": 1.8, "kp_alpha": 30.0,
                                   "kd_alpha": 2.5, "tau": 50.0}),
        sample_rate_hz=RATE, backend="sim", source="unit test",
        start_time="2026-11-21T12:00:00+00:00",
        excitation={"seeds": {"target_theta": 1, "target_alpha": 2, "feedforward": 3},
                    "feedforward": {"amplitude_V": 0.5, "bit_period_s": 0.1}},
        software_version="qube-koopman test",
    )
    base.update(changes)
    return EpisodeMetadata(**base)


def make_episode(n: int = 1000, seed: int = 0, **meta_changes) -> Episode:
    rng = np.random.default_rng(seed)
    signals = {name: rng.standard_normal(n) for name in SIGNALS if name != "t"}
    signals["lateness"][::7] = np.nan
    return Episode(t=np.arange(n) / RATE, controller_state=rng.standard_normal((n, 2)),
                   saturation=rng.integers(-1, 2, n), metadata=make_metadata(**meta_changes), **signals)


def sample(k: int) -> dict:
    """A deterministic sample, so the parent knows what the killed child wrote."""
    return dict(t=k / RATE, theta=np.sin(0.01 * k), alpha=np.cos(0.02 * k), target_theta=0.1 * k,
                target_alpha=-0.1 * k, feedforward=0.5, controller_state=(k, -k), control_output=1.0 * k,
                plant_input=2.0 * k, saturation=k % 3 - 1, lateness=1e-6 * k, compute_time=2e-6)
