"""Figures (--figures): what each figure plots is the report's and the model's arrays, not pixels.

Every figure is drawn by ``identify.report.figures.draw``; the tests record the matplotlib Figures it
returns and read the plotted arrays back from their ``Line2D`` artists (gid = curve label).
"""

from __future__ import annotations

import json
import re
import sys

import numpy as np
import pytest

from qube_koopman.identify.report import figures as figures_module
from qube_koopman.identify.cli.identify import main as qube_identify
from qube_koopman.reproduce.cli.reproduce import main as qube_reproduce


@pytest.fixture
def drawn(monkeypatch):
    """Every Figure ``draw`` returns, by its title (the first axes' title)."""
    found = {}
    original = figures_module.draw

    def recording(data):
        fig = original(data)
        found[fig.axes[0].get_title()] = fig
        return fig

    monkeypatch.setattr(figures_module, "draw", recording)
    return found


def lines(fig) -> dict:
    """The figure's plotted lines by gid: {gid: (n, 2) array of x, y}."""
    return {line.get_gid(): line.get_xydata() for ax in fig.axes for line in ax.get_lines() if line.get_gid()}


def nan_equal(a, b) -> bool:
    return np.array_equal(np.asarray(a, dtype=float), np.asarray(b, dtype=float), equal_nan=True)


@pytest.mark.dataset
@pytest.mark.slow
def test_identify_figures_plot_the_reported_arrays(small_set, tmp_path, drawn, capsys):
    from qube_koopman.daq.log.names import find_logs
    from qube_koopman.identify.data.logs import load_logs
    from qube_koopman.identify.models.model_file import load_model
    from qube_koopman.identify.metrics import r2_score

    test_logs = find_logs(small_set / "test")
    chosen = ["2", test_logs[3].name]  # a position and a file name
    code = qube_identify(
        [
            str(a)
            for a in (
                "--train",
                small_set / "train",
                "--test",
                small_set / "test",
                "--out",
                tmp_path,
                "--alpha-sweep",
                "1e-3",
                "1e3",
                "4",
                "--cv-splits",
                "2",
                "--offsets",
                "alpha",
                "--figures",
                "--figure-episodes",
                *chosen,
            )
        ]
    )
    assert code == 0, capsys.readouterr().err
    report = json.loads((tmp_path / "report.json").read_text())
    model = load_model(tmp_path / "model.json")
    logs = {log.path.name: log for log in load_logs(test_logs, skip=500)}

    # measured vs predicted: the log's own samples, predictions whose R^2 is the report's
    start = report["scored_from_sample"]
    assert start == 500
    for name in (test_logs[1].name, test_logs[3].name):
        (fig,) = [f for title, f in drawn.items() if title.startswith(name.removesuffix(".mcap") + ", R^2 ")]
        got, log = lines(fig), logs[name]
        t = np.arange(log.trajectory.n_samples) * log.trajectory.dt
        predicted = np.column_stack([got["theta predicted"][:, 1], got["alpha predicted"][:, 1]])
        for j, state in enumerate(("theta", "alpha")):
            assert np.array_equal(got[f"{state} measured"], np.column_stack([t, log.trajectory.x[:, j]]))
            assert np.array_equal(got[f"{state} predicted"][:, 0], t)
        r2 = r2_score(log.trajectory.x[start:], predicted[start:])
        assert r2 == pytest.approx(report["test"]["r2_per_episode"][report["scored_logs"].index(name)], abs=1e-12)
        assert got["mark: first scored sample"][0, 0] == pytest.approx(start * log.trajectory.dt)
        # the interval: the band written to predictions/, shaded over the scored samples
        band = np.load(tmp_path / "predictions" / name.replace(".mcap", ".npz"))
        for j, state in enumerate(("theta", "alpha")):
            (shade,) = [c for ax in fig.axes for c in ax.collections if c.get_gid() == f"{state} 95% interval"]
            edges = np.concatenate([path.vertices for path in shade.get_paths()])
            assert edges[:, 0].min() == pytest.approx(band["t"][0])
            assert edges[:, 1].min() == pytest.approx(band["lower"][:, j].min())
            assert edges[:, 1].max() == pytest.approx(band["upper"][:, j].max())

    # eigenvalues: the model file's, with the report's spectral radii
    got = lines(drawn["eigenvalues and the unit circle"])
    for label, kind in (("closed loop", "closed_loop"), ("plant", "plant")):
        expected = np.linalg.eigvals(getattr(model, kind).A)
        plotted = got[label][:, 0] + 1j * got[label][:, 1]
        np.testing.assert_allclose(np.sort_complex(plotted), np.sort_complex(expected), atol=1e-9)
        assert np.max(np.abs(plotted)) == pytest.approx(report["spectral_radius"][kind], rel=1e-9)
    assert np.allclose(np.hypot(*got["unit circle"].T), 1.0)

    # the alpha sweep: the report's alphas, CV scores, radii and chosen alpha
    got, sweep = lines(drawn["regularization sweep"]), report["sweep"]
    assert nan_equal(got["CV R^2"], np.column_stack([sweep["alpha"], sweep["cv_r2_mean"]]))
    assert nan_equal(got["spectral radius, plant"][:, 1], sweep["spectral_radius_plant"])
    assert nan_equal(got["spectral radius, closed loop"][:, 1], sweep["spectral_radius_closed_loop"])
    assert got["mark: chosen alpha"][0, 0] == report["alpha"]

    # written as PNG and PDF, listed in report.json, embedded in report.md by relative links
    assert len(report["figures"]) == len(drawn) == 4
    md = (tmp_path / "report.md").read_text()
    for entry in report["figures"]:
        assert (tmp_path / entry["png"]).stat().st_size > 1000 and (tmp_path / entry["pdf"]).stat().st_size > 1000
        assert f"]({entry['png']})" in md and f"]({entry['pdf']})" in md
    assert set(re.findall(r"\]\((figures/[^)]+)\)", md)) == {e[k] for e in report["figures"] for k in ("png", "pdf")}


