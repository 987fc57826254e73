"""Identify, select the regularization, score on test episodes: the qube-identify workflow."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from qube_koopman.identify._blas import limited_blas_threads
from qube_koopman.identify.arx import Arx, ClArx
from qube_koopman.identify.cl_edmd import ClEdmd, ClEdmdKnownRows, ClEdmdLstsq
from qube_koopman.identify.data import LoggedTrajectory, same_system
from qube_koopman.identify.mixed import FOLD_KINDS, cross_validation_folds, training_controllers_report
from qube_koopman.identify.edmd import Edmd
from qube_koopman.identify.stability import ClEdmdStable
from qube_koopman.identify.model_file import lifting_to_dict, save_model
from qube_koopman.identify.offsets import DEFAULT_BOUND, estimate_offsets_many, predict_with_offsets
from qube_koopman.identify.scores import DivergedPrediction, summarize_episodes
from qube_koopman.identify.structure import close_loop, controller_states
from qube_koopman.identify.sweep import SweepResult, regularization_sweep
from qube_koopman.sim.lti import DiscreteStateSpace

__all__ = ["IdentificationResult", "OffsetProtocol", "identify_and_score", "KOOPMAN_METHODS"]

KOOPMAN_METHODS = {"edmd": Edmd, "cl-edmd": ClEdmd, "cl-edmd-known-rows": ClEdmdKnownRows,
                   "cl-edmd-lstsq": ClEdmdLstsq, "cl-edmd-stable": ClEdmdStable}
MEASURED = [0, 1]  # theta and alpha are both fed back on the QUBE-Servo
# Methods whose model is one loop's (unstructured closed loop, or a constraint on one loop): one controller only.
SINGLE_LOOP_METHODS = {"cl-arx": "--method cl-arx", "cl-edmd-lstsq": "--method cl-edmd-lstsq",
                       "cl-edmd-stable": "--max-radius (the stability-constrained fit)"}


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
        return (f"offsets of {', '.join(self.channels)} estimated on each test episode from its first "
                f"{self.window_s:g} s ({self.window(dt)} samples) by simulation-error least squares, "
                f"estimates beyond {self.bound:g} flagged and not used; the whole episode is predicted "
                f"from its start and only the samples after the window are scored, with and without "
                f"the offsets")

    def window(self, dt: float) -> int:
        """The window in samples."""
        return int(round(self.window_s / dt))


PAPER_PROTOCOL = ("the paper's: each test episode predicted from its initial condition, "
                  "every sample after the first scored, no offsets")


def window_protocol(start: int, dt: float) -> str:
    """The plain protocol scored from the end of an estimation window, as the search scores candidates."""
    return (f"each test episode predicted from its initial condition, no offsets, scored from sample {start} "
            f"({start * dt:g} s: the end of the estimation window, as the search scored its candidates)")


@dataclass
class IdentificationResult:
    """What a run produced: the report, the models, the test predictions."""

    report: dict
    plant: object = None
    closed_loop: object = None
    sweep: SweepResult | None = None
    test_names: list[str] = field(default_factory=list)
    test_truth: list[np.ndarray] = field(default_factory=list)
    test_predictions: list[np.ndarray] = field(default_factory=list)
    test_time: list[np.ndarray] = field(default_factory=list)


def _spectral_radius(A) -> float | None:
    return None if A is None else float(np.max(np.abs(np.linalg.eigvals(A))))


def identify_and_score(*, method: str, lifting: Sequence, train: Sequence[LoggedTrajectory],
                       test: Sequence[LoggedTrajectory], controller: DiscreteStateSpace, alpha: float = 1e-3,
                       alphas: Sequence[float] | None = None, score: str = "cl", cv_splits: int = 3,
                       cv_seed: int = 1234, arx_lags: int = 10, model_path: str | Path | None = None,
                       offsets: OffsetProtocol | None = None, what_if: DiscreteStateSpace | None = None,
                       estimator_options: dict | None = None, progress: Callable[[str, int, int], None] | None = None,
                       score_from: int | None = None,
                       episode_statistics: Callable | None = None) -> IdentificationResult:
    """Fit ``method`` on the training logs and score it on the test logs.

    Training logs may come from several controllers: each episode is fitted
    with its own log's controller (one plant for all), and ``controller`` is
    the one whose closed loop the model describes (qube-identify: the
    majority's). With ``alphas`` the regularization is chosen by
    cross-validation on the training logs with the same ``score``: folds
    leave one controller out when the logs ran two or more, else
    episode-grouped random splits (``cv_splits``, ``cv_seed``). Test
    episodes are predicted in closed loop under their own log's controller
    (``score="cl"``) or from their plant input (``score="plant"``). With
    ``offsets`` each test episode's offsets are estimated from its initial
    window (see :class:`OffsetProtocol`). With ``what_if`` every test episode
    is predicted under that controller instead; only episodes recorded under
    it are scored. Without offsets, ``score_from`` (samples) scores the test
    episodes from that sample on instead of the paper's sample 1 (as a
    search scores its candidates), for every method. ``episode_statistics`` computes a Koopman
    method's per-episode statistics elsewhere, for the fit and the sweep (on a dask cluster:
    :class:`~qube_koopman.identify.distributed.ClusterStatistics`). A diverged test prediction is reported by
    episode and sample with a :class:`~qube_koopman.identify.scores.DivergedPrediction`
    warning.
    """
    if method not in KOOPMAN_METHODS and (offsets is not None or what_if is not None):
        raise ValueError(f"offsets and what-if controllers need a Koopman method, not {method}")
    if method == "arx" and score == "cl":
        raise ValueError("ARX models the plant only: its predictions come from the plant input, not the "
                         "closed loop; use score='plant', or method 'cl-arx' for closed-loop scores")
    if what_if is not None and score != "cl":
        raise ValueError("a what-if controller predicts the closed loop: use score='cl'")
    trajs = [log.trajectory for log in train]
    result = IdentificationResult(report={"method": method, "score": score,
                                          "train_logs": [log.path.name for log in train],
                                          "test_logs": [log.path.name for log in test],
                                          "controller": controller.as_dict(),
                                          "training_controllers": training_controllers_report(train, controller)})
    n_controllers = result.report["training_controllers"]["n_controllers"]
    if method in SINGLE_LOOP_METHODS and n_controllers > 1:
        raise ValueError(f"{SINGLE_LOOP_METHODS[method]} identifies one closed loop: its training logs must share "
                         f"one controller, these ran {n_controllers} (cl-edmd, cl-edmd-known-rows, edmd and arx fit "
                         "logs of several)")
    with limited_blas_threads(1):
        if method in KOOPMAN_METHODS:
            plant, closed = _koopman(method, lifting, train, controller, alpha, alphas, score,
                                     cv_splits, cv_seed, progress, result, estimator_options or {},
                                     episode_statistics)
            result.report["lifting"] = lifting_to_dict(plant.lifting)
            result.report["spectral_radius"] = {"closed_loop": closed.spectral_radius(),
                                                "plant": plant.spectral_radius()}
            if model_path is not None:
                save_model(model_path, method=method, alpha=result.report["alpha"], plant=plant, closed_loop=closed,
                           controller=controller, measured=MEASURED,
                           training={"logs": result.report["train_logs"]})
            _score_koopman(plant, closed, controller, test, score, offsets, what_if, result, score_from)
        elif method in ("arx", "cl-arx"):
            plant, closed, predictions = _arx(method, trajs, test, controller, arx_lags, score, result)
            if model_path is not None:
                Path(model_path).write_text(_arx_json(method, arx_lags, plant, closed))
            dt = test[0].trajectory.dt
            _summarize(result, test, predictions, None, 1 if score_from is None else score_from,
                       PAPER_PROTOCOL if score_from is None else window_protocol(score_from, dt))
        else:
            raise ValueError(f"unknown method {method!r}")
    result.plant, result.closed_loop = plant, closed
    return result


def _koopman(method, lifting, train, controller, alpha, alphas, score, cv_splits, cv_seed, progress, result,
             options, elsewhere=None):
    cls = KOOPMAN_METHODS[method]
    trajs, controllers = [log.trajectory for log in train], [log.controller for log in train]
    make = (lambda a: cls(lifting=lifting, alpha=a, **options)) if cls is Edmd else \
        (lambda a: cls(controller, lifting=lifting, alpha=a, **options))
    # EDMD fits the plant from its logged input, whatever the controller; the others from each episode's own.
    fit = lambda est: _fit(est, trajs, None if cls is Edmd else controllers, elsewhere)  # noqa: E731
    if alphas is not None:
        folds = cross_validation_folds(controllers, cv_splits, cv_seed)
        report = (lambda done, total: progress("cross-validation", done, total)) if progress else None
        sweep = regularization_sweep(make(0.0), trajs, alphas, folds.splits, scorings=(score,), controller=controller,
                                     measured=MEASURED, progress=report, controllers=controllers,
                                     episode_statistics=elsewhere)
        alpha = sweep.best_alpha(score)
        result.sweep = sweep
        best = int(np.flatnonzero(sweep.alphas == alpha)[0])
        result.report["sweep"] = {
            "alpha": [float(a) for a in sweep.alphas],
            "cv_r2_mean": sweep.cv_r2_mean(score).tolist(),
            "spectral_radius_closed_loop": (None if sweep.spectral_radius_closed_loop is None
                                            else sweep.spectral_radius_closed_loop.tolist()),
            "spectral_radius_plant": sweep.spectral_radius_plant.tolist(),
            "cv_kind": folds.kind, "cv_description": FOLD_KINDS[folds.kind],
            "cv_splits": len(folds.splits), "cv_seed": cv_seed if folds.kind == "episode-grouped" else None,
            "score": score,
            "folds": folds.report([log.path.name for log in train], sweep.cv_r2[score][:, best]),
        }
    result.report["alpha"] = float(alpha)
    fitted = fit(make(alpha))
    if hasattr(fitted, "unconstrained_radius_"):
        result.report["constraint"] = {**options, "unconstrained_radius": fitted.unconstrained_radius_,
                                       "solver_status": fitted.solver_status_}
    plant = fitted.model_ if cls is Edmd else fitted.plant_model_
    closed = close_loop(plant, controller, MEASURED) if cls is Edmd else fitted.closed_loop_model_
    return plant, closed


def _fit(estimator, trajs, controllers, elsewhere):
    """Fit ``estimator``: its statistics computed here one at a time, or ``elsewhere`` (a cluster) and
    folded as they come back. ``controllers``: each episode's (None for EDMD, fitted from the logged input)."""
    setup = estimator._setup(trajs) if controllers is None else estimator._setup(trajs, controllers)
    return estimator._fit(setup, None if elsewhere is None else elsewhere(estimator, setup, range(len(trajs))))


