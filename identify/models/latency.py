"""A test loop's command delay, estimated from the other logs of its recording session.

The host's latency between computing a command and the motor receiving it is a property of
the recording session (its computer, its USB path), not of the plant: the same QUBE under the
same controller ran about 1.7 samples (3.4 ms) later in one session than in another. A plant
identified from the training logs carries their sessions' latency, and predicts a loop that
ran later as better damped than it was.

What the logs show of it: the plant model predicts the measured angles a few tens of milliseconds
ahead from their measured history and the logged voltage. Held ``d`` samples late
(:func:`~qube_koopman.core.lti.held_late`: a fraction interpolates, as
:func:`~qube_koopman.core.lti.with_output_delay` delays a command), the voltage meets the angles'
response where the plant's timing has it; the ``d`` that predicts best is the log's *apparent*
delay. On the training logs themselves it is not zero (the model's bias sits there too: 0.6-1.1
samples on the rig's training logs for the search's rig-only lifting, 0.89 pooled over eight), so a
test loop's extra delay is its apparent delay minus the training logs' (the reference). On the
paper's data, with that lifting: the 20 test episodes (another session than the training's) come out
0.08-0.25 samples *below* the reference (no extra delay), the softer controller's earlier session
+0.36-0.43 and its later one +1.64-1.77. The difference between the two, 1.3-1.4 samples, is near
the 1.7 samples (3.4 ms) the twin's calibration per session finds between them.

The estimate for one test log never uses that log's samples: it pools the curves of up to
:data:`NEIGHBOURS` other test logs of its session (the ones recorded just before and after it, so a
latency that changes within a session is followed), as the offsets' window keeps the estimation off the scored
samples. One log's own apparent delay spreads about 0.25 samples around its session's; four
neighbours bring that to about 0.12 samples (0.25 ms), within which the predictions hardly change
(near the best delay, R^2 moves by 0.004 at most across half a sample). A log alone in its session gets no extra delay,
and the report says it was not estimated. The extra delay is clipped at zero: a loop faster than the
training's cannot be modelled by holding the command late, and the paper's test episodes come out
there.

The error curve starts after the first ``skip`` samples (the episodes' first second, when a hand
raises the pendulum and the voltage saturates) and takes a prediction every :data:`STRIDE` samples:
about 290 per 19 s episode, a fraction of a second per log.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from qube_koopman.core.lti import held_late
from qube_koopman.identify.data.trajectory import Trajectory

__all__ = ["DelayEstimate", "apparent_delay", "delay_errors", "estimate_command_delays"]

#: Trial delays in sample periods: whole samples, 0 to 5 (10 ms at 500 Hz). The error is smooth in the
#: delay, and the parabola through the best whole sample and its neighbours (:func:`apparent_delay`) lands
#: within 0.01 samples of a quarter-sample grid's on the paper's logs, at about a third of the cost.
DELAY_GRID = np.arange(6.0)
#: Samples each open-loop prediction covers (40 ms at 500 Hz: the balancing loop's fast response).
HORIZON = 20
#: Samples between the starts of two predictions.
STRIDE = 32
#: Other test logs of the session pooled for one log's estimate.
NEIGHBOURS = 4
#: Training logs pooled for the reference (evenly spread over them, by name).
REFERENCE_LOGS = 8
#: What the estimate is, in words (report.json's ``command_delay.note``).
NOTE = (
    "each test episode's loop predicted with its command reaching the plant later than in the training logs "
    "by its estimated extra delay: the apparent delay of the plant model's 40 ms open-loop predictions on up to "
    "four other test logs of its recording session, minus that on the training logs, clipped at zero and rounded "
    "to a quarter sample; a log alone in its session gets none"
)


def delay_errors(
    plant,
    trajectory: Trajectory,
    delays: np.ndarray = DELAY_GRID,
    skip: int = 500,
    horizon: int = HORIZON,
    stride: int = STRIDE,
) -> np.ndarray:
    """How well ``plant`` predicts the episode's angles ``horizon`` samples ahead with its voltage held late.

    Parameters
    ----------
    plant : KoopmanModel
        A plant model whose input is the logged voltage (``input_signals == ("u",)``).
    trajectory : Trajectory
        One episode.
    delays : ndarray
        Trial delays in sample periods (an even grid).
    skip : int
        Samples left out at the start.
    horizon, stride : int
        Samples each prediction covers, and between their starts.

    Returns
    -------
    ndarray of shape (len(delays),)
        Per delay, the sum over the angles of the mean squared error divided by that angle's least
        over the delays (each angle counts alike, whatever its range). NaN when the episode is too
        short for one prediction.
    """
    if tuple(plant.input_signals) != ("u",):
        raise ValueError(
            f"a command delay is estimated with a plant model of the voltage, not of {plant.input_signals}"
        )
    if trajectory.u is None:
        raise ValueError(f"trajectory {trajectory.name!r} has no logged voltage to estimate a command delay from")
    u = trajectory.u
    d = plant.n_delays
    starts = np.arange(max(skip, d), trajectory.n_samples - horizon, stride)
    if starts.size == 0:
        return np.full(len(delays), np.nan)
    window = np.arange(-d, horizon + 1)
    x_init = trajectory.x[starts[:, None] + window[: d + 1]]
    measured = trajectory.x[starts[:, None] + window[d + 1 :]]
    # Every trial delay's predictions in one batched simulation: 25 % faster than one call per delay.
    v = np.concatenate([held_late(u, samples)[starts[:, None] + window] for samples in delays])
    x, _ = plant.simulate(np.concatenate([x_init] * len(delays)), v)
    squared = (x[:, d + 1 :] - np.concatenate([measured] * len(delays))) ** 2
    errors = squared.mean(axis=1).reshape(len(delays), len(starts), -1).mean(axis=1)
    least = np.nanmin(errors, axis=0) if np.isfinite(errors).any() else np.ones(errors.shape[1])
    return np.sum(errors / np.maximum(least, np.finfo(float).tiny), axis=1)


def apparent_delay(errors: np.ndarray, delays: np.ndarray = DELAY_GRID) -> float:
    """The delay (sample periods) where an error curve of :func:`delay_errors` is least: the grid's best point,
    refined by the parabola through it and its neighbours."""
    i = int(np.nanargmin(errors))
    if 0 < i < len(errors) - 1:
        a, b, c = errors[i - 1 : i + 2]
        curvature = a - 2.0 * b + c
        if curvature > 0:
            return float(delays[i] + 0.5 * (a - c) / curvature * (delays[1] - delays[0]))
    return float(delays[i])


@dataclass
class DelayEstimate:
    """One test loop's estimated command delay.

    Parameters
    ----------
    samples : float
        The extra delay the loop is predicted with (sample periods, 0 or more).
    raw : float or None
        Its apparent delay minus the reference, before clipping at zero; None when not estimated.
    neighbours : list of int
        The other test logs (indices) whose curves gave it.
    """

    samples: float
    raw: float | None
    neighbours: list[int] = field(default_factory=list)


def estimate_command_delays(
    plant,
    reference: Sequence[Trajectory],
    test: Sequence[Trajectory],
    neighbours: Sequence[Sequence[int]],
    skip: int = 500,
    delays: np.ndarray = DELAY_GRID,
    stride: int = STRIDE,
) -> tuple[float | None, list[DelayEstimate]]:
    """Each test loop's extra command delay over the training logs', from the other logs of its session.

    Parameters
    ----------
    plant : KoopmanModel
        The identified plant (its input the voltage).
    reference : sequence of Trajectory
        Training episodes: their pooled apparent delay is the reference.
    test : sequence of Trajectory
        The test episodes.
    neighbours : sequence of sequence of int
        Per test episode, the other test episodes (indices into ``test``) pooled for it
        (:func:`~qube_koopman.identify.data.sessions.session_neighbours`).
    skip : int
        Samples left out at each episode's start.
    delays : ndarray
        Trial delays (an even grid of sample periods).
    stride : int
        Samples between the starts of two predictions.

    Returns
    -------
    reference : float or None
        The training episodes' pooled apparent delay (sample periods); None when no training episode is
        long enough for one prediction after ``skip`` (then no test loop's delay is estimated).
    estimates : list of DelayEstimate
    """
    ref_curves = [delay_errors(plant, t, delays, skip, stride=stride) for t in reference]
    finite = [c for c in ref_curves if np.all(np.isfinite(c))]
    if not finite:  # episodes too short for one prediction after ``skip``: nothing to measure against
        return None, [DelayEstimate(0.0, None, list(group)) for group in neighbours]
    ref = apparent_delay(np.mean(finite, axis=0), delays)
    needed = sorted({j for group in neighbours for j in group})
    curves = {j: delay_errors(plant, test[j], delays, skip, stride=stride) for j in needed}
    estimates = []
    for group in neighbours:
        pooled = [curves[j] for j in group if np.all(np.isfinite(curves[j]))]
        if not pooled:
            estimates.append(DelayEstimate(0.0, None, list(group)))
            continue
        raw = apparent_delay(np.mean(pooled, axis=0), delays) - ref
        estimates.append(DelayEstimate(max(raw, 0.0), raw, list(group)))
    return ref, estimates
