"""Statistics a lifting search's candidates share: a family's largest lifting is lifted once, and
the statistics of every candidate whose features it holds are columns of its own
(:func:`~qube_koopman.identify.model_selection.sweep.sub_statistics`).

Families: the same delays with a lower monomial order, sin/cos or constant (:func:`family_of`); the
same lifting with fewer delays (:func:`delays_family`); liftings that differ in their RBF centres
alone (:func:`radial_statistics`). The statistics are computed by parts of the episodes on the
workers and joined (:func:`shared_statistics`).
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Sequence

import numpy as np

from qube_koopman.identify.estimators.cl_edmd import ClEdmd
from qube_koopman.identify.model_selection.lifting_space import LiftingSpec, rbf_box, search_steps

if TYPE_CHECKING:
    from qube_koopman.identify.model_selection.evaluation import SearchData

__all__ = [
    "family_of",
    "holds_features",
    "delays_family",
    "family_statistics",
    "shared_statistics",
    "radial_statistics",
]


def shared_statistics(head: LiftingSpec, data: SearchData, run, n_parts: int) -> tuple:
    """:func:`family_statistics` of ``head`` on the workers: in ``n_parts`` parts of the episodes, joined."""
    return _statistics_by_parts(search_steps(head, data.trajectories, data.rbf_seed), data, run, n_parts)


def _statistics_by_parts(steps: list, data: SearchData, run, n_parts: int) -> tuple:
    """The fold statistics of the lifting ``steps`` on the workers: in ``n_parts`` parts of the episodes, joined."""
    import joblib

    from qube_koopman.identify.model_selection.sweep import merge_fold_statistics

    if n_parts <= 1:
        return next(iter(run([joblib.delayed(_family_part)(steps, data)])))
    parts = np.array_split(np.arange(len(data.trajectories)), n_parts)
    return merge_fold_statistics(list(run([joblib.delayed(_family_part)(steps, data, p) for p in parts])))


def _radial_family(specs: Sequence[LiftingSpec], data: SearchData) -> tuple[list, dict, dict]:
    """The lifting holding every one of ``specs``' (which differ in their RBF centres alone: one radial basis of
    the same kernel with all their centres, one candidate's after the other's), where each one's features are
    among its features, and each one's lifting."""
    from qube_koopman.identify.lifting import Lifting
    from qube_koopman.identify.lifting.rbf import RadialBasis

    box = rbf_box(specs[0], data.trajectories)  # the same for all: they differ in their RBF alone
    steps = {s: search_steps(s, data.trajectories, data.rbf_seed, box) for s in specs}
    first = steps[specs[0]]
    at = next(i for i, step in enumerate(first) if isinstance(step, RadialBasis))
    bases = [b for b in (steps[s][at] for s in specs) if isinstance(b, RadialBasis)]
    centers = np.vstack([b.centers for b in bases])
    union = first[:at] + [type(bases[0])(**{**bases[0].get_params(), "n_centers": len(centers), "centers": centers})]
    union += first[at + 1 :]
    sample = [data.trajectories[0].x]
    n_before = Lifting(first[:at]).fit(sample).n_features_out_
    n_union = Lifting(union).fit(sample).n_features_out_
    sizes = [int(s.rbf) for s in specs]  # each draws as many centres
    after = list(range(n_before + sum(sizes), n_union))  # the friction shapes and the constant
    columns = {}
    for k, s in enumerate(specs):
        start = n_before + sum(sizes[:k])
        columns[s] = list(range(n_before)) + list(range(start, start + sizes[k])) + after
    return union, columns, steps


def _family_part(steps: list, data: SearchData, episodes=None) -> tuple:
    """:func:`family_statistics` of a lifting given as its steps."""
    from qube_koopman.core.blas import limited_blas_threads
    from qube_koopman.identify.model_selection.sweep import fold_statistics

    with limited_blas_threads(1):  # (one BLAS thread: a second one made these tall QRs 2.7 times slower on 2 cores)
        return fold_statistics(
            ClEdmd(data.controller, lifting=steps), data.trajectories, data.splits, data.controllers, episodes
        )


