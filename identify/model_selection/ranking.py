"""The lifting search's scoring and ranking rule: a candidate's scores over the alpha grid
(:class:`CandidateResult`), its objective (the lower of its cross-validated and transfer R^2), the
ranking of every candidate (:class:`SearchResult`), and which screens go on to a full evaluation
(:func:`finalists`, :func:`screen_bar`).

Cross-validation under the training controller alone rewards liftings that fit that loop's own
correlations (high-order monomials, RBFs), which diverged under other controllers: candidates rank
by the lower of the two scores.

The winner is not the largest objective alone. Candidates whose objective is within
:attr:`SearchResult.tie_standard_errors` standard errors of the best one's (the standard error of the
paired difference over the folds, or the probe episodes, whichever sets the best one's objective:
:func:`objective_gap`) are tied, the one-standard-error rule of cross-validation; among them the
winner transfers best (the highest transfer R^2, the question a plant identified in closed loop is
for; among equal transfers the better objective). Why: the lower of two scores ignores the other one, and with a new
controller's few episodes in training its folds set the objective and differ between liftings by
less than their own noise, so the largest objective picked among a dozen near-equal liftings the
one whose noise was luckiest: on the rig's 28 logs and six soft episodes it chose a 40-delay,
50-RBF lifting (objective 0.9789, transfer 0.9822) over the same with the arm's friction shape
(0.9780, one standard error 0.0012 away; transfer 0.9902), and predicted the four soft episodes
it had not seen at 0.969 / 0.935 (mean / worst R^2), below the plant trained on the rig's logs
alone (0.972 / 0.942); with the rule the search wins with the friction shape, 0.974 / 0.942
(docs/transfer.md).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Sequence

import numpy as np

from qube_koopman.identify.model_selection.lifting_space import TIE_STANDARD_ERRORS, LiftingSpec
from qube_koopman.identify.model_selection.transfer import ProbeSet

if TYPE_CHECKING:
    from qube_koopman.identify.model_selection.evaluation import Reuse

__all__ = ["CandidateResult", "SearchResult", "finalists", "screen_bar", "objective_gap", "TIMING_KEYS"]

#: What a candidate's time is spent on (:attr:`CandidateResult.timing`), in the order it is spent.
TIMING_KEYS = ("statistics", "fits", "predictions", "offsets", "probe_fits", "probe_scoring")


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
        A screen's (:func:`~.screen_candidate`) lifting steps, its statistics (None when the
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
        episodes of a controller it trained on (:func:`~.same_controller_scores`).
    stage_seconds : dict of str to float
        Wall time of each stage (its candidates run side by side on ``n_jobs`` workers).
    shared_seconds : dict of str to float
        Of each stage's wall time, the part spent lifting its families' largest liftings
        once (:func:`~.family_statistics`), before its candidates ran.
    probe_seconds : float
        Time the probes took to simulate (set by the caller that made them).
    offsets_first : bool
        Whether every stage scored its candidates with offsets
        (:attr:`~.lifting_space.SearchSpace.offsets_first`, as decided for the training logs).
    screens : list of CandidateResult
        Every screen (:func:`~.screen_candidate`) of the stages that screened, finalists' included.
    screened : list of CandidateResult
        The screens of the candidates left out (not evaluated in full, not ranked).
    screen_bars : dict of str to float
        Per screened stage after the first, the lead's score on the screens' folds (:func:`screen_bar`),
        which a finalist's screen beat.
    tie_standard_errors : float
        Candidates within this many standard errors of the best objective are tied (:meth:`tied`);
        0: the best objective wins.
    """

    candidates: list[CandidateResult] = field(default_factory=list)
    window: int = 0
    seconds: float = 0.0
    probes: ProbeSet | None = None
    folds: object | None = None
    same_controller: list | None = None
    stage_seconds: dict = field(default_factory=dict)
    probe_seconds: float = 0.0
    offsets_first: bool = False
    shared_seconds: dict = field(default_factory=dict)
    screens: list = field(default_factory=list)
    screened: list = field(default_factory=list)
    screen_bars: dict = field(default_factory=dict)
    tie_standard_errors: float = TIE_STANDARD_ERRORS

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
        """The winner first (see :meth:`tied`), then the others by :attr:`CandidateResult.score`, best first;
        equal scores go to the smaller lifting, then the plain protocol."""
        by_score = sorted(self.candidates, key=_score_key)
        tied = self.tied(by_score)
        if not tied:
            return by_score
        winner = max(tied, key=_transfer)  # max keeps the first of equals: the better scored
        return [winner] + [r for r in by_score if r is not winner]

    def tied(self, by_score: "list[CandidateResult] | None" = None) -> list[CandidateResult]:
        """The candidates tied with the best objective, best first: within :attr:`tie_standard_errors`
        standard errors of it (:func:`objective_gap`). The winner is the one among them with the highest
        transfer R^2 (the best objective without probes). Empty without candidates."""
        ranked = sorted(self.candidates, key=_score_key) if by_score is None else by_score
        if not ranked or not np.isfinite(ranked[0].score):
            return ranked[:1]
        best = ranked[0]
        out = []
        for r in ranked:
            gap, standard_error = objective_gap(best, r)
            if gap <= self.tie_standard_errors * standard_error:
                out.append(r)
        return out

    @property
    def winner(self) -> CandidateResult:
        """The recommended candidate: of those tied with the best objective, the best transfer (see :meth:`tied`)."""
        return self.ranked()[0]


