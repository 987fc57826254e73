"""Bad input gives a ValueError that names the problem, never a silent wrong answer."""

import numpy as np
import pytest

from qube_koopman.identify import Arx, ClEdmd, Delay, Edmd, Polynomial, Trajectory
from qube_koopman.core.lti import DiscreteStateSpace
from linear_loops import closed_loop_trajectories, mass_spring_damper, pid_position_controller


@pytest.fixture(scope="module")
def loop():
    A_p, B_p = mass_spring_damper()
    controller = pid_position_controller()
    return controller, closed_loop_trajectories(A_p, B_p, controller, [0], n_episodes=2, n=100, seed=0)


def test_mismatched_signal_lengths():
    with pytest.raises(ValueError, match="trajectory 'ep': u has 9 samples, expected 10"):
        Trajectory(x=np.zeros((10, 2)), u=np.zeros((9, 1)), name="ep")


def test_non_finite_data_is_located():
    x = np.zeros((10, 2))
    x[4, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite value at sample 4, channel 1"):
        Trajectory(x=x, name="ep")


def test_wrong_dimensions():
    with pytest.raises(ValueError, match="1-D or 2-D"):
        Trajectory(x=np.zeros((3, 2, 2)))


def test_episode_too_short_for_the_delays(loop):
    controller, trajs = loop
    short = Trajectory(x=trajs[0].x[:5], u=trajs[0].u[:5], name="short", dt=trajs[0].dt)
    with pytest.raises(ValueError, match="trajectory short has 5 samples; EDMD needs at least 12"):
        Edmd(lifting=[Delay(10)]).fit([trajs[0], short])


def test_episodes_with_different_widths(loop):
    controller, trajs = loop
    other = Trajectory(x=trajs[0].x[:, :1], u=trajs[0].u, name="narrow")
    with pytest.raises(ValueError, match="narrow: x has 1 channels, the first trajectory has 2"):
        Edmd().fit([trajs[0], other])


def test_missing_signal(loop):
    controller, trajs = loop
    with pytest.raises(ValueError, match="needs signal 'xc', missing in trajectory plain"):
        ClEdmd(controller, measured=[0]).fit([Trajectory(x=trajs[0].x, r=trajs[0].r, name="plain")])


def test_controller_dimensions_must_match_the_data(loop):
    controller, trajs = loop
    one_state = DiscreteStateSpace([[1.0]], [[1.0]], [[1.0]], [[1.0]], controller.dt)
    with pytest.raises(ValueError, match="controller has 1 states but the data's controller state has 2"):
        ClEdmd(one_state, measured=[0]).fit(trajs)
    with pytest.raises(ValueError, match="takes 1 tracking errors; the data has 1 references and 2 fed-back"):
        ClEdmd(controller).fit(trajs)  # default: both states fed back, the controller takes one error
    with pytest.raises(ValueError, match="outside"):
        ClEdmd(controller, measured=[5]).fit(trajs)


def test_sample_period_must_match_the_controller(loop):
    controller, trajs = loop
    slow = [Trajectory(x=t.x, r=t.r, f=t.f, xc=t.xc, dt=0.02) for t in trajs]
    with pytest.raises(ValueError, match="sample period 0.02 s differs from the controller's 0.01 s"):
        ClEdmd(controller, measured=[0]).fit(slow)


def test_feedforward_in_some_episodes_only(loop):
    controller, trajs = loop
    without = Trajectory(x=trajs[1].x, r=trajs[1].r, xc=trajs[1].xc, dt=trajs[1].dt)
    with pytest.raises(ValueError, match="feedforward f is present in some episodes"):
        ClEdmd(controller, measured=[0]).fit([trajs[0], without])


@pytest.mark.parametrize("alpha", [-1.0, float("nan"), "big"])
def test_bad_alpha(loop, alpha):
    controller, trajs = loop
    with pytest.raises(ValueError, match="alpha must be a non-negative number"):
        Edmd(alpha=alpha).fit(trajs)


def test_unknown_options(loop):
    controller, trajs = loop
    with pytest.raises(ValueError, match="unknown regularize 'both'"):
        ClEdmd(controller, measured=[0], regularize="both").fit(trajs)
    with pytest.raises(ValueError, match="unknown parameter 'alhpa'"):
        Edmd().set_params(alhpa=1.0)
    with pytest.raises(ValueError, match="not a LiftingFunction"):
        Edmd(lifting=["poly"]).fit(trajs)


def test_predict_before_fit_and_with_wrong_data(loop):
    controller, trajs = loop
    with pytest.raises(ValueError, match="not fitted"):
        Edmd().predict(trajs[0])
    model = Edmd(lifting=[Polynomial(2)]).fit(trajs)
    with pytest.raises(ValueError, match="has 1 states, the model 2"):
        model.predict(Trajectory(x=trajs[0].x[:, :1], u=trajs[0].u))
    with pytest.raises(ValueError, match="lacks signal 'u'"):
        model.predict(Trajectory(x=trajs[0].x))


def test_bad_state_space():
    with pytest.raises(ValueError, match="D must have shape"):
        DiscreteStateSpace([[1.0]], [[1.0]], [[1.0]], [[1.0, 2.0]], 0.1)
    with pytest.raises(ValueError, match="dt must be a positive"):
        DiscreteStateSpace([[1.0]], [[1.0]], [[1.0]], [[1.0]], 0.0)
    with pytest.raises(ValueError, match="A has non-finite"):
        DiscreteStateSpace([[np.inf]], [[1.0]], [[1.0]], [[1.0]], 0.1)


def test_arx_needs_its_input_signals(loop):
    controller, trajs = loop
    with pytest.raises(ValueError, match="needs signal 'f'"):
        Arx(inputs=("r", "f")).fit([Trajectory(x=trajs[0].x, r=trajs[0].r)])


# Files: a reader never waits on a named pipe or a device, never allocates what a small file
# declares before checking it, never recurses as deep as a crafted file nests.


def _deep(n: int = 100_000) -> str:
    return "[" * n + "]" * n


def test_a_special_or_oversized_file_is_refused_before_it_is_read(tmp_path):
    import os

    from qube_koopman.core.files import read_bounded_bytes

    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)  # no writer: reading it would block forever
    with pytest.raises(ValueError, match=f"^{pipe}: a named pipe, not a regular file: not read as the log$"):
        read_bounded_bytes(pipe, 100, "log")
    with pytest.raises(ValueError, match="^/dev/zero: a character device, not a regular file"):
        read_bounded_bytes("/dev/zero", 100, "log")
    (tmp_path / "big").write_bytes(b"x" * 101)
    with pytest.raises(ValueError, match="big: 101 bytes; the largest log read is 100 bytes"):
        read_bounded_bytes(tmp_path / "big", 100, "log")
    assert read_bounded_bytes(tmp_path / "big", 101, "log") == b"x" * 101


