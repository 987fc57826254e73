"""Episodes predicted by a point model and its bootstrap members, with the offsets' uncertainty: the spread
``s_c(k)`` of the band."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from qube_koopman.identify.data.trajectory import Trajectory
from qube_koopman.identify.metrics import DIVERGED_FACTOR
from qube_koopman.identify.models.offsets import OffsetEstimate, estimate_offsets_many, shift_trajectory
from qube_koopman.identify.models.simulate import ring_capacity, simulate_chunks

__all__ = [
    "EpisodePrediction",
    "OFFSET_STEP",
    "diverged_from",
    "members_variance",
    "predict_episodes",
    "predict_groups",
    "predict_group_sets",
]


#: Offset step (rad) of the sensitivity's finite difference: a tenth of an encoder count.
OFFSET_STEP = 3e-4


@dataclass
class EpisodePrediction:
    """One episode predicted by a point model and its members.

    Parameters
    ----------
    prediction : ndarray of shape (n_samples, n_states)
        The point model's (offsets added back when estimated).
    variance : ndarray of shape (n_samples, n_states) or None
        The members' variance plus the offsets' (None without members); infinite where a
        member diverged.
    plain : ndarray or None
        With offsets: the point model's prediction without them.
    estimate : OffsetEstimate or None
        With offsets: the episode's.
    """

    prediction: np.ndarray
    variance: np.ndarray | None = None
    plain: np.ndarray | None = None
    estimate: OffsetEstimate | None = None


def _controller_states(t: Trajectory) -> np.ndarray:
    """``t``'s controller states, which a model with passthrough states predicts from (a ValueError without)."""
    if t.xc is None:
        raise ValueError(f"episode {t.name or '(unnamed)'}: a closed-loop prediction needs the controller state 'xc'")
    return t.xc


class _GroupedSink:
    """Per group of equally many models, each on its own episodes: the point model's prediction and the
    members' variance, gathered chunk by chunk (time first)."""

    def __init__(self, T: int, n_groups: int, n_eps: int, m: int, n_p: int, n_models: int) -> None:
        self.shape, self.n_p = (n_groups, n_models), n_p
        self.prediction = np.full((T, n_groups, n_eps, m), np.nan)
        self.variance = np.full((T, n_groups, n_eps, m), np.inf) if n_models > 1 else None

    def __call__(self, k0: int, chunk: np.ndarray, models: np.ndarray) -> None:
        at = slice(k0, k0 + len(chunk))
        grouped = chunk[..., self.n_p :].reshape((len(chunk),) + self.shape + chunk.shape[2:3] + (-1,))
        self.prediction[at] = grouped[:, :, 0]
        if self.variance is not None:
            with np.errstate(all="ignore"):  # a diverged member: a non-finite spread, an infinite variance
                spread = np.var(grouped[:, :, 1:], axis=2, ddof=1)
            self.variance[at] = np.where(np.isfinite(spread), spread, np.inf)


def _group_key(models: Sequence) -> tuple:
    point = models[0]
    return (len(models), point.A.shape, point.B.shape, point.n_passthrough, id(point.lifting))


def predict_groups(
    groups: Sequence[tuple[Sequence, Sequence[Trajectory]]], offsets=None
) -> list[list[EpisodePrediction]]:
    """:func:`predict_episodes` of several ensembles, each on its own episodes, in few passes.

    The calibration folds are such groups: each fold's point fit and members predict that
    fold's held-out episodes. Predicted one group at a time, most of the time goes into
    stepping through the samples, not into arithmetic; groups of the same shape (as many
    models, one lifting, the same controller order) step together instead
    (:func:`~qube_koopman.identify.models.simulate.simulate_chunks` with ``paired``). Shorter
    episodes and smaller groups are padded (a repeated episode, zero inputs past an
    episode's end) and the padding dropped: the predictions are each group's own. With
    ``offsets``, each group's point model estimates its episodes' offsets first; the
    predictions at them, and the offsets' sensitivities, step together again.

    Parameters
    ----------
    groups : sequence of (models, trajectories)
        A point model then its members (all groups' models of one lifting), and the episodes
        they predict.
    offsets : OffsetProtocol, optional
        As for :func:`predict_episodes`.

    Returns
    -------
    list of list of EpisodePrediction
        Per group, in its episodes' order.
    """
    if offsets is None:
        return _predict_plain_groups(groups)
    estimates = [
        estimate_offsets_many(models[0], trajs, offsets.channels, offsets.window(trajs[0].dt), offsets.bound)
        if len(trajs)
        else []
        for models, trajs in groups
    ]
    predicted = _predicted_at_offsets(groups, estimates)
    plain, runs = _plain_and_moved(groups, estimates)
    return [
        _with_offset_spread(models, len(trajs), found, group, at, o_s)
        for (models, trajs), found, group, at, o_s in zip(groups, estimates, predicted, plain, runs)
    ]


