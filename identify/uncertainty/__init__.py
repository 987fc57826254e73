"""Prediction intervals: how far to trust each predicted sample of an episode.

A test episode is predicted from its start for about 19 s; its interval at level ``L`` is, per
sample ``k`` and channel ``c`` (theta, alpha),

    prediction_c(k) +- k_c * sqrt(s_c(k)^2 + q_c * (1 - exp(-h / tau_c))),    h = k - n_delays,

built from three pieces, each measured on data the fit did not use where it can be:

- **Parameter uncertainty, by an episode bootstrap.** ``n_members`` refits on the training
  episodes drawn with replacement (episodes, not samples: a sample's neighbours are not
  independent, an episode of another session is). The statistics are per-episode triangular
  factors, so a resampled fit is one pass that folds each episode's factor, scaled by the
  square root of the times it was drawn (:meth:`~qube_koopman.identify.estimators.regression.Snapshots.repeated`),
  into each member's running total: exactly the fit on the duplicated episodes, with no
  episode lifted or factored twice. Members fit only the rows a re-lifted prediction uses.
  All members predict an episode in one batched simulation; ``s_c(k)`` is their spread
  (standard deviation). The lifting (RBF centres) is the point fit's, not resampled.
- **Offset uncertainty.** With per-episode offsets, each estimate's standard error ``se``
  (:class:`~qube_koopman.identify.models.offsets.OffsetEstimate`) is propagated through the prediction
  linearly: the prediction's sensitivity ``S(k)`` to the offset (one more simulation at the
  offset plus a tenth of an encoder count) adds ``(S(k) se)^2`` to ``s(k)^2``. The prediction is
  nearly affine in the offset (the estimation relies on it too), so this is what drawing the
  offset for every member would give, without the sampling noise of 20 draws. A standard
  error is capped at the plausibility bound, and an estimate beyond the bound (not used)
  counts as one bound of uncertainty: a flat cost widens the band, within what is plausible.
- **Model error, calibrated on held-out training episodes.** The bootstrap sees only how the
  fit varies with the data, not what the lifting cannot represent; on the paper's data that
  is most of the error (the members' spread is about a tenth of the held-out error). The
  training episodes are split into ``n_folds`` groups; each is held out once, predicted by an
  ensemble (point fit and members) fitted on the others exactly as the test episodes are
  (same protocol, offsets, scored samples). From the held-out errors ``e`` and spreads ``s``,
  per channel, ``q_c`` and ``tau_c`` are the Gaussian maximum-likelihood fit of
  ``e ~ N(0, s^2 + q_c (1 - exp(-h / tau_c)))``, and ``k_c`` the ``L`` quantile of
  ``|e| / s_eff`` over every held-out sample, so the pooled held-out coverage is ``L`` whatever
  the shape of the errors' distribution. ``1 - exp(-h / tau)`` is the growth of an AR(1)'s
  prediction variance with the horizon (exact for a first-order loop with white noise); on
  the rig it also absorbs the excitation's schedule (small errors in the first seconds).
  The test set is never looked at.
- **Model error under loops the training never ran, calibrated on the twin's probes.** Held-out
  training episodes ran the training controllers; another controller excites the plant
  differently (a softer arm wanders slowly where the model is least sure), and the error there
  is what matters for transfer. A test episode under such a loop gets ``q_c``, ``tau_c`` and
  ``k_c`` calibrated the same way on the twin's probe episodes (training excitations replayed
  on the twin as the rig's sessions differed: the command delay and the cables' stiffness of
  :func:`~qube_koopman.identify.model_selection.transfer.session_twins`, an episode each in turn,
  :func:`~qube_koopman.identify.model_selection.transfer.twin_probes`),
  predicted by the fit and its members wrapped with each probe's controller
  (:func:`calibrate_on_probes`): per channel, the wider (:func:`widest`) of the calibration on
  probes under the episode's own controller (when its PD gains are known) and that on the
  default probe controllers. The first measures this loop's error on the twin; the second keeps
  a floor for what the twin itself gets wrong under loops the rig never ran, which no data
  measures (with the rig's gains, the twin and the rig give the fit the same held-out error;
  under a soft arm loop the rig's error is twice the calibrated twin's). The session variants
  put the error that depends on the session in the band: on the soft controller's later, slower
  session the band of the search's lifting covered alpha 0.63-0.80 of the time on the one
  calibrated twin, 0.81-0.95 on the variants. It is an estimate from data the fit did not use,
  where the training loop's held-out error is no estimate at all.

A prediction that diverges (non-finite, or beyond :data:`~qube_koopman.identify.metrics.DIVERGED_FACTOR`
times the measured range), or whose bootstrap member diverges, gets an infinite interval from
that sample on, with a :class:`~qube_koopman.identify.metrics.DivergedPrediction` warning: an
unstable refit is a reason not to trust the prediction, not a narrow band.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from qube_koopman.core.files import atomic_path
from qube_koopman.core.lti import same_system
from qube_koopman.identify.models.offsets import (
    OffsetEstimate,
    estimate_offsets_many,
    shift_trajectory,
)
from qube_koopman.identify.metrics import DIVERGED_FACTOR, DivergedPrediction
from qube_koopman.identify.models.simulate import ring_capacity, simulate_chunks
from qube_koopman.identify.estimators.base import episode_statistics
from qube_koopman.identify.estimators.structure import close_loop
from qube_koopman.identify.model_selection.sweep import EPISODES_PER_BATCH  # episodes read and simulated together
from qube_koopman.identify.data.trajectory import Trajectory, as_episodes, select_episodes
from qube_koopman.core.lti import DiscreteStateSpace

if TYPE_CHECKING:
    from qube_koopman.identify.estimators.base import SnapshotEstimator
    from qube_koopman.identify.models.model import KoopmanModel

__all__ = [
    "OFFSET_STEP",
    "BandSummary",
    "EnsembleFit",
    "EpisodePrediction",
    "FoldEnsemble",
    "IntervalCalibration",
    "IntervalOptions",
    "Loop",
    "PredictionBand",
    "bootstrap_counts",
    "calibrate",
    "calibrate_on_probes",
    "widest",
    "ensemble_statistics",
    "episode_folds",
    "fit_ensemble",
    "held_out_figures",
    "held_out_loops",
    "loops_figures",
    "references",
    "loop_figures",
    "predict_episodes",
    "predict_groups",
    "prediction_band",
    "summarize_bands",
]

#: Offset step (rad) of the sensitivity's finite difference: a tenth of an encoder count.
OFFSET_STEP = 3e-4


@dataclass(frozen=True)
class IntervalOptions:
    """How prediction intervals are made (see the module docstring).

    Parameters
    ----------
    level : float
        Coverage asked for, in (0, 1) (``qube-identify --interval``).
    n_members : int
        Bootstrap refits (at least 2).
    n_calibration_members : int
        Bootstrap refits of each calibration fold (at least 2): the calibration needs the spread's
        size on the held-out episodes, not the test band itself, and each member costs a
        prediction of every held-out episode. On the training loop the spread is a small part of
        the held-out error, so few do: with 4 instead of 10 the paper split's bands are the same to
        three decimals with the default lifting and within 0.005 in coverage with the search's, for
        a third less time in the calibration.
    n_probe_members : int
        Members of the fit predicting the twin's probe episodes, which calibrate the bands of loops
        the training never ran (at least 2). Under another loop the spread is a larger part of the
        error: with 4 instead of 10 the soft controller's theta band covered 0.908 instead of 0.919
        (worst episode 0.784 instead of 0.806) with the search's lifting.
    n_folds : int
        Groups of training episodes held out in turn for the calibration (at most one per episode).
    n_calibration_episodes : int
        Training episodes held out at most (drawn at random), so that the calibration's cost does not
        grow with the training set: its few parameters per channel are fitted on thousands of samples.
    seed : int
        Seed of the resampling and of the folds.
    stride : int
        Every ``stride``-th held-out sample enters the calibration (neighbouring samples at 500 Hz
        say nearly the same; this bounds its memory and time).
    other_loops : {"twin", "none"}
        How a test episode under a loop the training never ran is calibrated: on the twin's probe
        episodes under other controllers (``"twin"``), or as the training loop's held-out
        episodes (``"none"``, flagged in the report as a loop the calibration did not see).
    """

    level: float = 0.95
    n_members: int = 20
    n_calibration_members: int = 4
    n_probe_members: int = 10
    n_folds: int = 5
    n_calibration_episodes: int = 16
    seed: int = 0
    stride: int = 5
    other_loops: str = "twin"

    def __post_init__(self) -> None:
        if self.other_loops not in ("twin", "none"):
            raise ValueError(f"other_loops must be 'twin' or 'none', got {self.other_loops!r}")
        if not 0 < self.level < 1:
            raise ValueError(f"the interval's level must be between 0 and 1, got {self.level}")
        counts = (
            self.n_members,
            self.n_calibration_members,
            self.n_probe_members,
            self.n_folds,
            self.n_calibration_episodes,
        )
        if min(int(c) for c in counts) < 2 or int(self.stride) < 1:
            raise ValueError(
                f"intervals need at least 2 members, calibration members, probe members, folds and calibration "
                f"episodes and a stride of 1 or more, got {', '.join(str(c) for c in counts)} and {self.stride}"
            )


@dataclass(frozen=True, eq=False)
class Loop:
    """Which model of a fit predicts an episode.

    Parameters
    ----------
    kind : {"closed", "plant", "wrapped"}
        The fit's closed loop, its plant from the logged input, or its plant wrapped with
        ``controller``.
    controller : DiscreteStateSpace, optional
        The wrapping controller (``"wrapped"``).
    """

    kind: str
    controller: DiscreteStateSpace | None = None

    @classmethod
    def of(cls, controller: DiscreteStateSpace, fitted: DiscreteStateSpace | None, scoring: str = "cl") -> Loop:
        """The loop predicting an episode recorded under ``controller`` by a fit whose closed loop is ``fitted``'s."""
        if scoring == "plant":
            return cls("plant")
        if fitted is not None and same_system(controller, fitted):
            return cls("closed")
        return cls("wrapped", controller)

    def model(self, closed, plant, measured: Sequence[int]):
        """This loop's model of a fit given by its closed loop and plant."""
        if self.kind == "plant":
            return plant
        if self.kind == "closed":
            return closed
        return close_loop(plant, self._wrapping(), measured)

    def same(self, other: Loop) -> bool:
        """Whether the two loops use the same model."""
        return self.kind == other.kind and (self.kind != "wrapped" or same_system(self._wrapping(), other._wrapping()))

    def _wrapping(self) -> DiscreteStateSpace:
        """The controller a ``"wrapped"`` loop wraps the plant with (a ValueError when it has none)."""
        if self.controller is None:
            raise ValueError(f"this {self.kind!r} loop has no controller to wrap the plant with")
        return self.controller


