"""From a model file to a controller file with its predicted figures: what ``qube-design`` does.

:func:`design_from_model` reads the model (``identify.models.model_file``), takes its plant as a shift
register of past measurements (:mod:`design.plant`), designs the LQ controller
(:mod:`design.lq`), checks the predicted closed loop and measures it (:mod:`design.predict`).
:func:`report_text` and :func:`provenance` say what was done, for the terminal and for the
controller file's ``[provenance]``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from qube_koopman.design.lq import LqDesign, Weights, design_lq
from qube_koopman.design.plant import IDENTIFY_FLAGS, DesignError, linear_plant
from qube_koopman.design.uncertainty import (
    NO_MEMBERS,
    FigureInterval,
    RobustChoice,
    interval_from_logs,
    model_uncertainty,
    robust_design,
)
from qube_koopman.design.predict import (
    VOLTAGE_LIMIT,
    CostPrediction,
    Margins,
    closed_loop_eigenvalues,
    closed_loop_matrix,
    loop_margins,
    predict_cost,
    predict_loop,
    rig_excitations,
)
from qube_koopman.core.controller import QUBE_SAMPLE_PERIOD
from qube_koopman.core.lti import DiscreteStateSpace, spectral_radius
from qube_koopman.identify.models.identified import IdentifiedModel

__all__ = [
    "DesignReport",
    "design_from_model",
    "report_text",
    "saturation_warning",
    "provenance",
    "record_design",
    "write_mpc",
    "offset_free_settings",
]


@dataclass(frozen=True, eq=False)
class DesignReport:
    """A design and what the model predicts of it.

    Parameters
    ----------
    model_path : Path
        The model file designed from.
    model : IdentifiedModel
        The model file as :func:`identify.models.model_file.load_model` reads it.
    design : LqDesign
        The design.
    spectral_radius : float
        Of the design plant in closed loop with the controller.
    open_loop_radius : float
        Of the design plant alone.
    margins : Margins
        At the plant input.
    predicted : CostPrediction
        The plant model under the designed controller on the rig's excitation.
    training : CostPrediction or None
        The same under the model file's (training) controller, for comparison.
    excitation : dict
        ``seed``, ``episodes``, ``duration`` of the excitation predicted on.
    interval : FigureInterval or None
        The predicted figures' interval (:mod:`design.uncertainty`); None when the model file
        gives none (``interval_note`` says why).
    interval_note : str or None
        Why there is no interval.
    robust : RobustChoice or None
        With ``robust``: what the robust design weighed.
    nominal : CostPrediction or None
        With ``robust``: the nominal design's prediction, for comparison.
    """

    model_path: Path
    model: IdentifiedModel
    design: LqDesign
    spectral_radius: float
    open_loop_radius: float
    margins: Margins
    predicted: CostPrediction
    training: CostPrediction | None
    excitation: dict
    interval: FigureInterval | None = None
    interval_note: str | None = None
    robust: RobustChoice | None = None
    nominal: CostPrediction | None = None

    @property
    def controller(self) -> DiscreteStateSpace:
        """The designed controller."""
        return self.design.controller


def _load(path: Path) -> tuple[Path, IdentifiedModel]:
    """The model file (or ``model.json`` in a ``qube-identify --out`` folder), or a DesignError naming it."""
    from qube_koopman.identify.models.model_file import load_model

    if path.is_dir() and (path / "model.json").is_file():
        path = path / "model.json"
    try:
        model = load_model(path)
    except ValueError as exc:
        raise DesignError(_arx_hint(path) or str(exc)) from None
    except (KeyError, TypeError, AttributeError, IndexError) as exc:
        raise DesignError(f"{path}: not a readable model file (missing or malformed {exc})") from None
    if abs(model.dt - QUBE_SAMPLE_PERIOD) > 1e-9 * QUBE_SAMPLE_PERIOD:
        raise DesignError(
            f"{path}: sample period {model.dt!r} s, not the loop's {QUBE_SAMPLE_PERIOD!r} s: a controller "
            "designed on it would not run (a discrete controller runs only at the period it was designed for)"
        )
    return path, model


def _arx_hint(path: Path) -> str | None:
    """The refusal of an ARX model file, which says how to identify a plant a design can use."""
    from qube_koopman.core.files import loads_json, read_bounded_text
    from qube_koopman.identify.models.model_file import MAX_MODEL_BYTES

    try:
        data = loads_json(read_bounded_text(path, MAX_MODEL_BYTES, "model file"), path)
    except (OSError, ValueError):
        return None
    if isinstance(data, dict) and data.get("format") == "qube-arx-model":
        return f"{path}: an ARX model; a design needs a Koopman plant model: identify it with {IDENTIFY_FLAGS}"
    return None


def design_from_model(
    path: str | Path,
    weights: Weights = Weights(),
    *,
    seed: int = 1,
    episodes: int = 20,
    duration: float = 20.0,
    level: float | None = 0.95,
    robust: bool = False,
) -> DesignReport:
    """Design a controller on a model file's plant and predict it.

    Parameters
    ----------
    path : str or Path
        A ``model.json`` of ``qube-identify``.
    weights : Weights
        The LQ weights.
    seed, episodes, duration
        The excitation the prediction runs: that of ``qube-run --seed seed --episodes episodes
        --duration duration``.
    level : float or None
        The level of the predicted figures' interval (:mod:`design.uncertainty`), from the model
        file's bootstrap plants and held-out episodes; None for no interval.
    robust : bool
        Design against that uncertainty (:func:`design.uncertainty.robust_design`) instead of
        on the point plant alone; the report keeps the nominal design's prediction beside it.

    Returns
    -------
    DesignReport

    Raises
    ------
    DesignError
        Naming the file when the model cannot be designed on (not a plant model file, a lifting
        with the arm's friction shape, not stabilizable), or when the predicted closed loop is
        unstable.
    """
    path, model = _load(Path(path))
    excitations = rig_excitations(seed, episodes, duration)
    uncertainty, nominal, choice = None, None, None
    try:
        plant = linear_plant(model.plant)
        design = design_lq(plant, weights)
        if level is not None or robust:
            uncertainty = model_uncertainty(model)
        if robust:
            if uncertainty is None:
                raise DesignError(f"--robust designs against the model's uncertainty, and {NO_MEMBERS}")
            choice = robust_design(plant, weights, uncertainty, excitations, level or 0.95)
            if choice.scale != 1.0:
                nominal = predict_cost(model.plant, design.controller, excitations)
            design = choice.design
    except DesignError as exc:
        raise DesignError(f"{path}: {exc}") from None
    radius = spectral_radius(closed_loop_matrix(plant, design.controller))
    if not radius < 1:
        raise DesignError(
            f"{path}: the predicted closed loop is unstable (spectral radius {radius:.6g}); change the weights"
        )
    predicted = predict_cost(model.plant, design.controller, excitations)
    if predicted.diverged:
        raise DesignError(
            f"{path}: the plant model under the designed controller diverges on {predicted.diverged} "
            f"of {episodes} excitations (the linearization it was designed on does not hold); change "
            f"the weights or identify with {IDENTIFY_FLAGS}"
        )
    training = None
    if model.controller is not None and model.controller.n_inputs in (2, 3):  # a QUBE loop
        training = predict_cost(model.plant, model.controller, excitations)
    interval, note = None, None
    if level is not None:
        if uncertainty is None:
            note = NO_MEMBERS
        else:
            interval = interval_from_logs(uncertainty, plant, design, predicted.summary(), excitations, level)
    return DesignReport(
        path,
        model,
        design,
        radius,
        spectral_radius(plant.F),
        loop_margins(plant, design.controller),
        predicted,
        training,
        {"seed": seed, "episodes": episodes, "duration": duration},
        interval,
        note,
        choice,
        nominal,
    )


def _row(name: str, prediction: CostPrediction) -> str:
    s = prediction.summary()
    return (
        f"  {name:<24} {s['J']:>10.3e} {s['tracking_rms']:>12.4f} {s['alpha_rms']:>10.4f} "
        f"{s['voltage_rms']:>12.3f} {s['voltage_peak']:>13.2f}"
    )


def report_text(report: DesignReport) -> str:
    """What the command prints: the plant, the design, its spectrum and margins, the predicted figures.

    Parameters
    ----------
    report : DesignReport
        The design (:func:`design_from_model`).

    Returns
    -------
    str
    """
    d, w, m = report.design, report.design.weights, report.margins.as_dict()
    integral = f", q_integral {w.q_integral:g} (integral action on the arm)" if w.integral else " (no integral action)"
    ex = report.excitation
    lines = [
        f"model {report.model_path}: {d.plant.note} ({d.plant.n_states} states)",
        f"design: LQ on the plant's history; weights q_theta {w.q_theta:g}, q_alpha {w.q_alpha:g}, "
        f"r_voltage {w.r_voltage:g}{integral}",
        f"controller: {d.controller.n_states} states (the past {d.plant.n_delays} tracking errors of theta and alpha"
        + (", the arm's integral)" if w.integral else ")"),
        f"closed loop: spectral radius {report.spectral_radius:.6f} (plant alone {report.open_loop_radius:.6f})",
        f"margins at the plant input: gain +{m['gain_margin_up_db']:.1f} dB / {m['gain_margin_down_db']:.1f} dB, "
        f"phase {m['phase_margin_deg']:.1f} deg at {m['phase_crossover_hz']:.2f} Hz, "
        f"stability margin min|1 + L| {m['stability_margin']:.3f}",
        f"predicted on the rig's excitation ({ex['episodes']} episodes of {ex['duration']:g} s, as qube-run "
        f"--seed {ex['seed']}), after the first second:",
        f"  {'controller':<24} {'J (rad^2)':>10} {'tracking RMS':>12} {'alpha RMS':>10} {'voltage RMS':>12} "
        f"{'voltage peak':>13}",
        _row("designed", report.predicted),
    ]
    if report.nominal is not None:
        lines.append(_row("nominal (not robust)", report.nominal))
    if report.training is not None:
        lines.append(_row("model's training one", report.training))
        ratio = report.predicted.summary()["J"] / report.training.summary()["J"]
        lines.append(f"  predicted J {100 * (ratio - 1):+.1f} % against the training controller")
    lines += _interval_lines(report)
    return "\n".join(lines)


def _interval_lines(report: DesignReport) -> list[str]:
    """The interval's and the robust design's lines of the report."""
    lines = []
    iv = report.interval
    if iv is not None:
        lines.append(f"interval at {iv.level:g} (from {iv.sources}):")
        percent = f"{100 * iv.level:g} %"
        for name, label, fmt in (
            ("J", "J (rad^2)", ".3e"),
            ("voltage_rms", "voltage RMS (V)", ".3f"),
            ("voltage_peak", "voltage peak (V)", ".2f"),
        ):
            lines.append(f"  {label:<17} {_figure_with_interval(iv, name, fmt, percent)}")
        if iv.n_held_out and not iv.propagated:
            lines.append(
                "  (the model's error is the training controller's ratio: the model file keeps no spectra of it to "
                "propagate through the design, and a design that feeds back harder draws more voltage than this "
                "interval says; identify the plant again for them)"
            )
    elif report.interval_note is not None:
        lines.append(f"no interval: {report.interval_note}")
    if report.robust is not None:
        worst = {c["scale"]: c["worst_upper_J"] for c in report.robust.candidates}
        tried = ", ".join(f"x{scale:g}: {value:.3e}" for scale, value in worst.items())
        if report.nominal is None:
            lines.append(
                f"robust: the nominal weights are the most robust (worst-case J over the bootstrap plants, "
                f"r_voltage {tried}); the design is the nominal one, at no cost in J"
            )
        else:
            cost = report.predicted.summary()["J"] / report.nominal.summary()["J"] - 1
            lines.append(
                f"robust: r_voltage x{report.robust.scale:g} (worst-case J over the bootstrap plants, "
                f"r_voltage {tried}); it costs {100 * cost:+.1f} % of predicted J against the nominal design"
            )
    return lines


def _figure_with_interval(iv: FigureInterval, name: str, fmt: str, percent: str) -> str:
    """One figure's line: the point plant's prediction, the same with the model's error, and the interval of the
    loop's figure (over the bootstrap plants, with the model's error) with its median; it says so when the point
    plant's prediction lies outside that interval."""
    predicted, lower, upper = iv.predicted[name], iv.lower[name], iv.upper[name]
    text = f"predicted {predicted:{fmt}} (the point model)"
    if iv.n_held_out:
        text += f", {iv.expected[name]:{fmt}} with the model's error"
    text += f"; {percent} interval of the loop's figure {lower:{fmt}} to {upper:{fmt}}"
    if iv.median is not None and np.isfinite(iv.median[name]):
        text += f", its median {iv.median[name]:{fmt}}"
    if predicted < lower or predicted > upper:
        text += f" (the point model's prediction lies {'below' if predicted < lower else 'above'} it)"
    return text


