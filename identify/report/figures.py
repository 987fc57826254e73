"""Figures of an identification run (matplotlib, optional: ``pip install "qube-koopman[figures]"``).

Each figure is drawn from a small data object of arrays, built from the same
arrays the report's numbers come from (the test predictions its R^2 are
computed on, the models whose spectral radii it lists, the sweep's scores):

- :class:`SeriesPlot`: curves against a common x (time or alpha), on one or
  more stacked panels, with optional vertical marks (the chosen alpha, the
  first scored sample) and shaded bands (a prediction's interval);
- :class:`EigenvaluePlot`: sets of eigenvalues in the complex plane with the
  unit circle.

:func:`draw` turns one into a matplotlib ``Figure`` (each curve a ``Line2D``
whose ``gid`` is its label, so what was plotted can be read back);
:func:`write_figures` saves each as PNG and PDF. matplotlib is imported only
there, figures drawn on Agg canvases without pyplot (no display needed, no global
backend changed); :func:`require_matplotlib`
says how to install it when it is missing. Non-finite values (a diverged
prediction, a -inf score) are stored as NaN: matplotlib leaves a gap there.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from qube_koopman.core.files import atomic_path
from qube_koopman.core.qube import STATE_NAMES

__all__ = [
    "Curve",
    "Band",
    "SeriesPlot",
    "EigenvaluePlot",
    "FigureSpec",
    "FiguresUnavailable",
    "require_matplotlib",
    "draw",
    "write_figures",
    "measured_range",
    "model_eigenvalues",
    "identification_figures",
    "choose_episodes",
]

INSTALL_HINT = 'pip install "qube-koopman[figures]"'
UNIT_CIRCLE_POINTS = 361


class FiguresUnavailable(ImportError):
    """matplotlib is not installed; the message says how to install it."""


def require_matplotlib(option: str = "--figures") -> None:
    """Check that matplotlib imports, or raise :class:`FiguresUnavailable`.

    Parameters
    ----------
    option : str
        The option that asked for figures, named in the message.

    Raises
    ------
    FiguresUnavailable
        One line: the option, the missing package and the command installing it.
    """
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise FiguresUnavailable(f"{option} needs matplotlib, which is optional: {INSTALL_HINT}") from None


def _finite_or_nan(values) -> np.ndarray:
    """Float array with every non-finite value (or None, or the strings "inf"/"-inf") as NaN."""
    array = np.array([np.nan if v is None else v for v in np.ravel(values)], dtype=float)
    array = array.reshape(np.shape(values))
    return np.where(np.isfinite(array), array, np.nan)


@dataclass(frozen=True)
class Curve:
    """One plotted curve: a label (the ``Line2D`` gid), values against the plot's x, a panel.

    Parameters
    ----------
    label : str
        The legend's label (and the line's gid).
    y : ndarray of shape (n,)
        Values against the plot's x.
    panel : int
        The panel it is drawn on.
    style : str
        A matplotlib line style.
    """

    label: str
    y: np.ndarray
    panel: int = 0
    style: str = "-"

    def __post_init__(self) -> None:
        object.__setattr__(self, "y", _finite_or_nan(self.y))


@dataclass(frozen=True)
class Band:
    """A shaded band between two curves: a prediction's interval (the ``PolyCollection``'s gid is its label).

    Parameters
    ----------
    label : str
        The legend's label (and the band's gid).
    lower, upper : ndarray of shape (n,)
        Its edges against the plot's x; non-finite values (an infinite interval) leave a gap.
    panel : int
        The panel it is drawn on.
    """

    label: str
    lower: np.ndarray
    upper: np.ndarray
    panel: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "lower", _finite_or_nan(self.lower))
        object.__setattr__(self, "upper", _finite_or_nan(self.upper))


@dataclass(frozen=True)
class SeriesPlot:
    """Curves against a common x on ``len(ylabels)`` stacked panels.

    Parameters
    ----------
    title : str
        The figure's title.
    x : ndarray of shape (n,)
        The common x values.
    xlabel : str
        The x axis' label.
    ylabels : tuple of str
        One per panel.
    curves : tuple of Curve
        Each of length n.
    log_x : bool
        Logarithmic x axis (alpha sweeps).
    marks : dict of str to float
        Vertical lines at these x values, by label (gid ``"mark: <label>"``).
    ylims : tuple of (float, float) or None, optional
        Each panel's y range (e.g. to let a diverged curve leave the plot);
        None (for all panels or one): matplotlib's autoscaling.
    bands : tuple of Band
        Shaded bands, each of length n, drawn under the curves.
    """

    title: str
    x: np.ndarray
    xlabel: str
    ylabels: tuple[str, ...]
    curves: tuple[Curve, ...]
    log_x: bool = False
    marks: dict[str, float] = field(default_factory=dict)
    ylims: tuple[tuple[float, float] | None, ...] | None = None
    bands: tuple[Band, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "x", np.asarray(self.x, dtype=float))
        drawn: tuple[Curve | Band, ...] = (*self.curves, *self.bands)
        for c in drawn:
            shape = c.y.shape if isinstance(c, Curve) else c.lower.shape
            if (
                shape != self.x.shape
                or (isinstance(c, Band) and c.upper.shape != shape)
                or not 0 <= c.panel < len(self.ylabels)
            ):
                raise ValueError(
                    f"{type(c).__name__.lower()} {c.label!r}: shape {shape} / panel {c.panel} does not "
                    f"fit x of shape {self.x.shape} and {len(self.ylabels)} panel(s)"
                )

    def curve(self, label: str) -> Curve:
        """The curve of this label."""
        return next(c for c in self.curves if c.label == label)


@dataclass(frozen=True)
class EigenvaluePlot:
    """Sets of eigenvalues in the complex plane, beside the unit circle.

    Attributes
    ----------
    title : str
    sets : dict of str to complex ndarray
        Eigenvalues by label (each drawn as markers, ``Line2D`` gid = label).
    """

    title: str
    sets: dict[str, np.ndarray]


@dataclass(frozen=True)
class FigureSpec:
    """A figure to write: file stem, caption (for reports) and its data."""

    stem: str
    caption: str
    data: SeriesPlot | EigenvaluePlot


def _draw_series(plot: SeriesPlot, fig) -> None:
    axes = fig.subplots(len(plot.ylabels), 1, sharex=True, squeeze=False)[:, 0]
    for b in plot.bands:
        axes[b.panel].fill_between(
            plot.x, b.lower, b.upper, color="C1", alpha=0.25, linewidth=0, label=b.label
        ).set_gid(b.label)
    for c in plot.curves:
        (line,) = axes[c.panel].plot(plot.x, c.y, c.style, label=c.label, linewidth=1.0)
        line.set_gid(c.label)
    for ax, ylim in zip(axes, plot.ylims or ()):
        if ylim is not None:
            ax.set_ylim(*ylim)
    for ax, ylabel in zip(axes, plot.ylabels):
        for label, x in plot.marks.items():
            ax.axvline(x, color="0.4", linestyle=":", linewidth=1.0, label=label).set_gid(f"mark: {label}")
        ax.set_ylabel(ylabel)
        if plot.log_x:
            ax.set_xscale("log")
        ax.grid(True, alpha=0.3)
        n_labels = len(ax.get_legend_handles_labels()[0])
        if n_labels:
            ax.legend(fontsize="small" if n_labels < 4 else "x-small", ncols=1 if n_labels < 4 else 2, loc="best")
    axes[-1].set_xlabel(plot.xlabel)
    _fitted_title(axes[0], plot.title)


def _draw_eigenvalues(plot: EigenvaluePlot, fig) -> None:
    ax = fig.subplots()
    circle = np.exp(1j * np.linspace(0.0, 2 * np.pi, UNIT_CIRCLE_POINTS))
    ax.plot(circle.real, circle.imag, color="0.5", linewidth=0.8, label="unit circle")[0].set_gid("unit circle")
    markers = "ox+^sv"
    for i, (label, eig) in enumerate(plot.sets.items()):
        eig = np.asarray(eig, dtype=complex)
        (line,) = ax.plot(
            eig.real,
            eig.imag,
            linestyle="none",
            marker=markers[i % len(markers)],
            fillstyle="none",
            markersize=5,
            label=f"{label} (radius {np.max(np.abs(eig)):.4f})",
        )
        line.set_gid(label)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("real part")
    ax.set_ylabel("imaginary part")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small", loc="upper left", framealpha=0.9)
    _fitted_title(ax, plot.title)


#: The smallest font (points) a title shrinks to so that it fits the figure's width.
MIN_TITLE_POINTS = 7.0


def _fitted_title(ax, title: str) -> None:
    """``ax``'s title, its font made smaller (down to :data:`MIN_TITLE_POINTS`) when it is wider than the figure:
    a long episode name ran past both edges and was cut off (the layout makes room above a title, not beside it)."""
    text = ax.set_title(title)
    fig = ax.get_figure()
    width = text.get_window_extent(fig.canvas.get_renderer()).width
    room = 0.96 * fig.bbox.width
    if width > room:
        text.set_fontsize(max(MIN_TITLE_POINTS, text.get_fontsize() * room / width))


def draw(data: SeriesPlot | EigenvaluePlot):
    """Draw one figure's data.

    Parameters
    ----------
    data : SeriesPlot or EigenvaluePlot

    Returns
    -------
    matplotlib.figure.Figure
        On an Agg canvas, not attached to pyplot: no display needed, pyplot's backend (a
        notebook's, say) left alone, garbage-collected when dropped.
    """
    require_matplotlib()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if isinstance(data, SeriesPlot):
        fig = Figure(figsize=(7.0, 2.2 + 1.6 * len(data.ylabels)), layout="constrained")
        FigureCanvasAgg(fig)
        _draw_series(data, fig)
    else:
        fig = Figure(figsize=(5.5, 5.0), layout="constrained")
        FigureCanvasAgg(fig)
        _draw_eigenvalues(data, fig)
    return fig


def write_figures(specs: Sequence[FigureSpec], folder: str | Path, dpi: int = 120) -> list[Path]:
    """Draw each spec and save it as ``folder/<stem>.png`` and ``.pdf``; returns the PNG paths.

    Parameters
    ----------
    specs : sequence of FigureSpec
        The figures (:func:`identification_figures`).
    folder : str or Path
        Where to write them (created if missing).
    dpi : int
        Resolution of the PNG files.

    Returns
    -------
    list of Path
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for spec in specs:
        # A diverged curve's huge values overflow in matplotlib's layout arithmetic: expected, not news.
        with np.errstate(over="ignore", invalid="ignore"):
            fig = draw(spec.data)
            for suffix in (".png", ".pdf"):
                with atomic_path(folder / f"{spec.stem}{suffix}") as tmp:
                    fig.savefig(tmp, dpi=dpi, format=suffix[1:])
        written.append(folder / f"{spec.stem}.png")
    return written


