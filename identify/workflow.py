"""Identify, select the regularization, score on test episodes: the qube-identify workflow."""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from qube_koopman.core.blas import episode_threads, limited_blas_threads
from qube_koopman.core.files import atomic_path
from qube_koopman.core.workers import resolve_n_jobs
from qube_koopman.core.controller import QUBE_SAMPLE_PERIOD
from qube_koopman.identify.estimators.arx import Arx, ClArx
from qube_koopman.identify.estimators.base import episode_statistics as statistics_here
from qube_koopman.identify.estimators.cl_edmd import ClEdmd, ClEdmdKnownRows, ClEdmdLstsq
from qube_koopman.identify.data.logs import LoggedTrajectory, LogTrajectories, recorded_controllers
from qube_koopman.core.lti import same_system, with_output_delay
from qube_koopman.identify.estimators.mixed import training_controllers_report
from qube_koopman.identify.model_selection.distributed import DEFAULT_WORKER_TIMEOUT
from qube_koopman.identify.model_selection.split import FOLD_KINDS, cross_validation_folds
from qube_koopman.identify.estimators.edmd import Edmd
from qube_koopman.identify.estimators.stability import ClEdmdStable
from qube_koopman.identify.models.model_file import lifting_to_dict, save_arx_model, save_model, uncertainty_to_dict
from qube_koopman.identify.models.offsets import DEFAULT_BOUND
from qube_koopman.identify.models.kstep import (
    MAX_EPISODES,
    AheadOptions,
    AheadScores,
    fit_training_disturbance,
    spread,
)
from qube_koopman.identify.metrics import DivergedPrediction, EpisodeScore, episode_score, summarize_scores
from qube_koopman.identify.estimators.structure import close_loop, command_delayed, controller_states
from qube_koopman.identify.model_selection.sweep import (
    SweepOptions,
    SweepResult,
    regularization_sweep,
    warn_at_grid_edge,
)
from qube_koopman.identify.uncertainty.spectra import error_spectra
from qube_koopman.identify.uncertainty.filter_band import (
    AheadBand,
    calibrate_filter,
    calibrate_filter_on_probe_sets,
    fold_fits,
    residual_model,
)
from qube_koopman.identify.uncertainty import (
    BandSummary,
    CalibrationOptions,
    IntervalCalibration,
    IntervalOptions,
    Loop,
    calibrate,
    calibrate_on_probe_sets,
    consecutive_runs,
    widest,
    fit_ensemble,
    held_out_loops,
    loops_figures,
    references,
    predict_episodes,
    prediction_band,
)
from qube_koopman.core.lti import DiscreteStateSpace, spectral_radius
from qube_koopman.core.qube import MEASURED, SKIP_SAMPLES, STATE_NAMES

if TYPE_CHECKING:
    from qube_koopman.identify.models.model import KoopmanModel
    from qube_koopman.identify.model_selection.lifting_space import SearchSpace
    from qube_koopman.identify.model_selection.transfer import ProbeSet

__all__ = [
    "FitOptions",
    "IdentificationResult",
    "IdentifyOptions",
    "OffsetProtocol",
    "OutputOptions",
    "ScoreOptions",
    "identify_and_score",
    "KOOPMAN_METHODS",
    "SearchOptions",
    "run_search",
]

KOOPMAN_METHODS = {
    "edmd": Edmd,
    "cl-edmd": ClEdmd,
    "cl-edmd-known-rows": ClEdmdKnownRows,
    "cl-edmd-lstsq": ClEdmdLstsq,
    "cl-edmd-stable": ClEdmdStable,
}
# Methods whose model is one loop's (unstructured closed loop, or a constraint on one loop): one controller only.
SINGLE_LOOP_METHODS = {
    "cl-arx": "--method cl-arx",
    "cl-edmd-lstsq": "--method cl-edmd-lstsq",
    "cl-edmd-stable": "--max-radius (the stability-constrained fit)",
}


@dataclass(frozen=True)
class OffsetProtocol:
    """Per-episode offsets estimated on each test episode before it is scored.

    Parameters
    ----------
    channels : tuple of str
        Measured channels with an offset (state names, e.g. ``("alpha",)``).
    window_s : float
        Estimation window (s) at the start of each test episode; scores
        cover only the samples after it.
    bound : float
        Plausibility bound; a larger estimate is flagged and not used.
    """

    channels: tuple[str, ...]
    window_s: float = 1.0
    bound: float = DEFAULT_BOUND

    def describe(self, dt: float) -> str:
        """The protocol in words, for reports."""
        return (
            f"offsets of {', '.join(self.channels)} estimated on each test episode from its first "
            f"{self.window_s:g} s ({self.window(dt)} samples) by simulation-error least squares, "
            f"estimates beyond {self.bound:g} flagged and not used; the whole episode is predicted "
            f"from its start and only the samples after the window are scored, with and without "
            f"the offsets"
        )

    def window(self, dt: float) -> int:
        """The window in samples."""
        return int(round(self.window_s / dt))


PAPER_PROTOCOL = (
    "the paper's: each test episode predicted from its initial condition, "
    "every sample after the first scored, no offsets"
)


def window_protocol(start: int, dt: float) -> str:
    """The plain protocol scored from the end of an estimation window, as the search scores candidates."""
    return (
        f"each test episode predicted from its initial condition, no offsets, scored from sample {start} "
        f"({start * dt:g} s: the end of the estimation window, as the search scored its candidates)"
    )


@dataclass
class IdentificationResult:
    """What a run produced: the report, the models, the test predictions.

    Parameters
    ----------
    report : dict
        The run's figures as ``qube-identify`` writes them to its JSON report (``alpha``,
        ``test`` scores, ``spectral_radius``, ...).
    plant, closed_loop : KoopmanModel or None
        The identified plant and closed loop (None where the method gives none).
    sweep : SweepResult, optional
        The cross-validation of alpha, when ``FitOptions.alphas`` were given.
    test_names : list of str
        The test episodes, in order.
    test_truth, test_predictions, test_time : list of ndarray
        Each test episode's measured and predicted states and its time axis (s) (empty without
        ``OutputOptions.keep_predictions``).
    test_bands : list of PredictionBand
        With intervals: each test episode's interval over its scored samples (empty without
        ``keep_predictions``).
    """

    report: dict
    plant: object = None
    closed_loop: object = None
    sweep: SweepResult | None = None
    test_names: list[str] = field(default_factory=list)
    test_truth: list[np.ndarray] = field(default_factory=list)
    test_predictions: list[np.ndarray] = field(default_factory=list)
    test_time: list[np.ndarray] = field(default_factory=list)
    test_bands: list = field(default_factory=list)


def _spectral_radius(A) -> float | None:
    return None if A is None else spectral_radius(A)


@dataclass(frozen=True)
class FitOptions:
    """How the model is fitted: the method, its lifting and its regularization.

    Parameters
    ----------
    method : str
        ``"cl-edmd"``, ``"cl-edmd-known-rows"``, ``"cl-edmd-lstsq"``, ``"cl-edmd-stable"``,
        ``"edmd"``, ``"arx"`` or ``"cl-arx"`` (``qube-identify --method``).
    lifting : sequence of LiftingFunction
        The lifting of the plant states (the Koopman methods).
    alpha : float
        The Tikhonov coefficient, when ``alphas`` is not given.
    alphas : sequence of float or ndarray, optional
        Candidates for alpha, chosen by cross-validation on the training logs with the test
        episodes' scoring: folds leave one controller out when the logs ran two or more, else
        episode-grouped random splits (``cv_splits``, ``cv_seed``).
    cv_splits, cv_seed : int
        The episode-grouped splits of the cross-validation and their seed.
    arx_lags : int
        Output and input lags of ``"arx"`` and ``"cl-arx"``.
    estimator_options : dict, optional
        More constructor arguments of the estimator (``max_radius`` of ``"cl-edmd-stable"``, ...).
    n_threads : int
        Training episodes factored side by side (-1: one per core this process may run on), each
        with one BLAS thread (:func:`~qube_koopman.core.blas.episode_threads`): the same model
        whatever the count.
    """

    method: str
    lifting: Sequence = ()
    alpha: float = 1e-3
    alphas: Sequence[float] | np.ndarray | None = None
    cv_splits: int = 3
    cv_seed: int = 1234
    arx_lags: int = 10
    estimator_options: dict | None = None
    n_threads: int = -1


