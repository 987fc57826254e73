"""EDMD with Tikhonov regularization for systems with inputs."""

from __future__ import annotations

import numpy as np

from qube_koopman.identify.estimators.base import FitSetup, SnapshotEstimator, pad_rows, resolve_lifting
from qube_koopman.identify._checks import check_alpha
from qube_koopman.identify.models.model import KoopmanModel
from qube_koopman.identify.estimators.regression import Snapshots, ridge_solve
from qube_koopman.identify.data.trajectory import Trajectory, check_trajectories, episode_signals

__all__ = ["Edmd"]


class Edmd(SnapshotEstimator):
    """Extended dynamic mode decomposition of a plant: ``theta_{k+1} = A theta_k + B u_k``.

    Parameters
    ----------
    lifting : Lifting or sequence of LiftingFunction, optional
        Lifting of the states (identity when None).
    alpha : float
        Tikhonov coefficient on ``||U||_F^2`` against the un-normalized sum
        of squares.
    input_lifting : Lifting or sequence of LiftingFunction, optional
        Pointwise lifting of the inputs; inputs are not lifted by default.

    Attributes
    ----------
    model_ : KoopmanModel
        The identified plant.
    koopman_matrix_ : ndarray of shape (n_lifted, n_lifted + n_inputs)
        ``U = [A B]``.
    snapshots_ : Snapshots
        Snapshot statistics the fit used.
    """

    def __init__(self, lifting=None, alpha: float = 0.0, input_lifting=None) -> None:
        self.lifting = lifting
        self.alpha = alpha
        self.input_lifting = input_lifting

    def setup_fit(self, trajectories) -> FitSetup:
        """Validate the data, fit the state and input liftings: the first step of a fit.

        Parameters
        ----------
        trajectories : sequence of Trajectory
            The episodes (signals x, u).

        Returns
        -------
        FitSetup
            What every other step of the statistics protocol takes.
        """
        check_alpha(self.alpha)
        lifting = resolve_lifting(self.lifting)
        trajs = check_trajectories(trajectories, ("x", "u"), lifting.n_delays + 2, "EDMD")
        lifting.fit(episode_signals(trajs, "x"), trajs[0].state_names)
        input_lifting = None
        if self.input_lifting is not None:
            input_lifting = resolve_lifting(self.input_lifting).fit(episode_signals(trajs, "u"), trajs[0].input_names)
            if input_lifting.n_delays_:
                raise ValueError("input lifting must be pointwise (no delays)")
        return FitSetup(trajs, lifting, trajs[0].dt, input_lifting=input_lifting)

    def episode_snapshots(self, setup: FitSetup, t: Trajectory) -> Snapshots:
        """Snapshot statistics of one episode: theta = lift(x), input u (lifted if asked).

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
        z = setup.lifting.transform(t.x)
        assert t.u is not None  # setup_fit's check_trajectories required it
        v = (t.u if setup.input_lifting is None else setup.input_lifting.transform(t.u))[d:]
        return Snapshots.from_snapshots(z[1:, : setup.target_rows], np.hstack([z[:-1], v[:-1]]))

    def relift_rows(self, setup: FitSetup) -> int:
        """The measured states: a re-lifted prediction recomputes the rest (see the base class)."""
        return setup.lifting.n_features_in_

    def finish_fit(self, setup: FitSetup, snapshots: Snapshots) -> "Edmd":
        """Solve for ``self.alpha`` and set the fitted attributes.

        Parameters
        ----------
        setup : FitSetup
            From :meth:`setup_fit`.
        snapshots : Snapshots
            A fold's ``total()``.

        Returns
        -------
        self
        """
        n_z = setup.lifting.n_features_out_
        U = pad_rows(ridge_solve(snapshots, check_alpha(self.alpha)), n_z)  # a partial fit's missing rows
        self.snapshots_ = snapshots
        self.koopman_matrix_ = U
        self.model_ = KoopmanModel(
            U[:, :n_z], U[:, n_z:], setup.lifting, ("u",), input_lifting=setup.input_lifting, dt=setup.dt
        )
        return self

    def predict(self, trajectory: Trajectory, relift: bool = True) -> np.ndarray:
        """Predicted plant states of one episode (see :meth:`KoopmanModel.predict`)."""
        self._check_fitted()
        return self.model_.predict(trajectory, relift=relift)
