"""The design's uncertainty: the predicted figures' interval and the robust design.

- the model file: the bootstrap plants and held-out figures ``qube-identify`` writes come back as
  plants (their rows of the measured states, the rest the point plant's);
- the batched simulation of the members is :func:`design.predict.predict_cost`, sample for sample;
- the interval from members equals an independent computation (a Monte Carlo of the same mixture);
- no members: the design says there is no interval and why, instead of failing; ``--robust`` is
  refused with the same reason.
"""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from qube_koopman.design import Weights, design_lq, linear_plant
from qube_koopman.design.cli.design import main as design_main
from qube_koopman.design.predict import predict_cost, rig_excitations
from qube_koopman.design.uncertainty import (
    FIGURES,
    NO_MEMBERS,
    ModelUncertainty,
    figure_interval,
    member_figures,
    model_uncertainty,
)
from qube_koopman.identify import Constant, Delay, KoopmanModel, Lifting
from qube_koopman.identify.models.model_file import load_model, save_model, uncertainty_to_dict
from qube_koopman.identify.uncertainty.spectra import error_spectra
from qube_koopman.core.lti import DiscreteStateSpace

NAMES = ("theta", "alpha")


def _plant(d: int = 3, seed: int = 0) -> KoopmanModel:
    """An unstable arm-and-pendulum-like plant over ``d`` delays and a constant, randomly perturbed."""
    rng = np.random.default_rng(seed)
    lifting = Lifting([Delay(d), Constant()]).fit([np.zeros((50, 2))], NAMES)
    n = lifting.n_features_out_
    A = np.eye(n, k=0) * 0.5
    A[:2] = 0.0
    A[:2, :4] = [[1.9, 0.0, -0.9, 0.0], [0.0, 2.02, 0.0, -1.0]]
    A[:2, : 2 * (d + 1)] += 0.01 * rng.standard_normal((2, 2 * (d + 1)))
    A[:2, -1] = [1e-4, -2e-4]
    B = np.zeros((n, 1))
    B[:2, 0] = [2e-4, -2e-4]
    return KoopmanModel(A, B, lifting, ("u",), dt=0.002)


def _members(plant: KoopmanModel, n: int = 6, size: float = 1e-3) -> list[KoopmanModel]:
    rng = np.random.default_rng(7)
    out = []
    for _ in range(n):
        A, B = plant.A.copy(), plant.B.copy()
        A[:2, :-1] *= 1 + size * rng.standard_normal(A[:2, :-1].shape)
        B[:2] *= 1 + size * rng.standard_normal((2, 1))
        A[2:] = np.nan  # a bootstrap refit fits only the rows a re-lifted prediction uses
        out.append(KoopmanModel(A, B, plant.lifting, ("u",), dt=plant.dt))
    return out


HELD_OUT = np.array(
    [
        [[1.05e-2, 1.50, 7.0], [1.00e-2, 1.45, 6.5]],
        [[1.51e-2, 1.55, 7.3], [1.48e-2, 1.47, 6.9]],
        [[1.30e-2, 1.49, 6.8], [1.31e-2, 1.44, 6.6]],
        [[1.42e-2, 1.52, 7.1], [1.36e-2, 1.46, 6.7]],
    ]
)


def _spectra(n: int = len(HELD_OUT)) -> dict:
    """Error spectra of ``n`` made-up held-out episodes (3 s each) under a static PD."""
    rng = np.random.default_rng(5)
    measured = [rng.standard_normal((1500, 2)).cumsum(axis=0) * 1e-3 for _ in range(n)]
    predicted = [x + 1e-3 * rng.standard_normal(x.shape) for x in measured]
    voltage = [rng.standard_normal(1500) for _ in range(n)]
    target = [np.zeros(1500)] * n
    pd = DiscreteStateSpace(np.zeros((1, 1)), np.zeros((1, 2)), np.zeros((1, 1)), [[-5.0, -30.0]], 0.002)
    return error_spectra(measured, predicted, voltage, target, [pd] * n, 0.002, 500).as_dict()


def _save(path, plant, members=None, spectra=None):
    uncertainty = (
        None if members is None else uncertainty_to_dict(plant, members, HELD_OUT, seed=3, skip=500, spectra=spectra)
    )
    save_model(
        path,
        method="cl-edmd",
        alpha=1e-3,
        plant=plant,
        closed_loop=None,
        controller=None,
        measured=[0, 1],
        training={"logs": []},
        uncertainty=uncertainty,
    )
    return path


def _provenance(path) -> dict:
    """The controller file's ``[provenance]`` as written."""
    return tomllib.loads(path.read_text())["provenance"]


