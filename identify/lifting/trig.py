"""Trigonometric lifting: sine and cosine of the angles."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from qube_koopman.identify.lifting.pipeline import LiftingFunction

__all__ = ["Trigonometric"]


class Trigonometric(LiftingFunction):
    """Append ``sin`` and ``cos`` of chosen input features (angles, in radians).

    The pendulum's gravity torque is ``sin(alpha)`` and its inertia terms
    involve ``cos(alpha)`` (:mod:`qube_koopman.sim.pendulum.physics`): these are the lifting functions
    its equations name. Pointwise: put it before a delay step.

    Parameters
    ----------
    features : sequence of int
        Indices of the input features that are angles (the plant states are
        always the first features of any pipeline, so ``(0, 1)`` means
        theta and alpha on the QUBE-Servo).
    """

    learns_from_data = False  # output depends on hyperparameters only: folds may share statistics

    def __init__(self, features: Sequence[int] = (0, 1)) -> None:
        self.features = features

    def _indices(self) -> tuple[int, ...]:
        """``features`` as a tuple of ints, checked."""
        features = tuple(int(i) for i in self.features)
        if not features or min(features) < 0 or len(set(features)) != len(features):
            raise ValueError(f"trigonometric lifting needs distinct non-negative feature indices, got {features}")
        return features

    def _check_params(self) -> None:
        self._indices()

    def _fit(self, episodes):
        features = self._indices()
        if max(features) >= self.n_features_in_:
            raise ValueError(
                f"trigonometric lifting of feature {max(features)}: only {self.n_features_in_} features come in"
            )
        self.features_ = features

    def _names_out(self, names):
        return list(names) + [f"sin({names[i]})" for i in self.features_] + [f"cos({names[i]})" for i in self.features_]

    def transform(self, X):
        X = np.asarray(X, dtype=float)
        angles = X[..., list(self.features_)]
        return np.concatenate([X, np.sin(angles), np.cos(angles)], axis=-1)