def measured_range(measured: np.ndarray, predicted: np.ndarray, factor: float = 10.0) -> tuple[float, float] | None:
    """A y range for a measured channel and its prediction: None (autoscale) while the prediction
    stays finite and within ``factor`` times the measured peak, else the measured range with a
    margin (the diverged prediction leaves the plot)."""
    peak = float(np.max(np.abs(measured)))
    if np.all(np.isfinite(predicted)) and np.max(np.abs(predicted)) <= factor * peak:
        return None
    lo, hi = float(np.min(measured)), float(np.max(measured))
    margin = 0.25 * (hi - lo) or 1.0
    return lo - margin, hi + margin


def model_eigenvalues(model) -> np.ndarray | None:
    """Eigenvalues of a model's state matrix (Koopman models, and ARX wrappers via their ``model_``)."""
    A = getattr(model, "A", None)
    if A is None:  # ARX wrappers keep their state-space form in model_
        inner = getattr(model, "model_", None) or getattr(model, "plant_", None)
        A = None if inner is None else inner.A
    return None if A is None else np.linalg.eigvals(np.asarray(A))


def choose_episodes(
    names: Sequence[str], wanted: Sequence[str] | None, scores: Sequence[float | None] | None
) -> list[int]:
    """Indices of the test episodes to plot.

    Parameters
    ----------
    names : sequence of str
        Test episode file names, in the report's order.
    wanted : sequence of str, optional
        Each a 1-based position in ``names`` or a file name (with or without
        ``.mcap``). None: the best and the worst scored episodes (by ``scores``),
        or the first when nothing was scored.
    scores : sequence of float, optional
        R^2 per episode of ``names`` (None where unscored).

    Raises
    ------
    ValueError
        Naming an episode that is not among the test episodes.
    """
    if wanted is None:
        finite = {i: s for i, s in enumerate(scores or []) if s is not None and np.isfinite(s)}
        if not finite:
            return [0]
        best, worst = max(finite, key=finite.__getitem__), min(finite, key=finite.__getitem__)
        return [best] if best == worst else [best, worst]
    chosen = []
    stems = [n.rsplit(".", 1)[0] for n in names]
    for w in wanted:
        if w.isdigit() and 1 <= int(w) <= len(names):
            chosen.append(int(w) - 1)
        elif w in names or w in stems:
            chosen.append(names.index(w) if w in names else stems.index(w))
        else:
            raise ValueError(
                f"--figure-episodes {w}: not a test episode (a position 1 to {len(names)} or a "
                f"test log's name, e.g. {names[0]})"
            )
    return list(dict.fromkeys(chosen))


