"""Identification of Koopman models of feedback-controlled systems.

Estimators follow scikit-learn's conventions (hyperparameters in the
constructor, stored unchanged and checked by ``fit``; ``fit`` returns self,
learned attributes end in ``_``; ``get_params``, ``set_params`` and
:func:`~qube_koopman.identify.params.clone`). Data come as
:class:`~qube_koopman.identify.trajectory.Trajectory` objects, one per episode
(:func:`~qube_koopman.identify.data.load_logs` reads them from episode logs); see NAMING.md for the
symbols. Import what is listed here from ``qube_koopman.identify``: each name
is imported from its module when first used, so heavy libraries (scipy,
cvxpy, python-control, matplotlib) load only when used.
"""

from qube_koopman.core.exports import lazy_exports

# Each public name and the module (relative to this package) that defines it.
_HOMES = {
    # data
    "Trajectory": "trajectory", "LoggedTrajectory": "data", "load_logs": "data",
    # liftings
    "Lifting": "lifting", "LiftingFunction": "lifting", "Constant": "lifting", "Polynomial": "lifting",
    "Delay": "lifting", "ThinPlateRbf": "lifting", "GaussianRbf": "lifting", "Trigonometric": "lifting",
    "CoulombFriction": "lifting",
    # estimators and the estimator contract
    "Edmd": "edmd", "ClEdmd": "cl_edmd", "ClEdmdKnownRows": "cl_edmd", "ClEdmdLstsq": "cl_edmd",
    "ClEdmdSdp": "sdp", "ClEdmdStable": "stability", "Arx": "arx", "ClArx": "arx", "clone": "params",
    # models and model files
    "KoopmanModel": "model", "save_model": "model_file", "load_model": "model_file",
    # what qube-identify runs: identification, regularization sweep, lifting search, probes
    "identify_and_score": "workflow", "IdentificationResult": "workflow", "regularization_sweep": "sweep",
    "search_liftings": "search", "LiftingSpec": "search", "twin_probes": "transfer", "probe_scores": "transfer",
    # per-episode offsets
    "OffsetEstimate": "offsets", "estimate_offsets": "offsets", "estimate_offsets_many": "offsets",
    "predict_with_offsets": "offsets", "predict_with_offsets_many": "offsets", "scores_after_window": "offsets",
    # prediction intervals
    "IntervalOptions": "uncertainty", "PredictionBand": "uncertainty",
    # least squares and the closed loop's structure
    "Snapshots": "regression", "ridge_solve": "regression", "constrained_plant_solve": "regression",
    "close_loop": "structure", "closed_loop_matrices": "structure", "extract_plant_lstsq": "structure",
    "output_selection": "structure", "plant_input_map": "structure", "controller_states": "structure",
    "plant_input": "structure",
    # scores
    "r2_score": "scores", "nrmse": "scores", "normalized_mean_error": "scores", "score_episodes": "scores",
    # figures (matplotlib only to draw them)
    "identification_figures": "figures", "write_figures": "figures", "draw": "figures", "Curve": "figures",
    "SeriesPlot": "figures",
}

__all__ = list(_HOMES)

__getattr__, __dir__ = lazy_exports(__name__, _HOMES)