def consecutive_runs(loops: Sequence[Loop], size: int = EPISODES_PER_BATCH) -> list[list[int]]:
    """Indices of consecutive episodes sharing a loop, at most ``size`` at a time (order kept)."""
    runs: list[list[int]] = []
    for i, loop in enumerate(loops):
        if runs and len(runs[-1]) < size and loops[runs[-1][0]].same(loop):
            runs[-1].append(i)
        else:
            runs.append([i])
    return runs


# --- the ensemble ------------------------------------------------------------------------------


def bootstrap_counts(n_episodes: int, n_members: int, rng: np.random.Generator) -> np.ndarray:
    """How many times each episode is drawn in each resample of ``n_episodes`` with replacement.

    Returns
    -------
    ndarray of int of shape (n_members, n_episodes)
        Each row sums to ``n_episodes``.
    """
    return rng.multinomial(n_episodes, np.full(n_episodes, 1.0 / n_episodes), size=n_members)


def episode_folds(
    n_episodes: int, n_folds: int, rng: np.random.Generator, max_held_out: int | None = None
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Episodes drawn at random (``max_held_out`` at most, all by default) and split into ``n_folds`` groups
    (at most one per episode), each held out once; each fold trains on every other episode.

    Returns
    -------
    list of (train_indices, validation_indices)
    """
    held_out = rng.permutation(n_episodes)[: n_episodes if max_held_out is None else int(max_held_out)]
    groups = np.array_split(held_out, min(int(n_folds), held_out.size))
    return [(np.setdiff1d(np.arange(n_episodes), g), np.sort(g)) for g in groups]


def ensemble_statistics(estimator, setup, selections: np.ndarray, elsewhere: Callable | None = None):
    """The statistics of all the setup's episodes and of weighted selections of them, in one pass.

    Each episode is lifted and factored once (here, or ``elsewhere``: see
    :meth:`~qube_koopman.identify.estimators.base.SnapshotEstimator.selection_statistics`), folded into the
    total of all episodes as a plain fit folds it (the same result, bit for bit), and into each
    selection that draws it, its factor scaled by the square root of its count. With a known
    set of rows that re-lifted predictions use (``estimator.relift_rows``), the selections keep
    only those targets (the factor's leading block: no new decomposition).

    Parameters
    ----------
    estimator : SnapshotEstimator
        The estimator, its setup made (``setup_fit``).
    setup : FitSetup
        The setup of all the episodes.
    selections : ndarray of int of shape (n_selections, n_episodes)
        How many times each selection counts each episode (0: left out).
    elsewhere : callable, optional
        Computes the episodes' statistics elsewhere (a dask cluster).

    Returns
    -------
    total : Snapshots or GroupedSnapshots
        Of all the episodes, once each.
    selected : list
        Of each selection.
    """
    selections = np.asarray(selections, dtype=int)
    trajectories = setup.trajectories
    n = len(trajectories)
    if selections.ndim != 2 or selections.shape[1] != n:
        raise ValueError(f"selections must count each of the {n} episodes, got shape {selections.shape}")
    partial = estimator.relift_rows(setup) is not None
    n_lifted, m = setup.lifting.n_features_out_, setup.lifting.n_features_in_
    total = estimator.statistics_fold(setup)
    folds = [estimator.statistics_fold(setup) for _ in selections]
    parts = (
        episode_statistics(estimator, setup, range(n))
        if elsewhere is None
        else elsewhere(estimator, setup, list(range(n)))
    )
    for j, part in enumerate(parts):
        total.add(j, part)
        # The targets are [controller states; lifted plant states]: keep the controller's and the plant's own.
        small = part.leading(part.R.shape[1] - part.n_regressors - n_lifted + m) if partial else part
        for fold, count in zip(folds, selections[:, j]):
            if count:
                fold.add(j, small.repeated(int(count)))
    return total.total(), [fold.total() for fold in folds]


@dataclass
class FoldEnsemble:
    """One calibration fold: the episodes it holds out, its point fit and members on the others.

    Parameters
    ----------
    validation : ndarray of int
        The held-out episodes.
    point : (closed, plant)
        Fitted on the fold's other episodes once each.
    members : list of (closed, plant)
        Fitted on resamples of them.
    """

    validation: np.ndarray
    point: tuple[KoopmanModel | None, KoopmanModel]
    members: list[tuple[KoopmanModel | None, KoopmanModel]]


@dataclass
class EnsembleFit:
    """A fit on all the training episodes, its bootstrap members and the calibration folds' ensembles.

    Parameters
    ----------
    estimator : SnapshotEstimator
        Fitted on all the episodes, as a plain fit is.
    members : list of (closed, plant)
        The bootstrap refits (only the rows re-lifted predictions use; closed None for a plant
        fit without a controller).
    folds : list of FoldEnsemble
    counts : ndarray of int of shape (n_members, n_episodes)
        Each member's draw of the episodes.
    """

    estimator: SnapshotEstimator
    members: list[tuple[KoopmanModel | None, KoopmanModel]]
    folds: list[FoldEnsemble]
    counts: np.ndarray


def fit_ensemble(
    estimator,
    trajectories,
    options: IntervalOptions = IntervalOptions(),
    controllers: Sequence[DiscreteStateSpace] | None = None,
    controller: DiscreteStateSpace | None = None,
    measured: Sequence[int] | None = None,
    elsewhere: Callable | None = None,
) -> EnsembleFit:
    """Fit ``estimator`` on all the episodes, its bootstrap members and the folds' ensembles in one pass.

    Parameters
    ----------
    estimator : SnapshotEstimator
        Unfitted (:class:`~qube_koopman.identify.ClEdmd`, :class:`~qube_koopman.identify.Edmd`, ...);
        it is fitted in place, as :meth:`fit` would.
    trajectories : sequence of Trajectory
        The training episodes (a lazy sequence is read one episode at a time).
    options : IntervalOptions
        Members, folds, seed.
    controllers : sequence of DiscreteStateSpace, optional
        Each episode's controller (a closed-loop estimator's episodes under several).
    controller : DiscreteStateSpace, optional
        Wraps a plant estimator's (EDMD's) members for their closed loops.
    measured : sequence of int, optional
        The fed-back states, for that wrapping.
    elsewhere : callable, optional
        Computes the per-episode statistics elsewhere (a dask cluster).

    Returns
    -------
    EnsembleFit
    """
    from qube_koopman.identify.model_selection.sweep import fitted_models

    trajectories = as_episodes(trajectories)
    n = len(trajectories)
    if n < 2:
        raise ValueError(
            f"prediction intervals are calibrated on held-out training episodes: they need at least 2, got {n}"
        )
    rng = np.random.default_rng(options.seed)
    counts = bootstrap_counts(n, options.n_members, rng)
    splits = episode_folds(n, options.n_folds, rng, options.n_calibration_episodes)
    B, C = options.n_members, options.n_calibration_members
    selections = [counts]
    for train, _ in splits:
        fold = np.zeros((C + 1, n), dtype=int)
        fold[0, train] = 1
        fold[1:, train] = bootstrap_counts(len(train), C, rng)
        selections.append(fold)
    setup = estimator.setup_fit(trajectories) if controllers is None else estimator.setup_fit(trajectories, controllers)
    total, selected = ensemble_statistics(estimator, setup, np.vstack(selections), elsewhere)
    rows = estimator.relift_rows(setup)
    partial = setup if rows is None else dataclasses.replace(setup, target_rows=rows)

    def refit(snapshots) -> tuple:
        closed, plants = fitted_models(estimator, partial, snapshots, [estimator.alpha], controller, measured)
        return closed[0], plants[0]

    models = [refit(s) for s in selected]
    estimator.finish_fit(setup, total)
    folds = [
        FoldEnsemble(validation, models[B + i * (C + 1)], models[B + i * (C + 1) + 1 : B + (i + 1) * (C + 1)])
        for i, (_, validation) in enumerate(splits)
    ]
    return EnsembleFit(estimator, models[:B], folds, counts)


# --- prediction with the spread -----------------------------------------------------------------


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
    shifted = [
        (models, [shift_trajectory(models[0], t, e.as_mapping()) for t, e in zip(trajs, found)])
        for (models, trajs), found in zip(groups, estimates)
    ]
    predicted = _predict_plain_groups(shifted)
    for found, group in zip(estimates, predicted):
        for e, p in zip(found, group):
            for c, value in e.as_mapping().items():
                p.prediction[:, c] += value
    # Each group's point model without its offsets, then (with members) at them with one channel moved.
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
    out = []
    for (models, trajs), found, group, at, o_s in zip(groups, estimates, predicted, plain, runs):
        n = len(trajs)
        for run, o in zip(at, o_s):
            for c, value in o.items():
                run.prediction[:, c] += value
        if len(models) > 1 and found:
            spread = np.array([_offset_spread(e) for e in found])  # (episodes, channels)
            for i in range(len(found[0].channels)):
                for j, p in enumerate(group):
                    assert p.variance is not None  # members give a variance
                    sensitivity = (at[n * (i + 1) + j].prediction - p.prediction) / OFFSET_STEP
                    with np.errstate(invalid="ignore", over="ignore"):
                        p.variance += (sensitivity * spread[j, i]) ** 2
        out.append(
            [
                EpisodePrediction(p.prediction, p.variance, at[j].prediction, e)
                for j, (p, e) in enumerate(zip(group, found))
            ]
        )
    return out


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


# --- calibration ---------------------------------------------------------------------------------


def _growth(horizons: np.ndarray, timescale: float) -> np.ndarray:
    """``1 - exp(-h / tau)`` for positive horizons, 0 at the initial condition."""
    h = np.asarray(horizons, dtype=float)
    return np.where(h > 0, -np.expm1(-np.maximum(h, 0.0) / timescale), 0.0)


def _fit_channel(errors: np.ndarray, variances: np.ndarray, horizons: np.ndarray, level: float):
    """``(q, tau, k)`` of one channel: Gaussian maximum likelihood (in log q, log tau), then the level's quantile."""
    # ndtri: the normal quantile (scipy.stats would add half a second of imports).
    from scipy.optimize import minimize
    from scipy.special import ndtri

    use = np.isfinite(errors) & np.isfinite(variances) & (horizons > 0)
    e2, v, h = errors[use] ** 2, variances[use], horizons[use].astype(float)
    if not np.any(e2 > 0):  # nothing to learn the model error from
        return 0.0, 1.0, float(ndtri(0.5 + level / 2))
    tiny = np.finfo(float).tiny

    @np.errstate(over="ignore", under="ignore")
    def cost(p: np.ndarray) -> tuple[float, np.ndarray]:
        q, tau = np.exp(p)
        decay = np.exp(-h / tau)
        total = np.maximum(v + q * (1.0 - decay), tiny)
        slope = (total - e2) / total**2  # d cost / d total, per sample
        gradient = [np.mean(slope * q * (1.0 - decay)), np.mean(slope * -q * decay * h / tau)]
        return float(np.mean(np.log(total) + e2 / total)), np.array(gradient)

    start = [np.log(np.mean(e2)), np.log(max(float(np.median(h)) / 10, 1.0))]
    best = minimize(cost, start, jac=True, method="L-BFGS-B", bounds=[(None, None), (np.log(1e-3), np.log(1e9))])
    q, tau = float(np.exp(best.x[0])), float(np.exp(best.x[1]))
    s = np.sqrt(v + q * _growth(h, tau))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(e2 > 0, np.sqrt(e2) / s, 0.0)
    return q, tau, float(np.quantile(ratio, level, method="higher"))


