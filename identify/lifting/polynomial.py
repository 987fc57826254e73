"""Polynomial lifting: all monomials of the features up to a given order."""

from __future__ import annotations

from itertools import combinations_with_replacement

import numpy as np

from qube_koopman.identify._checks import check_nonneg_int
from qube_koopman.identify.lifting.pipeline import LiftingFunction

__all__ = ["Polynomial"]


class Polynomial(LiftingFunction):
    """Monomials of degree 1..``order`` with cross terms (degree 1 first).

    For (theta, alpha) and order 2: theta, alpha, theta^2, theta*alpha, alpha^2.

    Parameters
    ----------
    order : int
        Highest total degree (1 is the identity).
    """

    learns_from_data = False  # output depends on hyperparameters only: folds may share statistics

    def __init__(self, order: int = 2) -> None:
        self.order = order

    @property
    def affine(self) -> bool:
        """Order 1 is the identity."""
        return self.order == 1

    def _check_params(self) -> None:
        check_nonneg_int(self.order, "polynomial order", minimum=1)

    def _fit(self, episodes):
        n = self.n_features_in_
        self.monomials_ = tuple(c for d in range(1, self.order + 1) for c in combinations_with_replacement(range(n), d))

    def _names_out(self, names):
        out = []
        for combo in self.monomials_:
            parts = []
            for i in sorted(set(combo)):
                k = combo.count(i)
                parts.append(names[i] if k == 1 else f"{names[i]}^{k}")
            out.append("*".join(parts))
        return out

    def transform(self, X):
        X = np.asarray(X, dtype=float)
        n = self.n_features_in_
        out = np.empty(X.shape[:-1] + (len(self.monomials_),))
        out[..., :n] = X
        for j, combo in enumerate(self.monomials_[n:], start=n):
            # column views multiplied in place: no fancy-index copies (this runs every predicted step)
            np.multiply(X[..., combo[0]], X[..., combo[1]], out=out[..., j])
            for i in combo[2:]:
                out[..., j] *= X[..., i]
        return out
