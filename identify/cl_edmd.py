"""Closed-loop EDMD: identify the closed loop and its plant with a known controller."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from qube_koopman.identify._base import FitSetup, SnapshotEstimator, pad_rows, resolve_lifting
from qube_koopman.identify._checks import check_alpha, check_choice
from qube_koopman.identify.model import KoopmanModel
from qube_koopman.identify.regression import Snapshots, constrained_plant_solve, ridge_solve
from qube_koopman.identify.structure import (close_loop, extract_plant_lstsq, output_selection,
                                plant_input_map)
from qube_koopman.identify.trajectory import Trajectory, check_trajectories
from qube_koopman.sim.lti import DiscreteStateSpace

__all__ = ["ClEdmd", "ClEdmdKnownRows", "ClEdmdLstsq"]

REGULARIZE = ("closed_loop", "plant")


class _ClosedLoopKoopman(SnapshotEstimator):
    """Shared data handling of the closed-loop estimators.

    Data: per episode the plant states ``x``, reference ``r``, controller
    state ``xc`` and optionally feedforward ``f`` (all episodes or none).
    Only the plant states are lifted; ``xc``, ``r`` and ``f`` are not.
    """

    def __init__(self, controller: DiscreteStateSpace, lifting=None, alpha: float = 0.0,
                 measured: Sequence[int] | None = None) -> None:
        self.controller = controller
        self.lifting = lifting
        self.alpha = alpha
        self.measured = measured

    # subclasses: return (U_f, U_p) from the statistics
    def _solve(self, snapshots: Snapshots, S: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _check_controller(self, trajs: list[Trajectory], measured: list[int], n_f: int) -> None:
        ctrl = self.controller
        if not isinstance(ctrl, DiscreteStateSpace):
            raise ValueError(f"controller must be a DiscreteStateSpace, got {type(ctrl).__name__}")
        first = trajs[0]
        if ctrl.n_states != first.xc.shape[1]:
            raise ValueError(f"the controller has {ctrl.n_states} states but the data's controller state "
                             f"has {first.xc.shape[1]} channels")
        if ctrl.n_inputs != first.r.shape[1] or ctrl.n_inputs != len(measured):
            raise ValueError(f"the controller takes {ctrl.n_inputs} tracking errors; the data has "
                             f"{first.r.shape[1]} references and {len(measured)} fed-back states")
        if n_f and ctrl.n_outputs != n_f:
            raise ValueError(f"the controller drives {ctrl.n_outputs} plant inputs, the feedforward "
                             f"has {n_f} channels")
        if first.dt is not None and abs(first.dt - ctrl.dt) > 1e-12 * ctrl.dt:
            raise ValueError(f"the data's sample period {first.dt} s differs from the controller's {ctrl.dt} s")

    def _setup(self, trajectories) -> FitSetup:
        """Validate the data and the controller, fit the lifting."""
        check_alpha(self.alpha)
        lifting = resolve_lifting(self.lifting)
        trajs = check_trajectories(trajectories, ("x", "r", "xc"), lifting.n_delays + 2, type(self).__name__)
        with_f = [t.f is not None for t in trajs]
        if any(with_f) and not all(with_f):
            raise ValueError("feedforward f is present in some episodes and missing in others")
        if all(with_f):
            trajs = check_trajectories(trajs, ("x", "r", "xc", "f"), lifting.n_delays + 2, type(self).__name__)
        n_f = trajs[0].f.shape[1] if all(with_f) else 0
        m = trajs[0].x.shape[1]
        measured = list(range(m)) if self.measured is None else [int(i) for i in self.measured]
        if any(not 0 <= i < m for i in measured):
            raise ValueError(f"measured state indices {measured} are outside 0..{m - 1}")
        self._check_controller(trajs, measured, n_f)
        lifting.fit([t.x for t in trajs], trajs[0].state_names)
        C_p = output_selection(lifting.n_features_out_, measured)
        return FitSetup(trajs, lifting, trajs[0].dt if trajs[0].dt is not None else self.controller.dt,
                        C_p, plant_input_map(self.controller, C_p, n_f), n_f)

    def _episode_snapshots(self, setup: FitSetup, t: Trajectory) -> Snapshots:
        """Snapshot statistics of one episode: theta = [x^c; lift(x)], upsilon = [r; f]."""
        d = setup.lifting.n_delays_
        theta = np.hstack([t.xc[d:], setup.lifting.transform(t.x)])
        v = np.hstack([t.r[d:]] + ([t.f[d:]] if setup.n_feedforward else []))
        return Snapshots.from_snapshots(theta[1:, :setup.target_rows], np.hstack([theta[:-1], v[:-1]]))

    def _finish(self, setup: FitSetup, snapshots: Snapshots) -> "_ClosedLoopKoopman":
        """Solve for ``self.alpha`` and set the fitted attributes."""
        alpha = check_alpha(self.alpha)
        self.snapshots_ = snapshots
        self.output_matrix_ = setup.output_matrix
        self.plant_input_map_ = setup.plant_input_map
        self.n_feedforward_ = setup.n_feedforward
        U_f, U_p = self._solve(snapshots, setup.plant_input_map, alpha)
        self._set_models(U_f, U_p, setup.lifting, setup.n_feedforward, setup.dt)
        return self

    def _set_models(self, U_f, U_p, lifting, n_f, dt) -> None:
        ctrl = self.controller
        n_c, n_theta_p = ctrl.n_states, lifting.n_features_out_
        n_theta = n_c + n_theta_p
        U_f, U_p = pad_rows(U_f, n_theta), pad_rows(U_p, n_theta_p)  # a partial fit's missing rows
        self.koopman_matrix_ = U_f
        self.plant_koopman_matrix_ = U_p
        feedback = tuple(range(lifting.n_features_in_)) if self.measured is None else tuple(self.measured)
        self.closed_loop_model_ = KoopmanModel(U_f[:, :n_theta], U_f[:, n_theta:], lifting,
                                               ("r", "f") if n_f else ("r",), n_passthrough=n_c, dt=dt,
                                               feedback=feedback)
        self.plant_model_ = KoopmanModel(U_p[:, :n_theta_p], U_p[:, n_theta_p:], lifting, ("u",), dt=dt)
        self.model_ = self.closed_loop_model_

    def wrap(self, controller: DiscreteStateSpace | None = None) -> KoopmanModel:
        """The identified plant closed with a controller (the training one by default)."""
        self._check_fitted()
        measured = list(range(self.plant_model_.n_states)) if self.measured is None else self.measured
        return close_loop(self.plant_model_, controller or self.controller, measured,
                          feedforward=bool(self.n_feedforward_))

    def predict(self, trajectory: Trajectory, relift: bool = True) -> np.ndarray:
        """Closed-loop prediction of the plant states of one episode (inputs ``r``, ``f``)."""
        self._check_fitted()
        return self.closed_loop_model_.predict(trajectory, relift=relift)

    def predict_plant(self, trajectory: Trajectory, relift: bool = True) -> np.ndarray:
        """Plant prediction of one episode from its plant input ``u``."""
        self._check_fitted()
        return self.plant_model_.predict(trajectory, relift=relift)


class ClEdmd(_ClosedLoopKoopman):
    """Closed-loop EDMD, solved in exact closed form (generalized ridge).

    Solves the paper's constrained problem: the plant rows of the closed-loop
    Koopman matrix are ``U^p S`` with the known controller; ``U^p`` follows
    from ``U^p = G_2 S^T (S H_alpha S^T)^-1`` (FACTS section 1).

    Parameters
    ----------
    controller : DiscreteStateSpace
        The known controller (A^c, B^c, C^c, D^c), input: tracking error.
    lifting : Lifting or sequence of LiftingFunction, optional
        Lifting of the plant states (identity when None).
    alpha : float
        Tikhonov coefficient.
    measured : sequence of int, optional
        Indices of the plant states fed back (``C^p``); all by default.
    regularize : {"closed_loop", "plant"}
        Penalize ``||U^f||_F^2`` (the paper's choice) or ``||U^p||_F^2``.
    known_controller_rows : bool
        False (default, the paper's problem and its SDP): the controller
        rows of ``U^f`` are fitted by ridge like the plant rows; they drift
        from the known controller along poorly excited directions (measured
        on the paper's 28 training episodes at alpha 1e-3: by at most 3.8e-3
        with 10 delays, 3.9e-3 with 20) while predicting the same controller
        state. True (:class:`ClEdmdKnownRows`): they are the known
        controller, so ``U^f`` is exactly the identified plant wrapped with
        it. The plant ``U^p`` is the same either way.

    Attributes
    ----------
    koopman_matrix_ : ndarray
        Closed-loop Koopman matrix ``U^f``.
    plant_koopman_matrix_ : ndarray
        Plant Koopman matrix ``U^p = [A^p B^p]``.
    closed_loop_model_, plant_model_ : KoopmanModel
        The closed loop (inputs r, f) and the plant (input u).
    snapshots_ : Snapshots
        Snapshot statistics.
    """

    def __init__(self, controller: DiscreteStateSpace, lifting=None, alpha: float = 0.0,
                 measured: Sequence[int] | None = None, regularize: str = "closed_loop",
                 known_controller_rows: bool = False) -> None:
        super().__init__(controller, lifting, alpha, measured)
        self.regularize = regularize
        self.known_controller_rows = known_controller_rows

    def _relift_rows(self, setup: FitSetup) -> int:
        # Solved row by row: the controller rows and the plant states' rows alone are exact.
        return self.controller.n_states + setup.lifting.n_features_in_

    def _solve(self, snapshots, S, alpha):
        regularize = check_choice(self.regularize, "regularize", REGULARIZE)
        n_c = self.controller.n_states
        U_p = constrained_plant_solve(snapshots, S, alpha, slice(n_c, None), regularize)
        if self.known_controller_rows:
            U_c = self._known_controller_rows()
        else:
            # Only the closed-loop penalty covers the controller rows; "plant" leaves them free.
            alpha_c = alpha if regularize == "closed_loop" else 0.0
            U_c = ridge_solve(snapshots, alpha_c, slice(0, n_c))
        return np.vstack([U_c, U_p @ S]), U_p


    def _known_controller_rows(self) -> np.ndarray:
        """The controller rows of ``U^f``: ``[A^c, -B^c C^p, B^c, 0]``."""
        ctrl = self.controller
        return np.hstack([ctrl.A, -ctrl.B @ self.output_matrix_, ctrl.B,
                          np.zeros((ctrl.n_states, self.n_feedforward_))])


class ClEdmdKnownRows(ClEdmd):
    """CL EDMD with the controller rows of ``U^f`` fixed to the known controller (a variant).

    Same plant as :class:`ClEdmd`; the closed-loop matrix is exactly that
    plant wrapped with the controller, so its controller rows do not drift.
    Parameters as :class:`ClEdmd`, with ``known_controller_rows=True``.
    """

    def __init__(self, controller: DiscreteStateSpace, lifting=None, alpha: float = 0.0,
                 measured: Sequence[int] | None = None, regularize: str = "closed_loop",
                 known_controller_rows: bool = True) -> None:
        super().__init__(controller, lifting, alpha, measured, regularize, known_controller_rows)


class ClEdmdLstsq(_ClosedLoopKoopman):
    """Closed-loop EDMD by least squares (paper appendix): fit ``U^f`` freely, then extract.

    ``B^p = [U21 U23 U24] [C^c D^c I]^+`` and ``A^p = U22 + B^p D^c C^p``.
    The closed-loop model is the unstructured ``U^f``; re-wrapping the
    extracted plant with the controller generally moves its eigenvalues.

    Parameters
    ----------
    controller : DiscreteStateSpace
        The known controller.
    lifting : Lifting or sequence of LiftingFunction, optional
        Lifting of the plant states.
    alpha : float
        Tikhonov coefficient on ``||U^f||_F^2``.
    measured : sequence of int, optional
        Indices of the plant states fed back; all by default.
    """

    def _solve(self, snapshots, S, alpha):
        U_f = ridge_solve(snapshots, alpha)
        A_p, B_p = extract_plant_lstsq(U_f, self.controller, self.output_matrix_, self.n_feedforward_)
        return U_f, np.hstack([A_p, B_p])