@dataclass(frozen=True)
class ScoreOptions:
    """How the test episodes are predicted and scored.

    Parameters
    ----------
    score : {"cl", "plant"}
        Predict the test episodes in closed loop under their own log's controller, or from their
        plant input (and score the cross-validation so).
    offsets : OffsetProtocol, optional
        Estimate each test episode's offsets from its initial window.
    score_from : int, optional
        Without ``offsets``: score the test episodes from this sample on instead of the paper's
        sample 1 (as a search scores its candidates), for every method.
    what_if : DiscreteStateSpace, optional
        Predict every test episode under this controller instead; only episodes recorded under it
        are scored.
    command_delay : float or "estimate"
        Predict every test episode's loop with its command reaching the plant this many sample
        periods later than in the training logs (:func:`~qube_koopman.identify.estimators.structure.command_delayed`):
        a host with more latency. ``"estimate"``: each test episode's own extra delay, estimated
        from the other test logs of its recording session
        (:func:`~qube_koopman.identify.models.latency.estimate_command_delays`; report.json's
        ``command_delay`` lists them). Closed-loop scoring of a Koopman method only.
    """

    score: str = "cl"
    offsets: OffsetProtocol | None = None
    score_from: int | None = None
    what_if: DiscreteStateSpace | None = None
    command_delay: float | str = 0.0

    def first_scored(self, dt: float) -> int:
        """The first scored sample of each test episode: after the offsets' window, ``score_from``, or the second."""
        return _first_scored(self.offsets, self.score_from, dt)


@dataclass(frozen=True)
class OutputOptions:
    """What a run writes and keeps.

    Parameters
    ----------
    model_path : str or Path, optional
        Write the identified model there (:func:`save_model`).
    predictions_folder : str or Path, optional
        With intervals or K-step predictions: write each test episode's prediction, interval and
        K-step predictions there (``<log>.npz``).
    keep_predictions : bool
        Keep every test episode's truth and prediction in the result (for a recording); without it
        only their scores are kept.
    """

    model_path: str | Path | None = None
    predictions_folder: str | Path | None = None
    keep_predictions: bool = True


@dataclass(frozen=True)
class IdentifyOptions:
    """Everything :func:`identify_and_score` is asked to do, checked together when made.

    Parameters
    ----------
    fit : FitOptions
        The method, its lifting and its regularization.
    scoring : ScoreOptions
        How the test episodes are predicted and scored.
    intervals : IntervalOptions, optional
        Give every test prediction an interval (a Koopman method).
    probe_cache : str or Path, optional
        With ``intervals``: where the twin's probe episodes calibrating the intervals of loops the
        training never ran are kept between runs (``twin_probes``' ``cache``).
    ahead : AheadOptions, optional
        A Koopman method: fit a disturbance model on the training episodes, store it in the model
        file, and score every test episode at these horizons with the measurements up to each
        start (:mod:`~qube_koopman.identify.models.kstep`; report.json's ``ahead``).
    output : OutputOptions
        What is written and kept.

    Raises
    ------
    ValueError
        When the options contradict one another (offsets, a what-if controller, intervals, K-step
        predictions or a command delay with a method or scoring that cannot have them).
    """

    fit: FitOptions
    scoring: ScoreOptions = field(default_factory=ScoreOptions)
    intervals: IntervalOptions | None = None
    probe_cache: str | Path | None = None
    ahead: AheadOptions | None = None
    output: OutputOptions = field(default_factory=OutputOptions)

    def __post_init__(self) -> None:
        method, score, delay = self.fit.method, self.scoring.score, self.scoring.command_delay
        koopman = method in KOOPMAN_METHODS
        if not koopman and (
            self.scoring.offsets is not None
            or self.scoring.what_if is not None
            or self.intervals is not None
            or self.ahead is not None
        ):
            raise ValueError(
                f"offsets, what-if controllers, intervals and K-step predictions need a Koopman method, not {method}"
            )
        if method == "arx" and score == "cl":
            raise ValueError(
                "ARX models the plant only: its predictions come from the plant input, not the "
                "closed loop; use score='plant', or method 'cl-arx' for closed-loop scores"
            )
        if self.scoring.what_if is not None and score != "cl":
            raise ValueError("a what-if controller predicts the closed loop: use score='cl'")
        if delay and (score != "cl" or not koopman):
            raise ValueError(
                "a command delay changes the predicted loop: it needs closed-loop scores of a Koopman method"
            )
        if isinstance(delay, str):
            if delay != "estimate":
                raise ValueError(f"the command delay is a number of sample periods or 'estimate', got {delay!r}")
        elif not (np.isfinite(delay) and delay >= 0):
            raise ValueError(f"the command delay must be 0 or more sample periods, got {delay}")
        if not koopman and method not in ("arx", "cl-arx"):
            raise ValueError(f"unknown method {method!r}")

    @property
    def filtered(self) -> bool:
        """Whether the intervals are the disturbance filter's (not the bootstrap's)."""
        return self.intervals is not None and self.intervals.method == "disturbance"


def identify_and_score(
    train: Sequence[LoggedTrajectory],
    test: Sequence[LoggedTrajectory],
    controller: DiscreteStateSpace,
    options: IdentifyOptions,
    *,
    progress: Callable[[str, int, int], None] | None = None,
    episode_statistics: Callable | None = None,
    probes: ProbeSet | None = None,
) -> IdentificationResult:
    """Fit ``options.fit``'s method on the training logs and score it on the test logs.

    Training logs may come from several controllers: each episode is fitted with its own log's
    controller (one plant for all), and ``controller`` is the one whose closed loop the model
    describes (qube-identify: the majority's). The stages, in order: the fit (and the choice of
    alpha), the intervals' calibration, the model file, the test scores, the K-step predictions.
    A diverged test prediction is reported by episode and sample with a
    :class:`~qube_koopman.identify.metrics.DivergedPrediction` warning.

    Logs may be :class:`~qube_koopman.identify.data.logs.StoredLog` (read when needed): the fit, the
    cross-validation and the test scores then read one episode at a time, and memory does not grow
    with the number of logs.

    With ``options.intervals`` every predicted sample of every test episode gets an interval: an
    episode bootstrap of the fit, the offsets' standard errors, and a scale of the model's error
    calibrated on held-out training episodes (:mod:`~qube_koopman.identify.uncertainty`), or with
    ``method == "disturbance"`` the disturbance filter's variance
    (:mod:`~qube_koopman.identify.uncertainty.filter_band`); report.json's ``intervals`` gives each
    episode's and the pooled coverage, mean half-width and RMS error per channel.

    Parameters
    ----------
    train, test : sequence of LoggedTrajectory
        The training and test logs (:func:`load_logs`).
    controller : DiscreteStateSpace
        The controller whose closed loop the model describes.
    options : IdentifyOptions
        What to fit, how to score, what to write.
    progress : callable, optional
        ``progress(stage, done, total)``, called as the work advances.
    episode_statistics : callable, optional
        Computes a Koopman method's per-episode statistics elsewhere, for the fit and the sweep (on
        a dask cluster: :class:`~qube_koopman.identify.model_selection.distributed.ClusterStatistics`).
    probes : ProbeSet, optional
        With intervals (``other_loops="twin"``): the twin's probe episodes calibrating the
        intervals of test episodes under a loop the training never ran; when needed and not given,
        simulated from the training episodes on the twin as the rig's sessions differed (a
        search's transfer probes run on the calibrated twin alone and are not these).

    Returns
    -------
    IdentificationResult
    """
    result = _new_result(train, test, controller, options)
    with limited_blas_threads(1), episode_threads(resolve_n_jobs(options.fit.n_threads, len(train), "n_threads")):
        if options.fit.method in KOOPMAN_METHODS:
            fitted = _identify_koopman(train, test, controller, options, result, progress, episode_statistics, probes)
            plant, closed = fitted.plant, fitted.closed
        else:
            plant, closed = _identify_arx(train, test, controller, options, result, progress)
    result.plant, result.closed_loop = plant, closed
    return result


