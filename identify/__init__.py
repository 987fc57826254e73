"""Identification of Koopman models of feedback-controlled systems.

Estimators follow scikit-learn's conventions (hyperparameters in the constructor, stored unchanged
and checked by ``fit``; ``fit`` returns self, learned attributes end in ``_``; ``get_params``,
``set_params`` and :func:`~qube_koopman.identify.params.clone`); the least-squares ones also fit
from per-episode statistics (:class:`~qube_koopman.identify.SnapshotEstimator`). Data come as
:class:`~qube_koopman.identify.Trajectory` objects, one per episode (:func:`~qube_koopman.identify.load_logs`
reads them from episode logs); see NAMING.md for the symbols. Import what is listed here from
``qube_koopman.identify``: each name is imported from its module when first used, so heavy
libraries (scipy, cvxpy, python-control, matplotlib) load only when used.
"""

from qube_koopman.core.exports import lazy_exports

# Each public name and the module (relative to this package) that defines it.
_HOMES = {
    # data
    "Trajectory": "data.trajectory",
    "LoggedTrajectory": "data.logs",
    "load_logs": "data.logs",
    "session_delays": "data.sessions",
    # liftings
    "Lifting": "lifting",
    "LiftingFunction": "lifting",
    "Constant": "lifting",
    "Polynomial": "lifting",
    "Delay": "lifting",
    "ThinPlateRbf": "lifting",
    "GaussianRbf": "lifting",
    "Trigonometric": "lifting",
    "CoulombFriction": "lifting",
    # estimators and the estimator contract
    "Edmd": "estimators.edmd",
    "ClEdmd": "estimators.cl_edmd",
    "ClEdmdKnownRows": "estimators.cl_edmd",
    "ClEdmdLstsq": "estimators.cl_edmd",
    "ClEdmdSdp": "estimators.sdp",
    "ClEdmdStable": "estimators.stability",
    "Arx": "estimators.arx",
    "ClArx": "estimators.arx",
    "clone": "params",
    "SnapshotEstimator": "estimators.base",  # the statistics protocol: setup_fit, episode_snapshots, ...
    "FitSetup": "estimators.base",
    # models and model files
    "KoopmanModel": "models.model",
    "save_model": "models.model_file",
    "load_model": "models.model_file",
    "IdentifiedModel": "models.identified",
    # what qube-identify runs: identification, regularization sweep, lifting search, probes
    **dict.fromkeys(
        ("identify_and_score", "IdentifyOptions", "FitOptions", "ScoreOptions", "OutputOptions"), "workflow"
    ),
    **dict.fromkeys(("IdentificationResult", "OffsetProtocol", "run_search", "SearchOptions"), "workflow"),
    "regularization_sweep": "model_selection.sweep",
    "SweepOptions": "model_selection.sweep",
    **dict.fromkeys(("search_liftings", "SearchSettings"), "model_selection.search"),
    "LiftingSpec": "model_selection.lifting_space",
    "twin_probes": "model_selection.transfer",
    "probe_scores": "metrics",
    # per-episode offsets
    "OffsetEstimate": "models.offsets",
    "estimate_offsets": "models.offsets",
    "estimate_offsets_many": "models.offsets",
    "predict_with_offsets": "models.offsets",
    "predict_with_offsets_many": "models.offsets",
    "scores_after_window": "metrics",
    # a test loop's command delay
    "DelayEstimate": "models.latency",
    "estimate_command_delays": "models.latency",
    "session_neighbours": "data.sessions",
    # prediction intervals
    "IntervalOptions": "uncertainty",
    "PredictionBand": "uncertainty",
    # least squares and the closed loop's structure
    "Snapshots": "estimators.regression",
    "ridge_solve": "estimators.regression",
    "constrained_plant_solve": "estimators.regression",
    "close_loop": "estimators.structure",
    "closed_loop_matrices": "estimators.structure",
    "extract_plant_lstsq": "estimators.structure",
    "output_selection": "estimators.structure",
    "plant_input_map": "estimators.structure",
    "controller_states": "estimators.structure",
    "plant_input": "estimators.structure",
    "with_command_delay": "estimators.structure",
    # scores
    "r2_score": "metrics",
    "nrmse": "metrics",
    "normalized_mean_error": "metrics",
    "score_episodes": "metrics",
    # figures (matplotlib only to draw them)
    "identification_figures": "report.figures",
    "write_figures": "report.figures",
    "draw": "report.figures",
    "Curve": "report.figures",
    "SeriesPlot": "report.figures",
}

__all__ = list(_HOMES)
__getattr__, __dir__ = lazy_exports(__name__, _HOMES)