def test_nesting_is_bounded_without_recursion():
    from qube_koopman.core.files import check_nesting, loads_json, loads_toml

    for loads in (loads_json, loads_toml):
        text = _deep() if loads is loads_json else f"x = {_deep()}"
        with pytest.raises(ValueError, match="^f: lists and tables nested more than 64 levels deep$"):
            loads(text, "f")
    deep: list = []
    for _ in range(100_000):  # deeper than Python's stack: measured all the same
        deep = [deep]
    with pytest.raises(ValueError, match="nested more than 64"):
        check_nesting(deep, "f")
    assert loads_json(_deep(64), "f") == loads_json(_deep(64), "f", max_depth=64)


def _npz_declaring(path, shape) -> None:
    """An .npz whose array header declares ``shape`` float64 entries; its data a few zeros."""
    import io
    import zipfile

    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": shape})
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("A.npy", header.getvalue() + bytes(1000))


_STATE_SPACE = 'format = "qube-controller/1"\nkind = "state-space"\ndt = 0.002\ninputs = ["e_theta", "e_alpha"]\n'


@pytest.mark.parametrize(
    "case, message",
    [
        ("pipe", "{c}: a named pipe, not a regular file: not read as the controller file (--controller)"),
        (
            "/dev/zero",
            "/dev/zero: a character device, not a regular file: not read as the controller file (--controller)",
        ),
        ("deep", "{c}: lists and tables nested more than 64 levels deep (--controller)"),
        (
            "npz",
            "{c}: {d}/m.npz: array A declares 40000 x 40000 entries, more than the controller's matrices file "
            "may hold (matrices) (--controller)",
        ),
        (
            "npz-pipe",
            "{c}: {d}/m.npz: a named pipe, not a regular file: not read as the controller's matrices file "
            "(matrices) (--controller)",
        ),
    ],
)
def test_qube_run_refuses_a_crafted_controller_file_in_one_line(tmp_path, capsys, case, message):
    import os

    from qube_koopman.daq.cli.run import main

    controller = tmp_path / "c.toml"
    if case == "pipe":
        os.mkfifo(controller)
    elif case == "deep":
        controller.write_text(
            _STATE_SPACE + "A = [[1.0]]\nB = [[1.0, 1.0]]\nC = [[1.0]]\nD = [[0.0, 0.0]]\n"
            f"[provenance]\nx = {_deep()}\n"
        )
    elif case.startswith("npz"):
        if case == "npz":
            _npz_declaring(tmp_path / "m.npz", (40000, 40000))  # 12.8 GB once loaded
        else:
            os.mkfifo(tmp_path / "m.npz")
        controller.write_text(_STATE_SPACE + 'matrices = "m.npz"\n')
    else:
        controller = case
    assert (
        main(
            [
                "--episodes",
                "1",
                "--duration",
                "1",
                "--controller",
                str(controller),
                "--out",
                str(tmp_path / "runs"),
                "-q",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err == "qube-run: error: " + message.format(c=controller, d=tmp_path) + "\n"


def test_qube_run_never_waits_on_a_named_pipe_given_as_a_log(tmp_path, capsys):
    import os

    from qube_koopman.daq.cli.run import main

    os.mkfifo(tmp_path / "log.mcap")
    assert main(["--replay", str(tmp_path / "log.mcap"), "--out", str(tmp_path / "runs"), "-q"]) == 2
    assert "log.mcap: cannot read the episode log (a named pipe, not a regular file" in capsys.readouterr().err


def test_qube_run_refuses_to_replay_a_log_whose_seeds_are_not_64_bit(tmp_path, capsys):
    from _episodes import make_episode

    from qube_koopman.daq.cli.run import main
    from qube_koopman.daq.log import write_episode

    seeds = {"target_theta": 2**80, "target_alpha": 1, "feedforward": 2}
    write_episode(tmp_path / "log.mcap", make_episode(400, excitation={"seeds": seeds}))
    assert main(["--replay", str(tmp_path / "log.mcap"), "--out", str(tmp_path / "runs"), "-q"]) == 2
    err = capsys.readouterr().err
    assert err == (
        f"qube-run: error: {tmp_path / 'log.mcap'}: excitation seeds [{2**80}, 1, 2] are not 64-bit "
        "integers (qube-run records such seeds only); it cannot be replayed (--replay)\n"
    )


@pytest.mark.parametrize("command", ["export", "import"])
def test_qube_export_and_import_never_read_a_named_pipe(tmp_path, capsys, command):
    import os

    from qube_koopman.daq.cli.export import main as export_main
    from qube_koopman.daq.cli.import_csv import main as import_main

    pipe = tmp_path / ("log.mcap" if command == "export" else "qube_20230828T120000_1_2_3.csv")
    os.mkfifo(pipe)
    argv = [str(pipe), "--out", str(tmp_path / "out")] + (["--format", "csv"] if command == "export" else [])
    assert (export_main if command == "export" else import_main)(argv) == 2
    assert f"qube-{command}: error: {pipe}: not a regular file or folder\n" in capsys.readouterr().err
