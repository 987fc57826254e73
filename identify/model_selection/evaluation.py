"""Evaluating one lifting search candidate on the search's folds: cross-validated over the alpha
grid (:func:`evaluate_candidate`), screened on its first folds (:func:`screen_candidate`), or scored
on same-controller folds (:func:`same_controller_scores`); what every evaluation needs
(:class:`SearchData`) and what an offsets candidate takes from its plain twin (:class:`Reuse`).

The closed loop predicts each validation episode's measured states from the episode's start, under
the recorded controller, and R^2 is taken from the end of the offset estimation window on (the same
samples whether offsets are estimated or not, so the two protocols compare). A candidate's
statistics are computed once per episode and merged per fold, and every alpha is then a small solve
on them (:func:`~qube_koopman.identify.model_selection.sweep.regularization_sweep`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from qube_koopman.core.lti import DiscreteStateSpace
from qube_koopman.identify.data.trajectory import Trajectory, as_episodes
from qube_koopman.identify.estimators.cl_edmd import ClEdmd
from qube_koopman.identify.model_selection.candidate_scores import (
    best_alphas,
    fold_scores,
    offset_scores,
    probe_plants,
    transfer_scores,
)
from qube_koopman.identify.model_selection.lifting_space import LiftingSpec, search_steps
from qube_koopman.identify.model_selection.ranking import TIMING_KEYS, CandidateResult
from qube_koopman.identify.model_selection.sweep import SweepOptions, regularization_sweep
from qube_koopman.identify.model_selection.transfer import ProbeSet
from qube_koopman.identify.models.model import FittedRows
from qube_koopman.identify.models.offsets import DEFAULT_BOUND

__all__ = [
    "SearchData",
    "Reuse",
    "evaluate_candidate",
    "screen_candidate",
    "same_controller_scores",
    "SameControllerFolds",
]


@dataclass(frozen=True)
class Reuse:
    """A plain candidate's models at its best alphas, for the same lifting with offsets.

    The offsets stage scores the best plain candidates again with per-episode offsets, at
    their best alphas: with these (each fold's closed loop, and the plant on all training
    episodes, as :class:`~qube_koopman.identify.models.model.FittedRows`) it predicts without
    computing any statistics again; the models are exactly the ones the plain candidate fitted.

    Attributes
    ----------
    lifting : Lifting
        The fitted lifting every model shares.
    folds : list of (dict of int to FittedRows, ndarray)
        Per fold: the closed loop at each kept alpha index, and the validation episodes.
    plants : dict of int to FittedRows
        The plant fitted on all training episodes at each kept alpha index.
    """

    lifting: object
    folds: list
    plants: dict

    def covers(self, indices) -> bool:
        """Whether models at every alpha index in ``indices`` are kept."""
        return all(int(j) in self.plants and all(int(j) in f for f, _ in self.folds) for j in indices)


@dataclass(frozen=True)
class SearchData:
    """What every candidate evaluation needs (sent once to each worker)."""

    trajectories: Sequence[Trajectory]  # a list, or a lazy sequence (logs read when needed)
    splits: list[tuple[np.ndarray, np.ndarray]]
    controller: DiscreteStateSpace
    alphas: np.ndarray
    window: int
    bound: float = DEFAULT_BOUND
    rbf_seed: int = 0
    probes: ProbeSet | None = None
    n_transfer_alphas: int = 3
    #: Alphas an offsets candidate is scored at: its plain twin's best (:attr:`~.SearchSpace.n_offset_alphas`).
    n_offset_alphas: int = 3
    #: Each episode's controller when they ran several (None: all ran ``controller``).
    controllers: list[DiscreteStateSpace] | None = None


def evaluate_candidate(
    spec: LiftingSpec,
    data: SearchData,
    stage: str = "",
    plain: "np.ndarray | CandidateResult | None" = None,
    shared: tuple | None = None,
    screen: "CandidateResult | None" = None,
) -> CandidateResult:
    """Cross-validate one lifting over the alpha grid (see the module docstring).

    With ``spec.offsets``, ``plain`` (the same lifting's fold scores without offsets,
    when already known) picks the alphas to estimate offsets at, instead of scoring
    the folds again; given as that candidate's :class:`~.CandidateResult`, its models
    (:attr:`~.CandidateResult.reuse`) predict again without any statistics computed.
    ``shared``: the fold statistics of a lifting whose features include this one's
    (:func:`~.family_statistics`), from which this one's are taken exactly.
    ``screen``: this lifting's screen (:func:`screen_candidate`): its lifting, its statistics
    (when it computed them) and its scores are used again, and only the folds and probe alphas
    it left out are scored: the same numbers as an evaluation from scratch.
    """
    return _evaluate(spec, data, stage, plain, shared, screen)[0]


def _evaluate(
    spec: LiftingSpec,
    data: SearchData,
    stage: str,
    plain,
    shared: tuple | None,
    screen: "CandidateResult | None",
    steps: list | None = None,
) -> tuple:
    """:func:`evaluate_candidate` (``steps``: its lifting, when already built), and its folds' models at every
    alpha (per fold: {alpha index: closed loop}, validation episodes)."""
    started = time.perf_counter()
    timing = dict.fromkeys(TIMING_KEYS, 0.0)
    top = None if plain is None else best_alphas(fold_scores(plain), data.n_offset_alphas)
    reuse = plain.reuse if isinstance(plain, CandidateResult) else None
    if spec.offsets and reuse is not None and top is not None and reuse.covers(top):  # top: set with any plain
        cv = offset_scores(reuse.folds, reuse.lifting, data, top, timing)
        plants = {j: rows.model(reuse.lifting) for j, rows in reuse.plants.items()}
        transfer = None if data.probes is None else transfer_scores(spec, data, cv, plants, timing)
        return CandidateResult(
            spec, stage, np.asarray(data.alphas, dtype=float), cv, time.perf_counter() - started, transfer, timing
        ), []
    screened_folds = []
    if screen is not None:
        if screen.kept is None:
            raise ValueError(f"{spec.label()}: the screen given kept nothing (its lifting, statistics and folds)")
        steps, statistics, screened_folds = screen.kept
        shared = statistics if statistics is not None else shared
    elif steps is None:
        steps = search_steps(spec, data.trajectories, data.rbf_seed)
    estimator = ClEdmd(data.controller, lifting=steps)
    n_screened = len(screened_folds)
    splits = data.splits[n_screened:]
    if shared is not None and n_screened:
        shared = type(shared)((shared[0], shared[1][n_screened:], *shared[2:]))
    rescore = not spec.offsets or plain is None
    # A lifting that learns from each fold's episodes has no lifting the folds share: its models are kept whole.
    subset = not any(getattr(step, "learns_from_data", True) for step in estimator.lifting)
    sweep = regularization_sweep(
        estimator,
        data.trajectories,
        data.alphas,
        splits,
        scorings=("cl",) if rescore else (),
        controllers=data.controllers,
        options=SweepOptions(
            score_from=data.window,
            measured_only=True,
            keep_fold_models="rows" if subset else spec.offsets,
            fit_all=False,
            shared=shared,
        ),
    )
    timing |= sweep.seconds
    cv = sweep.cv_r2["cl"] if rescore else fold_scores(plain)
    if screen is not None and n_screened:  # only a screen has screened folds
        cv = np.vstack([screen.cv_r2, cv])
    lifting = None if sweep.statistics is None else sweep.statistics[0].lifting
    folds = screened_folds + [
        ({j: rows for j, rows in enumerate(closed)}, validation) for closed, _, validation in sweep.fold_models or []
    ]
    if spec.offsets:
        top = best_alphas(cv, data.n_offset_alphas)
        cv = offset_scores(folds, lifting, data, top, timing)
    transfer, plants = None, {}
    if data.probes is not None:
        plants = probe_plants(estimator, data, cv, sweep.statistics, timing)
        transfer = transfer_scores(spec, data, cv, plants, timing, None if screen is None else screen.transfer_r2)
    kept = None
    if not spec.offsets and lifting is not None:
        best = [int(j) for j in best_alphas(cv, data.n_offset_alphas)]
        kept = Reuse(
            lifting,
            [({j: f[j] for j in best}, v) for f, v in folds],
            {j: FittedRows.of(m) for j, m in plants.items() if j in best},
        )
    return CandidateResult(
        spec, stage, np.asarray(data.alphas, dtype=float), cv, time.perf_counter() - started, transfer, timing, kept
    ), folds


def screen_candidate(
    spec: LiftingSpec, data: SearchData, stage: str = "", shared: tuple | None = None, n_folds: int = 1
) -> CandidateResult:
    """A lifting's screen: its first ``n_folds`` folds scored over the alpha grid, and its transfer at
    the alpha that scores best on them only.

    A stage gives the full evaluation (:func:`evaluate_candidate` with ``screen=``) to the
    candidates that screen best (:attr:`~.SearchSpace.n_finalists`). The screen's statistics are those
    of every fold (one pass over the episodes computes them all); it keeps them, its lifting
    and its folds' models (:attr:`~.CandidateResult.kept`), so a finalist scores only the
    other folds and the other probe alphas: the same numbers as a full evaluation from scratch.
    ``shared``: as for :func:`evaluate_candidate` (then the screen does not keep them: the
    stage has them).

    Returns
    -------
    CandidateResult
        Its ``cv_r2`` has ``n_folds`` rows; its ``transfer_r2`` one scored alpha.
    """
    from qube_koopman.core.blas import limited_blas_threads
    from qube_koopman.identify.model_selection.sweep import OwnStatistics, fold_statistics

    started = time.perf_counter()
    # Statistics of this very lifting hold its steps (RBF centres drawn already).
    steps = (
        list(shared[0].lifting.steps)
        if isinstance(shared, OwnStatistics)
        else search_steps(spec, data.trajectories, data.rbf_seed)
    )
    own = shared is None
    if shared is None:
        with limited_blas_threads(1):
            shared = OwnStatistics(
                fold_statistics(
                    ClEdmd(data.controller, lifting=steps), data.trajectories, data.splits, data.controllers
                )
            )
    seconds = time.perf_counter() - started
    screen_data = replace(data, splits=data.splits[:n_folds], n_transfer_alphas=1)
    result, folds = _evaluate(
        spec, screen_data, stage, None, type(shared)((shared[0], shared[1][:n_folds], *shared[2:])), None, steps
    )
    result.timing["statistics"] += seconds
    result.seconds = time.perf_counter() - started
    result.reuse = None
    result.kept = (steps, shared if own else None, folds)
    return result


@dataclass(frozen=True)
class SameControllerFolds:
    """The folds :func:`same_controller_scores` scores a candidate on.

    Parameters
    ----------
    n_splits : int
        Folds per controller (:func:`~qube_koopman.identify.model_selection.split.within_controller_splits`).
    seed : int
        Seed of the folds' draw.
    loops : sequence of DiscreteStateSpace, optional
        Each episode's loop when it is not its controller alone (a session's command delay
        after it); a fold whose validation episodes ran several loops is scored as one fold per loop.
    """

    n_splits: int = 3
    seed: int = 1234
    loops: Sequence[DiscreteStateSpace] | None = None


def same_controller_scores(
    result: CandidateResult,
    trajectories: Sequence[Trajectory],
    controller: DiscreteStateSpace,
    controllers: Sequence[DiscreteStateSpace],
    *,
    window: int,
    folds: SameControllerFolds = SameControllerFolds(),
    bound: float = DEFAULT_BOUND,
    rbf_seed: int = 0,
) -> list[tuple[int, float]]:
    """A candidate's same-controller score when the training episodes ran several controllers.

    The search ranks by per-controller folds
    (:func:`~qube_koopman.identify.model_selection.split.per_controller_splits`); this scores the
    candidate (its lifting, offset protocol and chosen alpha) on folds that
    hold out some episodes of one controller and train on all the rest
    (:func:`~qube_koopman.identify.model_selection.split.within_controller_splits`), as the
    loop a model was trained under is predicted.

    Parameters
    ----------
    result : CandidateResult
        The candidate (the search's winner).
    trajectories : sequence of Trajectory
        The training episodes.
    controller : DiscreteStateSpace
        The candidate's closed loop (the majority's controller).
    controllers : sequence of DiscreteStateSpace
        Each episode's recorded controller.
    window : int
        First scored sample of every validation episode.
    folds : SameControllerFolds
        How many folds per controller, their seed, and each episode's loop.
    bound : float
        Plausibility bound of the offset estimates (rad).
    rbf_seed : int
        Seed of the RBF centres.

    Returns
    -------
    list of (controller label, fold R^2)
        Labels index :func:`~qube_koopman.identify.estimators.mixed.distinct_controllers`' list.
    """
    from qube_koopman.identify.estimators.mixed import distinct_controllers
    from qube_koopman.identify.model_selection.split import split_by_loop, within_controller_splits

    loops = folds.loops
    _, labels = distinct_controllers(controllers)
    splits = within_controller_splits(labels, folds.n_splits, folds.seed)
    if loops is not None:
        loop_labels = distinct_controllers(loops)[1]
        splits = [(tr, va, label) for tr0, va0, label in splits for tr, va in split_by_loop([(tr0, va0)], loop_labels)]
    data = SearchData(
        as_episodes(trajectories),
        [(tr, va) for tr, va, _ in splits],
        controller,
        np.array([result.best_alpha]),
        int(window),
        bound,
        rbf_seed,
        None,
        controllers=list(controllers if loops is None else loops),
    )
    cv = evaluate_candidate(result.spec, data).cv_r2[:, 0]
    return [(label, float(score)) for (_, _, label), score in zip(splits, cv)]