def _new_result(train, test, controller, options: IdentifyOptions) -> IdentificationResult:
    """The result with the run's inputs reported; refuses a one-loop method on logs of several controllers."""
    method = options.fit.method
    result = IdentificationResult(
        report={
            "method": method,
            "score": options.scoring.score,
            "train_logs": [log.path.name for log in train],
            "test_logs": [log.path.name for log in test],
            "controller": controller.as_dict(),
            "training_controllers": training_controllers_report(train, controller),
        }
    )
    n_controllers = result.report["training_controllers"]["n_controllers"]
    if method in SINGLE_LOOP_METHODS and n_controllers > 1:
        raise ValueError(
            f"{SINGLE_LOOP_METHODS[method]} identifies one closed loop: its training logs must share "
            f"one controller, these ran {n_controllers} (cl-edmd, cl-edmd-known-rows, edmd and arx fit "
            "logs of several)"
        )
    return result


@dataclass(frozen=True)
class _KoopmanFit:
    """A Koopman method's fit: the plant, its closed loop, and with intervals the ensemble of refits."""

    plant: KoopmanModel
    closed: KoopmanModel
    ensemble: Any = None

    def model(self, score: str):
        """The model scored: the closed loop (``score="cl"``) or the plant."""
        return self.closed if score == "cl" else self.plant


def _identify_koopman(train, test, controller, options: IdentifyOptions, result, progress, elsewhere, probes):
    """A Koopman method's stages: fit, intervals' calibration, model file, test scores, K-step predictions."""
    scoring, output = options.scoring, options.output
    fitted = _fit_koopman(options.fit, train, controller, scoring.score, options.intervals, result, progress, elsewhere)
    start = scoring.first_scored(test[0].dt)
    held_out: dict = {}  # the calibration's held-out predictions, which the model file's design figures reuse
    disturbance = None
    if options.ahead is not None:
        disturbance, result.report["disturbance"] = _training_disturbance(
            fitted.model(scoring.score), train, controller, scoring.score, options.ahead
        )
    bands = None
    if fitted.ensemble is not None and options.filtered:
        bands = _filter_bands(fitted, options, train, controller, start, result, probes, disturbance)
    elif fitted.ensemble is not None:
        bands = _test_bands(fitted.ensemble, options, train, controller, start, result, probes, held_out)
    ahead_scores = None
    if options.ahead is not None:
        ahead_band = None if bands is None or not options.filtered else bands.ahead_band
        ahead_scores = AheadScores(options.ahead, disturbance, start, output.predictions_folder is not None, ahead_band)
    if output.model_path is not None:
        _write_koopman_model(options, fitted, controller, train, result, disturbance, held_out)
    held_out.clear()
    loops = _predicted_loops(fitted.plant, train, test, controller, scoring, start, result)
    scores = _TestScores(result, start, output.keep_predictions, progress, len(test))
    _score_koopman(fitted, loops, test, scoring, scores, bands, ahead_scores)
    if ahead_scores is not None:
        result.report["ahead"] = ahead_scores.report()
        if output.predictions_folder is not None:
            _save_ahead(Path(output.predictions_folder), test, ahead_scores)
    return fitted


def _identify_arx(train, test, controller, options: IdentifyOptions, result, progress):
    """ARX's stages: fit from every training episode at once (not streamed: a baseline, small liftings),
    model file, test scores."""
    fit, scoring = options.fit, options.scoring
    trajs = list(LogTrajectories(train))
    plant, closed, predict = _arx(fit.method, trajs, test, controller, fit.arx_lags, scoring.score, result)
    if options.output.model_path is not None:
        model = plant if fit.method == "arx" else closed
        save_arx_model(options.output.model_path, method=fit.method, lags=fit.arx_lags, model=model)
    _score_arx(predict, test, result, scoring.score_from, options.output.keep_predictions, progress)
    return plant, closed


def _fit_koopman(fit: FitOptions, train, controller, score, intervals, result, progress, elsewhere) -> _KoopmanFit:
    """The fit on every training episode (alpha chosen by cross-validation when ``fit.alphas`` are given);
    with ``intervals``, its refits too, in the same pass over the episodes."""
    cls = KOOPMAN_METHODS[fit.method]
    options = fit.estimator_options or {}
    trajs, controllers = LogTrajectories(train), [log.controller for log in train]
    make = (
        (lambda a: cls(lifting=fit.lifting, alpha=a, **options))
        if cls is Edmd
        else (lambda a: cls(controller, lifting=fit.lifting, alpha=a, **options))
    )
    # EDMD fits the plant from its logged input, whatever the controller; the others from each episode's own.
    own = None if cls is Edmd else controllers
    counted = _counted_statistics(elsewhere, progress, "fit: training episodes")
    alpha = fit.alpha
    if fit.alphas is not None:
        alpha = _select_alpha(make(0.0), train, controller, fit, score, result, progress, elsewhere)
    result.report["alpha"] = float(alpha)
    ensemble = None
    if intervals is None:
        fitted = _fit(make(alpha), trajs, own, counted)
    else:  # the plain fit, its bootstrap refits and the calibration folds' in one pass over the episodes
        ensemble = (fold_fits if intervals.method == "disturbance" else fit_ensemble)(
            make(alpha), trajs, intervals, own, controller, MEASURED, counted
        )
        fitted = ensemble.estimator
    if hasattr(fitted, "unconstrained_radius_"):
        result.report["constraint"] = {
            **options,
            "unconstrained_radius": fitted.unconstrained_radius_,
            "solver_status": fitted.solver_status_,
        }
    plant = fitted.model_ if cls is Edmd else fitted.plant_model_
    closed = close_loop(plant, controller, MEASURED) if cls is Edmd else fitted.closed_loop_model_
    result.report["lifting"] = lifting_to_dict(plant.lifting)
    result.report["spectral_radius"] = {"closed_loop": closed.spectral_radius(), "plant": plant.spectral_radius()}
    return _KoopmanFit(plant, closed, ensemble)


