"""Fitted Koopman models: linear dynamics on lifted states, with prediction."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Mapping, Sequence

import numpy as np

from qube_koopman.identify.lifting import Lifting
from qube_koopman.identify.data.trajectory import Trajectory
from qube_koopman.core.lti import spectral_radius

__all__ = ["KoopmanModel", "FittedRows"]


@dataclass(frozen=True, eq=False)
class KoopmanModel:
    """``z_{k+1} = A z_k + B v_k`` on the lifted state ``z = [p; lift(x history)]``.

    ``p`` are ``n_passthrough`` states that are not lifted (the controller
    state of a closed-loop model), ``x`` the measured plant states and ``v``
    the exogenous input built from the trajectory signals ``input_signals``
    (``("u",)`` for a plant, ``("r", "f")`` for a closed loop).

    Parameters
    ----------
    A : ndarray of shape (n_lifted, n_lifted)
    B : ndarray of shape (n_lifted, n_inputs)
    lifting : Lifting
        Fitted lifting of the plant states.
    input_signals : tuple of str
        Trajectory attributes stacked (in order) into ``v``.
    n_passthrough : int
        Leading states that are not lifted.
    input_lifting : Lifting, optional
        Fitted pointwise lifting of the inputs.
    dt : float, optional
        Sample period in seconds.
    passthrough_names : tuple of str
        Names of the passthrough states.
    feedback : tuple of int
        For a closed-loop model: the measured state each reference channel
        is compared with (``C^p``); empty means states ``0..n_r-1``.
    """

    A: np.ndarray
    B: np.ndarray
    lifting: Lifting
    input_signals: tuple[str, ...]
    n_passthrough: int = 0
    input_lifting: Lifting | None = None
    dt: float | None = None
    passthrough_names: tuple[str, ...] = ()
    feedback: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        A = np.asarray(self.A, dtype=float)
        B = np.asarray(self.B, dtype=float)
        n_z = self.n_passthrough + self.lifting.n_features_out_
        if A.shape != (n_z, n_z) or B.shape[0] != n_z:
            raise ValueError(f"A {A.shape} and B {B.shape} do not fit {n_z} lifted states")
        object.__setattr__(self, "A", A)
        object.__setattr__(self, "B", B)
        if not self.passthrough_names:
            object.__setattr__(self, "passthrough_names", tuple(f"xc{i}" for i in range(self.n_passthrough)))

    # --- structure -----------------------------------------------------------------
    @property
    def n_delays(self) -> int:
        """Samples of history the lifting needs before the first prediction."""
        return self.lifting.n_delays_

    @property
    def n_states(self) -> int:
        """Number of measured (original) plant states."""
        return self.lifting.n_features_in_

    @property
    def state_names(self) -> tuple[str, ...]:
        """Name of every lifted state."""
        return tuple(self.passthrough_names) + tuple(self.lifting.feature_names_out_)

    @property
    def koopman_matrix(self) -> np.ndarray:
        """``U = [A B]``."""
        return np.hstack([self.A, self.B])

    @property
    def C(self) -> np.ndarray:
        """Output matrix picking the original plant states out of the lifted state."""
        C = np.zeros((self.n_states, self.A.shape[0]))
        C[:, self.n_passthrough : self.n_passthrough + self.n_states] = np.eye(self.n_states)
        return C

    @property
    def D(self) -> np.ndarray:
        """Zero feedthrough."""
        return np.zeros((self.n_states, self.B.shape[1]))

    def eigenvalues(self) -> np.ndarray:
        """Eigenvalues of ``A``."""
        return np.linalg.eigvals(self.A)

    def spectral_radius(self) -> float:
        """Largest eigenvalue magnitude of ``A``; above 1 the model is unstable."""
        return spectral_radius(self.A)

    def to_state_space(self):
        """The model as a discrete ``control.StateSpace`` (outputs: the original states)."""
        import control  # lazily: python-control imports matplotlib

        return control.ss(self.A, self.B, self.C, self.D, self.dt if self.dt is not None else True)

    # --- prediction ----------------------------------------------------------------
    def inputs_of(self, trajectory: Trajectory) -> np.ndarray:
        """The exogenous input ``v`` of a trajectory (lifted when the model lifts inputs)."""
        parts = []
        for key in self.input_signals:
            value = getattr(trajectory, key)
            if value is None:
                raise ValueError(f"trajectory {trajectory.name!r} lacks signal {key!r} the model needs")
            parts.append(value)
        v = np.hstack(parts) if parts else np.zeros((trajectory.n_samples, 0))
        if self.input_lifting is not None:
            v = self.input_lifting.transform(v)
        if v.shape[1] != self.B.shape[1]:
            raise ValueError(
                f"trajectory {trajectory.name!r} gives {v.shape[1]} inputs, the model takes {self.B.shape[1]}"
            )
        return v

    def predict(
        self,
        trajectory: Trajectory,
        relift: bool = True,
        offsets: Mapping[int, float] | Sequence[int | str] | None = None,
        window: int | None = None,
    ) -> np.ndarray:
        """Predict the plant states of one episode from its initial condition and inputs.

        The first ``n_delays + 1`` samples are the initial condition (copied);
        the rest is predicted. A diverging prediction yields non-finite values.

        Parameters
        ----------
        trajectory : Trajectory
            Episode giving the initial states, the inputs and (closed loop)
            the initial controller state.
        relift : bool
            Re-lift the predicted original state at every step (default, as
            the reference code) or propagate the lifted state linearly.
        offsets : mapping or sequence, optional
            Per-episode sensor offsets (measured = true + offset), see
            :mod:`identify.models.offsets`: a mapping ``{channel: value}`` of known
            offsets, or channels (indices or state names such as
            ``"alpha"``) whose offsets are estimated from the first
            ``window`` samples. An implausible estimate (beyond
            :data:`identify.models.offsets.DEFAULT_BOUND`) is not used, with an
            :class:`~identify.models.offsets.OffsetWarning`.
        window : int, optional
            Samples of the estimation window (needed when estimating).

        Returns
        -------
        ndarray of shape (n_samples, n_states)
            The measured states (offsets added back).
        """
        if offsets is not None:
            from qube_koopman.identify.models import offsets as off

            if isinstance(offsets, Mapping):
                known = {
                    c: float(v)
                    for c, v in zip(
                        off.resolve_channels(list(offsets), trajectory.state_names, self.n_states), offsets.values()
                    )
                }
                return off.predict_with_offsets(self, trajectory, known, relift)
            if window is None:
                raise ValueError("estimating offsets needs window (samples from the start)")
            return off.predict_estimating_offsets(self, trajectory, offsets, window, relift=relift)[0]
        return self.predict_many([trajectory], relift=relift)[0]

    def check_trajectory(self, trajectory: Trajectory) -> None:
        """Refuse (ValueError naming it) a trajectory this model cannot predict: too short, other states, no
        controller state where the model has one."""
        self._initial_passthrough(trajectory)

    def _initial_passthrough(self, trajectory: Trajectory) -> np.ndarray | None:
        """Check that ``trajectory`` can be predicted; its controller state at sample ``n_delays``."""
        d = self.n_delays
        if trajectory.n_samples < d + 2:
            raise ValueError(
                f"trajectory {trajectory.name!r} has {trajectory.n_samples} samples; prediction needs at least {d + 2}"
            )
        if trajectory.x.shape[1] != self.n_states:
            raise ValueError(
                f"trajectory {trajectory.name!r} has {trajectory.x.shape[1]} states, the model {self.n_states}"
            )
        if not self.n_passthrough:
            return None
        if trajectory.xc is None or trajectory.xc.shape[1] != self.n_passthrough:
            raise ValueError(
                f"trajectory {trajectory.name!r} needs a controller state of {self.n_passthrough} channels"
            )
        return trajectory.xc[d]

    def simulate(
        self, x_init: np.ndarray, v: np.ndarray, p0: np.ndarray | None = None, relift: bool = True
    ) -> tuple[np.ndarray, np.ndarray]:
        """Prediction from arrays for one or several episodes.

        Parameters
        ----------
        x_init : ndarray of shape ([n_episodes,] n_delays + 1, n_states)
            Initial history of the plant states.
        v : ndarray of shape ([n_episodes,] n_samples, n_inputs)
            Input at every sample (the first ``n_delays`` are not used).
        p0 : ndarray of shape ([n_episodes,] n_passthrough), optional
            Passthrough (controller) state at sample ``n_delays``.
        relift : bool
            Re-lift at every step, or propagate linearly.

        Returns
        -------
        x : ndarray of shape ([n_episodes,] n_samples, n_states)
        p : ndarray of shape ([n_episodes,] n_samples, n_passthrough)
            NaN before sample ``n_delays``.
        """
        from qube_koopman.identify.models.simulate import simulate_batch

        v = np.asarray(v, dtype=float)
        single = v.ndim == 2
        if single:
            x_init, v = np.asarray(x_init)[None], v[None]
            p0 = None if p0 is None else np.asarray(p0)[None]
        x, p = simulate_batch(
            self.A[None],
            self.B[None],
            self.lifting,
            self.n_passthrough,
            np.asarray(x_init, dtype=float),
            v,
            p0,
            relift=relift,
        )
        return (x[0, 0], p[0, 0]) if single else (x[0], p[0])

    def predict_many(self, trajectories: Sequence[Trajectory], relift: bool = True) -> list[np.ndarray]:
        """:meth:`predict` for several episodes, simulated together (one batch per episode length).

        The same numbers as one :meth:`predict` each, in one pass over the
        samples instead of one per episode.
        """
        trajectories = list(trajectories)
        p0s = [self._initial_passthrough(t) for t in trajectories]
        out: dict[int, np.ndarray] = {}
        by_length: dict[int, list[int]] = {}
        for i, t in enumerate(trajectories):
            by_length.setdefault(t.n_samples, []).append(i)
        d = self.n_delays
        for group in by_length.values():
            given = [p for p in (p0s[i] for i in group) if p is not None]  # all, or none without passthrough
            p0 = np.stack(given) if given else None
            x, _ = self.simulate(
                np.stack([trajectories[i].x[: d + 1] for i in group]),
                np.stack([self.inputs_of(trajectories[i]) for i in group]),
                p0,
                relift=relift,
            )
            for j, i in enumerate(group):
                out[i] = x[j]
        return [out[i] for i in range(len(trajectories))]


@dataclass(frozen=True)
class FittedRows:
    """The fitted rows of a partially fitted :class:`KoopmanModel`, and what rebuilds the model.

    A sweep that only ranks liftings fits the rows re-lifted predictions use (the others NaN:
    4 rows of 370 on a 40-delay search lifting); these are a few kilobytes where the model's
    matrices are megabytes, so a search can keep them to predict with the same model again.

    Parameters
    ----------
    A, B : ndarray
        The model's leading rows up to its first unfitted (NaN) one.
    n_rows : int
        The model's number of lifted states (the rows of ``A``).
    settings : dict
        The model's other fields but its lifting (given back to :meth:`model`).
    """

    A: np.ndarray
    B: np.ndarray
    n_rows: int
    settings: dict

    @classmethod
    def of(cls, model: KoopmanModel) -> "FittedRows":
        """The fitted rows of ``model`` (all of them when it is fully fitted)."""
        unfitted = np.flatnonzero(~np.isfinite(model.A).all(axis=1))
        k = int(unfitted[0]) if unfitted.size else model.A.shape[0]
        settings = {f.name: getattr(model, f.name) for f in fields(model) if f.name not in ("A", "B", "lifting")}
        return cls(model.A[:k].copy(), model.B[:k].copy(), model.A.shape[0], settings)

    def model(self, lifting: Lifting) -> KoopmanModel:
        """The model again, its unfitted rows NaN, with ``lifting`` (the fitted one it had)."""
        A = np.full((self.n_rows, self.A.shape[1]), np.nan)
        B = np.full((self.n_rows, self.B.shape[1]), np.nan)
        A[: self.A.shape[0]], B[: self.B.shape[0]] = self.A, self.B
        return KoopmanModel(A, B, lifting, **self.settings)