def saturation_warning(report: DesignReport) -> str | None:
    """The warning when the predicted voltage exceeds the loop's clamp (saturation), else None."""
    peak = report.predicted.summary()["voltage_peak"]
    if peak > VOLTAGE_LIMIT:
        return (
            f"the predicted voltage peaks at {peak:.2f} V, beyond the loop's {VOLTAGE_LIMIT:g} V clamp: the "
            "loop would saturate, which the prediction leaves out"
        )
    return None


def provenance(report: DesignReport) -> dict:
    """The controller file's ``[provenance]``: model, weights, cost, margins, spectrum."""
    from qube_koopman.core.cli import package_version

    out = {
        "designed_by": "qube-design (LQ on the identified plant's history)",
        "software_version": f"qube-koopman {package_version()}",
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "model": str(report.model_path),
        "model_method": str(report.model.method),
        "design_plant": report.design.plant.note,
        "n_delays": report.design.plant.n_delays,
        "weights": report.design.weights.as_dict(),
        "spectral_radius": report.spectral_radius,
        "margins": report.margins.as_dict(),
        "excitation": report.excitation,
        "predicted": report.predicted.summary(),
    }
    if report.training is not None:
        out["predicted_training_controller"] = report.training.summary()
    if report.interval is not None:
        out["interval"] = report.interval.as_dict()
    elif report.interval_note is not None:
        out["interval"] = {"none": report.interval_note}
    if report.robust is not None:
        out["robust"] = report.robust.as_dict()
        if report.nominal is not None:
            out["predicted_nominal_design"] = report.nominal.summary()
    return _finite(out)