def _select_alpha(estimator, train, controller, fit, score, result, progress, elsewhere):
    """Alpha among ``fit.alphas``, the best cross-validated ``score``; the sweep kept in ``result``."""
    controllers = [log.controller for log in train]
    # Folds hold out a recorded controller's episodes together, one loop per fold (with_command_delay).
    recorded = recorded_controllers(train)
    folds = cross_validation_folds(
        recorded or controllers, fit.cv_splits, fit.cv_seed, None if recorded is None else controllers
    )
    report = (lambda done, total: progress("cross-validation", done, total)) if progress else None
    sweep = regularization_sweep(
        estimator,
        LogTrajectories(train),
        fit.alphas,
        folds.splits,
        scorings=(score,),
        controller=controller,
        controllers=controllers,
        options=SweepOptions(measured=MEASURED, progress=report, episode_statistics=elsewhere),
    )
    alpha = sweep.best_alpha(score)
    warn_at_grid_edge(sweep.alphas, alpha, sweep.cv_r2_mean(score))
    result.sweep = sweep
    best = int(np.flatnonzero(sweep.alphas == alpha)[0])
    result.report["sweep"] = {
        "alpha": [float(a) for a in sweep.alphas],
        "cv_r2_mean": sweep.cv_r2_mean(score).tolist(),
        "spectral_radius_closed_loop": (
            None if sweep.spectral_radius_closed_loop is None else sweep.spectral_radius_closed_loop.tolist()
        ),
        "spectral_radius_plant": sweep.spectral_radius_plant.tolist(),
        "cv_kind": folds.kind,
        "cv_description": FOLD_KINDS[folds.kind],
        "cv_splits": len(folds.splits),
        "cv_seed": None if folds.kind == "leave-one-controller-out" else fit.cv_seed,
        "score": score,
        "folds": folds.report([log.path.name for log in train], sweep.cv_r2[score][:, best]),
    }
    return alpha


def _write_koopman_model(options, fitted, controller, train, result, disturbance, held_out):
    """The model file; with bootstrap intervals, the bootstrap plants and the held-out episodes' figures in it
    (``held_out``: the predictions the calibration made already)."""
    intervals, ensemble = options.intervals, fitted.ensemble
    no_plants = ensemble is None or intervals is None or options.filtered  # no bootstrap plants
    save_model(
        options.output.model_path,
        method=options.fit.method,
        alpha=result.report["alpha"],
        plant=fitted.plant,
        closed_loop=fitted.closed,
        controller=controller,
        measured=MEASURED,
        training={"logs": result.report["train_logs"]},
        uncertainty=None if no_plants else _design_uncertainty(ensemble, fitted.plant, train, intervals.seed, held_out),
        disturbance=disturbance,
    )


def _predicted_loops(plant, train, test, controller, scoring: ScoreOptions, start: int, result) -> _TestLoops:
    """How each test episode's loop is predicted; with ``command_delay="estimate"``, each test log's delay
    estimated (and reported) first."""
    if scoring.command_delay == "estimate":
        estimated = _estimated_delays(plant, train, test, max(start, SKIP_SAMPLES), result)
        return _TestLoops(controller, scoring.score, scoring.what_if, per_log=estimated)
    return _TestLoops(controller, scoring.score, scoring.what_if, float(scoring.command_delay))


def _design_uncertainty(ensemble, plant, train, seed: int, points: dict | None = None) -> dict:
    """The model file's ``uncertainty``: the bootstrap plants, the held-out episodes' figures and their error's
    spectra (for qube-design); ``points``: held-out episodes the intervals' calibration predicted already."""
    controllers = [log.controller for log in train]
    loops = held_out_loops(ensemble, LogTrajectories(train), controllers, MEASURED, points)
    held_out = loops_figures(loops, SKIP_SAMPLES)
    order = [j for fold in ensemble.folds for j in fold.validation]
    dt = loops[0][0].dt if loops[0][0].dt is not None else plant.dt
    try:
        spectra = error_spectra(
            [t.x for t, _, _ in loops],
            [x for _, x, _ in loops],
            [u for _, _, u in loops],
            [references(t)[:, 0] for t, _, _ in loops],
            [controllers[j] for j in order],
            float(dt if dt is not None else QUBE_SAMPLE_PERIOD),
            SKIP_SAMPLES,
        ).as_dict()
    except ValueError:  # an episode too short, or a held-out prediction that diverged: qube-design takes the ratio
        spectra = None
    names = [train[j].path.name for j in order]
    return uncertainty_to_dict(
        plant,
        [member[1] for member in ensemble.members],
        held_out,
        seed=seed,
        skip=SKIP_SAMPLES,
        logs=names,
        spectra=spectra,
    )


def _counted_statistics(elsewhere, progress, label: str):
    """``elsewhere`` (None: :func:`~qube_koopman.identify.estimators.base.episode_statistics` here) with
    ``progress(label, done, total)`` as each episode's statistics come back; ``elsewhere`` itself without
    ``progress``."""
    if progress is None:
        return elsewhere

    def compute(estimator, setup, ids):
        ids = list(ids)
        parts = statistics_here(estimator, setup, ids) if elsewhere is None else elsewhere(estimator, setup, ids)
        progress(label, 0, len(ids))
        for done, part in enumerate(parts, 1):
            progress(label, done, len(ids))  # before the yield: a consumer that zips stops after the last
            yield part

    return compute


def _fit(estimator, trajs, controllers, elsewhere):
    """Fit ``estimator``: its statistics computed here one at a time, or ``elsewhere`` (a cluster) and
    folded as they come back. ``controllers``: each episode's (None for EDMD, fitted from the logged input)."""
    setup = estimator.setup_fit(trajs) if controllers is None else estimator.setup_fit(trajs, controllers)
    return estimator.fit_setup(setup, elsewhere)


@dataclass(frozen=True)
class _TestLoops:
    """How each test episode's loop is predicted: under its own log's controller or ``what_if``, with the
    command held ``command_delay`` samples late, by the fit's closed loop (``controller``'s) or its plant."""

    controller: DiscreteStateSpace
    score: str
    what_if: DiscreteStateSpace | None = None
    command_delay: float = 0.0
    per_log: dict = field(default_factory=dict)  # a log's path -> its own command delay (estimated)

    def delay(self, log) -> float:
        """The command delay (samples) of one test episode's loop."""
        return self.per_log.get(log.path, self.command_delay)

    def loop(self, log) -> Loop:
        """The loop predicting one test episode: the plant (plant scoring), the what-if controller's, or its own
        log's (a plant model must predict the loop under any known controller); with a command delay, that
        controller followed by the delay."""
        if self.delay(log):
            running = log.controller if self.what_if is None else self.what_if
            return Loop("wrapped", with_output_delay(running, self.delay(log)))
        if self.what_if is not None and self.score == "cl":
            return Loop("wrapped", self.what_if)
        return Loop.of(log.controller, self.controller, self.score)

    def trajectory(self, log):
        """The trajectory one test episode is predicted from (under a what-if controller it never ran, that
        controller's state run on the logged tracking errors; with a command delay, the delay's states and the
        feedforward held as late: :func:`command_delayed`)."""
        t, running = log.trajectory, log.controller
        if self.what_if is not None and not same_system(log.controller, self.what_if):
            t, running = replace(t, xc=controller_states(self.what_if, t.r, t.x[:, MEASURED], t.f)), self.what_if
        if self.delay(log):
            _, xc, f = command_delayed(running, self.delay(log), t.xc, t.r, t.x[:, MEASURED], t.f)
            t = replace(t, xc=xc, f=f)
        return t

    def runs_own(self, log) -> bool:
        """Whether the episode's loop runs its own log's controller (no what-if, or the what-if is the log's)."""
        return self.what_if is None or same_system(log.controller, self.what_if)

    def scored(self, log) -> bool:
        """Whether the episode is scored: only those recorded under a what-if controller are."""
        return self.runs_own(log)


