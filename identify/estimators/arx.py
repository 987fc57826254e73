"""ARX baselines: a multi-episode least-squares ARX and the indirect closed-loop ARX."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from qube_koopman.identify.estimators.base import Estimator
from qube_koopman.identify._checks import check_alpha, check_nonneg_int
from qube_koopman.identify.estimators.regression import Snapshots, ridge_solve
from qube_koopman.identify.data.trajectory import Trajectory, check_trajectories
from qube_koopman.core.lti import DiscreteStateSpace

__all__ = ["Arx", "ClArx"]


def _stack(traj: Trajectory, signals: Sequence[str]) -> np.ndarray:
    parts = []
    for key in signals:
        value = getattr(traj, key)
        if value is None:
            raise ValueError(f"trajectory {traj.name!r} lacks signal {key!r}")
        parts.append(value)
    return np.hstack(parts)


class Arx(Estimator):
    """ARX model ``y_k = sum_i A_i y_{k-i} + sum_j B_j v_{k-j}`` (i, j from 1).

    Fitted by (ridge) least squares over all episodes jointly, episode
    boundaries respected (the reference code averaged per-episode fits).

    Parameters
    ----------
    output_lags : int
        Number of past outputs ``na``.
    input_lags : int
        Number of past inputs ``nb``.
    inputs : tuple of str
        Trajectory signals forming ``v``: ``("u",)`` for a plant model,
        ``("r",)`` or ``("r", "f")`` for a closed-loop model.
    alpha : float
        Tikhonov coefficient (0: ordinary least squares).

    Attributes
    ----------
    coef_ : ndarray of shape (n_outputs, na n_outputs + nb n_inputs)
        ``[A_1 ... A_na B_1 ... B_nb]``.
    """

    def __init__(
        self, output_lags: int = 1, input_lags: int = 1, inputs: tuple[str, ...] = ("u",), alpha: float = 0.0
    ) -> None:
        self.output_lags = output_lags
        self.input_lags = input_lags
        self.inputs = inputs
        self.alpha = alpha

    @property
    def _lag(self) -> int:
        return max(self.output_lags, self.input_lags)

    def _regressors(self, y: np.ndarray, v: np.ndarray) -> np.ndarray:
        na, nb, n = self.output_lags, self.input_lags, y.shape[0]
        lag = self._lag
        cols = [y[lag - i : n - i] for i in range(1, na + 1)] + [v[lag - j : n - j] for j in range(1, nb + 1)]
        return np.hstack(cols)

    def fit(self, trajectories) -> "Arx":
        """Fit on episodes with output ``x`` and the input signals.

        Returns
        -------
        self
        """
        check_nonneg_int(self.output_lags, "output_lags", minimum=1)
        check_nonneg_int(self.input_lags, "input_lags", minimum=1)
        alpha = check_alpha(self.alpha)
        signals = tuple(self.inputs)
        trajs = check_trajectories(trajectories, ("x",) + signals, self._lag + 2, "ARX")
        parts = []
        for t in trajs:
            y, v = t.x, _stack(t, signals)
            parts.append(Snapshots.from_snapshots(y[self._lag :], self._regressors(y, v)))
        snapshots = Snapshots.total(parts)
        self.coef_ = ridge_solve(snapshots, alpha)
        self.n_outputs_ = trajs[0].x.shape[1]
        self.n_inputs_ = sum(getattr(trajs[0], k).shape[1] for k in signals)
        self.dt_ = trajs[0].dt
        self.model_ = self.to_state_space_matrices()
        return self

    def to_state_space_matrices(self) -> DiscreteStateSpace:
        """The fitted ARX as a state-space system (block companion form).

        State ``[y_k, ..., y_{k-na+1}, v_{k-1}, ..., v_{k-nb+1}]``, output ``y_k``.
        """
        na, nb, m, p = self.output_lags, self.input_lags, self.n_outputs_, self.n_inputs_
        n = na * m + (nb - 1) * p
        A = np.zeros((n, n))
        B = np.zeros((n, p))
        A_blocks = self.coef_[:, : na * m]
        B_blocks = self.coef_[:, na * m :]
        A[:m, : na * m] = A_blocks
        A[:m, na * m :] = B_blocks[:, p:]
        B[:m] = B_blocks[:, :p]
        A[m : na * m, : (na - 1) * m] = np.eye((na - 1) * m)
        if nb > 1:
            B[na * m : na * m + p] = np.eye(p)
            A[na * m + p :, na * m : n - p] = np.eye((nb - 2) * p)
        C = np.zeros((m, n))
        C[:, :m] = np.eye(m)
        return DiscreteStateSpace(A, B, C, np.zeros((m, p)), self.dt_ or 1.0)

    def predict(self, trajectory: Trajectory) -> np.ndarray:
        """Free-run simulation from the first ``max(na, nb)`` samples and the inputs."""
        self._check_fitted()
        y, v = trajectory.x, _stack(trajectory, tuple(self.inputs))
        lag = self._lag
        if y.shape[0] < lag + 1 or y.shape[1] != self.n_outputs_ or v.shape[1] != self.n_inputs_:
            raise ValueError(
                f"trajectory {trajectory.name!r} does not fit this ARX model "
                f"({self.n_outputs_} outputs, {self.n_inputs_} inputs, {lag} lags)"
            )
        na, nb = self.output_lags, self.input_lags
        out = np.empty_like(y)
        out[:lag] = y[:lag]
        coef_y = self.coef_[:, : na * self.n_outputs_]
        coef_v = self.coef_[:, na * self.n_outputs_ :]
        v_reg = np.hstack([v[lag - j : v.shape[0] - j] for j in range(1, nb + 1)]) @ coef_v.T
        with np.errstate(all="ignore"):
            for k in range(lag, y.shape[0]):
                past = out[k - na : k][::-1].reshape(-1)
                out[k] = coef_y @ past + v_reg[k - lag]
        return out

    def _check_fitted(self) -> None:
        if not hasattr(self, "coef_"):
            raise ValueError("this Arx is not fitted yet; call fit first")


def _ss_inverse(sys):
    """Inverse of a square discrete system with invertible feedthrough, in state space."""
    import control

    D_inv = np.linalg.inv(np.atleast_2d(sys.D))
    return control.ss(sys.A - sys.B @ D_inv @ sys.C, sys.B @ D_inv, -D_inv @ sys.C, D_inv, sys.dt)


class ClArx(Estimator):
    """The indirect approach: a closed-loop ARX, then the plant recovered with the controller.

    With a feedforward input the plant follows from the feedforward channel
    ``T_f = G (1 + K G)^-1`` as ``G = T_f (1 - K T_f)^-1`` (one SISO inverse,
    as the paper does for the QUBE-Servo); without, from the reference
    channel of a SISO loop, ``G = T_r (1 - T_r)^-1 K^-1``. The algebra is done
    in state space with python-control (inverses of systems with invertible
    feedthrough): transfer-function polynomials lose the near-cancelling
    pole/zero pairs at z = 1 to rounding and the recovered plant diverges.

    Parameters
    ----------
    controller : DiscreteStateSpace
        The known controller (single output, invertible feedthrough for the
        reference-channel case).
    output_lags, input_lags : int
        Orders of the closed-loop ARX.
    alpha : float
        Tikhonov coefficient of the closed-loop ARX.

    Attributes
    ----------
    closed_loop_ : Arx
        The closed-loop ARX (inputs ``r`` and, if present, ``f``).
    plant_ : control.StateSpace
        Recovered plant from ``u`` to the measured states (non-minimal).
    """

    def __init__(
        self, controller: DiscreteStateSpace, output_lags: int = 1, input_lags: int = 1, alpha: float = 0.0
    ) -> None:
        self.controller = controller
        self.output_lags = output_lags
        self.input_lags = input_lags
        self.alpha = alpha

    def fit(self, trajectories) -> "ClArx":
        """Fit on closed-loop episodes (``x``, ``r``, optional ``f``).

        Returns
        -------
        self
        """
        trajs = check_trajectories(trajectories, ("x", "r"), 2, "CL ARX")
        with_f = trajs[0].f is not None
        ctrl = self.controller
        assert trajs[0].r is not None  # check_trajectories required it
        n_r = trajs[0].r.shape[1]
        if ctrl.n_inputs != n_r or ctrl.n_outputs != 1:
            raise ValueError(
                f"CL ARX needs a single-output controller taking {n_r} errors; "
                f"got {ctrl.n_outputs} outputs, {ctrl.n_inputs} inputs"
                + (
                    " (a controller that also takes the feedforward is not supported: use CL EDMD)"
                    if ctrl.n_inputs > n_r
                    else ""
                )
            )
        if n_r != trajs[0].x.shape[1]:
            raise ValueError(
                f"CL ARX feeds back every measured state: {trajs[0].x.shape[1]} states but {n_r} references"
            )
        if not with_f and n_r != 1:
            raise ValueError("without feedforward CL ARX recovers only a SISO plant")
        inputs = ("r", "f") if with_f else ("r",)
        self.closed_loop_ = Arx(self.output_lags, self.input_lags, inputs, self.alpha).fit(trajs)
        T = self.closed_loop_.model_.to_control()
        K = ctrl.to_control()
        if with_f:
            T_f = T[:, n_r]
            self.plant_ = T_f * _ss_inverse(1 - K * T_f)
        else:
            if abs(ctrl.D[0, 0]) == 0:
                raise ValueError("the reference-channel recovery needs a controller with feedthrough")
            T_r = T[0, 0]
            self.plant_ = T_r * _ss_inverse(1 - T_r) * _ss_inverse(K)
        self.dt_ = ctrl.dt
        return self

    def predict(self, trajectory: Trajectory) -> np.ndarray:
        """Plant prediction from the plant input ``u``, started from the episode's history.

        The recovered plant's initial state is the least-squares (minimum
        norm) fit of its free response to the first ``n_history`` measured
        samples, ``n_history = max(ARX lag, plant order)``; those samples are
        the initial condition (copied), the rest is predicted. An episode cut
        from a longer run therefore starts where it really was, not at rest.
        """
        import control

        if not hasattr(self, "plant_"):
            raise ValueError("this ClArx is not fitted yet; call fit first")
        if trajectory.u is None or trajectory.u.shape[1] != 1:
            raise ValueError(f"trajectory {trajectory.name!r} needs a single plant input u")
        A, C = np.atleast_2d(self.plant_.A), np.atleast_2d(self.plant_.C)
        n_hist = max(self.closed_loop_._lag, A.shape[0])
        if trajectory.n_samples <= n_hist:
            raise ValueError(
                f"trajectory {trajectory.name!r} has {trajectory.n_samples} samples; the recovered "
                f"plant needs more than {n_hist} (its initial history)"
            )
        u, y = trajectory.u[:, 0], trajectory.x
        with np.errstate(all="ignore"):
            forced = np.asarray(control.forced_response(self.plant_, U=u).outputs, dtype=float).reshape(len(u), -1)
            rows, M = [], np.eye(A.shape[0])
            for _ in range(n_hist):  # observability matrix over the history: y_k = C A^k x0 + forced_k
                rows.append(C @ M)
                M = A @ M
            x0 = np.linalg.lstsq(np.vstack(rows), (y[:n_hist] - forced[:n_hist]).reshape(-1), rcond=None)[0]
            out = np.asarray(control.forced_response(self.plant_, U=u, X0=x0).outputs, dtype=float).reshape(len(u), -1)
        out[:n_hist] = y[:n_hist]
        return out

    def predict_closed_loop(self, trajectory: Trajectory) -> np.ndarray:
        """Closed-loop prediction from the references (and feedforward)."""
        return self.closed_loop_.predict(trajectory)
