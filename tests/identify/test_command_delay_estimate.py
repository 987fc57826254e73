"""A test loop's command delay estimated from the other logs of its recording session
(``identify.models.latency``, ``session_neighbours``, ``qube-identify --command-delay estimate``).

A plant identified from the training logs carries their sessions' latency; a test session whose
host delivered every command later is predicted with that much more delay. The estimate pools
other test logs of the session, never the log's own samples.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from _twin_logs import collect_pd_logs

from qube_koopman.core.controller import load_pd_gains
from qube_koopman.core.lti import DiscreteStateSpace, held_late, with_output_delay
from qube_koopman.identify.cli.identify import main as qube_identify
from qube_koopman.identify.data.logs import load_logs
from qube_koopman.identify.data.sessions import order_neighbours, session_neighbours
from qube_koopman.identify.model_selection.search import LiftingSpec
from qube_koopman.identify.models.latency import (
    DELAY_GRID,
    apparent_delay,
    estimate_command_delays,
)
from qube_koopman.identify.workflow import FitOptions, IdentifyOptions, OutputOptions, identify_and_score
from qube_koopman.sim.pendulum import PendulumParameters


@pytest.mark.parametrize("samples", [0.0, 0.5, 1.0, 1.75, 3.25])
def test_a_command_held_late_is_the_output_of_the_delayed_gain(samples):
    u = np.random.default_rng(3).normal(size=(40, 1))
    gain = DiscreteStateSpace(A=np.zeros((0, 0)), B=np.zeros((0, 1)), C=np.zeros((1, 0)), D=[[1.0]], dt=0.002)
    delayed = with_output_delay(gain, samples)
    # The delay's states start at rest; held_late holds the first value before the start instead.
    _, y = delayed.simulate(u - u[0])
    np.testing.assert_allclose(held_late(u, samples), y + u[0], atol=1e-12)


def test_the_apparent_delay_is_the_least_of_the_parabola_through_the_best_whole_sample():
    grid = DELAY_GRID
    assert apparent_delay(3.0 * (grid - 1.3) ** 2 + 2.0) == pytest.approx(1.3)
    assert apparent_delay(3.0 * (grid - 3.8) ** 2 + 2.0, grid) == pytest.approx(3.8)
    assert apparent_delay(grid + 1.0) == 0.0  # least at the grid's edge: no parabola beyond it


def test_the_plant_finds_a_slower_sessions_extra_delay_on_twin_logs(tmp_path):
    """Twin logs of two hosts, the second delivering every command 4 ms (2 samples) later. A plant fitted to
    the first's logs gives the first's held-out logs no extra delay and the second's about 2 samples, each
    estimated from the others of its session only."""
    params = PendulumParameters.previous()
    rig = load_pd_gains("rig")

    def logs(name, p, n, seed):
        return load_logs(sorted(collect_pd_logs(tmp_path / name, rig, n, seed, p, duration=10.0).glob("*.mcap")))

    fast = logs("fast", params, 8, 1)
    slow = logs("slow", replace(params, delay=params.delay + 4e-3), 3, 5)
    train, test = fast[:5], fast[5:] + slow
    options = IdentifyOptions(
        FitOptions("cl-edmd", LiftingSpec(delays=10, poly=1).steps(0), alpha=1e-4),
        output=OutputOptions(keep_predictions=False),
    )
    fit = identify_and_score(train, test[:1], train[0].controller, options)
    neighbours = [[1, 2], [0, 2], [0, 1], [4, 5], [3, 5], [3, 4]]
    reference, estimates = estimate_command_delays(
        fit.plant, [log.trajectory for log in train], [log.trajectory for log in test], neighbours, skip=250
    )
    extra = [e.samples for e in estimates]
    print(f"reference {reference:.3f} samples; extra delays {np.round([e.raw for e in estimates], 3)}")
    assert all(e.neighbours == n for e, n in zip(estimates, neighbours))
    np.testing.assert_allclose(extra[:3], 0.0, atol=0.3)
    np.testing.assert_allclose(extra[3:], 2.0, atol=0.4)
    # Alone in its session, a log gets none, said as not estimated.
    _, alone = estimate_command_delays(fit.plant, [train[0].trajectory], [test[3].trajectory], [[]], skip=250)
    assert alone[0].samples == 0.0 and alone[0].raw is None
    # Episodes too short for one prediction after the skipped samples: none estimated, and no error.
    short = [log.trajectory for log in test[3:5]]
    reference, none = estimate_command_delays(fit.plant, short, short, [[1], [0]], skip=10_000)
    assert reference is None and [(e.samples, e.raw) for e in none] == [(0.0, None), (0.0, None)]


@pytest.mark.dataset
def test_a_logs_neighbours_are_the_others_of_its_session_recorded_just_before_and_after_it(soft_logs, qube_logs):
    soft = sorted(soft_logs.glob("*.mcap"))  # two sessions of five, 20 minutes apart
    rig = sorted(qube_logs.glob("*.mcap"))[-3:]
    neighbours = session_neighbours([*soft, *rig], 2)
    assert neighbours[:10] == [[1, 2], [0, 2], [1, 3], [2, 4], [3, 2], [6, 7], [5, 7], [6, 8], [7, 9], [8, 7]]
    assert neighbours[10:] == [[11, 12], [10, 12], [11, 10]]
    assert session_neighbours(soft[:1], 4) == [[]]
    assert session_neighbours(soft, 4)[2] == [1, 3, 0, 4]  # two on each side, the nearer first


def test_the_neighbours_follow_the_recording_order_not_the_seconds_between_starts():
    # The twin's episodes run in parallel start within seconds of each other, in an order qube-run keeps
    # from one recording to the next; the seconds between them move with the machine's load. Two
    # recordings of the same eight episodes, their starts spaced differently: the same neighbours.
    names = [f"qube_ep{k}.mcap" for k in range(8)]
    first = [f"2026-11-28T16:20:{s:02d}" for s in (16, 16, 17, 19, 19, 20, 25, 26)]
    second = [f"2026-11-28T16:20:{s:02d}" for s in (16, 18, 18, 18, 21, 24, 24, 24)]
    one, other = order_neighbours(first, names, 4), order_neighbours(second, names, 4)
    assert one == other
    assert one[0] == [1, 2, 3, 4] and one[4] == [3, 5, 2, 6] and one[7] == [6, 5, 4, 3]
    # Starts that tie to the second are ordered as logged (milliseconds), then by name; a log of
    # another session (more than ten minutes later) or without a start time is no one's neighbour.
    ms = ["2026-11-28T16:20:16.900", "2026-11-28T16:20:16.100", "2026-11-28T16:20:16.500", "2026-11-28T16:40:00", None]
    assert order_neighbours(ms, ["a", "b", "c", "d", "e"], 1) == [[2], [2], [1], [], []]
    assert order_neighbours(["2026-11-28T16:20:16"] * 3, ["c", "a", "b"], 1) == [[2], [2], [1]]


@pytest.mark.slow
@pytest.mark.dataset
def test_rig_trained_predictions_of_a_later_slower_session_gain_from_its_estimated_delay(
    qube_logs, soft_logs, tmp_path
):
    """Trained on the rig's 28 logs; tested on the soft controller's two sessions and five of the paper's
    test logs. The later soft session's host was about 1.7 samples (3.4 ms) slower than the earlier one's
    (the twin's calibration per session): the estimate finds that difference, gives the paper's test logs
    none (their predictions unchanged to the bit), and the later session's predictions improve."""
    rig = sorted(qube_logs.glob("*.mcap"))
    soft = sorted(soft_logs.glob("*.mcap"))
    test = [*soft, *rig[28:33]]
    common = [
        "--train",
        *map(str, rig[:28]),
        "--test",
        *map(str, test),
        "--poly",
        "1",
        "--delays",
        "20",
        "--alpha",
        "1e-4",
        "--offsets",
        "alpha",
        "--interval",
        "0",
        "-q",
    ]
    reports = {}
    for name, extra in (("estimated", []), ("none", ["--command-delay", "0"])):
        assert qube_identify([*common, *extra, "--out", str(tmp_path / name)]) == 0
        reports[name] = json.loads((tmp_path / name / "report.json").read_text())
    delays = reports["estimated"]["command_delay"]
    assert delays["estimated"] is True and "command_delay" not in reports["none"]
    samples = np.array([entry["samples"] for entry in delays["logs"]])
    raw = np.array([entry["raw_samples"] for entry in delays["logs"]])
    print(f"reference {delays['reference_samples']:.3f}; raw extra delays {np.round(raw, 2)}")
    assert np.median(raw[5:10]) - np.median(raw[:5]) == pytest.approx(1.68, abs=0.4)
    assert np.all(samples[10:] == 0.0) and np.all(samples[5:10] >= 1.25)
    after, before = (np.array(reports[k]["test"]["r2_per_episode"]) for k in ("estimated", "none"))
    np.testing.assert_array_equal(after[10:], before[10:])
    assert np.mean(after[5:10]) > np.mean(before[5:10]) + 0.01
    assert "estimated (`--command-delay estimate`)" in (tmp_path / "estimated" / "report.md").read_text()


def test_the_estimate_is_refused_with_session_delays_and_a_negative_delay(tmp_path, capsys):
    out = tmp_path / "out"
    for name in ("a.mcap", "b.mcap", "plant.toml"):
        (tmp_path / name).write_text("")
    args = ["--train", str(tmp_path / "a.mcap"), "--test", str(tmp_path / "b.mcap"), "--out", str(out), "-q"]
    assert qube_identify([*args, "--command-delay", "estimate", "--session-delays", str(tmp_path / "plant.toml")]) == 2
    assert "leave out --command-delay estimate" in capsys.readouterr().err
    assert qube_identify([*args, "--command-delay", "-1"]) == 2
    assert "--command-delay must be 0 or more milliseconds" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:
        qube_identify([*args, "--command-delay", "soon"])
    assert exit_.value.code == 2
    assert "'soon' is neither a number of milliseconds nor 'estimate'" in capsys.readouterr().err
    assert not out.exists()
