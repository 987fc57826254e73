"""Plans are made per episode, when asked for: planning many episodes costs what planning one does."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from qube_koopman.daq.session import MAX_EPISODES, EpisodePlans, excitation_settings, plan_episodes, run_seeds
from qube_koopman.core.controller_file import load_controller


def test_lazy_plans_equal_the_plans_made_one_by_one():
    seeds, _ = run_seeds(7, 4)
    plans = plan_episodes(load_controller(), seeds, excitation_settings(1.0), source="t", extra={"a": 1})
    assert isinstance(plans, EpisodePlans) and len(plans) == 4
    for i, plan in enumerate(plans):
        one = plan_episodes(load_controller(), [tuple(seeds[i])], excitation_settings(1.0))[0]
        assert plan.index == i and plan.extra == {"a": 1} and plan.source == "t"
        assert plan.excitation_info == one.excitation_info
        np.testing.assert_array_equal(plan.excitation.feedforward, one.excitation.feedforward)
    assert plans[-1].index == 3 and [p.index for p in plans[1:3]] == [1, 2]
    with pytest.raises(IndexError):
        plans[4]


def test_planning_ten_thousand_episodes_allocates_next_to_nothing():
    controller, settings = load_controller(), excitation_settings(20.0)
    tracemalloc.start()
    seeds, _ = run_seeds(1, 10_000)
    plans = plan_episodes(controller, seeds, settings)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert len(plans) == 10_000
    assert peak < 2_000_000, f"{peak} bytes to plan 10,000 episodes"  # one 20 s plan alone is 240 kB


def test_absurd_episode_counts_are_refused():
    with pytest.raises(ValueError, match="n_episodes must be in"):
        run_seeds(1, MAX_EPISODES + 1)
    with pytest.raises(ValueError, match="n_episodes must be in"):
        run_seeds(1, -1)


def test_the_loop_follows_the_plan_across_its_chunks():
    # The loop turns the excitation into floats 4096 ticks at a time: 10,000 ticks cross two seams.
    from qube_koopman.daq.backends import SimBackend
    from qube_koopman.daq.loop import run_episode
    from qube_koopman.daq.sinks import MemorySink

    plan = plan_episodes(load_controller(), [(11, 22, 33)], excitation_settings(20.0))[0]
    memory = MemorySink()
    assert run_episode(SimBackend(seed=3), plan, [memory], handle_signals=False).complete
    ep = memory.episodes[0].episode()
    np.testing.assert_array_equal(ep.target_theta, plan.excitation.target_theta)
    np.testing.assert_array_equal(ep.target_alpha, plan.excitation.target_alpha)
    np.testing.assert_array_equal(ep.feedforward, plan.excitation.feedforward)
