"""Synthetic episodes for the tests: the rig's controller, metadata and deterministic samples."""

from __future__ import annotations

import numpy as np

from qube_koopman.daq.episode import SIGNALS, Episode, EpisodeMetadata
from qube_koopman.core.controller_file import ControllerInfo
from qube_koopman.core.lti import DiscreteStateSpace

RATE = 500.0

# The rig's backward-Euler PD controller (the discretization its C program used; the paper's
# text says ZOH), written out so the
# tests do not depend on python-control.
_A = 1 / 1.1
QUBE_PD = DiscreteStateSpace(
    np.eye(2) * _A,
    np.eye(2),
    [[-1.8 * 50 * (_A - 1) * _A, -2.5 * 50 * (_A - 1) * _A]],
    [[-6 - 1.8 * 50 * _A, -30 - 2.5 * 50 * _A]],
    1 / RATE,
)


def assert_follows_controller(ep: Episode, controller: DiscreteStateSpace = QUBE_PD, max_voltage: float = 10.0) -> None:
    """What every backend's complete episode must satisfy, whoever measured the angles.

    The controller run offline from zero on the logged tracking error
    reproduces the logged controller state and output (to 1e-14 V on the dataset); the
    plant input is their sum with the feedforward, clamped and flagged; the
    samples are evenly spaced from t = 0.
    """
    from qube_koopman.identify import controller_states
    from qube_koopman.core.lti import controller_inputs

    xc = controller_states(controller, ep.references, ep.states, ep.feedforward)
    np.testing.assert_allclose(ep.controller_state, xc, rtol=0, atol=1e-10)
    inputs = controller_inputs(controller, ep.references, ep.states, ep.feedforward)
    u = ep.controller_state @ controller.C[0] + inputs @ controller.D[0]
    np.testing.assert_allclose(ep.control_output, u, rtol=0, atol=1e-10)
    wanted = ep.control_output + ep.feedforward
    np.testing.assert_array_equal(ep.plant_input, np.clip(wanted, -max_voltage, max_voltage))
    assert np.array_equal(ep.saturation, np.where(wanted > max_voltage, 1, np.where(wanted < -max_voltage, -1, 0)))
    assert np.all(ep.controller_state[0] == 0.0), "the rig started from a zero controller state"
    assert np.array_equal(ep.t, np.arange(len(ep)) / ep.metadata.sample_rate_hz), "samples are evenly spaced"


def make_metadata(**changes) -> EpisodeMetadata:
    base = dict(
        controller=ControllerInfo(
            QUBE_PD,
            "backward-euler",
            {"kp_theta": 6.0, "kd_theta": 1.8, "kp_alpha": 30.0, "kd_alpha": 2.5, "tau": 50.0},
        ),
        sample_rate_hz=RATE,
        backend="sim",
        source="unit test",
        start_time="2026-11-21T12:00:00+00:00",
        excitation={
            "seeds": {"target_theta": 1, "target_alpha": 2, "feedforward": 3},
            "feedforward": {"amplitude_V": 0.5, "bit_period_s": 0.1},
        },
        software_version="qube-koopman test",
    )
    base.update(changes)
    return EpisodeMetadata(**base)


def make_episode(n: int = 1000, seed: int = 0, **meta_changes) -> Episode:
    rng = np.random.default_rng(seed)
    signals = {name: rng.standard_normal(n) for name in SIGNALS if name != "t"}
    signals["lateness"][::7] = np.nan
    return Episode(
        t=np.arange(n) / RATE,
        controller_state=rng.standard_normal((n, 2)),
        saturation=rng.integers(-1, 2, n),
        metadata=make_metadata(**meta_changes),
        **signals,
    )


def sample(k: int) -> dict:
    """A deterministic sample, so the parent knows what the killed child wrote."""
    return dict(
        t=k / RATE,
        theta=np.sin(0.01 * k),
        alpha=np.cos(0.02 * k),
        target_theta=0.1 * k,
        target_alpha=-0.1 * k,
        feedforward=0.5,
        controller_state=(k, -k),
        control_output=1.0 * k,
        plant_input=2.0 * k,
        saturation=k % 3 - 1,
        lateness=1e-6 * k,
        compute_time=2e-6,
    )


def nan_controller() -> ControllerInfo:
    """A state-space controller whose output becomes NaN a few ticks after any non-zero error.

    Its two states grow by 1e300 a tick with opposite signs: their sum, the output, reads 0 V until
    they overflow to +inf and -inf, then nan (as any diverging controller's can).
    """
    system = DiscreteStateSpace(
        np.diag([1e300, 1e300]),
        np.array([[1.0, 1.0], [-1.0, -1.0]]),
        np.array([[1.0, 1.0]]),
        np.zeros((1, 2)),
        dt=0.002,
    )
    return ControllerInfo(system, "given", {}, kind="state-space")


def probe_sources(n: int = 3, samples: int = 1200) -> list:
    """Excitations the twin balances under every probe controller: small arm steps, no feedforward."""
    from qube_koopman.identify.data.trajectory import Trajectory

    t = np.arange(samples)
    return [
        Trajectory(
            x=np.zeros((samples, 2)),
            u=np.zeros((samples, 1)),
            r=np.column_stack([0.03 * (k + 1) * np.sign(np.sin(2 * np.pi * t / 600)), np.zeros(samples)]),
            f=np.zeros((samples, 1)),
            xc=np.zeros((samples, 2)),
            dt=0.002,
            name=f"s{k}",
        )
        for k in range(n)
    ]
