"""Lifting search: choose the lifting, the regularization and the offset protocol on the
training episodes only, for the question users ask: transfer to another controller.

Every candidate is scored twice. Cross-validation: the way the test episodes will be, its closed loop
predicts each validation episode's measured states from the episode's start,
under the recorded controller, and R^2 is taken from the end of the offset
estimation window on (the same samples whether offsets are estimated or not,
so the two protocols compare). A candidate's statistics are computed once per
episode and merged per fold, and every alpha is then a small solve on them
(:func:`~qube_koopman.identify.model_selection.sweep.regularization_sweep`). Transfer: with
probes (:mod:`~qube_koopman.identify.model_selection.transfer`), its plant fitted on all the
training episodes, wrapped with probe controllers unlike the training one,
predicts twin episodes run under them. Candidates rank by the lower of the
two (:attr:`CandidateResult.objective`): cross-validation under the training
controller alone rewards liftings that fit that loop's own correlations
(high-order monomials, RBFs), which diverged under other controllers.

The space is searched in stages, each a coordinate step from the best so far
(a full product of the default space would be about 1,400 liftings):

1. ``delays``: every delay count, with the base form (monomials of order 2);
2. ``form``: at the best delays, every monomial order x constant x sin/cos;
3. ``friction``: the best so far with and without the arm's Coulomb friction
   shape (:class:`~qube_koopman.identify.lifting.CoulombFriction`);
4. ``rbf``: at the best so far, every number of thin-plate RBF centres;
5. ``offsets``: the best candidates so far again, with per-episode offsets
   estimated on each validation episode and probe (at their best alphas).

Candidates of a stage are independent: they run through joblib on local
cores (``n_jobs``), or on a dask.distributed cluster (see :func:`search_liftings` and
:mod:`~qube_koopman.identify.model_selection.distributed`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Callable, Sequence

import numpy as np

from qube_koopman.core.qube import MEASURED
from qube_koopman.identify.estimators.cl_edmd import ClEdmd
from qube_koopman.identify.model_selection.distributed import (
    DEFAULT_WORKER_TIMEOUT,
    candidate_runner,
    connect,
    release_workers,
)
from qube_koopman.identify.models.model import FittedRows
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
from qube_koopman.identify.models.offsets import DEFAULT_BOUND
from qube_koopman.identify.metrics import scores_after_window_models
from qube_koopman.identify.model_selection.sweep import regularization_sweep
from qube_koopman.identify.data.trajectory import Trajectory, as_episodes
from qube_koopman.identify.model_selection.transfer import ProbeSet
from qube_koopman.core.lti import DiscreteStateSpace

__all__ = [
    "LiftingSpec",
    "SearchSpace",
    "CandidateResult",
    "SearchResult",
    "search_liftings",
    "evaluate_candidate",
    "screen_candidate",
    "screen_bar",
    "same_controller_scores",
    "search_steps",
    "family_of",
    "holds_features",
    "delays_family",
    "family_statistics",
]

#: What a candidate's time is spent on (:attr:`CandidateResult.timing`), in the order it is spent.
TIMING_KEYS = ("statistics", "fits", "predictions", "offsets", "probe_fits", "probe_scoring")
STAGES = ("delays", "form", "friction", "rbf", "offsets")
FRICTION_LAG = CoulombFriction().lag  # samples: the fewest delays the friction lifting needs
#: Parts of the training episodes a family's shared statistics are computed in, side by side (4 episodes at least each).
FAMILY_PARTS = 4
_log = logging.getLogger(__name__)


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
        Append the arm's Coulomb friction shape (:class:`CoulombFriction` of
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
    #: Successive halving: the stages ``screened_stages`` screen their candidates (:func:`screen_candidate`)
    #: and evaluate in full the ``n_finalists`` best whose screens did not diverge (0: every candidate
    #: in full, no screening).
    n_finalists: int = 3
    screen_folds: int = 1  # folds a screen scores (the first ones)
    screened_stages: tuple[str, ...] = ("delays", "form", "rbf")
    #: After the first stage a finalist's screen must also beat the stage's lead scored as a screen
    #: (:func:`screen_bar`); False: the ``n_finalists`` best screens go on whatever the lead scored.
    screen_against_lead: bool = True

    def __post_init__(self):
        for name in ("delays", "poly", "rbf", "alphas"):
            values = getattr(self, name)
            if not values or any(not np.isfinite(v) or v < 0 for v in values):
                raise ValueError(f"search space: {name} needs non-negative values, got {values!r}")
        if min(self.poly) < 1:
            raise ValueError("search space: poly (monomial orders) starts at 1")
        if self.n_finalists < 0 or self.screen_folds < 1:
            raise ValueError("search space: n_finalists must be >= 0 and screen_folds >= 1")

    def tries_friction(self, lead: LiftingSpec) -> bool:
        """Whether the friction stage would try ``lead`` with the friction shape (it lacks it and has the delays)."""
        return True in self.friction and not lead.friction and lead.delays >= FRICTION_LAG and lead.rbf == 0

    def screens(self, stage: str, n_candidates: int) -> bool:
        """Whether ``stage`` screens its ``n_candidates`` new candidates before the full evaluation."""
        return self.n_finalists > 0 and n_candidates > 1 and stage in self.screened_stages

    def stage_candidates(self, stage: str, best: Sequence["CandidateResult"]) -> list[LiftingSpec]:
        """The liftings a stage tries, given the results so far (best first)."""
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


@dataclass
class CandidateResult:
    """Cross-validated and transfer scores of one lifting over the alpha grid.

    Attributes
    ----------
    spec : LiftingSpec
    stage : str
    alphas : ndarray of shape (n_alphas,)
    cv_r2 : ndarray of shape (n_folds, n_alphas)
        Mean R^2 of each fold's validation episodes (NaN: alpha not scored,
        as offsets are only estimated at the best alphas; -inf: diverged).
    seconds : float
        Wall time of the evaluation.
    transfer_r2 : ndarray of shape (n_probe_episodes, n_alphas), optional
        R^2 of each transfer probe episode (:mod:`~qube_koopman.identify.model_selection.transfer`)
        predicted by the plant fitted on all training episodes (NaN: alpha not
        probed; -inf: diverged). None when the search has no probes.
    reuse : Reuse, optional
        What the same lifting with offsets needs from this plain candidate (its models at
        its best alphas), so the offsets stage does not lift the episodes again.
    kept : tuple, optional
        A screen's (:func:`screen_candidate`) lifting steps, its statistics (None when the
        stage shared them) and its folds' models at every alpha: what its full evaluation
        needs from it.
    timing : dict of str to float
        Where ``seconds`` went (:data:`TIMING_KEYS`): ``statistics`` (lifting the
        training episodes, their factors), ``fits`` (every fold's solves),
        ``predictions`` (the folds' validation episodes), ``offsets`` (their
        offsets estimated and predicted again), ``probe_fits`` and
        ``probe_scoring`` (the plants on all episodes, predicting the probes).
    """

    spec: LiftingSpec
    stage: str
    alphas: np.ndarray
    cv_r2: np.ndarray
    seconds: float
    transfer_r2: np.ndarray | None = None
    timing: dict = field(default_factory=dict)
    reuse: "Reuse | None" = field(default=None, repr=False, compare=False)
    kept: tuple | None = field(default=None, repr=False, compare=False)

    @property
    def mean(self) -> np.ndarray:
        """Mean cross-validated R^2 over folds per alpha (-inf where unscored)."""
        m = self.cv_r2.mean(axis=0)
        return np.where(np.isnan(m), -np.inf, m)

    @property
    def transfer_mean(self) -> np.ndarray | None:
        """Mean transfer R^2 over the probe episodes per alpha (-inf where unprobed or diverged)."""
        if self.transfer_r2 is None:
            return None
        m = self.transfer_r2.mean(axis=0)
        return np.where(np.isnan(m), -np.inf, m)

    @property
    def objective(self) -> np.ndarray:
        """What the search maximizes per alpha: the lower of the cross-validated and transfer R^2.

        Without probes, the cross-validated R^2 alone.
        """
        t = self.transfer_mean
        return self.mean if t is None else np.minimum(self.mean, t)

    @property
    def best_index(self) -> int:
        """Index of the best alpha (the largest among ties: the better conditioned)."""
        m = self.objective
        return int(np.flatnonzero(m == m.max())[-1])

    @property
    def best_alpha(self) -> float:
        """The alpha with the best objective."""
        return float(self.alphas[self.best_index])

    @property
    def score(self) -> float:
        """The best objective (see :attr:`objective`)."""
        return float(self.objective[self.best_index])

    @property
    def cv_score(self) -> float:
        """Mean cross-validated R^2 at the best alpha."""
        return float(self.mean[self.best_index])

    @property
    def transfer_score(self) -> float | None:
        """Mean transfer R^2 at the best alpha (None without probes)."""
        t = self.transfer_mean
        return None if t is None else float(t[self.best_index])

    @property
    def transfer_worst(self) -> float | None:
        """The worst probe episode's R^2 at the best alpha (None without probes)."""
        return None if self.transfer_r2 is None else float(np.min(self.transfer_r2[:, self.best_index]))

    @property
    def score_std(self) -> float:
        """Spread of the fold scores at the best alpha (NaN when a fold's prediction diverged)."""
        folds = self.cv_r2[:, self.best_index]
        return float(np.std(folds)) if np.all(np.isfinite(folds)) else float("nan")

    def as_dict(self) -> dict:
        """Plain data for reports (None for scores that are not finite numbers)."""
        number = lambda v: None if v is None or not np.isfinite(v) else float(v)  # noqa: E731
        out = {
            **asdict(self.spec),
            "label": self.spec.label(),
            "stage": self.stage,
            "n_features": self.spec.n_features(),
            "alpha": self.best_alpha,
            "objective": number(self.score),
            "cv_r2": number(self.cv_score),
            "cv_r2_std": number(self.score_std),
            "transfer_r2": number(self.transfer_score),
            "transfer_r2_worst": number(self.transfer_worst),
            "seconds": self.seconds,
            "timing": {k: round(v, 3) for k, v in self.timing.items()},
            "cv_r2_by_alpha": [number(v) for v in self.mean],
        }
        transfer = self.transfer_mean  # None without probes
        if transfer is not None:
            out["transfer_r2_by_alpha"] = [number(v) for v in transfer]
        return out


@dataclass
class SearchResult:
    """Every candidate tried, and the winner.

    Attributes
    ----------
    candidates : list of CandidateResult
        In the order they were evaluated.
    window : int
        First scored sample of every validation episode.
    seconds : float
        Wall time of the search.
    probes : ProbeSet, optional
        The transfer probes the candidates were scored on.
    folds : CrossValidationFolds, optional
        The folds, with what each holds out (set by the caller that made them).
    same_controller : list of (int, float), optional
        With several training controllers, the winner's scores on folds holding out
        episodes of a controller it trained on (:func:`same_controller_scores`).
    stage_seconds : dict of str to float
        Wall time of each stage (its candidates run side by side on ``n_jobs`` workers).
    shared_seconds : dict of str to float
        Of each stage's wall time, the part spent lifting its families' largest liftings
        once (:func:`family_statistics`), before its candidates ran.
    probe_seconds : float
        Time the probes took to simulate (set by the caller that made them).
    screens : list of CandidateResult
        Every screen (:func:`screen_candidate`) of the stages that screened, finalists' included.
    screened : list of CandidateResult
        The screens of the candidates left out (not evaluated in full, not ranked).
    screen_bars : dict of str to float
        Per screened stage after the first, the lead's score on the screens' folds (:func:`screen_bar`),
        which a finalist's screen beat.
    """

    candidates: list[CandidateResult] = field(default_factory=list)
    window: int = 0
    seconds: float = 0.0
    probes: ProbeSet | None = None
    folds: object | None = None
    same_controller: list | None = None
    stage_seconds: dict = field(default_factory=dict)
    probe_seconds: float = 0.0
    shared_seconds: dict = field(default_factory=dict)
    screens: list = field(default_factory=list)
    screened: list = field(default_factory=list)
    screen_bars: dict = field(default_factory=dict)

    def timing(self) -> dict:
        """Where the search's time went: per stage its wall time and its candidates' summed
        time per kind of work (:data:`TIMING_KEYS`; with parallel workers the sums exceed
        the wall time), and the probes' simulation."""
        stages = {}
        for stage, wall in self.stage_seconds.items():
            work = dict.fromkeys(TIMING_KEYS, 0.0)
            for r in self.candidates + self.screens:
                if r.stage == stage:
                    for key, value in r.timing.items():
                        work[key] = work.get(key, 0.0) + value
            stages[stage] = {
                "wall": round(wall, 3),
                "candidates": sum(r.stage == stage for r in self.candidates),
                "screened_out": sum(r.stage == stage for r in self.screened),
                "shared_statistics": round(self.shared_seconds.get(stage, 0.0), 3),
                **{k: round(v, 3) for k, v in work.items()},
            }
        return {"probe_simulation": round(self.probe_seconds, 3), "stages": stages, "search": round(self.seconds, 3)}

    def ranked(self) -> list[CandidateResult]:
        """Best :attr:`CandidateResult.score` first; ties go to the smaller lifting, then the plain protocol."""
        return sorted(self.candidates, key=lambda r: (-r.score, r.spec.n_features(), r.spec.offsets, r.spec))

    @property
    def winner(self) -> CandidateResult:
        """The best candidate."""
        return self.ranked()[0]


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
    #: Alphas an offsets candidate is scored at: its plain twin's best (:attr:`SearchSpace.n_offset_alphas`).
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
    the folds again; given as that candidate's :class:`CandidateResult`, its models
    (:attr:`CandidateResult.reuse`) predict again without any statistics computed.
    ``shared``: the fold statistics of a lifting whose features include this one's
    (:func:`family_statistics`), from which this one's are taken exactly.
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
    top = None if plain is None else _best_alphas(_fold_scores(plain), data.n_offset_alphas)
    reuse = plain.reuse if isinstance(plain, CandidateResult) else None
    if spec.offsets and reuse is not None and top is not None and reuse.covers(top):  # top: set with any plain
        cv = _offset_scores(reuse.folds, reuse.lifting, data, top, timing)
        plants = {j: rows.model(reuse.lifting) for j, rows in reuse.plants.items()}
        transfer = None if data.probes is None else _transfer_scores(spec, data, cv, plants, timing)
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
        score_from=data.window,
        measured_only=True,
        keep_fold_models="rows" if subset else spec.offsets,
        fit_all=False,
        controllers=data.controllers,
        shared=shared,
    )
    timing |= sweep.seconds
    cv = sweep.cv_r2["cl"] if rescore else _fold_scores(plain)
    if screen is not None and n_screened:  # only a screen has screened folds
        cv = np.vstack([screen.cv_r2, cv])
    lifting = None if sweep.statistics is None else sweep.statistics[0].lifting
    folds = screened_folds + [
        ({j: rows for j, rows in enumerate(closed)}, validation) for closed, _, validation in sweep.fold_models or []
    ]
    if spec.offsets:
        top = _best_alphas(cv, data.n_offset_alphas)
        cv = _offset_scores(folds, lifting, data, top, timing)
    transfer, plants = None, {}
    if data.probes is not None:
        plants = _probe_plants(estimator, data, cv, sweep.statistics, timing)
        transfer = _transfer_scores(spec, data, cv, plants, timing, None if screen is None else screen.transfer_r2)
    kept = None
    if not spec.offsets and lifting is not None:
        best = [int(j) for j in _best_alphas(cv, data.n_offset_alphas)]
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
    candidates that screen best (:attr:`SearchSpace.n_finalists`). The screen's statistics are those
    of every fold (one pass over the episodes computes them all); it keeps them, its lifting
    and its folds' models (:attr:`CandidateResult.kept`), so a finalist scores only the
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