#: Horizons (samples predicted) at which reports give a calibration's half-width (0.2, 2 and 20 s at 500 Hz).
REPORTED_HORIZONS = (100, 1000, 10000)


class IntervalCalibration:
    """The band's half-width ``k_c sqrt(s^2 + q_c (1 - exp(-h / tau_c)))``, fitted on held-out errors.

    Parameters
    ----------
    level : float
        The coverage the factor ``k_c`` gives on the held-out samples.

    Attributes
    ----------
    scale_ : ndarray of shape (n_states,)
        ``q_c``, the model error's variance at long horizons (squared state units).
    timescale_ : ndarray of shape (n_states,)
        ``tau_c`` in samples.
    factor_ : ndarray of shape (n_states,)
        ``k_c``.
    coverage_ : ndarray of shape (n_states,)
        The held-out samples' coverage with these.
    n_samples_ : int
        Held-out samples (per channel) the fit used.
    n_diverged_ : int
        Held-out predictions that diverged (:func:`calibrate`; their samples from there are left out).
    parts_ : tuple of IntervalCalibration
        Set by :func:`widest`: the calibrations whose widest band, at each horizon, this one's is
        (``scale_``, ``timescale_`` and ``factor_`` are then those of the band widest at long horizons,
        for the reports); empty for a calibration fitted on its own.
    """

    parts_: tuple = ()

    def __init__(self, level: float = 0.95) -> None:
        self.level = level

    def fit(self, errors: np.ndarray, variances: np.ndarray, horizons: np.ndarray) -> IntervalCalibration:
        """Fit each channel on held-out samples.

        Parameters
        ----------
        errors, variances : ndarray of shape (n, n_states)
            Measured minus predicted, and the members' (and offsets') variance, of each sample.
        horizons : ndarray of shape (n,)
            Steps predicted since the initial condition (``sample - n_delays``).

        Returns
        -------
        self
        """
        errors, variances = np.asarray(errors, dtype=float), np.asarray(variances, dtype=float)
        horizons = np.asarray(horizons)
        fits = np.array(
            [_fit_channel(errors[:, c], variances[:, c], horizons, self.level) for c in range(errors.shape[1])]
        )
        self.scale_, self.timescale_, self.factor_ = fits[:, 0], fits[:, 1], fits[:, 2]
        with np.errstate(invalid="ignore"):
            inside = np.abs(errors) <= self.half_width(variances, horizons)
        self.coverage_ = inside.mean(axis=0) if len(errors) else np.full(errors.shape[1], np.nan)
        self.n_samples_ = len(errors)
        self.n_diverged_ = 0
        return self

    def half_width(self, variances: np.ndarray, horizons: np.ndarray) -> np.ndarray:
        """Half-widths of samples with these variances (..., n_states) at these horizons (...,)."""
        if self.parts_:
            return np.maximum.reduce([part.half_width(variances, horizons) for part in self.parts_])
        h = np.asarray(horizons)
        growth = np.stack([_growth(h, tau) for tau in self.timescale_], axis=-1)
        total = np.asarray(variances, dtype=float) + self.scale_ * growth
        with np.errstate(invalid="ignore"):
            return np.where(np.isnan(total), np.inf, self.factor_ * np.sqrt(total))

    def as_dict(self, names: Sequence[str]) -> dict:
        """Plain data for reports, by channel name.

        ``model_error_half_width``: the band's half-width without refits or offsets (``s = 0``) after
        :data:`REPORTED_HORIZONS` samples predicted. It is what the band is at those horizons, whatever
        the parameters: an error that grows as a random walk over every horizon the calibration saw
        fits ``q`` and ``tau`` both at their largest (the variance ``q h / tau``), a scale of many
        radians and a timescale of weeks that mean nothing alone.
        """
        h = np.array(REPORTED_HORIZONS, dtype=float)
        widths = self.half_width(np.zeros((h.size, len(self.scale_))), h)
        return {
            name: {
                "scale": float(np.sqrt(q)),
                "timescale_samples": float(tau),
                "factor": float(k),
                "held_out_coverage": float(cov),
                "model_error_half_width": {str(n): float(w) for n, w in zip(REPORTED_HORIZONS, widths[:, c])},
            }
            for c, (name, q, tau, k, cov) in enumerate(
                zip(names, self.scale_, self.timescale_, self.factor_, self.coverage_)
            )
        }


