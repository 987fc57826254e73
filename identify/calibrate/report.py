"""Text of ``qube-calibrate``: parameter table, residuals, validation; ``report.md`` and ``calibration.rrd``."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from qube_koopman.sim.pendulum.params_file import named_parameters

__all__ = ["calibration_text", "validation_text", "write_report"]

_log = logging.getLogger(__name__)


def calibration_text(cal, names: list[str], seconds: float) -> str:
    """Markdown: fitted parameters with standard errors beside the defaults, correlations, residuals."""
    default = named_parameters("default")
    lines = [f"## Calibration on {len(names)} episodes ({seconds:.1f} s, {cal.nfev_} model evaluations)", "",
             "| parameter | fitted | std. error | default |", "|---|---|---|---|"]
    for name in cal.fitted_names_:
        lines.append(f"| {name} | {getattr(cal.params_, name):.5g} | {cal.standard_errors_[name]:.2g} "
                     f"| {getattr(default, name):.5g} |")
    lines += ["", "Correlation of the fitted parameters:", "",
              "| | " + " | ".join(cal.fitted_names_) + " |", "|---" * (len(cal.fitted_names_) + 1) + "|"]
    for name, row in zip(cal.fitted_names_, cal.correlation_):
        lines.append(f"| {name} | " + " | ".join(f"{v:+.2f}" for v in row) + " |")
    lines += ["", "| episode | alpha offset (mrad) | residual RMS theta (mrad) | alpha (mrad) |", "|---|---|---|---|"]
    for name, off, err, rms in zip(names, cal.alpha_offsets_, cal.alpha_offset_errors_, cal.residual_rms_):
        lines.append(f"| {name} | {1e3 * off:+.2f} +- {1e3 * err:.2f} | {1e3 * rms[0]:.2f} | {1e3 * rms[1]:.2f} |")
    if cal.warnings_:
        lines += ["", "Warnings:", ""] + [f"- {w}" for w in cal.warnings_]
    return "\n".join(lines) + "\n"


def validation_text(replay, open_loop: np.ndarray, names: list[str]) -> str:
    """Markdown: closed-loop replay ratios, balance, NRMSE and 0.2 s open-loop error per episode."""
    r = replay.std_ratio
    lines = [f"## Validation on {len(names)} episodes not fitted", "",
             f"- balanced: {int(replay.balanced.sum())} of {len(names)}",
             "- std ratio twin/real, min..max (mean): " + ", ".join(
                 f"{label} {r[:, i].min():.3f}..{r[:, i].max():.3f} ({r[:, i].mean():.3f})"
                 for i, label in enumerate(("theta", "alpha", "voltage"))),
             f"- closed-loop replay NRMSE: {replay.nrmse.mean():.2f} +- {replay.nrmse.std():.2f} %",
             f"- open-loop 0.2 s prediction RMS error: theta {1e3 * open_loop[:, 0].mean():.2f} mrad, "
             f"alpha {1e3 * open_loop[:, 1].mean():.2f} mrad", "",
             "| episode | balanced | std ratio theta | alpha | voltage | replay NRMSE (%) | offset (mrad) "
             "| open-loop RMS theta, alpha (mrad) |", "|---|---|---|---|---|---|---|---|"]
    for i, name in enumerate(names):
        lines.append(f"| {name} | {'yes' if replay.balanced[i] else 'NO'} | {r[i, 0]:.3f} | {r[i, 1]:.3f} "
                     f"| {r[i, 2]:.3f} | {replay.nrmse[i]:.2f} | {1e3 * replay.offsets[i]:+.2f} "
                     f"| {1e3 * open_loop[i, 0]:.2f}, {1e3 * open_loop[i, 1]:.2f} |")
    return "\n".join(lines) + "\n"


def write_report(folder: Path, text: str, validation=None, dt: float | None = None) -> list[Path]:
    """Write ``report.md`` and, with validation and rerun-sdk, ``calibration.rrd`` in ``folder``.

    Parameters
    ----------
    folder : Path
        An existing folder.
    text : str
        The tables (:func:`calibration_text`, :func:`validation_text`).
    validation : tuple, optional
        ``(replay, open_loop, names)`` as for :func:`validation_text`: the
        replay's band-power table (:func:`spectra.spectra_text`) is appended
        to the report and the replay written to ``calibration.rrd``
        (:func:`recording.write_recording`). Without rerun-sdk (the optional
        ``viz`` extra) one warning says the recording was skipped.
    dt : float, optional
        Sample period (s) of the replay; needed with ``validation``.

    Returns
    -------
    list of Path
        The files written.
    """
    path = folder / "report.md"
    if validation is None:
        path.write_text("# qube-calibrate report\n\n" + text)
        return [path]
    if dt is None:
        raise ValueError("write_report needs dt (the replay's sample period) with validation")
    from qube_koopman.identify.calibrate.spectra import spectra_text

    replay, _, names = validation
    path.write_text("# qube-calibrate report\n\n" + text + "\n" + spectra_text(replay, dt))
    rrd = folder / "calibration.rrd"
    try:
        import rerun  # noqa: F401  (the optional viz extra)
    except ImportError:
        _log.warning("%s not written: rerun-sdk is not installed (the viewer is optional): "
                     'pip install "qube-koopman[viz]" (in a checkout: pip install -e ".[viz]")', rrd)
        return [path]
    from qube_koopman.identify.calibrate.recording import write_recording

    return [path, write_recording(rrd, replay, names, dt)]
