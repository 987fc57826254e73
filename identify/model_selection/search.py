"""Lifting search: choose the lifting, the regularization and the offset protocol on the
training episodes only, for the question users ask: transfer to another controller.

Every candidate is scored twice. Cross-validation: the way the test episodes will be, its closed loop
predicts each validation episode's measured states from the episode's start, under the recorded
controller (:mod:`~qube_koopman.identify.model_selection.evaluation`). Transfer: with probes
(:mod:`~qube_koopman.identify.model_selection.transfer`), its plant fitted on all the training
episodes, wrapped with probe controllers unlike the training one, predicts twin episodes run under
them (:mod:`~qube_koopman.identify.model_selection.candidate_scores`). Candidates rank by the lower
of the two, and of those within a standard error of the best, the one that transfers best leads each
stage and wins (:mod:`~qube_koopman.identify.model_selection.ranking`).

The space is searched in stages, each a coordinate step from the best so far (a full product of
the default space would be about 1,400 liftings; the stages and the space:
:mod:`~qube_koopman.identify.model_selection.lifting_space`). A family's largest lifting is lifted
once for every candidate of a stage whose features it holds
(:mod:`~qube_koopman.identify.model_selection.families`); a screened stage scores every candidate
on its first folds and evaluates the best few in full (successive halving).

Candidates of a stage are independent: they run through joblib on local cores
(:attr:`SearchSettings.n_jobs`), or on a dask.distributed cluster (see :func:`search_liftings` and
:mod:`~qube_koopman.identify.model_selection.distributed`). This module runs the stages; the
names of the modules above are importable from here too.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np

from qube_koopman.core.lti import DiscreteStateSpace
from qube_koopman.identify.data.trajectory import Trajectory, as_episodes
from qube_koopman.identify.model_selection.distributed import (
    DEFAULT_WORKER_TIMEOUT,
    candidate_runner,
    connect,
    release_workers,
)
from qube_koopman.identify.model_selection.evaluation import (
    Reuse,
    SameControllerFolds,
    SearchData,
    evaluate_candidate,
    same_controller_scores,
    screen_candidate,
)
from qube_koopman.identify.model_selection.families import (
    delays_family,
    family_of,
    family_statistics,
    holds_features,
    radial_statistics,
    shared_statistics,
)
from qube_koopman.identify.model_selection.lifting_space import (
    FRICTION_LAG,
    STAGES,
    LiftingSpec,
    SearchSpace,
    rbf_box,
    search_steps,
)
from qube_koopman.identify.model_selection.ranking import (
    TIMING_KEYS,
    CandidateResult,
    SearchResult,
    finalists,
    screen_bar,
)
from qube_koopman.identify.model_selection.transfer import ProbeSet
from qube_koopman.identify.models.offsets import DEFAULT_BOUND

__all__ = [
    "LiftingSpec",
    "SearchSpace",
    "SearchSettings",
    "CandidateResult",
    "SearchResult",
    "search_liftings",
    "evaluate_candidate",
    "screen_candidate",
    "screen_bar",
    "finalists",
    "same_controller_scores",
    "SameControllerFolds",
    "search_steps",
    "rbf_box",
    "family_of",
    "holds_features",
    "delays_family",
    "family_statistics",
    "shared_statistics",
    "radial_statistics",
    "SearchData",
    "Reuse",
    "STAGES",
    "TIMING_KEYS",
    "FRICTION_LAG",
    "FAMILY_PARTS",
]

#: Parts of the training episodes a family's shared statistics are computed in, side by side (4 episodes at least each).
FAMILY_PARTS = 4
_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SearchSettings:
    """How a lifting search runs, besides its episodes, folds and space: the candidates' fixed
    settings, and the workers they run on.

    Parameters
    ----------
    bound : float
        Plausibility bound of the offset estimates (rad).
    rbf_seed : int
        Seed of the RBF centres.
    n_jobs : int
        Local worker processes (joblib's convention: -1 for every core).
    scheduler : str, optional
        Address of a dask.distributed scheduler to run the candidates on
        instead (needs the ``dask`` extra).
    connect_timeout : float
        Seconds to keep trying to reach ``scheduler`` before giving up.
    security : distributed.security.Security, optional
        The TLS certificates of a ``tls://`` ``scheduler`` (default: dask's configuration).
    worker_timeout : float
        Seconds the ``scheduler``'s cluster may have no worker, results awaited, before the
        search gives up (:class:`~qube_koopman.identify.model_selection.distributed.NoWorkersError`).
    progress : callable(label, done, total), optional
        Called as each stage's candidates finish.
    """

    bound: float = DEFAULT_BOUND
    rbf_seed: int = 0
    n_jobs: int = 1
    scheduler: str | None = None
    connect_timeout: float = 30.0
    security: object = None
    worker_timeout: float = DEFAULT_WORKER_TIMEOUT
    progress: Callable[[str, int, int], None] | None = None


@dataclass
class _Search:
    """A running search: what its stages share, and what they add to."""

    data: SearchData
    space: SearchSpace
    run: Callable  # the candidate runner (distributed.candidate_runner)
    n_parts: int  # parts of the episodes a family's statistics are computed in
    result: SearchResult
    sharing: Callable  # times a stage's statistics shared by its candidates
    progress: Callable[[str, int, int], None] | None
    seen: set = field(default_factory=set)
    #: The family heads' statistics, by head, for later stages' liftings they hold.
    earlier: dict = field(default_factory=dict)


def search_liftings(
    trajectories: Sequence[Trajectory],
    controller: DiscreteStateSpace,
    *,
    splits,
    window: int,
    space: SearchSpace | None = None,
    probes: ProbeSet | None = None,
    controllers: Sequence[DiscreteStateSpace] | None = None,
    settings: SearchSettings = SearchSettings(),
) -> SearchResult:
    """Search the lifting space in stages (see the module docstring).

    Parameters
    ----------
    trajectories : sequence of Trajectory
        Training episodes, recorded under ``controller`` (or ``controllers``).
    controller : DiscreteStateSpace
        The candidates' closed loop.
    splits : sequence of (train_indices, validation_indices)
        Episode-grouped folds, or with several controllers
        :func:`~qube_koopman.identify.model_selection.split.leave_one_controller_out`'s.
    window : int
        Offset estimation window in samples; every candidate is scored from
        this sample on.
    space : SearchSpace, optional
    probes : ProbeSet, optional
        Transfer probes (:func:`~qube_koopman.identify.model_selection.transfer.twin_probes`):
        each candidate is then ranked by the lower of its cross-validated and
        its transfer R^2 (:attr:`~.CandidateResult.objective`); without them by
        the cross-validated R^2 alone.
    controllers : sequence of DiscreteStateSpace, optional
        Each episode's controller, when they ran several: every candidate's
        plant is fitted to all of them, and each fold's closed loop is that of
        the controller its validation episodes ran.
    settings : SearchSettings
        The offsets' bound, the RBF seed, the workers (local or a dask cluster) and the progress.

    Returns
    -------
    SearchResult
    """
    from qube_koopman.identify.model_selection.sweep import seconds_timer

    space = space or SearchSpace()
    data = SearchData(
        as_episodes(trajectories),
        list(splits),
        controller,
        np.asarray(space.alphas, dtype=float),
        int(window),
        settings.bound,
        settings.rbf_seed,
        probes,
        controllers=None if controllers is None else list(controllers),
        n_offset_alphas=space.n_offset_alphas,
    )
    client = connect(settings.scheduler, settings.connect_timeout, settings.security) if settings.scheduler else None
    run = candidate_runner(settings.n_jobs, client, settings.worker_timeout)
    # A family's statistics are computed by parts of the episodes on the workers, joined here: as many
    # parts whatever the workers (the same numbers on any machine).
    n_parts = max(1, min(FAMILY_PARTS, len(data.trajectories) // 4))
    started = time.perf_counter()
    result = SearchResult(window=int(window), probes=probes, tie_standard_errors=space.tie_standard_errors)
    # the time each stage spends on statistics shared by its candidates
    search = _Search(data, space, run, n_parts, result, seconds_timer(result.shared_seconds), settings.progress)
    try:
        for stage in STAGES:
            _run_stage(search, stage)
    finally:
        release_workers(settings.n_jobs, client)
    result.seconds = time.perf_counter() - started
    return result


def _run_stage(search: _Search, stage: str) -> None:
    """One stage: its new candidates, the statistics they share, their screens, their full evaluations."""
    result, space = search.result, search.space
    stage_started = time.perf_counter()
    specs = [s for s in space.stage_candidates(stage, result.ranked()) if s not in search.seen]
    search.seen.update(specs)
    # An offsets candidate reuses its plain twin: its fold scores choose the alphas, its models predict.
    plain = {r.spec: r for r in result.candidates}
    shared = _stage_statistics(search, stage, specs)
    screens: dict[LiftingSpec, CandidateResult] = {}
    if space.screens(stage, len(specs)):
        screens = _screen_stage(search, stage, specs, shared)
        chosen = _stage_finalists(search, stage, screens)
        specs = [s for s in specs if s in chosen]
    _evaluate_stage(search, stage, specs, plain, shared, screens)
    result.stage_seconds[stage] = time.perf_counter() - stage_started
    _log.info(
        "search: stage %s: %d candidates in %.1f s%s",
        stage,
        len(specs),
        result.stage_seconds[stage],
        f" ({len(screens)} screened, {len(screens) - len(specs)} left out)" if screens else "",
    )


def _stage_statistics(search: _Search, stage: str, specs: list[LiftingSpec]) -> dict:
    """The statistics a stage's candidates share, by candidate (None: it lifts the episodes itself).

    A family's largest lifting is lifted once; the others' statistics are columns of its own.
    """
    from qube_koopman.identify.model_selection.sweep import episode_heads

    data, run, n_parts, sharing = search.data, search.run, search.n_parts, search.sharing
    heads = {s: family_of(s, specs) for s in specs}
    shared: dict[LiftingSpec, tuple | None] = {}
    for head in sorted(set(h for h in heads.values() if h is not None)):
        with sharing(stage):
            # With the friction shape too when the friction stage may try it: that stage's new
            # candidate (the best so far with friction) then takes its statistics from these.
            big = replace(head, friction=True) if search.space.tries_friction(head) else head
            search.earlier[big] = shared_statistics(big, data, run, n_parts)
            shared.update({s: search.earlier[big] for s in specs if heads[s] == head})
    longest = delays_family(specs)
    if longest is not None:  # liftings but for their delays: the longest's statistics, and the heads
        with sharing(stage):
            stats = (*shared_statistics(longest, data, run, n_parts), episode_heads(data.trajectories, longest.delays))
            shared.update({s: stats for s in specs if replace(s, delays=longest.delays) == longest})
    for s in specs:  # a lifting whose features an earlier stage's family head holds
        if shared.get(s) is None:
            shared[s] = next((v for h, v in search.earlier.items() if holds_features(h, s)), None)
    alone = [s for s in specs if shared.get(s) is None]
    radial = [s for s in alone if s.rbf and replace(s, rbf=0) == replace(alone[0], rbf=0)]
    if len(radial) > 1:  # the RBF stage: one factorization for every number of centres, in parts
        with sharing(stage):
            shared.update(radial_statistics(radial, data, run, n_parts))
    return shared


def _screen_stage(search: _Search, stage: str, specs: list[LiftingSpec], shared: dict) -> dict:
    """Successive halving's first step: every candidate of the stage screened cheaply (by lifting)."""
    import joblib

    space = search.space
    # The largest first: the last to start on a worker is then a short one.
    calls = [
        joblib.delayed(screen_candidate)(s, search.data, stage, shared.get(s), space.screen_folds)
        for s in sorted(specs, key=lambda s: -s.n_features())
    ]
    screens = {}
    for done, res in enumerate(search.run(calls), start=1):
        screens[res.spec] = res
        if search.progress:
            search.progress(f"search: {stage} (screen)", done, len(specs))
    return screens


def _stage_finalists(search: _Search, stage: str, screens: dict) -> set[LiftingSpec]:
    """The screened liftings evaluated in full; the screens (and those left out) go to the result."""
    result, space = search.result, search.space
    lead = result.ranked()[0] if result.candidates and space.screen_against_lead else None
    bar = None if lead is None else screen_bar(lead, space.screen_folds)
    if bar is not None:
        result.screen_bars[stage] = bar
    chosen = finalists(list(screens.values()), space.n_finalists, bar)
    result.screened += [replace(r, kept=None) for r in screens.values() if r.spec not in chosen]
    result.screens += [replace(r, kept=None) for r in screens.values()]
    return chosen


def _evaluate_stage(
    search: _Search, stage: str, specs: list[LiftingSpec], plain: dict, shared: dict, screens: dict
) -> None:
    """The full evaluations of a stage's candidates (``plain``: the candidates so far, by lifting, whose
    plain twins an offsets candidate reuses), the largest first as the screens, added to the result as
    they finish."""
    import joblib

    calls = [
        joblib.delayed(evaluate_candidate)(
            s, search.data, stage, plain.get(replace(s, offsets=False)), shared.get(s), screens.get(s)
        )
        for s in sorted(specs, key=lambda s: -s.n_features())
    ]
    for done, res in enumerate(search.run(calls), start=1):
        search.result.candidates.append(res)
        if search.progress:
            search.progress(f"search: {stage}", done, len(specs))
