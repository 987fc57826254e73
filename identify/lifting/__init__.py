"""Lifting functions: composable, fitted on training data, episode-aware."""

from identify.lifting.base import Lifting, LiftingFunction
from identify.lifting.constant import Constant
from identify.lifting.delay import Delay
from identify.lifting.polynomial import Polynomial
from identify.lifting.rbf import GaussianRbf, ThinPlateRbf

__all__ = ["Lifting", "LiftingFunction", "Constant", "Polynomial", "Delay", "ThinPlateRbf", "GaussianRbf"]
