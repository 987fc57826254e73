"""Rerun recordings that cannot be written: one error line, exit 1, every other result intact, never a hang.

Each command runs in a child process under a file-size limit (RLIMIT_FSIZE) that lets its logs,
model files and reports through but not its ``.rrd``: the kernel refuses the write past the limit
with EFBIG (Python ignores SIGXFSZ, as it is started; a shell's ``ulimit -f`` leaves the rest to
it). Before, rerun-sdk's file writer thread ended on that error and a flush queued behind it was
never answered: a traceback, or a process hung for good. The child's timeout turns a hang into a
failure.
"""

from __future__ import annotations

import resource
import signal
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("rerun", reason="the viewer is the optional viz extra")

TIMEOUT_S = 120  # a run takes seconds; a hang fails the test instead of blocking the suite


def _limited(limit: int):
    def setup():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # as Python sets it anyway: EFBIG, not a kill
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return setup


def _run_limited(module: str, argv: list, limit: int) -> subprocess.CompletedProcess:
    code = f"import sys; from qube_koopman.{module} import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run(
        [sys.executable, "-c", code, *map(str, argv)],
        capture_output=True,
        text=True,
        preexec_fn=_limited(limit),
        timeout=TIMEOUT_S,
    )


def _assert_one_error_line(proc, prog: str, rrd: Path) -> None:
    # The command's own warnings (a calibration stopped by --max-nfev) may come first; nothing else may.
    err = [line for line in proc.stderr.strip().splitlines() if not line.startswith(f"{prog}: warning: ")]
    assert proc.returncode == 1, proc.stderr
    assert len(err) == 1 and err[0].startswith(f"{prog}: error: {rrd}: ") and "File too large" in err[0], err
    assert not rrd.exists(), "no recording (nor a partial one) under the final name"
    assert [p.name for p in rrd.parent.iterdir() if ".part" in p.name] == [], "no temporary file left"


@pytest.fixture(scope="module")
def logs(tmp_path_factory) -> list[Path]:
    from qube_koopman.daq.cli.run import main as run_main

    folder = tmp_path_factory.mktemp("logs")
    assert run_main(["--episodes", "3", "--duration", "10", "--seed", "3", "--out", str(folder), "-q"]) == 0
    return sorted(folder.glob("*.mcap"))


def test_qube_run_on_a_file_size_limit_keeps_its_logs_and_summary(tmp_path):
    rrd = tmp_path / "run.rrd"
    proc = _run_limited(
        "daq.cli.run",
        ["--episodes", "1", "--duration", "3", "--seed", "1", "--out", tmp_path / "ep", "--rerun-save", rrd],
        limit=200_000,
    )
    _assert_one_error_line(proc, "qube-run", rrd)
    assert "the rerun recording was not written" in proc.stderr
    assert "1 complete, 0 aborted; 1 episode log in" in proc.stdout and "rerun recording in" not in proc.stdout
    assert len(list((tmp_path / "ep").glob("*.mcap"))) == 1


def test_qube_calibrate_on_a_file_size_limit_keeps_its_plant_report_and_tables(logs, tmp_path):
    rrd = tmp_path / "rep" / "calibration.rrd"
    proc = _run_limited(
        "identify.cli.calibrate",
        [
            logs[0],
            logs[1],
            "--validate",
            logs[2],
            "--max-nfev",
            "2",
            "--out",
            tmp_path / "c.toml",
            "--report",
            tmp_path / "rep",
        ],
        limit=100_000,
    )
    _assert_one_error_line(proc, "qube-calibrate", rrd)
    assert (tmp_path / "c.toml").stat().st_size > 0 and "## Validation" in (tmp_path / "rep" / "report.md").read_text()
    assert "## Validation on 1 episodes not fitted" in proc.stdout


def test_qube_identify_on_a_file_size_limit_keeps_its_model_reports_and_scores(logs, tmp_path):
    rrd = tmp_path / "id.rrd"
    proc = _run_limited(
        "identify.cli.identify",
        [
            "--train",
            logs[0],
            logs[1],
            "--test",
            logs[2],
            "--delays",
            "5",
            "--interval",
            "0",
            "--out",
            tmp_path / "model",
            "--rerun-save",
            rrd,
        ],
        limit=150_000,
    )
    _assert_one_error_line(proc, "qube-identify", rrd)
    assert "the rerun recording was not written" in proc.stderr
    for name in ("model.json", "report.json", "report.md"):
        assert (tmp_path / "model" / name).stat().st_size > 0, name
    assert "R^2" in proc.stdout and f"wrote {tmp_path / 'model' / 'model.json'}" in proc.stdout


def test_qube_design_on_a_file_size_limit_keeps_its_controller_and_summary(logs, tmp_path):
    from qube_koopman.identify.cli.identify import main as identify_main

    model = tmp_path / "model"
    assert (
        identify_main(
            [
                "--train",
                str(logs[0]),
                str(logs[1]),
                "--test",
                str(logs[2]),
                "--poly",
                "1",
                "--delays",
                "35",
                "--const",
                "--out",
                str(model),
                "-q",
            ]
        )
        == 0
    )
    rrd, out = tmp_path / "design.rrd", tmp_path / "designed.toml"
    proc = _run_limited(
        "design.cli.design",
        [model, "--out", out, "--episodes", "2", "--rerun-save", rrd, "--rerun-episodes", "1"],
        limit=500_000,
    )
    _assert_one_error_line(proc, "qube-design", rrd)
    assert out.stat().st_size > 0 and f"wrote {out}: qube-run --controller {out}" in proc.stdout


def test_a_full_disk_is_an_error_naming_the_recording_and_leaves_nothing(tmp_path, monkeypatch):
    import errno
    import os

    from qube_koopman.core.rrd import RrdFile

    rrd = RrdFile(tmp_path / "x.rrd", "qube-test")
    rrd.recording.log("note", __import__("rerun").TextLog("hello"))

    def full(self, data):  # the disk fills half-way through the recording
        self.open("wb").write(data[: len(data) // 2])
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(Path, "write_bytes", full)
    with pytest.raises(OSError) as caught:
        rrd.save()
    assert (caught.value.errno, caught.value.filename) == (errno.ENOSPC, str(tmp_path / "x.rrd"))
    assert list(tmp_path.iterdir()) == []


def test_the_recordings_writer_ends_when_its_command_is_killed(tmp_path):
    # A command killed outright (here after its writer's disk refused the data): the child that
    # writes the recording sees its input end and exits by itself, file complete or not.
    psutil = pytest.importorskip("psutil")
    code = (
        "import os, signal, sys, numpy as np\n"
        "from qube_koopman.core.rrd import RrdProcess\n"
        f"rrd = RrdProcess({str(tmp_path / 'x.rrd')!r}, 'qube-test')\n"
        "for i in range(200):\n"
        "    rrd.send_scalars(f'a/{i}', [('time', 'duration', np.arange(500) * 0.002)], np.random.rand(500))\n"
        "print(rrd._child.pid, flush=True)\n"
        "sys.stdin.read()\n"
    )
    killed = subprocess.Popen(
        [sys.executable, "-c", code],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        preexec_fn=_limited(20_000),
    )
    try:
        child = psutil.Process(int(killed.stdout.readline()))
    finally:
        killed.kill()
        killed.wait(timeout=30)
    child.wait(timeout=TIMEOUT_S)  # psutil.TimeoutExpired: the writer outlived its command
    assert [p.name for p in tmp_path.iterdir() if p.name == "x.rrd"] == []
