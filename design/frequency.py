"""Frequency responses of a design: ``qube-design --figures DIR``.

Two figures, written as PNG files named after the controller file:

- ``<stem>_bode.png``: Bode plots (python-control's ``bode_plot``) of the identified plant from the
  voltage to each angle, of the designed controller from each tracking error to the voltage, and of the
  loop broken at the plant input, ``L(z) = K(z) P(z)`` (:func:`~qube_koopman.design.predict.loop_response`);
- ``<stem>_margins.png``: the loop's Bode plot (unit gain, -180 deg and the phase margin's frequency marked),
  titled with its margins as :func:`~qube_koopman.design.predict.loop_margins` computes them
  (``control.stability_margins`` on the same frequency grid): the gain margins up and down (an unstable
  plant has both), the phase margin and where, and ``min |1 + L|``. The title is also the PNG's ``Title``
  text, so the file says its margins.

The responses are computed on the grid of :func:`~qube_koopman.design.predict.loop_margins` (1500 points from
0.01 rad/s to the Nyquist frequency) and plotted as python-control frequency-response data. Matplotlib runs on
its Agg backend, imported only when figures are asked for.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from qube_koopman.core.lti import DiscreteStateSpace
from qube_koopman.design.plant import LinearPlant
from qube_koopman.design.predict import Margins, loop_margins, loop_response

__all__ = ["FrequencyFigures", "frequency_grid", "margins_title", "write_frequency_figures"]

#: Points of the logarithmic frequency grid (as :func:`~qube_koopman.design.predict.loop_margins` uses).
N_POINTS = 1500


@dataclass(frozen=True)
class FrequencyFigures:
    """The figures written and the margins their title gives.

    Parameters
    ----------
    bode : Path
        The plant's, the controller's and the loop's Bode plots.
    margins_figure : Path
        The loop's Bode plot with its margins.
    margins : Margins
        The loop's margins at the plant input.
    title : str
        The margins figure's title (also its PNG ``Title``).
    """

    bode: Path
    margins_figure: Path
    margins: Margins
    title: str


def frequency_grid(dt: float, n_points: int = N_POINTS) -> np.ndarray:
    """The frequencies (rad/s) the figures and the margins use: logarithmic from 0.01 rad/s to the Nyquist frequency.

    Parameters
    ----------
    dt : float
        Sample period (s).
    n_points : int
        Points.

    Returns
    -------
    ndarray
    """
    return np.geomspace(1e-2, np.pi / dt, n_points)


def margins_title(margins: Margins) -> str:
    """The margins as the figure's title says them (as ``qube-design`` prints them)."""
    m = margins.as_dict()
    return (
        f"loop at the plant input: gain margin +{m['gain_margin_up_db']:.2f} dB / {m['gain_margin_down_db']:.2f} dB, "
        f"phase margin {m['phase_margin_deg']:.2f} deg at {m['phase_crossover_hz']:.3f} Hz, "
        f"min|1 + L| {m['stability_margin']:.3f}"
    )


def write_frequency_figures(
    folder: str | Path, stem: str, plant: LinearPlant, controller: DiscreteStateSpace
) -> FrequencyFigures:
    """Write the design's Bode and margin figures into ``folder`` (created if missing).

    Parameters
    ----------
    folder : str or Path
        Where (``qube-design --figures DIR``).
    stem : str
        The files' name before ``_bode.png`` and ``_margins.png`` (the controller file's stem).
    plant : LinearPlant
        The plant designed on.
    controller : DiscreteStateSpace
        The designed controller (tracking errors in, voltage out).

    Returns
    -------
    FrequencyFigures
    """
    import matplotlib

    matplotlib.use("Agg")  # lazily, and never a window: the figures go to files
    import control
    import matplotlib.pyplot as plt

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    omega = frequency_grid(plant.dt)
    hz = omega / (2 * np.pi)
    P = plant.frequency_response(hz)  # (n_f, 2, 1): voltage to theta, alpha
    K = controller.frequency_response(hz)  # (n_f, 1, 2): e_theta, e_alpha to voltage
    L = loop_response(plant, controller, omega)
    margins = loop_margins(plant, controller, N_POINTS)
    title = margins_title(margins)

    def frd(response, name):
        return control.frd(np.asarray(response), omega, dt=plant.dt, name=name)

    systems = [
        (frd(P[:, 0, 0], "P_theta"), "plant: voltage to theta"),
        (frd(P[:, 1, 0], "P_alpha"), "plant: voltage to alpha"),
        (frd(K[:, 0, 0], "K_theta"), "controller: e_theta to voltage"),
        (frd(K[:, 0, 1], "K_alpha"), "controller: e_alpha to voltage"),
        (frd(L, "L"), "loop L = K P at the plant input"),
    ]
    bode = folder / f"{stem}_bode.png"
    fig = plt.figure(figsize=(9, 7))
    control.bode_plot(
        [s for s, _ in systems],
        Hz=True,
        label=[label for _, label in systems],
        title=f"{stem}: the identified plant, the designed controller and the loop",
    )
    fig.savefig(bode, dpi=100, metadata={"Title": f"{stem}: Bode plots of the plant, the controller and the loop"})
    plt.close(fig)

    figure = folder / f"{stem}_margins.png"
    fig = plt.figure(figsize=(9, 7))
    # The crossings marked by hand, not python-control's overlay: a phase crossing exactly at the Nyquist
    # frequency (a real response there) is a gain margin its overlay would not show, and the title gives it.
    plot = control.bode_plot(systems[-1][0], Hz=True, title=title)
    magnitude, phase = plot.axes[0, 0], plot.axes[1, 0]
    magnitude.axhline(1.0, color="k", linestyle=":", linewidth=1)
    phase.axhline(-180.0, color="k", linestyle=":", linewidth=1)
    if np.isfinite(margins.phase_frequency):
        for ax in (magnitude, phase):
            ax.axvline(margins.phase_frequency, color="k", linestyle="--", linewidth=1)
    fig.savefig(figure, dpi=100, metadata={"Title": title})
    plt.close(fig)
    return FrequencyFigures(bode, figure, margins, title)
