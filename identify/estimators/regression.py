"""Least-squares building blocks: snapshot statistics and (generalized) ridge solves.

Convention (that of pykoop, the paper's reference code): ``alpha`` weighs
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
problem ``[M; sqrt(alpha) I]``, including its rank cutoff. Statistics solved
for one alpha (a plain fit, a bootstrap refit) take a QR of the stacked
problem instead, several times faster (:class:`_RidgePath`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, TypeVar

import numpy as np
from scipy import linalg
from scipy.linalg import lapack

#: Block size of LAPACK's triangular-pentagonal QR (the fastest measured on the search's factors).
_TPQRT_BLOCK = 16

__all__ = [
    "Snapshots",
    "SnapshotFold",
    "GroupedSnapshots",
    "ridge_solve",
    "constrained_plant_solve",
    "grouped_plant_solve",
    "solved_for_many_alphas",
]


def _triangular_factor(M: np.ndarray) -> np.ndarray:
    # mode="r" returns the full (rows x columns) R; only its top square part is non-zero. It is
    # copied out: a slice would keep the whole (snapshots x columns) array alive behind every
    # episode's statistics (8 MB an episode at 20 delays).
    return linalg.qr(M, mode="r", check_finite=False)[0][: min(M.shape)].copy()


def _copied_columns(target: np.ndarray, regressor: np.ndarray) -> np.ndarray:
    """For each target column, the index of a regressor column equal to it in every row (-1: none).

    A candidate is the first regressor column that agrees exactly at a few rows spread over the
    episode (not its first ones: an episode that starts at rest zeroes many features there); it is
    then checked in every row, so a missed or a false candidate costs time, never a wrong factor.
    """
    copies = np.full(target.shape[1], -1)
    if not target.shape[0] or not target.shape[1] or not regressor.shape[1]:
        return copies
    rows = np.unique(np.linspace(0, target.shape[0] - 1, 8).astype(int))
    by_key: dict[bytes, list[int]] = {}
    for j, key in enumerate(np.ascontiguousarray(regressor[rows].T)):
        by_key.setdefault(key.tobytes(), []).append(j)
    pairs = [
        (i, by_key[key][0])
        for i, key in enumerate(k.tobytes() for k in np.ascontiguousarray(target[rows].T))
        if key in by_key
    ]
    if not pairs:
        return copies
    I, J = np.array(pairs).T
    same = np.ones(I.size, dtype=bool)
    for lo in range(0, target.shape[0], 2048):  # by blocks of rows: each block's columns gathered in cache
        same &= (target[lo : lo + 2048, I] == regressor[lo : lo + 2048, J]).all(axis=0)
    copies[I[same]] = J[same]
    return copies


def _merge_triangles(factors: list[np.ndarray]) -> np.ndarray:
    """The upper-triangular factor of square upper-triangular ``factors`` stacked.

    LAPACK's triangular-pentagonal QR (``tpqrt``) folds one triangle into the running one,
    using that both are triangular: about a fifth of the work of a QR of the stacked
    matrix at the search's sizes (a few hundred columns), the same ``R^T R``.
    """
    n = factors[0].shape[1]
    merged = np.array(factors[0], dtype=float, order="F")
    for factor in factors[1:]:
        merged, _, _, info = lapack.dtpqrt(n, min(_TPQRT_BLOCK, n), merged, factor, overwrite_a=1)
        if info != 0:
            raise ValueError(f"LAPACK dtpqrt failed (info {info})")
    return np.triu(merged)


@dataclass(frozen=True, eq=False)
class Snapshots:
    """Sufficient statistics of a regression ``theta_{k+1} ~ U psi_k``.

    Parameters
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
        """Statistics of one episode: row k of ``target`` follows row k of ``regressor``.

        A target column equal to a regressor column in every snapshot (with delays, the lifted
        state's older slots at k + 1 are its newer slots at k; the constant is itself) is not
        factored again: only the regressors and the other targets are, and such a column of the
        factor is its regressor's column (``Q^T y = Q^T psi_j = R e_j``; its residual is zero).
        The factor is the same up to rounding, at a quarter of the work for a full delayed fit
        (half the columns are copies).
        """
        if target.shape[0] != regressor.shape[0]:
            raise ValueError(f"{target.shape[0]} targets for {regressor.shape[0]} regressors")
        q, n_r, n_t = regressor.shape[0], regressor.shape[1], target.shape[1]
        copies = _copied_columns(target, regressor)
        unique = np.flatnonzero(copies < 0)
        if unique.size == n_t or q < n_r + unique.size:  # nothing to save, or a factor with fewer rows than columns
            return cls(_triangular_factor(np.hstack([regressor, target])), n_r, q)
        small = _triangular_factor(np.hstack([regressor, target[:, unique]]))
        # Rows and columns of the small factor go where their columns are in [regressors, targets]: upper
        # triangular still, with zero rows where the copies are.
        at = np.concatenate([np.arange(n_r), n_r + unique])
        R = np.zeros((n_r + n_t, n_r + n_t))
        R[np.ix_(at, at)] = small
        copied = np.flatnonzero(copies >= 0)
        R[:n_r, n_r + copied] = small[:n_r, copies[copied]]
        return cls(R, n_r, q)

    @classmethod
    def total(cls, parts, batch: int = 4) -> "Snapshots":
        """Statistics of several episodes together (exact, order-independent up to rounding).

        Parameters
        ----------
        parts : iterable of Snapshots
            May be a generator: the factors are folded ``batch`` at a time into a running one,
            so memory stays that of ``batch + 1`` factors whatever the number of episodes.
        batch : int
            Factors stacked per fold.
        """
        running = SnapshotFold(batch)
        for part in parts:
            running.add(part)
        return running.total()

    def columns(self, regressors: list[int], targets: list[int]) -> "Snapshots":
        """The statistics of the regression on some of these columns: exactly, from the factor alone.

        ``regressors`` and ``targets`` index the regressor and target columns. A lifting whose
        features are some of another's has its statistics so, without lifting an episode again:
        ``M[:, c] = Q R[:, c]``, so the factor of ``R[:, c]`` is that of ``M[:, c]``.
        """
        cols = [int(i) for i in regressors] + [self.n_regressors + int(i) for i in targets]
        return type(self)(_triangular_factor(self.R[:, cols]), len(regressors), self.q)

    @classmethod
    def _fold(cls, running: "Snapshots | None", parts: list["Snapshots"]) -> "Snapshots":
        parts = ([] if running is None else [running]) + parts
        if not parts:
            raise ValueError("no snapshot statistics to combine")
        if len(parts) == 1:
            return parts[0]
        n = parts[0].R.shape[1]
        if all(p.R.shape == (n, n) for p in parts):  # square factors: merged two triangles at a time
            R = _merge_triangles([p.R for p in parts])
        else:  # a factor with fewer rows (fewer snapshots than columns): the stack's QR
            R = _triangular_factor(np.vstack([p.R for p in parts]))
        return cls(R, parts[0].n_regressors, sum(p.q for p in parts))

    def repeated(self, count: int) -> Snapshots:
        """The statistics of ``count`` copies of these snapshots (an episode drawn ``count`` times).

        ``R^T R`` of the copies stacked is ``count R^T R``: the factor scaled by ``sqrt(count)``,
        with no new decomposition (an episode bootstrap folds its resamples so).
        """
        if count == 1:
            return self
        return Snapshots(np.sqrt(count) * self.R, self.n_regressors, self.q * int(count))

    def leading(self, n_targets: int) -> Snapshots:
        """The statistics of the first ``n_targets`` targets alone (the other target rows dropped).

        The factor's columns are the regressors, then the targets; the factor of the leading
        columns of a QR factorization is its leading block, so no new decomposition is needed.
        """
        k = self.n_regressors + int(n_targets)
        if k >= self.R.shape[1]:
            return self
        return Snapshots(self.R[: min(self.R.shape[0], k), :k].copy(), self.n_regressors, self.q)

    @property
    def _psi(self) -> np.ndarray:
        return self.R[:, : self.n_regressors]

    @property
    def _theta(self) -> np.ndarray:
        return self.R[:, self.n_regressors :]

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