def _estimated_delays(plant, train, test, skip: int, result) -> dict:
    """Each test log's extra command delay (samples) over the training logs', estimated from the other test logs
    of its session (:mod:`~qube_koopman.identify.models.latency`), rounded to a quarter sample: the estimate's own
    precision, so that a session's logs share one loop (one batched prediction, one interval calibration)."""
    from qube_koopman.identify.data.sessions import session_neighbours
    from qube_koopman.identify.models import latency

    dt = test[0].dt
    neighbours = session_neighbours([log.path for log in test], latency.NEIGHBOURS)
    picked = np.unique(np.linspace(0, len(train) - 1, min(len(train), latency.REFERENCE_LOGS)).round().astype(int))
    ordered = sorted(range(len(train)), key=lambda i: train[i].path.name)
    if any(neighbours):
        reference, estimates = latency.estimate_command_delays(
            plant,
            LogTrajectories([train[ordered[i]] for i in picked]),
            LogTrajectories(test),
            neighbours,
            skip,
        )
    else:  # no test log has another of its session: nothing to estimate from
        reference, estimates = None, [latency.DelayEstimate(0.0, None, []) for _ in test]
    delays = {log.path: round(4 * e.samples) / 4 for log, e in zip(test, estimates)}
    result.report["command_delay"] = {
        "estimated": True,
        "reference_samples": reference,
        "logs": [
            {
                "log": log.path.name,
                "samples": delays[log.path],
                "seconds": delays[log.path] * dt,
                "raw_samples": e.raw,
                "neighbours": [test[j].path.name for j in e.neighbours],
            }
            for log, e in zip(test, estimates)
        ],
        "note": latency.NOTE,
    }
    return delays


def _first_scored(offsets: OffsetProtocol | None, score_from: int | None, dt: float) -> int:
    """The first scored sample of each test episode: after the offsets' window, ``score_from``, or the second."""
    return offsets.window(dt) if offsets is not None else 1 if score_from is None else score_from


class _TestScores:
    """Test episodes scored as they stream by: per-episode scores kept, predictions only when asked."""

    def __init__(
        self, result: IdentificationResult, start: int, keep_predictions: bool, progress=None, total: int = 0
    ) -> None:
        self.result, self.start, self.keep = result, start, keep_predictions
        self.progress, self.total = progress, total
        if progress is not None:
            progress("test episodes", 0, total)
        self.names: list[str] = []
        self.scored: list[str] = []  # the scored episodes' names
        self.scores: list[EpisodeScore] = []
        self.plain_scores: list[EpisodeScore] = []
        result.test_names, result.test_truth, result.test_predictions, result.test_time = [], [], [], []

    def add(
        self, log, truth: np.ndarray, prediction: np.ndarray, plain: np.ndarray | None = None, scored: bool = True
    ) -> None:
        """One test episode's prediction (and without offsets, ``plain``); ``scored``: counted in the means."""
        self.result.test_names.append(log.path.name)
        if scored:
            self.scored.append(log.path.name)
            self.scores.append(episode_score(truth, prediction, self.start))
            if plain is not None:
                self.plain_scores.append(episode_score(truth, plain, self.start))
        if self.keep:
            self.result.test_truth.append(truth)
            self.result.test_predictions.append(prediction)
            self.result.test_time.append(np.arange(len(truth)) * log.dt)
        if self.progress is not None:
            self.progress("test episodes", len(self.result.test_names), self.total)

    def report(self, protocol: str, dt: float) -> None:
        """The scores' part of the report, with a warning per diverged prediction."""
        report = self.result.report
        report["protocol"] = protocol
        report["scored_from_sample"] = self.start
        report["scored_logs"] = self.scored
        if not self.scored:
            report["test"] = None
            return
        report["test"] = summarize_scores(self.scores, self.scored)
        _warn_diverged(report["test"], dt, "")
        if self.plain_scores:
            report["test_without_offsets"] = summarize_scores(self.plain_scores, self.scored)
            _warn_diverged(report["test_without_offsets"], dt, " without offsets")


def _score_koopman(fitted: _KoopmanFit, how: _TestLoops, test, scoring: ScoreOptions, scores, bands=None, ahead=None):
    """Test logs read, predicted and scored a batch at a time (only their scores kept, and their predictions
    if asked); with ``bands``, every member of the ensemble predicts each batch in the same simulation."""
    start, estimates = scores.start, []
    counted = [how.scored(log) for log in test]
    loops = [how.loop(log) for log in test]
    for run in consecutive_runs(loops):
        loop = loops[run[0]]
        models = [loop.model(fitted.closed, fitted.plant, MEASURED)]
        if bands is not None:
            models += [loop.model(closed_m, plant_m, MEASURED) for closed_m, plant_m in bands.members]
        trajectories = [how.trajectory(test[i]) for i in run]
        predicted = predict_episodes(models, trajectories, scoring.offsets)
        for i, traj, episode in zip(run, trajectories, predicted):
            estimates.append(episode.estimate)
            scores.add(test[i], traj.x, episode.prediction, episode.plain, counted[i])
            if bands is not None:
                bands.add(test[i], traj, episode, counted[i], start, models[0].n_delays, loop, how.runs_own(test[i]))
        if ahead is not None:
            scored = [j for j, i in enumerate(run) if counted[i]]
            ahead.add_many(
                [test[run[j]].path.name for j in scored],
                models[0],
                [trajectories[j] for j in scored],
                [_offset_mapping(predicted[j].estimate) for j in scored],
            )
    _report_loops(how, test, counted, scores)
    if bands is not None:
        bands.report()
    _report_scores(scoring, test, estimates, scores)


def _report_loops(how: _TestLoops, test, counted: list[bool], scores) -> None:
    """The report's ``command_delay`` (a given one) and ``what_if``: how the test loops differ from the logs'."""
    report, dt = scores.result.report, test[0].dt
    if how.command_delay:
        report["command_delay"] = {
            "samples": float(how.command_delay),
            "seconds": float(how.command_delay) * dt,
            "note": "every test episode's loop predicted with its command reaching the plant this much later "
            "than in the training logs (the feedforward held as late)",
        }
    if how.what_if is not None:
        report["what_if"] = {
            "controller": how.what_if.as_dict(),
            "n_scored": len(scores.scored),
            "unscored_logs": [log.path.name for log, scored in zip(test, counted) if not scored],
            "note": "test episodes are predicted under this controller; only those recorded under it are scored",
        }


def _report_scores(scoring: ScoreOptions, test, estimates: list, scores) -> None:
    """The test scores' part of the report, with each episode's offsets when they were estimated."""
    dt, offsets, score_from = test[0].dt, scoring.offsets, scoring.score_from
    if offsets is None:
        scores.report(PAPER_PROTOCOL if score_from is None else window_protocol(score_from, dt), dt)
        return
    names = list(offsets.channels)
    scores.result.report["offsets"] = [
        {"log": log.path.name, **est.as_dict(names)}
        for log, est in zip(test, estimates)
        if est is not None  # every episode's, with offsets estimated
    ]
    scores.result.report["offset_bound"] = offsets.bound
    scores.report(offsets.describe(dt), dt)


def _training_disturbance(model, train, controller, score, options: AheadOptions):
    """The disturbance model fitted on the training episodes the model's own loop ran (all, scoring the plant)."""
    own = [log for log in train if score == "plant" or Loop.of(log.controller, controller).kind == "closed"]
    # Only the episodes the estimate uses are read (stored logs stay on disk).
    return fit_training_disturbance(
        model, [log.trajectory for log in spread(own or list(train), MAX_EPISODES)], options
    )


def _offset_mapping(estimate) -> dict[int, float] | None:
    """An episode's estimated offsets by channel (None without offsets; empty when implausible, so unused)."""
    return None if estimate is None else estimate.as_mapping()


