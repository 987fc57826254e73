"""The cables' relaxation estimated from closed-loop logs: the slow load's arm-driven part, by instrumental variables.

Ground truth from the twin: the soft controller's real episodes (their references and feedforward,
the excitation) replayed in closed loop with a known relaxation and random load, then run backwards
by the arm's equation, which knows nothing of either.
"""

from __future__ import annotations

import numpy as np
import pytest

from qube_koopman.core.qube import SKIP_SAMPLES
from qube_koopman.identify.calibrate.load_fit import fit_relaxation, reconstruct_load
from qube_koopman.identify.calibrate.validate import replay_episodes
from qube_koopman.sim.pendulum import CableRelaxation, PendulumParameters, RandomLoad

DT = 1 / 500


@pytest.fixture(scope="module")
def soft_episodes(soft_logs):
    from qube_koopman.identify.data.logs import load_logs, read_episodes

    return read_episodes(load_logs(sorted(soft_logs.glob("*.mcap"))))


#: The cases: (relaxation, random load). About as fitted on the soft day's logs; the rig day's,
#: relaxing slower; and a load alone, the soft day's whole load (0.045 V), no relaxation.
CASES = {
    "soft": (CableRelaxation(0.27, 0.39, 1.0), RandomLoad(0.013, 4.0)),
    "rig": (CableRelaxation(0.13, 0.15, 2.0), RandomLoad(0.0075, 3.0)),
    "load alone": (None, RandomLoad(0.09, 0.5)),
}


@pytest.fixture(scope="module")
def fits(soft_episodes):
    """Per case, the fit on the soft episodes replayed once each with its relaxation and load (all cases in
    one batch: a replay's time is its steps'), with the loads and arm angles it was given."""
    twin, n = PendulumParameters(), len(soft_episodes)
    episodes = soft_episodes * len(CASES)
    run = replay_episodes(
        episodes,
        twin,
        n_draws=1,
        load=[load for _, load in CASES.values() for _ in range(n)],
        relaxation=[r for r, _ in CASES.values() for _ in range(n)],
    ).twin  # from SKIP_SAMPLES on
    skipped = 2 * SKIP_SAMPLES  # the replay's and the reconstruction's first second
    out = {}
    for k, case in enumerate(CASES):
        members = range(k * n, (k + 1) * n)
        loads = [reconstruct_load(run[:, i, :2], run[:, i, 2], twin, DT) for i in members]
        thetas = [run[SKIP_SAMPLES:, i, 0] for i in members]
        excitations = [
            np.column_stack([np.asarray(e.references)[skipped:, 0], np.asarray(e.feedforward)[skipped:]])
            for e in soft_episodes
        ]
        out[case] = fit_relaxation(loads, thetas, excitations, DT), loads, thetas
    return out


@pytest.mark.dataset
@pytest.mark.parametrize("case", ["soft", "rig"])
def test_a_known_relaxation_is_recovered_through_the_closed_loop(fits, case):
    # The twin's loop with the relaxation and a random load, run backwards by the arm's equation (which
    # knows nothing of either): the relaxation time exactly from the grid, the stiffnesses within 15 %.
    # Over five draws of the loads and start angles they scattered by up to 12 % (soft 0.237-0.283 and
    # 0.351-0.404, rig 0.116-0.133 and 0.134-0.153 V/rad), the time always exact; this draw 0.269 /
    # 0.392 and 0.116 / 0.147.
    truth = CASES[case][0]
    fit = fits[case][0]
    assert fit.relaxation.time_constant == truth.time_constant, fit.explained_by_time
    assert fit.relaxation.fast == pytest.approx(truth.fast, rel=0.15)
    assert fit.relaxation.relaxing == pytest.approx(truth.relaxing, rel=0.15)
    assert fit.explained > 0.5 and fit.driven > 0.5  # measured 0.69-0.82 and 0.51-0.70
    # The standard errors (whole episodes resampled): the truth within four of them, each a few percent of
    # its estimate. On the soft case over the five draws they averaged 0.011 and 0.015 V/rad against the
    # estimates' spread of 0.017 and 0.021: about 0.7 of it.
    for name in ("fast", "relaxing"):
        estimate, se = getattr(fit.relaxation, name), fit.standard_errors[name]
        assert 0.01 * estimate < se < 0.2 * estimate, (name, estimate, se)
        assert abs(estimate - getattr(truth, name)) <= 4 * se, (name, estimate, se)


