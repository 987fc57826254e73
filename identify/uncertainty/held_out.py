"""What a design needs of the uncertainty: the calibration folds' held-out episodes predicted in closed
loop, and their figures (cost, voltage) measured and predicted."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from qube_koopman.core.lti import DiscreteStateSpace
from qube_koopman.core.qube import loop_cost
from qube_koopman.identify.data.trajectory import Trajectory, as_episodes, select_episodes
from qube_koopman.identify.uncertainty.ensemble import EnsembleFit
from qube_koopman.identify.uncertainty.loops import Loop, consecutive_runs
from qube_koopman.identify.uncertainty.prediction import predict_groups

__all__ = ["held_out_figures", "held_out_loops", "loop_figures", "loops_figures", "references"]


def loop_figures(x: np.ndarray, target_theta: np.ndarray, voltage: np.ndarray, skip: int) -> np.ndarray:
    """``[J, voltage RMS, voltage peak]`` of one episode after ``skip`` samples (inf when non-finite).

    J is :func:`~qube_koopman.core.qube.loop_cost`, the cost ``qube-design`` predicts.

    Parameters
    ----------
    x : ndarray of shape (n_samples, 2)
        Theta and alpha (rad).
    target_theta : ndarray of shape (n_samples,)
        The arm's reference (rad).
    voltage : ndarray of shape (n_samples,)
        The plant input (V).
    skip : int
        Samples left out at the start.

    Returns
    -------
    ndarray of shape (3,)
    """
    tracking, alpha, u = x[skip:, 0] - target_theta[skip:], x[skip:, 1], np.asarray(voltage, dtype=float)[skip:]
    if not (np.all(np.isfinite(tracking)) and np.all(np.isfinite(alpha)) and np.all(np.isfinite(u))):
        return np.full(3, np.inf)
    return np.array(
        [loop_cost(x[:, 0], target_theta, x[:, 1], skip), np.sqrt(np.mean(u**2)), np.max(np.abs(u), initial=0.0)]
    )


def held_out_loops(
    fit: EnsembleFit,
    trajectories,
    controllers: Sequence[DiscreteStateSpace],
    measured: Sequence[int],
    points: dict[int, tuple[Trajectory, np.ndarray]] | None = None,
) -> list[tuple[Trajectory, np.ndarray, np.ndarray]]:
    """The calibration folds' held-out episodes, each predicted in closed loop by its fold's point fit.

    Each held-out training episode is predicted in closed loop under the controller it ran
    (from its first samples, with its references and feedforward), by the fit on the fold's
    other episodes; the voltage is that controller's output on the predicted angles plus the
    feedforward.

    Parameters
    ----------
    fit : EnsembleFit
        Its folds' point fits.
    trajectories : sequence of Trajectory
        The training episodes the fit was made on.
    controllers : sequence of DiscreteStateSpace
        Each episode's controller.
    measured : sequence of int
        The fed-back states.
    points : dict, optional
        Held-out episodes already predicted, ``{index: (trajectory, prediction)}``
        (:func:`calibrate`'s ``points``: the fold's fitted closed loop, which is its plant
        wrapped with the controller the fit knew, to rounding: 5e-5 rad apart on the paper's
        folds); the other held-out episodes are predicted here.

    Returns
    -------
    list of (Trajectory, ndarray, ndarray)
        In the folds' order: the episode, its predicted states (n_samples, n_states) and voltage (n_samples,).
    """
    from qube_koopman.identify.estimators.structure import controller_states, plant_input

    trajectories = as_episodes(trajectories)
    found: dict[int, tuple[Any, np.ndarray]] = {} if points is None else dict(points)
    groups, indices = [], []  # per fold and controller: its point fit wrapped, the episodes; their indices
    for fold in fit.folds:
        missing = [int(j) for j in fold.validation if int(j) not in found]
        held_out = select_episodes(trajectories, missing)
        loops = [Loop.of(controllers[j], None) for j in missing]
        for run in consecutive_runs(loops):  # the episodes of one controller in one batch
            groups.append(([loops[run[0]].model(*fold.point, measured)], [held_out[i] for i in run]))
            indices.append([missing[i] for i in run])
    for idx, (_, trajs), predicted in zip(indices, groups, predict_groups(groups) if groups else []):
        found.update((j, (t, p.prediction)) for j, t, p in zip(idx, trajs, predicted))
    order = [int(j) for fold in fit.folds for j in fold.validation]
    voltages: dict[int, np.ndarray] = {}
    # The predicted voltage: each controller replayed on its episodes' predicted angles, all of them in
    # one pass over the samples (padded to the longest; the replay is causal, the padding comes after).
    for run in consecutive_runs([Loop("wrapped", controllers[j]) for j in order], size=len(order)):
        same = [order[i] for i in run]
        c, n = controllers[same[0]], max(len(found[j][1]) for j in same)
        r = _stacked([found[j][0].r for j in same], n)
        y = _stacked([found[j][1][:, list(measured)] for j in same], n)
        f = None if found[same[0]][0].f is None else _stacked([found[j][0].f for j in same], n)
        with np.errstate(all="ignore"):
            u = plant_input(c, np.nan_to_num(controller_states(c, r, np.nan_to_num(y), f)), r, y, f)
        for b, j in enumerate(same):
            voltages[j] = u[b, : len(found[j][1]), 0]
    return [(found[j][0], found[j][1], voltages[j]) for j in order]


def held_out_figures(
    fit: EnsembleFit,
    trajectories,
    controllers: Sequence[DiscreteStateSpace],
    measured: Sequence[int],
    skip: int,
    points: dict[int, tuple[Trajectory, np.ndarray]] | None = None,
) -> np.ndarray:
    """The figures of the calibration folds' held-out episodes, measured and as their fold's point fit predicts them.

    What the measured figures differ by is the model's error on an episode it was not fitted
    on: ``qube-design`` widens its predicted cost with it.

    Parameters
    ----------
    fit, trajectories, controllers, measured, points
        As for :func:`held_out_loops`.
    skip : int
        Samples left out at each episode's start (:func:`loop_figures`).

    Returns
    -------
    ndarray of shape (n_held_out, 2, 3)
        Per held-out episode, ``[measured, predicted]`` of ``[J, voltage RMS, voltage peak]``.
    """
    return loops_figures(held_out_loops(fit, trajectories, controllers, measured, points), skip)


def loops_figures(loops: Sequence[tuple[Trajectory, np.ndarray, np.ndarray]], skip: int) -> np.ndarray:
    """``[measured, predicted]`` of ``[J, voltage RMS, voltage peak]`` (n, 2, 3) of :func:`held_out_loops`' episodes,
    after ``skip`` samples (:func:`loop_figures`)."""
    rows = [
        [
            loop_figures(t.x, references(t)[:, 0], _logged_input(t)[:, 0], skip),
            loop_figures(x, references(t)[:, 0], u, skip),
        ]
        for t, x, u in loops
    ]
    return np.array(rows).reshape(-1, 2, 3)


def _logged_input(t: Trajectory) -> np.ndarray:
    """``t``'s logged plant input ``u`` (a ValueError without)."""
    if t.u is None:
        raise ValueError(f"episode {t.name or '(unnamed)'}: its measured figures need the logged input 'u'")
    return t.u


def references(t: Trajectory) -> np.ndarray:
    """``t``'s references ``r``, which a closed-loop figure scores against (a ValueError without)."""
    if t.r is None:
        raise ValueError(f"episode {t.name or '(unnamed)'}: a closed-loop figure needs its references 'r'")
    return t.r


def _stacked(arrays: Sequence[np.ndarray], n: int) -> np.ndarray:
    """``arrays`` (each of ``n`` samples or fewer) zero-padded to ``n`` samples and stacked on a new first axis."""
    out = np.zeros((len(arrays), n) + np.shape(arrays[0])[1:])
    for b, a in enumerate(arrays):
        out[b, : len(a)] = a
    return out