def _finalists(screens: Sequence[CandidateResult], k: int, bar: float | None = None) -> set[LiftingSpec]:
    """The liftings of the ``k`` best screens (ranked as :meth:`SearchResult.ranked` ranks candidates)
    that did not diverge and, with a ``bar`` (:func:`screen_bar`), score above it.

    Without a bar, the best one when all diverged (the first stage evaluates one candidate in full at
    least); with one, none when none beats it: the stage's lead stays the best so far.
    """
    ranked = SearchResult(list(screens)).ranked()
    passed = [r for r in ranked if np.isfinite(r.score) and (bar is None or r.score > bar)][:k]
    return {r.spec for r in (passed or (ranked[:1] if bar is None else []))}


def screen_bar(lead: CandidateResult, n_folds: int) -> float:
    """What a screened candidate must beat to be evaluated in full: the stage's lead (the best candidate
    so far, which every candidate of the stage varies) scored as a screen is, on the first ``n_folds``
    folds and the probes, at the alphas it was probed at.

    Successive halving with the incumbent among the arms: a screen that scores below the lead on the
    same folds and probes is not evaluated further. The transfer R^2, the lower of the two on the
    rig's data, does not depend on the folds (the probes' plant is fitted on every training episode),
    so a screen sees most of what decides the ranking. The lead counts the best of the alphas it was
    probed at (up to :attr:`SearchData.n_transfer_alphas`), a screen its one.
    """
    cv = lead.cv_r2[:n_folds].mean(axis=0)
    cv = np.where(np.isnan(cv), -np.inf, cv)
    transfer = lead.transfer_mean
    objective = cv if transfer is None else np.minimum(cv, transfer)
    return float(np.max(objective))