def calibrate(
    fit: EnsembleFit,
    trajectories,
    loops: Sequence[Loop],
    level: float,
    start: int = 1,
    offsets=None,
    measured: Sequence[int] | None = None,
    stride: int = 5,
    points: dict[int, tuple[Trajectory, np.ndarray]] | None = None,
) -> IntervalCalibration:
    """Calibrate the band on the folds' held-out episodes, predicted as test episodes are.

    Parameters
    ----------
    fit : EnsembleFit
        Its folds' ensembles.
    trajectories : sequence of Trajectory
        The training episodes the fit was made on (a lazy sequence is read a batch at a time).
    loops : sequence of Loop
        The loop predicting each of them.
    level : float
        The coverage asked for.
    start : int
        First scored sample of each episode (the end of the offsets' window, as the test's).
    offsets : OffsetProtocol, optional
        Estimate each held-out episode's offsets first, as the test episodes'.
    measured : sequence of int, optional
        The fed-back states (for wrapped loops).
    stride : int
        Every ``stride``-th scored sample is used.
    points : dict, optional
        Filled with ``{index: (trajectory, prediction)}`` of the held-out episodes predicted in
        closed loop (not under a ``"plant"`` loop): the prediction by the fold's point fit,
        without offsets. :func:`held_out_figures` takes them instead of predicting again.

    Returns
    -------
    IntervalCalibration
    """
    trajectories = as_episodes(trajectories)
    groups, indices = [], []  # (models, held-out episodes) of every fold's runs of one loop; their indices
    for fold in fit.folds:
        held_out = select_episodes(trajectories, fold.validation)
        for run in consecutive_runs([loops[j] for j in fold.validation]):
            loop = loops[fold.validation[run[0]]]
            models = [loop.model(*fold.point, measured)] + [loop.model(*m, measured) for m in fold.members]
            groups.append((models, [held_out[i] for i in run]))
            indices.append([int(fold.validation[i]) for i in run])
    predictions = predict_groups(groups, offsets)  # the folds' ensembles together
    if points is not None:
        for idx, (_, trajs), predicted in zip(indices, groups, predictions):
            points.update(
                (j, (t, p.prediction if p.plain is None else p.plain))
                for j, t, p in zip(idx, trajs, predicted)
                if loops[j].kind != "plant"
            )
    errors, variances, horizons, diverged = [], [], [], 0
    for (models, trajs), predicted in zip(groups, predictions):
        d = models[0].n_delays
        for t, p in zip(trajs, predicted):
            # A diverged held-out prediction says nothing about the size of the errors: left out from there.
            end = _diverged_from(p.prediction, t.x, start) or t.n_samples
            diverged += end < t.n_samples
            k = np.arange(max(start, d + 1), end, stride)
            errors.append(t.x[k] - p.prediction[k])
            variances.append(_members_variance(p)[k])
            horizons.append(k - d)
    calibration = IntervalCalibration(level).fit(
        np.concatenate(errors), np.concatenate(variances), np.concatenate(horizons)
    )
    calibration.n_diverged_ = diverged
    return calibration


