"""The lifting search's candidate space: one candidate's lifting (:class:`LiftingSpec`), the values each
stage tries (:class:`SearchSpace`), and the lifting functions a candidate is scored with
(:func:`search_steps`, its RBF centres drawn on the training episodes).

The stages, in order (:data:`STAGES`), each a coordinate step from the best so far:

1. ``delays``: every delay count, with the base form (monomials of order 2);
2. ``form``: at the best delays, every monomial order x constant x sin/cos;
3. ``friction``: the best so far with and without the arm's Coulomb friction
   shape (:class:`~qube_koopman.identify.lifting.CoulombFriction`);
4. ``rbf``: at the best so far, every number of thin-plate RBF centres;
5. ``offsets``: the best candidates so far again, with per-episode offsets
   estimated on each validation episode and probe (at their best alphas).

With :attr:`SearchSpace.offsets_first` every stage scores its candidates with the offsets, and
the last stage has nothing to add: where the validation episodes' encoder zeros are far from the
training's (a loop that amplifies them, as the soft controller's does seventeenfold), the scores
without offsets measure the zeros more than the lifting, and the stages before the last would
choose the lifting on them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Sequence

import numpy as np

from qube_koopman.core.qube import MEASURED
from qube_koopman.identify.data.trajectory import Trajectory, as_episodes
from qube_koopman.identify.lifting import (
    Constant,
    CoulombFriction,
    Delay,
    GaussianRbf,
    LiftingFunction,
    Polynomial,
    ThinPlateRbf,
    Trigonometric,
)

if TYPE_CHECKING:
    from qube_koopman.identify.model_selection.ranking import CandidateResult

__all__ = ["LiftingSpec", "SearchSpace", "search_steps", "rbf_box", "STAGES", "FRICTION_LAG", "TIE_STANDARD_ERRORS"]

#: The search's stages, in the order they run (see the module docstring).
STAGES = ("delays", "form", "friction", "rbf", "offsets")
FRICTION_LAG = CoulombFriction().lag  # samples: the fewest delays the friction lifting needs
#: Candidates within this many standard errors of the best objective are tied, and the one of them that
#: transfers best wins (:meth:`~.ranking.SearchResult.ranked`, the one-standard-error rule).
TIE_STANDARD_ERRORS = 1.0


@dataclass(frozen=True, order=True)
class LiftingSpec:
    """One lifting of the search: monomials (and sin/cos), delays, RBFs, constant, in that order.

    Parameters
    ----------
    delays : int
        Time delays.
    poly : int
        Monomial order (1: the states themselves).
    trig : bool
        Append sin and cos of both angles (before the delays).
    rbf : int
        Thin-plate RBF centres on the delayed state (0: none).
    const : bool
        Append a constant (an affine term).
    friction : bool
        Append the arm's Coulomb friction shape (:class:`~qube_koopman.identify.lifting.CoulombFriction` of
        theta over 10 samples, after the RBFs); needs at least 10 delays.
    offsets : bool
        Estimate an alpha offset on each validation (and test) episode.
    """

    delays: int = 10
    poly: int = 2
    trig: bool = False
    rbf: int = 0
    const: bool = False
    offsets: bool = False
    friction: bool = False

    def steps(
        self, rbf_seed: int = 0, rbf_kind: str = "thin-plate", rbf_shape: float = 1.0, rbf_offset: float = 1e-3
    ) -> list[LiftingFunction]:
        """The lifting functions, in the order of ``qube-identify``'s options.

        The search's radial bases are thin-plate with the default shape and offset;
        ``qube-identify`` builds its lifting here too, with its ``--rbf*`` options.
        """
        steps: list[LiftingFunction] = [Polynomial(self.poly)] if self.poly > 1 else []
        if self.trig:
            steps.append(Trigonometric(MEASURED))
        if self.delays:
            steps.append(Delay(self.delays))
        if self.rbf and rbf_kind == "thin-plate":
            steps.append(ThinPlateRbf(self.rbf, rbf_shape, rbf_offset, seed=rbf_seed))
        elif self.rbf and rbf_kind == "gaussian":
            steps.append(GaussianRbf(self.rbf, rbf_shape, seed=rbf_seed))
        elif self.rbf:
            raise ValueError(f"unknown RBF kind {rbf_kind!r}; expected 'thin-plate' or 'gaussian'")
        if self.friction:
            steps.append(CoulombFriction())
        if self.const:
            steps.append(Constant())
        return steps

    def n_features(self, n_states: int = 2) -> int:
        """Lifted plant features (a measure of size: the smaller wins a tie)."""
        from math import comb

        pointwise = comb(n_states + self.poly, self.poly) - 1 + (2 * n_states if self.trig else 0)
        return pointwise * (self.delays + 1) + self.rbf + int(self.friction) + int(self.const)

    def flags(self, rbf_seed: int = 0) -> list[str]:
        """The ``qube-identify`` options that fit this lifting by hand (without alpha)."""
        out = ["--poly", str(self.poly)] + (["--trig"] if self.trig else []) + ["--delays", str(self.delays)]
        if self.rbf:
            out += ["--rbf", "thin-plate", "--rbf-centers", str(self.rbf)] + (
                ["--rbf-seed", str(rbf_seed)] if rbf_seed else []
            )
        return (
            out
            + (["--friction"] if self.friction else [])
            + (["--const"] if self.const else [])
            + (["--offsets", "alpha"] if self.offsets else [])
        )

    def label(self) -> str:
        """A short readable name, e.g. ``"poly 2, 20 delays, const, offsets"``."""
        parts = [f"poly {self.poly}"] + (["sin/cos"] if self.trig else []) + [f"{self.delays} delays"]
        parts += ([f"{self.rbf} RBF"] if self.rbf else []) + (["friction"] if self.friction else [])
        parts += ["const"] if self.const else []
        return ", ".join(parts + (["offsets"] if self.offsets else []))


@dataclass(frozen=True)
class SearchSpace:
    """The values each stage tries (see the module docstring), and the alpha grid.

    The defaults span delays 0 to 40, monomial orders 1 to 3, constant and
    sin/cos on and off, the arm's friction shape on and off, 0 to 100 RBF
    centres, alpha on a log grid of two points per decade, offsets on and off.
    """

    delays: tuple[int, ...] = (0, 5, 10, 15, 20, 25, 30, 35, 40)
    poly: tuple[int, ...] = (1, 2, 3)
    const: tuple[bool, ...] = (False, True)
    trig: tuple[bool, ...] = (False, True)
    rbf: tuple[int, ...] = (0, 25, 50, 100)
    alphas: tuple[float, ...] = tuple(np.logspace(-6, 2, 17).tolist())
    offsets: tuple[bool, ...] = (False, True)
    friction: tuple[bool, ...] = (False, True)
    base: LiftingSpec = LiftingSpec(delays=0, poly=2)
    n_offset_candidates: int = 3  # stage 4 re-scores this many of the best with offsets
    n_offset_alphas: int = 3  # ... each at its best alphas
    #: Every stage scores its candidates with per-episode offsets (the offsets stage then adds none); needs
    #: ``True in offsets``. None: decided by the training logs (:meth:`for_training`), which
    #: :func:`~.search_liftings` itself takes as False.
    offsets_first: bool | None = None
    #: Successive halving: the stages ``screened_stages`` screen their candidates (:func:`~.screen_candidate`)
    #: and evaluate in full the ``n_finalists`` best whose screens did not diverge (0: every candidate
    #: in full, no screening).
    n_finalists: int = 3
    screen_folds: int = 1  # folds a screen scores (the first ones)
    screened_stages: tuple[str, ...] = ("delays", "form", "rbf")
    #: After the first stage a finalist's screen must also beat the stage's lead scored as a screen
    #: (:func:`~.screen_bar`); False: the ``n_finalists`` best screens go on whatever the lead scored.
    screen_against_lead: bool = True
    #: Candidates within this many standard errors of the best objective are tied, and the one of them that
    #: transfers best leads each stage and wins (:meth:`~.ranking.SearchResult.ranked`); 0: the best objective.
    tie_standard_errors: float = TIE_STANDARD_ERRORS

    def __post_init__(self):
        for name in ("delays", "poly", "rbf", "alphas"):
            values = getattr(self, name)
            if not values or any(not np.isfinite(v) or v < 0 for v in values):
                raise ValueError(f"search space: {name} needs non-negative values, got {values!r}")
        if min(self.poly) < 1:
            raise ValueError("search space: poly (monomial orders) starts at 1")
        if self.n_finalists < 0 or self.screen_folds < 1:
            raise ValueError("search space: n_finalists must be >= 0 and screen_folds >= 1")
        if not np.isfinite(self.tie_standard_errors) or self.tie_standard_errors < 0:
            raise ValueError("search space: tie_standard_errors must be a finite number >= 0")
        if self.offsets_first and True not in self.offsets:
            raise ValueError("search space: offsets_first needs offsets to include true")

    def for_training(self, several_controllers: bool) -> "SearchSpace":
        """This space with :attr:`offsets_first` decided where it is None: on when the training logs ran
        two or more controllers (``several_controllers``) and offsets are tried.

        Why: a softer loop's episodes are predictable only with their encoder zeros estimated (under the
        soft controller a count's error moves the arm seventeen times as far), so scored without them
        its folds rank liftings by how they bear the zeros; on the rig's 28 logs and half of ten soft
        ones, the staged search then chose heavily regularized liftings (alpha 0.03-0.1) that
        predicted the soft episodes it did not see worse than the rig-only recommendation on three
        of four splits, and with offsets from the first stage better on three (docs/transfer.md).
        """
        if self.offsets_first is not None:
            return self
        return replace(self, offsets_first=several_controllers and True in self.offsets)

    def tries_friction(self, lead: LiftingSpec) -> bool:
        """Whether the friction stage would try ``lead`` with the friction shape (it lacks it and has the delays)."""
        return True in self.friction and not lead.friction and lead.delays >= FRICTION_LAG and lead.rbf == 0

    def screens(self, stage: str, n_candidates: int) -> bool:
        """Whether ``stage`` screens its ``n_candidates`` new candidates before the full evaluation."""
        return self.n_finalists > 0 and n_candidates > 1 and stage in self.screened_stages

    def stage_candidates(self, stage: str, best: Sequence["CandidateResult"]) -> list[LiftingSpec]:
        """The liftings a stage tries, given the results so far (best first)."""
        if not self.offsets_first:
            return self._stage_candidates(stage, best)
        if stage == "offsets":
            return []  # every candidate had them
        return [replace(spec, offsets=True) for spec in self._stage_candidates(stage, best)]

    def _stage_candidates(self, stage: str, best: Sequence["CandidateResult"]) -> list[LiftingSpec]:
        lead = best[0].spec if best else self.base
        if stage == "delays":
            return [replace(self.base, delays=d) for d in self.delays]
        if stage == "form":
            return [replace(lead, poly=p, const=c, trig=t) for p in self.poly for c in self.const for t in self.trig]
        if stage == "friction":
            return [replace(lead, friction=f) for f in self.friction if not f or lead.delays >= FRICTION_LAG]
        if stage == "rbf":
            return [replace(lead, rbf=n) for n in self.rbf]
        if stage == "offsets":
            if True not in self.offsets:
                return []
            return [replace(r.spec, offsets=True) for r in best[: self.n_offset_candidates]]
        raise ValueError(f"unknown stage {stage!r}")


def rbf_box(spec: LiftingSpec, trajectories: Sequence[Trajectory]) -> tuple[np.ndarray, np.ndarray] | None:
    """The box the training episodes span in the features ``spec``'s radial basis sees (None without one):
    where :func:`search_steps` draws its centres. Liftings that differ in their RBF alone share it."""
    from qube_koopman.identify.lifting import Lifting
    from qube_koopman.identify.lifting.rbf import RadialBasis, data_box
    from qube_koopman.identify.data.trajectory import episode_signals

    steps = spec.steps()
    at = [i for i, step in enumerate(steps) if isinstance(step, RadialBasis)]
    if not at:
        return None
    episodes = episode_signals(as_episodes(trajectories), "x")
    head = Lifting(steps[: at[0]]).fit(episodes[:1])
    return data_box((head.transform(x) for x in episodes), head.n_features_out_)


def search_steps(
    spec: LiftingSpec,
    trajectories: Sequence[Trajectory],
    rbf_seed: int = 0,
    box: tuple[np.ndarray, np.ndarray] | None = None,
) -> list[LiftingFunction]:
    """The lifting a candidate is scored with: ``spec.steps``, its RBF centres drawn once on all the
    training episodes.

    The thin-plate centres are a Latin hypercube scaled to the box the training episodes' lifted
    states span; drawn per fold, every fold and the probes' plant would lift the episodes anew
    (four times the statistics, on the search's slowest candidates), for boxes that differ by
    the few samples of extreme states a fold holds out. Drawn on all the training episodes they
    are the centres the winner's final fit draws (``qube-identify`` with the winner's flags). ``box``: the
    episodes' box (:func:`rbf_box`) when already known.
    """
    from qube_koopman.identify.lifting.rbf import RadialBasis

    steps = spec.steps(rbf_seed)
    at = [i for i, step in enumerate(steps) if isinstance(step, RadialBasis)]
    if not at:
        return steps
    rbf = steps[at[0]]
    assert isinstance(rbf, RadialBasis)  # found so above
    found = rbf_box(spec, trajectories) if box is None else box
    assert found is not None  # spec has a radial basis
    low, high = found
    steps[at[0]] = type(rbf)(**{**rbf.get_params(), "centers": rbf.centers_in(low, high)})
    return steps
