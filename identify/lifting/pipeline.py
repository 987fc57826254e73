"""The lifting-function contract and the pipeline that composes them."""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from collections.abc import Sequence

import numpy as np

from qube_koopman.identify.params import Params

__all__ = ["LiftingFunction", "Lifting"]


class LiftingFunction(Params, ABC):
    """One lifting step: maps a window of feature vectors to new features.

    Hyperparameters live in the constructor, stored unchanged (``get_params``,
    ``set_params``); :meth:`fit` checks them and learns from training episodes,
    setting attributes ending in ``_``. A step that uses
    the past consumes ``n_delays`` samples at the start of each episode.
    Every step keeps its input features first, so the first lifted features
    are always the original states.
    """

    n_delays: int = 0

    @property
    def affine(self) -> bool:
        """Whether the output is an affine function of the input window (delays, a constant, degree-1
        monomials). A model on an affine lifting predicts affinely, re-lifted or not, so its K-step
        predictions are a filter of the measurements (:mod:`~qube_koopman.identify.models.disturbance`).
        Conservative default False; steps that are affine set it True."""
        return False

    @property
    def learns_from_data(self) -> bool:
        """Whether the output depends on the training data (then refit on every fold). Conservative
        default True; steps whose output depends on hyperparameters only set it False."""
        return True

    def fit(self, episodes: Sequence[np.ndarray], names: Sequence[str]) -> "LiftingFunction":
        """Learn from training episodes (each of shape (n_samples, n_features_in)).

        Returns
        -------
        self
        """
        self._check_params()
        names = tuple(names)
        self.n_features_in_ = len(names)
        self.feature_names_in_ = names
        self._fit(episodes)
        self.feature_names_out_ = tuple(self._names_out(names))
        self.n_features_out_ = len(self.feature_names_out_)
        return self

    def _check_params(self) -> None:
        """Raise a ValueError naming a hyperparameter that cannot be used; none to check by default."""

    def _fit(self, episodes: Sequence[np.ndarray]) -> None:
        """Learn what the step needs; nothing by default.

        ``episodes`` may be lifted only when each is asked for (:class:`Lifting` passes a lazy
        sequence): a step that learns from the data reads them one at a time.
        """

    @abstractmethod
    def _names_out(self, names: tuple[str, ...]) -> list[str]:
        """Names of the output features."""

    @abstractmethod
    def transform(self, X: np.ndarray) -> np.ndarray:
        """Lift ``X`` of shape (..., n_samples, n_features_in).

        Returns an array of shape (..., n_samples - n_delays, n_features_out).
        Leading dimensions are independent episodes (batched prediction).
        """


class Lifting(Params):
    """Lifting functions applied in order, fitted on training episodes only.

    Parameters
    ----------
    steps : sequence of LiftingFunction
        Applied first to last; empty means identity (no lifting).

    Attributes
    ----------
    steps_ : list of LiftingFunction
        Fitted copies of ``steps`` (the constructor's objects stay untouched).
    n_delays_ : int
        Samples consumed at the start of each episode (sum over steps).
    feature_names_out_ : tuple of str
        Readable name of every lifted state.
    """

    def __init__(self, steps: Sequence[LiftingFunction] = ()) -> None:
        self.steps = steps

    def _check_steps(self) -> None:
        """Every step is a LiftingFunction whose hyperparameters can be used (else a ValueError)."""
        for step in self.steps:
            if not isinstance(step, LiftingFunction):
                raise ValueError(f"lifting step {step!r} is not a LiftingFunction")
            step._check_params()

    @property
    def affine(self) -> bool:
        """Whether every step is affine (:attr:`LiftingFunction.affine`): then so is the lifting."""
        return all(step.affine for step in self.steps)

    @property
    def n_delays(self) -> int:
        """Samples the steps consume at the start of each episode (known before fitting; the steps checked)."""
        self._check_steps()
        return sum(step.n_delays for step in self.steps)

    def fit(self, episodes: Sequence[np.ndarray], names: Sequence[str] | None = None) -> "Lifting":
        """Fit every step on the output of the previous one, episode by episode.

        Parameters
        ----------
        episodes : sequence of ndarray of shape (n_samples, n_states)
            Training episodes; no step ever sees two episodes joined.
        names : sequence of str, optional
            State names; ``x0, x1, ...`` by default.

        Returns
        -------
        self
        """
        self._check_steps()
        # Not copied into a list: the episodes may be read from their logs when asked for (a list of
        # every episode's states grows with the data, 72 MB at 448 episodes).
        episodes = episodes if isinstance(episodes, Sequence) else list(episodes)
        if not len(episodes):
            raise ValueError("lifting needs at least one training episode")
        n_states = np.shape(episodes[0])[1]
        names = tuple(names) if names is not None else tuple(f"x{i}" for i in range(n_states))
        if len(names) != n_states:
            raise ValueError(f"{len(names)} state names for {n_states} states")
        self.n_features_in_ = n_states
        self.feature_names_in_ = names
        self.steps_: list[LiftingFunction] = []
        for step in self.steps:
            # Each step sees the episodes lifted by the steps before it, one episode at a time: holding
            # them all (10000 x 250 features an episode) would grow memory with the data.
            fitted = copy.deepcopy(step).fit(_LiftedEpisodes(episodes, tuple(self.steps_)), names)
            self.steps_.append(fitted)
            names = fitted.feature_names_out_
        self.feature_names_out_ = tuple(names)
        self.n_features_out_ = len(names)
        self.n_delays_ = sum(step.n_delays for step in self.steps_)
        return self

    def transform(self, X: np.ndarray) -> np.ndarray:
        """Lift ``(..., n_samples, n_states)`` to ``(..., n_samples - n_delays_, n_features_out_)``."""
        X = np.asarray(X, dtype=float)
        if X.shape[-1] != self.n_features_in_:
            raise ValueError(f"lifting expects {self.n_features_in_} states, got {X.shape[-1]}")
        for step in self.steps_:
            X = step.transform(X)
        return X

    def __repr__(self) -> str:
        return f"Lifting({list(self.steps)!r})"


class _LiftedEpisodes(Sequence):
    """Episodes passed through fitted steps, each lifted when asked for and not kept."""

    def __init__(self, episodes: Sequence, steps: tuple) -> None:
        self._episodes = episodes
        self._steps = steps

    def __len__(self) -> int:
        return len(self._episodes)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        X = np.asarray(self._episodes[index], dtype=float)
        for step in self._steps:
            X = step.transform(X)
        return X