def calibrate_on_probes(
    fit: EnsembleFit,
    probes,
    level: float,
    start: int = 1,
    offsets=None,
    measured: Sequence[int] | None = None,
    stride: int = 5,
    n_members: int | None = None,
) -> IntervalCalibration:
    """Calibrate the band of loops the training never ran on the twin's probe episodes.

    The probes are not training data, so the fit on all the training episodes and its members
    predict them (each wrapped with its probe's controller) as test episodes are predicted, and
    :func:`calibrate` fits the model error of those predictions.

    Parameters
    ----------
    fit : EnsembleFit
        The fit and its bootstrap members.
    probes : ProbeSet
        Twin episodes under probe controllers
        (:func:`~qube_koopman.identify.model_selection.transfer.twin_probes`).
    level : float
        The coverage asked for.
    start : int
        First scored sample of each episode (the end of the offsets' window, as the test's).
    offsets : OffsetProtocol, optional
        Estimate each probe episode's offsets first, as the test episodes'.
    measured : sequence of int, optional
        The fed-back states.
    stride : int
        Every ``stride``-th scored sample is used.
    n_members : int, optional
        Members predicting the probes (all when None): the spread's size is what the
        calibration needs, as the folds' fewer members give it.

    Returns
    -------
    IntervalCalibration
    """
    estimator = fit.estimator  # a closed-loop fit's plant, or EDMD's model of the plant
    point = (getattr(estimator, "closed_loop_model_", None), getattr(estimator, "plant_model_", estimator.model_))
    members = fit.members if n_members is None else fit.members[:n_members]
    episodes = [episode for group in probes.episodes for episode in group]
    loops = [
        Loop("wrapped", controller) for controller, group in zip(probes.controllers, probes.episodes) for _ in group
    ]
    on_probes = dataclasses.replace(fit, folds=[FoldEnsemble(np.arange(len(episodes)), point, members)])
    return calibrate(on_probes, episodes, loops, level, start, offsets, measured, stride)


