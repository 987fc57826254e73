"""Identification's memory does not grow with the number of training episodes (issue 29).

The lifting is fitted and the regression's statistics folded one episode at a time: the peak of
the memory traced while fitting 24 episodes is that of fitting 6, where holding every episode's
lifted snapshots (as before) made it grow four times. Numpy reports its arrays to tracemalloc, so
the measure is the arrays', deterministic and independent of the machine's load.
"""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from qube_koopman.identify import ClEdmd, Constant, Delay, Lifting, Polynomial, ThinPlateRbf, Trajectory
from qube_koopman.identify.regression import Snapshots
from qube_koopman.sim.lti import DiscreteStateSpace

N_SAMPLES = 2000
CONTROLLER = DiscreteStateSpace(np.eye(2) * 0.5, np.eye(2), -np.eye(2), np.zeros((2, 2)), dt=0.002)


def _lifting() -> Lifting:
    return Lifting([Polynomial(2), Delay(20), ThinPlateRbf(20, seed=0), Constant()])


def _episodes(n: int) -> list[Trajectory]:
    rng = np.random.default_rng(0)
    out = []
    for _ in range(n):
        x = np.cumsum(rng.standard_normal((N_SAMPLES, 2)), axis=0) * 1e-2
        out.append(Trajectory(x=x, r=rng.standard_normal((N_SAMPLES, 2)) * 1e-2,
                              xc=rng.standard_normal((N_SAMPLES, 2)), dt=0.002))
    return out


def _peak(work) -> int:
    """Peak traced bytes while ``work()`` runs, above what was allocated before it."""
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        before = tracemalloc.get_traced_memory()[0]
        work()
        return tracemalloc.get_traced_memory()[1] - before
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("fit", ["lifting", "cl_edmd"])
def test_the_peak_memory_of_a_fit_does_not_grow_with_the_episodes(fit):
    small, large = _episodes(6), _episodes(24)
    lifted_episode = N_SAMPLES * _lifting().fit([small[0].x]).n_features_out_ * 8

    def run(trajectories):
        if fit == "lifting":
            return lambda: _lifting().fit([t.x for t in trajectories])
        return lambda: ClEdmd(CONTROLLER, _lifting(), alpha=1e-6).fit(trajectories)

    peak_small, peak_large = _peak(run(small)), _peak(run(large))
    # 18 more lifted episodes held at once would add 18 x 0.67 MB; folding one at a time adds nothing.
    assert peak_large - peak_small < 2 * lifted_episode, (peak_small, peak_large, lifted_episode)


def test_folding_statistics_in_batches_equals_one_factor_of_everything():
    rng = np.random.default_rng(1)
    parts = [Snapshots.from_snapshots(rng.standard_normal((50, 3)), rng.standard_normal((50, 5))) for _ in range(37)]
    everything = Snapshots.from_snapshots(np.vstack([p.R[:, 5:] for p in parts]), np.vstack([p.R[:, :5] for p in parts]))
    folded = Snapshots.total(iter(parts), batch=4)
    assert folded.q == sum(p.q for p in parts)
    np.testing.assert_allclose(folded.H, everything.H, rtol=1e-12)
    np.testing.assert_allclose(folded.G, everything.G, rtol=1e-12)
    np.testing.assert_allclose(folded.F, everything.F, rtol=1e-12)
    np.testing.assert_allclose(Snapshots.total(parts).H, folded.H, rtol=1e-12)
