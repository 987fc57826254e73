"""``qube-run`` (daq.cli.run) on the simulator: defaults, logs, errors, rerun, signals."""

from __future__ import annotations

import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from qube_koopman.daq.cli.run import main
from qube_koopman.core.controller import PdGains, pd_controller
from qube_koopman.daq.excitation import ExcitationSettings, generate_excitation
from qube_koopman.daq.log import read_episode, read_episode_metadata

REPO = Path(__file__).resolve().parents[2]
NAME = re.compile(r"^qube_\d{8}T\d{6}\.\d{3}_(\d+)_(\d+)_(\d+)(_\d+)?\.mcap$")


def _episodes(folder: Path):
    """The run's episodes, in file-name order (which must be the order they ran)."""
    return [read_episode(p) for p in sorted(folder.glob("*.mcap"))]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_no_arguments_collects_a_small_default_set_and_says_where(tmp_path, monkeypatch, capsys):
    # The fresh seed is pinned: a drawn one can, rarely, send the twin's arm past the 90 degree safety
    # stop (seed 214060 does, in episode 0; 200 of 200 episodes of seed 3 do not), which is the safety
    # layer working, not this test's subject.
    from qube_koopman.daq.cli import run

    monkeypatch.setattr(run, "fresh_seed", lambda: 5)
    monkeypatch.chdir(tmp_path)
    assert main([]) == 0
    out = capsys.readouterr().out
    assert "seed 5" in out
    files = sorted((tmp_path / "episodes").glob("*.mcap"))
    assert len(files) == 3 and all(NAME.match(f.name) for f in files)
    assert [read_episode_metadata(f).extra["episode_index"] for f in files] == [0, 1, 2]
    assert str(tmp_path / "episodes") in out and "3 complete, 0 aborted" in out
    for f in files:
        meta = read_episode_metadata(f)
        assert meta.status == "complete" and meta.backend == "sim"
        assert meta.excitation["settings"]["n_samples"] == 10_000  # 20 s at 500 Hz


def test_logs_hold_what_reproduces_the_run(tmp_path):
    assert main(["--episodes", "2", "--duration", "4", "--seed", "7", "--out", str(tmp_path), "-q"]) == 0
    eps = _episodes(tmp_path)
    assert [e.metadata.extra["episode_index"] for e in eps] == [0, 1]
    rig = pd_controller(PdGains(6.0, 1.8, 30.0, 2.5, 50.0))
    for path in tmp_path.glob("*.mcap"):
        ep = read_episode(path)
        meta = ep.metadata
        seeds = meta.excitation["seeds"]
        assert NAME.match(path.name).groups()[:3] == tuple(
            str(seeds[k]) for k in ("target_theta", "target_alpha", "feedforward")
        )
        # The excitation regenerates exactly from the log's seeds and settings.
        settings = ExcitationSettings.from_dict(meta.excitation["settings"])
        assert (settings.n_samples, settings.window_start, settings.window_stop) == (2000, 400, 1600)
        ex = generate_excitation(tuple(seeds[k] for k in ("target_theta", "target_alpha", "feedforward")), settings)
        assert np.array_equal(ep.target_theta, ex.target_theta)
        assert np.array_equal(ep.target_alpha, ex.target_alpha)
        assert np.array_equal(ep.feedforward, ex.feedforward)
        np.testing.assert_array_equal(ep.controller.A, rig.A)
        np.testing.assert_array_equal(ep.controller.D, rig.D)
        assert meta.controller.method == "backward-euler" and meta.extra["run_seed"] == 7
        assert meta.timing["n_ticks"] == 2000 and meta.timing["paced"] is False
        assert np.array_equal(ep.t, np.arange(2000) / 500)


def test_same_seed_same_episodes(tmp_path):
    for name in ("a", "b"):
        assert main(["--episodes", "2", "--duration", "2", "--seed", "11", "--out", str(tmp_path / name), "-q"]) == 0
    a, b = _episodes(tmp_path / "a"), _episodes(tmp_path / "b")
    for ea, eb in zip(a, b):
        assert ea.metadata.excitation == eb.metadata.excitation
        assert np.array_equal(ea.states, eb.states) and np.array_equal(ea.plant_input, eb.plant_input)
    assert a[0].metadata.excitation["seeds"] != a[1].metadata.excitation["seeds"]


