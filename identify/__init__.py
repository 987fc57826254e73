"""Identification of Koopman models of feedback-controlled systems.

Estimators follow scikit-learn's conventions (hyperparameters in the
constructor, stored unchanged and checked by ``fit``; ``fit`` returns self,
learned attributes end in ``_``; ``get_params``, ``set_params`` and
:func:`clone`). Data
come as :class:`Trajectory` objects, one per episode; see NAMING.md for the
symbols. Heavy libraries (cvxpy, python-control) are imported only when used.
"""

from qube_koopman.identify.arx import Arx, ClArx
from qube_koopman.identify.cl_edmd import ClEdmd, ClEdmdKnownRows, ClEdmdLstsq
from qube_koopman.identify.edmd import Edmd
from qube_koopman.identify.lifting import (Constant, CoulombFriction, Delay, GaussianRbf, Lifting, LiftingFunction,
                                           Polynomial, ThinPlateRbf, Trigonometric)
from qube_koopman.identify.model import KoopmanModel
from qube_koopman.identify.params import clone
from qube_koopman.identify.regression import Snapshots, constrained_plant_solve, ridge_solve
from qube_koopman.identify.scores import normalized_mean_error, nrmse, r2_score, score_episodes
from qube_koopman.identify.sdp import ClEdmdSdp
from qube_koopman.identify.stability import ClEdmdStable
from qube_koopman.identify.structure import (close_loop, closed_loop_matrices, controller_states,
                                extract_plant_lstsq, output_selection, plant_input,
                                plant_input_map)
from qube_koopman.identify.trajectory import Trajectory

__all__ = [
    "Trajectory", "Lifting", "LiftingFunction", "Constant", "Polynomial", "Delay", "ThinPlateRbf", "GaussianRbf", "Trigonometric",
    "CoulombFriction",
    "Edmd", "ClEdmd", "ClEdmdKnownRows", "ClEdmdLstsq", "ClEdmdSdp", "ClEdmdStable", "Arx", "ClArx", "clone",
    "KoopmanModel",
    "Snapshots", "ridge_solve", "constrained_plant_solve",
    "close_loop", "closed_loop_matrices", "extract_plant_lstsq", "output_selection",
    "plant_input_map", "controller_states", "plant_input",
    "r2_score", "nrmse", "normalized_mean_error", "score_episodes",
]
