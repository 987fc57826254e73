"""Identify, select the regularization, score on test episodes: the qube-identify workflow."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from identify._blas import limited_blas_threads
from identify.arx import Arx, ClArx
from identify.cl_edmd import ClEdmd, ClEdmdLstsq
from identify.data import LoggedTrajectory, group_shuffle_splits, same_system
from identify.edmd import Edmd
from identify.model_file import lifting_to_dict, save_model
from identify.scores import summarize_episodes
from identify.structure import close_loop
from identify.sweep import SweepResult, regularization_sweep
from sim.lti import DiscreteStateSpace

__all__ = ["IdentificationResult", "identify_and_score", "KOOPMAN_METHODS"]

KOOPMAN_METHODS = {"edmd": Edmd, "cl-edmd": ClEdmd, "cl-edmd-lstsq": ClEdmdLstsq}
MEASURED = [0, 1]  # theta and alpha are both fed back on the QUBE-Servo


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
                       progress: Callable[[str, int, int], None] | None = None) -> IdentificationResult:
    """Fit ``method`` on the training logs and score it on the test logs.

    With ``alphas`` the regularization is chosen by episode-grouped
    cross-validation on the training logs with the same ``score``. Test
    episodes are predicted in closed loop under their own log's controller
    (``score="cl"``) or from their plant input (``score="plant"``).
    """
    trajs = [log.trajectory for log in train]
    result = IdentificationResult(report={"method": method, "score": score,
                                          "train_logs": [log.path.name for log in train],
                                          "test_logs": [log.path.name for log in test],
                                          "controller": controller.as_dict()})
    with limited_blas_threads(1):
        if method in KOOPMAN_METHODS:
            plant, closed, predictions = _koopman(method, lifting, trajs, test, controller, alpha, alphas, score,
                                                  cv_splits, cv_seed, progress, result)
            result.report["lifting"] = lifting_to_dict(plant.lifting)
            result.report["spectral_radius"] = {"closed_loop": closed.spectral_radius(),
                                                "plant": plant.spectral_radius()}
            if model_path is not None:
                save_model(model_path, method=method, alpha=result.report["alpha"], plant=plant, closed_loop=closed,
                           controller=controller, measured=MEASURED,
                           training={"logs": result.report["train_logs"]})
        elif method in ("arx", "cl-arx"):
            plant, closed, predictions = _arx(method, trajs, test, controller, arx_lags, score, result)
            if model_path is not None:
                Path(model_path).write_text(_arx_json(method, arx_lags, plant, closed))
        else:
            raise ValueError(f"unknown method {method!r}")
    result.plant, result.closed_loop = plant, closed
    result.test_names = [log.path.name for log in test]
    result.test_truth = [log.trajectory.x for log in test]
    result.test_predictions = predictions
    result.test_time = [np.arange(log.trajectory.n_samples) * log.trajectory.dt for log in test]
    result.report["test"] = summarize_episodes(result.test_truth, predictions)
    return result


def _koopman(method, lifting, trajs, test, controller, alpha, alphas, score, cv_splits, cv_seed, progress, result):
    cls = KOOPMAN_METHODS[method]
    make = (lambda a: cls(lifting=lifting, alpha=a)) if cls is Edmd else \
        (lambda a: cls(controller, lifting=lifting, alpha=a))
    if alphas is not None:
        splits = group_shuffle_splits(len(trajs), n_splits=cv_splits, test_size=0.2, seed=cv_seed)
        report = (lambda done, total: progress("cross-validation", done, total)) if progress else None
        sweep = regularization_sweep(make(0.0), trajs, alphas, splits, scorings=(score,), controller=controller,
                                     measured=MEASURED, progress=report)
        alpha = sweep.best_alpha(score)
        result.sweep = sweep
        result.report["sweep"] = {
            "alpha": [float(a) for a in sweep.alphas],
            "cv_r2_mean": sweep.cv_r2_mean(score).tolist(),
            "spectral_radius_closed_loop": (None if sweep.spectral_radius_closed_loop is None
                                            else sweep.spectral_radius_closed_loop.tolist()),
            "spectral_radius_plant": sweep.spectral_radius_plant.tolist(),
            "cv_splits": cv_splits, "cv_seed": cv_seed, "score": score,
        }
    result.report["alpha"] = float(alpha)
    fitted = make(alpha).fit(trajs)
    plant = fitted.model_ if cls is Edmd else fitted.plant_model_
    closed = close_loop(plant, controller, MEASURED) if cls is Edmd else fitted.closed_loop_model_
    predictions = []
    for log in test:
        if score == "plant":
            predictions.append(plant.predict(log.trajectory))
            continue
        # A plant model must predict the loop under any known controller.
        model = closed if same_system(log.controller, controller) else close_loop(plant, log.controller, MEASURED)
        predictions.append(model.predict(log.trajectory))
    return plant, closed, predictions


def _arx(method, trajs, test, controller, lags, score, result):
    result.report["alpha"] = None
    if method == "arx":
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