def _shared_statistics(head: LiftingSpec, data: SearchData, run, n_parts: int) -> tuple:
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


def _radial_statistics(specs: Sequence[LiftingSpec], data: SearchData, run, n_parts: int) -> dict:
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


def _fold_scores(plain) -> np.ndarray:
    """The plain fold scores, given as an array or a :class:`CandidateResult`."""
    return np.asarray(plain.cv_r2 if isinstance(plain, CandidateResult) else plain, dtype=float)


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


def _probe_plants(estimator, data: SearchData, cv: np.ndarray, statistics, timing: dict) -> dict:
    """The plants fitted on all training episodes at the best CV alphas ({alpha index: plant}).

    They fit only the rows re-lifted predictions use, from the statistics of all the
    episodes the sweep folded with its folds' when it had them. ``timing["probe_fits"]``
    gets their time.
    """
    from qube_koopman.core.blas import limited_blas_threads
    from qube_koopman.identify.model_selection.sweep import fit_alphas, fitted_models

    started = time.perf_counter()
    top = np.sort(_best_alphas(cv, data.n_transfer_alphas))
    if statistics is not None:
        setup, snapshots = statistics
        with limited_blas_threads(1):
            _, plants = fitted_models(estimator, setup, snapshots, data.alphas[top], None, None)
    else:
        _, plants = fit_alphas(
            estimator, data.trajectories, data.alphas[top], relift_rows_only=True, controllers=data.controllers
        )
    timing["probe_fits"] = time.perf_counter() - started
    return {int(j): plant for j, plant in zip(top, plants)}


