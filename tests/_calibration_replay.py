"""A synthetic twin-against-real replay with known band-power ratios (the calibration report's tests)."""

from __future__ import annotations

import numpy as np

from qube_koopman.identify.calibrate.validate import ReplayResult

DT = 0.002
SCALE = np.array([0.5, 2.0, 1.5])  # twin = real * SCALE per channel (theta, alpha, voltage)
NAMES = ["val_a.mcap", "val_b.mcap"]


def synthetic_replay(scale=SCALE, n_steps: int = 4000, seed: int = 0) -> ReplayResult:
    """Two episodes: theta at 2 Hz, alpha at 5 Hz, voltage at 20 Hz (amplitudes 0.1, 0.02, 3), plus noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_steps) * DT
    real = np.stack(
        [
            np.column_stack(
                [
                    0.1 * np.sin(2 * np.pi * 2 * t + k),
                    0.02 * np.sin(2 * np.pi * 5 * t + k),
                    3.0 * np.sin(2 * np.pi * 20 * t + k),
                ]
            )
            for k in range(2)
        ],
        axis=1,
    )
    real += rng.normal(0.0, 1e-3, real.shape)
    n = real.shape[1]
    return ReplayResult(np.ones((n, 3)), np.ones(n, bool), np.zeros(n), np.zeros(n), real * scale, real)
