"""A synthetic legacy CSV episode the rig's controller reproduces exactly (qube-import's tests and fixtures)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from _episodes import QUBE_PD
from qube_koopman.core.lti import replay_controller
from qube_koopman.daq.legacy_csv import LEGACY_COLUMNS

GAINS_TOML = "kp_theta = 6.0\nkd_theta = 1.8\nkp_alpha = 30.0\nkd_alpha = 2.5\ntau = 50.0\n"
GOOD = "qube_20230828T150615_434_696_394"


def write_synthetic_csv(path: Path, n: int = 1000, seed: int = 0) -> np.ndarray:
    """A legacy-format CSV whose control_output the rig's controller reproduces exactly."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.002
    target = np.column_stack((np.cumsum(rng.normal(0, 1e-3, n)), 0.01 * np.sign(rng.normal(size=n))))
    measured = target + rng.normal(0, 0.02, (n, 2))
    _, output = replay_controller(QUBE_PD, target, measured)
    feedforward = 0.5 * np.sign(rng.normal(size=n))
    plant_input = np.clip(output[:, 0] + feedforward, -10, 10)
    saturation = np.where(output[:, 0] + feedforward > 10, 1, np.where(output[:, 0] + feedforward < -10, -1, 0))
    data = np.column_stack(
        (
            t,
            target[:, 0],
            target[:, 1],
            measured[:, 0],
            measured[:, 1],
            output[:, 0],
            feedforward,
            plant_input,
            saturation,
        )
    )
    np.savetxt(path, data, delimiter=", ", fmt="%.17e", header=", ".join(LEGACY_COLUMNS), comments="")
    return data