def predict_group_sets(
    group_sets: Sequence[Sequence[tuple[Sequence, Sequence[Trajectory]]]], offsets=None
) -> list[list[list[EpisodePrediction]]]:
    """:func:`predict_groups` of several lists of groups in one call (one simulation where their shapes
    agree), the predictions handed back per list: ``[set][group][episode]``."""
    flat = predict_groups([group for groups in group_sets for group in groups], offsets)
    out, first = [], 0
    for groups in group_sets:
        out.append(flat[first : first + len(groups)])
        first += len(groups)
    return out


def _predicted_at_offsets(groups, estimates) -> list[list[EpisodePrediction]]:
    """Each group's episodes predicted at their estimated offsets (the offsets added back)."""
    shifted = [
        (models, [shift_trajectory(models[0], t, e.as_mapping()) for t, e in zip(trajs, found)])
        for (models, trajs), found in zip(groups, estimates)
    ]
    predicted = _predict_plain_groups(shifted)
    for found, group in zip(estimates, predicted):
        for e, p in zip(found, group):
            for c, value in e.as_mapping().items():
                p.prediction[:, c] += value
    return predicted


def _plain_and_moved(groups, estimates) -> tuple[list[list[EpisodePrediction]], list[list[dict]]]:
    """Each group's point model without its offsets, then (with members) at them with one channel moved by
    :data:`OFFSET_STEP`: the predictions (the offsets added back) and the offsets of each run."""
    runs: list[list[dict]] = []
    for (models, trajs), found in zip(groups, estimates):
        used = [{c: e.as_mapping().get(c, 0.0) for c in found[0].channels} for e in found] if found else []
        moved = (
            []
            if len(models) < 2 or not found
            else [{**u, c: u[c] + OFFSET_STEP} for c in found[0].channels for u in used]
        )
        runs.append([{}] * len(trajs) + moved)
    plain = _predict_plain_groups(
        [
            (
                [models[0]],
                [
                    shift_trajectory(models[0], t, o)
                    for t, o in zip(list(trajs) * (len(o_s) // max(len(trajs), 1)), o_s)
                ],
            )
            for (models, trajs), o_s in zip(groups, runs)
        ]
    )
    for at, o_s in zip(plain, runs):
        for run, o in zip(at, o_s):
            for c, value in o.items():
                run.prediction[:, c] += value
    return plain, runs


def _with_offset_spread(models, n: int, found, group, at, o_s) -> list[EpisodePrediction]:
    """One group's predictions, the offsets' standard errors propagated into the members' variance."""
    if len(models) > 1 and found:
        spread = np.array([_offset_spread(e) for e in found])  # (episodes, channels)
        for i in range(len(found[0].channels)):
            for j, p in enumerate(group):
                assert p.variance is not None  # members give a variance
                sensitivity = (at[n * (i + 1) + j].prediction - p.prediction) / OFFSET_STEP
                with np.errstate(invalid="ignore", over="ignore"):
                    p.variance += (sensitivity * spread[j, i]) ** 2
    return [
        EpisodePrediction(p.prediction, p.variance, at[j].prediction, e) for j, (p, e) in enumerate(zip(group, found))
    ]


def _predict_plain_groups(groups: Sequence[tuple[Sequence, Sequence[Trajectory]]]) -> list[list[EpisodePrediction]]:
    """:func:`predict_groups` without offsets."""
    out: list[list[EpisodePrediction]] = [[] for _ in groups]
    buckets: dict[tuple, list[int]] = {}
    for g, (models, trajectories) in enumerate(groups):
        if len(trajectories):
            buckets.setdefault(_group_key(models), []).append(g)
    batches = []
    for same in buckets.values():  # as many groups at once as the ring loop takes
        models = groups[same[0]][0]
        step = max(1, ring_capacity(models[0].lifting, models[0].A.shape[1], models[0].n_passthrough) // len(models))
        batches += [same[i : i + step] for i in range(0, len(same), step)]
    for members in batches:
        point = groups[members[0]][0][0]
        d, n_p, m, M = point.n_delays, point.n_passthrough, point.n_states, len(groups[members[0]][0])
        T = max(t.n_samples for g in members for t in groups[g][1])
        E = max(len(groups[g][1]) for g in members)
        x_init = np.empty((len(members), E, d + 1, m))
        v = np.zeros((len(members), E, T, point.B.shape[1]))
        p0 = np.zeros((len(members), E, n_p))
        for i, g in enumerate(members):
            models, trajectories = groups[g]
            for e in range(E):
                t = trajectories[min(e, len(trajectories) - 1)]
                x_init[i, e] = t.x[: d + 1]
                v[i, e, : t.n_samples] = models[0].inputs_of(t)
                if n_p:
                    p0[i, e] = _controller_states(t)[d]
        sink = _GroupedSink(T, len(members), E, m, n_p, M)
        sink.prediction[: d + 1] = np.moveaxis(x_init, 2, 0)
        if sink.variance is not None:
            sink.variance[: d + 1] = 0.0
        A = np.stack([model.A for g in members for model in groups[g][0]])
        B = np.stack([model.B for g in members for model in groups[g][0]])
        simulate_chunks(A, B, point.lifting, n_p, x_init, v, p0 if n_p else None, True, sink, paired=True)
        for i, g in enumerate(members):
            for e, t in enumerate(groups[g][1]):
                n = t.n_samples
                variance = None if sink.variance is None else sink.variance[:n, i, e].copy()
                out[g].append(EpisodePrediction(sink.prediction[:n, i, e].copy(), variance))
    return out


def _offset_spread(estimate: OffsetEstimate) -> np.ndarray:
    """The standard deviation each offset counts with: its standard error, at most the bound (the bound when unused)."""
    if not estimate.plausible or estimate.std_error is None:
        return np.full(len(estimate.channels), estimate.bound)
    return np.where(np.isfinite(estimate.std_error), np.minimum(estimate.std_error, estimate.bound), estimate.bound)


def predict_episodes(models: Sequence, trajectories: Sequence[Trajectory], offsets=None) -> list[EpisodePrediction]:
    """Predict episodes with a point model and its members, in one batch (:func:`predict_groups`, one group).

    Parameters
    ----------
    models : sequence of KoopmanModel
        The point model, then its members (all of one lifting and structure); the point alone
        gives no variance.
    trajectories : sequence of Trajectory
        The episodes.
    offsets : OffsetProtocol, optional
        Estimate each episode's offsets (``channels``, ``window(dt)``, ``bound``) with the point
        model first, predict with them, and count their uncertainty.

    Returns
    -------
    list of EpisodePrediction
        In the episodes' order.
    """
    return predict_groups([(models, list(trajectories))], offsets)[0]


def members_variance(prediction: EpisodePrediction) -> np.ndarray:
    """The members' variance of a prediction, which a band needs (a ValueError when it was made without members)."""
    if prediction.variance is None:
        raise ValueError("a band needs the members' spread: the episode was predicted without members")
    return prediction.variance


def diverged_from(prediction: np.ndarray, measured: np.ndarray, start: int) -> int | None:
    """First sample from ``start`` on that is non-finite or beyond the divergence bound, or None."""
    bound = DIVERGED_FACTOR * max(1.0, float(np.nanmax(np.abs(measured[start:]), initial=0.0)))
    with np.errstate(invalid="ignore"):
        beyond = ~(np.abs(prediction[start:]) <= bound).all(axis=1)
    return int(np.argmax(beyond)) + start if beyond.any() else None
