"""A loop whose command reaches the motor later: ``command_delayed`` and ``qube-identify --command-delay``.

The host's latency between computing a command and the motor receiving it differed between the
rig's recording sessions (1 to 5 ms). A plant identified from one session's logs carries that
session's latency; predicting a loop run with more latency means holding the command later.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from _twin_logs import collect_pd_logs

from qube_koopman.core.controller import load_pd_gains, pd_controller
from qube_koopman.core.lti import DiscreteStateSpace
from qube_koopman.identify.cli.identify import main as qube_identify
from qube_koopman.identify.estimators.structure import command_delayed, plant_input
from qube_koopman.sim.pendulum import PendulumParameters

RIG = load_pd_gains("rig")


def _held(signal: np.ndarray, samples: float) -> np.ndarray:
    """``signal`` held ``samples`` later, written out sample by sample (the first value before the start)."""
    out = np.empty_like(signal)
    whole, w = int(np.floor(samples)), samples - np.floor(samples)
    for k in range(len(signal)):
        a, b = signal[max(k - whole, 0)], signal[max(k - whole - 1, 0)]
        out[k] = (1 - w) * a + w * b
    return out


@pytest.mark.parametrize("samples", [0.0, 1.0, 1.5, 2.25])
def test_the_delayed_controller_on_its_states_gives_the_command_held_late(samples):
    """The delayed controller's output, from the states command_delayed gives along an episode, is the
    undelayed controller's output held ``samples`` later; the feedforward is held alike."""
    rng = np.random.default_rng(3)
    controller = pd_controller(RIG)
    n = 200
    r, y, f = rng.normal(size=(n, 2)), rng.normal(size=(n, 2)), rng.normal(size=(n, 1))
    xc = controller.simulate(r - y)[0]
    output = plant_input(controller, xc, r, y)
    delayed, xc_delayed, f_held = command_delayed(controller, samples, xc, r, y, f)
    assert delayed.n_inputs == controller.n_inputs and delayed.n_outputs == controller.n_outputs
    assert xc_delayed.shape[1] == delayed.n_states
    np.testing.assert_array_equal(xc_delayed[:, : controller.n_states], xc)
    # Away from the start (where the states' history is the first sample's), output and hold agree.
    k0 = int(np.ceil(samples)) + 1
    np.testing.assert_allclose(plant_input(delayed, xc_delayed, r, y)[k0:], _held(output, samples)[k0:], atol=1e-12)
    np.testing.assert_allclose(f_held, _held(f, samples), atol=1e-15)
    # The states follow the delayed controller's own dynamics on the tracking errors.
    stepped = xc_delayed[:-1] @ delayed.A.T + (r - y)[:-1] @ delayed.B.T
    np.testing.assert_allclose(stepped[k0:], xc_delayed[1:][k0:], atol=1e-12)


def test_a_controller_taking_the_feedforward_and_a_negative_delay_are_refused():
    taking_f = DiscreteStateSpace(
        A=np.zeros((0, 0)), B=np.zeros((0, 3)), C=np.zeros((1, 0)), D=np.ones((1, 3)), dt=0.002
    )
    z = np.zeros((5, 2))
    with pytest.raises(ValueError, match="takes the feedforward"):
        command_delayed(taking_f, 1.0, np.zeros((5, 0)), z, z, np.zeros((5, 1)))
    with pytest.raises(ValueError, match="0 or more"):
        command_delayed(pd_controller(RIG), -1.0, np.zeros((5, 2)), z, z)


def _collect(out, params, n, seed, duration=20.0):
    return collect_pd_logs(out, RIG, n, seed, params, duration=duration)


@pytest.mark.slow
def test_a_slower_hosts_episodes_are_predicted_as_well_as_the_trainings_with_its_extra_delay(tmp_path, capsys):
    """Trained on the twin without a command delay and tested on the same loop run with 4 ms of delay:
    without ``--command-delay`` the scores drop below those of test episodes run like the training;
    with ``--command-delay 4`` they come back to them, and the report says what was assumed."""
    params = PendulumParameters.previous()  # the workbook plant: no friction for the lifting to miss
    train = _collect(tmp_path / "train", params, 8, 1)
    same = _collect(tmp_path / "same", params, 3, 2)  # the same excitations as the delayed ones
    delayed = _collect(tmp_path / "delayed", replace(params, delay=4e-3), 3, 2)
    scores = {}
    for name, test, ms in (("same loop", same, "0"), ("delayed", delayed, "0"), ("delayed, told", delayed, "4")):
        out = tmp_path / name.replace(" ", "_").replace(",", "")
        assert (
            qube_identify(
                [
                    "--train",
                    str(train),
                    "--test",
                    str(test),
                    "--delays",
                    "10",
                    "--interval",
                    "0",
                    "--command-delay",
                    ms,
                    "--out",
                    str(out),
                    "-q",
                ]
            )
            == 0
        )
        report = json.loads((out / "report.json").read_text())
        scores[name] = report["test"]["r2_mean"]
        assert ("command_delay" in report) == (ms != "0")
    with capsys.disabled():
        print("R^2:", scores)
    assert scores["delayed"] < scores["same loop"] - 0.01
    assert scores["delayed, told"] > scores["delayed"] + 0.01
    assert scores["delayed, told"] >= scores["same loop"] - 0.005
    told = json.loads((tmp_path / "delayed_told" / "report.json").read_text())["command_delay"]
    assert told["samples"] == pytest.approx(2.0) and told["seconds"] == pytest.approx(4e-3)
    assert "command delay: 4 ms (2 samples)" in (tmp_path / "delayed_told" / "report.md").read_text()
    capsys.readouterr()
    assert (
        qube_identify(
            [
                "--train",
                str(train),
                "--test",
                str(delayed),
                "--command-delay",
                "-1",
                "--out",
                str(tmp_path / "bad"),
                "-q",
            ]
        )
        == 2
    )
    assert "--command-delay must be 0 or more milliseconds" in capsys.readouterr().err