def _save_ahead(folder: Path, test, ahead: AheadScores) -> None:
    """Each scored test episode's K-step predictions into its ``<log>.npz`` (written beside its band, or alone)."""
    for log in test:
        kept = ahead.predictions.get(log.path.name)
        if kept is None:
            continue
        path = folder / f"{log.path.stem}.npz"
        arrays: dict = {}
        first = 0
        if path.exists():  # the band's file: its samples start at the first scored one, the same rows kept here
            with np.load(path) as old:
                arrays = {key: old[key] for key in old.files}
            first = int(round(float(arrays["t"][0]) / log.dt)) if len(arrays.get("t", ())) else 0
        else:
            x = np.asarray(log.trajectory.x, dtype=float)
            arrays = {"t": np.arange(len(x)) * log.dt, "measured": x}
        arrays.update({key: value[first:] for key, value in kept.items()})
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez(f, **arrays)


#: How the intervals are made, in words (report.json's ``intervals.method``).
INTERVAL_METHOD = (
    "prediction +- k_c sqrt(s_c(t)^2 + q_c (1 - exp(-h / tau_c))): s_c the spread of bootstrap refits "
    "on the training episodes drawn with replacement, plus the estimated offsets' standard errors "
    "propagated through the prediction; q_c, tau_c (Gaussian maximum likelihood) and k_c (the level's "
    "quantile) calibrated per channel on training episodes held out in turn, never the test episodes; "
    "for a loop the training never ran (another controller), calibrated the same way on the twin's "
    "probe episodes: per channel and horizon the wider of the bands calibrated under the loop's own "
    "controller (its PD gains known) and under the default probe controllers (other_loops 'twin')"
)


class _TestBands:
    """Each test episode's interval, written and summarized as the episodes stream by."""

    #: How a loop the training never ran is calibrated (each band's ``calibration``).
    other_calibration = "twin probes"
    #: The K-step predictions' band (the filter's), or None.
    ahead_band: AheadBand | None = None

    def __init__(
        self, members, calibration, loops, options, result, output: OutputOptions, seconds, other=None
    ) -> None:
        folder, keep = output.predictions_folder, output.keep_predictions
        self.members, self.calibration, self.options, self.keep = members, calibration, options, keep
        # The calibrations of loops the training never ran, (loop, calibration, report entry) each:
        # made when the first episode under the loop comes.
        self._other = other
        self.elsewhere: list[tuple[Loop, IntervalCalibration, dict]] = []
        self.loops = [loop for i, loop in enumerate(loops) if not any(loop.same(seen) for seen in loops[:i])]
        self.result, self.folder, self.seconds = result, None if folder is None else Path(folder), seconds
        self.summary = BandSummary(STATE_NAMES)
        self.files: list[str] = []

    def add(self, log, trajectory, predicted, scored, start, n_delays, loop, own: bool = True) -> None:
        """One test episode's band: saved, counted, kept with the predictions if they are. ``own``: the loop
        runs the log's own controller (perhaps with a command delay), not a what-if's."""
        seen = any(loop.same(known) for known in self.loops)
        calibration = self.calibration if seen or self._other is None else self._calibration_elsewhere(loop, log, own)
        band = prediction_band(log.path.name, trajectory, predicted, calibration, start, n_delays, scored)
        band.calibrated_loop = seen
        band.calibration = "held-out" if calibration is self.calibration else self.other_calibration
        if self.folder is not None:
            name = f"{log.path.stem}.npz"
            band.save(self.folder / name)
            self.files.append(name)
        self.summary.add(band)
        if self.keep:
            self.result.test_bands.append(band)

    def _calibration_elsewhere(self, loop, log, own: bool):
        for known, calibration, _ in self.elsewhere:
            if known.same(loop):
                return calibration
        started = time.perf_counter()
        # The log's own PD gains, also when its loop is predicted with a command delay (the delayed
        # controller is not the log's, but the probes of its gains measure the model's error under it);
        # a what-if's, the plant's or a state-space controller's loop: none.
        gains = _pd_gains(log.gains) if own and loop.kind == "wrapped" else None
        calibration, entry = self._other(gains, loop)
        entry["log"] = log.path.name
        self.elsewhere.append((loop, calibration, entry))
        self.seconds["other_loops"] = self.seconds.get("other_loops", 0.0) + time.perf_counter() - started
        return calibration

    def report(self) -> None:
        """The intervals' part of report.json."""
        o, cal = self.options, self.calibration
        self.result.report["intervals"] = {
            "level": o.level,
            "interval_method": "bootstrap",
            "why": "IntervalOptions' method 'bootstrap'",
            "method": INTERVAL_METHOD,
            "n_members": o.n_members,
            "n_folds": o.n_folds,
            "seed": o.seed,
            "calibration": {
                "n_samples": cal.n_samples_,
                "stride": o.stride,
                "n_diverged": cal.n_diverged_,
                "channels": cal.as_dict(STATE_NAMES),
            },
            "other_loops": o.other_loops,
            "calibration_other_loops": [entry for _, _, entry in self.elsewhere],
            **self.summary.report(),
            "files": self.files,
            "seconds": self.seconds,
        }


def _pd_gains(gains: dict) -> tuple | None:
    """(kp_theta, kd_theta, kp_alpha, kd_alpha, tau) of a log's PD gains, or None (another kind of controller)."""
    keys = ("kp_theta", "kd_theta", "kp_alpha", "kd_alpha", "tau")
    return tuple(float(gains[k]) for k in keys) if gains and all(k in gains for k in keys) else None


#: Probe episodes per controller calibrating the intervals of loops the training never ran: three on
#: each of the six session twins. A batch of 18 simulates in the time of 6 (the loop's steps cost, not
#: the episodes), and with 6 the soft controller's band moved by a third between two draws of them.
INTERVAL_PROBES = 18


def _test_bands(ensemble, options: IdentifyOptions, train, controller, start, result, probes, points) -> _TestBands:
    """The intervals' calibration on the training episodes the folds held out, ready for the test episodes;
    with ``options.intervals.other_loops == "twin"``, that of loops the training never ran on the twin's probes,
    made when a test episode needs it. ``points`` is filled with the held-out closed-loop predictions
    (:func:`~qube_koopman.identify.uncertainty.calibrate`)."""
    started = time.perf_counter()
    intervals, score = options.intervals, options.scoring.score
    assert intervals is not None  # bands are made only with intervals
    loops = [Loop.of(log.controller, controller, score) for log in train]
    scoring = CalibrationOptions(intervals.level, start, options.scoring.offsets, MEASURED, intervals.stride)
    calibration = calibrate(ensemble, LogTrajectories(train), loops, scoring, points)
    seconds = {"calibration": time.perf_counter() - started}
    default: list[tuple[ProbeSet, IntervalCalibration]] = []  # the default probes' calibration, made once
    by_gains: dict[tuple, tuple] = {}  # gains -> (their calibration or None, the report's fields on them)

    def on_probes(*probe_sets):
        return calibrate_on_probe_sets(ensemble, probe_sets, scoring, intervals.n_probe_members)

    def on_session_twins(*gain_sets):
        return _interval_probe_sets(train, gain_sets, options.probe_cache)

    def elsewhere(gains, loop=None):
        """The calibration of a loop the training never ran (``gains``: its PD gains, when known)."""
        from qube_koopman.identify.model_selection.transfer import DEFAULT_PROBE_GAINS

        own = None
        if not default:
            # The probe set given, the same one read back from the cache, or simulated and kept; the first
            # loop's own probes with it, in the same batch (the twin's step costs little more for both).
            wanted = ([] if probes is not None else [DEFAULT_PROBE_GAINS]) + ([] if gains is None else [[gains]])
            sets = on_session_twins(*wanted) if wanted else []
            probe_set = probes if probes is not None else sets.pop(0)
            if not probe_set.controllers:
                raise ValueError("no probe episode stayed balanced on the twin")
            own = sets[0] if sets else None
            # Both calibrated in one simulation of their episodes.
            made = on_probes(probe_set, *([own] if own is not None and own.controllers else []))
            default.append((probe_set, made[0]))
            if len(made) > 1:
                by_gains[gains] = _own_fields(own, made[1])
        probe_set, calibration = default[0]
        entry = {
            "default_probes": probe_set.describe(),
            "n_default_episodes": probe_set.n_episodes,
            "default_channels": calibration.as_dict(STATE_NAMES),
            "gains": gains,
        }
        if gains is not None:
            if gains not in by_gains:  # made once per gains: loops that differ by a command delay share them
                by_gains[gains] = _own_calibration(gains, own, on_session_twins, on_probes)
            own_calibration, fields = by_gains[gains]
            entry.update(fields)
            if own_calibration is not None:
                calibration = widest([own_calibration, calibration])
        entry["channels"] = calibration.as_dict(STATE_NAMES)
        return calibration, entry

    other = elsewhere if intervals.other_loops == "twin" and score == "cl" else None
    return _TestBands(ensemble.members, calibration, loops, intervals, result, options.output, seconds, other)