def radial_statistics(specs: Sequence[LiftingSpec], data: SearchData, run, n_parts: int) -> dict:
    """The fold statistics of liftings that differ in their RBF centres alone (the search's are thin-plate of one
    shape), from one factorization of the episodes with all their centres, in ``n_parts`` parts on the workers."""
    from qube_koopman.identify.model_selection.sweep import OwnStatistics, sub_statistics

    union, columns, steps = _radial_family(specs, data)
    merged = _statistics_by_parts(union, data, run, n_parts)
    out = {}
    for s in specs:
        taken = sub_statistics(ClEdmd(data.controller, lifting=steps[s]), merged, data.controllers, columns=columns[s])
        if taken is None:
            raise ValueError(f"{s.label()}: its statistics are not columns of its RBF family's")
        out[s] = OwnStatistics(taken)
    return out


def holds_features(big: LiftingSpec, small: LiftingSpec) -> bool:
    """Whether every feature of ``small``'s lifting is one of ``big``'s (the statistics of ``small`` are then
    columns of ``big``'s): the same delays, no RBFs, and as much or more of the monomials, sin/cos, constant
    and friction shape. Never for offsets candidates (their statistics are their plain twin's)."""
    return (
        not big.offsets
        and not small.offsets
        and big.delays == small.delays
        and big.rbf == small.rbf == 0
        and big.friction >= small.friction
        and big.poly >= small.poly
        and big.trig >= small.trig
        and big.const >= small.const
    )


def delays_family(specs: Sequence[LiftingSpec]) -> LiftingSpec | None:
    """The lifting with the most delays among ``specs`` that differ from it in their delays alone, when
    there are two at least (else None); not with RBFs (their centres live on the delayed state), the
    friction shape or offsets.

    A lifting with fewer delays has the same features at lags it holds: its statistics are columns of
    the longest one's, with the snapshots of each episode's first samples added
    (:func:`~qube_koopman.identify.model_selection.sweep.sub_statistics`): the delays stage lifts its
    episodes once.
    """
    plain = [s for s in specs if not (s.rbf or s.friction or s.offsets)]
    if not plain:
        return None
    longest = max(plain, key=lambda s: s.delays)
    members = [s for s in plain if replace(s, delays=longest.delays) == longest]
    return longest if len(members) > 1 else None


def family_of(spec: LiftingSpec, specs: Sequence[LiftingSpec]) -> LiftingSpec | None:
    """The candidate among ``specs`` whose lifting holds every feature of ``spec``'s, with the most features
    (``spec`` itself when it is the largest), when it holds another candidate too.

    Monomials of a lower order, sin/cos and the constant are columns of a lifting with a
    higher order, sin/cos and the constant at the same delays (RBFs and friction equal; RBF
    centres depend on the features before them, so liftings with RBFs are their own family).
    None when it shares its features with no other candidate (or has offsets: its statistics are
    its plain twin's).
    """

    def holds(big: LiftingSpec, small: LiftingSpec) -> bool:
        return (
            not big.offsets
            and not small.offsets
            and big.delays == small.delays
            and big.rbf == small.rbf == 0
            and big.friction == small.friction
            and big.poly >= small.poly
            and big.trig >= small.trig
            and big.const >= small.const
        )

    containers = [s for s in specs if holds(s, spec)]
    if not containers:
        return None
    head = max(containers, key=lambda s: s.n_features())
    return head if sum(holds(head, s) for s in specs) > 1 else None


def family_statistics(spec: LiftingSpec, data: SearchData, episodes=None) -> tuple:
    """The fold statistics of ``spec``'s lifting on the search's folds (shared by its family).

    ``episodes``: of these training episodes only (a part, joined with the others' by
    :func:`~qube_koopman.identify.model_selection.sweep.merge_fold_statistics`).
    """
    return _family_part(search_steps(spec, data.trajectories, data.rbf_seed), data, episodes)