def record_design(path: str | Path, report: DesignReport, controller, n_episodes: int = 3) -> Path:
    """Write ``qube-design --rerun-save``'s recording: the first episodes predicted and on the twin, the eigenvalues.

    Parameters
    ----------
    path : str or Path
        The .rrd file (:func:`design.recording.write_recording`).
    report : DesignReport
        The design; its excitation's first ``n_episodes`` are predicted and run.
    controller : daq.episode.ControllerInfo
        The designed controller as the loop runs it (the written controller file, loaded).
    n_episodes : int
        Episodes shown (at most the excitation's).

    Returns
    -------
    Path
    """
    from qube_koopman.core.controller_file import ControllerInfo
    from qube_koopman.design.recording import write_recording
    from qube_koopman.design.twin import run_on_twin

    ex = report.excitation
    n = min(n_episodes, ex["episodes"])
    predicted = predict_loop(report.model.plant, report.controller, rig_excitations(ex["seed"], n, ex["duration"]))
    twin = {"twin": run_on_twin(controller, ex["seed"], n, of=ex["episodes"], duration=ex["duration"])}
    eigenvalues = {"design": closed_loop_eigenvalues(report.design.plant, report.controller)}
    training = report.model.controller
    if report.training is not None and training is not None:  # a training prediction needs the model's controller
        info = ControllerInfo(
            training, "as the model file records it", kind="state-space", provenance={"model": str(report.model_path)}
        )
        twin["twin_training"] = run_on_twin(info, ex["seed"], n, of=ex["episodes"], duration=ex["duration"])
        eigenvalues["training"] = closed_loop_eigenvalues(report.design.plant, training)
    return write_recording(path, predicted, twin, eigenvalues)