def _interval_probe_sets(train, gain_sets, cache) -> list:
    """The twin's probe sets of ``gain_sets`` calibrating the intervals of loops the training never ran,
    simulated from the training episodes on each session's twin (or read from ``cache``)."""
    from qube_koopman.identify.model_selection.transfer import session_twins, twin_probe_sets

    return twin_probe_sets(
        LogTrajectories(train), gain_sets, per_controller=INTERVAL_PROBES, params=session_twins(), cache=cache
    )


def _own_calibration(gains, own, on_session_twins, on_probes) -> tuple:
    """The calibration on the probes of a loop's own PD gains (``own``: those probes, when simulated
    already) and the report's fields on them; None and why, when there are none."""
    try:
        own = own if own is not None else on_session_twins([gains])[0]
    except ValueError as exc:  # e.g. excitations the twin cannot replay: the default probes alone, said so
        return None, {"own_probes": f"none: {exc}"}
    if not own.controllers:
        return None, {"own_probes": "none: no probe episode stayed balanced on the twin"}
    return _own_fields(own, on_probes(own)[0])


def _own_fields(own, calibration) -> tuple:
    """A loop's own probes' calibration and the report's fields on them."""
    fields = {
        "own_probes": own.describe(),
        "n_own_episodes": own.n_episodes,
        "own_channels": calibration.as_dict(STATE_NAMES),
    }
    return calibration, fields


#: How the filter's intervals are made, in words (report.json's ``intervals.method`` with ``method`` disturbance).
FILTER_INTERVAL_METHOD = (
    "prediction +- k_c sqrt(V_c(h) + q_c (1 - exp(-h / tau_c))): V_c(h) the prediction error variance of the "
    "disturbance model's Kalman filter h samples from the prediction's start (the innovations' covariance "
    "propagated through the loop's response, re-lifted, to an innovation and to the disturbance estimate it "
    "moves), in place of the bootstrap refits' spread; q_c, tau_c and k_c calibrated per channel on training "
    "episodes held out in turn (one refit per fold, no bootstrap refits); a loop the training never ran keeps "
    "the calibration with its own loop's V_c(h); K-step predictions get k_{c,K} sqrt(V_c(K)), k_{c,K} the "
    "level's quantile on the held-out episodes' K-step predictions"
)


class _FilterBands(_TestBands):
    """:class:`_TestBands` of the disturbance filter's band (:mod:`~qube_koopman.identify.uncertainty.filter_band`)."""

    other_calibration = "twin probes, the loop's own filter variance"
    filter_report: dict
    n_folds: int

    def report(self) -> None:
        super().report()
        entry = self.result.report["intervals"]
        entry.update(
            {
                "interval_method": "disturbance",
                "n_folds": self.n_folds,
                "why": "IntervalOptions' method 'disturbance'",
                "method": FILTER_INTERVAL_METHOD,
                "n_members": 0,
                "other_loops": self.options.other_loops,
                "filter": self.filter_report,
            }
        )


def _filter_bands(fitted: _KoopmanFit, options: IdentifyOptions, train, controller, start, result, probes, disturbance):
    """The disturbance filter's bands (``options.intervals.method == "disturbance"``): calibrated on the folds'
    held-out training episodes; a loop the training never ran gets its own filter variance, calibrated as the
    bootstrap band's is (``other_loops "twin"``: on the twin's probe episodes, the point fit predicting them, each
    probe loop's own variance; per channel and horizon the wider of the default probes' and the loop's own gains')
    or with the training loop's calibration (``"none"``)."""
    started = time.perf_counter()
    intervals, score, ahead = options.intervals, options.scoring.score, options.ahead
    assert intervals is not None  # bands are made only with intervals
    closed, plant = fitted.closed, fitted.plant
    model = fitted.model(score)
    # Without --horizon (no disturbance model fitted) or none supported: the filter of the measured history alone.
    if disturbance is None:
        disturbance = residual_model(model, [log.trajectory for log in spread(list(train), MAX_EPISODES)])
    loops = [Loop.of(log.controller, controller, score) for log in train]
    scoring = CalibrationOptions(intervals.level, start, options.scoring.offsets, MEASURED, intervals.stride)
    dt = model.dt if model.dt is not None else train[0].dt
    horizons = [] if ahead is None else [max(1, K) for K in ahead.samples(dt)]
    folds = fitted.ensemble.folds
    calibration = calibrate_filter(folds, LogTrajectories(train), loops, scoring, disturbance, model, horizons)
    seconds = {"calibration": time.perf_counter() - started}
    band = AheadBand(calibration, disturbance, model)

    default: list = []  # the default probes' calibration, made once (before its loop's variance)

    def on_probes(probe_sets):
        return calibrate_filter_on_probe_sets((closed, plant), probe_sets, scoring, disturbance, model, band.variance)

    def elsewhere(gains, loop):
        own_variance = band.variance(loop.model(closed, plant, MEASURED))
        if intervals.other_loops != "twin" or score != "cl":
            own = calibration.for_loop(own_variance)
            return own, {"gains": gains, "channels": own.as_dict(STATE_NAMES), "calibration": "held-out"}
        from qube_koopman.identify.model_selection.transfer import DEFAULT_PROBE_GAINS

        wanted = ([] if probes is not None or default else [DEFAULT_PROBE_GAINS]) + ([] if gains is None else [[gains]])
        sets = _interval_probe_sets(train, wanted, options.probe_cache) if wanted else []
        todo = []
        if not default:
            probe_set = probes if probes is not None else sets.pop(0)
            if not probe_set.controllers:
                raise ValueError("no probe episode stayed balanced on the twin")
            todo.append(probe_set)
        made = on_probes(todo + [own for own in sets if own.controllers])  # in one simulation
        if not default:
            default.append((todo[0], made.pop(0)))
        parts = [default[0][1]] + made
        combined = widest([part.for_loop(own_variance) for part in parts])
        combined.uses_spread = False  # its parts are the filter's
        entry = {
            "default_probes": default[0][0].describe(),
            "gains": gains,
            "own_probes": "yes" if len(parts) > 1 else "none",
            "channels": combined.as_dict(STATE_NAMES),
        }
        return combined, entry

    bands = _FilterBands([], calibration, loops, intervals, result, options.output, seconds, elsewhere)
    bands.ahead_band, bands.n_folds = band, len(folds)
    bands.filter_report = {
        "innovations_covariance": np.asarray(disturbance.R, dtype=float).tolist(),
        "disturbance_entry": disturbance.entry if disturbance.q > 0 else "none",
        "why": "IntervalOptions' method 'disturbance'",
    }
    return bands


