"""A model file as one typed object: what ``qube-identify`` fitted, for every reader of ``model.json``.

:func:`~qube_koopman.identify.models.model_file.load_model` returns an :class:`IdentifiedModel`;
``qube-design``, the benchmarks and the tests read its attributes, never the file's keys.
:meth:`IdentifiedModel.save` writes it back as the same file, byte for byte.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from qube_koopman.core.lti import DiscreteStateSpace
from qube_koopman.identify.lifting import Lifting
from qube_koopman.identify.models.model import KoopmanModel

if TYPE_CHECKING:  # only for annotations: the model file's reader imports them when a file holds them
    from qube_koopman.identify.models.disturbance import DisturbanceModel
    from qube_koopman.identify.uncertainty.spectra import ErrorSpectra

__all__ = ["IdentifiedModel", "FitUncertainty", "HeldOutFigures"]


@dataclass(frozen=True, eq=False)
class HeldOutFigures:
    """The training episodes the intervals' calibration held out: their figures, measured and predicted.

    Each was predicted in closed loop under its own controller by the fit on the other episodes.

    Parameters
    ----------
    measured : ndarray of shape (n, 3)
        ``[J, voltage RMS, voltage peak]`` of each episode as logged, after ``skip_samples``
        (:func:`qube_koopman.core.qube.loop_cost` is J); inf where a figure is not finite.
    predicted : ndarray of shape (n, 3)
        The same figures of each episode's prediction.
    skip_samples : int
        Samples left out at each episode's start.
    logs : tuple of str or None
        The episodes' names (None when the file does not name them).
    error_spectra : ErrorSpectra or None
        Their prediction error's band spectra, which ``qube-design`` propagates through a designed
        loop (None in a file written without them).
    """

    measured: np.ndarray
    predicted: np.ndarray
    skip_samples: int
    logs: tuple[str, ...] | None = None
    error_spectra: ErrorSpectra | None = None

    @property
    def n_episodes(self) -> int:
        """Held-out episodes."""
        return len(self.measured)


@dataclass(frozen=True, eq=False)
class FitUncertainty:
    """A model file's ``uncertainty``: the plant's bootstrap refits and the calibration's held-out figures.

    Parameters
    ----------
    plant_members : tuple of KoopmanModel
        The plant's episode-bootstrap refits (the fit repeated on the training episodes drawn with
        replacement); the rows past the measured states are the plant's (a re-lifted prediction uses
        only the measured rows). Empty when the file holds none.
    held_out : HeldOutFigures or None
        The held-out training episodes' figures (None when the file holds none).
    seed : int or None
        The resampling's seed.
    method : str
        How the members were drawn (``"episode bootstrap"``).
    """

    plant_members: tuple[KoopmanModel, ...]
    held_out: HeldOutFigures | None
    seed: int | None
    method: str = "episode bootstrap"


@dataclass(frozen=True, eq=False)
class IdentifiedModel:
    """A fitted Koopman model as its model file holds it (MODEL_FORMAT.md).

    Parameters
    ----------
    method : str or None
        The identification method (``qube-identify --method``: ``"cl-edmd"``, ``"edmd"``, ...).
    alpha : float or None
        The Tikhonov coefficient of the fit (None for a method without one).
    dt : float
        The sample period (s).
    lifting : Lifting
        The fitted lifting (the plant's and the closed loop's).
    measured : tuple of int
        The plant states fed back to the controller (``C^p``).
    plant : KoopmanModel
        The plant model (input ``u``).
    closed_loop : KoopmanModel or None
        The closed-loop model (inputs ``r``, ``f``), if the method identified one.
    controller : DiscreteStateSpace or None
        The training controller, whose loop ``closed_loop`` is (input: the tracking error).
    training : dict or None
        What the model was fitted on, as the file stores it (``logs``: the training logs' names).
    uncertainty : FitUncertainty or None
        The fit's bootstrap plants and held-out figures (None when identified with ``--interval 0``).
    disturbance : DisturbanceModel or None
        The disturbance model and its Kalman filter's gain (``qube-identify --horizon``), if any.
    """

    method: str | None
    alpha: float | None
    dt: float
    lifting: Lifting
    measured: tuple[int, ...]
    plant: KoopmanModel
    closed_loop: KoopmanModel | None
    controller: DiscreteStateSpace | None
    training: dict[str, Any] | None
    uncertainty: FitUncertainty | None = None
    disturbance: DisturbanceModel | None = None

    @property
    def plant_members(self) -> tuple[KoopmanModel, ...] | None:
        """The uncertainty's bootstrap plants (:attr:`FitUncertainty.plant_members`), None when the file holds none."""
        if self.uncertainty is None or not self.uncertainty.plant_members:
            return None
        return self.uncertainty.plant_members

    def save(self, path: str | Path) -> None:
        """Write the model file again (:func:`~qube_koopman.identify.models.model_file.save_model`), atomically.

        A model :func:`~qube_koopman.identify.models.model_file.load_model` read from a file
        ``save_model`` wrote is written back byte for byte.

        Parameters
        ----------
        path : str or Path
            The file to write (replaced if it exists).
        """
        from qube_koopman.identify.models.model_file import save_model, uncertainty_to_dict

        uncertainty = None
        u = self.uncertainty
        if u is not None:
            held = u.held_out
            uncertainty = uncertainty_to_dict(
                self.plant,
                list(u.plant_members),
                None if held is None else np.stack([held.measured, held.predicted], axis=1),
                seed=u.seed,
                skip=None if held is None else held.skip_samples,
                logs=None if held is None or held.logs is None else list(held.logs),
                spectra=None if held is None or held.error_spectra is None else held.error_spectra.as_dict(),
                method=u.method,
            )
        save_model(
            path,
            method=self.method,
            alpha=self.alpha,
            plant=self.plant,
            closed_loop=self.closed_loop,
            controller=self.controller,
            measured=list(self.measured),
            training=self.training,
            uncertainty=uncertainty,
            disturbance=self.disturbance,
        )