def _finite(value):
    """Non-finite floats as strings (TOML has inf, but the log's JSON has not)."""
    if isinstance(value, float) and not np.isfinite(value):
        return str(value)
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def _where(entry: str) -> str:
    return "a load at the plant input (V)" if entry == "input" else f"a rate on {entry} (rad per tick)"


def offset_free_settings(report: DesignReport, settings, entries: tuple[str, ...] | None = None):
    """The MPC's settings with ``offset_free`` as the model file allows it, and a line saying which.

    Offset-free control (``settings.offset_free``, what ``qube-design --mpc`` asks for unless
    ``--no-offset-free``) needs the model file's disturbance model with a nonzero gain: from its
    covariances the MPC estimates ``entries`` (default :data:`design.mpc.OFFSET_FREE_ENTRIES`, a
    load at the plant input and a rate on the arm's angle) as random walks
    (:func:`design.mpc.mpc_disturbance`), whatever the model's own entry and pole. Without one the
    MPC is the one without a disturbance model.

    Parameters
    ----------
    report : DesignReport
    settings : design.mpc.MpcSettings
    entries : tuple of str, optional
        The disturbances the offset-free MPC estimates (``--disturbances``).

    Returns
    -------
    settings : design.mpc.MpcSettings
    line : str
    """
    from dataclasses import replace

    from qube_koopman.design.mpc import OFFSET_FREE_ENTRIES, model_disturbance

    entries = OFFSET_FREE_ENTRIES if entries is None else tuple(entries)
    disturbance = model_disturbance(report.model)
    if disturbance is None:
        line = (
            "offset-free: off: the model file has no disturbance model (qube-identify --horizon S[,S...] "
            "--disturbance ...), so the MPC is as without one"
        )
        return replace(settings, offset_free=False), line
    if not np.any(np.asarray(disturbance.gain, dtype=float)):
        line = (
            "offset-free: off: the model file's disturbance model has a zero gain (q = 0: the training episodes "
            "show no disturbance), so the MPC is as without one"
        )
        return replace(settings, offset_free=False), line
    own = _where(disturbance.entry)
    if not settings.offset_free:
        return settings, f"offset-free: off (--no-offset-free): the MPC records its estimate of {own} per tick"
    kind = "a random walk" if disturbance.pole == 1.0 else f"first-order (pole {disturbance.pole:g})"
    line = (
        f"offset-free: on: the MPC estimates {' and '.join(map(_where, entries))} each tick as random walks, with "
        f"the Kalman gain of the model file's R and the filter speed of its disturbance ({own}, {kind}; nothing "
        "refitted), and holds the arm at its reference under constant ones "
        f"(--disturbances {','.join(entries)}; --no-offset-free: off)"
    )
    return settings, line


