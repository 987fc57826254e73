"""Grey-box calibration (identify.calibrate): identifiability on simulated logs, solver pieces, CLI errors."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

from _episodes import QUBE_PD
from qube_koopman.daq.episode import REFERENCE_SIGNALS, stack_signals
from qube_koopman.daq.excitation import ExcitationSettings, generate_excitation
from qube_koopman.identify.calibrate import HoldRefused, PlantCalibration
from qube_koopman.identify.calibrate import shooting as ms
from qube_koopman.sim.pendulum import PendulumParameters, SensorModel, simulate_closed_loop

DT = 1 / 500
# Near the rig's calibrated values (a weaker motor with this much arm inertia lets the pendulum fall).
# A linear cable spring unless a test gives it the softening the rig's cables show.
TRUTH = PendulumParameters(
    km=0.048, Dr=2.0e-4, Cr=3.0e-4, Lp=0.126, Dp=4e-5, dead_zone=0.1, Jh=8e-5, delay=0.001, Kr=7e-4, cable_softening=0.0
)


def soft_pd():
    """The shipped second controller (soft-theta: the rig's structure with a three times softer arm)."""
    from qube_koopman.core.controller import controller_file, load_pd_gains, pd_controller

    return pd_controller(load_pd_gains(controller_file("soft-theta")))


def simulated_logs(
    params: PendulumParameters, n: int = 3, seconds: float = 6.0, seed: int = 0, controller=QUBE_PD, **closed_loop
):
    """Closed-loop episodes of the rig's excitation (active from 1 s), encoder noise and offsets; ``closed_loop``:
    more of simulate_closed_loop's arguments (a relaxation)."""
    rng = np.random.default_rng(seed)
    samples = int(seconds / DT)
    settings = ExcitationSettings(n_samples=samples, window_start=250, window_stop=samples)
    ex = [generate_excitation((11 + i, 22 + i, 33 + i), settings) for i in range(n)]
    refs = np.stack([stack_signals(e, REFERENCE_SIGNALS) for e in ex], axis=1)
    ff = np.stack([e.feedforward for e in ex], axis=1)
    offsets = rng.normal(0.0025, 0.002, n)
    state0 = np.column_stack([np.zeros(n), rng.uniform(-0.02, 0.02, n), np.zeros((n, 2))])
    run = simulate_closed_loop(
        state0, controller, refs, ff, params, SensorModel(noise_std=5e-4), alpha_offsets=offsets, rng=rng, **closed_loop
    )
    return ([run.measurements[:, i] for i in range(n)], [run.plant_input[:, i] for i in range(n)], offsets)


def test_parameter_map_round_trips():
    from dataclasses import asdict

    z = ms.from_params(TRUTH, PendulumParameters())
    assert asdict(ms.to_params(z, PendulumParameters())) == pytest.approx(asdict(TRUTH), rel=1e-12, abs=0)


def jacobian_matches_dense_differences(z, seg, method="tangents"):
    """The residuals at ``z`` and their dense forward differences, which the sparse Jacobian (by the
    simulation's tangents, or by grouped differences) matches within its pattern."""
    r0 = ms.residuals(z, seg, 2, PendulumParameters(), DT, 1e-3)
    J = ms.jacobian(z, r0, seg, 2, PendulumParameters(), DT, 1e-3, method=method).toarray()
    dense = np.empty_like(J)
    for j in range(z.size):
        zj = z.copy()
        zj[j] += 1e-6
        dense[:, j] = (ms.residuals(zj, seg, 2, PendulumParameters(), DT, 1e-3) - r0) / 1e-6
    np.testing.assert_allclose(J, dense, rtol=1e-4, atol=1e-3 * np.abs(dense).max())
    assert not np.any(J[ms.sparsity(seg, 2).toarray() == 0])
    return r0, dense


@pytest.mark.parametrize("method", ["tangents", "differences"])
@pytest.mark.parametrize("softening", [0.0, 5.0])  # a linear spring, and the rig's levelling pull
def test_sparse_jacobian_matches_dense_differences(method, softening):
    ys, us, _ = simulated_logs(TRUTH, n=2, seconds=1.0)
    seg = ms.make_segments(ys, us, horizon=10, skip=300, stride=40)
    rng = np.random.default_rng(1)
    # A fractional delay (1.7 samples) and a dead zone the voltage crosses: every term of the model is on.
    params = replace(TRUTH, cable_softening=softening, delay=0.0034, dead_zone=0.3)
    z = np.concatenate(
        [
            ms.from_params(params, PendulumParameters()),
            [2.0, 3.0],
            (np.column_stack([seg.y[0], rng.normal(0, 0.1, (seg.n, 2))])).ravel(),
        ]
    )
    assert np.mean(np.abs(seg.u) < params.dead_zone) > 0.05
    jacobian_matches_dense_differences(z, seg, method)


def test_jacobian_methods_agree_to_the_differences_rounding_on_the_datasets_scale():
    # The simulation's tangents and forward differences are two independent computations of the same
    # columns: they agree to the differences' truncation and rounding (about 1e-6 of a column's scale),
    # every physical variable and node, with per-segment weights, two setups and a known load on the arm.
    ys, us, _ = simulated_logs(replace(TRUTH, cable_softening=5.0), n=2, seconds=2.0)
    loads = [np.random.default_rng(7).normal(0, 0.3, len(u)) for u in us]
    seg = ms.make_segments(ys, us, horizon=100, skip=250, loads=loads)
    np.testing.assert_array_equal(seg.load[:, 1], loads[seg.episode[1]][seg.start[1] : seg.start[1] + 100])
    seg = replace(seg, setups={"Kr": seg.episode.copy()}, weight=np.linspace(0.5, 1.5, seg.n))
    rng = np.random.default_rng(2)
    z = np.concatenate(
        [
            ms.from_params(replace(TRUTH, cable_softening=5.0), PendulumParameters()),
            [12.0],
            [2.0, 3.0],
            (np.column_stack([seg.y[0], rng.normal(0, 0.3, (seg.n, 2))])).ravel(),
        ]
    )
    r0 = ms.residuals(z, seg, 2, PendulumParameters(), DT, 1e-3)
    tangents = ms.jacobian(z, r0, seg, 2, PendulumParameters(), DT, 1e-3).toarray()
    differences = ms.jacobian(z, r0, seg, 2, PendulumParameters(), DT, 1e-3, method="differences").toarray()
    scale = np.abs(differences).max(axis=0)
    assert np.all(np.abs(tangents - differences).max(axis=0) <= 2e-5 * np.maximum(scale, 1e-12))
    with pytest.raises(ValueError, match="unknown Jacobian method"):
        ms.jacobian(z, r0, seg, 2, PendulumParameters(), DT, 1e-3, method="adjoint")
    # Its normal matrix from the arrow's blocks is the general sparse product's, the same entries.
    J = ms.jacobian(z, r0, seg, 2, PendulumParameters(), DT, 1e-3)
    general, blocks = (J.T @ J).tocsc(), ms.normal_matrix(J, seg, 2)
    assert blocks.nnz == general.nnz
    np.testing.assert_allclose(blocks.toarray(), general.toarray(), rtol=1e-12, atol=1e-12 * abs(general).max())


@pytest.mark.parametrize("method", ["tangents", "differences"])
def test_sparse_jacobian_with_setups_matches_dense_differences(method):
    # Two setups: the second episode's segments simulate with their own cables' stiffness and delay,
    # two variables after the physical ones that touch only them.
    ys, us, _ = simulated_logs(TRUTH, n=2, seconds=1.0)
    seg = ms.make_segments(ys, us, horizon=10, skip=300, stride=40)
    seg = replace(seg, setups={"Kr": seg.episode.copy(), "delay": seg.episode.copy()})
    assert ms.setup_variables(seg) == [("Kr", 1), ("delay", 1)]
    rng = np.random.default_rng(1)
    z = np.concatenate(
        [
            ms.from_params(TRUTH, PendulumParameters()),
            [25.0, 2.5],
            [2.0, 3.0],
            (np.column_stack([seg.y[0], rng.normal(0, 0.1, (seg.n, 2))])).ravel(),
        ]
    )
    r0, dense = jacobian_matches_dense_differences(z, seg, method)
    for extra in (ms.N_PHYSICAL, ms.N_PHYSICAL + 1):
        column = dense[:, extra].reshape(seg.n, -1)
        assert np.all(column[seg.episode == 0] == 0) and np.abs(column[seg.episode == 1]).max() > 0
    values = ms.setup_values(z[: ms.N_PHYSICAL + 2], seg)
    np.testing.assert_allclose(values["Kr"], [TRUTH.Kr, 25.0 * 1e-4])
    np.testing.assert_allclose(values["delay"], [TRUTH.delay, 2.5e-3])
    # The second episode's residuals are those of the plain problem on its own with its setup's values.
    alone = ms.make_segments(ys[1:], us[1:], horizon=10, skip=300, stride=40)
    own = replace(TRUTH, Kr=2.5e-3, delay=2.5e-3)
    z_alone = np.concatenate(
        [ms.from_params(own, PendulumParameters()), [3.0], z[ms.N_PHYSICAL + 4 + 4 * np.sum(seg.episode == 0) :]]
    )
    np.testing.assert_allclose(
        r0.reshape(seg.n, -1)[seg.episode == 1].ravel(),
        ms.residuals(z_alone, alone, 1, PendulumParameters(), DT, 1e-3),
        rtol=1e-12,
        atol=1e-12,
    )


@pytest.mark.slow
def test_known_parameters_are_recovered_within_two_standard_errors():
    # The cables' pull softening as the rig's does (levelling off near 0.45 rad): the arm's excursions
    # under the rig's gains (up to 0.95 rad here) pin it down with the rest.
    known = replace(TRUTH, cable_softening=5.0)
    ys, us, offsets = simulated_logs(known)
    assert max(np.abs(y[:, 1]).max() for y in ys) < 0.5  # the simulated rig stayed up
    cal = PlantCalibration(horizon=0.2, skip=0.5, stride=0.2, nominal=PendulumParameters()).fit(ys, us, DT)
    assert "cable_softening" in cal.fitted_names_
    for name in cal.fitted_names_:
        fitted, truth, se = getattr(cal.params_, name), getattr(known, name), cal.standard_errors_[name]
        assert abs(fitted - truth) <= 2 * se + 1e-12, (name, fitted, truth, se)
        assert se < 0.2 * truth, (name, se)  # identified, not merely uncertain
    np.testing.assert_array_less(np.abs(cal.alpha_offsets_ - offsets), 2 * cal.alpha_offset_errors_ + 1e-9)
    # The one expected warning: the arm's torque constant and extra inertia are ~0.99 correlated.
    assert cal.warnings_ == [w for w in cal.warnings_ if w.startswith("km and Jh are strongly correlated")]
    assert len(cal.warnings_) <= 1


@pytest.mark.slow
def test_told_the_cables_relaxation_the_fit_recovers_the_spring_it_otherwise_takes_up():
    # Episodes of a twin whose cables relax (stiffer against fast motion by 0.1 V/rad, four fifths of the
    # spring's stiffness, relaxing over a second, as the rig's logs show): fitted without it, the spring
    # takes up the fast stiffness over its 0.2 s segments; simulated with the relaxation's torque along the
    # logged arm angle (what qube-calibrate --relaxation's passes do), every parameter comes back within
    # three of its standard errors (measured: at most 1.8) and the segments' residuals fall.
    from qube_koopman.sim.pendulum import CableRelaxation

    relaxation = CableRelaxation(fast=0.1, relaxing=0.1, time_constant=1.0)
    ys, us, _ = simulated_logs(TRUTH, n=2, relaxation=relaxation)
    fit = lambda: PlantCalibration(horizon=0.2, skip=0.5, stride=0.2, nominal=PendulumParameters())  # noqa: E731
    blind = fit().fit(ys, us, DT)
    told = fit().fit(ys, us, DT, loads=[relaxation.torque_of(y[:, 0], DT) for y in ys])
    for name in told.fitted_names_:
        fitted, truth, se = getattr(told.params_, name), getattr(TRUTH, name), told.standard_errors_[name]
        assert abs(fitted - truth) <= 3 * se + 1e-12, (name, fitted, truth, se)
    # Blind, the spring, the torque constant and the hub's inertia all come out high, each by more than ten of
    # its standard errors (measured: 23, 21 and 19; the spring by half the fast stiffness, km by a tenth).
    for name in ("Kr", "km", "Jh"):
        fitted, truth, se = getattr(blind.params_, name), getattr(TRUTH, name), blind.standard_errors_[name]
        assert fitted - truth > 10 * se, (name, fitted, truth, se)
    assert blind.params_.Kr - TRUTH.Kr > 0.3 * relaxation.fast * TRUTH.km / TRUTH.Rm  # of the fast N m/rad
    assert np.all(told.residual_rms_ < blind.residual_rms_) and told.cost_ < 0.95 * blind.cost_
    with pytest.raises(ValueError, match="one load per episode"):
        fit().fit(ys, us, DT, loads=[np.zeros(3), np.zeros(3)])


def test_the_validations_open_loop_predictions_carry_the_plants_relaxation():
    # The held-out logs' 0.25 s open-loop predictions simulate a relaxation plant's torque as its fit did:
    # on logs of a twin whose cables relax they come closer with it, and a zero relaxation changes nothing.
    from types import SimpleNamespace

    from qube_koopman.identify.calibrate.validate import open_loop_error
    from qube_koopman.sim.pendulum import CableRelaxation

    relaxation = CableRelaxation(fast=0.3, relaxing=0.3, time_constant=1.0)
    ys, us, offsets = simulated_logs(TRUTH, n=2, seconds=4.0, relaxation=relaxation)
    episodes = [SimpleNamespace(states=y, plant_input=u, dt=DT) for y, u in zip(ys, us)]
    plain = open_loop_error(episodes, TRUTH, offsets)
    told = open_loop_error(episodes, TRUTH, offsets, relaxation=[relaxation, relaxation])
    assert np.all(told[:, 0] < 0.9 * plain[:, 0]), (told, plain)
    np.testing.assert_array_equal(open_loop_error(episodes, TRUTH, offsets, relaxation=CableRelaxation(0, 0, 1)), plain)


def test_a_held_parameter_keeps_its_value_and_the_rest_are_recovered_around_it():
    # A linear cable spring (no levelling-off), held at that: the fit must not move it, give it no
    # error and no warning, and recover the rest within three of their (conditional) standard errors
    # (asymptotic ones, which take the encoders' quantization for white noise).
    known = replace(TRUTH, cable_softening=0.0)
    ys, us, _ = simulated_logs(known, n=2)
    fit = lambda hold, n=40: PlantCalibration(
        horizon=0.2, skip=0.5, stride=0.2, nominal=PendulumParameters(), hold=hold, max_nfev=n
    )  # noqa: E731
    cal = fit({"cable_softening": 0.0}).fit(ys, us, DT)
    assert cal.params_.cable_softening == 0.0 and cal.held_ == {"cable_softening": 0.0}
    assert cal.standard_errors_["cable_softening"] == 0.0 and cal.summary()["held"] == {"cable_softening": 0.0}
    assert not [w for w in cal.warnings_ if "cable_softening" in w]
    for name in set(cal.fitted_names_) - {"cable_softening"}:
        fitted, truth, se = getattr(cal.params_, name), getattr(known, name), cal.standard_errors_[name]
        assert 0 < se and abs(fitted - truth) <= 3 * se + 1e-12, (name, fitted, truth, se)
    # Held at a wrong value the same logs fit worse, and the stiffness absorbs what it can.
    wrong = fit({"cable_softening": 20.0}, 10).fit(ys, us, DT)  # (10 steps: a fit not done only costs more)
    assert (
        wrong.params_.cable_softening == 20.0
        and wrong.cost_ > 1.2 * cal.cost_
        and wrong.params_.Kr > 1.5 * cal.params_.Kr
    )


@pytest.mark.parametrize(
    ("hold", "setups", "message"),
    [
        ({"theta_rest": 0.0}, None, "cannot hold 'theta_rest': the fitted parameters are km, "),
        ({"Kr": 1e-3}, {"Kr": ["a", "b"]}, "cannot hold Kr: it has a value per setup in this fit"),
        ({"cable_softening": -1.0}, None, "cannot hold cable_softening at -1: its physical range is [0, 100]"),
        ({"km": 0.0}, None, "cannot hold km at 0: its physical range is ["),
    ],
)
def test_a_hold_the_fit_cannot_keep_is_refused_in_one_line(hold, setups, message):
    ys, us, _ = simulated_logs(TRUTH, n=2, seconds=2.0)
    with pytest.raises(HoldRefused, match="^" + re.escape(message)) as refused:
        PlantCalibration(horizon=0.2, skip=0.5, hold=hold).fit(ys, us, DT, setups=setups)
    assert isinstance(refused.value, ValueError) and refused.value.per_setup == (setups is not None)


@pytest.mark.slow
def test_known_parameters_are_recovered_from_two_controllers_logs_at_once():
    # Twin logs under the rig's gains and under soft-theta, fitted together (the fit is open loop:
    # the controllers only shape the excitation). A stiffer cable than TRUTH's, as under the soft day.
    truth = replace(TRUTH, Kr=1.2e-3)
    rig_y, rig_u, rig_off = simulated_logs(truth, n=2, seed=1)
    soft_y, soft_u, soft_off = simulated_logs(truth, n=2, seed=2, controller=soft_pd())
    assert max(np.abs(y[:, 1]).max() for y in soft_y) < 0.5  # the soft loop kept the pendulum up too
    # From the calibration's own start (the workbook's masses, another project's damping), as
    # qube-calibrate fits: the cost has local minima (the dead zone and the dry friction), and a start
    # at the shipped twin, which moves with each calibration, stopped in another (cost 0.02 % higher).
    cal = PlantCalibration(horizon=0.2, skip=0.5, stride=0.2).fit(rig_y + soft_y, rig_u + soft_u, DT)
    # Within three asymptotic standard errors (they take the encoders' quantization for white noise).
    for name in cal.fitted_names_:
        fitted, value, se = getattr(cal.params_, name), getattr(truth, name), cal.standard_errors_[name]
        assert abs(fitted - value) <= 3 * se + 1e-12, (name, fitted, value, se)
    assert cal.standard_errors_["Kr"] < 0.05 * truth.Kr and cal.params_.Kr == pytest.approx(truth.Kr, rel=0.02)
    np.testing.assert_array_less(
        np.abs(cal.alpha_offsets_ - np.concatenate([rig_off, soft_off])), 2.5 * cal.alpha_offset_errors_ + 1e-9
    )


@pytest.mark.slow
def test_each_days_cables_and_each_sessions_delay_are_recovered_with_the_rest_of_the_physics_shared():
    # The rig's recording days: the cables dressed softer on one (under the rig's gains) than on the
    # other (under soft-theta), and on the second day two sessions whose host ran with different
    # latencies. Fitted per setup, each day's stiffness and each session's delay come back within three
    # standard errors and the other parameters are the shared truth's; one stiffness for all lands in
    # between, off both, which is what the twin fitted on both days' logs did. The cables' pull softens
    # alike on both days (one softening, as the rig's logs show): it comes back with the shared physics.
    truth = [
        replace(TRUTH, Kr=6e-4, delay=1e-3, cable_softening=5.0),
        replace(TRUTH, Kr=2e-3, delay=2e-3, cable_softening=5.0),
        replace(TRUTH, Kr=2e-3, delay=5e-3, cable_softening=5.0),
    ]
    logs = [
        simulated_logs(truth[0], n=2, seed=1),
        simulated_logs(truth[1], n=1, seed=2, controller=soft_pd()),
        simulated_logs(truth[2], n=1, seed=3, controller=soft_pd()),
    ]
    ys = [y for log in logs for y in log[0]]
    us = [u for log in logs for u in log[1]]
    setups = {"Kr": ["2023-08-28"] * 2 + ["2023-09-15"] * 2, "delay": ["a", "a", "b", "c"]}
    kwargs = dict(horizon=0.2, skip=0.5, stride=0.2, nominal=PendulumParameters())
    cal = PlantCalibration(**kwargs).fit(ys, us, DT, setups=setups)
    expected = {"Kr": {"2023-08-28": 6e-4, "2023-09-15": 2e-3}, "delay": {"a": 1e-3, "b": 2e-3, "c": 5e-3}}
    assert {k: list(v) for k, v in cal.setup_values_.items()} == {k: list(v) for k, v in expected.items()}
    for name, values in expected.items():
        for label, value in values.items():
            fitted, se = cal.setup_values_[name][label], cal.setup_errors_[name][label]
            assert abs(fitted - value) <= 3 * se and se < 0.05 * value, (name, label, fitted, se)
    # The shared physics within 3.5 asymptotic standard errors (they take the encoders' quantization for
    # white noise: measured at most 3.2 of them).
    assert "cable_softening" in cal.fitted_names_
    for name in cal.fitted_names_:
        if name not in expected:
            fitted, value, se = getattr(cal.params_, name), getattr(truth[0], name), cal.standard_errors_[name]
            assert abs(fitted - value) <= 3.5 * se + 1e-12, (name, fitted, value, se)
    assert cal.standard_errors_["cable_softening"] < 0.2 * 5.0
    # The central twin (a setup no log shows): the median setup's (of the logarithms for the stiffness).
    assert cal.params_.Kr == pytest.approx(np.sqrt(np.prod(list(cal.setup_values_["Kr"].values()))), rel=1e-12)
    assert cal.params_.delay == cal.setup_values_["delay"]["b"]
    shared = PlantCalibration(**kwargs).fit(ys, us, DT)
    se = shared.standard_errors_["Kr"]
    assert 6e-4 + 3 * se < shared.params_.Kr < 2e-3 - 3 * se and shared.cost_ > cal.cost_


def test_one_setup_is_the_shared_fit_digit_for_digit():
    ys, us, _ = simulated_logs(TRUTH, n=2, seconds=1.5, seed=3)
    kwargs = dict(horizon=0.1, skip=0.5, stride=0.2, nominal=TRUTH, max_nfev=3)
    plain = PlantCalibration(**kwargs).fit(ys, us, DT)
    one_day = PlantCalibration(**kwargs).fit(ys, us, DT, setups={"Kr": ["2023-08-28"] * 2, "delay": ["s"] * 2})
    assert one_day.params_ == plain.params_ and one_day.cost_ == plain.cost_ and one_day.setup_values_ == {}
    with pytest.raises(ValueError, match="one Kr setup label per episode"):
        PlantCalibration(**kwargs).fit(ys, us, DT, setups={"Kr": ["2023-08-28"]})
    with pytest.raises(ValueError, match="no setup may have its own km"):
        PlantCalibration(**kwargs).fit(ys, us, DT, setups={"km": ["a", "b"]})


def test_cli_refuses_missing_logs_in_one_line(tmp_path, capsys):
    from qube_koopman.identify.cli.calibrate import main

    assert main([str(tmp_path / "nope.mcap"), "--out", str(tmp_path / "p.toml")]) == 2
    err = capsys.readouterr().err
    assert "nope.mcap" in err and "Traceback" not in err


def test_cli_writes_a_plant_file_qube_run_accepts_and_a_report(tmp_path):
    from qube_koopman.daq.cli.run import main as run_main
    from qube_koopman.identify.cli.calibrate import main
    from qube_koopman.sim.pendulum.params_file import load_plant

    assert run_main(["--episodes", "3", "--duration", "3", "--seed", "5", "--out", str(tmp_path / "logs"), "-q"]) == 0
    logs = sorted(map(str, (tmp_path / "logs").glob("*.mcap")))
    assert (
        main(
            [
                *logs[:2],
                "--validate",
                logs[2],
                "--out",
                str(tmp_path / "plant.toml"),
                "--max-nfev",
                "8",
                "--report",
                str(tmp_path / "report"),
                "--hold",
                "cable_softening=0",
                "-q",
            ]
        )
        == 0
    )
    plant = load_plant(tmp_path / "plant.toml")
    assert plant.provenance["logs"] == [p.rsplit("/", 1)[-1] for p in logs[:2]]
    assert set(plant.standard_errors) == {p[0] for p in ms.PHYSICAL}
    report = (tmp_path / "report" / "report.md").read_text()
    assert "## Validation on 1 episodes not fitted" in report and "| km |" in report
    # --hold: the linear spring kept, marked in the report and the provenance
    assert plant.params.cable_softening == 0.0 and plant.standard_errors["cable_softening"] == 0.0
    assert "| cable_softening | 0 | held |" in report and plant.provenance["held"] == ["cable_softening=0"]
    assert (
        run_main(
            [
                "--episodes",
                "1",
                "--duration",
                "1",
                "--plant",
                str(tmp_path / "plant.toml"),
                "--out",
                str(tmp_path / "again"),
                "-q",
            ]
        )
        == 0
    )


def test_cli_refuses_a_log_too_short_to_fit_or_validate_before_the_fit(tmp_path, capsys):
    # The first second is skipped, then a fit needs one segment (--horizon) and a validation a 0.2 s
    # open-loop prediction: a shorter log is named with its length, exit 2, before the minute of fitting.
    from qube_koopman.daq.cli.run import main as run_main
    from qube_koopman.identify.cli.calibrate import main

    for name, seconds in (("long", "3"), ("short", "0.8")):
        argv = ["--episodes", "1", "--duration", seconds, "--seed", "5", "--out", str(tmp_path / name), "-q"]
        assert run_main(argv) == 0
    long, short = (str(next((tmp_path / n).glob("*.mcap"))) for n in ("long", "short"))
    capsys.readouterr()
    for argv in ([short], [long, "--validate", short]):
        assert main([*argv, "--out", str(tmp_path / "plant.toml"), "-q"]) == 2
        err = capsys.readouterr().err
        assert short in err and "too short" in err and "Traceback" not in err, err
    assert not (tmp_path / "plant.toml").exists()


@pytest.fixture
def one_log(tmp_path):
    from qube_koopman.daq.cli.run import main as run_main

    assert run_main(["--episodes", "1", "--duration", "2", "--seed", "5", "--out", str(tmp_path / "logs"), "-q"]) == 0
    return next((tmp_path / "logs").glob("*.mcap"))


def test_cli_refuses_an_absurd_delay_or_measurement_in_one_line_before_the_fit(one_log, tmp_path, capsys):
    # A delay of 1e8 samples asked for gigabytes; alpha = 1e300 overflowed the fit into a plant of
    # infinite standard errors, written with exit 0.
    from qube_koopman.daq.log import read_episode, write_episode
    from qube_koopman.identify.cli.calibrate import main

    episode = read_episode(one_log)
    alpha = episode.alpha.copy()
    alpha[800] = 1e300
    write_episode(tmp_path / "crafted.mcap", replace(episode, alpha=alpha))
    capsys.readouterr()
    for argv, message in (
        ([str(one_log), "--delay", "100000000"], "error: --delay must be at most 500 samples"),
        (
            [str(tmp_path / "crafted.mcap")],
            f"error: {tmp_path / 'crafted.mcap'}: alpha at sample 800 is 1e+300 (1 sample beyond +-100); refused",
        ),
        (
            [str(one_log), "--hold", "cable_softening=-1"],
            "error: --hold: cannot hold cable_softening at -1: its physical range is [0, 100]",
        ),
    ):
        assert main([*argv, "--out", str(tmp_path / "p.toml"), "-q"]) == 2
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and message in err, err
    for hold, message in (
        ("theta_rest=0", "error: argument --hold: expected NAME=VALUE with NAME one of km,"),
        ("Kr=nan", "error: argument --hold: Kr: 'nan' is not a finite number"),
    ):
        with pytest.raises(SystemExit) as exit_:  # the parser's own usage error
            main([str(one_log), "--hold", hold, "--out", str(tmp_path / "p.toml"), "-q"])
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and len(err.splitlines()) == 1 and message in err, err
    assert not (tmp_path / "p.toml").exists()


def test_cli_warns_that_a_fit_stopped_by_max_nfev_did_not_converge_and_names_the_file(one_log, tmp_path, capsys):
    from qube_koopman.identify.cli.calibrate import main

    capsys.readouterr()
    out = tmp_path / "p.toml"
    assert main([str(one_log), "--out", str(out), "--max-nfev", "1"]) == 0  # (-q would silence the warning)
    captured = capsys.readouterr()
    assert (
        "qube-calibrate: warning: the fit did not converge within --max-nfev 1 steps (its cost was still "
        f"falling): {out} holds the last step's parameters; run again with a larger --max-nfev"
    ) in captured.err
    assert captured.out.endswith(f"wrote {out}: qube-run --plant {out}\n") and out.exists()


def test_cli_never_writes_a_plant_of_non_finite_values():
    from types import SimpleNamespace

    from qube_koopman.core.command import CliError
    from qube_koopman.identify.cli.calibrate import _check_finite

    fit = SimpleNamespace(params_=PendulumParameters(), standard_errors_={"km": float("inf"), "Dr": 1e-5})
    with pytest.raises(CliError, match=r"^p\.toml: not written: the fit gave standard error of km = inf") as info:
        _check_finite(fit, "p.toml")
    assert info.value.status == 1
    _check_finite(SimpleNamespace(params_=PendulumParameters(), standard_errors_={"km": 1e-3}), "p.toml")


def test_offsets_estimated_together_are_each_episodes_own_and_recover_the_injected_ones():
    # With the physics fixed the batched problem is separable: each episode's offset is its own
    # problem's minimizer. Cross-checked against MINPACK's Levenberg-Marquardt (scipy, dense
    # differences) on one episode at a time. Encoder noise 0.5 mrad: the offsets come back within 0.2 mrad.
    from scipy.optimize import least_squares

    from qube_koopman.identify.calibrate.validate import estimate_offset, estimate_offset_many

    ys, us, offsets = simulated_logs(TRUTH, n=3, seconds=2.5, seed=4)
    many = estimate_offset_many(ys, us, TRUTH, DT, start=500, window=500)
    np.testing.assert_allclose(many, offsets, atol=2e-4)
    one = [estimate_offset(y, u, TRUTH, DT, start=500, window=500) for y, u in zip(ys, us)]
    np.testing.assert_allclose(many, one, atol=1e-7)

    phys = ms.from_params(TRUTH, TRUTH)
    seg = ms.make_segments([ys[2][:1001]], [us[2][:1001]], 100, 500)  # the 5 segments of the window

    def fun(z):
        return ms.residuals(np.concatenate([phys, z]), seg, 1, TRUTH, DT, 1e-3)

    z0 = np.concatenate([[0.0], np.column_stack([seg.y[0], np.zeros((seg.n, 2))]).ravel()])
    fit = least_squares(fun, z0, method="lm", xtol=1e-12)
    assert fit.status > 0 and fit.x[0] * ms.OFFSET_SCALE == pytest.approx(many[2], abs=1e-6)


@pytest.mark.parametrize("controller", ["rig", "soft-theta"])
def test_closed_loop_offsets_recover_the_twins_encoder_zeros(tmp_path, controller):
    # A twin log records the pendulum encoder zero its episode drew. The replay's estimate (the zero
    # whose closed-loop replay of the first scored second matches the log) finds it within 0.4 counts
    # (measured over 24 episodes of 3 and 5 s: rms 0.13 counts under soft-theta, 0.06 under the rig's
    # gains; here at most 0.36); the open-loop segments' estimate comes within 0.1 on the twin's own
    # physics, but on the real soft episodes the two part by up to 5 counts, and only the closed
    # loop's replays match the logs (test_calibrate_dataset.py).
    from qube_koopman.daq.cli.run import main as run_main
    from qube_koopman.daq.log import read_episode
    from qube_koopman.identify.calibrate.validate import ENCODER_COUNT, estimate_offset_closed_loop

    argv = ["--episodes", "4", "--duration", "3", "--seed", "7", "--controller", controller]
    assert run_main([*argv, "--out", str(tmp_path), "-q"]) == 0
    episodes = [read_episode(p) for p in sorted(tmp_path.glob("*.mcap"))]
    truth = np.array([e.metadata.extra["backend"]["sensor"]["alpha_offset"] for e in episodes])
    assert np.all(np.abs(truth) > 0.2 * ENCODER_COUNT)  # drawn off zero, as the rig's are
    found = estimate_offset_closed_loop(episodes, PendulumParameters())
    errors = (found - truth) / ENCODER_COUNT
    assert np.all(np.abs(errors) <= 0.5) and np.sqrt(np.mean(errors**2)) <= 0.25, errors
    # A window longer than the logs takes what they hold (a short validation log is replayed, not refused).
    np.testing.assert_array_equal(
        estimate_offset_closed_loop(episodes, PendulumParameters(), window=10_000),
        estimate_offset_closed_loop(episodes, PendulumParameters(), window=1000),
    )
    with pytest.raises(ValueError, match="window"):
        estimate_offset_closed_loop(episodes, PendulumParameters(), start=1499)


@pytest.mark.slow
def test_a_calibration_under_the_rigs_gains_holds_under_another_controller(tmp_path, capsys):
    # The method's check of issue 27: twin episodes under the rig's gains are fitted, twin episodes
    # under soft-theta (an arm gain three times softer) validate; with the physics family right the
    # twin under the other controller moves like the "rig" (std ratios measured 0.997-1.001).
    import re

    from qube_koopman.daq.cli.run import main as run_main
    from qube_koopman.identify.cli.calibrate import main

    assert run_main(["--episodes", "3", "--duration", "8", "--seed", "21", "--out", str(tmp_path / "rig"), "-q"]) == 0
    assert (
        run_main(
            [
                "--episodes",
                "2",
                "--duration",
                "8",
                "--seed",
                "22",
                "--controller",
                "soft-theta",
                "--out",
                str(tmp_path / "soft"),
                "-q",
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        main(
            [
                *map(str, sorted((tmp_path / "rig").glob("*.mcap"))),
                "--validate",
                *map(str, sorted((tmp_path / "soft").glob("*.mcap"))),
                "--out",
                str(tmp_path / "p.toml"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "balanced: 2 of 2" in out
    ratios = re.search(r"theta ([\d.]+)\.\.([\d.]+) .*alpha ([\d.]+)\.\.([\d.]+) .*voltage ([\d.]+)\.\.([\d.]+)", out)
    assert ratios, out
    assert all(0.97 <= float(v) <= 1.03 for v in ratios.groups()), ratios.group(0)


def test_group_weights_give_every_group_the_same_share_and_one_group_changes_nothing():
    from qube_koopman.identify.calibrate.fit import _group_weights

    episode_of_segment = np.array([0, 0, 0, 1, 1, 1, 2, 2])  # episodes 0, 1 under "a", episode 2 under "b"
    w = _group_weights(episode_of_segment, ["a", "a", "b"])
    share = {g: float(np.sum(w[np.isin(episode_of_segment, e)] ** 2)) for g, e in (("a", [0, 1]), ("b", [2]))}
    assert share["a"] == pytest.approx(share["b"]) and sum(share.values()) == pytest.approx(len(w))
    np.testing.assert_array_equal(_group_weights(episode_of_segment, ["a"] * 3), 1.0)
    # One controller: group weighting is the plain fit, digit for digit.
    ys, us, _ = simulated_logs(TRUTH, n=2, seconds=1.5, seed=3)
    kwargs = dict(horizon=0.1, skip=0.5, stride=0.2, nominal=TRUTH, max_nfev=3)
    plain = PlantCalibration(**kwargs).fit(ys, us, DT)
    grouped = PlantCalibration(weighting="group", **kwargs).fit(ys, us, DT, ["rig", "rig"])
    assert grouped.params_ == plain.params_ and grouped.cost_ == plain.cost_
    with pytest.raises(ValueError, match="weighting"):
        PlantCalibration(weighting="controllers").fit(ys, us, DT)
    with pytest.raises(ValueError, match="one group label per episode"):
        PlantCalibration(weighting="group").fit(ys, us, DT, ["rig"])


@pytest.mark.slow
def test_group_weighting_moves_the_fit_towards_the_smaller_group():
    # Two groups of twin logs with different cable springs (softening alike): weighted alike, the fitted
    # stiffness moves from the larger group's towards the smaller one's.
    truth = replace(TRUTH, cable_softening=5.0)
    big = [simulated_logs(replace(truth, Kr=5e-4), n=1, seconds=2.5, seed=s) for s in (5, 6, 7)]
    small = simulated_logs(replace(truth, Kr=2e-3), n=1, seconds=2.5, seed=8, controller=soft_pd())
    ys = [b[0][0] for b in big] + small[0]
    us = [b[1][0] for b in big] + small[1]
    kwargs = dict(horizon=0.2, skip=0.5, stride=0.4, nominal=truth, max_nfev=6)
    groups = ["rig"] * 3 + ["soft"]
    plain = PlantCalibration(**kwargs).fit(ys, us, DT, groups)
    weighted = PlantCalibration(weighting="group", **kwargs).fit(ys, us, DT, groups)
    assert 5e-4 < plain.params_.Kr < weighted.params_.Kr < 2e-3


def test_cli_takes_folders_of_logs_as_every_command_does(tmp_path, capsys):
    from qube_koopman.daq.cli.run import main as run_main
    from qube_koopman.identify.cli.calibrate import main
    from qube_koopman.sim.pendulum.params_file import load_plant

    assert run_main(["--episodes", "2", "--duration", "2", "--seed", "9", "--out", str(tmp_path / "fit"), "-q"]) == 0
    assert run_main(["--episodes", "1", "--duration", "2", "--seed", "10", "--out", str(tmp_path / "val"), "-q"]) == 0
    assert (
        main(
            [
                str(tmp_path / "fit"),
                "--validate",
                str(tmp_path / "val"),
                "--out",
                str(tmp_path / "p.toml"),
                "--max-nfev",
                "2",
                "-q",
            ]
        )
        == 0
    )
    plant = load_plant(tmp_path / "p.toml")
    assert plant.provenance["logs"] == [p.name for p in sorted((tmp_path / "fit").glob("*.mcap"))]
    assert len(plant.provenance["validated_on"]) == 1
    (tmp_path / "empty").mkdir()
    capsys.readouterr()
    assert main([str(tmp_path / "empty"), "--out", str(tmp_path / "q.toml")]) == 2
    err = capsys.readouterr().err
    assert "empty: folder has no .mcap logs" in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow
def test_a_host_latency_of_two_and_a_half_samples_is_recovered():
    # One session of the rig's soft-controller logs ran with 4.9 ms from command to motor (the other
    # with 1.9 ms): the host's latency, beyond the 4 ms the fit was once bounded to.
    truth = replace(TRUTH, delay=0.005)
    ys, us, _ = simulated_logs(truth, n=2, seed=3, controller=soft_pd())
    assert max(np.abs(y[:, 1]).max() for y in ys) < 0.5  # the slower loop kept the pendulum up
    cal = PlantCalibration(horizon=0.2, skip=0.5, stride=0.2, nominal=PendulumParameters()).fit(ys, us, DT)
    se = cal.standard_errors_["delay"]
    assert abs(cal.params_.delay - truth.delay) <= 3 * se + 1e-12 and se < 2e-4, (cal.params_.delay, se)


def test_a_fit_by_differences_lands_where_the_fit_by_tangents_does():
    # The two Jacobians differ by the differences' rounding: the solver takes the same steps, and the
    # fitted parameters agree far within their standard errors.
    ys, us, _ = simulated_logs(TRUTH, n=2, seconds=2.0)
    fits = [
        PlantCalibration(skip=0.5, max_nfev=4, nominal=PendulumParameters(), jacobian=method).fit(ys, us, DT)
        for method in ("tangents", "differences")
    ]
    assert fits[0].nfev_ == fits[1].nfev_
    for name, se in fits[0].standard_errors_.items():
        assert abs(getattr(fits[0].params_, name) - getattr(fits[1].params_, name)) <= 0.01 * se + 1e-12, name
    with pytest.raises(ValueError, match="jacobian must be"):
        PlantCalibration(jacobian="adjoint").fit(ys, us, DT)


def test_the_commands_list_of_parameters_to_hold_is_the_fits():
    # qube-calibrate names them without importing the fit (its --help stays quick)
    from qube_koopman.identify.cli import calibrate

    assert calibrate._FITTED == ms.PHYSICAL_NAMES
