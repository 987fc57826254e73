"""Controller design from identified plant models (``qube-design``).

The package above ``identify``: it reads a model file, designs a controller (an LQ state
feedback on the plant's history with integral action on the arm), predicts the closed loop
it gives on the rig's excitation, and writes it as a state-space controller file that
``qube-run --controller`` runs. Imports go one way: ``design`` uses ``identify``, ``daq`` and
``sim``; none of them imports ``design``.

Import what is listed here from ``qube_koopman.design``: each name is imported from its module
when first used.
"""

from qube_koopman.core.exports import lazy_exports

# Each public name and the module (relative to this package) that defines it.
_HOMES = {
    # the plant on its history
    "DesignError": "plant",
    "LinearPlant": "plant",
    "linear_plant": "plant",
    # the LQ design and its realization as a controller
    "Weights": "lq",
    "LqDesign": "lq",
    "augment": "lq",
    "design_lq": "lq",
    "realize": "lq",
    # the model predictive controller
    "MpcSettings": "mpc",
    "MpcProblem": "mpc",
    "build_problem": "mpc",
    "MpcRuntime": "mpc",
    "MpcDisturbance": "mpc",
    # the plant's multi-step predictors: the model's own, Korda & Mezić's lifted map, the MPC's
    "PREDICTORS": "predictors",
    "PredictorScores": "predictors",
    "lifted_condensed": "predictors",
    "predict_windows": "predictors",
    "score_predictors": "predictors",
    # the closed loop it predicts
    "CostPrediction": "predict",
    "predict_cost": "predict",
    "predict_loop": "predict",
    "closed_loop_eigenvalues": "predict",
    "Margins": "predict",
    "loop_margins": "predict",
    "loop_response": "predict",
    # what qube-design runs, and the design run on the twin
    "DesignReport": "controller_design",
    "design_from_model": "controller_design",
    "report_text": "controller_design",
    # the model's uncertainty: the predicted figures' interval, the robust design
    "ModelUncertainty": "uncertainty",
    "model_uncertainty": "uncertainty",
    "member_figures": "uncertainty",
    "FigureInterval": "uncertainty",
    "figure_interval": "uncertainty",
    "interval_from_logs": "uncertainty",
    "RobustChoice": "uncertainty",
    "robust_design": "uncertainty",
    "run_on_twin": "twin",
    # the design's frequency responses (qube-design --figures)
    "FrequencyFigures": "frequency",
    "write_frequency_figures": "frequency",
    # an MPC episode's figure (bench/bench_mpc.py --only figure)
    "MpcEpisodeFigure": "mpc_figure",
    "write_mpc_episode_figure": "mpc_figure",
    # episodes run under a design against its prediction (qube-compare)
    "RunComparison": "compare",
    "compare_runs": "compare",
    "comparison_text": "compare",
}

__all__ = list(_HOMES)

__getattr__, __dir__ = lazy_exports(__name__, _HOMES)
