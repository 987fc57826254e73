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

Every solve is a ridge problem ``min ||M w - Y||^2 + alpha ||w||^2`` on the
factor: one singular value decomposition of ``M`` serves every alpha (a
regularization sweep solves hundreds), kept with the statistics. It gives
what LAPACK's SVD-based least squares (``gelsd``) gives on the stacked
problem ``[M; sqrt(alpha) I]``, including its rank cutoff.
"""

from __future__ import annotations

from dataclasses import dataclass, field

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
    # Decompositions of the factor, built at the first solve that needs each (see _RidgePath).
    _paths: dict = field(default_factory=dict, repr=False, compare=False)

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


@dataclass(frozen=True)
class _RidgePath:
    """``u = back @ argmin_w ||M w - Y||^2 + alpha ||w||^2`` for any ``Y`` and alpha.

    From one thin SVD ``M = U diag(s) V^T``: ``w = V diag(s / (s^2 + alpha)) U^T Y``,
    with the rank cutoff of ``scipy.linalg.lstsq`` on ``[M; sqrt(alpha) I]`` (whose
    singular values are ``sqrt(s^2 + alpha)``): those at most ``eps`` times the largest
    are dropped.
    """

    U: np.ndarray
    s: np.ndarray
    Vt: np.ndarray
    back: np.ndarray | None = None  # upper triangular: u = back^-1 w

    @classmethod
    def of(cls, M: np.ndarray, back: np.ndarray | None = None) -> "_RidgePath":
        return cls(*linalg.svd(M, full_matrices=False, check_finite=False, lapack_driver="gesdd"), back)

    def solve(self, Y: np.ndarray, alpha: float) -> np.ndarray:
        # The stacked problem's singular values beyond those of M (a wide M) are sqrt(alpha):
        # never the largest, and their directions get no weight either way.
        s = self.s
        augmented = np.sqrt(s * s + alpha)
        keep = augmented > np.finfo(float).eps * augmented.max(initial=np.sqrt(alpha))
        gain = np.divide(s, s * s + alpha, out=np.zeros_like(s), where=keep)
        W = self.Vt.T @ (gain[:, None] * (self.U.T @ Y))
        return W if self.back is None else linalg.solve_triangular(self.back, W, check_finite=False)


def _psi_block(snapshots: Snapshots) -> slice:
    """Rows of the factor where the regressors' columns can be non-zero (it is upper triangular)."""
    return slice(0, min(snapshots.R.shape[0], snapshots.n_regressors))


def _path(snapshots: Snapshots, key, build) -> _RidgePath | None:
    if key not in snapshots._paths:
        snapshots._paths[key] = build()
    return snapshots._paths[key]


def ridge_solve(snapshots: Snapshots, alpha: float, rows: slice = slice(None)) -> np.ndarray:
    """``argmin ||Theta_+ - U Psi||^2 + alpha ||U||^2`` for the selected target rows.

    With ``alpha = 0`` and collinear regressors this is the minimum-norm
    (pseudoinverse) solution.
    """
    top = _psi_block(snapshots)
    path = _path(snapshots, ("ridge",), lambda: _RidgePath.of(snapshots._psi[top]))
    return path.solve(snapshots._theta[top, rows], alpha).T


def constrained_plant_solve(snapshots: Snapshots, S: np.ndarray, alpha: float, rows: slice,
                            regularize: str = "closed_loop") -> np.ndarray:
    """Exact solution of the paper's constrained CL EDMD problem for the plant rows.

    The plant rows of the closed-loop Koopman matrix are ``U^p S``, so

    * ``regularize="closed_loop"`` (the paper): minimizing
      ``||Theta_2 - U^p S Psi||^2 + alpha ||U^p S||^2`` gives
      ``U^p = G_2 S^T (S (H + alpha I) S^T)^-1``;
    * ``regularize="plant"``: minimizing ``... + alpha ||U^p||^2`` gives
      ``U^p = G_2 S^T (S H S^T + alpha I)^-1``.

    Both are solved as ridge problems on the triangular factor: with the
    closed-loop penalty, in the coordinates ``w = R_s u`` of ``S^T = Q_s R_s``
    (``||S^T u|| = ||w||``), when ``S`` has full row rank (else by least squares
    on the stacked problem).
    """
    if regularize not in ("closed_loop", "plant"):
        raise ValueError(f"unknown regularize {regularize!r}; expected 'closed_loop' or 'plant'")
    top = _psi_block(snapshots)
    Y = snapshots._theta[top, rows]
    key = (regularize, S.shape, S.tobytes())
    if regularize == "plant":
        return _path(snapshots, key, lambda: _RidgePath.of(snapshots._psi[top] @ S.T)).solve(Y, alpha).T
    path = _path(snapshots, key, lambda: _closed_loop_path(snapshots._psi[top], S))
    if path is not None:
        return path.solve(Y, alpha).T
    A = np.vstack([snapshots._psi[top] @ S.T, np.sqrt(alpha) * S.T])
    return _lstsq(A, np.vstack([Y, np.zeros((S.shape[1], Y.shape[1]))])).T


def _closed_loop_path(R_psi: np.ndarray, S: np.ndarray) -> _RidgePath | None:
    """The closed-loop penalty's path in ``w = R_s u`` (None when ``S`` is rank deficient)."""
    Q_s, R_s = linalg.qr(S.T, mode="economic", check_finite=False)
    diag = np.abs(np.diag(R_s))
    if not diag.size or diag.min() <= np.finfo(float).eps * S.shape[1] * diag.max():
        return None
    return _RidgePath.of(R_psi @ Q_s, R_s)
