"""Identification of Koopman models of feedback-controlled systems.

Estimators follow scikit-learn's conventions (hyperparameters in the
constructor, ``fit`` returns self, learned attributes end in ``_``). Data
come as :class:`Trajectory` objects, one per episode; see NAMING.md for the
symbols. Heavy libraries (cvxpy, python-control) are imported only when used.
"""

from identify.arx import Arx, ClArx
from identify.cl_edmd import ClEdmd, ClEdmdKnownRows, ClEdmdLstsq
from identify.edmd import Edmd
from identify.lifting import Constant, Delay, GaussianRbf, Lifting, LiftingFunction, Polynomial, ThinPlateRbf
from identify.model import KoopmanModel
from identify.regression import Snapshots, constrained_plant_solve, ridge_solve
from identify.scores import normalized_mean_error, nrmse, r2_score, score_episodes
from identify.sdp import ClEdmdSdp
from identify.structure import (close_loop, closed_loop_matrices, controller_states,
                                extract_plant_lstsq, output_selection, plant_input,
                                plant_input_map)
from identify.trajectory import Trajectory

__all__ = [
    "Trajectory", "Lifting", "LiftingFunction", "Constant", "Polynomial", "Delay", "ThinPlateRbf", "GaussianRbf",
    "Edmd", "ClEdmd", "ClEdmdKnownRows", "ClEdmdLstsq", "ClEdmdSdp", "Arx", "ClArx", "KoopmanModel",
    "Snapshots", "ridge_solve", "constrained_plant_solve",
    "close_loop", "closed_loop_matrices", "extract_plant_lstsq", "output_selection",
    "plant_input_map", "controller_states", "plant_input",
    "r2_score", "nrmse", "normalized_mean_error", "score_episodes",
]
