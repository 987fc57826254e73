"""Every file a command writes appears only whole: interrupted mid-write, nothing partial is left.

Each writer is stopped by a KeyboardInterrupt (what Ctrl-C raises) after it has put half its
bytes on disk: the final name must not exist (or keep its previous content), and no temporary
file may be left beside it.
"""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from qube_koopman.core.files import atomic_path


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".part" in p.name)


@pytest.fixture
def interrupt_text_writes(monkeypatch):
    """Path.write_text / write_bytes write half their data, then raise KeyboardInterrupt."""
    for name in ("write_text", "write_bytes"):
        original = getattr(Path, name)

        def half(self, data, *args, _original=original, **kwargs):
            _original(self, data[: len(data) // 2], *args, **kwargs)
            raise KeyboardInterrupt

        monkeypatch.setattr(Path, name, half)


def test_atomic_path_renames_whole_files_and_removes_interrupted_ones(tmp_path):
    target = tmp_path / "a.txt"
    with atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".txt" and tmp.name.startswith(".a.txt.")
        tmp.write_text("first")
    assert target.read_text() == "first"
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(target) as tmp:
            tmp.write_text("half of the seco")
            raise KeyboardInterrupt
    assert target.read_text() == "first" and _leftovers(tmp_path) == []
    with pytest.raises(FileExistsError, match="a.txt: file exists"):
        with atomic_path(target, overwrite=False) as tmp:
            tmp.write_text("never")
    assert target.read_text() == "first" and _leftovers(tmp_path) == []
    with pytest.raises(OSError):
        with atomic_path(tmp_path / "missing" / "b.txt"):
            pass


def test_devices_pipes_and_links_are_written_where_they_are(tmp_path):
    # A device is written in place (never renamed over: /dev/full stays a device and says ENOSPC).
    with pytest.raises(OSError, match="No space left"):
        with atomic_path("/dev/full") as target:
            assert target == Path("/dev/full")
            target.write_text("x")
    assert stat.S_ISCHR(os.stat("/dev/full").st_mode)
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    with atomic_path(fifo) as target:
        assert target == fifo
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    (tmp_path / "real.txt").write_text("old")
    (tmp_path / "link.txt").symlink_to(tmp_path / "real.txt")
    with atomic_path(tmp_path / "link.txt") as tmp:
        tmp.write_text("new")
    assert (tmp_path / "link.txt").is_symlink() and (tmp_path / "real.txt").read_text() == "new"


def test_atomic_files_get_the_mode_open_would_give(tmp_path):
    old = os.umask(0o027)
    try:
        with atomic_path(tmp_path / "m.txt") as tmp:
            tmp.write_text("x")
    finally:
        os.umask(old)
    assert stat.S_IMODE(os.stat(tmp_path / "m.txt").st_mode) == 0o640


def _episode():
    from _episodes import make_episode

    return make_episode(n=400)


@pytest.mark.parametrize("fmt", ["csv", "mat", "parquet"])
def test_an_interrupted_export_leaves_no_partial_file(fmt, tmp_path, monkeypatch, interrupt_text_writes):
    from qube_koopman.daq import export

    if fmt == "mat":
        import scipy.io

        def savemat(name, data, **kwargs):
            Path(name).open("wb").write(b"MATLAB 5.0 MAT-file, half")
            raise KeyboardInterrupt

        monkeypatch.setattr(scipy.io, "savemat", savemat)
    if fmt == "parquet":
        pq = pytest.importorskip("pyarrow.parquet")

        def write_table(table, name, **kwargs):
            Path(name).open("wb").write(b"PAR1 half")
            raise KeyboardInterrupt

        monkeypatch.setattr(pq, "write_table", write_table)
    target = tmp_path / f"episode.{fmt}"
    with pytest.raises(KeyboardInterrupt):
        export._WRITERS[fmt](_episode(), target)
    assert not target.exists() and _leftovers(tmp_path) == []


def test_interrupted_controller_plant_and_json_files_leave_nothing(tmp_path, monkeypatch, interrupt_text_writes):
    from qube_koopman.core.controller_file import write_controller_file
    from qube_koopman.core.command import write_json
    from qube_koopman.identify.report import markdown as reports
    from qube_koopman.core.lti import DiscreteStateSpace
    from qube_koopman.sim.pendulum import PendulumParameters
    from qube_koopman.sim.pendulum.params_file import PlantFile, save_plant

    system = DiscreteStateSpace(np.eye(2) * 0.5, np.eye(2), np.ones((1, 2)), np.ones((1, 2)), 0.002)
    writers = {
        "c.toml": lambda p: write_controller_file(p, system),
        "p.toml": lambda p: save_plant(p, PlantFile(PendulumParameters())),
        "r.json": lambda p: write_json(p, {"a": 1.0}),
        "r.md": lambda p: reports.write_markdown_report(p, {}),
    }
    monkeypatch.setattr(reports, "markdown_report", lambda report: "# a report\n" * 50)  # the writing is tested
    for name, write in writers.items():
        with pytest.raises(KeyboardInterrupt):
            write(tmp_path / name)
        assert not (tmp_path / name).exists(), name
    # the matrices of a controller file in a sibling .npz

    def savez(name, **arrays):
        Path(name).write_bytes(b"PK half")

    monkeypatch.setattr(np, "savez", savez)  # (write_bytes itself stops after half)
    with pytest.raises(KeyboardInterrupt):
        write_controller_file(tmp_path / "big.toml", system, npz=True)
    assert not (tmp_path / "big.npz").exists() and not (tmp_path / "big.toml").exists()
    assert _leftovers(tmp_path) == []


def test_an_interrupted_figure_or_recording_leaves_nothing(tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    from matplotlib.figure import Figure

    from qube_koopman.identify.report.figures import EigenvaluePlot, FigureSpec, write_figures

    def savefig(self, name, **kwargs):
        Path(name).open("wb").write(b"\x89PNG half")
        raise KeyboardInterrupt

    monkeypatch.setattr(Figure, "savefig", savefig)
    spec = FigureSpec("radius", "a caption", EigenvaluePlot("eigenvalues", {"plant": np.array([0.5 + 0.1j])}))
    with pytest.raises(KeyboardInterrupt):
        write_figures([spec], tmp_path)
    assert list(tmp_path.glob("radius*")) == [] and _leftovers(tmp_path) == []

    pytest.importorskip("rerun")
    from qube_koopman.identify.calibrate.validation_recording import write_recording
    from _calibration_replay import DT, NAMES, synthetic_replay

    def half(self, data):  # the recording's bytes half on disk when Ctrl-C comes
        self.open("wb").write(data[: len(data) // 2])
        raise KeyboardInterrupt

    monkeypatch.setattr(Path, "write_bytes", half)
    with pytest.raises(KeyboardInterrupt):
        write_recording(tmp_path / "calibration.rrd", synthetic_replay(), NAMES, DT)
    assert not (tmp_path / "calibration.rrd").exists() and _leftovers(tmp_path) == []


def test_an_interrupted_identification_leaves_no_partial_model_or_report(tmp_path, monkeypatch, capsys):
    from qube_koopman.daq.cli.run import main as run_main
    from qube_koopman.identify.cli.identify import main as identify_main

    assert run_main(["--episodes", "2", "--duration", "3", "--seed", "4", "--out", str(tmp_path / "logs"), "-q"]) == 0
    logs = sorted(map(str, (tmp_path / "logs").glob("*.mcap")))
    original = Path.write_text

    def half(self, data, *args, **kwargs):  # the model file is the first file written
        original(self, data[: len(data) // 2], *args, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(Path, "write_text", half)
    assert (
        identify_main(["--train", logs[0], "--test", logs[1], "--delays", "5", "--out", str(tmp_path / "m"), "-q"])
        == 130
    )
    assert "interrupted" in capsys.readouterr().err
    out = tmp_path / "m"
    assert not (out / "model.json").exists() and not (out / "report.json").exists()
    assert not out.exists() or _leftovers(out) == []


@pytest.mark.parametrize("signum, status", [("SIGINT", 130), ("SIGTERM", 143)])
def test_commands_stopped_by_a_signal_say_interrupted_in_one_line(signum, status, tmp_path, monkeypatch, capsys):
    # Each command's work is stopped by the signal (sent to the process itself, in the middle of it):
    # one "interrupted" line, the shell's exit status, no traceback, and no folder left empty.
    import signal

    from qube_koopman.daq.cli.export import main as export_main
    from qube_koopman.daq.cli.import_csv import main as import_main
    from qube_koopman.daq.cli.run import main as run_main
    from qube_koopman.identify.cli import identify as identify_cli

    assert run_main(["--episodes", "2", "--duration", "2", "--seed", "4", "--out", str(tmp_path / "logs"), "-q"]) == 0
    capsys.readouterr()
    logs = sorted(map(str, (tmp_path / "logs").glob("*.mcap")))

    def stop(*args, **kwargs):
        os.kill(os.getpid(), getattr(signal, signum))
        raise AssertionError("the signal should have stopped the command")

    from qube_koopman.daq import export as export_module
    from qube_koopman.daq import legacy_csv

    monkeypatch.setattr(export_module, "export_episode", stop)
    monkeypatch.setattr(legacy_csv, "legacy_episode", stop)
    monkeypatch.setattr(identify_cli, "identify_and_score", stop, raising=False)
    monkeypatch.setattr("qube_koopman.identify.workflow.identify_and_score", stop)
    from qube_koopman.core.controller import controller_file

    rig = controller_file("rig")
    (tmp_path / "episode.csv").write_text("t\n")
    runs = {
        "qube-export": lambda: export_main([*logs, "--format", "csv", "--out", str(tmp_path / "x")]),
        "qube-import": lambda: import_main(
            [str(tmp_path / "episode.csv"), "--controller", str(rig), "--out", str(tmp_path / "y")]
        ),
        "qube-identify": lambda: identify_cli.main(
            ["--train", logs[0], "--test", logs[1], "--out", str(tmp_path / "z" / "deep")]
        ),
    }
    for name, command in runs.items():
        assert command() == status, name
        err = capsys.readouterr().err
        assert err.strip().splitlines()[-1].endswith("interrupted") and "Traceback" not in err, (name, err)
    assert not (tmp_path / "z").exists()  # qube-identify created z/deep, stopped, removed them


def _writer_stopped_mid_write(target: Path) -> subprocess.Popen:
    """A process inside ``atomic_path(target)`` with half a file written, waiting for its stdin."""
    code = (
        "import sys; from qube_koopman.core.files import atomic_path\n"
        f"with atomic_path({str(target)!r}) as tmp:\n"
        "    tmp.write_bytes(b'half a file'); print(tmp, flush=True); sys.stdin.read()\n"
    )
    return subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


def test_the_next_write_removes_the_parts_killed_writers_left_never_a_live_ones(tmp_path):
    target = tmp_path / "run.rrd"
    killed, live = _writer_stopped_mid_write(target), _writer_stopped_mid_write(target)
    try:
        killed_part, live_part = Path(killed.stdout.readline().strip()), Path(live.stdout.readline().strip())
        killed.kill()  # SIGKILL: no finally runs, the part stays
        killed.wait(timeout=30)
        other = tmp_path / ".notes.txt.1a2b3c4d.part.txt"  # another file's: not this write's business
        other.write_text("x")
        assert killed_part.exists() and live_part.exists()
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"whole")
        assert not killed_part.exists(), "the killed writer's part is removed by the next write"
        assert live_part.exists() and other.exists(), "a live writer's part (and another file's) is kept"
        assert target.read_bytes() == b"whole"
    finally:
        live.communicate("", timeout=30)
        killed.wait(timeout=30)
    assert live.returncode == 0 and target.read_bytes() == b"half a file" and not live_part.exists()
