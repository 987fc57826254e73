"""The twin calibrated on the paper's 28 training episodes, judged on its 20 test episodes.

The issue's validation targets (standard deviation ratios of theta, alpha
and voltage within 1 +- 0.05 in closed-loop replay, every test episode
balanced) are not met yet: that test is a strict xfail stating the measured
gap, so it fails loudly once the twin meets them.
"""

from __future__ import annotations

import numpy as np
import pytest

from qube_koopman.identify.calibrate import PlantCalibration
from qube_koopman.identify.calibrate.validate import replay_episodes
from qube_koopman.identify.data import paper_split
from qube_koopman.sim.pendulum import PendulumParameters

pytestmark = [pytest.mark.dataset, pytest.mark.slow]


@pytest.fixture(scope="module")
def split(qube_logs):
    from qube_koopman.daq.log import read_episode

    train, test = paper_split(sorted(qube_logs.glob("*.mcap")))
    return [read_episode(p) for p in train], [read_episode(p) for p in test]


@pytest.fixture(scope="module")
def calibration(split):
    train, _ = split
    return PlantCalibration().fit([e.states for e in train], [e.plant_input for e in train], train[0].dt)


@pytest.fixture(scope="module")
def replay(split, calibration):
    return replay_episodes(split[1], calibration.params_)


def test_fit_predicts_short_horizons_to_near_encoder_resolution(calibration):
    # 0.1 s open-loop segments from free node states: residuals within ~1.5 counts' quantization noise.
    quantization = 2 * np.pi / 2048 / np.sqrt(12)
    assert np.all(calibration.residual_rms_ < 2.0 * quantization), calibration.residual_rms_
    assert calibration.cost_ > 0 and len(calibration.alpha_offsets_) == 28
    # The motor's torque per volt is well identified and far from the workbook's.
    se = calibration.standard_errors_["km"]
    assert se < 0.01 * calibration.params_.km
    assert abs(calibration.params_.km - PendulumParameters().km) > 10 * se


def test_calibrated_twin_replays_closer_than_the_defaults(split, replay):
    # Closed-loop replay error of the episodes the twin keeps up, against the built-in parameters.
    default = replay_episodes(split[1], PendulumParameters())
    ok = replay.balanced
    assert ok.sum() >= 15
    assert np.median(replay.nrmse[ok]) < np.median(default.nrmse[ok])


@pytest.mark.xfail(strict=True, reason="measured: 18 of 20 test episodes balanced; on those the std ratios "
                                       "are theta 0.96-1.11, alpha 1.06-1.40, voltage 1.06-1.32 (target not met)")
def test_validation_targets(replay):
    assert replay.balanced.all()
    assert np.all(np.abs(replay.std_ratio - 1.0) < 0.05)
