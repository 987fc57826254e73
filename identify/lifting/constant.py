"""The constant lifting function: an affine term for the Koopman model."""

from __future__ import annotations

import numpy as np

from qube_koopman.identify.lifting.pipeline import LiftingFunction

__all__ = ["Constant"]


class Constant(LiftingFunction):
    """Append a feature that is always 1 (named ``"1"``).

    With it a linear Koopman model becomes affine: its equilibrium is no
    longer pinned at the origin of the measured states, which matters when
    an encoder's zero is off the true equilibrium (the QUBE's pendulum encoder is, by a
    few counts; see :mod:`qube_koopman.identify.models.offsets`). Put it
    last in a pipeline: a delay step after it would stack copies of the
    same constant.
    """

    learns_from_data = False  # output depends on hyperparameters only: folds may share statistics
    affine = True

    def _names_out(self, names):
        return list(names) + ["1"]

    def transform(self, X):
        X = np.asarray(X, dtype=float)
        return np.concatenate([X, np.ones(X.shape[:-1] + (1,))], axis=-1)
