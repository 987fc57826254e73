"""The pieces several packages share have one home each: file names, controller replay, signal stacking."""

from __future__ import annotations

from datetime import datetime, timezone

import numpy as np
import pytest

from _episodes import QUBE_PD
from qube_koopman.daq.episode import REFERENCE_SIGNALS, STATE_SIGNALS, stack_signals
from qube_koopman.daq.excitation import parse_seeds
from qube_koopman.daq.legacy_csv import parse_legacy_name
from qube_koopman.daq.log.names import LOG_SUFFIX, episode_stem, find_logs, log_path, parse_episode_name
from qube_koopman.identify import controller_states
from qube_koopman.core.lti import DiscreteStateSpace, replay_controller


# --- the episode file-name pattern -------------------------------------------------------------


def test_a_log_name_round_trips_through_the_pattern():
    start = datetime(2026, 11, 21, 12, 34, 56, 789_999, tzinfo=timezone.utc)
    seeds = {"target_theta": 1, "target_alpha": 22, "feedforward": 333}
    stem = episode_stem(start, seeds)
    assert stem == "qube_20261121T123456.789_1_22_333"
    parsed = parse_episode_name(log_path("/x", stem), LOG_SUFFIX)
    assert parsed.stamp == "20261121T123456" and parsed.milliseconds == 789 and parsed.seeds == seeds
    taken = parse_episode_name(f"{stem}_2{LOG_SUFFIX}", LOG_SUFFIX)
    assert taken.seeds == seeds, "a '_<n>' added to a taken name is not a seed"


def test_the_rig_csv_names_follow_the_same_pattern():
    name = "qube_20230828T150615_434_696_394.csv"
    assert parse_episode_name(name, ".csv").seeds == {"target_theta": 434, "target_alpha": 696, "feedforward": 394}
    assert parse_seeds(name) == (434, 696, 394)
    assert parse_legacy_name(name) == ("2023-08-28T15:06:15", parse_episode_name(name, ".csv").seeds)
    # An exported log (milliseconds in its name) imports with its milliseconds.
    assert parse_legacy_name("qube_20230828T150615.250_1_2_3.csv")[0] == "2023-08-28T15:06:15.250000"
    assert parse_episode_name(name, LOG_SUFFIX) is None and parse_episode_name("run1.csv", ".csv") is None


def test_a_zone_aware_start_is_named_in_utc():
    from datetime import timedelta

    start = datetime(2026, 1, 1, 1, 0, 0, tzinfo=timezone(timedelta(hours=2)))
    assert episode_stem(start, {}) == "qube_20251231T230000.000"


def test_find_logs_lists_only_logs_in_name_order(tmp_path):
    for stem in ("qube_b", "qube_a"):
        log_path(tmp_path, stem).write_bytes(b"")
    (tmp_path / "qube_c.csv").write_bytes(b"")
    assert [p.name for p in find_logs(tmp_path)] == ["qube_a.mcap", "qube_b.mcap"]


def test_the_mcap_sink_names_its_files_with_the_pattern(tmp_path):
    from _episodes import make_metadata
    from qube_koopman.daq.sinks import EpisodeOutcome, McapSink
    from qube_koopman.daq.timing import TimingStats

    meta = make_metadata(start_time="2026-11-21T12:34:56.789+00:00")
    sink = McapSink(tmp_path)
    sink.open(meta)
    sink.close(EpisodeOutcome("complete", "", 0, TimingStats(0, 0.002, False)))
    stem = episode_stem(meta.start_datetime, meta.excitation.get("seeds", {}))
    assert sink.paths == [log_path(tmp_path, stem)] and sink.paths[0].exists()


# --- the controller-state replay ----------------------------------------------------------------


def test_replay_controller_runs_the_controller_on_the_tracking_error():
    rng = np.random.default_rng(3)
    r, y = rng.normal(size=(50, 2)), rng.normal(size=(50, 2))
    x, u = replay_controller(QUBE_PD, r, y)
    e = r - y
    expected = np.zeros(2)
    for k in range(50):
        np.testing.assert_allclose(x[k], expected, rtol=0, atol=1e-12)
        np.testing.assert_allclose(u[k], QUBE_PD.C @ expected + QUBE_PD.D @ e[k], rtol=0, atol=1e-12)
        expected = QUBE_PD.A @ expected + QUBE_PD.B @ e[k]
    np.testing.assert_array_equal(controller_states(QUBE_PD, r, y), x)


def test_replay_controller_takes_one_channel_as_1d_and_a_starting_state():
    pi = DiscreteStateSpace([[1.0]], [[0.5]], [[2.0]], [[1.0]], 0.01)
    x, u = replay_controller(pi, np.ones(4), np.zeros(4), x0=np.array([1.0]))
    np.testing.assert_array_equal(x[:, 0], [1.0, 1.5, 2.0, 2.5])
    np.testing.assert_array_equal(u[:, 0], 2.0 * x[:, 0] + 1.0)
    with pytest.raises(ValueError, match="shape"):
        replay_controller(QUBE_PD, np.ones(4), np.zeros(4))


def test_replay_controller_runs_a_batch_of_episodes_as_each_alone():
    """Leading axes replay episodes side by side in one pass; each is the replay of that episode alone,
    and the starting state is one for all or one each."""
    rng = np.random.default_rng(5)
    r, y = rng.normal(size=(3, 40, 2)), rng.normal(size=(3, 40, 2))
    x, u = replay_controller(QUBE_PD, r, y)
    assert x.shape == (3, 40, QUBE_PD.n_states) and u.shape == (3, 40, QUBE_PD.n_outputs)
    for b in range(3):
        alone_x, alone_u = replay_controller(QUBE_PD, r[b], y[b])
        np.testing.assert_allclose(x[b], alone_x, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(u[b], alone_u, rtol=1e-13, atol=1e-13)
    starts = rng.normal(size=(3, QUBE_PD.n_states))
    x_each, _ = replay_controller(QUBE_PD, r, y, x0=starts)
    for b in range(3):
        np.testing.assert_allclose(x_each[b], replay_controller(QUBE_PD, r[b], y[b], x0=starts[b])[0], atol=1e-13)
    shared, _ = replay_controller(QUBE_PD, r, y, x0=starts[0])
    np.testing.assert_allclose(shared[2], replay_controller(QUBE_PD, r[2], y[2], x0=starts[0])[0], atol=1e-13)


# --- signal stacking ------------------------------------------------------------------------------


def test_stack_signals_reads_items_or_attributes_column_per_name():
    columns = {
        "theta": np.arange(3.0),
        "alpha": np.arange(3.0) + 10,
        "target_theta": np.ones(3),
        "target_alpha": np.zeros(3),
    }
    np.testing.assert_array_equal(stack_signals(columns, STATE_SIGNALS), [[0, 10], [1, 11], [2, 12]])

    class Holder:
        target_theta, target_alpha = np.ones(3), np.zeros(3)

    np.testing.assert_array_equal(stack_signals(Holder(), REFERENCE_SIGNALS), stack_signals(columns, REFERENCE_SIGNALS))
    batch = {"theta": np.zeros((5, 4)), "alpha": np.ones((5, 4))}
    stacked = stack_signals(batch, STATE_SIGNALS)
    assert stacked.shape == (5, 4, 2) and np.all(stacked[..., 1] == 1)


def test_episode_states_and_references_are_the_stacked_signals():
    from _episodes import make_episode

    ep = make_episode(20)
    np.testing.assert_array_equal(ep.states, np.column_stack((ep.theta, ep.alpha)))
    np.testing.assert_array_equal(ep.references, np.column_stack((ep.target_theta, ep.target_alpha)))