class SnapshotFold:
    """A running :meth:`Snapshots.total`: parts added one at a time, folded ``batch`` at a time.

    Memory is that of ``batch + 1`` factors however many parts are added: a sweep keeps one per
    cross-validation fold and adds each episode to the folds that train on it, so its memory grows
    with the folds, not with the episodes. The total equals :meth:`Snapshots.total` of
    the same parts in the same order, bit for bit.
    """

    def __init__(self, batch: int = 4) -> None:
        self.batch = batch
        self._running: Snapshots | None = None
        self._pending: list[Snapshots] = []

    def add(self, part: Snapshots) -> None:
        """Fold in one part's statistics."""
        self._pending.append(part)
        if len(self._pending) == self.batch:
            self._running = Snapshots._fold(self._running, self._pending)
            self._pending = []

    def total(self) -> Snapshots:
        """The statistics of every part added (a ValueError when none was)."""
        if self._pending or self._running is None:
            self._running = Snapshots._fold(self._running, self._pending)
            self._pending = []
        return self._running


def _lstsq(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    return linalg.lstsq(A, B, check_finite=False, lapack_driver="gelsd")[0]


class _RidgePath:
    """``u = back @ argmin_w ||M w - Y||^2 + alpha ||w||^2`` for any ``Y`` and alpha.

    From one thin SVD ``M = U diag(s) V^T``: ``w = V diag(s / (s^2 + alpha)) U^T Y``,
    with the rank cutoff of ``scipy.linalg.lstsq`` on ``[M; sqrt(alpha) I]`` (whose
    singular values are ``sqrt(s^2 + alpha)``): those at most ``eps`` times the largest
    are dropped.

    Statistics solved for one alpha only (a plain fit, each bootstrap refit of the
    intervals) do not need the SVD: until a second alpha is asked for, the stacked problem
    is solved by LAPACK's QR of ``[sqrt(alpha) I; M]`` (``tpqrt``, whose top block is
    triangular), 4.4 times faster than the SVD on the search winner's 330 regressors
    (measured; the two agree to 1e-12). Where the cutoff could drop a direction (alpha
    below ``eps`` times ``M``'s norm), the SVD is used. A sweep marks its statistics
    (:func:`solved_for_many_alphas`) and builds the SVD at its first solve.
    """

    def __init__(self, M: np.ndarray, back: np.ndarray | None = None) -> None:
        self.M, self.back = M, back  # back: upper triangular, u = back^-1 w
        self.many_alphas = False  # set by _path for statistics a sweep marked
        self._svd: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._alpha: float | None = None  # the one alpha solved directly so far
        self._scale = float(np.linalg.norm(M))  # bounds the largest singular value

    def solve(self, Y: np.ndarray, alpha: float) -> np.ndarray:
        if not self.many_alphas and self._svd is None and self._alpha in (None, alpha) and self._direct(alpha):
            self._alpha = alpha
            W = self._direct_solve(Y, alpha)
        else:
            W = self._svd_solve(Y, alpha)
        return W if self.back is None else linalg.solve_triangular(self.back, W, check_finite=False)

    def _direct(self, alpha: float) -> bool:
        """Whether no singular value of the stacked problem can fall under its cutoff (all are kept)."""
        n = self.M.shape[1]
        return n > 0 and alpha > 0 and np.sqrt(alpha) > np.finfo(float).eps * np.hypot(self._scale, np.sqrt(alpha))

    def _direct_solve(self, Y: np.ndarray, alpha: float) -> np.ndarray:
        n = self.M.shape[1]
        top = np.asfortranarray(np.sqrt(alpha) * np.eye(n))
        R, V, T, info = lapack.dtpqrt(0, min(_TPQRT_BLOCK, n), top, np.asfortranarray(self.M), overwrite_a=1)
        if info:
            raise np.linalg.LinAlgError(f"tpqrt failed (info {info})")
        C, _, info = lapack.dtpmqrt(
            0, V, T, np.zeros((n, Y.shape[1]), order="F"), np.asfortranarray(Y), side="L", trans="T", overwrite_a=1
        )
        if info:
            raise np.linalg.LinAlgError(f"tpmqrt failed (info {info})")
        return linalg.solve_triangular(R, C, check_finite=False)

    def _svd_solve(self, Y: np.ndarray, alpha: float) -> np.ndarray:
        if self._svd is None:
            self._svd = linalg.svd(self.M, full_matrices=False, check_finite=False, lapack_driver="gesdd")
        U, s, Vt = self._svd
        # The stacked problem's singular values beyond those of M (a wide M) are sqrt(alpha):
        # never the largest, and their directions get no weight either way.
        augmented = np.sqrt(s * s + alpha)
        keep = augmented > np.finfo(float).eps * augmented.max(initial=np.sqrt(alpha))
        gain = np.divide(s, s * s + alpha, out=np.zeros_like(s), where=keep)
        return Vt.T @ (gain[:, None] * (U.T @ Y))


#: The key a sweep's mark takes in statistics' ``_paths`` (:func:`solved_for_many_alphas`).
_MANY_ALPHAS = "many alphas"


def solved_for_many_alphas(statistics) -> None:
    """Mark statistics (:class:`Snapshots` or :class:`GroupedSnapshots`) that a sweep solves for many alphas:
    their solves decompose once for every alpha from the first (see :class:`_RidgePath`)."""
    statistics._paths[_MANY_ALPHAS] = True
    for part in getattr(statistics, "parts", ()):
        part._paths[_MANY_ALPHAS] = True


def _psi_block(snapshots: Snapshots) -> slice:
    """Rows of the factor where the regressors' columns can be non-zero (it is upper triangular)."""
    return slice(0, min(snapshots.R.shape[0], snapshots.n_regressors))


_Path = TypeVar("_Path", bound="_RidgePath | None")


def _path(snapshots, key, build: Callable[[], _Path]) -> _Path:
    """What ``build`` makes, made once per ``key`` and kept in ``snapshots``; told to build its SVD at once
    when a sweep marked the statistics (:func:`solved_for_many_alphas`), before or after it was made."""
    if key not in snapshots._paths:
        snapshots._paths[key] = build()
    path = snapshots._paths[key]
    if path is not None and snapshots._paths.get(_MANY_ALPHAS):
        path.many_alphas = True
    return path


def ridge_solve(snapshots: Snapshots, alpha: float, rows: slice = slice(None)) -> np.ndarray:
    """``argmin ||Theta_+ - U Psi||^2 + alpha ||U||^2`` for the selected target rows.

    With ``alpha = 0`` and collinear regressors this is the minimum-norm
    (pseudoinverse) solution.

    Parameters
    ----------
    snapshots : Snapshots
        The regression's statistics.
    alpha : float
        Tikhonov coefficient on ``||U||^2`` against the un-normalized sum of squares.
    rows : slice
        The target rows to solve for (all by default).

    Returns
    -------
    ndarray of shape (n_rows, n_regressors)
    """
    top = _psi_block(snapshots)
    path = _path(snapshots, ("ridge",), lambda: _RidgePath(snapshots._psi[top]))
    return path.solve(snapshots._theta[top, rows], alpha).T


def constrained_plant_solve(
    snapshots: Snapshots, S: np.ndarray, alpha: float, rows: slice, regularize: str = "closed_loop"
) -> np.ndarray:
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

    Parameters
    ----------
    snapshots : Snapshots
        The closed loop's statistics.
    S : ndarray
        The plant input map (:func:`~qube_koopman.identify.estimators.structure.plant_input_map`).
    alpha : float
        Tikhonov coefficient.
    rows : slice
        The plant rows of the closed-loop targets.
    regularize : {"closed_loop", "plant"}
        Which matrix the penalty is on.

    Returns
    -------
    ndarray
        ``U^p = [A^p B^p]``.
    """
    top = _psi_block(snapshots)
    block = _Block(snapshots._psi[top], snapshots._theta[top, rows], S, 1.0)
    return _plant_solve([block], snapshots, (regularize, S.shape, S.tobytes()), alpha, regularize)


@dataclass(frozen=True, eq=False)
class GroupedSnapshots:
    """Statistics of episodes recorded under several controllers, one :class:`Snapshots` per controller.

    Each controller's episodes have their own regressor ``Psi_g = [x^c; theta^p; r; f]``
    (the controller state's width may differ) and plant input map ``S_g``
    (:func:`~qube_koopman.identify.estimators.structure.plant_input_map`), but the plant
    ``U^p`` is common: :func:`grouped_plant_solve` fits it to all of them.

    Attributes
    ----------
    parts : tuple of Snapshots
        Statistics of each controller's episodes.
    maps : tuple of ndarray
        ``S_g`` of each part.
    plant_rows : tuple of slice
        The plant's target rows in each part (those after its controller states).
    controllers : tuple
        The controller of each part (the estimator picks its own out of them).
    """

    parts: tuple[Snapshots, ...]
    maps: tuple[np.ndarray, ...]
    plant_rows: tuple[slice, ...]
    controllers: tuple
    _paths: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.parts or not len(self.parts) == len(self.maps) == len(self.plant_rows) == len(self.controllers):
            raise ValueError("grouped snapshots need one map, row range and controller per (non-empty) part")

    @property
    def q(self) -> int:
        """Number of snapshots of all parts."""
        return sum(p.q for p in self.parts)

    @property
    def weights(self) -> tuple[float, ...]:
        """Each part's share of the snapshots, ``w_g = q_g / q``: its weight in the closed-loop penalty."""
        return tuple(p.q / self.q for p in self.parts)


def grouped_plant_solve(grouped: GroupedSnapshots, alpha: float, regularize: str = "closed_loop") -> np.ndarray:
    """The common plant ``U^p`` of episodes under several controllers (stacked least squares).

    Minimizes ``sum_g ||Theta2_g - U^p S_g Psi_g||^2`` plus, with
    ``regularize="closed_loop"``, ``alpha sum_g w_g ||U^p S_g||_F^2`` (``w_g``:
    :attr:`GroupedSnapshots.weights`), or with ``"plant"`` ``alpha ||U^p||_F^2``.
    With one part it is :func:`constrained_plant_solve` (to the last bit). Solved
    like it on the stacked factors ``R_g S_g^T``: with the closed-loop penalty in
    ``w = R_p u``, where ``P = [sqrt(w_g) S_g^T]_g = Q_p R_p`` and so
    ``R_g S_g^T R_p^-1 = R_g Q_p,g / sqrt(w_g)``. Memory grows with the number
    of controllers, not with the data.
    """
    blocks = []
    for part, S, rows, w in zip(grouped.parts, grouped.maps, grouped.plant_rows, grouped.weights):
        top = _psi_block(part)
        blocks.append(_Block(part._psi[top], part._theta[top, rows], S, w))
    return _plant_solve(blocks, grouped, (regularize,), alpha, regularize)


@dataclass(frozen=True)
class _Block:
    """One controller's part of the plant problem: factor rows ``R_psi``, targets ``Y``, map ``S``, weight."""

    R_psi: np.ndarray
    Y: np.ndarray
    S: np.ndarray
    weight: float

    @property
    def penalty(self) -> np.ndarray:
        """``sqrt(w) S^T``: this block's rows of the closed-loop penalty."""
        return self.S.T if self.weight == 1.0 else np.sqrt(self.weight) * self.S.T


def _stack(arrays: list[np.ndarray]) -> np.ndarray:
    # One block is used as it is: a single controller's solve stays that of constrained_plant_solve.
    return arrays[0] if len(arrays) == 1 else np.vstack(arrays)


def _plant_solve(blocks: list[_Block], owner, key, alpha: float, regularize: str) -> np.ndarray:
    """``U^p`` of the stacked blocks; the alpha-independent decomposition is cached on ``owner``."""
    if regularize not in ("closed_loop", "plant"):
        raise ValueError(f"unknown regularize {regularize!r}; expected 'closed_loop' or 'plant'")
    Y = _stack([b.Y for b in blocks])
    if regularize == "plant":
        return _path(owner, key, lambda: _RidgePath(_stack([b.R_psi @ b.S.T for b in blocks]))).solve(Y, alpha).T
    path = _path(owner, key, lambda: _closed_loop_path(blocks))
    if path is not None:
        return path.solve(Y, alpha).T
    P = _stack([b.penalty for b in blocks])
    A = np.vstack([_stack([b.R_psi @ b.S.T for b in blocks]), np.sqrt(alpha) * P])
    return _lstsq(A, np.vstack([Y, np.zeros((P.shape[0], Y.shape[1]))])).T


def _closed_loop_path(blocks: list[_Block]) -> _RidgePath | None:
    """The closed-loop penalty's path in ``w = R_p u`` (None when the penalty ``P`` is rank deficient)."""
    P = _stack([b.penalty for b in blocks])
    Q_p, R_p = linalg.qr(P, mode="economic", check_finite=False)
    diag = np.abs(np.diag(R_p))
    if not diag.size or diag.min() <= np.finfo(float).eps * P.shape[0] * diag.max():
        return None
    if len(blocks) == 1:
        return _RidgePath(blocks[0].R_psi @ Q_p, R_p)
    at = np.cumsum([0] + [b.S.shape[1] for b in blocks])
    return _RidgePath(
        np.vstack([b.R_psi @ (Q_p[at[g] : at[g + 1]] / np.sqrt(b.weight)) for g, b in enumerate(blocks)]), R_p
    )
