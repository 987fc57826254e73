"""A rerun recording of an identification run (rerun-sdk imported lazily).

Entities: ``test/<episode>/<state>/{measured,predicted}`` against time;
``eigenvalues/{closed_loop,plant}`` beside ``eigenvalues/unit_circle``;
``sweep/{cv_r2,spectral_radius_closed_loop,spectral_radius_plant}`` against
the sweep index (timeline ``alpha_index``; ``sweep/log10_alpha`` gives the
value); with ``--search``, ``search/cv_r2`` against the number of delays
(timeline ``delays``, the search's delays stage).

The recording carries a blueprint (:func:`blueprint`): one tab of measured
vs predicted trajectories, one plot per test episode; one of the plant's and
closed loop's eigenvalues with the unit circle; one of the alpha sweep; one
of the search's cross-validated R^2 against delays.
"""

from __future__ import annotations

import numpy as np

from qube_koopman.core.rrd import RrdFile, import_rerun
from qube_koopman.core.qube import STATE_NAMES
from qube_koopman.identify.report.figures import model_eigenvalues


def blueprint(result):
    """The recording's layout: tabs of test trajectories, eigenvalues, alpha sweep, lifting search."""
    import rerun.blueprint as rrb

    episodes = [
        rrb.TimeSeriesView(origin=f"test/{name.rsplit('.', 1)[0]}", name=name.rsplit(".", 1)[0])
        for name in result.test_names
    ]
    tabs = [
        rrb.Grid(*episodes, name="test episodes: measured vs predicted"),
        rrb.Spatial2DView(origin="eigenvalues", name="eigenvalues and the unit circle"),
    ]
    if result.report.get("sweep"):
        tabs.append(rrb.TimeSeriesView(origin="sweep", name="alpha sweep (x: alpha index)"))
    if result.report.get("search"):
        tabs.append(rrb.TimeSeriesView(origin="search", name="search: CV R^2 against delays"))
    return rrb.Blueprint(rrb.Tabs(*tabs), collapse_panels=True)


def _log_search(rec, search: dict) -> None:
    import rerun as rr

    stage = sorted((c for c in search["candidates"] if c["stage"] == "delays"), key=lambda c: c["delays"])
    if not stage:
        return
    values = np.array([np.nan if c["cv_r2"] is None else c["cv_r2"] for c in stage], dtype=float)
    rec.send_columns(
        "search/cv_r2",
        indexes=[rr.TimeColumn("delays", sequence=[c["delays"] for c in stage])],
        columns=rr.Scalars.columns(scalars=np.where(np.isfinite(values), values, np.nan)),
    )


def write_recording(path, result) -> None:
    """Write ``result`` (an :class:`identify.workflow.IdentificationResult`) to an .rrd file.

    The file appears whole or not at all (:class:`core.rrd.RrdFile`); ``OSError`` naming ``path``
    when it cannot be written.
    """
    rr = import_rerun()
    rrd = RrdFile(path, "qube-identify", blueprint=blueprint(result))  # whole or not at all
    rec = rrd.recording
    for name, t, truth, pred in zip(result.test_names, result.test_time, result.test_truth, result.test_predictions):
        stem = name.rsplit(".", 1)[0]
        for j, state in enumerate(STATE_NAMES[: truth.shape[1]]):
            for kind, values in (("measured", truth[:, j]), ("predicted", pred[:, j])):
                rec.send_columns(
                    f"test/{stem}/{state}/{kind}",
                    indexes=[rr.TimeColumn("time", duration=t)],
                    columns=rr.Scalars.columns(scalars=np.where(np.isfinite(values), values, np.nan)),
                )
    circle = np.exp(1j * np.linspace(0, 2 * np.pi, 181))
    rec.log("eigenvalues/unit_circle", rr.LineStrips2D([np.column_stack([circle.real, circle.imag])]), static=True)
    for kind, model in (("closed_loop", result.closed_loop), ("plant", result.plant)):
        eig = None if model is None else model_eigenvalues(model)
        if eig is not None:
            rec.log(f"eigenvalues/{kind}", rr.Points2D(np.column_stack([eig.real, eig.imag]), radii=0.01), static=True)
    sweep = result.report.get("sweep")
    if sweep:
        index = rr.TimeColumn("alpha_index", sequence=np.arange(len(sweep["alpha"])))
        series = {
            "log10_alpha": np.log10(sweep["alpha"]),
            "cv_r2": sweep["cv_r2_mean"],
            "spectral_radius_closed_loop": sweep["spectral_radius_closed_loop"],
            "spectral_radius_plant": sweep["spectral_radius_plant"],
        }
        for key, values in series.items():
            if values is not None:
                values = np.asarray(values, dtype=float)
                rec.send_columns(
                    f"sweep/{key}",
                    indexes=[index],
                    columns=rr.Scalars.columns(scalars=np.where(np.isfinite(values), values, np.nan)),
                )
    if result.report.get("search"):
        _log_search(rec, result.report["search"])
    rrd.save()