def test_the_model_file_gives_back_the_bootstrap_plants_and_the_held_out_figures(tmp_path):
    plant = _plant()
    members = _members(plant)
    model = load_model(_save(tmp_path / "model.json", plant, members))
    assert len(model.plant_members) == len(members)
    for loaded, member in zip(model.plant_members, members):
        np.testing.assert_array_equal(loaded.A[:2], member.A[:2])
        np.testing.assert_array_equal(loaded.B[:2], member.B[:2])
        np.testing.assert_array_equal(loaded.A[2:], plant.A[2:])  # the rows no prediction uses: the plant's
    uncertainty = model_uncertainty(model)
    np.testing.assert_array_equal(uncertainty.held_out, HELD_OUT)
    np.testing.assert_allclose(uncertainty.model_error(), np.log(HELD_OUT[:, 0] / HELD_OUT[:, 1]))
    assert load_model(_save(tmp_path / "old.json", plant)).plant_members is None


def test_the_members_batched_simulation_is_predict_cost_sample_for_sample():
    plant = _plant(4)
    design = design_lq(linear_plant(plant), Weights())
    excitations = rig_excitations(2, 3, 4.0)
    members = [plant] + [_plant(4, seed) for seed in (1, 2)]
    figures = member_figures([linear_plant(m) for m in members], design, excitations)
    for model, got in zip(members, figures):
        expected = predict_cost(model, design.controller, excitations)
        np.testing.assert_allclose(
            got, np.column_stack([expected.cost, expected.voltage_rms, expected.voltage_peak]), rtol=1e-10
        )


def test_the_interval_from_members_is_the_mixtures_quantiles_by_monte_carlo():
    """Members' log-ratios shifted by the held-out errors' Student-t: the quantiles agree with 2 million draws."""
    rng = np.random.default_rng(0)
    nominal = np.abs(rng.normal(1.0, 0.1, (5, 3)))
    members = nominal * np.exp(rng.normal(0, 0.02, (8, 1, 3)))
    error = rng.normal(0.03, 0.02, (6, 3))
    predicted = {name: 2.0 + i for i, name in enumerate(FIGURES)}
    interval = figure_interval(predicted, nominal, members, error, 0.9)
    pooled = np.stack([members[..., 0].mean(-1), np.sqrt((members[..., 1] ** 2).mean(-1)), members[..., 2].max(-1)], -1)
    base = np.array([nominal[:, 0].mean(), np.sqrt((nominal[:, 1] ** 2).mean()), nominal[:, 2].max()])
    n = len(error)
    draws = 2_000_000
    for i, name in enumerate(FIGURES):
        shift = np.log(pooled[rng.integers(0, len(members), draws), i] / base[i])
        t = rng.standard_t(n - 1, draws)
        scale = error[:, i].std(ddof=1) * np.sqrt(1 + 1 / n)
        samples = predicted[name] * np.exp(shift + error[:, i].mean() + scale * t)
        lo, hi = np.quantile(samples, [0.05, 0.95])
        assert interval.lower[name] == pytest.approx(lo, rel=2e-3)
        assert interval.upper[name] == pytest.approx(hi, rel=2e-3)
    alone = figure_interval(predicted, nominal, members, None, 0.9)  # the members alone: their own quantiles
    for i, name in enumerate(FIGURES):
        ratios = pooled[:, i] / base[i]
        expected = predicted[name] * np.array(
            [np.quantile(ratios, 0.05, method="lower"), np.quantile(ratios, 0.95, method="higher")]
        )
        np.testing.assert_allclose([alone.lower[name], alone.upper[name]], expected, rtol=1e-12)
    assert alone.n_held_out == 0 and "alone" in alone.sources


def test_a_diverging_member_gives_an_infinite_upper_bound():
    nominal = np.ones((2, 3))
    members = np.ones((3, 2, 3))
    members[1, 0, 0] = np.inf
    interval = figure_interval({name: 1.0 for name in FIGURES}, nominal, members, None, 0.95)
    assert interval.upper["J"] == np.inf and np.isfinite(interval.upper["voltage_rms"])


def test_too_few_held_out_episodes_leave_the_model_error_out():
    assert ModelUncertainty([], HELD_OUT[:2]).model_error() is None
    assert ModelUncertainty([], HELD_OUT).model_error().shape == (4, 3)


