"""Text of ``qube-calibrate``: parameter table, residuals, validation; ``report.md`` and ``calibration.rrd``."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from qube_koopman.core.files import atomic_path
from qube_koopman.sim.pendulum.physics import Coefficients
from qube_koopman.sim.pendulum.params_file import named_parameters

__all__ = ["calibration_text", "validation_text", "controller_summary_text", "write_report"]

_log = logging.getLogger(__name__)


def _which(setups: dict) -> str:
    """What the setups hold, in words."""
    words = {"Kr": "the cables' stiffness Kr per recording day", "delay": "the command delay per session"}
    return " and ".join(words.get(name, name) for name in setups)


def calibration_text(cal, names: list[str], seconds: float, groups: list | None = None) -> str:
    """Markdown: fitted parameters with standard errors beside the defaults, correlations, residuals.

    ``groups`` (``validate.controller_groups`` of the fitted episodes): with
    more than one controller, a table gives each one's mean residual.
    """
    default = named_parameters("default")
    lines = [
        f"## Calibration on {len(names)} episodes ({seconds:.1f} s, {cal.nfev_} model evaluations)",
        "",
        "| parameter | fitted | std. error | default |",
        "|---|---|---|---|",
    ]
    held = getattr(cal, "held_", {})
    for name in cal.fitted_names_:
        error = "held" if name in held else f"{cal.standard_errors_[name]:.2g}"
        lines.append(f"| {name} | {getattr(cal.params_, name):.5g} | {error} | {getattr(default, name):.5g} |")
    setups = getattr(cal, "setup_values_", {})
    if setups:
        lines += [
            "",
            f"Per setup, the rest of the physics shared ({_which(setups)}); the table above gives the median "
            "setup's (of the logarithms for Kr), the twin of a setup no log shows:",
            "",
            "| parameter | setup | fitted | std. error | |",
            "|---|---|---|---|---|",
        ]
        for name, values in setups.items():
            for label, value in values.items():
                volts = f"{value / Coefficients.of(cal.params_).torque_per_volt:.3f} V/rad at the motor"
                note = volts if name == "Kr" else f"{1e3 * value:.2f} ms"
                lines.append(f"| {name} | {label} | {value:.4g} | {cal.setup_errors_[name][label]:.2g} | {note} |")
    lines += [
        "",
        "Correlation of the fitted parameters:",
        "",
        "| | " + " | ".join(cal.fitted_names_) + " |",
        "|---" * (len(cal.fitted_names_) + 1) + "|",
    ]
    for name, row in zip(cal.fitted_names_, cal.correlation_):
        lines.append(f"| {name} | " + " | ".join(f"{v:+.2f}" for v in row) + " |")
    lines += ["", "| episode | alpha offset (mrad) | residual RMS theta (mrad) | alpha (mrad) |", "|---|---|---|---|"]
    for name, off, err, rms in zip(names, cal.alpha_offsets_, cal.alpha_offset_errors_, cal.residual_rms_):
        lines.append(f"| {name} | {1e3 * off:+.2f} +- {1e3 * err:.2f} | {1e3 * rms[0]:.2f} | {1e3 * rms[1]:.2f} |")
    if groups and len(groups) > 1:
        lines += [
            "",
            f"Fit per controller ({cal.horizon:g} s segments of the logged voltage, open loop):",
            "",
            "| controller | episodes | residual RMS theta (mrad) | alpha (mrad) |",
            "|---|---|---|---|",
        ]
        for label, members in groups:
            rms = cal.residual_rms_[members]
            lines.append(f"| {label} | {len(members)} | {1e3 * rms[:, 0].mean():.2f} | {1e3 * rms[:, 1].mean():.2f} |")
    if cal.warnings_:
        lines += ["", "Warnings:", ""] + [f"- {w}" for w in cal.warnings_]
    return "\n".join(lines) + "\n"


def validation_text(
    replay, open_loop: np.ndarray, names: list[str], controller: str | None = None, fitted: int = 0
) -> str:
    """Markdown: closed-loop replay ratios, balance, NRMSE and 0.2 s open-loop error per episode.

    ``controller`` (a label) names the controller in the title when the validation has several.
    ``fitted`` counts the episodes that the fit used too: the title then says their replay is
    not a held-out check.
    """
    r = replay.std_ratio
    under = f" under {controller}" if controller else ""
    held = "not fitted" if not fitted else f"({fitted} of them fitted too: not held out)"
    lines = [
        f"## Validation on {len(names)} episodes {held}{under}",
        "",
        f"- balanced: {int(replay.balanced.sum())} of {len(names)}",
        "- std ratio twin/real, min..max (mean): "
        + ", ".join(
            f"{label} {r[:, i].min():.3f}..{r[:, i].max():.3f} ({r[:, i].mean():.3f})"
            for i, label in enumerate(("theta", "alpha", "voltage"))
        ),
        f"- closed-loop replay NRMSE: {replay.nrmse.mean():.2f} +- {replay.nrmse.std():.2f} %",
        f"- open-loop 0.2 s prediction RMS error: theta {1e3 * open_loop[:, 0].mean():.2f} mrad, "
        f"alpha {1e3 * open_loop[:, 1].mean():.2f} mrad",
        "",
        "| episode | balanced | std ratio theta | alpha | voltage | replay NRMSE (%) | offset (mrad) "
        "| open-loop RMS theta, alpha (mrad) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for i, name in enumerate(names):
        lines.append(
            f"| {name} | {'yes' if replay.balanced[i] else 'NO'} | {r[i, 0]:.3f} | {r[i, 1]:.3f} "
            f"| {r[i, 2]:.3f} | {replay.nrmse[i]:.2f} | {1e3 * replay.offsets[i]:+.2f} "
            f"| {1e3 * open_loop[i, 0]:.2f}, {1e3 * open_loop[i, 1]:.2f} |"
        )
    return "\n".join(lines) + "\n"


def controller_summary_text(groups: list, dt: float) -> str:
    """Markdown: per controller, the replay's median std ratios overall, of the slow motion and by band.

    Parameters
    ----------
    groups : list of (str, validate.ReplayResult)
        Each controller's label and the replay of its validation episodes.
    dt : float
        Sample period (s).
    """
    from qube_koopman.identify.calibrate.replay_spectra import STD_BANDS, band_std_ratios, slow_std_ratio

    bands = [f"{lo:g}-{hi:g} Hz" if np.isfinite(hi) else f"above {lo:g} Hz" for lo, hi in STD_BANDS]
    lines = [
        "## Replay per controller: std ratio twin / real, median over episodes",
        "",
        "Each cell gives theta / alpha / voltage. Slow: the signals low-passed at 0.5 Hz "
        "(the arm's wander); the bands from Welch spectra (4096-sample segments).",
        "",
        "| controller | episodes | balanced | overall | slow (< 0.5 Hz) | " + " | ".join(bands) + " |",
        "|---" * (5 + len(bands)) + "|",
    ]
    for label, replay in groups:

        def cell(v):
            return " / ".join(f"{x:.3f}" for x in v)

        band = band_std_ratios(replay, dt)
        lines.append(
            f"| {label} | {len(replay.balanced)} | {int(replay.balanced.sum())} "
            f"| {cell(np.median(replay.std_ratio, axis=0))} | {cell(slow_std_ratio(replay, dt))} | "
            + " | ".join(cell(row) for row in band)
            + " |"
        )
    return "\n".join(lines) + "\n"


def load_band_ratios(replay, dt: float) -> np.ndarray:
    """A replay's std ratios twin / real, median over episodes: overall, then each band of ``STD_BANDS``.

    Shape ``(1 + n_bands, 3)`` (theta, alpha, voltage); every band's twin power is the mean over the
    replays (their start angles, and the load's draws).
    """
    from qube_koopman.identify.calibrate.replay_spectra import band_std_ratios

    return np.vstack([np.median(replay.std_ratio, axis=0), band_std_ratios(replay, dt, all_draws=True)])


def load_bands_text(groups: list) -> str:
    """Markdown: per controller, the replay's std ratios overall and by band with the random load off and on.

    Parameters
    ----------
    groups : list of (str, ndarray, ndarray)
        Each controller's label and the :func:`load_band_ratios` of its validation episodes' replays
        without and with the load.
    """
    from qube_koopman.identify.calibrate.replay_spectra import STD_BANDS

    bands = [f"{lo:g}-{hi:g} Hz" if np.isfinite(hi) else f"above {lo:g} Hz" for lo, hi in STD_BANDS]
    lines = [
        "## Replay with the arm's random load: std ratio twin / real, median over episodes",
        "",
        "Each cell gives theta / alpha / voltage; each episode's twin band power is the mean over its "
        "replays (each with its own draw of the load).",
        "",
        "| controller | load | overall | " + " | ".join(bands) + " |",
        "|---" * (3 + len(bands)) + "|",
    ]

    def cell(v):
        return " / ".join(f"{x:.3f}" for x in v)

    for label, off, on in groups:
        for name, rows in (("off", off), ("on", on)):
            lines.append(f"| {label} | {name} | " + " | ".join(cell(row) for row in rows) + " |")
    return "\n".join(lines) + "\n"


def write_report(folder: Path, text: str, validation=None, dt: float | None = None) -> list[Path]:
    """Write ``report.md`` and, with validation and rerun-sdk, ``calibration.rrd`` in ``folder``.

    Parameters
    ----------
    folder : Path
        An existing folder.
    text : str
        The tables (:func:`calibration_text`, :func:`validation_text`).
    validation : tuple or list of tuples, optional
        ``(replay, open_loop, names)`` as for :func:`validation_text`, or one
        such tuple per controller: each replay's band-power table
        (:func:`spectra.spectra_text`) is appended to the report and the
        replay written to ``calibration.rrd`` (the second controller's to
        ``calibration_2.rrd``, and so on; :func:`recording.write_recording`).
        Without rerun-sdk (the optional ``viz`` extra) one warning says the
        recordings were skipped.
    dt : float, optional
        Sample period (s) of the replay; needed with ``validation``.

    Returns
    -------
    list of Path
        The files written.
    """
    path = folder / "report.md"
    if validation is None:
        with atomic_path(path) as tmp:
            tmp.write_text("# qube-calibrate report\n\n" + text)
        return [path]
    if dt is None:
        raise ValueError("write_report needs dt (the replay's sample period) with validation")
    from qube_koopman.identify.calibrate.replay_spectra import spectra_text

    groups = validation if isinstance(validation, list) else [validation]
    spectra = [spectra_text(replay, dt) for replay, *_ in groups]
    with atomic_path(path) as tmp:
        tmp.write_text("# qube-calibrate report\n\n" + text + "\n" + "\n".join(spectra))
    rrds = [folder / ("calibration.rrd" if i == 0 else f"calibration_{i + 1}.rrd") for i in range(len(groups))]
    try:
        import rerun  # noqa: F401  (the optional viz extra)
    except ImportError:
        _log.warning(
            "%s not written: rerun-sdk is not installed (the viewer is optional): "
            'pip install "qube-koopman[viz]" (in a checkout: pip install -e ".[viz]")',
            ", ".join(str(r) for r in rrds),
        )
        return [path]
    from qube_koopman.identify.calibrate.validation_recording import write_recording

    return [path] + [write_recording(rrd, replay, names, dt) for rrd, (replay, _, names, *_) in zip(rrds, groups)]
