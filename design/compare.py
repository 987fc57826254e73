"""Episodes run under a designed controller against what its design predicted: what ``qube-compare`` prints.

A controller file ``qube-design`` wrote names, in its ``[provenance]``, the model file it was designed
on and the LQ weights. :func:`compare_runs` designs it again from them (the same matrices, or it says
the file and the model no longer agree), predicts the plant model under it on exactly the logged
episodes' excitations (regenerated from the seeds and settings each log records,
:func:`~qube_koopman.design.predict.predict_cost`), with the interval of the design's level from the
model file's bootstrap plants and held-out error (:func:`~qube_koopman.design.uncertainty.interval_from_logs`),
and scores the logs with the same definition of the figures
(:func:`~qube_koopman.design.predict.episode_cost`, pooled as
:meth:`~qube_koopman.design.predict.CostPrediction.summary` pools them). Episodes the safety supervisor
stopped are left out of both and counted.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from qube_koopman.core.controller_file import STATE_SPACE_KIND, ControllerInfo, load_controller
from qube_koopman.core.lti import same_system
from qube_koopman.daq.excitation import Excitation, ExcitationSettings, generate_excitation
from qube_koopman.daq.log import read_episode
from qube_koopman.daq.log.names import SEED_SIGNALS
from qube_koopman.design.lq import LqDesign, Weights, design_lq
from qube_koopman.design.plant import DesignError, linear_plant
from qube_koopman.design.predict import CostPrediction, episode_cost, predict_cost
from qube_koopman.design.uncertainty import FigureInterval, interval_from_logs, model_uncertainty
from qube_koopman.identify.models.identified import IdentifiedModel

__all__ = ["FIGURES", "RunComparison", "compare_runs", "comparison_text"]

#: The figures compared: name, label, format. J and the voltage's RMS have the design's interval; the
#: tracking RMS has none (the interval is not made for it) and is compared with the point prediction only.
FIGURES = (
    ("J", "J (rad^2)", ".3e"),
    ("tracking_rms", "tracking RMS (rad)", ".4f"),
    ("voltage_rms", "voltage RMS (V)", ".3f"),
)


@dataclass(frozen=True, eq=False)
class RunComparison:
    """What the logs measured beside what the design predicts for the same excitations.

    Parameters
    ----------
    controller_path : Path
        The controller file.
    model_path : Path
        The model file it was designed on (and predicted with again).
    logs : tuple of Path
        The episodes compared (complete ones).
    skipped : tuple of (Path, str)
        Logs left out, with their status (an episode the safety supervisor stopped has no figures).
    measured : dict
        ``CostPrediction.summary()`` of the logs.
    predicted : dict
        The same of the plant model under the controller on the logs' excitations.
    interval : FigureInterval or None
        The predicted figures' interval at the design's level; None when the design had none.
    design_excitation : bool
        Whether the logs ran the excitation the design predicted on (``qube-design --seed``, ``--episodes``,
        ``--duration``), every episode of it: then ``predicted`` is the provenance's prediction again.
    """

    controller_path: Path
    model_path: Path
    logs: tuple[Path, ...]
    skipped: tuple[tuple[Path, str], ...]
    measured: dict
    predicted: dict
    interval: FigureInterval | None
    design_excitation: bool

    def inside(self, figure: str) -> bool | None:
        """Whether the measured ``figure`` lies within the interval (None: no interval for it)."""
        if self.interval is None or figure not in self.interval.lower:
            return None
        return self.interval.contains(figure, self.measured[figure])


def _designed_controller(path: Path) -> tuple[ControllerInfo, dict]:
    """The controller file and its provenance; a DesignError naming it when qube-design did not write it."""
    try:
        info = load_controller(path)
    except ValueError as exc:
        raise DesignError(str(exc)) from None
    p = dict(info.provenance)
    if info.kind != STATE_SPACE_KIND:
        what = "PD gains" if info.kind == "pd" else f"a controller of kind {info.kind!r}"
        raise DesignError(
            f"{path}: {what}; the comparison predicts an LQ design qube-design wrote (kind {STATE_SPACE_KIND!r})"
        )
    if not str(p.get("designed_by", "")).startswith("qube-design") or not {"model", "weights"} <= set(p):
        raise DesignError(f"{path}: its [provenance] names no qube-design model and weights: not a designed controller")
    return info, p


def _model(provenance: dict, controller_path: Path, model: str | Path | None) -> tuple[Path, IdentifiedModel]:
    """The model file the design names (as written, else beside the controller file), or ``model``."""
    from qube_koopman.identify.models.model_file import load_model

    if model is not None:
        candidates = [Path(model)]
    else:
        named = Path(str(provenance["model"]))
        candidates = [named] + ([controller_path.parent / named] if not named.is_absolute() else [])
    for candidate in candidates:
        path = candidate / "model.json" if candidate.is_dir() else candidate
        if path.is_file():
            try:
                return path, load_model(path)
            except ValueError as exc:
                raise DesignError(str(exc)) from None
    if model is not None:
        raise DesignError(f"{model}: no such model file (--model)")
    raise DesignError(
        f"{controller_path}: its model file {candidates[0]} is not there (nor beside the controller file); give "
        "it with --model"
    )


def _redesign(info: ControllerInfo, provenance: dict, controller_path: Path, model_path: Path, model: IdentifiedModel):
    """The design again from the model and the provenance's weights; it must give the file's matrices."""
    plant_model = model.plant  # a model file without a plant is refused as it loads
    try:
        weights = Weights(**provenance["weights"])
        plant = linear_plant(plant_model)
        design = design_lq(plant, weights)
    except (DesignError, TypeError) as exc:
        raise DesignError(f"{controller_path}: its design cannot be made again from {model_path}: {exc}") from None
    if not same_system(design.controller, info.system):
        raise DesignError(
            f"{controller_path}: designed again from {model_path} with its weights, it is another controller: the "
            "model file is not the one it was designed on"
        )
    return plant_model, plant, design


def _episodes(paths: Sequence[Path], info: ControllerInfo, controller_path: Path):
    """The complete episodes (each checked to have run ``info``), their excitations, and the logs skipped."""
    episodes, excitations, kept, skipped = [], [], [], []
    for path in paths:
        try:
            episode = read_episode(path, warn=False)
        except OSError as exc:
            raise DesignError(f"{path}: cannot read the episode log ({exc.strerror or exc})") from None
        except ValueError as exc:
            raise DesignError(f"{path}: cannot read the episode log ({str(exc).removeprefix(f'{path}: ')})") from None
        meta = episode.metadata
        if not same_system(meta.controller.system, info.system):
            raise DesignError(
                f"{path}: recorded under another controller ({meta.controller.kind}, "
                f"{meta.controller.system.n_states} states), not {controller_path}"
            )
        seeds = meta.excitation.get("seeds", {})
        if not all(isinstance(seeds.get(k), int) for k in SEED_SIGNALS):
            raise DesignError(f"{path}: the log records no excitation seeds: its excitation cannot be predicted")
        if meta.status != "complete":
            skipped.append((path, meta.status))
            continue
        settings = meta.excitation.get("settings")
        try:
            settings = ExcitationSettings() if settings is None else ExcitationSettings.from_dict(settings)
        except (TypeError, ValueError) as exc:
            raise DesignError(f"{path}: its excitation settings cannot be used ({exc})") from None
        a, b, c = (int(seeds[k]) for k in SEED_SIGNALS)
        excitation = generate_excitation((a, b, c), settings)
        if len(excitation.target_theta) != len(episode.theta):
            raise DesignError(f"{path}: {len(episode.theta)} samples, its excitation {len(excitation.target_theta)}")
        episodes.append(episode)
        excitations.append(excitation)
        kept.append(path)
    if not kept:
        raise DesignError(f"no complete episode among the {len(paths)} logs: nothing to compare")
    return episodes, excitations, kept, skipped


def _is_design_excitation(excitations: list[Excitation], provenance: dict) -> bool:
    """Whether ``excitations`` are, in order, those the design predicted on (``qube-design --seed --episodes``)."""
    from qube_koopman.design.predict import rig_excitations

    ex = provenance.get("excitation", {})
    try:
        theirs = rig_excitations(int(ex["seed"]), int(ex["episodes"]), float(ex["duration"]))
    except (KeyError, TypeError, ValueError):
        return False
    return len(theirs) == len(excitations) and all(
        np.array_equal(a.target_theta, b.target_theta) and np.array_equal(a.feedforward, b.feedforward)
        for a, b in zip(theirs, excitations)
    )


def compare_runs(
    controller: str | Path, logs: Sequence[str | Path], *, model: str | Path | None = None
) -> RunComparison:
    """Compare episodes run under a designed controller with the design's prediction on the same excitations.

    Parameters
    ----------
    controller : str or Path
        A controller file ``qube-design`` wrote (kind state-space, with its ``[provenance]``).
    logs : sequence of str or Path
        Episode logs recorded under it (``qube-run --controller``).
    model : str or Path, optional
        The model file designed on, when not where the provenance says (a path relative to where
        ``qube-design`` ran, then to the controller file's folder).

    Returns
    -------
    RunComparison

    Raises
    ------
    DesignError
        One line naming the file: not a designed controller, the model missing or not the one designed on, a
        log unreadable or recorded under another controller, no complete episode.
    """
    controller_path = Path(controller)
    info, provenance = _designed_controller(controller_path)
    paths = [Path(p) for p in logs]
    episodes, excitations, kept, skipped = _episodes(paths, info, controller_path)
    model_path, model_data = _model(provenance, controller_path, model)
    plant_model, plant, design = _redesign(info, provenance, controller_path, model_path, model_data)
    predicted = predict_cost(plant_model, design.controller, excitations).summary()
    rows = np.array([episode_cost(e.theta, e.target_theta, e.alpha, e.plant_input) for e in episodes])
    J, tracking, alpha, voltage, peak = rows.T
    measured = CostPrediction(J, tracking, alpha, voltage, peak, diverged=int(np.sum(~np.isfinite(J)))).summary()
    interval = _interval(provenance, model_data, plant, design, predicted, excitations)
    return RunComparison(
        controller_path,
        model_path,
        tuple(kept),
        tuple(skipped),
        measured,
        predicted,
        interval,
        _is_design_excitation(excitations, provenance),
    )


def _interval(provenance: dict, model: IdentifiedModel, plant, design: LqDesign, predicted: dict, excitations):
    """The interval at the design's level on these excitations; None when the design had none."""
    level = provenance.get("interval", {}).get("level") if isinstance(provenance.get("interval"), dict) else None
    if level is None:
        return None
    uncertainty = model_uncertainty(model)
    if uncertainty is None:
        return None
    return interval_from_logs(uncertainty, plant, design, predicted, excitations, float(level))


def comparison_text(comparison: RunComparison) -> str:
    """The table ``qube-compare`` prints: each figure measured, predicted, its interval, and whether it is inside.

    Parameters
    ----------
    comparison : RunComparison

    Returns
    -------
    str
    """
    c, iv = comparison, comparison.interval
    n = len(c.logs)
    on = (
        "the excitation it was designed on"
        if c.design_excitation
        else "the logs' excitations (not the design's: its provenance's figures are for another run)"
    )
    lines = [
        f"controller {c.controller_path}: designed on {c.model_path}, designed again from it: the same matrices",
        f"{n} episode{'s' if n != 1 else ''} compared, after the first second, predicted by the model on {on}",
    ]
    if c.skipped:
        statuses = ", ".join(sorted({status for _, status in c.skipped}))
        lines.append(f"  left out: {len(c.skipped)} episodes not complete ({statuses}), in neither column")
    level = f"{100 * iv.level:g} % interval" if iv is not None else "interval"
    lines.append(f"  {'figure':<19} {'measured':>10} {'predicted':>10} {'with error':>10}   {level:<24} inside")
    for name, label, fmt in FIGURES:
        span, expected = "-", "-"
        if iv is not None and name in iv.lower:
            span = f"{iv.lower[name]:{fmt}} to {iv.upper[name]:{fmt}}"
            if iv.n_held_out:
                expected = f"{iv.expected[name]:{fmt}}"
        inside = {None: "-", True: "yes", False: "no"}[c.inside(name)]
        lines.append(
            f"  {label:<19} {c.measured[name]:>10{fmt}} {c.predicted[name]:>10{fmt}} {expected:>10}   "
            f"{span:<24} {inside}"
        )
    lines.append(
        "  (predicted: the point model; with error: with the model's error on held-out episodes, which the "
        "interval is around)"
        if iv is not None
        else "  (no interval: the design asked for none, or its model file keeps no bootstrap plants)"
    )
    ratio = c.measured["J"] / c.predicted["J"] - 1 if c.predicted["J"] > 0 else float("nan")
    lines.append(f"measured J {100 * ratio:+.1f} % against the prediction")
    return "\n".join(lines)
