"""Closed-loop EDMD: identify the closed loop and its plant with a known controller."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from qube_koopman.identify.estimators.base import FitSetup, SnapshotEstimator, pad_rows, resolve_lifting
from qube_koopman.identify._checks import check_alpha, check_choice, check_loop_controller
from qube_koopman.identify.models.model import KoopmanModel
from qube_koopman.core.lti import same_system
from qube_koopman.identify.estimators.mixed import ControllerGroups, distinct_controllers
from qube_koopman.identify.estimators.regression import (
    GroupedSnapshots,
    Snapshots,
    constrained_plant_solve,
    grouped_plant_solve,
    ridge_solve,
)
from qube_koopman.identify.estimators.structure import (
    close_loop,
    extract_plant_lstsq,
    feedforward_columns,
    output_selection,
    plant_input_map,
)
from qube_koopman.identify.data.trajectory import (
    EpisodeShape,
    Trajectory,
    as_episodes,
    check_trajectories,
    described_episodes,
    episode_signals,
)
from qube_koopman.core.lti import DiscreteStateSpace

__all__ = ["ClEdmd", "ClEdmdKnownRows", "ClEdmdLstsq"]

REGULARIZE = ("closed_loop", "plant")


class ClosedLoopKoopman(SnapshotEstimator):
    """The base of the closed-loop Koopman estimators (:class:`ClEdmd`, :class:`ClEdmdLstsq`, ``ClEdmdSdp``).

    Their shared data handling. Data: per episode the plant states ``x``, reference ``r``,
    controller state ``xc`` and optionally feedforward ``f`` (all episodes or none). Only the
    plant states are lifted; ``xc``, ``r`` and ``f`` are not. Episodes may come from several
    controllers (``fit``'s ``controllers``) where the subclass allows it (``_mixed_controllers``).
    A subclass solves for the Koopman matrices (``_solve``). The parameters ``controller``,
    ``lifting``, ``alpha`` and ``measured`` are those of every subclass (see :class:`ClEdmd`).
    """

    #: Whether the plant can be fitted to episodes recorded under several controllers.
    _mixed_controllers = False

    def __init__(
        self, controller: DiscreteStateSpace, lifting=None, alpha: float = 0.0, measured: Sequence[int] | None = None
    ) -> None:
        self.controller = controller
        self.lifting = lifting
        self.alpha = alpha
        self.measured = measured

    def fit(self, trajectories, controllers: Sequence[DiscreteStateSpace] | None = None) -> ClosedLoopKoopman:
        """Fit on a list of :class:`~identify.Trajectory` (signals x, r, xc, optionally f).

        Parameters
        ----------
        trajectories : sequence of Trajectory
            The episodes.
        controllers : sequence of DiscreteStateSpace, optional
            The controller each episode was recorded under (its ``xc`` is that
            controller's state). None: every episode ran ``self.controller``.
            The fitted closed loop (``closed_loop_model_``, ``koopman_matrix_``)
            is always ``self.controller``'s, which need not be among them.

        Returns
        -------
        self
        """
        return self.fit_setup(self.setup_fit(trajectories, controllers))

    # subclasses: return (U_f, U_p) from the statistics
    def _solve(self, snapshots, S: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _per_episode_controllers(self, trajs: Sequence[Trajectory], controllers) -> list[DiscreteStateSpace] | None:
        """The controllers given per episode, checked; None when every episode ran ``self.controller``."""
        if not isinstance(self.controller, DiscreteStateSpace):
            raise ValueError(f"controller must be a DiscreteStateSpace, got {type(self.controller).__name__}")
        if controllers is None:
            return None
        controllers = list(controllers)
        if len(controllers) != len(trajs):
            raise ValueError(f"{len(controllers)} controllers for {len(trajs)} episodes: give one per episode")
        distinct, _ = distinct_controllers(controllers)
        if len(distinct) == 1 and same_system(distinct[0], self.controller):
            return None
        if not self._mixed_controllers:
            raise ValueError(
                f"{type(self).__name__} fits episodes of one controller, its own; these were "
                f"recorded under {len(distinct)} controller(s) (ClEdmd fits several)"
            )
        return controllers

    def setup_fit(self, trajectories, controllers: Sequence[DiscreteStateSpace] | None = None) -> FitSetup:
        """Validate the data and the controllers, fit the lifting: the first step of a fit.

        Parameters
        ----------
        trajectories : sequence of Trajectory
            The episodes (signals x, r, xc, optionally f).
        controllers : sequence of DiscreteStateSpace, optional
            The controller each episode was recorded under, as in :meth:`fit`.

        Returns
        -------
        FitSetup
            What every other step of the statistics protocol takes.
        """
        check_alpha(self.alpha)
        lifting = resolve_lifting(self.lifting)
        what, min_samples = type(self).__name__, lifting.n_delays + 2
        trajs = as_episodes(trajectories)
        if not len(trajs):
            check_trajectories(trajs, ("x", "r"), min_samples, what)  # says there is none
        per_episode = self._per_episode_controllers(trajs, controllers)
        # One controller: one controller state width for all; several: each episode's own (checked below).
        needs = ("x", "r", "xc") if per_episode is None else ("x", "r")
        first = trajs[0] if len(trajs) else None
        with_f = isinstance(first, Trajectory) and first.f is not None

        def same_feedforward(i: int, t: Trajectory | EpisodeShape) -> None:
            if (t.width("f") is not None) != with_f:
                raise ValueError("feedforward f is present in some episodes and missing in others")

        # One pass: a stored log is read once for every check.
        trajs = check_trajectories(trajs, needs + (("f",) if with_f else ()), min_samples, what, same_feedforward)
        assert first is not None  # check_trajectories raised for no episodes
        n_f = first.f.shape[1] if with_f else 0
        m = first.x.shape[1]
        measured = list(range(m)) if self.measured is None else [int(i) for i in self.measured]
        if any(not 0 <= i < m for i in measured):
            raise ValueError(f"measured state indices {measured} are outside 0..{m - 1}")
        dt = first.dt
        if per_episode is None:  # the same widths in every episode
            check_loop_controller(self.controller, measured, n_f, dt, first)
        else:
            check_loop_controller(self.controller, measured, n_f, dt)
            for t, ctrl in zip(described_episodes(trajs), per_episode):
                check_loop_controller(ctrl, measured, n_f, dt, t)
        lifting.fit(episode_signals(trajs, "x"), first.state_names)
        C_p = output_selection(lifting.n_features_out_, measured)
        groups = None if per_episode is None else ControllerGroups.of(per_episode, C_p, n_f)
        return FitSetup(
            trajs,
            lifting,
            dt if dt is not None else self.controller.dt,
            C_p,
            plant_input_map(self.controller, C_p, n_f),
            n_f,
            controller_groups=groups,
        )

    def episode_snapshots(self, setup: FitSetup, t: Trajectory) -> Snapshots:
        """Snapshot statistics of one episode: theta = [x^c; lift(x)], upsilon = [r; f].

        Parameters
        ----------
        setup : FitSetup
            From :meth:`setup_fit`.
        t : Trajectory
            An episode with the signals of the setup's episodes.

        Returns
        -------
        Snapshots
            Its statistics, for a fold's ``add``.
        """
        d = setup.lifting.n_delays_
        # setup_fit's check_trajectories required them (f when there is a feedforward)
        assert t.xc is not None and t.r is not None and (t.f is not None or not setup.n_feedforward)
        theta = np.hstack([t.xc[d:], setup.lifting.transform(t.x)])
        v = np.hstack([t.r[d:]] + ([t.f[d:]] if t.f is not None and setup.n_feedforward else []))
        # A partial fit's rows count this episode's own controller states (their number may differ).
        rows = None if setup.target_rows is None else setup.target_rows - self.controller.n_states + t.xc.shape[1]
        return Snapshots.from_snapshots(theta[1:, :rows], np.hstack([theta[:-1], v[:-1]]))

    def total_statistics(self, setup: FitSetup, per_episode: list, indices=None):
        """One :class:`Snapshots`; :class:`GroupedSnapshots` (per controller) for several controllers."""
        if setup.controller_groups is None:
            return super().total_statistics(setup, per_episode, indices)
        return setup.controller_groups.statistics(list(per_episode), indices)

    def statistics_fold(self, setup: FitSetup):
        """A running total per controller with several controllers (see :meth:`total_statistics`)."""
        return super().statistics_fold(setup) if setup.controller_groups is None else setup.controller_groups.fold()

    def finish_fit(self, setup: FitSetup, snapshots) -> ClosedLoopKoopman:
        """Solve for ``self.alpha`` and set the fitted attributes.

        Parameters
        ----------
        setup : FitSetup
            From :meth:`setup_fit`.
        snapshots : Snapshots or GroupedSnapshots
            A fold's ``total()``.

        Returns
        -------
        self
        """
        alpha = check_alpha(self.alpha)
        assert setup.output_matrix is not None and setup.plant_input_map is not None  # setup_fit made them
        self.snapshots_ = snapshots
        self.output_matrix_ = setup.output_matrix
        self.n_feedforward_ = setup.n_feedforward
        # The statistics' controllers (a fold's may lack the setup's); the closed loop is self.controller's.
        grouped = isinstance(snapshots, GroupedSnapshots)
        self.training_controllers_ = snapshots.controllers if grouped else (self.controller,)
        self.plant_input_map_ = (
            plant_input_map(self.controller, setup.output_matrix, setup.n_feedforward)
            if grouped
            else setup.plant_input_map
        )
        U_f, U_p = self._solve(snapshots, self.plant_input_map_, alpha)
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
        self.closed_loop_model_ = KoopmanModel(
            U_f[:, :n_theta],
            U_f[:, n_theta:],
            lifting,
            ("r", "f") if n_f else ("r",),
            n_passthrough=n_c,
            dt=dt,
            feedback=feedback,
        )
        self.plant_model_ = KoopmanModel(U_p[:, :n_theta_p], U_p[:, n_theta_p:], lifting, ("u",), dt=dt)
        self.model_ = self.closed_loop_model_

    def wrap(self, controller: DiscreteStateSpace | None = None) -> KoopmanModel:
        """The identified plant closed with a controller (the training one by default)."""
        self._check_fitted()
        measured = list(range(self.plant_model_.n_states)) if self.measured is None else self.measured
        return close_loop(
            self.plant_model_, controller or self.controller, measured, feedforward=bool(self.n_feedforward_)
        )

    def predict(self, trajectory: Trajectory, relift: bool = True) -> np.ndarray:
        """Closed-loop prediction of the plant states of one episode (inputs ``r``, ``f``)."""
        self._check_fitted()
        return self.closed_loop_model_.predict(trajectory, relift=relift)

    def predict_plant(self, trajectory: Trajectory, relift: bool = True) -> np.ndarray:
        """Plant prediction of one episode from its plant input ``u``."""
        self._check_fitted()
        return self.plant_model_.predict(trajectory, relift=relift)


class ClEdmd(ClosedLoopKoopman):
    """Closed-loop EDMD, solved in exact closed form (generalized ridge).

    Solves the paper's constrained problem: the plant rows of the closed-loop
    Koopman matrix are ``U^p S`` with the known controller; ``U^p`` follows
    from ``U^p = G_2 S^T (S H_alpha S^T)^-1``, with ``G = Theta_+ Psi^T``, ``H_alpha = Psi Psi^T
    + alpha I`` and ``G_2`` the plant rows of ``G``: the constrained problem separates by block
    rows into this generalized ridge (it equals the paper's SDP to solver tolerance).

    Episodes recorded under several controllers (``fit(trajectories,
    controllers)``) share the plant: with controller g's statistics and map
    ``S_g``, ``U^p`` minimizes ``sum_g ||Theta2_g - U^p S_g Psi_g||^2 + alpha
    sum_g w_g ||U^p S_g||^2`` (``w_g``: g's share of the snapshots; with
    ``regularize="plant"`` the penalty is ``alpha ||U^p||^2``), which with one
    controller is the problem above
    (:func:`~qube_koopman.identify.estimators.regression.grouped_plant_solve`). The
    closed loop is ``self.controller``'s: its controller rows are fitted to its
    own episodes (penalty ``alpha w_g``), or are the known controller when
    none of the episodes ran it.

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
    snapshots_ : Snapshots or GroupedSnapshots
        Snapshot statistics (per controller when the episodes ran several).
    training_controllers_ : tuple of DiscreteStateSpace
        The distinct controllers of the training episodes.
    """

    def __init__(
        self,
        controller: DiscreteStateSpace,
        lifting=None,
        alpha: float = 0.0,
        measured: Sequence[int] | None = None,
        regularize: str = "closed_loop",
        known_controller_rows: bool = False,
    ) -> None:
        super().__init__(controller, lifting, alpha, measured)
        self.regularize = regularize
        self.known_controller_rows = known_controller_rows

    def relift_rows(self, setup: FitSetup) -> int | None:
        # Solved row by row: the controller rows and the plant states' rows alone are exact.
        return self.controller.n_states + setup.lifting.n_features_in_

    _mixed_controllers = True

    def _solve(self, snapshots, S, alpha):
        regularize = check_choice(self.regularize, "regularize", REGULARIZE)
        n_c = self.controller.n_states
        if isinstance(snapshots, GroupedSnapshots):
            U_p = grouped_plant_solve(snapshots, alpha, regularize)
            own = [
                (part, w)
                for part, w, ctrl in zip(snapshots.parts, snapshots.weights, snapshots.controllers)
                if same_system(ctrl, self.controller)
            ]
        else:
            U_p = constrained_plant_solve(snapshots, S, alpha, slice(n_c, None), regularize)
            own = [(snapshots, 1.0)]
        if self.known_controller_rows or not own:  # no episode of self.controller: nothing to fit them to
            U_c = self._known_controller_rows()
        else:
            # Only the closed-loop penalty covers the controller rows; "plant" leaves them free.
            # Several controllers: fitted to self.controller's episodes, penalty weighted by their share.
            part, weight = own[0]
            alpha_c = alpha * weight if regularize == "closed_loop" else 0.0
            U_c = ridge_solve(part, alpha_c, slice(0, n_c))
        return np.vstack([U_c, U_p @ S]), U_p

    def _known_controller_rows(self) -> np.ndarray:
        """The controller rows of ``U^f``: ``[A^c, -B^c C^p, B^c, 0]`` (``B^c_f`` for the 0 when the
        controller takes the feedforward)."""
        ctrl, C_p = self.controller, self.output_matrix_
        B_e, _, B_f, _ = feedforward_columns(ctrl, C_p.shape[0], self.n_feedforward_)
        return np.hstack([ctrl.A, -B_e @ C_p, B_e, B_f])


class ClEdmdKnownRows(ClEdmd):
    """CL EDMD with the controller rows of ``U^f`` fixed to the known controller (a variant).

    Same plant as :class:`ClEdmd`; the closed-loop matrix is exactly that
    plant wrapped with the controller, so its controller rows do not drift.

    Parameters
    ----------
    controller, lifting, alpha, measured, regularize
        As for :class:`ClEdmd`.
    known_controller_rows : bool
        True (the variant's point); False makes it :class:`ClEdmd`.
    """

    def __init__(
        self,
        controller: DiscreteStateSpace,
        lifting=None,
        alpha: float = 0.0,
        measured: Sequence[int] | None = None,
        regularize: str = "closed_loop",
        known_controller_rows: bool = True,
    ) -> None:
        super().__init__(controller, lifting, alpha, measured, regularize, known_controller_rows)


class ClEdmdLstsq(ClosedLoopKoopman):
    """Closed-loop EDMD by least squares (paper appendix): fit ``U^f`` freely, then extract.

    ``B^p = [U21 U23 U24] [C^c D^c I]^+`` and ``A^p = U22 + B^p D^c C^p``.
    The closed-loop model is the unstructured ``U^f``; re-wrapping the
    extracted plant with the controller generally moves its eigenvalues.
    The episodes must share one controller: the unstructured ``U^f`` is one loop's.

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
