"""Time-delay lifting: the features stacked with their own past."""

from __future__ import annotations

import numpy as np

from qube_koopman.identify._checks import check_nonneg_int
from qube_koopman.identify.lifting.pipeline import LiftingFunction

__all__ = ["Delay"]


class Delay(LiftingFunction):
    """Stack ``[z_k, z_{k-1}, ..., z_{k-n}]``; consumes ``n`` samples per episode.

    Parameters
    ----------
    n_delays : int
        Number of past samples appended.
    """

    learns_from_data = False  # output depends on hyperparameters only: folds may share statistics
    affine = True  # a stack of past samples

    def __init__(self, n_delays: int = 1) -> None:
        self.n_delays = n_delays

    def _check_params(self) -> None:
        check_nonneg_int(self.n_delays, "number of delays")

    def _names_out(self, names):
        return list(names) + [f"{name}[k-{i}]" for i in range(1, self.n_delays + 1) for name in names]

    def transform(self, X):
        X = np.asarray(X, dtype=float)
        d = self.n_delays
        n = X.shape[-2]
        if n <= d:
            raise ValueError(f"{n} samples are too few for {d} delays")
        return np.concatenate([X[..., d - i : n - i, :] for i in range(d + 1)], axis=-1)