def test_summary_counts_aborted_episodes(tmp_path, capsys):
    # A 3 deg motor-angle limit: the excitation's motor reference goes well past it.
    status = main(
        ["--episodes", "2", "--duration", "10", "--seed", "3", "--theta-limit", "3", "--out", str(tmp_path), "-q"]
    )
    out = capsys.readouterr().out
    assert status == 0, "a safety stop is a recorded outcome of an episode, not an error of the run"
    assert "0 complete, 2 aborted" in out and "safety stop: |theta|" in out
    for ep in _episodes(tmp_path):
        assert ep.metadata.status == "aborted" and "|theta|" in ep.metadata.status_reason
        assert abs(ep.theta[-1]) > math.radians(3) and ep.plant_input[-1] == 0.0
        assert np.all(np.abs(ep.theta[:-1]) <= math.radians(3))


@pytest.mark.parametrize(
    "args, message",
    [
        (["--controller", "missing.toml"], "qube-run: error: missing.toml: cannot read"),
        (["--controller", "{bad}"], "not valid TOML"),
        (["--out", "{file}"], "cannot write episode logs"),
        (["--backend", "quantum"], "invalid choice: 'quantum'"),
        (["--backend", "serial"], "--backend serial needs --port DEV"),
        (["--backend", "serial", "--port", "/dev/null", "--realtime"], "--realtime is for --backend sim"),
        (["--spin"], "--spin is for a loop that waits: give --realtime"),
        (["--port", "/dev/ttyACM0"], "--port, --baud and --link-timeout are for --backend serial"),
        (["--link-timeout", "100"], "--port, --baud and --link-timeout are for --backend serial"),
        (["--backend", "serial", "--port", "/dev/x", "--baud", "0"], "must be at least 1"),
        (["--episodes", "0"], "must be at least 1"),
        (["--episodes", "1000001"], "--episodes 1000001: at most 1,000,000 in one run"),
        (["--duration", "86400.002"], "at most 86400 s (24 h) per episode"),
        (["--duration", "nan"], "must be a finite number"),
        (["--duration", "-1"], "must be a positive number"),
        (["--duration", "0.0013"], "not a whole, positive number of samples"),
        (["--perturbation", "6"], "start gate"),
        (["--alpha-limit", "2"], "start_alpha"),
        (["--rerun-save", "no/such/folder/run.rrd"], "does not exist"),
        (["--rerun-save", "{file}"], "a_file: exists (use --force to overwrite) (--rerun-save)"),
        (["--controller", "{binary}"], "binary.toml: not a text file (a TOML controller file is expected)"),
    ],
)
def test_user_mistakes_get_one_line_and_no_traceback(tmp_path, capsys, args, message):
    bad = tmp_path / "bad.toml"
    bad.write_text("kp_theta = [")
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    binary = tmp_path / "binary.toml"
    binary.write_bytes(bytes(range(256)))
    args = [a.format(bad=bad, file=a_file, binary=binary) for a in args]
    out_dir = tmp_path / "out"
    if "--out" not in args:
        args += ["--out", str(out_dir)]
    status = main(args + ["-q"])
    err = capsys.readouterr().err
    assert status == 2
    assert err.count("\n") == 1 and err.startswith("qube-run: error:") and message in err
    assert "Traceback" not in err
    assert not out_dir.exists()  # a refused command leaves no empty episode folder behind


def test_help_documents_the_options(capsys):
    assert main(["--help"]) == 0
    text = capsys.readouterr().out
    for option in (
        "--backend",
        "--episodes",
        "--duration",
        "--seed",
        "--out",
        "--controller",
        "--realtime",
        "--rerun",
        "--rerun-save",
        "exit status",
    ):
        assert option in text