@pytest.mark.dataset
def test_a_load_from_outside_the_loop_is_not_credited_to_the_arm(fits):
    # No relaxation, the soft day's whole load (four times what the relaxation leaves of it on the logs):
    # the excitation explains next to nothing of the load (0.05-0.06 over five draws), and what the fit
    # takes for a relaxation explains next to nothing either (0.00-0.05), its stiffnesses within
    # 0.12 V/rad of zero (this draw 0.081 / 0.094): a third of the soft day's on the logs.
    fit = fits["load alone"][0]
    assert abs(fit.relaxation.fast) < 0.15 and fit.relaxation.relaxing < 0.15, fit.relaxation
    assert fit.driven < 0.1 and fit.explained < 0.1


@pytest.mark.dataset
def test_the_residual_loads_are_the_loads_less_the_relaxations_torque(fits):
    fit, loads, thetas = fits["soft"]
    r = fit.relaxation
    for d, t, left in zip(loads, thetas, fit.residuals):
        np.testing.assert_allclose(left, d - (r.relaxing * r.remembered(t, DT) - r.fast * t))


def test_bad_input_is_refused_with_a_clear_error():
    d = np.zeros(100)
    with pytest.raises(ValueError, match="one arm angle and one excitation"):
        fit_relaxation([d], [d], [], DT)
    with pytest.raises(ValueError, match="load's length"):
        fit_relaxation([d], [d[:50]], [d], DT)
    with pytest.raises(ValueError, match="at least one relaxation time"):
        fit_relaxation([d], [d], [d], DT, time_constants=())