def _warn_diverged(summary: dict, dt: float, what: str) -> None:
    """One warning per diverged test prediction, naming the log and the sample."""
    others = summary["n_episodes"] - summary["n_diverged"]
    for d in summary["diverged"]:
        at = "" if d["sample"] is None else f" at sample {d['sample']} ({d['sample'] * dt:.2f} s)"
        mean = summary["r2_mean_converged"]
        rest = (
            f"the mean over the other {others} episode(s) is {mean:.4f}" if mean is not None else "no episode converged"
        )
        warnings.warn(
            f"{d['name']}: the prediction{what} diverged{at}; its R^2 is -inf and so is the test mean; {rest}",
            DivergedPrediction,
            stacklevel=3,
        )


def _arx(method, trajs, test, controller, lags, score, result):
    result.report["alpha"] = None
    if method == "arx":  # plant scoring only (identify_and_score refuses score="cl")
        plant = Arx(lags, lags, inputs=("u",)).fit(trajs)
        result.report["spectral_radius"] = {"closed_loop": None, "plant": _spectral_radius(plant.model_.A)}
        return plant, None, plant.predict
    model = ClArx(controller, lags, lags).fit(trajs)
    result.report["spectral_radius"] = {
        "closed_loop": _spectral_radius(model.closed_loop_.model_.A),
        "plant": _spectral_radius(model.plant_.A),
    }
    if score == "cl":
        for log in test:
            if not same_system(log.controller, controller):
                raise ValueError(
                    f"{log.path}: its controller differs from the training one; a closed-loop "
                    "ARX cannot predict another loop (use a Koopman method)"
                )
        return model, model.closed_loop_, model.predict_closed_loop
    return model, model.closed_loop_, model.predict


def _score_arx(predict, test, result, score_from, keep_predictions, progress=None) -> None:
    """Each test log read, predicted by ``predict`` and scored in turn."""
    dt = test[0].dt
    scores = _TestScores(result, 1 if score_from is None else score_from, keep_predictions, progress, len(test))
    for log in test:
        traj = log.trajectory
        scores.add(log, traj.x, predict(traj))
    scores.report(PAPER_PROTOCOL if score_from is None else window_protocol(score_from, dt), dt)


@dataclass(frozen=True)
class SearchOptions:
    """How the complete lifting search runs (``qube-identify --search``'s options).

    Parameters
    ----------
    space : SearchSpace, optional
        The values to try (:class:`~qube_koopman.identify.model_selection.lifting_space.SearchSpace`'s
        defaults when None).
    estimate_window : float
        Offset estimation window (s); every candidate is scored from its end on.
    offset_bound : float
        Plausibility bound of the offset estimates (rad).
    cv_splits, cv_seed : int
        Episode-grouped folds with one training controller (several: one fold per controller).
    transfer : {"twin", "none"}
        ``"twin"`` ranks candidates by the lower of their cross-validated and twin-probe
        transfer R^2; ``"none"`` by the cross-validated R^2 alone.
    probe_cache : Path, optional
        Folder of cached twin probe sets (None: simulate them every time).
    rbf_seed : int
        Seed of the RBF centres.
    n_jobs : int
        Worker processes (-1: every core); unused with ``scheduler``.
    scheduler : str, optional
        Address of a dask scheduler to run the candidates on.
    security : distributed.security.Security, optional
        The TLS settings of that scheduler.
    worker_timeout : float
        Seconds that scheduler's cluster may have no worker, results awaited, before the
        search gives up.
    """

    space: SearchSpace | None = None
    estimate_window: float = 1.0
    offset_bound: float = DEFAULT_BOUND
    cv_splits: int = 3
    cv_seed: int = 1234
    transfer: str = "twin"
    probe_cache: Path | None = None
    rbf_seed: int = 0
    n_jobs: int = -1
    scheduler: str | None = None
    security: object = None
    worker_timeout: float = DEFAULT_WORKER_TIMEOUT


def run_search(
    train: Sequence[LoggedTrajectory],
    controller: DiscreteStateSpace,
    options: SearchOptions = SearchOptions(),
    progress: Callable | None = None,
):
    """The complete lifting search: folds, the twin's transfer probes, the candidates, the winner.

    What ``qube-identify --search`` runs before it fits the winner on all training logs.

    Parameters
    ----------
    train : sequence of LoggedTrajectory
        The training logs (:func:`~qube_koopman.identify.load_logs`).
    controller : DiscreteStateSpace
        The closed loop's controller (with several training controllers, the majority's).
    options : SearchOptions
    progress : callable, optional
        Wraps an iterable to show progress (``tqdm``-like).

    Returns
    -------
    SearchResult
        The candidates, the winner, the folds (``folds``), the probes' time
        (``probe_seconds``) and, with several controllers, the winner's
        same-controller scores (``same_controller``).

    Raises
    ------
    ValueError
        When the estimation window and the largest delay leave nothing to score.
    """
    from qube_koopman.identify.model_selection.evaluation import SameControllerFolds, same_controller_scores
    from qube_koopman.identify.model_selection.lifting_space import SearchSpace
    from qube_koopman.identify.model_selection.search import search_liftings
    from qube_koopman.identify.model_selection.transfer import twin_probes

    space = options.space or SearchSpace()
    trajs = LogTrajectories(train)  # read when needed (stored logs), not all held at once
    window = int(round(options.estimate_window / train[0].dt))
    if min(log.n_samples for log in train) <= window + max(space.delays) + 2:
        raise ValueError(
            f"an estimation window of {options.estimate_window:g} s and {max(space.delays)} delays "
            "leave nothing to score in the shortest training episode"
        )
    folds, recorded, controllers, loops = _search_folds(train, options)
    started = time.perf_counter()
    probes = twin_probes(trajs, cache=options.probe_cache) if options.transfer == "twin" else None
    probe_seconds = time.perf_counter() - started if probes is not None else 0.0
    several = folds.kind == "per-controller"
    space = space.for_training(several)
    result = search_liftings(
        trajs,
        controller,
        splits=folds.splits,
        window=window,
        space=space,
        probes=probes,
        controllers=controllers if several or loops is not None else None,
        settings=_search_settings(options, progress),
    )
    result.folds = folds
    result.offsets_first = bool(space.offsets_first)
    result.probe_seconds = probe_seconds
    if several:
        result.same_controller = same_controller_scores(
            result.winner,
            trajs,
            controller,
            recorded or controllers,
            window=window,
            folds=SameControllerFolds(options.cv_splits, options.cv_seed, loops),
            bound=options.offset_bound,
            rbf_seed=options.rbf_seed,
        )
    return result


def _search_settings(options: SearchOptions, progress: Callable | None):
    """The search's settings besides its space: the offsets' bound, the RBF seed, its workers, the progress."""
    from qube_koopman.identify.model_selection.search import SearchSettings

    return SearchSettings(
        bound=options.offset_bound,
        rbf_seed=options.rbf_seed,
        n_jobs=options.n_jobs,
        scheduler=options.scheduler,
        security=options.security,
        worker_timeout=options.worker_timeout,
        progress=progress,
    )


def _search_folds(train, options: SearchOptions) -> tuple:
    """The search's folds, the recorded controllers (None: every log's loop is its controller alone), each
    episode's controller, and the loops the folds hold out. A recorded controller's episodes are held out
    together, one loop per fold (its sessions' loops, each with its own command delay, are several:
    with_command_delay); each episode runs its own loop."""
    controllers = [log.controller for log in train]
    recorded = recorded_controllers(train)
    loops = None if recorded is None else controllers
    folds = cross_validation_folds(recorded or controllers, options.cv_splits, options.cv_seed, loops)
    return folds, recorded, controllers, loops