def widest(calibrations: Sequence[IntervalCalibration]) -> IntervalCalibration:
    """Per channel and horizon, the widest of the calibrations' bands.

    A band that grows slowly to a wide limit can be the narrower one over the horizons an episode
    lasts (a timescale of 19 s against 5 s on a 20 s episode), so the band is the widest at each
    horizon, not the one widest at long horizons alone. The reports' numbers (``scale_``,
    ``timescale_``, ``factor_``) are, per channel, those of the band widest at long horizons
    (largest ``k_c sqrt(q_c)``).

    Parameters
    ----------
    calibrations : sequence of IntervalCalibration
        Fitted, of the same level and channels.

    Returns
    -------
    IntervalCalibration
        A new calibration: its half-width the calibrations' largest at each horizon (``parts_``), each
        channel's scale, timescale and factor from the one widest at long horizons (the counts of
        samples and diverged predictions are summed).
    """
    calibrations = list(calibrations)
    width = np.array([c.factor_ * np.sqrt(c.scale_) for c in calibrations])
    pick = np.argmax(width, axis=0)
    out = IntervalCalibration(calibrations[0].level)
    for name in ("scale_", "timescale_", "factor_", "coverage_"):
        values = np.array([getattr(c, name) for c in calibrations])
        setattr(out, name, values[pick, np.arange(values.shape[1])])
    out.n_samples_ = sum(c.n_samples_ for c in calibrations)
    out.n_diverged_ = sum(c.n_diverged_ for c in calibrations)
    out.parts_ = tuple(part for c in calibrations for part in (c.parts_ or (c,)))
    return out