def _test_model(plant, closed, controller, log, score, what_if):
    """The model predicting one test episode, and the trajectory it predicts from."""
    if score == "plant":
        return plant, log.trajectory
    if what_if is not None:
        t = log.trajectory
        if not same_system(log.controller, what_if):
            # No record under this controller: its state is run on the logged tracking errors.
            t = replace(t, xc=controller_states(what_if, t.r, t.x[:, MEASURED]))
        return close_loop(plant, what_if, MEASURED), t
    # A plant model must predict the loop under any known controller: each log's own.
    return (closed if same_system(log.controller, controller) else close_loop(plant, log.controller, MEASURED),
            log.trajectory)


def _score_koopman(plant, closed, controller, test, score, offsets, what_if, result, score_from=None):
    dt = test[0].trajectory.dt
    predictions, plain, estimates = [], [], []
    for log in test:
        model, traj = _test_model(plant, closed, controller, log, score, what_if)
        plain.append(model.predict(traj))
        if offsets is None:
            continue
        est = estimate_offsets_many(model, [traj], offsets.channels, offsets.window(dt), offsets.bound)[0]
        estimates.append(est)
        predictions.append(predict_with_offsets(model, traj, est.as_mapping()) if est.plausible else plain[-1])
    scored = test if what_if is None else [log for log in test if same_system(log.controller, what_if)]
    if what_if is not None:
        result.report["what_if"] = {
            "controller": what_if.as_dict(), "n_scored": len(scored),
            "unscored_logs": [log.path.name for log in test if log not in scored],
            "note": "test episodes are predicted under this controller; only those recorded under it are scored"}
    keep = [i for i, log in enumerate(test) if log in scored]
    if offsets is None:
        protocol = PAPER_PROTOCOL if score_from is None else window_protocol(score_from, dt)
        _summarize(result, test, plain, None, 1 if score_from is None else score_from, protocol, keep)
        return
    names = list(offsets.channels)
    result.report["offsets"] = [{"log": log.path.name, **est.as_dict(names)} for log, est in zip(test, estimates)]
    result.report["offset_bound"] = offsets.bound
    _summarize(result, test, predictions, plain, offsets.window(dt), offsets.describe(dt), keep)


