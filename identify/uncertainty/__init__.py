"""Prediction intervals: how far to trust each predicted sample of an episode.

The method is described in :mod:`~qube_koopman.identify.uncertainty.bands`; the modules are its
steps: the bootstrap ensemble (``ensemble``), the loops that predict the episodes (``loops``), the
ensemble's predictions and their spread (``prediction``), the model error's calibration
(``calibration``), the bands (``bands``), what a design needs of them (``held_out``), and the
held-out error's spectra that ``qube-design`` propagates (``spectra``). This package only
re-exports their names.
"""

from __future__ import annotations

from qube_koopman.identify.uncertainty.bands import BandSummary, PredictionBand, prediction_band, summarize_bands
from qube_koopman.identify.uncertainty.calibration import (
    REPORTED_HORIZONS,
    CalibrationOptions,
    IntervalCalibration,
    calibrate,
    calibrate_on_probes,
    calibrate_on_probe_sets,
    widest,
)
from qube_koopman.identify.uncertainty.ensemble import (
    EnsembleFit,
    FoldEnsemble,
    IntervalOptions,
    bootstrap_counts,
    ensemble_statistics,
    episode_folds,
    fit_ensemble,
)
from qube_koopman.identify.uncertainty.held_out import (
    held_out_figures,
    held_out_loops,
    loop_figures,
    loops_figures,
    references,
)
from qube_koopman.identify.uncertainty.loops import Loop, consecutive_runs
from qube_koopman.identify.uncertainty.prediction import (
    OFFSET_STEP,
    EpisodePrediction,
    predict_episodes,
    predict_groups,
)

__all__ = [
    "OFFSET_STEP",
    "REPORTED_HORIZONS",
    "BandSummary",
    "CalibrationOptions",
    "EnsembleFit",
    "EpisodePrediction",
    "FoldEnsemble",
    "IntervalCalibration",
    "IntervalOptions",
    "Loop",
    "PredictionBand",
    "bootstrap_counts",
    "calibrate",
    "calibrate_on_probes",
    "calibrate_on_probe_sets",
    "consecutive_runs",
    "widest",
    "ensemble_statistics",
    "episode_folds",
    "fit_ensemble",
    "held_out_figures",
    "held_out_loops",
    "loops_figures",
    "references",
    "loop_figures",
    "predict_episodes",
    "predict_groups",
    "prediction_band",
    "summarize_bands",
]
