"""Judging a calibrated plant on logs it did not see: closed-loop replay and open-loop prediction.

Closed-loop replay: from one second in (after the hand-raising and the
derivative kick, as the paper drops it) each logged episode is rerun with
the simulator, the log's own controller (state taken from the log), its
references and feedforward; the loop is closed on the simulated encoders
only. Each episode's pendulum encoder offset is estimated from its first
scored second (:func:`estimate_offset`, the fitted physics held fixed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import savgol_filter

from qube_koopman.identify.calibrate import shooting as ms
from qube_koopman.identify.calibrate.fit import ENCODER_SIGMA
from qube_koopman.sim.pendulum import PendulumParameters, simulate_closed_loop

__all__ = ["estimate_offset", "ReplayResult", "replay_episodes", "open_loop_error"]


def _rates(y: np.ndarray, dt: float) -> np.ndarray:
    return savgol_filter(np.asarray(y, float), 21, 2, deriv=1, delta=dt, axis=0)


def estimate_offset(y: np.ndarray, u: np.ndarray, params: PendulumParameters, dt: float,
                    start: int, window: int, horizon: int = 100) -> float:
    """One episode's alpha encoder offset (rad) from samples ``start .. start + window``.

    Multiple shooting with the physics fixed: the segments' node states and
    the offset are free.
    """
    seg = ms.make_segments([y[:start + window + 1]], [u[:start + window + 1]], horizon, start, 0, horizon)
    nodes = np.concatenate([seg.y[0], _rates(y, dt)[seg.start]], axis=1)
    phys = ms.from_params(params, params)
    offset0 = float(np.mean(y[start:start + window, 1]))
    pattern = ms.sparsity(seg, 1)[:, ms.N_PHYSICAL:]

    def fun(z):
        return ms.residuals(np.concatenate([phys, z]), seg, 1, params, dt, ENCODER_SIGMA)

    nodes[:, 1] -= offset0
    z0 = np.concatenate([[offset0 / ms.OFFSET_SCALE], nodes.ravel()])
    result = least_squares(fun, z0, jac_sparsity=pattern, method="trf", tr_solver="lsmr", max_nfev=30)
    return float(result.x[0] * ms.OFFSET_SCALE)


@dataclass(frozen=True)
class ReplayResult:
    """Per-episode closed-loop replay scores (arrays over episodes).

    Attributes
    ----------
    std_ratio : ndarray (n, 3)
        Standard deviation twin / real of theta, alpha, voltage.
    balanced : ndarray (n,) of bool
        Stayed within |theta| < pi/2 and |alpha| < pi/4.
    nrmse : ndarray (n,)
        Mean over theta and alpha of RMSE / max|real| (percent).
    offsets : ndarray (n,)
        The offsets used (rad).
    twin : ndarray (n_steps, n, 3)
        The twin's theta, alpha (measured) and voltage; ``real`` the log's.
    """

    std_ratio: np.ndarray
    balanced: np.ndarray
    nrmse: np.ndarray
    offsets: np.ndarray
    twin: np.ndarray
    real: np.ndarray


def replay_episodes(episodes: Sequence, params: PendulumParameters, start: int = 500,
                    offset_window: int = 500) -> ReplayResult:
    """Closed-loop replay of logged episodes (``daq.episode.Episode``) through ``params``.

    All episodes must share the controller and length.
    """
    dt = episodes[0].dt
    controller = episodes[0].controller
    ys = [np.asarray(e.states, float) for e in episodes]
    us = [np.asarray(e.plant_input, float) for e in episodes]
    offsets = np.array([estimate_offset(y, u, params, dt, start, offset_window) for y, u in zip(ys, us)])
    state0 = np.stack([np.concatenate([y[start] - [0.0, o], _rates(y, dt)[start]]) for y, o in zip(ys, offsets)])
    refs = np.stack([np.asarray(e.references, float)[start:] for e in episodes], axis=1)
    ff = np.stack([np.asarray(e.feedforward, float)[start:] for e in episodes], axis=1)
    xc0 = np.stack([np.asarray(e.controller_state, float)[start] for e in episodes])
    max_v = float(np.max(np.abs(np.concatenate(us)))) if episodes else 10.0
    past = np.stack([u[max(0, start - ms.N_PAST):start] for u in us], axis=1)
    run = simulate_closed_loop(state0, controller, refs, ff, params, controller_state0=xc0,
                               max_voltage=max(max_v, 1e-3), alpha_offsets=offsets,
                               past_voltages=past if len(past) else None)
    twin = np.concatenate([run.measurements, run.plant_input[..., None]], axis=-1)
    real = np.stack([np.column_stack([y[start:], u[start:]]) for y, u in zip(ys, us)], axis=1)
    ratio = twin.std(axis=0) / real.std(axis=0)
    peak = np.max(np.abs(run.measurements), axis=0)
    balanced = (peak[:, 0] < math.pi / 2) & (peak[:, 1] < math.pi / 4)
    rmse = np.sqrt(np.mean((twin[..., :2] - real[..., :2]) ** 2, axis=0))
    nrmse = 100 * np.mean(rmse / np.max(np.abs(real[..., :2]), axis=0), axis=1)
    return ReplayResult(ratio, balanced, nrmse, offsets, twin, real)


def open_loop_error(episodes: Sequence, params: PendulumParameters, offsets: np.ndarray,
                    horizon: float = 0.2, start: int = 500) -> np.ndarray:
    """RMS error (rad) of theta and alpha over open-loop predictions of ``horizon`` seconds.

    Each prediction starts from the data (measured angles less the offset,
    Savitzky-Golay rates) every ``horizon`` seconds and is driven by the
    logged voltage. Returns (n_episodes, 2).
    """
    dt = episodes[0].dt
    h = int(round(horizon / dt))
    out = []
    for e, o in zip(episodes, offsets):
        y, u = np.asarray(e.states, float), np.asarray(e.plant_input, float)
        seg = ms.make_segments([y], [u], h, start)
        nodes = np.concatenate([seg.y[0] - [0.0, o], _rates(y, dt)[seg.start]], axis=1)
        pred = ms.simulate_segments(nodes, seg.u, params, dt, past=seg.past)
        pred[..., 1] += o
        out.append(np.sqrt(np.mean((pred - seg.y) ** 2, axis=(0, 1))))
    return np.array(out)
