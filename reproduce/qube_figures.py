"""The paper's QUBE-Servo figures (section 5), regenerated from ``qube-reproduce qube``'s results.

Built from the results dict of :func:`qube_koopman.reproduce.qube_study.reproduce_qube`,
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
  that test episode by every row of the table, ARX included;
- ``predictions_plant``: the plant prediction errors of that episode (each Koopman row's
  plant driven by the logged plant input) and the plant input itself.

A prediction that diverges leaves the plot (the y ranges are those of the others), as in
the paper.
"""

from __future__ import annotations

import numpy as np

from qube_koopman.identify.report.figures import Curve, EigenvaluePlot, FigureSpec, SeriesPlot

__all__ = ["qube_figures", "EIGENVALUE_ROWS", "METHODS"]

#: The rows whose eigenvalues the paper compares (its four method/scoring combinations).
EIGENVALUE_ROWS = ("edmd_plant_plant", "edmd_plant_cl", "cl_edmd_cl_plant", "cl_edmd_cl_cl")
#: The regularization study's two methods: results["sweep"] key and label.
METHODS = (("edmd", "EDMD"), ("cl-edmd", "CL EDMD"))


def _sweep_spec(results: dict, stem: str, key: str, ylabel: str, caption: str) -> FigureSpec:
    sweep = results["sweep"]
    curves = tuple(Curve(label, sweep[method][key]) for method, label in METHODS)
    return FigureSpec(
        stem, caption, SeriesPlot(f"{ylabel} against alpha", sweep["alpha"], "alpha", (ylabel,), curves, log_x=True)
    )


def _eigenvalue_spec(results: dict, kind: str, stem: str, caption: str) -> FigureSpec:
    sets = {}
    for key in EIGENVALUE_ROWS:
        e = results["eigenvalues"][key][kind]
        sets[f"{results['labels'][key]}, alpha {results['rows'][key]['alpha']:.3g}"] = np.asarray(
            e["real"]
        ) + 1j * np.asarray(e["imag"])
    return FigureSpec(stem, caption, EigenvaluePlot(f"{kind.replace('_', ' ')} eigenvalues", sets))


def _episode_specs(results: dict) -> list[FigureSpec]:
    episode = results["figure_episode"]
    t = np.arange(len(episode["measured"])) * episode["dt"]
    name = episode["name"]
    inputs = SeriesPlot(
        f"exogenous inputs of {name}",
        t,
        "time (s)",
        ("reference (rad)", "feedforward (V)"),
        (
            Curve("r theta", episode["r"][:, 0]),
            Curve("r alpha", episode["r"][:, 1]),
            Curve("f", episode["f"][:, 0], panel=1),
        ),
    )
    cl = _errors_plot(results, episode, "predicted", f"closed-loop prediction errors, {name}", t)
    plant = _errors_plot(
        results,
        episode,
        "plant_predicted",
        f"plant prediction errors, {name}",
        t,
        Curve("plant input u", episode["u"][:, 0], panel=2),
    )
    return [
        FigureSpec(
            "inputs",
            f"Exogenous inputs of test episode {name}: references of theta and alpha, "
            "feedforward voltage (paper: sample of the exogenous test inputs).",
            inputs,
        ),
        FigureSpec(
            "predictions_cl",
            f"Closed-loop prediction errors (measured minus predicted) of test episode "
            f"{name} by every row of the table, each at its selected alpha; a "
            "diverged prediction leaves the plot (paper: prediction errors of the CL "
            "systems).",
            cl,
        ),
        FigureSpec(
            "predictions_plant",
            f"Plant prediction errors of test episode {name}: each Koopman row's "
            "plant at its selected alpha driven by the logged plant input, which "
            "the last panel shows; an unstable plant's prediction diverges and "
            "leaves the plot (paper: prediction errors and controller output of "
            "the plant systems).",
            plant,
        ),
    ]