def _transfer_scores(
    spec: LiftingSpec, data: SearchData, cv: np.ndarray, plants: dict, timing: dict, known: np.ndarray | None = None
) -> np.ndarray:
    """Probe scores (episodes x alphas) of ``plants`` ({alpha index: plant}) at the best CV alphas.

    ``known``: scores already computed at some alphas (NaN elsewhere), kept. Without offsets, the
    plants' closed loops with each probe controller are simulated together.
    ``timing["probe_scoring"]`` gets their time.
    """
    from qube_koopman.core.blas import limited_blas_threads

    probes = data.probes
    if probes is None:
        raise ValueError("transfer scores need the search's probes (SearchData.probes)")
    started = time.perf_counter()
    # The alphas with a plant: an offsets candidate predicting with its plain twin's has them at its scored alphas.
    top = [int(j) for j in np.sort(_best_alphas(cv, data.n_transfer_alphas)) if int(j) in plants]
    out = np.full((probes.n_episodes, data.alphas.size), np.nan)
    if known is not None:  # the columns a screen scored already (the same plants: the same numbers)
        done = [j for j in top if not np.all(np.isnan(known[:, j]))]
        out[:, done] = known[:, done]
        top = [j for j in top if j not in done]
    with limited_blas_threads(1):
        if spec.offsets and top:
            out[:, top] = _offset_probe_scores([plants[j] for j in top], probes, data.window, data.bound)
        elif top:
            out[:, top] = _plain_probe_scores([plants[j] for j in top], probes, data.window)
    timing["probe_scoring"] = time.perf_counter() - started
    return out