def test_qube_calibrate_relaxation_writes_its_tables_and_qube_run_simulates_and_records_them(tmp_path, capsys):
    from qube_koopman.daq.cli.run import main as run_main
    from qube_koopman.daq.log import read_episode
    from qube_koopman.identify.cli.calibrate import main
    from qube_koopman.sim.pendulum.params_file import PlantFile, load_plant, save_plant

    truth = CableRelaxation(0.27, 0.39, 1.0)
    save_plant(tmp_path / "truth.toml", PlantFile(PendulumParameters(), load=RandomLoad(0.013, 4.0), relaxation=truth))
    out = tmp_path / "logs"
    args = ["--episodes", "3", "--duration", "4", "--seed", "5", "--plant", str(tmp_path / "truth.toml"), "-q"]
    assert run_main([*args, "--out", str(out)]) == 0
    logs = sorted(map(str, out.glob("*.mcap")))
    assert read_episode(logs[0]).metadata.extra["backend"]["relaxation"] == {
        "fast": 0.27,
        "relaxing": 0.39,
        "time_constant": 1.0,
    }
    assert main([*logs, "--out", str(tmp_path / "x.toml"), "--relaxation", "-q"]) == 2
    assert "--relaxation needs --load" in capsys.readouterr().err
    plant_path, report = tmp_path / "plant.toml", tmp_path / "report"
    assert main([*logs[:2], "--validate", logs[2], "--out", str(plant_path), "--max-nfev", "4", "--load",
                 "--relaxation", "--report", str(report), "-q"]) == 0  # fmt: skip
    plant = load_plant(plant_path)
    assert plant.relaxation is not None and plant.relaxation.time_constant in (0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
    # A time given by hand is the one fitted (and the provenance says so).
    fixed = [*logs[:2], "--out", str(tmp_path / "fixed.toml"), "--max-nfev", "4", "--load", "--relaxation"]
    assert main([*fixed, "--relaxation-time", "0.7", "--relaxation-passes", "0", "-q"]) == 0
    fixed_plant = load_plant(tmp_path / "fixed.toml")
    assert fixed_plant.relaxation.time_constant == 0.7 and fixed_plant.provenance["relaxation_time"] == 0.7
    assert fixed_plant.provenance["relaxation_passes"] == 0
    assert main([*logs, "--out", str(tmp_path / "z.toml"), "--load", "--relaxation-passes", "1", "-q"]) == 2
    assert "--relaxation-passes needs --relaxation" in capsys.readouterr().err
    assert main([*fixed, "--relaxation-passes", "-1", "-q"]) == 2
    assert "--relaxation-passes must be 0 or more" in capsys.readouterr().err
    assert main([*logs, "--out", str(tmp_path / "y.toml"), "--load", "--relaxation-time", "1", "-q"]) == 2
    assert "--relaxation-time needs --relaxation" in capsys.readouterr().err
    assert plant.relaxation_setups == {} and plant.provenance["relaxation"] is True  # one recording day
    # The relaxation's standard errors (the episode bootstrap's) are written beside it, as the load's are.
    assert set(plant.relaxation_standard_errors) == {"fast", "relaxing"}
    assert all(0 < e < 1 for e in plant.relaxation_standard_errors.values()), plant.relaxation_standard_errors
    assert plant.relaxation_setup_standard_errors == {}
    text = (report / "report.md").read_text()
    assert "## The cables' relaxation" in text and "| on |" in text
    # The default passes: the physics fitted again twice under the relaxation estimated before, each a row.
    assert plant.provenance["relaxation_passes"] == 2
    passes = text.split("## The relaxation in the fit")[1].split("\n## ")[0]
    assert [line.split("|")[1].strip() for line in passes.splitlines() if line.startswith("| ")][1:] == ["0", "1", "2"]


def test_a_plant_files_relaxation_round_trips_and_bad_tables_are_refused(tmp_path):
    from qube_koopman.sim.pendulum.params_file import PlantFile, PlantFileError, load_plant, save_plant

    central, day = CableRelaxation(0.26, 0.38, 1.0), CableRelaxation(0.13, 0.14, 2.0)
    errors, day_errors = {"fast": 0.011, "relaxing": 0.018}, {"fast": 0.03, "relaxing": float("nan")}
    save_plant(
        tmp_path / "p.toml",
        PlantFile(
            PendulumParameters(),
            relaxation=central,
            relaxation_setups={"2023-08-28": day},
            relaxation_standard_errors=errors,
            relaxation_setup_standard_errors={"2023-08-28": day_errors},
        ),
    )
    plant = load_plant(tmp_path / "p.toml")
    assert plant.relaxation == central and plant.relaxation_setups == {"2023-08-28": day}
    assert plant.relaxation_standard_errors == errors
    assert plant.relaxation_setup_standard_errors["2023-08-28"]["fast"] == 0.03
    assert np.isnan(plant.relaxation_setup_standard_errors["2023-08-28"]["relaxing"])  # one episode: no spread
    assert plant.relaxations_for_logs(["2023-08-28T16:00:00", "2023-09-15T15:00:00", None]) == [day, central, central]
    text = (tmp_path / "p.toml").read_text()
    for bad, message in [
        ("[relaxation]\nfast = 0.1\nrelaxing = 0.2\n", "missing time_constant"),
        ("[relaxation]\nfast = 0.1\nrelaxing = 0.2\ntime_constant = 1\nstiff = 2\n", "unknown key"),
        ("[relaxation]\nfast = 0.1\nrelaxing = -0.2\ntime_constant = 1\n", "at least 0"),
        ("[relaxation]\nfast = true\nrelaxing = 0.2\ntime_constant = 1\n", "finite number"),
    ]:
        start = text.index("[relaxation]")
        (tmp_path / "bad.toml").write_text(text[:start] + bad)
        with pytest.raises(PlantFileError, match=message):
            load_plant(tmp_path / "bad.toml")
    (tmp_path / "orphan.toml").write_text(
        text[: text.index("[relaxation]")]
        + '[relaxation_setups."2023-08-28"]\nfast = 0.1\nrelaxing = 0.2\ntime_constant = 1\n'
    )
    with pytest.raises(PlantFileError, match="needs a \\[relaxation\\] table"):
        load_plant(tmp_path / "orphan.toml")
    save_plant(tmp_path / "plain.toml", PlantFile(PendulumParameters(), relaxation=central))
    plain = (tmp_path / "plain.toml").read_text()
    assert "standard_errors" not in plain  # none given, none written
    for bad, message in [
        ("[relaxation_standard_errors]\nfast = 0.1\ntime_constant = 0.2\n", "unknown key"),
        ("[relaxation_standard_errors]\nfast = -0.1\n", "0 or more"),
        ("[relaxation_standard_errors]\nfast = true\n", "0 or more"),
        ('[relaxation_setup_standard_errors."2023-09-15"]\nfast = 0.1\n', "no relaxation beside it"),
    ]:
        (tmp_path / "bad.toml").write_text(plain + "\n" + bad)
        with pytest.raises(PlantFileError, match=message):
            load_plant(tmp_path / "bad.toml")
    (tmp_path / "orphan.toml").write_text(
        text[: text.index("[relaxation]")] + "[relaxation_standard_errors]\nfast = 0.1\n"
    )
    with pytest.raises(PlantFileError, match="no relaxation beside it"):
        load_plant(tmp_path / "orphan.toml")


def test_the_bootstraps_two_stage_fit_from_moments_is_the_fits_own():
    # The resamplings solve two-stage least squares from the episodes' moments: with every episode once it
    # is the point estimate itself (the same two stages over all samples).
    from qube_koopman.identify.calibrate.load_fit import _two_stage

    rng = np.random.default_rng(3)
    z = rng.normal(size=(4000, 5))
    regressors = z @ rng.normal(size=(5, 2)) + 0.3 * rng.normal(size=(4000, 2))
    y = regressors @ np.array([0.4, -0.2]) + 0.1 * rng.normal(size=4000)
    predicted = z @ np.linalg.lstsq(z, regressors, rcond=None)[0]
    direct = np.linalg.lstsq(predicted, y, rcond=None)[0]
    np.testing.assert_allclose(_two_stage(z.T @ z, z.T @ regressors, z.T @ y), direct, rtol=1e-9)