def test_rerun_save_records_the_run_with_a_blueprint(tmp_path):
    from rerun.chunk import RrdReader

    rrd = tmp_path / "run.rrd"
    assert (
        main(
            [
                "--episodes",
                "2",
                "--duration",
                "2",
                "--seed",
                "1",
                "--out",
                str(tmp_path / "ep"),
                "--rerun-save",
                str(rrd),
                "-q",
            ]
        )
        == 0
    )
    reader = RrdReader(str(rrd))
    assert len(reader.recordings()) == 1 and len(reader.blueprints()) == 1
    rows: dict[str, int] = {}
    for chunk in reader.stream():
        if not chunk.is_static:
            rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    # One entity per plot, one series per column: angles with their references, voltages, timing.
    for path in ("/theta", "/alpha", "/voltage", "/timing"):
        assert rows[path] == 2 * 1000, path
    theta = next(c for c in reader.stream() if c.entity_path == "/theta" and not c.is_static)
    assert len(theta.to_record_batch().column("Scalars:scalars")[0]) == 2  # measured, reference
    assert rows["/events"] == 4  # a start and an end per episode


def test_rerun_without_a_viewer_or_display_fails_cleanly(tmp_path, capsys, monkeypatch):
    probe = socket.socket()
    if probe.connect_ex(("127.0.0.1", 9876)) == 0:
        probe.close()
        pytest.skip("a rerun viewer is listening on 127.0.0.1:9876")
    probe.close()
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    status = main(["--rerun", "--episodes", "1", "--duration", "1", "--out", str(tmp_path), "-q"])
    err = capsys.readouterr().err
    assert status == 1 and err.count("\n") == 1 and "--rerun-save" in err and "Traceback" not in err
    assert not list(tmp_path.glob("*.mcap"))