def _interval_bands(result, i: int, n: int, states) -> tuple[tuple[Band, ...], str]:
    """The test episode's interval as one band per panel (full length, NaN before its scored samples), and
    the caption's words for it."""
    bands = getattr(result, "test_bands", None)
    if not bands:
        return (), ""
    band = bands[i]
    lower, upper = np.full((n, len(states)), np.nan), np.full((n, len(states)), np.nan)
    lower[n - len(band.t) :], upper[n - len(band.t) :] = band.lower, band.upper
    label = f"{band.level:.0%} interval"
    return (
        tuple(Band(f"{s} {label}", lower[:, j], upper[:, j], panel=j) for j, s in enumerate(states)),
        f", shaded: the prediction's {label}",
    )


def _trajectory_spec(result, i: int, r2: float | None, start: int) -> FigureSpec:
    name, t = result.test_names[i], result.test_time[i]
    truth, pred = result.test_truth[i], result.test_predictions[i]
    states = STATE_NAMES[: truth.shape[1]]
    curves = tuple(
        Curve(f"{s} {kind}", values[:, j], panel=j, style="-" if kind == "measured" else "--")
        for j, s in enumerate(states)
        for kind, values in (("measured", truth), ("predicted", pred))
    )
    bands, shaded = _interval_bands(result, i, len(t), states)
    score = "" if r2 is None else f", R^2 {r2:.4f}" if abs(r2) < 1e3 else f", R^2 {r2:.3g}"
    plot = SeriesPlot(
        f"{name.rsplit('.', 1)[0]}{score}",
        t,
        "time (s)",
        tuple(f"{s} (rad)" for s in states),
        curves,
        marks={"first scored sample": float(t[start])} if start > 1 else {},
        ylims=tuple(measured_range(truth[:, j], pred[:, j]) for j in range(len(states))),
        bands=bands,
    )
    stem = "trajectory_" + name.rsplit(".", 1)[0]
    return FigureSpec(
        stem, f"Test episode {name}: measured and predicted angles{score} (scored from sample {start}){shaded}.", plot
    )


