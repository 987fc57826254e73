"""``qube-design`` (issue 28): LQ on the identified plant's history, realized on the tracking errors.

- the realization: the controller file's tick on the tracking errors gives, sample for sample, the
  lifted state feedback ``u = -K [s - s_ref; w]`` on the plant model it was designed on;
- the design: on a known linear plant the gain is python-control's ``dlqr`` of the system built
  here by hand; the margins are where the closed loop's eigenvalues leave the unit circle;
- refusals: an unstabilizable model, models a design cannot use, bad weights;
- the command: a model file in, a controller file out that ``qube-run`` loads;
- the twin (slow): a design from a model identified on twin episodes beats the rig's PD.
"""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from qube_koopman.daq.cli.run import main as run_main
from qube_koopman.core.controller_file import load_controller
from qube_koopman.design import DesignError, Weights, design_lq, linear_plant
from qube_koopman.design.cli.design import main as design_main
from qube_koopman.design.predict import closed_loop_eigenvalues, loop_margins
from qube_koopman.identify import Constant, CoulombFriction, Delay, KoopmanModel, Lifting, Polynomial, close_loop
from qube_koopman.identify.cli.identify import main as identify_main
from qube_koopman.identify.models.model_file import save_model
from qube_koopman.core.lti import DiscreteStateSpace

DT = 0.002
NAMES = ("theta", "alpha")


def _plant_model(steps, A_x: np.ndarray, B_x: np.ndarray) -> KoopmanModel:
    """A plant model whose measured rows are ``A_x``, ``B_x``; its other rows the lifting's own (shift, constant)."""
    lifting = Lifting(list(steps)).fit([np.zeros((50, 2))], NAMES)
    n = lifting.n_features_out_
    A = np.zeros((n, n))
    A[:2] = A_x
    A[2:, :] = np.eye(n)[2:] * 0.5  # rows a re-lifted prediction never uses: anything
    B = np.zeros((n, 1))
    B[:2, 0] = B_x
    return KoopmanModel(A, B, lifting, ("u",), dt=DT)


def _pendulum_like(d: int, const: bool, seed: int = 0) -> KoopmanModel:
    """An unstable arm-and-pendulum-like plant over ``d`` delays (and a constant), randomly perturbed."""
    rng = np.random.default_rng(seed)
    steps = [Delay(d)] + ([Constant()] if const else [])
    n = 2 * (d + 1) + int(const)
    A_x = np.zeros((2, n))
    if d == 0:  # first order: an arm that drifts, a pendulum that falls
        A_x[:, :2] = [[1.0, 0.01], [0.0, 1.03]]
    else:  # theta_k+1 ~ 2 theta_k - theta_k-1: second order, the pendulum unstable
        A_x[:, :4] = [[1.9, 0.0, -0.9, 0.0], [0.0, 2.02, 0.0, -1.0]]
    A_x[:, : 2 * (d + 1)] += 0.01 * rng.standard_normal((2, 2 * (d + 1)))
    if const:
        A_x[:, -1] = [1e-4, -2e-4]
    return _plant_model(steps, A_x, np.array([2e-4, -2e-4]))


def _feedback_by_hand(model: KoopmanModel, K: np.ndarray, r: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, ...]:
    """The plant model (re-lifted each step) under ``u = -K_s (s - s_ref) - K_w w + f``, from rest."""
    d, n_s = model.n_delays, 2 * (model.n_delays + 1)
    x = np.zeros((len(r), 2))
    u = np.zeros(len(r))
    w = 0.0
    for k in range(d, len(r) - 1):
        s = x[k - d : k + 1][::-1].ravel()  # newest first, as the lifting orders it
        s_ref = r[k - d : k + 1][::-1].ravel()
        u[k] = -K[0, :n_s] @ (s - s_ref) - K[0, n_s] * w + f[k]
        w += DT * (r[k, 0] - x[k, 0])
        z = model.lifting.transform(x[k - d : k + 1])[-1]
        x[k + 1] = model.A[:2] @ z + model.B[:2, 0] * u[k]
    return x, u