def _summarize(result, test, predictions, plain, start, protocol, keep=None):
    """Scores of the kept episodes from sample ``start`` on (and without offsets on the same samples)."""
    keep = list(range(len(test))) if keep is None else keep
    result.test_names = [log.path.name for log in test]
    result.test_truth = [log.trajectory.x for log in test]
    result.test_predictions = predictions
    result.test_time = [np.arange(log.trajectory.n_samples) * log.trajectory.dt for log in test]
    result.report["protocol"] = protocol
    result.report["scored_from_sample"] = start
    result.report["scored_logs"] = [test[i].path.name for i in keep]
    if not keep:
        result.report["test"] = None
        return
    truth = [result.test_truth[i] for i in keep]
    names = [test[i].path.name for i in keep]
    result.report["test"] = summarize_episodes(truth, [predictions[i] for i in keep], start, names)
    _warn_diverged(result.report["test"], test[0].trajectory.dt, "")
    if plain is not None:
        result.report["test_without_offsets"] = summarize_episodes(truth, [plain[i] for i in keep], start, names)
        _warn_diverged(result.report["test_without_offsets"], test[0].trajectory.dt, " without offsets")


def _warn_diverged(summary: dict, dt: float, what: str) -> None:
    """One warning per diverged test prediction, naming the log and the sample."""
    others = summary["n_episodes"] - summary["n_diverged"]
    for d in summary["diverged"]:
        at = "" if d["sample"] is None else f" at sample {d['sample']} ({d['sample'] * dt:.2f} s)"
        mean = summary["r2_mean_converged"]
        rest = (f"the mean over the other {others} episode(s) is {mean:.4f}" if mean is not None
                else "no episode converged")
        warnings.warn(f"{d['name']}: the prediction{what} diverged{at}; its R^2 is -inf and so is the test "
                      f"mean; {rest}", DivergedPrediction, stacklevel=3)


