"""Groups of models scored together, each on its own episodes, score as each group alone."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from qube_koopman.core.controller import PdGains, pd_controller
from qube_koopman.identify import ClEdmd, Constant, Delay, Polynomial, Trajectory
from qube_koopman.identify.estimators.structure import close_loop
from qube_koopman.identify.model_selection.sweep import episode_scores, grouped_episode_scores

DT = 0.002
GAINS = [
    PdGains(-2.0, -0.1, 30.0, 2.5, 0.01),
    PdGains(-4.0, -0.2, 35.0, 3.0, 0.01),
    PdGains(-1.5, -0.1, 25.0, 2.0, 0.02),
]


def _episode(rng, n: int, n_c: int) -> Trajectory:
    x = np.cumsum(rng.standard_normal((n, 2)), axis=0) * 1e-3
    return Trajectory(
        x=x,
        r=rng.standard_normal((n, 2)) * 1e-3,
        f=rng.standard_normal((n, 1)) * 1e-2,
        xc=rng.standard_normal((n, n_c)) * 1e-3,
        dt=DT,
        name=f"{n}",
    )


@pytest.fixture(scope="module")
def plants():
    """A plant at two alphas, fitted on random-walk episodes (what they predict does not matter here)."""
    rng = np.random.default_rng(5)
    controller = pd_controller(GAINS[0], DT, "backward-euler")
    train = [_episode(rng, 800, controller.n_states) for _ in range(3)]
    lifting = [Polynomial(2), Delay(4), Constant()]
    return [ClEdmd(controller, lifting, alpha=a).fit(train).plant_model_ for a in (1e-6, 1e-2)]


def test_groups_scored_together_score_as_each_group_alone(plants):
    rng = np.random.default_rng(6)
    controllers = [pd_controller(g, DT, "backward-euler") for g in GAINS]
    broken = replace(plants[1], A=plants[1].A * 3.0)  # diverges under any controller
    # Unequal episode counts and lengths: groups are padded per length, the padding dropped.
    lengths = [(300, 300, 500), (500,), (300, 700)]
    groups = []
    for g, (controller, ns) in enumerate(zip(controllers, lengths)):
        models = [close_loop(p, controller, [0, 1]) for p in (plants[0], broken if g == 2 else plants[1])]
        groups.append((models, [_episode(rng, n, controller.n_states) for n in ns]))
    together = grouped_episode_scores(groups, "cl", start=20)
    for (models, episodes), scores in zip(groups, together):
        alone = episode_scores(models, episodes, "cl", True, 20, True)
        assert scores.shape == (2, len(episodes))
        np.testing.assert_allclose(scores, alone, rtol=1e-12, atol=0)
    assert np.all(together[2][1] == -np.inf) and np.all(np.isfinite(together[0]))


def test_groups_of_unequal_model_counts_are_refused(plants):
    controller = pd_controller(GAINS[0], DT, "backward-euler")
    rng = np.random.default_rng(7)
    one = ([close_loop(plants[0], controller, [0, 1])], [_episode(rng, 300, controller.n_states)])
    two = ([close_loop(p, controller, [0, 1]) for p in plants], [_episode(rng, 300, controller.n_states)])
    with pytest.raises(ValueError, match="as many models"):
        grouped_episode_scores([one, two])