def write_mpc(path: str | Path, report: DesignReport, settings, entries: tuple[str, ...] | None = None) -> Path:
    """Write the MPC on the report's plant and weights (``qube-design --mpc``): kind ``mpc``, with the provenance.

    The model file's disturbance model, when it has one, goes in the file: with
    ``settings.offset_free`` as the disturbances ``entries`` that the MPC estimates and rejects
    (:func:`offset_free_settings`), without it as the model's own, estimated and logged each tick.

    Parameters
    ----------
    path : str or Path
        The controller file.
    report : DesignReport
        The LQ design (:func:`design_from_model`): its plant and weights; its Riccati cost is the
        MPC's terminal cost.
    settings : design.mpc.MpcSettings
    entries : tuple of str, optional
        With ``settings.offset_free``, the disturbances estimated (default
        :data:`design.mpc.OFFSET_FREE_ENTRIES`).

    Returns
    -------
    Path

    Raises
    ------
    DesignError
        When ``settings.offset_free`` and the model file has no disturbance model, or the plant
        no steady state with the arm at its reference under it.
    """
    import control  # lazily: python-control imports matplotlib

    from qube_koopman.design.lq import augment
    from qube_koopman.design.mpc import OFFSET_FREE_ENTRIES, model_disturbance, mpc_disturbance
    from qube_koopman.design.mpc_file import write_mpc_file

    plant, weights = report.design.plant, report.design.weights
    model = model_disturbance(report.model)
    disturbance = None
    if model is not None and np.any(model.gain):
        if settings.offset_free:  # random walks, as many as asked for
            entries = OFFSET_FREE_ENTRIES if entries is None else tuple(entries)
            disturbance = mpc_disturbance(plant, model, integrate=True, entries=entries)
        else:
            disturbance = mpc_disturbance(plant, model)
    if settings.offset_free:
        if disturbance is None:
            raise DesignError("offset-free MPC needs the model file's disturbance model")
        disturbance.target_map()  # the steady state exists, or a DesignError says why
    P, _, _ = control.dare(*augment(plant, weights))
    out = provenance(report)
    out["designed_by"] = "qube-design --mpc (condensed linear MPC on the identified plant's history)"
    out["lq_predicted"] = out.pop("predicted")  # the LQ design's: the MPC's law while no constraint binds
    return write_mpc_file(path, plant, weights, np.asarray(P), settings, out, disturbance)