def _arx(method, trajs, test, controller, lags, score, result):
    result.report["alpha"] = None
    if method == "arx":  # plant scoring only (identify_and_score refuses score="cl")
        plant = Arx(lags, lags, inputs=("u",)).fit(trajs)
        result.report["spectral_radius"] = {"closed_loop": None, "plant": _spectral_radius(plant.model_.A)}
        return plant, None, [plant.predict(log.trajectory) for log in test]
    model = ClArx(controller, lags, lags).fit(trajs)
    result.report["spectral_radius"] = {"closed_loop": _spectral_radius(model.closed_loop_.model_.A),
                                        "plant": _spectral_radius(model.plant_.A)}
    if score == "cl":
        for log in test:
            if not same_system(log.controller, controller):
                raise ValueError(f"{log.path}: its controller differs from the training one; a closed-loop "
                                 "ARX cannot predict another loop (use a Koopman method)")
        return model, model.closed_loop_, [model.predict_closed_loop(log.trajectory) for log in test]
    return model, model.closed_loop_, [model.predict(log.trajectory) for log in test]


def _arx_json(method, lags, plant, closed) -> str:
    import json

    arx = plant if method == "arx" else closed
    return json.dumps({"format": "qube-arx-model", "version": 1, "method": method, "output_lags": lags,
                       "input_lags": lags, "inputs": list(arx.inputs), "coef": arx.coef_.tolist(),
                       "dt": arx.dt_}, indent=1) + "\n"
