"""The controllers' discretization, built without python-control, against python-control's own.

``pd_controller`` and ``pi_controller`` write each channel's continuous block by hand and
discretize it with the cont2discrete formulas (``_sample_block``), so that a command building
the rig's controller does not import python-control. Checked here against python-control's
``tf`` arithmetic, ``ss`` realization and ``sample_system``: two independent constructions of
the same controllers.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from qube_koopman.core.controller import (
    DISCRETIZATIONS,
    PdGains,
    _sample_block,
    discretize_channels,
    pd_controller,
    pi_controller,
)

GAINS = [PdGains(6.0, 1.8, 30.0, 2.5, 50.0), PdGains(2.0, 2.0, 35.0, 3.0, 50.0), PdGains(4.0, 0.0, 20.0, 0.0, 30.0)]


def _with_control(gains: PdGains, dt: float, method: str):
    """The PD controller as python-control builds it: transfer functions, realized, sampled."""
    import control

    s = control.tf("s")
    channels = [
        -(kp + kd * gains.tau * s / (s + gains.tau))
        for kp, kd in ((gains.kp_theta, gains.kd_theta), (gains.kp_alpha, gains.kd_alpha))
    ]
    blocks = []
    for channel in channels:
        sys_d = control.sample_system(control.ss(channel), dt, method=DISCRETIZATIONS[method])
        A, B, C, D = (np.atleast_2d(np.asarray(m, dtype=float)) for m in (sys_d.A, sys_d.B, sys_d.C, sys_d.D))
        blocks.append((A, B, C, D))
    return blocks


def _impulse_responses(system, n: int = 40) -> np.ndarray:
    """Markov parameters D, CB, CAB, ...: what a realization cannot change."""
    out, power = [system.D], system.B
    for _ in range(n):
        out.append(system.C @ power)
        power = system.A @ power
    return np.array(out)


@pytest.mark.parametrize("method", sorted(DISCRETIZATIONS))
@pytest.mark.parametrize("gains", GAINS)
def test_the_pd_controller_is_python_controls_to_rounding(gains, method):
    dt = 0.002
    ours = pd_controller(gains, dt, method)
    blocks = _with_control(gains, dt, method)
    # a state per channel with a derivative gain (none without: a static gain, as python-control leaves it)
    assert ours.A.shape[0] == sum(A.shape[0] for A, *_ in blocks) == (gains.kd_theta != 0) + (gains.kd_alpha != 0)
    i = 0
    for j, (A, B, C, D) in enumerate(blocks):
        np.testing.assert_allclose(ours.D[0, j], D[0, 0], rtol=1e-13)
        if A.shape[0]:  # scaled to B = 1, as on the rig
            np.testing.assert_allclose(ours.A[i, i], A[0, 0], rtol=1e-13)
            assert ours.B[i, j] == 1.0 and ours.B[i, 1 - j] == 0.0
            np.testing.assert_allclose(ours.C[0, i], C[0, 0] * B[0, 0], rtol=1e-12)
            i += 1
    assert ours.dt == dt


@pytest.mark.parametrize("method", sorted(DISCRETIZATIONS))
def test_the_pi_controller_and_transfer_function_channels_agree(method):
    import control

    s = control.tf("s")
    dt = 0.01
    by_hand = pi_controller(1.5, 0.7, dt, method)
    from_tf = discretize_channels([1.5 + 0.7 / s], dt, method)
    np.testing.assert_allclose(_impulse_responses(by_hand), _impulse_responses(from_tf), rtol=1e-12, atol=1e-14)
    sampled = control.sample_system(control.ss(1.5 + 0.7 / s), dt, method=DISCRETIZATIONS[method])
    np.testing.assert_allclose(_impulse_responses(by_hand), _impulse_responses(sampled), rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("method", sorted(DISCRETIZATIONS))
def test_sample_block_is_cont2discrete_on_a_multi_state_block(method):
    from scipy.signal import cont2discrete

    rng = np.random.default_rng(3)
    A, B, C, D = (
        rng.normal(size=(3, 3)) - 2 * np.eye(3),
        rng.normal(size=(3, 2)),
        rng.normal(size=(2, 3)),
        rng.normal(size=(2, 2)),
    )
    ours = _sample_block(A, B, C, D, 0.05, method)
    theirs = cont2discrete((A, B, C, D), 0.05, method=DISCRETIZATIONS[method])[:4]
    for mine, reference in zip(ours, theirs):
        np.testing.assert_allclose(mine, reference, rtol=1e-12, atol=1e-14)


def test_an_unknown_discretization_is_named():
    with pytest.raises(ValueError, match="unknown discretization 'euler'"):
        pd_controller(GAINS[0], 0.002, "euler")


def test_building_the_rigs_controller_does_not_import_python_control():
    """What the speed is for: qube-run and qube-import build a PD controller at start-up."""
    code = (
        "import sys; from qube_koopman.core.controller import PdGains, pd_controller; "
        "pd_controller(PdGains(6.0, 1.8, 30.0, 2.5, 50.0)); print('control' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "False"