@pytest.mark.parametrize(
    "command, argv",
    [
        (qube_identify, ["--train", "a.mcap", "--test", "b.mcap", "--figures"]),
        (qube_reproduce, ["qube", "--data", "{tmp}", "--figures"]),
    ],
)
def test_figures_without_matplotlib_is_one_line(command, argv, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib raises ImportError
    code = command([a.replace("{tmp}", str(tmp_path)) for a in argv] + ["--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 1
    assert err.count("\n") == 1 and "Traceback" not in err
    assert 'error: --figures needs matplotlib, which is optional: pip install "qube-koopman[figures]"' in err
    assert not (tmp_path / "out").exists()  # refused before any work


@pytest.mark.dataset
def test_figure_episode_options_need_figures_and_a_test_episode(small_set, tmp_path, capsys):
    code = qube_identify(
        [
            "--train",
            str(small_set / "train"),
            "--test",
            str(small_set / "test"),
            "--figure-episodes",
            "1",
            "--out",
            str(tmp_path),
        ]
    )
    assert code == 2 and "--figure-episodes chooses what --figures draws: add --figures" in capsys.readouterr().err
    code = qube_identify(
        [
            "--train",
            str(small_set / "train"),
            "--test",
            str(small_set / "test"),
            "--figures",
            "--figure-episodes",
            "9",
            "--out",
            str(tmp_path / "o"),
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and "--figure-episodes 9: not a test episode (a position 1 to 4" in err
    assert not (tmp_path / "o").exists()


def _synthetic_results() -> dict:
    """A reproduce_qube results dict in miniature: 5 alphas, 3-state models, a 50-sample episode."""
    from qube_koopman.reproduce.qube_study import ROWS

    rng = np.random.default_rng(0)
    alphas = np.logspace(-3, 3, 5).tolist()
    sweep = {
        "alpha": alphas,
        **{
            m: {
                "cv_r2_cl": [0.9, 0.8, -np.inf, 0.5, 0.1],
                "cv_r2_plant": [-np.inf, -np.inf, -np.inf, 0.2, 0.3],
                "spectral_radius_closed_loop": [1.0, 1.0, 1.2, 1.5, 2.0],
                "spectral_radius_plant": [1.03, 1.02, 1.0, 0.99, 0.98],
            }
            for m in ("edmd", "cl-edmd")
        },
    }
    koopman = [row for row in ROWS if row.method != "arx"]
    eig = {
        row.key: {
            kind: {"real": rng.normal(size=3).tolist(), "imag": [0.0, 0.3, -0.3]} for kind in ("closed_loop", "plant")
        }
        for row in koopman
    }
    measured = rng.normal(size=(50, 2))
    predicted = {row.key: measured + 0.01 * rng.normal(size=(50, 2)) for row in ROWS}
    predicted["edmd_plant_plant"][10:] = np.inf  # a diverged prediction
    plant = {row.key: measured + 0.02 * rng.normal(size=(50, 2)) for row in koopman}
    plant["cl_edmd_cl_cl"] *= np.exp(np.arange(50))[:, None]  # an unstable plant: finite, far out of range
    rows = {
        row.key: {"alpha": 1e-3, "r2_per_episode": [0.5, -np.inf if row.key == "edmd_plant_plant" else 0.9]}
        for row in ROWS
    }
    return {
        "sweep": sweep,
        "eigenvalues": eig,
        "rows": rows,
        "labels": {row.key: row.label for row in ROWS},
        "figure_episode": {
            "name": "ep.mcap",
            "index": 1,
            "dt": 0.002,
            "measured": measured,
            "r": rng.normal(size=(50, 2)),
            "f": rng.normal(size=(50, 1)),
            "u": rng.normal(size=(50, 1)),
            "predicted": predicted,
            "plant_predicted": plant,
        },
    }


def test_paper_figures_plot_the_results_arrays():
    from qube_koopman.reproduce.qube_figures import EIGENVALUE_ROWS, METHODS, qube_figures

    results = _synthetic_results()
    specs = {spec.stem: spec for spec in qube_figures(results)}
    assert set(specs) == {
        "spectral_radius_cl",
        "spectral_radius_plant",
        "cross_validation_cl",
        "cross_validation_plant",
        "eigenvalues_cl",
        "eigenvalues_plant",
        "inputs",
        "predictions_cl",
        "predictions_plant",
    }
    sweep = results["sweep"]
    for stem, key in (
        ("spectral_radius_cl", "spectral_radius_closed_loop"),
        ("cross_validation_plant", "cv_r2_plant"),
        ("spectral_radius_plant", "spectral_radius_plant"),
        ("cross_validation_cl", "cv_r2_cl"),
    ):
        got = lines(figures_module.draw(specs[stem].data))
        for method, label in METHODS:
            values = np.array(sweep[method][key], dtype=float)
            assert nan_equal(
                got[label], np.column_stack([sweep["alpha"], np.where(np.isfinite(values), values, np.nan)])
            )
    for stem, kind in (("eigenvalues_cl", "closed_loop"), ("eigenvalues_plant", "plant")):
        got = lines(figures_module.draw(specs[stem].data))
        assert len(got) == 5  # four rows and the unit circle
        for key in EIGENVALUE_ROWS:
            e = results["eigenvalues"][key]
            (label,) = [g for g in got if g.startswith(results["labels"][key] + ",")]
            assert np.array_equal(got[label], np.column_stack([e[kind]["real"], e[kind]["imag"]]))
    episode = results["figure_episode"]
    t = np.arange(50) * 0.002
    got = lines(figures_module.draw(specs["inputs"].data))
    assert np.array_equal(got["r theta"], np.column_stack([t, episode["r"][:, 0]]))
    assert np.array_equal(got["f"], np.column_stack([t, episode["f"][:, 0]]))
    for stem, which, diverged in (
        ("predictions_cl", "predicted", "edmd_plant_plant"),
        ("predictions_plant", "plant_predicted", "cl_edmd_cl_cl"),
    ):
        fig = figures_module.draw(specs[stem].data)
        for ax, j in zip(fig.axes, range(2)):
            plotted = {line.get_gid(): line.get_xydata() for line in ax.get_lines()}
            assert len(plotted) == len(episode[which])
            for key, prediction in episode[which].items():
                error = episode["measured"][:, j] - prediction[:, j]
                assert nan_equal(plotted[results["labels"][key]][:, 1], np.where(np.isfinite(error), error, np.nan))
            # the diverged row leaves the plot: the y range is the others'
            others = [episode["measured"][:, j] - p[:, j] for k, p in episode[which].items() if k != diverged]
            assert ax.get_ylim() == pytest.approx((1.1 * np.min(others), 1.1 * np.max(others)))
    u = lines(figures_module.draw(specs["predictions_plant"].data))["plant input u"]
    assert np.array_equal(u, np.column_stack([t, episode["u"][:, 0]]))


def test_trajectory_figures_choose_episodes_and_keep_diverged_predictions_off_the_plot():
    from types import SimpleNamespace

    names = ["a.mcap", "b.mcap", "c.mcap"]
    assert figures_module.choose_episodes(names, None, [0.9, 0.95, -np.inf]) == [1, 0]  # best, worst finite
    assert figures_module.choose_episodes(names, None, [None, None, None]) == [0]
    assert figures_module.choose_episodes(names, ["3", "a", "c.mcap"], None) == [2, 0]
    with pytest.raises(ValueError, match="--figure-episodes d: not a test episode"):
        figures_module.choose_episodes(names, ["d"], None)

    t = np.arange(100) * 0.002
    truth = np.column_stack([np.sin(t), 0.1 * np.cos(t)])
    diverged = truth.copy()
    diverged[50:, 1] = np.exp(np.arange(50.0)) * 1e200  # alpha: finite, then inf
    result = SimpleNamespace(
        test_names=names[:2],
        test_time=[t, t],
        test_truth=[truth, truth],
        test_predictions=[truth + 0.01, diverged],
        closed_loop=None,
        plant=None,
        report={"scored_logs": names[:2], "test": {"r2_per_episode": [0.99, -np.inf]}, "scored_from_sample": 1},
    )
    specs = figures_module.identification_figures(result, ["1", "2"])
    assert [s.stem for s in specs] == ["trajectory_a", "trajectory_b"]  # no models: no eigenvalue figure
    good, bad = (figures_module.draw(s.data) for s in specs)
    assert good.axes[0].get_title() == "a, R^2 0.9900" and bad.axes[0].get_title() == "b, R^2 -inf"
    assert np.array_equal(
        lines(bad)["alpha predicted"][:, 1], np.where(np.isfinite(diverged[:, 1]), diverged[:, 1], np.nan)
    )
    lo, hi = bad.axes[1].get_ylim()  # the measured range with a margin: the diverged prediction leaves the plot
    assert lo < truth[:, 1].min() and hi > truth[:, 1].max() and hi - lo < 1
    assert specs[1].data.ylims[0] is None  # theta stayed in range: autoscaled


def test_a_long_title_fits_the_figure():
    """An episode's name in a series plot's title ran past both edges of the saved figure."""
    pytest.importorskip("matplotlib")
    from qube_koopman.identify import Curve, SeriesPlot, draw

    t = np.linspace(0.0, 1.0, 50)
    title = "qube_20261201T235548.995_837_262_110 under soft-theta (offset estimated), a little longer still"
    plot = SeriesPlot(
        title, t, "time (s)", ("theta (rad)", "alpha (rad)"), (Curve("theta", t, panel=0), Curve("alpha", -t, panel=1))
    )
    fig = draw(plot)
    fig.canvas.draw()
    box = fig.axes[0].title.get_window_extent(fig.canvas.get_renderer())
    assert fig.axes[0].get_title() == title
    assert 0 <= box.x0 and box.x1 <= fig.bbox.width and box.y1 <= fig.bbox.height, (box, fig.bbox)