def _plain_probe_scores(plants: list, probes: ProbeSet, window: int) -> np.ndarray:
    """:func:`~qube_koopman.identify.metrics.probe_scores` without offsets of several plants (one lifting),
    every probe controller's closed loops of all of them simulated together: shape (n_episodes, n_plants)."""
    from qube_koopman.identify.model_selection.sweep import grouped_episode_scores

    return np.concatenate(grouped_episode_scores(_probe_loops(plants, probes), "cl", window, True), axis=1).T


def _offset_probe_scores(plants: list, probes: ProbeSet, window: int, bound: float) -> np.ndarray:
    """:func:`~qube_koopman.identify.metrics.probe_scores` with offsets of several plants (one lifting), each
    probe controller's closed loops of all of them estimated and predicted together: shape (n_episodes, n_plants)."""
    return np.concatenate(
        [scores_after_window_models(loops, held, window, bound) for loops, held in _probe_loops(plants, probes)],
        axis=1,
    ).T


def _probe_loops(plants: list, probes: ProbeSet) -> list[tuple[list, list]]:
    """Per probe controller: the plants' closed loops with it, and its probe episodes."""
    from qube_koopman.identify.estimators.structure import close_loop

    return [
        ([close_loop(p, controller, list(MEASURED)) for p in plants], episodes)
        for controller, episodes in zip(probes.controllers, probes.episodes)
    ]