@pytest.mark.slow  # the SDK gives up an unreachable viewer after about 10 s
def test_rerun_to_a_viewer_that_is_not_there_is_one_line_after_the_summary(tmp_path):
    pytest.importorskip("rerun", reason="the viewer is the optional viz extra")
    with socket.socket() as probe:  # a port nothing listens on once closed
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    code = "import sys; from qube_koopman.daq.cli.run import main; sys.exit(main(sys.argv[1:]))"
    proc = subprocess.run(
        [
            sys.executable,
            "-c",
            code,
            "--rerun",
            f"rerun+http://127.0.0.1:{port}/proxy",
            "--episodes",
            "1",
            "--duration",
            "1",
            "--out",
            str(tmp_path),
            "-q",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 1 and len(err) == 1, proc.stderr  # no traceback, none of the SDK's own lines
    assert err[0].startswith("qube-run: error: --rerun: the viewer did not take the recording: "), err
    assert "1 complete, 0 aborted; 1 episode log in" in proc.stdout and len(list(tmp_path.glob("*.mcap"))) == 1


def test_rerun_streams_to_a_listening_server(tmp_path):
    if shutil.which("rerun") is None:
        pytest.skip("the rerun command (from rerun-sdk) is not on PATH")
    port = _free_port()
    # `rerun` is a wrapper that runs the viewer binary as its child: its own session, so that
    # stopping it stops the binary too (terminating the wrapper alone left the server running).
    server = subprocess.Popen(
        ["rerun", "--serve-grpc", "--port", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 20
        while socket.socket().connect_ex(("127.0.0.1", port)) != 0:
            assert time.monotonic() < deadline, "rerun server did not start"
            assert server.poll() is None, "rerun server exited"
            time.sleep(0.1)
        assert (
            main(
                [
                    "--rerun",
                    f"rerun+http://127.0.0.1:{port}/proxy",
                    "--episodes",
                    "1",
                    "--duration",
                    "1",
                    "--out",
                    str(tmp_path),
                    "-q",
                ]
            )
            == 0
        )
    finally:
        _stop_group(server)


def _stop_group(proc: subprocess.Popen, grace: float = 5.0) -> None:
    """SIGTERM a process group led by ``proc``; SIGKILL whatever of it still runs after ``grace``."""
    os.killpg(proc.pid, signal.SIGTERM)
    proc.wait(timeout=10)
    deadline = time.monotonic() + grace
    while _group_alive(proc.pid):
        if time.monotonic() > deadline:
            os.killpg(proc.pid, signal.SIGKILL)
            break
        time.sleep(0.05)


def _group_alive(pgid: int) -> bool:
    """Whether a live (not zombie) process of group ``pgid`` remains (from /proc)."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[0] != "Z" and int(fields[3]) == pgid:
            return True
    return False


# --- signals: a real process, paced in real time -------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_stops_the_motor_and_closes_the_log_aborted(tmp_path, signum):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    code = "import sys; from daq.cli.run import main; sys.exit(main(sys.argv[1:]))"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            code,
            "--realtime",
            "--episodes",
            "3",
            "--duration",
            "20",
            "--seed",
            "5",
            "--out",
            str(tmp_path),
            "-q",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        deadline = time.monotonic() + 30
        # Wait until the first log exists and has flushed data (0.5 s chunks), then signal.
        while not any(p.stat().st_size > 4000 for p in tmp_path.glob("*.mcap")):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "qube-run wrote no log in 30 s"
            time.sleep(0.05)
        time.sleep(0.3)
        proc.send_signal(signum)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signum, err
    name = signal.Signals(signum).name
    files = list(tmp_path.glob("*.mcap"))
    assert len(files) == 1, "the run stops at the signal: no further episodes"
    ep = read_episode(files[0])  # warns if anything was salvaged: it must not be
    meta = ep.metadata
    assert meta.status == "aborted" and meta.status_reason == f"interrupted by {name}"
    assert not meta.salvaged
    n = len(ep)
    assert 250 < n < 10_000
    assert np.array_equal(ep.t, np.arange(n) / 500), "no sample lost"
    assert ep.plant_input[-1] == 0.0, "0 V in the tick that saw the signal"
    assert meta.timing["n_ticks"] == n and meta.timing["paced"] is True
    assert "0 complete, 1 aborted" in out and f"interrupted by {name}" in err


@pytest.mark.parametrize("signum, status", [("SIGINT", 130), ("SIGTERM", 143)])
def test_a_signal_before_the_episodes_is_one_interrupted_line(signum, status, tmp_path, monkeypatch, capsys):
    # Before its episodes qube-run stops as every command does (run_command): one line, the shell's
    # status, nothing written; during them its own handlers stop the motor (the test above).
    from qube_koopman.daq import session

    def stop(*args, **kwargs):
        os.kill(os.getpid(), getattr(signal, signum))
        raise AssertionError("the signal should have stopped the command")

    monkeypatch.setattr(session, "plan_episodes", stop)
    assert main(["--episodes", "1", "--duration", "2", "--out", str(tmp_path / "logs"), "-q"]) == status
    assert capsys.readouterr().err == "qube-run: error: interrupted\n"
    assert not (tmp_path / "logs").exists()


@pytest.mark.parametrize("text,expected", [("0", 0.0), ("0.00", 0.0), ("0e0", 0.0), ("-0", 0.0), ("2.5", 2.5)])
def test_non_negative_options_accept_any_spelling_of_zero(text, expected):
    from qube_koopman.daq.cli.run import build_parser

    assert build_parser().parse_args(["--perturbation", text]).perturbation == expected


def test_negative_perturbation_is_refused(capsys):
    from qube_koopman.daq.cli.run import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["--perturbation", "-1"])
    assert "must be zero or positive" in capsys.readouterr().err


def test_shipped_controllers_by_name_and_a_file_of_that_name_wins(tmp_path, monkeypatch):
    from qube_koopman.core.controller import load_pd_gains

    assert load_pd_gains("rig") == PdGains(6.0, 1.8, 30.0, 2.5, 50.0)  # the dataset's controller.toml
    assert load_pd_gains("soft-theta") == PdGains(2.0, 1.0, 35.0, 3.0, 50.0)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "soft-theta").write_text(
        "kp_theta = 1.0\nkd_theta = 1.0\nkp_alpha = 30.0\nkd_alpha = 2.5\ntau = 50.0\n"
    )
    assert load_pd_gains("soft-theta").kp_theta == 1.0
    assert main(["--episodes", "1", "--duration", "2", "--controller", "rig", "--out", "e", "-q"]) == 0
    assert read_episode_metadata(next((tmp_path / "e").glob("*.mcap"))).controller.gains["kp_theta"] == 6.0
    # A folder named like a shipped controller (episodes in ./rig, say) is not a controller file.
    assert main(["--episodes", "1", "--duration", "2", "--out", "rig", "-q"]) == 0
    assert load_pd_gains("rig") == PdGains(6.0, 1.8, 30.0, 2.5, 50.0)
    assert main(["--episodes", "1", "--duration", "2", "--out", "rig", "--append", "-q"]) == 0


@pytest.mark.parametrize(
    "content, problem", [(None, "No such file or directory"), (b"not a log", "not an MCAP file (bad magic bytes)")]
)
def test_a_replay_log_that_cannot_be_read_is_named_once_and_first(content, problem, tmp_path, capsys):
    log = tmp_path / "junk.mcap"
    if content is not None:
        log.write_bytes(content)
    assert main(["--replay", str(log), "--out", str(tmp_path / "o"), "-q"]) == 2
    assert capsys.readouterr().err == (f"qube-run: error: {log}: cannot read the episode log ({problem}) (--replay)\n")


@pytest.mark.parametrize("value", ["0", "100", "-1"])
def test_rt_priority_out_of_its_range_is_a_one_line_usage_error(value, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["--rt-priority", value, "--episodes", "1", "--duration", "1", "--out", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    said = f"argument --rt-priority: must be a whole number in [1, 99], got {value}"
    assert err == f"qube-run: error: {said} (see qube-run --help)\n"
    assert not out.exists()


def test_an_out_folder_with_logs_is_refused_unless_append(tmp_path, capsys):
    out = tmp_path / "runs"
    assert main(["--episodes", "2", "--duration", "0.2", "--out", str(out), "-q"]) == 0
    capsys.readouterr()
    assert main(["--episodes", "1", "--duration", "0.2", "--out", str(out), "-q"]) == 2
    assert capsys.readouterr().err == (
        f"qube-run: error: {out}: already holds 2 episode logs; add --append to add "
        "this run's to them, or give another --out\n"
    )
    assert len(list(out.glob("*.mcap"))) == 2
    assert main(["--episodes", "1", "--duration", "0.2", "--out", str(out), "--append", "-q"]) == 0
    assert len(list(out.glob("*.mcap"))) == 3
    (empty := tmp_path / "empty").mkdir()
    (empty / "notes.txt").write_text("no logs here")
    assert main(["--episodes", "1", "--duration", "0.2", "--out", str(empty), "-q"]) == 0


def test_a_run_that_fails_before_any_log_leaves_no_folder_it_made(tmp_path, capsys):
    # A bridge that answers the handshake, then sends no telemetry: the link is lost at the start gate,
    # before any episode log. The folders the run made for its logs go again; one that was there stays.
    from bridge_helpers import FakeDevice

    from qube_koopman.firmware_protocol import Config, ConfigAck, Hello, HelloReply, encode_frame

    def respond(frame):
        if isinstance(frame.message, Hello):
            return encode_frame(HelloReply(nonce=frame.message.nonce, capabilities=0x7F, module_id=777), 1, 0)
        if isinstance(frame.message, Config):
            return encode_frame(ConfigAck(), 2, 0)
        return b""

    (kept := tmp_path / "kept").mkdir()
    for out in (tmp_path / "a" / "b", kept):
        with FakeDevice(respond) as dev:
            status = main(["--backend", "serial", "--port", dev.path, "--episodes", "1", "--out", str(out), "-q"])
        assert status == 1 and "link lost" in capsys.readouterr().err
    assert not (tmp_path / "a").exists(), "the folders it made are gone"
    assert kept.is_dir() and not list(kept.iterdir())


def test_max_voltage_lowers_the_clamp_for_any_controller(tmp_path, capsys):
    out = tmp_path / "low"
    assert (
        main(
            [
                "--episodes",
                "1",
                "--duration",
                "4",
                "--seed",
                "2",
                "--max-voltage",
                "0.8",
                "--out",
                str(out),
                "--n-jobs",
                "1",
                "-q",
            ]
        )
        == 0
    )
    episode = read_episode(next(out.glob("*.mcap")))
    assert episode.metadata.extra["safety"]["max_voltage"] == 0.8
    assert np.max(np.abs(episode.plant_input)) == pytest.approx(0.8) and episode.saturation.any()
    clipped = np.clip(episode.control_output + episode.feedforward, -0.8, 0.8)
    np.testing.assert_array_equal(episode.plant_input[episode.saturation != 0], clipped[episode.saturation != 0])
    assert main(["--max-voltage", "12", "--out", str(tmp_path / "x")]) == 2
    assert "--max-voltage 12: at most the rig's 10 V" in capsys.readouterr().err


# --- a controller file checked on the twin before it runs ----------------------------------------------------

#: The rig's gains with the pendulum's proportional gain turned round: the twin's linearized loop diverges
#: (spectral radius 1.053).
_FLIPPED = "kp_theta = 6.0\nkd_theta = 1.8\nkp_alpha = -30.0\nkd_alpha = 2.5\ntau = 50.0\n"


def test_a_controller_destabilising_the_twin_is_refused_on_the_rig_before_the_port_is_opened(tmp_path, capsys):
    bad = tmp_path / "flipped.toml"
    bad.write_text(_FLIPPED)
    port = tmp_path / "no-such-device"  # never opened: the refusal comes first
    out = tmp_path / "runs"
    argv = ["--backend", "serial", "--port", str(port), "--controller", str(bad), "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err == (
        f"qube-run: error: {bad}: the controller destabilises the twin's loop linearized at upright "
        "(spectral radius 1.0535 > 1): refused on the rig; --run-unstable runs it anyway\n"
    )
    assert not out.exists()
    # --run-unstable lifts the refusal: a warning, then the run goes on to the port (missing here: exit 1)
    assert main([*argv, "--run-unstable"]) == 1
    err = capsys.readouterr().err
    warning, error = err.splitlines()
    assert (
        warning.startswith(f"qube-run: warning: {bad}: the controller destabilises")
        and "--run-unstable asks" in warning
    )
    assert str(port) in error and "destabilises" not in error


def test_a_controller_destabilising_the_twin_runs_on_the_simulator_with_a_warning(tmp_path, capsys):
    bad = tmp_path / "flipped.toml"
    bad.write_text(_FLIPPED)
    out = tmp_path / "runs"
    assert (
        main(["--controller", str(bad), "--episodes", "1", "--duration", "2", "--seed", "1", "--out", str(out), "-q"])
        == 0
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"qube-run: warning: {bad}: the controller destabilises the twin's")
    assert len(list(out.glob("*.mcap"))) == 1
    assert main(["--run-unstable", "--controller", str(bad), "--out", str(tmp_path / "x")]) == 2
    assert "--run-unstable is for --backend serial" in capsys.readouterr().err


def test_a_stable_controller_file_runs_without_a_word_and_a_kind_beyond_lti_is_not_judged(tmp_path, capsys):
    from qube_koopman.core.controller_file import ControllerInfo, write_controller_file
    from qube_koopman.core.lti import DiscreteStateSpace
    from qube_koopman.daq.twin_check import check_controller_file_on_twin, judged_system

    rig = pd_controller(PdGains(6.0, 1.8, 30.0, 2.5, 50.0))
    # the rig's PD with a feedforward input that cancels the feedforward: judged on its tracking-error columns
    with_f = DiscreteStateSpace(
        rig.A, np.hstack([rig.B, np.zeros((rig.n_states, 1))]), rig.C, np.hstack([rig.D, [[-1.0]]]), rig.dt
    )
    path = write_controller_file(tmp_path / "rig_ff.toml", with_f)
    assert (
        main(
            [
                "--controller",
                str(path),
                "--episodes",
                "1",
                "--duration",
                "2",
                "--seed",
                "1",
                "--out",
                str(tmp_path / "runs"),
                "-q",
            ]
        )
        == 0
    )
    assert capsys.readouterr().err == ""
    flipped = pd_controller(PdGains(6.0, 1.8, -30.0, 2.5, 50.0))
    judged = ControllerInfo(flipped, "given", kind="state-space")
    assert judged_system(judged) is flipped
    assert check_controller_file_on_twin(judged, "f.toml", "sim").startswith("f.toml: the controller destabilises")
    beyond = ControllerInfo(flipped, "given", kind="mpc", runtime=object())  # an MPC's loop is not its system's
    assert judged_system(beyond) is None and check_controller_file_on_twin(beyond, "m.toml", "serial") is None


def test_realtime_spin_runs_paced_and_the_log_says_the_loop_spun(tmp_path):
    """``qube-run --realtime --spin``: the episode runs paced, as without it, and its log records the wait."""
    assert main(["--realtime", "--spin", "--episodes", "1", "--duration", "0.5", "--out", str(tmp_path), "-q"]) == 0
    (log,) = tmp_path.glob("*.mcap")
    meta = read_episode(log).metadata
    assert meta.status == "complete" and meta.timing["paced"] is True
    assert meta.extra["backend"]["spin"] is True and meta.extra["backend"]["realtime"] is True
