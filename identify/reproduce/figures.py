"""The paper's QUBE-Servo figures (section 5), regenerated from ``qube-reproduce qube``'s results.

Built from the results dict of :func:`qube_koopman.identify.reproduce.qube.reproduce_qube`,
the same arrays qube.json and qube.md report:

- ``inputs``: the exogenous inputs of one test episode (the paper's "sample of the
  exogenous test inputs"): references of theta and alpha, feedforward;
- ``spectral_radius_cl``, ``spectral_radius_plant``: spectral radii of the closed loops
  (EDMD's plant wrapped with the known controller) and plants against alpha;
- ``cross_validation_cl``, ``cross_validation_plant``: cross-validated closed-loop and
  plant R^2 against alpha (the plant's, -inf where a fold diverged, left as gaps);
- ``eigenvalues_cl``, ``eigenvalues_plant``: eigenvalues of the four method/scoring
  rows' closed loops and plants at their selected alphas, with the unit circle;
- ``predictions_cl``: the closed-loop prediction errors (measured minus predicted) of
  that test episode by every row of the table, ARX included.

Not regenerated: the paper's plant prediction errors with the controller output.
"""

from __future__ import annotations

import numpy as np

from qube_koopman.identify.figures import Curve, EigenvaluePlot, FigureSpec, SeriesPlot

__all__ = ["qube_figures", "EIGENVALUE_ROWS", "METHODS"]

#: The rows whose eigenvalues the paper compares (its four method/scoring combinations).
EIGENVALUE_ROWS = ("edmd_plant_plant", "edmd_plant_cl", "cl_edmd_cl_plant", "cl_edmd_cl_cl")
#: The regularization study's two methods: results["sweep"] key and label.
METHODS = (("edmd", "EDMD"), ("cl-edmd", "CL EDMD"))


def _sweep_spec(results: dict, stem: str, key: str, ylabel: str, caption: str) -> FigureSpec:
    sweep = results["sweep"]
    curves = tuple(Curve(label, sweep[method][key]) for method, label in METHODS)
    return FigureSpec(stem, caption, SeriesPlot(f"{ylabel} against alpha", sweep["alpha"], "alpha", (ylabel,), curves,
                                                log_x=True))


def _eigenvalue_spec(results: dict, kind: str, stem: str, caption: str) -> FigureSpec:
    sets = {}
    for key in EIGENVALUE_ROWS:
        e = results["eigenvalues"][key][kind]
        sets[f"{results['labels'][key]}, alpha {results['rows'][key]['alpha']:.3g}"] = (
            np.asarray(e["real"]) + 1j * np.asarray(e["imag"]))
    return FigureSpec(stem, caption, EigenvaluePlot(f"{kind.replace('_', ' ')} eigenvalues", sets))


def _episode_specs(results: dict) -> list[FigureSpec]:
    episode = results["figure_episode"]
    t = np.arange(len(episode["measured"])) * episode["dt"]
    name = episode["name"]
    inputs = SeriesPlot(f"exogenous inputs of {name}", t, "time (s)", ("reference (rad)", "feedforward (V)"),
                        (Curve("r theta", episode["r"][:, 0]), Curve("r alpha", episode["r"][:, 1]),
                         Curve("f", episode["f"][:, 0], panel=1)))
    errors = tuple(Curve(results["labels"][key], episode["measured"][:, j] - prediction[:, j], panel=j)
                   for j in range(2) for key, prediction in episode["predicted"].items())
    # The y ranges of the predictions that did not diverge: a diverged one leaves the plot, as in the paper.
    kept = [c for c in errors if np.isfinite(results["rows"][_key(results, c.label)]["r2_per_episode"][episode["index"]])]
    ylims = tuple((1.1 * min(np.nanmin(c.y) for c in kept if c.panel == j),
                   1.1 * max(np.nanmax(c.y) for c in kept if c.panel == j)) for j in range(2)) if kept else None
    predictions = SeriesPlot(f"closed-loop prediction errors, {name}", t, "time (s)",
                             ("theta error (rad)", "alpha error (rad)"), errors, ylims=ylims)
    return [FigureSpec("inputs", f"Exogenous inputs of test episode {name}: references of theta and alpha, "
                                 "feedforward voltage (paper: sample of the exogenous test inputs).", inputs),
            FigureSpec("predictions_cl", f"Closed-loop prediction errors (measured minus predicted) of test episode "
                                         f"{name} by every row of the table, each at its selected alpha; a "
                                         "diverged prediction leaves the plot (paper: prediction errors of the CL "
                                         "systems).", predictions)]


def _key(results: dict, label: str) -> str:
    return next(key for key, value in results["labels"].items() if value == label)


def qube_figures(results: dict) -> list[FigureSpec]:
    """The paper's QUBE-Servo figures from ``reproduce_qube``'s results.

    Parameters
    ----------
    results : dict
        From :func:`~qube_koopman.identify.reproduce.qube.reproduce_qube` (or
        qube.json, read back); the episode figures need it run with
        ``figure_episode`` (their arrays are not written to qube.json).

    Returns
    -------
    list of FigureSpec
    """
    specs = [
        _sweep_spec(results, "spectral_radius_cl", "spectral_radius_closed_loop", "closed-loop spectral radius",
                    "Closed-loop spectral radius against alpha: CL EDMD's closed loop stays asymptotically stable, "
                    "EDMD's (its plant wrapped with the known controller) does not (paper: spectral radii of the "
                    "CL systems)."),
        _sweep_spec(results, "spectral_radius_plant", "spectral_radius_plant", "plant spectral radius",
                    "Plant spectral radius against alpha: both plants are stabilized by large alphas "
                    "(paper: spectral radii of the plant systems)."),
        _sweep_spec(results, "cross_validation_cl", "cv_r2_cl", "CV R^2 (closed loop)",
                    "Cross-validated closed-loop R^2 against alpha; gaps where a prediction diverged "
                    "(paper: R^2 scores of the CL systems)."),
        _sweep_spec(results, "cross_validation_plant", "cv_r2_plant", "CV R^2 (plant)",
                    "Cross-validated plant R^2 against alpha: finite only at large alphas; gaps where a "
                    "prediction diverged (paper: R^2 scores of the plant systems)."),
        _eigenvalue_spec(results, "closed_loop", "eigenvalues_cl",
                         "Closed-loop eigenvalues of the four method/scoring rows at their selected alphas "
                         "(paper: eigenvalues of the CL systems)."),
        _eigenvalue_spec(results, "plant", "eigenvalues_plant",
                         "Plant eigenvalues of the four method/scoring rows at their selected alphas "
                         "(paper: eigenvalues of the plant systems)."),
    ]
    if "measured" in results.get("figure_episode", {}):  # the arrays, not qube.json's name and index
        specs += _episode_specs(results)
    return specs