def _eigenvalue_spec(result) -> FigureSpec | None:
    sets = {
        label: eig
        for label, model in (("closed loop", result.closed_loop), ("plant", result.plant))
        if model is not None and (eig := model_eigenvalues(model)) is not None
    }
    if not sets:
        return None
    return FigureSpec(
        "eigenvalues",
        "Eigenvalues of the identified closed loop and plant, with the unit circle.",
        EigenvaluePlot("eigenvalues and the unit circle", sets),
    )


def _sweep_spec(sweep: dict, alpha: float) -> FigureSpec:
    radii = [
        Curve(f"spectral radius, {label}", sweep[key], panel=1)
        for key, label in (("spectral_radius_closed_loop", "closed loop"), ("spectral_radius_plant", "plant"))
        if sweep.get(key) is not None
    ]
    plot = SeriesPlot(
        "regularization sweep",
        sweep["alpha"],
        "alpha",
        ("CV R^2", "spectral radius"),
        (Curve("CV R^2", sweep["cv_r2_mean"], style="o-"), *radii),
        log_x=True,
        marks={"chosen alpha": alpha},
    )
    return FigureSpec(
        "alpha_sweep",
        f"Cross-validated R^2 ({sweep.get('score', 'cl')} scoring) and spectral radii "
        f"against alpha; the chosen alpha {alpha:g} marked.",
        plot,
    )


def identification_figures(result, episodes: Sequence[str] | None = None) -> list[FigureSpec]:
    """The figures of a ``qube-identify`` run.

    Parameters
    ----------
    result : IdentificationResult
        From :func:`qube_koopman.identify.workflow.identify_and_score`.
    episodes : sequence of str, optional
        Test episodes to plot (see :func:`choose_episodes`).

    Returns
    -------
    list of FigureSpec
        Measured vs predicted trajectories of the chosen test episodes; the
        eigenvalues of the closed loop and plant; the alpha sweep when one ran.
    """
    report = result.report
    scored = report.get("scored_logs", [])
    per_episode = (report.get("test") or {}).get("r2_per_episode", [])
    r2 = [per_episode[scored.index(n)] if n in scored else None for n in result.test_names]
    r2 = [None if v is None else float(v) for v in r2]
    start = int(report.get("scored_from_sample", 1))
    specs = [_trajectory_spec(result, i, r2[i], start) for i in choose_episodes(result.test_names, episodes, r2)]
    eig = _eigenvalue_spec(result)
    specs += [eig] if eig is not None else []
    if report.get("sweep"):
        specs.append(_sweep_spec(report["sweep"], report["alpha"]))
    return specs