def _errors_plot(results: dict, episode: dict, which: str, title: str, t: np.ndarray, *extra: Curve) -> SeriesPlot:
    """Measured minus predicted angles of ``episode[which]``'s rows, on the y ranges of those that stayed finite."""
    errors = tuple(
        Curve(results["labels"][key], episode["measured"][:, j] - prediction[:, j], panel=j)
        for j in range(2)
        for key, prediction in episode[which].items()
    )
    # Kept in range: predictions that stay finite and within ten times the measured range (an unstable
    # plant's grows to 1e250 before it overflows).
    scale = 10 * np.max(np.abs(episode["measured"]))
    finite = {
        key
        for key, prediction in episode[which].items()
        if np.all(np.isfinite(prediction)) and np.max(np.abs(prediction)) <= scale
    }
    kept = [c for c in errors if _key(results, c.label) in finite]
    ylims = (
        tuple(
            (1.1 * min(np.min(c.y) for c in kept if c.panel == j), 1.1 * max(np.max(c.y) for c in kept if c.panel == j))
            for j in range(2)
        )
        if kept
        else None
    )
    if ylims and extra:  # the extra panels keep matplotlib's own range
        ylims += tuple((float(np.min(c.y)) - 0.1, float(np.max(c.y)) + 0.1) for c in extra)
    labels = ("theta error (rad)", "alpha error (rad)") + (("plant input (V)",) if extra else ())
    return SeriesPlot(title, t, "time (s)", labels, errors + extra, ylims=ylims)


def _key(results: dict, label: str) -> str:
    return next(key for key, value in results["labels"].items() if value == label)


def qube_figures(results: dict) -> list[FigureSpec]:
    """The paper's QUBE-Servo figures from ``reproduce_qube``'s results.

    Parameters
    ----------
    results : dict
        From :func:`~qube_koopman.reproduce.qube_study.reproduce_qube` (or
        qube.json, read back); the episode figures need it run with
        ``figure_episode`` (their arrays are not written to qube.json).

    Returns
    -------
    list of FigureSpec
    """
    specs = [
        _sweep_spec(
            results,
            "spectral_radius_cl",
            "spectral_radius_closed_loop",
            "closed-loop spectral radius",
            "Closed-loop spectral radius against alpha: CL EDMD's closed loop stays asymptotically stable, "
            "EDMD's (its plant wrapped with the known controller) does not (paper: spectral radii of the "
            "CL systems).",
        ),
        _sweep_spec(
            results,
            "spectral_radius_plant",
            "spectral_radius_plant",
            "plant spectral radius",
            "Plant spectral radius against alpha: both plants are stabilized by large alphas "
            "(paper: spectral radii of the plant systems).",
        ),
        _sweep_spec(
            results,
            "cross_validation_cl",
            "cv_r2_cl",
            "CV R^2 (closed loop)",
            "Cross-validated closed-loop R^2 against alpha; gaps where a prediction diverged "
            "(paper: R^2 scores of the CL systems).",
        ),
        _sweep_spec(
            results,
            "cross_validation_plant",
            "cv_r2_plant",
            "CV R^2 (plant)",
            "Cross-validated plant R^2 against alpha: finite only at large alphas; gaps where a "
            "prediction diverged (paper: R^2 scores of the plant systems).",
        ),
        _eigenvalue_spec(
            results,
            "closed_loop",
            "eigenvalues_cl",
            "Closed-loop eigenvalues of the four method/scoring rows at their selected alphas "
            "(paper: eigenvalues of the CL systems).",
        ),
        _eigenvalue_spec(
            results,
            "plant",
            "eigenvalues_plant",
            "Plant eigenvalues of the four method/scoring rows at their selected alphas "
            "(paper: eigenvalues of the plant systems).",
        ),
    ]
    if "measured" in results.get("figure_episode", {}):  # the arrays, not qube.json's name and index
        specs += _episode_specs(results)
    return specs
