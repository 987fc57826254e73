"""Least-squares building blocks: snapshot statistics and (generalized) ridge solves.

Convention (the reference code's, FACTS section 1): ``alpha`` weighs
``||U||_F^2`` against the un-normalized sum of squared residuals, so the
ridge solution is ``U = G (H + alpha I)^-1`` with ``G = Theta_+ Psi^T`` and
``H = Psi Psi^T``.

The statistics are kept as the triangular factor ``R`` of the snapshot
matrix ``[Psi^T Theta_+^T]`` (``R^T R`` is the joint Gram matrix). Like Gram
matrices they are accumulated once per episode and merged across episodes
and folds, but solving from ``R`` does not square the condition number:
unregularized fits with nearly collinear lifted states (thin-plate RBFs)
stay accurate where ``G H^-1`` loses every digit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import linalg

__all__ = ["Snapshots", "ridge_solve", "constrained_plant_solve"]


def _triangular_factor(M: np.ndarray) -> np.ndarray:
    # mode="r" returns the full (rows x columns) R; only its top square part is non-zero.
    return linalg.qr(M, mode="r", check_finite=False)[0][:min(M.shape)]


@dataclass(frozen=True, eq=False)
class Snapshots:
    """Sufficient statistics of a regression ``theta_{k+1} ~ U psi_k``.

    Attributes
    ----------
    R : ndarray of shape (r, n_regressors + n_targets)
        Upper-triangular factor with ``R^T R = [Psi; Theta_+] [Psi; Theta_+]^T``.
    n_regressors : int
        Length of ``psi``.
    q : int
        Number of snapshots.
    """

    R: np.ndarray
    n_regressors: int
    q: int

    @classmethod
    def from_snapshots(cls, target: np.ndarray, regressor: np.ndarray) -> "Snapshots":
        """Statistics of one episode: row k of ``target`` follows row k of ``regressor``."""
        if target.shape[0] != regressor.shape[0]:
            raise ValueError(f"{target.shape[0]} targets for {regressor.shape[0]} regressors")
        return cls(_triangular_factor(np.hstack([regressor, target])), regressor.shape[1], regressor.shape[0])

    @classmethod
    def total(cls, parts) -> "Snapshots":
        """Statistics of several episodes together (exact, order-independent up to rounding)."""
        parts = list(parts)
        if not parts:
            raise ValueError("no snapshot statistics to combine")
        if len(parts) == 1:
            return parts[0]
        return cls(_triangular_factor(np.vstack([p.R for p in parts])), parts[0].n_regressors,
                   sum(p.q for p in parts))

    @property
    def _psi(self) -> np.ndarray:
        return self.R[:, :self.n_regressors]

    @property
    def _theta(self) -> np.ndarray:
        return self.R[:, self.n_regressors:]

    @property
    def G(self) -> np.ndarray:
        """``Theta_+ Psi^T``."""
        return self._theta.T @ self._psi

    @property
    def H(self) -> np.ndarray:
        """``Psi Psi^T``."""
        return self._psi.T @ self._psi

    @property
    def F(self) -> np.ndarray:
        """``Theta_+ Theta_+^T``."""
        return self._theta.T @ self._theta


def _lstsq(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    return linalg.lstsq(A, B, check_finite=False, lapack_driver="gelsd")[0]


def ridge_solve(snapshots: Snapshots, alpha: float, rows: slice = slice(None)) -> np.ndarray:
    """``argmin ||Theta_+ - U Psi||^2 + alpha ||U||^2`` for the selected target rows.

    With ``alpha = 0`` and collinear regressors this is the minimum-norm
    (pseudoinverse) solution.
    """
    R_psi = snapshots._psi
    Y = snapshots._theta[:, rows]
    p = snapshots.n_regressors
    A = np.vstack([R_psi, np.sqrt(alpha) * np.eye(p)])
    B = np.vstack([Y, np.zeros((p, Y.shape[1]))])
    return _lstsq(A, B).T


def constrained_plant_solve(snapshots: Snapshots, S: np.ndarray, alpha: float, rows: slice,
                            regularize: str = "closed_loop") -> np.ndarray:
    """Exact solution of the paper's constrained CL EDMD problem for the plant rows.

    The plant rows of the closed-loop Koopman matrix are ``U^p S``, so

    * ``regularize="closed_loop"`` (the paper): minimizing
      ``||Theta_2 - U^p S Psi||^2 + alpha ||U^p S||^2`` gives
      ``U^p = G_2 S^T (S (H + alpha I) S^T)^-1``;
    * ``regularize="plant"``: minimizing ``... + alpha ||U^p||^2`` gives
      ``U^p = G_2 S^T (S H S^T + alpha I)^-1``.

    Both are solved as least-squares problems on the triangular factor.
    """
    if regularize == "closed_loop":
        penalty = S.T
    elif regularize == "plant":
        penalty = np.eye(S.shape[0])
    else:
        raise ValueError(f"unknown regularize {regularize!r}; expected 'closed_loop' or 'plant'")
    Y = snapshots._theta[:, rows]
    A = np.vstack([snapshots._psi @ S.T, np.sqrt(alpha) * penalty])
    B = np.vstack([Y, np.zeros((penalty.shape[0], Y.shape[1]))])
    return _lstsq(A, B).T