def _score_key(r: CandidateResult) -> tuple:
    return (-r.score, r.spec.n_features(), r.spec.offsets, r.spec)


def _transfer(r: CandidateResult) -> float:
    t = r.transfer_score
    return -np.inf if t is None or not np.isfinite(t) else t


def objective_gap(best: CandidateResult, other: CandidateResult) -> tuple[float, float]:
    """How far ``other``'s objective is below ``best``'s, and the standard error of that difference.

    The objective is the lower of two means (:attr:`CandidateResult.objective`); the standard error is that of
    the paired differences of the mean ``best``'s objective takes: over the folds (each candidate at its best
    alpha) when its cross-validated R^2 is the lower, over the probe episodes when its transfer R^2 is. A
    paired difference, since the candidates are scored on the same folds and probes, whose own difficulty
    is shared. NaN standard error (never tied unless equal) where a difference is not finite or fewer than
    two are scored.
    """
    gap = best.score - other.score
    transfer = best.transfer_score
    if (
        best.transfer_r2 is not None
        and other.transfer_r2 is not None
        and transfer is not None
        and transfer <= best.cv_score
    ):
        a, b = best.transfer_r2[:, best.best_index], other.transfer_r2[:, other.best_index]
    else:
        a, b = best.cv_r2[:, best.best_index], other.cv_r2[:, other.best_index]
    d = a - b
    if d.size < 2 or not np.all(np.isfinite(d)):
        return gap, float("nan") if gap else 0.0
    return gap, float(np.std(d, ddof=1) / np.sqrt(d.size))


def finalists(screens: Sequence[CandidateResult], k: int, bar: float | None = None) -> set[LiftingSpec]:
    """The liftings of the ``k`` best screens (ranked as :meth:`SearchResult.ranked` ranks candidates)
    that did not diverge and, with a ``bar`` (:func:`screen_bar`), score above it.

    Without a bar, the best one when all diverged (the first stage evaluates one candidate in full at
    least); with one, none when none beats it: the stage's lead stays the best so far.
    """
    # a screen's one fold gives no standard error: the screens rank by their objective
    ranked = SearchResult(list(screens), tie_standard_errors=0.0).ranked()
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
    probed at (up to :attr:`~.SearchData.n_transfer_alphas`), a screen its one.
    """
    cv = lead.cv_r2[:n_folds].mean(axis=0)
    cv = np.where(np.isnan(cv), -np.inf, cv)
    transfer = lead.transfer_mean
    objective = cv if transfer is None else np.minimum(cv, transfer)
    return float(np.max(objective))
