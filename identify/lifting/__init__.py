"""Lifting functions: composable, fitted on training data, episode-aware."""

from qube_koopman.identify.lifting.pipeline import Lifting, LiftingFunction
from qube_koopman.identify.lifting.constant import Constant
from qube_koopman.identify.lifting.delay import Delay
from qube_koopman.identify.lifting.friction import CoulombFriction
from qube_koopman.identify.lifting.polynomial import Polynomial
from qube_koopman.identify.lifting.rbf import GaussianRbf, ThinPlateRbf
from qube_koopman.identify.lifting.trig import Trigonometric

__all__ = [
    "Lifting",
    "LiftingFunction",
    "Constant",
    "Polynomial",
    "Delay",
    "ThinPlateRbf",
    "GaussianRbf",
    "Trigonometric",
    "CoulombFriction",
]
