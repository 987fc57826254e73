"""One rule for what every command writes, checked before any work.

- An output that cannot be written (its folder missing or read-only, its parent a file) is a user
  error: exit 2, one line naming the path and the option, before the command reads its inputs.
- An existing output file is replaced only with ``--force``: commands that write one result refuse
  it before any work (exit 2); ``qube-import`` and ``qube-export`` refuse each existing file on its
  own and go on with the others (exit 1, as for any file refused).
- Every command stopped by SIGINT / SIGTERM says so in one line (130 / 143).

Each command runs in-process in a copy of the ``template`` folder the argument fuzzing starts from
too (two short real episode logs, a legacy CSV, junk files); its long work is stubbed (``stubs``,
both tests/_command_stubs.py's), so reaching it counts as "passed the checks".
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from _command_stubs import run_in_process

GOOD_CSV = "qube_20230828T150615_434_696_394"
IDENTIFY = ["--train", "logs/a.mcap", "--test", "logs/b.mcap", "--skip", "0"]

#: command, argv with OUT where the output goes, what the command writes there (None: OUT is the file).
SINGLE_RESULT = [
    ("qube-identify", [*IDENTIFY, "--out", "OUT"], "model.json"),
    ("qube-identify", [*IDENTIFY, "--rerun-save", "OUT"], None),
    # The test episodes' predictions and intervals (--interval, on by default): a folder of one file per log.
    ("qube-identify", [*IDENTIFY, "--interval", "0.9", "--out", "OUT"], "predictions"),
    ("qube-calibrate", ["logs/a.mcap", "--out", "OUT"], None),
    ("qube-calibrate", ["logs/a.mcap", "--out", "p.toml", "--report", "OUT"], "report.md"),
    ("qube-design", ["junk.bin", "--out", "OUT"], None),
    ("qube-reproduce", ["duffing", "--out", "OUT"], "duffing.json"),
    ("qube-reproduce", ["qube", "--data", "logs", "--out", "OUT"], "qube.json"),
    ("qube-run", ["--episodes", "1", "--duration", "1", "--rerun-save", "OUT"], None),
    ("qube-emulate", ["--record", "OUT"], None),
    ("qube-emulate", ["--stats", "OUT"], None),
]
BATCH = [
    ("qube-import", ["csv", "--out", "OUT"], f"{GOOD_CSV}.mcap"),
    ("qube-export", ["logs", "--format", "csv", "--out", "OUT"], "a.csv"),
]
FOLDER_OUTPUTS = [case for case in SINGLE_RESULT + BATCH if case[2] is not None] + [
    ("qube-run", ["--episodes", "1", "--duration", "1", "--out", "OUT"], None)
]


def _ids(cases):
    return [f"{c} {a[a.index('OUT') - 1]}" for c, a, _ in cases]


def _argv(argv: list[str], out: str) -> list[str]:
    return [out if word == "OUT" else word for word in argv]


@pytest.fixture
def folder(template, tmp_path):
    shutil.copytree(template, tmp_path / "run")
    return tmp_path / "run"


def _existing(folder: Path, name: str | None, out: str) -> Path:
    """The output file that is already there (its folder made when the output is a folder)."""
    target = folder / out / name if name else folder / out
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_bytes(b"earlier result\n")
    return target


@pytest.mark.parametrize("command, argv, name", SINGLE_RESULT, ids=_ids(SINGLE_RESULT))
def test_an_existing_result_is_refused_before_any_work_and_kept(command, argv, name, folder, stubs):
    target = _existing(folder, name, "result.rrd" if "--rerun" in argv or "--rerun-save" in argv else "result")
    out = target.parent.name if name else target.name
    status, err = run_in_process(command, _argv(argv, out), folder)
    assert status == 2, err
    assert err.strip().splitlines() == [
        f"{command}: error: {target.relative_to(folder)}: exists (use --force to "
        f"overwrite) ({argv[argv.index('OUT') - 1]})"
    ], err
    assert target.read_bytes() == b"earlier result\n"


@pytest.mark.parametrize("command, argv, name", SINGLE_RESULT, ids=_ids(SINGLE_RESULT))
def test_force_lets_the_command_past_an_existing_result(command, argv, name, folder, stubs):
    target = _existing(folder, name, "result.rrd" if "--rerun" in argv or "--rerun-save" in argv else "result")
    out = target.parent.name if name else target.name
    status, err = run_in_process(command, [*_argv(argv, out), "--force"], folder)
    # Past the output's check: on to the work (stubbed), or to the next check, which is about the inputs.
    assert "exists" not in err and "Traceback" not in err, err
    assert status in (0, 1, "reached") or str(target.relative_to(folder)) not in err, err


@pytest.mark.parametrize("command, argv, name", BATCH, ids=_ids(BATCH))
def test_batch_commands_refuse_each_existing_file_and_go_on(command, argv, name, folder, stubs):
    target = _existing(folder, name, "o")
    status, err = run_in_process(command, _argv(argv, "o"), folder)
    assert status == 1 and "exists (use --force to overwrite)" in err and str(target.relative_to(folder)) in err, err
    assert target.read_bytes() == b"earlier result\n"
    status, err = run_in_process(command, [*_argv(argv, "o"), "--force", "-q"], folder)
    assert status == 0 and target.read_bytes() != b"earlier result\n", err


@pytest.mark.parametrize("command, argv, name", FOLDER_OUTPUTS, ids=_ids(FOLDER_OUTPUTS))
def test_an_output_folder_under_a_file_is_a_user_error_before_any_work(command, argv, name, folder, stubs):
    status, err = run_in_process(command, _argv(argv, "empty.txt/o"), folder)
    lines = err.strip().splitlines()
    assert status == 2 and len(lines) == 1 and "empty.txt" in lines[0] and "Traceback" not in err, err


@pytest.mark.parametrize("command, argv, name", FOLDER_OUTPUTS[:-1], ids=_ids(FOLDER_OUTPUTS[:-1]))
def test_a_read_only_output_folder_is_a_user_error_before_any_work(
    command,
    argv,
    name,
    folder,
    stubs,
    monkeypatch,
):
    # Read-only as the permission check sees it (the tests may run as root, whom a mode does not stop).
    (folder / "ro").mkdir()
    real_access = os.access
    monkeypatch.setattr(
        os,
        "access",
        lambda path, mode, *a, **k: (
            (Path(path).name != "ro" or not mode & os.W_OK) and real_access(path, mode, *a, **k)
        ),
    )
    status, err = run_in_process(command, _argv(argv, "ro"), folder)
    assert status == 2 and err.strip().splitlines() == [
        f"{command}: error: ro: cannot write in ro (permission denied) ({argv[argv.index('OUT') - 1]})"
    ], err
    assert list((folder / "ro").iterdir()) == []


def test_a_missing_output_folder_for_a_file_is_named(folder, stubs):
    status, err = run_in_process("qube-design", ["junk.bin", "--out", "missing/c.toml"], folder)
    assert status == 2 and err.strip() == "qube-design: error: missing/c.toml: folder missing does not exist (--out)"


@pytest.mark.parametrize("signum, status", [("SIGINT", 130), ("SIGTERM", 143)])
def test_calibrate_design_and_reproduce_stopped_by_a_signal_say_so_in_one_line(signum, status, folder, monkeypatch):
    # The commands test_atomic_writes does not stop: each is stopped in its long work by the signal.
    import signal

    from qube_koopman.design import controller_design
    from qube_koopman.identify import calibrate
    from qube_koopman.reproduce import duffing_study

    def stop(*args, **kwargs):
        os.kill(os.getpid(), getattr(signal, signum))
        raise AssertionError("the signal should have stopped the command")

    monkeypatch.setattr(calibrate.PlantCalibration, "fit", stop)
    monkeypatch.setattr(controller_design, "design_from_model", stop)
    monkeypatch.setattr(duffing_study, "reproduce_duffing", stop)
    for command, argv in (
        ("qube-calibrate", ["logs/a.mcap", "--out", "p.toml"]),
        ("qube-design", ["junk.bin", "--out", "c.toml"]),
        ("qube-reproduce", ["duffing", "--out", "new/results"]),
    ):
        got, err = run_in_process(command, argv, folder)
        assert got == status and err.strip().splitlines() == [f"{command}: error: interrupted"], (command, err)
    assert not (folder / "p.toml").exists() and not (folder / "c.toml").exists() and not (folder / "new").exists()