def _best_alphas(cv: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` best alphas by mean fold score (-inf where a fold diverged), best first."""
    mean = cv.mean(axis=0)
    mean = np.where(np.isfinite(mean), mean, -np.inf)
    return np.argsort(-mean, kind="stable")[: min(k, mean.size)]


def _offset_scores(folds: list, lifting, data: SearchData, top: np.ndarray, timing: dict) -> np.ndarray:
    """Fold scores with an alpha offset estimated on each validation episode, at the alphas ``top``.

    ``folds``: per fold, {alpha index: closed loop} and the validation episodes; the closed loops
    are FittedRows rebuilt with ``lifting``, or models themselves when ``lifting`` is None.
    """
    from qube_koopman.core.blas import limited_blas_threads
    from qube_koopman.identify.model_selection.sweep import EPISODES_PER_BATCH

    started = time.perf_counter()
    out = np.full((len(folds), data.alphas.size), np.nan)
    with limited_blas_threads(1):
        for i, (closed, validation) in enumerate(folds):
            models = {int(j): closed[int(j)] if lifting is None else closed[int(j)].model(lifting) for j in top}
            scores = []
            for lo in range(0, len(validation), EPISODES_PER_BATCH):  # a few episodes read at a time
                held_out = [data.trajectories[k] for k in validation[lo : lo + EPISODES_PER_BATCH]]
                scores.append(scores_after_window_models(list(models.values()), held_out, data.window, data.bound))
            out[i, list(models)] = np.concatenate(scores, axis=1).mean(axis=1)
    timing["offsets"] = time.perf_counter() - started
    return out


def same_controller_scores(
    result: CandidateResult,
    trajectories: Sequence[Trajectory],
    controller: DiscreteStateSpace,
    controllers: Sequence[DiscreteStateSpace],
    *,
    window: int,
    n_splits: int = 3,
    seed: int = 1234,
    bound: float = DEFAULT_BOUND,
    rbf_seed: int = 0,
    loops: Sequence[DiscreteStateSpace] | None = None,
) -> list[tuple[int, float]]:
    """A candidate's same-controller score when the training episodes ran several controllers.

    The search ranks by per-controller folds
    (:func:`~qube_koopman.identify.model_selection.split.per_controller_splits`); this scores the
    candidate (its lifting, offset protocol and chosen alpha) on folds that
    hold out some episodes of one controller and train on all the rest
    (:func:`~qube_koopman.identify.model_selection.split.within_controller_splits`), as the
    loop a model was trained under is predicted.

    ``loops``: each episode's loop when it is not its controller alone (a session's command delay
    after it); a fold whose validation episodes ran several loops is scored as one fold per loop.

    Returns
    -------
    list of (controller label, fold R^2)
        Labels index :func:`~qube_koopman.identify.estimators.mixed.distinct_controllers`' list.
    """
    from qube_koopman.identify.estimators.mixed import distinct_controllers
    from qube_koopman.identify.model_selection.split import split_by_loop, within_controller_splits

    _, labels = distinct_controllers(controllers)
    folds = within_controller_splits(labels, n_splits, seed)
    if loops is not None:
        loop_labels = distinct_controllers(loops)[1]
        folds = [(tr, va, label) for tr0, va0, label in folds for tr, va in split_by_loop([(tr0, va0)], loop_labels)]
    data = SearchData(
        as_episodes(trajectories),
        [(tr, va) for tr, va, _ in folds],
        controller,
        np.array([result.best_alpha]),
        int(window),
        bound,
        rbf_seed,
        None,
        controllers=list(controllers if loops is None else loops),
    )
    cv = evaluate_candidate(result.spec, data).cv_r2[:, 0]
    return [(label, float(score)) for (_, _, label), score in zip(folds, cv)]


def search_liftings(
    trajectories: Sequence[Trajectory],
    controller: DiscreteStateSpace,
    *,
    splits,
    window: int,
    space: SearchSpace | None = None,
    n_jobs: int = 1,
    scheduler: str | None = None,
    bound: float = DEFAULT_BOUND,
    rbf_seed: int = 0,
    probes: ProbeSet | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    connect_timeout: float = 30.0,
    controllers: Sequence[DiscreteStateSpace] | None = None,
    security=None,
    worker_timeout: float = DEFAULT_WORKER_TIMEOUT,
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
    n_jobs : int
        Local worker processes (joblib's convention: -1 for every core).
    scheduler : str, optional
        Address of a dask.distributed scheduler to run the candidates on
        instead (needs the ``dask`` extra).
    probes : ProbeSet, optional
        Transfer probes (:func:`~qube_koopman.identify.model_selection.transfer.twin_probes`):
        each candidate is then ranked by the lower of its cross-validated and
        its transfer R^2 (:attr:`CandidateResult.objective`); without them by
        the cross-validated R^2 alone.
    progress : callable(label, done, total), optional
    connect_timeout : float
        Seconds to keep trying to reach ``scheduler`` before giving up.
    controllers : sequence of DiscreteStateSpace, optional
        Each episode's controller, when they ran several: every candidate's
        plant is fitted to all of them, and each fold's closed loop is that of
        the controller its validation episodes ran.
    security : distributed.security.Security, optional
        The TLS certificates of a ``tls://`` ``scheduler`` (default: dask's configuration).
    worker_timeout : float
        Seconds the ``scheduler``'s cluster may have no worker, results awaited, before the
        search gives up (:class:`~qube_koopman.identify.model_selection.distributed.NoWorkersError`).

    Returns
    -------
    SearchResult
    """
    import joblib

    from qube_koopman.identify.model_selection.sweep import episode_heads, seconds_timer

    space = space or SearchSpace()
    data = SearchData(
        as_episodes(trajectories),
        list(splits),
        controller,
        np.asarray(space.alphas, dtype=float),
        int(window),
        bound,
        rbf_seed,
        probes,
        controllers=None if controllers is None else list(controllers),
        n_offset_alphas=space.n_offset_alphas,
    )
    client = connect(scheduler, connect_timeout, security) if scheduler else None
    run = candidate_runner(n_jobs, client, worker_timeout)
    # A family's statistics are computed by parts of the episodes on the workers, joined here: as many
    # parts whatever the workers (the same numbers on any machine).
    n_parts = max(1, min(FAMILY_PARTS, len(data.trajectories) // 4))
    started = time.perf_counter()
    result, seen = SearchResult(window=int(window), probes=probes), set()
    sharing = seconds_timer(result.shared_seconds)  # the time each stage spends on statistics shared by its candidates
    # The family heads' statistics, by head, for later stages' liftings they hold.
    earlier: dict[LiftingSpec, tuple] = {}
    try:
        for stage in STAGES:
            stage_started = time.perf_counter()
            specs = [s for s in space.stage_candidates(stage, result.ranked()) if s not in seen]
            seen.update(specs)
            # An offsets candidate reuses its plain twin: its fold scores choose the alphas, its models predict.
            plain = {r.spec: r for r in result.candidates}
            # A family's largest lifting is lifted once; the others' statistics are columns of its own.
            heads = {s: family_of(s, specs) for s in specs}
            shared: dict[LiftingSpec, tuple | None] = {}
            for head in sorted(set(h for h in heads.values() if h is not None)):
                with sharing(stage):
                    # With the friction shape too when the friction stage may try it: that stage's new
                    # candidate (the best so far with friction) then takes its statistics from these.
                    big = replace(head, friction=True) if space.tries_friction(head) else head
                    earlier[big] = _shared_statistics(big, data, run, n_parts)
                    shared.update({s: earlier[big] for s in specs if heads[s] == head})
            longest = delays_family(specs)
            if longest is not None:  # liftings but for their delays: the longest's statistics, and the heads
                with sharing(stage):
                    stats = (
                        *_shared_statistics(longest, data, run, n_parts),
                        episode_heads(data.trajectories, longest.delays),
                    )
                    shared.update({s: stats for s in specs if replace(s, delays=longest.delays) == longest})
            for s in specs:  # a lifting whose features an earlier stage's family head holds
                if shared.get(s) is None:
                    shared[s] = next((v for h, v in earlier.items() if holds_features(h, s)), None)
            screens = {}
            alone = [s for s in specs if shared.get(s) is None]
            radial = [s for s in alone if s.rbf and replace(s, rbf=0) == replace(alone[0], rbf=0)]
            if len(radial) > 1:  # the RBF stage: one factorization for every number of centres, in parts
                with sharing(stage):
                    shared.update(_radial_statistics(radial, data, run, n_parts))
            if space.screens(stage, len(specs)):
                # Successive halving: every candidate screened cheaply, the best few evaluated in full.
                # The largest first: the last to start on a worker is then a short one.
                calls = [
                    joblib.delayed(screen_candidate)(s, data, stage, shared.get(s), space.screen_folds)
                    for s in sorted(specs, key=lambda s: -s.n_features())
                ]
                for done, res in enumerate(run(calls), start=1):
                    screens[res.spec] = res
                    if progress:
                        progress(f"search: {stage} (screen)", done, len(specs))
                lead = result.ranked()[0] if result.candidates and space.screen_against_lead else None
                bar = None if lead is None else screen_bar(lead, space.screen_folds)
                if bar is not None:
                    result.screen_bars[stage] = bar
                finalists = _finalists(list(screens.values()), space.n_finalists, bar)
                result.screened += [replace(r, kept=None) for r in screens.values() if r.spec not in finalists]
                result.screens += [replace(r, kept=None) for r in screens.values()]
                specs = [s for s in specs if s in finalists]
            calls = [
                joblib.delayed(evaluate_candidate)(
                    s, data, stage, plain.get(replace(s, offsets=False)), shared.get(s), screens.get(s)
                )
                for s in sorted(specs, key=lambda s: -s.n_features())
            ]  # the largest first, as the screens
            for done, res in enumerate(run(calls), start=1):
                result.candidates.append(res)
                if progress:
                    progress(f"search: {stage}", done, len(specs))
            result.stage_seconds[stage] = time.perf_counter() - stage_started
            _log.info(
                "search: stage %s: %d candidates in %.1f s%s",
                stage,
                len(specs),
                result.stage_seconds[stage],
                f" ({len(screens)} screened, {len(screens) - len(specs)} left out)" if screens else "",
            )
    finally:
        release_workers(n_jobs, client)
    result.seconds = time.perf_counter() - started
    return result