# --- bands ------------------------------------------------------------------------------------


@dataclass
class PredictionBand:
    """One episode's prediction and interval over its scored samples.

    Parameters
    ----------
    name : str
        The episode (its log's file name).
    t : ndarray of shape (n,)
        Time of each scored sample from the episode's start (s).
    measured, predicted, lower, upper : ndarray of shape (n, n_states)
        The band is ``lower <= measured <= upper`` at the ``level``; infinite where the
        prediction or a bootstrap member diverged. ``measured`` is NaN for an episode recorded
        under another controller than the one predicted (not scored).
    level : float
    scored : bool
        Whether the measured states belong to the predicted loop.
    diverged_at : int or None
        First sample (of the episode) from which the band is infinite.
    calibrated_loop : bool
        Whether the predicted loop is one the calibration's held-out episodes ran.
    calibration : {"held-out", "twin probes"}
        What the band's model error was calibrated on: held-out training episodes, or (a loop
        the training never ran) the twin's probe episodes under other controllers.
    """

    name: str
    t: np.ndarray
    measured: np.ndarray
    predicted: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    level: float
    scored: bool = True
    diverged_at: int | None = None
    calibrated_loop: bool = True
    calibration: str = "held-out"

    def inside(self) -> np.ndarray:
        """Whether each measured sample is within the band, per channel."""
        with np.errstate(invalid="ignore"):
            return (self.lower <= self.measured) & (self.measured <= self.upper)

    def coverage(self) -> np.ndarray:
        """Share of the samples within the band, per channel."""
        return self.inside().mean(axis=0)

    def mean_half_width(self) -> np.ndarray:
        """Mean half-width per channel (inf when the band is infinite anywhere)."""
        with np.errstate(invalid="ignore"):
            return np.mean((self.upper - self.lower) / 2, axis=0)

    def rms_error(self) -> np.ndarray:
        """RMS of measured minus predicted per channel (inf when the prediction diverged)."""
        with np.errstate(invalid="ignore", over="ignore"):
            rms = np.sqrt(np.mean((self.measured - self.predicted) ** 2, axis=0))
        return np.where(np.isnan(rms) & self.scored, np.inf, rms)

    def save(self, path: str | Path) -> None:
        """Write the arrays to ``path`` (``.npz``: t, measured, predicted, lower, upper, level), whole or not at all."""
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez(
                f,
                t=self.t,
                measured=self.measured,
                predicted=self.predicted,
                lower=self.lower,
                upper=self.upper,
                level=np.float64(self.level),
            )


def _members_variance(prediction: EpisodePrediction) -> np.ndarray:
    """The members' variance of a prediction, which a band needs (a ValueError when it was made without members)."""
    if prediction.variance is None:
        raise ValueError("a band needs the members' spread: the episode was predicted without members")
    return prediction.variance


def _diverged_from(prediction: np.ndarray, measured: np.ndarray, start: int) -> int | None:
    """First sample from ``start`` on that is non-finite or beyond the divergence bound, or None."""
    bound = DIVERGED_FACTOR * max(1.0, float(np.nanmax(np.abs(measured[start:]), initial=0.0)))
    with np.errstate(invalid="ignore"):
        beyond = ~(np.abs(prediction[start:]) <= bound).all(axis=1)
    return int(np.argmax(beyond)) + start if beyond.any() else None


