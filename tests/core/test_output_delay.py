"""core.lti.with_output_delay: a system's output held late by whole and fractional samples."""

from __future__ import annotations

import numpy as np
import pytest

from qube_koopman.core.lti import DiscreteStateSpace, with_output_delay


def _system(n_outputs: int = 1, seed: int = 0) -> DiscreteStateSpace:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3, 3))
    A *= 0.9 / max(abs(np.linalg.eigvals(A)))
    return DiscreteStateSpace(
        A, rng.normal(size=(3, 2)), rng.normal(size=(n_outputs, 3)), rng.normal(size=(n_outputs, 2)), 0.002
    )


def _late(y: np.ndarray, samples: int) -> np.ndarray:
    """``y`` shifted ``samples`` later, zeros before (the system starts at rest)."""
    return np.vstack([np.zeros((samples,) + y.shape[1:]), y[: len(y) - samples]])


@pytest.mark.parametrize("n_outputs", [1, 2])
@pytest.mark.parametrize("samples", [1, 2, 5])
def test_a_whole_sample_delay_shifts_the_output(samples, n_outputs):
    system = _system(n_outputs)
    u = np.random.default_rng(1).normal(size=(50, 2))
    _, y = system.simulate(u)
    delayed = with_output_delay(system, samples)
    assert delayed.n_states == system.n_states + samples * n_outputs
    np.testing.assert_allclose(delayed.simulate(u)[1], _late(y, samples), atol=1e-12)


@pytest.mark.parametrize("samples", [0.25, 1.5, 2.75])
def test_a_fraction_of_a_sample_interpolates_between_the_whole_delays(samples):
    system = _system(2, seed=3)
    u = np.random.default_rng(4).normal(size=(40, 2))
    _, y = system.simulate(u)
    whole, w = int(samples), samples - int(samples)
    expected = (1 - w) * _late(y, whole) + w * _late(y, whole + 1)
    np.testing.assert_allclose(with_output_delay(system, samples).simulate(u)[1], expected, atol=1e-12)


def test_no_delay_is_the_system_itself():
    system = _system()
    same = with_output_delay(system, 0)
    for a, b in zip((same.A, same.B, same.C, same.D), (system.A, system.B, system.C, system.D)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("samples", [-0.5, float("nan"), float("inf")])
def test_a_delay_that_is_not_a_time_is_refused(samples):
    with pytest.raises(ValueError, match="delay"):
        with_output_delay(_system(), samples)