def test_without_bootstrap_plants_the_design_says_there_is_no_interval_and_robust_is_refused(tmp_path, capsys):
    path = _save(tmp_path / "model.json", _plant())
    out = tmp_path / "c.toml"
    assert design_main([str(path), "--out", str(out), "--episodes", "2", "--duration", "4"]) == 0
    assert f"no interval: {NO_MEMBERS}" in capsys.readouterr().out
    assert _provenance(out)["interval"] == {"none": NO_MEMBERS}
    assert (
        design_main([str(path), "--out", str(tmp_path / "r.toml"), "--robust", "--episodes", "2", "--duration", "4"])
        == 2
    )
    err = capsys.readouterr().err
    assert "--robust designs against the model's uncertainty, and the model file holds no bootstrap plants" in err
    assert not (tmp_path / "r.toml").exists()


def test_with_bootstrap_plants_the_report_gives_the_interval_and_the_robust_choice(tmp_path, capsys):
    plant = _plant()
    path = _save(tmp_path / "model.json", plant, _members(plant))
    out = tmp_path / "c.toml"
    assert (
        design_main(
            [str(path), "--out", str(out), "--episodes", "2", "--duration", "4", "--robust", "--interval", "0.9"]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert "interval at 0.9 (from 6 bootstrap plants and the model's error on 4 held-out training episodes)" in text
    assert "robust: " in text
    p = _provenance(out)
    J = p["interval"]["J"]
    assert J["lower"] < J["upper"] and J["predicted"] == pytest.approx(p["predicted"]["J"])
    assert p["robust"]["r_voltage_scale"] in (1.0, 2.0, 4.0, 8.0)


def test_with_the_error_spectra_the_report_says_the_error_is_propagated(tmp_path, capsys):
    plant = _plant()
    path = _save(tmp_path / "model.json", plant, _members(plant), _spectra())
    out = tmp_path / "c.toml"
    assert design_main([str(path), "--out", str(out), "--episodes", "2", "--duration", "4"]) == 0
    text = capsys.readouterr().out
    assert "held-out training episodes, propagated through the designed loop)" in text
    assert "training controller's ratio" not in text
    interval = _provenance(out)["interval"]
    assert interval["propagated"] is True
    for name in ("J", "voltage_rms", "voltage_peak"):
        figure = interval[name]
        assert 0 < figure["lower"] < figure["upper"] < np.inf and np.isfinite(figure["expected"]), (name, figure)


def test_each_figure_line_says_what_its_numbers_are_and_its_interval_holds_the_expected_figure(tmp_path, capsys):
    """The point prediction can lie outside the interval (the interval is of the loop's figure, moved by the model's
    error): the line names each number and says where the prediction lies rather than "X in [a, b]"."""
    import re

    plant = _plant()
    path = _save(tmp_path / "model.json", plant, _members(plant), _spectra())
    assert design_main([str(path), "--out", str(tmp_path / "c.toml"), "--episodes", "2", "--duration", "4"]) == 0
    text = capsys.readouterr().out
    pattern = re.compile(
        r"predicted (\S+) \(the point model\), (\S+) with the model's error; "
        r"95 % interval of the loop's figure (\S+) to (\S+), its median (\S+?)"
        r"(?: \(the point model's prediction lies (below|above) it\))?$"
    )
    found = [m for line in text.splitlines() if (m := pattern.search(line))]
    assert len(found) == 3, text
    for m in found:
        predicted, expected, lower, upper, median = (float(m.group(i)) for i in range(1, 6))
        assert lower <= median <= upper and np.isfinite(expected)
        assert m.group(6) == ("below" if predicted < lower else "above" if predicted > upper else None), m.group(0)


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda s: s.pop("input"), "input is missing"),
        (lambda s: s["error"]["re"].pop(), "error must hold re and im of shape (4, "),
        (
            lambda s: s.__setitem__("controller_of_episode", [0, 0, 0, 3]),
            "controller_of_episode must give each of the 4",
        ),
        (lambda s: s["edges_hz"].__setitem__(1, float("nan")), "edges_hz has a non-finite entry"),
        (lambda s: s.__setitem__("error_input", [1.0]), "error_input is missing (an object of re and im)"),
    ],
    ids=["missing", "shape", "index", "nan", "type"],
)
def test_damaged_error_spectra_are_one_error_naming_the_entry(tmp_path, capsys, damage, message):
    plant = _plant()
    spectra = _spectra()
    damage(spectra)
    path = _save(tmp_path / "model.json", plant, _members(plant), spectra)
    assert design_main([str(path), "--out", str(tmp_path / "c.toml"), "--episodes", "2", "--duration", "4"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{path}: uncertainty.held_out.error_spectra: {message}" in err[0], err
    assert not (tmp_path / "c.toml").exists()


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda h: h["predicted"].pop(), "uncertainty.held_out: 4 measured rows, 3 predicted"),
        (
            lambda h: h.__setitem__("measured", [[1.0, 2.0]] * 4),
            "uncertainty.held_out.measured must be rows of 3 numbers",
        ),
        (lambda h: h.__setitem__("predicted", "none"), "uncertainty.held_out.predicted must be rows of 3 numbers"),
    ],
    ids=["rows", "columns", "type"],
)
def test_damaged_held_out_figures_are_one_error_naming_the_entry(tmp_path, capsys, damage, message):
    import json

    plant = _plant()
    path = _save(tmp_path / "model.json", plant, _members(plant))
    data = json.loads(path.read_text())
    damage(data["uncertainty"]["held_out"])
    path.write_text(json.dumps(data))
    assert design_main([str(path), "--out", str(tmp_path / "c.toml"), "--episodes", "2", "--duration", "4"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{path}: {message}" in err[0], err


def test_a_level_outside_zero_one_is_a_usage_error(tmp_path, capsys):
    path = _save(tmp_path / "model.json", _plant())
    assert design_main([str(path), "--out", str(tmp_path / "c.toml"), "--interval", "1.5"]) == 2
    assert "--interval must be a level between 0 and 1 (0: no interval), got 1.5" in capsys.readouterr().err


def test_the_robust_design_ranks_the_candidates_by_their_worst_case_and_leaves_out_unstable_ones():
    from dataclasses import replace

    from qube_koopman.design import DesignError
    from qube_koopman.design.uncertainty import robust_design

    plant = linear_plant(_plant())
    excitations = rig_excitations(2, 1, 3.0)
    agreeing = ModelUncertainty([plant, plant], None)
    # The first scale is the nominal one (it wins ties); here it is worse, so the ranking decides.
    choice = robust_design(plant, Weights(), agreeing, excitations, scales=(4.0, 1.0))
    assert choice.scale == 1.0 and choice.candidates[0]["worst_upper_J"] > choice.candidates[1]["worst_upper_J"]
    assert choice.candidates[1]["stable_members"] == 2 and choice.candidates[0]["stable_members"] is None
    strong = replace(plant, G=6 * plant.G)  # a refit whose input gain no candidate's closed loop survives
    with pytest.raises(DesignError, match="under every candidate design a bootstrap plant's closed loop is unstable"):
        robust_design(plant, Weights(), ModelUncertainty([plant, strong], None), excitations)


def test_j_has_one_definition_and_the_design_reports_it(tmp_path):
    """J = mean((theta - target_theta)^2) + mean(alpha^2) after the skip is core.qube.loop_cost alone: the design's
    predicted J, the bootstrap plants' batched J and identify's held-out J are its values."""
    from qube_koopman.core.qube import loop_cost
    from qube_koopman.design.predict import episode_cost, predict_loop
    from qube_koopman.design.controller_design import design_from_model
    from qube_koopman.identify.uncertainty import loop_figures

    # Its definition, by hand: tracking errors (1, -1) and alpha (2, 0) after one skipped sample.
    assert loop_cost([9.0, 1.0, 2.0], [0.0, 0.0, 3.0], [9.0, 2.0, 0.0], skip=1) == 1.0 + 2.0
    plant = _plant()
    report = design_from_model(_save(tmp_path / "model.json", plant), episodes=2, duration=3.0)
    loop = predict_loop(plant, report.controller, rig_excitations(1, 2, 3.0))
    J = np.array([loop_cost(loop.theta[i], loop.target_theta[i], loop.alpha[i]) for i in range(2)])
    assert np.all(J > 0)
    np.testing.assert_array_equal(report.predicted.cost, J)  # what the design reports, to the bit
    assert report.predicted.summary()["J"] == float(np.mean(J))
    # Over episodes at once (the batched simulations' form): the same sums, to rounding.
    np.testing.assert_allclose(loop_cost(loop.theta, loop.target_theta, loop.alpha), J, rtol=1e-12)
    batched = member_figures([linear_plant(plant)], report.design, rig_excitations(1, 2, 3.0))[0, :, 0]
    np.testing.assert_allclose(batched, J, rtol=1e-9)
    for i in range(2):
        assert episode_cost(loop.theta[i], loop.target_theta[i], loop.alpha[i], loop.voltage[i])[0] == J[i]
        x = np.column_stack([loop.theta[i], loop.alpha[i]])
        assert loop_figures(x, loop.target_theta[i], loop.voltage[i], 500)[0] == J[i]