@pytest.mark.parametrize("d, const", [(0, False), (3, True), (12, False)])
def test_the_realization_is_the_lifted_state_feedback_sample_for_sample(d, const):
    model = _pendulum_like(d, const)
    design = design_lq(linear_plant(model), Weights())
    rng = np.random.default_rng(1)
    n = 400
    r = np.cumsum(rng.normal(0, 0.01, (n, 2)), axis=0)
    r[: d + 1] = 0.0  # the controller starts at rest: no reference before the first controlled sample
    f = np.repeat(rng.choice([-0.5, 0.5], n // 20), 20)
    by_hand, u_by_hand = _feedback_by_hand(model, design.gain, r, f)
    loop = close_loop(model, design.controller)  # the controller file's tick, as identify predicts it
    x, xc = loop.simulate(np.zeros((d + 1, 2)), np.column_stack([r, f]), np.zeros(design.controller.n_states))
    assert np.abs(by_hand).max() > 1e-2, "the loop moves: not a comparison of zeros"
    np.testing.assert_allclose(x, by_hand, rtol=0, atol=1e-10)
    u = xc[d:] @ design.controller.C.T + (r[d:] - x[d:]) @ design.controller.D.T + f[d:, None]
    np.testing.assert_allclose(u[:-1, 0], u_by_hand[d:-1], rtol=0, atol=1e-10)


def test_the_shift_register_is_the_model_itself_for_a_linear_lifting():
    model = _pendulum_like(4, True)
    plant = linear_plant(model)
    assert plant.exact and plant.n_states == 10 and "the identified plant itself" in plant.note
    np.testing.assert_allclose(plant.F[:2], model.A[:2, :10], rtol=0, atol=1e-14)
    np.testing.assert_array_equal(plant.F[2:], np.eye(10, k=-2)[2:])  # the history shifts, exactly
    np.testing.assert_allclose(plant.c[:2], model.A[:2, 10], rtol=0, atol=1e-15)


def test_a_design_on_a_known_linear_plant_is_dlqrs_gain():
    import control

    A1, A2 = np.array([[1.9, 0.01], [0.0, 2.03]]), np.array([[-0.9, 0.0], [0.0, -1.0]])
    b = np.array([3e-4, -2e-4])
    model = _plant_model([Delay(1)], np.hstack([A1, A2]), b)
    weights = Weights(q_theta=5.0, q_alpha=0.3, r_voltage=0.02, q_integral=2.0)
    # By hand: s = [theta_k, alpha_k, theta_k-1, alpha_k-1, w_k], w_k+1 = w_k - dt theta_k.
    F = np.zeros((5, 5))
    F[:2, :2], F[:2, 2:4], F[2:4, :2], F[4, 0], F[4, 4] = A1, A2, np.eye(2), -DT, 1.0
    G = np.array([[b[0]], [b[1]], [0.0], [0.0], [0.0]])
    K, _, _ = control.dlqr(F, G, np.diag([5.0, 0.3, 0.0, 0.0, 2.0]), [[0.02]])
    design = design_lq(linear_plant(model), weights)
    np.testing.assert_allclose(design.gain, K, rtol=1e-9, atol=0)
    c = design.controller  # u = K_s E - K_w w: D and C are the gain, signs turned
    np.testing.assert_allclose(c.D[0], K[0, :2], rtol=1e-9)
    np.testing.assert_allclose(c.C[0], [K[0, 2], K[0, 3], -K[0, 4]], rtol=1e-9)
    assert max(abs(closed_loop_eigenvalues(linear_plant(model), c))) < 1


def test_the_margins_are_where_the_closed_loop_leaves_the_unit_circle():
    """Gain margins at the plant input (python-control on the loop's frequency response) against the
    eigenvalues of the loop with the controller's output scaled: stable just inside, unstable just outside."""
    plant = linear_plant(_pendulum_like(6, False))
    c = design_lq(plant, Weights()).controller
    margins = loop_margins(plant, c)

    def radius(k: float) -> float:
        scaled = DiscreteStateSpace(c.A, c.B, k * c.C, k * c.D, c.dt)
        return float(max(abs(closed_loop_eigenvalues(plant, scaled))))

    assert 0 < margins.gain_decrease < 1 < margins.gain_increase < np.inf  # an unstable plant: both exist
    for edge in (margins.gain_decrease, margins.gain_increase):
        assert radius(edge * 0.98 if edge > 1 else edge * 1.02) < 1 < radius(edge * 1.02 if edge > 1 else edge * 0.98)
    assert 0 < margins.phase < 90 and 0 < margins.stability <= 1


# --- refusals ----------------------------------------------------------------------------------------------


def _save(path: Path, model: KoopmanModel) -> Path:
    save_model(
        path,
        method="cl-edmd",
        alpha=1e-3,
        plant=model,
        closed_loop=None,
        controller=None,
        measured=[0, 1],
        training={"logs": []},
    )
    return path


def test_an_unstabilizable_model_is_refused_naming_the_mode(tmp_path, capsys):
    # The pendulum (|lambda| 1.05) does not feel the voltage and nothing couples it to the arm.
    model = _plant_model([Delay(0)], np.array([[1.0, 0.0], [0.0, 1.05]]), np.array([1e-3, 0.0]))
    with pytest.raises(DesignError, match=r"not stabilizable: its mode at 1\.05 \(\|lambda\| = 1\.05\)"):
        design_lq(linear_plant(model), Weights())
    path = _save(tmp_path / "model.json", model)
    assert design_main([str(path), "--out", str(tmp_path / "c.toml")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"qube-design: error: {path}: the plant model is not stabilizable") and "Traceback" not in err
    assert not (tmp_path / "c.toml").exists()


@pytest.mark.parametrize(
    "kind, expected",
    [
        ("friction", "its lifting holds the arm's Coulomb friction shape (--friction)"),
        (
            "arx",
            "an ARX model; a design needs a Koopman plant model: "
            "identify it with qube-identify ... --poly 1 --delays N",
        ),
        ("not json", "not a readable model file"),
        ("missing", "not a readable model file (No such file or directory)"),
    ],
)
def test_a_model_a_design_cannot_use_is_refused_saying_what_to_identify(kind, expected, tmp_path, capsys):
    path = tmp_path / "model.json"
    if kind == "friction":
        model = _plant_model([Delay(2), CoulombFriction(0, 2, 0.002)], np.zeros((2, 7)), np.array([1e-3, -1e-3]))
        _save(path, model)
    elif kind == "arx":
        path.write_text(
            json.dumps(
                {
                    "format": "qube-arx-model",
                    "version": 1,
                    "method": "arx",
                    "output_lags": 2,
                    "input_lags": 1,
                    "inputs": ["u"],
                    "coef": [[0.0]],
                    "dt": DT,
                }
            )
        )
    elif kind == "not json":
        path.write_text("kp_theta = 6\n")
    assert design_main([str(path), "--out", str(tmp_path / "c.toml")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"qube-design: error: {path}: ") and expected in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "c.toml").exists()


def test_a_nonlinear_lifting_is_designed_on_its_linearization_at_upright_and_says_so():
    linear = _pendulum_like(3, False)
    steps = [Polynomial(2), Delay(3)]  # theta, alpha, theta^2, theta alpha, alpha^2 at each delay
    lifting = Lifting(steps).fit([np.zeros((50, 2))], NAMES)
    A = np.zeros((20, 20))
    A[:2, [0, 1, 5, 6, 10, 11, 15, 16]] = linear.A[:2, :8]  # the linear terms
    A[:2, [2, 4]] = [[0.3, -0.2], [0.1, 0.4]]  # quadratic terms: no slope at upright
    nonlinear = KoopmanModel(A, np.vstack([linear.B[:2], np.zeros((18, 1))]), lifting, ("u",), dt=DT)
    plant = linear_plant(nonlinear)
    assert not plant.exact and "linearization at upright" in plant.note and "--poly 1" in plant.note
    np.testing.assert_allclose(plant.F, linear_plant(linear).F, rtol=0, atol=1e-9)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--r-voltage", "0"], "--r-voltage must be a finite number > 0, got 0.0"),
        (["--q-theta", "-1"], "--q-theta must be a finite number >= 0, got -1.0"),
        (["--q-alpha", "nan"], "--q-alpha must be a finite number >= 0, got nan"),
        (["--q-integral", "inf"], "--q-integral must be a finite number >= 0, got inf"),
        (["--q-theta", "0", "--q-alpha", "0"], "--q-theta and --q-alpha are both 0"),
        (["--duration", "1"], "--duration must be between 2 and 60 s, got 1.0"),
    ],
)
def test_bad_weights_are_a_usage_error_naming_the_option(argv, message, tmp_path, capsys):
    path = _save(tmp_path / "model.json", _pendulum_like(2, False))
    assert design_main([str(path), "--out", str(tmp_path / "c.toml"), *argv]) == 2
    err = capsys.readouterr().err
    assert err == f"qube-design: error: {message}\n" or (message in err and "Traceback" not in err), err
    assert not (tmp_path / "c.toml").exists()


# --- the command ---------------------------------------------------------------------------------------------


def test_qube_design_writes_a_controller_file_qube_run_loads_with_its_provenance(tmp_path, capsys):
    model = _save(tmp_path / "model.json", _pendulum_like(5, True))
    out = tmp_path / "designed.toml"
    assert design_main([str(model), "--out", str(out), "--episodes", "3", "--duration", "6", "--q-theta", "4"]) == 0
    text = capsys.readouterr().out
    for line in (
        "the identified plant itself: 5 delays of theta, alpha and a constant (12 states)",
        "weights q_theta 4, q_alpha 0.1, r_voltage 0.01, q_integral 10",
        "closed loop: spectral radius 0.9",
        "margins at the plant input: gain +",
        "predicted on the rig's excitation (3 episodes of 6 s",
        f"wrote {out}: qube-run --controller {out}",
    ):
        assert line in text, text
    info = load_controller(out)
    assert info.kind == "state-space" and info.system.n_states == 2 * 5 + 1
    expected = design_lq(linear_plant(_pendulum_like(5, True)), Weights(q_theta=4.0)).controller
    for m in "ABCD":
        np.testing.assert_array_equal(getattr(info.system, m), getattr(expected, m))
    p = info.provenance
    assert p["model"] == str(model) and p["weights"]["q_theta"] == 4.0 and p["n_delays"] == 5
    assert 0 < p["predicted"]["J"] < np.inf and p["predicted"]["episodes"] == 3 and p["spectral_radius"] < 1
    assert set(p["margins"]) >= {"gain_margin_up_db", "gain_margin_down_db", "phase_margin_deg"}


def test_the_folder_qube_identify_wrote_is_taken_for_its_model_and_npz_matrices_load(tmp_path, capsys):
    folder = tmp_path / "identified"
    folder.mkdir()
    _save(folder / "model.json", _pendulum_like(2, False))
    out = tmp_path / "c.toml"
    assert design_main([str(folder), "--out", str(out), "--npz", "--episodes", "2", "--no-integral", "-q"]) == 0
    assert f"model {folder / 'model.json'}:" in capsys.readouterr().out
    info = load_controller(out)
    assert out.with_suffix(".npz").is_file() and info.system.n_states == 4  # 2 past errors of 2 channels, no integral
    assert info.provenance["weights"]["integral"] is False


# --- the twin ------------------------------------------------------------------------------------------------


def _twin_figures(folder: Path) -> dict:
    from qube_koopman.daq.log import read_episode
    from qube_koopman.design.predict import episode_cost

    episodes = [read_episode(p) for p in sorted(folder.glob("*.mcap"))]
    rows = np.array([episode_cost(e.theta, e.target_theta, e.alpha, e.plant_input) for e in episodes])
    return {
        "complete": sum(e.metadata.status == "complete" for e in episodes),
        "J": rows[:, 0].mean(),
        "voltage_rms": float(np.sqrt(np.mean(rows[:, 3] ** 2))),
        "saturated": int(sum(e.saturation[500:].sum() for e in episodes)),
    }


@pytest.fixture(scope="module")
def twin_cycle(tmp_path_factory) -> SimpleNamespace:
    """Issue 28's cycle on the twin, shrunk to run in CI: run -> identify -> design -> run.

    A model identified on 6 rig-PD episodes (``--seed 3``; 35 delays and a constant, as the design
    page's cycle on the paper's data: with 20 delays the 6-episode model misses enough of the arm's slow
    dynamics that its design runs hotter, voltage RMS 1.76 V against 1.53 V), a design with
    the default weights, then 6 episodes under each controller on the same excitations (``--seed 5``)
    and 4 more under the design on new ones (``--seed 6``). The file's tests share these folders
    (``--dist loadfile`` keeps them on one worker, so the runs happen once).
    """
    root = tmp_path_factory.mktemp("cycle")

    def run(out: str, episodes: int, seed: int, *extra: str) -> Path:
        assert run_main(["--episodes", str(episodes), "--seed", str(seed), "--out", str(root / out), "-q", *extra]) == 0
        return root / out

    train, test = run("train", 6, 3), run("test", 2, 4)
    assert (
        identify_main(
            [
                "--train",
                *map(str, sorted(train.glob("*.mcap"))),
                "--test",
                *map(str, test.glob("*.mcap")),
                "--poly",
                "1",
                "--delays",
                "35",
                "--const",
                "--out",
                str(root / "model"),
                "-q",
            ]
        )
        == 0
    )
    controller = root / "designed.toml"
    assert design_main([str(root / "model"), "--out", str(controller), "--seed", "5", "--episodes", "6", "-q"]) == 0
    return SimpleNamespace(
        pd_train=train,
        model=root / "model",
        controller=controller,
        pd=run("pd", 6, 5),
        designed=run("designed", 6, 5, "--controller", str(controller)),
        designed_new=run("designed_new", 4, 6, "--controller", str(controller)),
    )


@pytest.mark.slow
def test_on_the_twin_a_design_from_an_identified_model_beats_the_rigs_pd(twin_cycle):
    """Issue 28 section 3, shrunk: J at least 40 % below the PD's on the same excitations, no saturation."""
    pd, designed = _twin_figures(twin_cycle.pd), _twin_figures(twin_cycle.designed)
    predicted = load_controller(twin_cycle.controller).provenance["predicted"]
    assert pd["complete"] == designed["complete"] == 6
    assert designed["J"] < 0.6 * pd["J"], (designed, pd)  # at least 40 % lower
    assert designed["saturated"] == 0 and designed["voltage_rms"] < 1.6 * pd["voltage_rms"], (designed, pd)
    assert abs(predicted["J"] / designed["J"] - 1) < 0.2, (predicted, designed)  # the model predicted it


def _cl_edmd_r2(train: Path, test: Path, out: Path) -> float:
    """Test R^2 of CL EDMD (poly 1, 35 delays, a constant) fitted on ``train``'s logs, predicting ``test``'s.

    Each log records the controller it ran under, so the plant identified under one controller
    predicts the other's closed loop: that is the transfer.
    """
    assert (
        identify_main(
            [
                "--train",
                *map(str, sorted(train.glob("*.mcap"))),
                "--test",
                *map(str, sorted(test.glob("*.mcap"))),
                "--poly",
                "1",
                "--delays",
                "35",
                "--const",
                "--alpha",
                "1e-3",
                "--out",
                str(out),
                "-q",
                "--interval",
                "0",
            ]
        )
        == 0
    )  # the test R^2 is the point here, not the intervals (13 s less)
    test = json.loads((out / "report.json").read_text())["test"]
    assert test["n_diverged"] == 0, test["diverged"]
    return test["r2_mean"]


@pytest.mark.slow
def test_re_identified_under_the_design_the_plant_predicts_both_loops(twin_cycle, tmp_path):
    """Issue 28 section 4, shrunk to 6 training episodes: CL EDMD on episodes run under the design
    predicts new ones (R^2 >= 0.95), and the plants identified under the design and under the rig's
    PD predict each other's closed loops, on excitations neither was trained on: the PD's plant the
    design's at R^2 >= 0.95, the design's plant the PD's at R^2 >= 0.93.

    Here 0.997, 0.943 and 0.997 (0.956 for the design's plant on the PD before the twin had the
    arm's cable spring); at full size (28 training, 20 test episodes each, the design from the
    paper's data, the twin without the spring) 0.997, 0.971 and 0.997. The weak direction is the
    design's plant predicting the PD: the design holds the arm tighter, so its episodes show less of
    the arm's slow motion, which the cables' spring now loads (a plant that fits the design's
    episodes at 0.997 predicts the PD's at 0.943 whatever the regularization: 0.943-0.947 for
    alpha 1e-4 to 1e-2).
    """
    scores = {
        "design -> design": _cl_edmd_r2(twin_cycle.designed, twin_cycle.designed_new, tmp_path / "dd"),
        "design -> PD": _cl_edmd_r2(twin_cycle.designed, twin_cycle.pd_train, tmp_path / "dp"),
        "PD -> design": _cl_edmd_r2(twin_cycle.pd_train, twin_cycle.designed_new, tmp_path / "pd"),
    }
    assert scores["design -> design"] >= 0.95 and scores["PD -> design"] >= 0.95, scores
    assert scores["design -> PD"] >= 0.93, scores


def _rrd_series(path: Path) -> dict[str, np.ndarray]:
    """Every entity's logged values in a recording: scalar series, and Points2D positions as complex numbers."""
    from rerun.chunk import RrdReader

    out: dict[str, list] = {}
    for chunk in RrdReader(path).store().stream():
        batch = chunk.to_record_batch()
        if "Scalars:scalars" in batch.schema.names:
            out.setdefault(chunk.entity_path, []).append(batch.column("Scalars:scalars").flatten().to_numpy())
        elif "Points2D:positions" in batch.schema.names:
            xy = np.asarray(batch.column("Points2D:positions").flatten().flatten().to_numpy()).reshape(-1, 2)
            out.setdefault(chunk.entity_path, []).append(xy[:, 0] + 1j * xy[:, 1])
    return {path.lstrip("/"): np.concatenate(parts) for path, parts in out.items()}


@pytest.mark.slow
def test_the_rerun_recording_shows_the_prediction_the_twins_episodes_and_both_loops_eigenvalues(twin_cycle, tmp_path):
    """``qube-design --rerun-save``: the twin series are the episodes ``qube-run`` logged under each controller
    on that excitation, the predicted ones the plant model's closed loop, the eigenvalues the design
    plant's closed loops (float32 in the recording)."""
    pytest.importorskip("rerun", reason="the viewer is the optional viz extra")
    from qube_koopman.daq.log import read_episode
    from qube_koopman.design.predict import predict_loop, rig_excitations
    from qube_koopman.identify.models.model_file import load_model

    rrd, out = tmp_path / "design.rrd", tmp_path / "again.toml"
    assert (
        design_main(
            [
                str(twin_cycle.model),
                "--out",
                str(out),
                "--seed",
                "5",
                "--episodes",
                "6",
                "--rerun-save",
                str(rrd),
                "--rerun-episodes",
                "1",
                "-q",
            ]
        )
        == 0
    )
    series = _rrd_series(rrd)
    assert {p for p in series if p.startswith("episodes/")} == (
        {
            f"episodes/episode_00/{c}/{k}"
            for c in ("theta", "alpha", "voltage")
            for k in ("predicted", "twin", "twin_training")
        }
        | {"episodes/episode_00/theta/target"}
    )
    for kind, folder in (("twin", twin_cycle.designed), ("twin_training", twin_cycle.pd)):
        logged = read_episode(sorted(folder.glob("*.mcap"))[0])
        for channel, values in (("theta", logged.theta), ("alpha", logged.alpha), ("voltage", logged.plant_input)):
            np.testing.assert_array_equal(series[f"episodes/episode_00/{channel}/{kind}"], values)
    model, controller = load_model(twin_cycle.model / "model.json"), load_controller(out)
    predicted = predict_loop(model.plant, controller.system, rig_excitations(5, 1))
    np.testing.assert_allclose(series["episodes/episode_00/theta/predicted"], predicted.theta[0], rtol=1e-12)
    np.testing.assert_array_equal(series["episodes/episode_00/theta/target"], predicted.target_theta[0])
    plant = linear_plant(model.plant)
    for kind, system in (("design", controller.system), ("training", model.controller)):
        expected = closed_loop_eigenvalues(plant, system)
        np.testing.assert_allclose(series[f"eigenvalues/{kind}"], expected, atol=1e-6)
    radius = {kind: np.max(np.abs(series[f"eigenvalues/{kind}"])) for kind in ("design", "training")}
    assert radius["design"] == pytest.approx(controller.provenance["spectral_radius"], abs=1e-6)
    assert radius["training"] < 1  # the rig's PD stabilizes the identified plant too


# --- the design's uncertainty on the twin --------------------------------------------------------------------


@pytest.mark.slow
def test_on_the_twin_the_designs_measured_cost_falls_in_its_predicted_interval(twin_cycle):
    """Over 20 seeds (the 20 episodes of ``qube-run --seed 5 --episodes 20``, 6 s each: their cost after the
    first second is what the interval is about, and 6 s keep the test at 6 s of twin time) the design's mean
    measured J and its voltage RMS lie within the interval at 0.95 that its model file's bootstrap plants
    and held-out episodes give (design.uncertainty), and the interval is not the bootstrap's alone (which
    misses: the bootstrap plants' J spans about 1.5 %, the model's error on held-out episodes is 2 to 5 %)."""
    from qube_koopman.design.predict import episode_cost, predict_cost, rig_excitations
    from qube_koopman.design.twin import run_on_twin
    from qube_koopman.design.uncertainty import interval_from_logs, model_uncertainty
    from qube_koopman.identify.models.model_file import load_model

    model = load_model(twin_cycle.model / "model.json")
    plant = linear_plant(model.plant)
    design = design_lq(plant, Weights())  # the fixture's controller file, designed with the default weights
    np.testing.assert_array_equal(design.controller.D, load_controller(twin_cycle.controller).system.D)
    excitations = rig_excitations(5, 20, 6.0)
    predicted = predict_cost(model.plant, design.controller, excitations).summary()
    interval = interval_from_logs(model_uncertainty(model), plant, design, predicted, excitations, 0.95)
    episodes = run_on_twin(twin_cycle.controller, 5, 20, duration=6.0)
    assert [e.metadata.status for e in episodes] == ["complete"] * 20
    costs = np.array([episode_cost(e.theta, e.target_theta, e.alpha, e.plant_input) for e in episodes])
    measured, voltage = np.mean(costs[:, 0]), np.sqrt(np.mean(costs[:, 3] ** 2))
    assert interval.n_members == 20 and interval.n_held_out == 6 and interval.propagated, interval.sources
    # The spectra the propagation starts from add up to what the held-out figures say (two computations).
    held = model.uncertainty.held_out
    spectra = model_uncertainty(model).spectra
    np.testing.assert_allclose(spectra.input.sum(axis=1), held.predicted[:, 1] ** 2, rtol=1e-5)
    assert interval.contains("J", measured), (measured, interval.as_dict()["J"])
    assert interval.upper["J"] / interval.lower["J"] < 1.25, interval.as_dict()["J"]  # and says something
    # The voltage too: the held-out error propagated through the design's loop, which turns more of the
    # sensors' noise into voltage than the PD the held-out episodes ran (the PD's ratio alone missed it).
    assert interval.contains("voltage_rms", voltage), (voltage, interval.as_dict()["voltage_rms"])
    assert interval.upper["voltage_rms"] / interval.lower["voltage_rms"] < 1.25, interval.as_dict()["voltage_rms"]


@pytest.mark.slow
def test_the_robust_design_is_the_nominal_one_when_the_bootstrap_plants_agree(twin_cycle):
    """``--robust`` on the twin's model: the worst case of J over the bootstrap plants rises with the voltage
    weight, and every bootstrap plant is stable under the nominal design, so it is the robust one; under the
    perturbed twins of the design's robustness check it then completes as many episodes as the nominal one,
    at the same J (docs/design.md gives the counts)."""
    from qube_koopman.design.predict import rig_excitations
    from qube_koopman.design.uncertainty import model_uncertainty, robust_design
    from qube_koopman.identify.models.model_file import load_model

    model = load_model(twin_cycle.model / "model.json")
    plant = linear_plant(model.plant)
    choice = robust_design(plant, Weights(), model_uncertainty(model), rig_excitations(5, 6, 6.0))
    worst = [c["worst_upper_J"] for c in choice.candidates]
    assert worst == sorted(worst) and choice.scale == 1.0, choice.candidates
    assert choice.candidates[0]["stable_members"] == 20, choice.candidates
    np.testing.assert_array_equal(choice.design.gain, design_lq(plant, Weights()).gain)


# --- the design's runs against its prediction (qube-compare) ---------------------------------------------------


@pytest.mark.slow
def test_qube_compare_finds_the_designs_twin_runs_inside_the_interval_it_predicted(twin_cycle, tmp_path, capsys):
    """The fixture's 6 episodes under the design on the excitation it was designed on (``--seed 5``), then 2 short
    twin episodes of another run (``--seed 8 --duration 6``): each compared with the prediction made again from
    the controller file's provenance, on the logs' own excitations; a log of the rig's PD is refused."""
    from qube_koopman.design.cli.compare import main as compare_main
    from qube_koopman.design.compare import compare_runs

    provenance = load_controller(twin_cycle.controller).provenance
    same = compare_runs(twin_cycle.controller, sorted(twin_cycle.designed.glob("*.mcap")))
    assert same.design_excitation and len(same.logs) == 6
    assert same.predicted["J"] == pytest.approx(provenance["predicted"]["J"], rel=1e-9)
    assert (same.interval.lower["J"], same.interval.upper["J"]) == pytest.approx(
        (provenance["interval"]["J"]["lower"], provenance["interval"]["J"]["upper"]), rel=1e-9
    )
    assert same.inside("J") and same.inside("voltage_rms"), (same.measured, same.interval.as_dict())

    short = tmp_path / "short"
    assert (
        run_main(
            [
                "--backend",
                "sim",
                "--episodes",
                "2",
                "--seed",
                "8",
                "--duration",
                "6",
                "--controller",
                str(twin_cycle.controller),
                "--out",
                str(short),
                "-q",
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert compare_main([str(twin_cycle.controller), str(short)]) == 0
    text = capsys.readouterr().out
    assert "2 episodes compared, after the first second, predicted by the model on the logs' excitations" in text
    other = compare_runs(twin_cycle.controller, sorted(short.glob("*.mcap")))
    lower, upper = other.interval.lower["J"], other.interval.upper["J"]
    assert 0.9 * lower <= other.measured["J"] <= 1.1 * upper, (other.measured["J"], lower, upper)
    assert other.predicted["J"] != pytest.approx(same.predicted["J"], rel=1e-3)  # another excitation, predicted anew

    pd_log = sorted(twin_cycle.pd.glob("*.mcap"))[0]
    assert compare_main([str(twin_cycle.controller), str(pd_log)]) == 1
    assert capsys.readouterr().err == (
        f"qube-compare: error: {pd_log}: recorded under another controller (pd, 2 "
        f"states), not {twin_cycle.controller}\n"
    )