def prediction_band(
    name: str,
    trajectory: Trajectory,
    prediction: EpisodePrediction,
    calibration: IntervalCalibration,
    start: int,
    n_delays: int,
    scored: bool = True,
) -> PredictionBand:
    """The band of one predicted episode over its samples from ``start`` on.

    A diverged prediction, or a diverged member (infinite variance), makes the band infinite
    from there, with a :class:`~qube_koopman.identify.metrics.DivergedPrediction` warning.

    Parameters
    ----------
    name : str
        The episode's name.
    trajectory : Trajectory
        Its measured signals.
    prediction : EpisodePrediction
        From :func:`predict_episodes` (with members).
    calibration : IntervalCalibration
        Fitted.
    start : int
        First scored sample.
    n_delays : int
        The model's delays (horizon = sample - n_delays).
    scored : bool
        Whether the measured states belong to the predicted loop (else stored as NaN).

    Returns
    -------
    PredictionBand
    """
    x, pred = trajectory.x, prediction.prediction
    k = np.arange(start, trajectory.n_samples)
    half = calibration.half_width(_members_variance(prediction)[k], k - n_delays)
    diverged = _diverged_from(pred, x, start)
    infinite = ~np.isfinite(half).all(axis=1)
    first_infinite = int(k[np.argmax(infinite)]) if infinite.any() else None
    candidates = [s for s in (diverged, first_infinite) if s is not None]
    at = min(candidates) if candidates else None
    with np.errstate(invalid="ignore"):
        lower, upper = pred[k] - half, pred[k] + half
    if at is not None:
        lower[k >= at], upper[k >= at] = -np.inf, np.inf
        why = "the prediction diverged" if diverged is not None and diverged <= at else "a bootstrap refit diverged"
        dt = trajectory.dt or 0.0
        warnings.warn(
            f"{name}: the prediction interval is infinite from sample {at} ({at * dt:.2f} s): {why}",
            DivergedPrediction,
            stacklevel=2,
        )
    measured = x[k] if scored else np.full_like(pred[k], np.nan)
    t = k * (trajectory.dt or 1.0)
    return PredictionBand(name, t, measured, pred[k].copy(), lower, upper, calibration.level, scored, at)


def _channel_dict(names: Sequence[str], values: np.ndarray) -> dict:
    return {n: float(v) for n, v in zip(names, values)}


class BandSummary:
    """Coverage, mean half-width and RMS error per channel, gathered band by band (no band kept).

    Parameters
    ----------
    names : sequence of str
        The channels' names.
    """

    def __init__(self, names: Sequence[str]) -> None:
        self.names = list(names)
        self.episodes: list[dict] = []
        m = len(self.names)
        self._inside, self._half, self._squared = np.zeros(m), np.zeros(m), np.zeros(m)
        self._worst, self._n, self._infinite, self._elsewhere, self._probed = np.ones(m), 0, 0, 0, 0

    def add(self, band: PredictionBand) -> None:
        """Count one band (an unscored one is left out)."""
        if not band.scored:
            return
        coverage = band.coverage()
        self.episodes.append(
            {
                "log": band.name,
                "coverage": _channel_dict(self.names, coverage),
                "mean_half_width": _channel_dict(self.names, band.mean_half_width()),
                "rms_error": _channel_dict(self.names, band.rms_error()),
                "infinite_from_sample": band.diverged_at,
                "calibrated_loop": band.calibrated_loop,
                "calibration": band.calibration,
            }
        )
        n = len(band.t)
        with np.errstate(invalid="ignore", over="ignore"):
            self._inside += coverage * n
            self._half += np.sum((band.upper - band.lower) / 2, axis=0)
            self._squared += np.sum((band.measured - band.predicted) ** 2, axis=0)
        self._worst = np.minimum(self._worst, coverage)
        self._n += n
        self._infinite += band.diverged_at is not None
        self._elsewhere += not band.calibrated_loop and band.calibration == "held-out"
        self._probed += band.calibration == "twin probes"

    def report(self) -> dict:
        """``pooled`` (``coverage``, ``mean_half_width``, ``rms_error``, ``worst_episode_coverage``,
        ``n_samples``, ``n_infinite``: bands infinite somewhere, ``n_uncalibrated_loop``: bands of a loop
        nothing calibrated, ``n_probe_calibrated``: bands of a loop calibrated on the twin's probes; None
        when no band was scored) and ``episodes`` (one entry per scored band)."""
        if not self._n:
            return {"pooled": None, "episodes": self.episodes}
        with np.errstate(invalid="ignore"):
            rms = np.sqrt(self._squared / self._n)
        return {
            "pooled": {
                "coverage": _channel_dict(self.names, self._inside / self._n),
                "mean_half_width": _channel_dict(self.names, self._half / self._n),
                "rms_error": _channel_dict(self.names, np.where(np.isnan(rms), np.inf, rms)),
                "worst_episode_coverage": _channel_dict(self.names, self._worst),
                "n_samples": self._n,
                "n_infinite": self._infinite,
                "n_uncalibrated_loop": self._elsewhere,
                "n_probe_calibrated": self._probed,
            },
            "episodes": self.episodes,
        }


def summarize_bands(bands: Sequence[PredictionBand], names: Sequence[str]) -> dict:
    """:class:`BandSummary` of ``bands``: coverage, mean half-width and RMS error per channel and episode.

    Parameters
    ----------
    bands : sequence of PredictionBand
    names : sequence of str
        The channels' names.

    Returns
    -------
    dict
        See :meth:`BandSummary.report`.
    """
    summary = BandSummary(names)
    for band in bands:
        summary.add(band)
    return summary.report()


# --- what a design needs of the uncertainty ------------------------------------------------------


def loop_figures(x: np.ndarray, target_theta: np.ndarray, voltage: np.ndarray, skip: int) -> np.ndarray:
    """``[J, voltage RMS, voltage peak]`` of one episode after ``skip`` samples (inf when non-finite).

    ``J = mean((theta - target_theta)^2) + mean(alpha^2)``, the cost ``qube-design`` predicts.

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
    return np.array([np.mean(tracking**2) + np.mean(alpha**2), np.sqrt(np.mean(u**2)), np.max(np.abs(u), initial=0.0)])


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
