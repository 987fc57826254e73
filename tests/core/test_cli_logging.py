"""-v/-q on every command through the standard logging module; qube-reproduce --strict."""

from __future__ import annotations

import argparse
import importlib
import sys

import pytest
from _episodes import make_episode

from qube_koopman.daq.log import write_episode

COMMANDS = [
    ("qube_koopman.daq.cli.run", "qube-run"),
    ("qube_koopman.daq.cli.import_csv", "qube-import"),
    ("qube_koopman.daq.cli.export", "qube-export"),
    ("qube_koopman.sim.cli.emulate", "qube-emulate"),
    ("qube_koopman.identify.cli.calibrate", "qube-calibrate"),
    ("qube_koopman.identify.cli.identify", "qube-identify"),
    ("qube_koopman.reproduce.cli.reproduce", "qube-reproduce"),
]

# A quick invocation of each command that gets past its argument parsing (and fails on a file).
QUICK = {
    "qube-run": ["--controller", "{missing}", "--episodes", "1", "--duration", "1", "--out", "{tmp}"],
    "qube-import": ["{missing}", "--out", "{tmp}/o"],
    "qube-export": ["{missing}", "--format", "csv", "--out", "{tmp}/o"],
    "qube-emulate": ["--record", "{missing}/x.csv"],
    "qube-calibrate": ["{missing}", "--out", "{tmp}/plant.toml"],
    "qube-identify": ["--train", "{missing}", "--test", "{missing}", "--out", "{tmp}/o"],
    "qube-reproduce": ["qube", "--data", "{missing}", "--out", "{tmp}/o"],
}


def call(module: str, argv: list[str]) -> int:
    try:
        return importlib.import_module(module).main(argv)
    except SystemExit as exc:  # --version, from the commands that leave it to argparse
        return int(exc.code or 0)


@pytest.mark.parametrize("module, prog", COMMANDS, ids=[c[1] for c in COMMANDS])
def test_every_command_accepts_v_and_q(module, prog, capsys):
    for flags in (["-v"], ["-vv"], ["-q"], ["--verbose", "--quiet"]):
        assert call(module, [*flags, "--version"]) == 0, flags
        assert capsys.readouterr().out.startswith(f"{prog} "), flags


@pytest.mark.parametrize("module, prog", COMMANDS, ids=[c[1] for c in COMMANDS])
def test_v_logs_what_runs_and_q_only_errors(module, prog, tmp_path, capsys):
    argv = [a.format(missing=tmp_path / "missing", tmp=tmp_path) for a in QUICK[prog]]
    call(module, argv)
    quiet_default = capsys.readouterr().err
    assert f"{prog}: info:" not in quiet_default, "no info lines by default"
    call(module, [*argv, "-v"])
    err = capsys.readouterr().err
    assert f"{prog}: info: {prog} " in err, err  # the version line, in the commands' line style
    assert f"{prog}: error: " in err, "the error still reads as before"
    call(module, [*argv, "-q"])
    err = capsys.readouterr().err
    assert ": info:" not in err and ": debug:" not in err and f"{prog}: error: " in err


def test_v_and_vv_show_the_work_of_a_real_run(tmp_path, capsys):
    from qube_koopman.daq.cli.run import main

    assert main(["--episodes", "1", "--duration", "0.2", "--out", str(tmp_path), "-v"]) == 0
    err = capsys.readouterr().err
    assert "qube-run: info: episode 0: complete after 100 of 100 ticks" in err
    assert "debug" not in err
    assert main(["--episodes", "1", "--duration", "0.2", "--out", str(tmp_path), "--append", "-vv"]) == 0
    assert "qube-run: debug: writing " in capsys.readouterr().err


@pytest.mark.parametrize("quiet", [False, True])
def test_q_silences_the_progress_bar_on_a_terminal(quiet, legacy_folder, tmp_path, capsys, monkeypatch):
    from qube_koopman.daq.cli.import_csv import main

    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert main([str(legacy_folder), "--out", str(tmp_path / "o"), *(["-q"] if quiet else [])]) == 0
    err = capsys.readouterr().err
    assert ("1/1" in err) != quiet, err


@pytest.mark.parametrize("quiet", [False, True])
def test_q_silences_the_identification_progress_bars(quiet, capsys, monkeypatch):
    from qube_koopman.core.command import progress, run_command

    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)

    def command(args):
        for done in range(3):
            progress("alpha sweep", done, 2)
        return 0

    try:
        assert run_command("qube-identify", command, argparse.Namespace(quiet=quiet, verbose=0)) == 0
    finally:
        progress.enabled = True
    assert ("alpha sweep" in capsys.readouterr().err) != quiet


# --- qube-reproduce --strict --------------------------------------------------------------------------


@pytest.fixture
def logs_with_an_empty_one(tmp_path):
    """29 readable logs (the paper's split needs more than 28) and an empty one among the training logs."""
    data = tmp_path / "data"
    data.mkdir()
    good = write_episode(data / "g_00.mcap", make_episode(700, seed=1)).read_bytes()
    for i in range(1, 29):
        (data / f"g_{i:02d}.mcap").write_bytes(good)
    (data / "b_empty.mcap").write_bytes(b"")
    return data


def _without_split_warning(err: str) -> str:
    """stderr without the warning that these 30 logs are not the paper's 48 (the fixture's size, not under test)."""
    return "".join(line for line in err.splitlines(keepends=True) if "the paper's split is for its 48 logs" not in line)


def test_qube_reproduce_strict_refuses_an_unreadable_log(logs_with_an_empty_one, tmp_path, capsys):
    from qube_koopman.reproduce.cli.reproduce import main

    status = main(["qube", "--data", str(logs_with_an_empty_one), "--out", str(tmp_path / "o"), "--strict", "-q"])
    assert status == 2
    err = _without_split_warning(capsys.readouterr().err)
    assert err == (
        f"qube-reproduce: error: {logs_with_an_empty_one / 'b_empty.mcap'}: "
        "empty file, not an MCAP episode log; refused because of --strict\n"
    )
    assert not (tmp_path / "o" / "qube.json").exists()


def test_qube_reproduce_without_strict_skips_it_with_a_warning(logs_with_an_empty_one, tmp_path, capsys):
    from qube_koopman.reproduce.cli.reproduce import main

    status = main(
        ["qube", "--data", str(logs_with_an_empty_one), "--out", str(tmp_path / "o"), "--n-alphas", "2", "-q"]
    )
    err = _without_split_warning(capsys.readouterr().err)
    assert err.splitlines()[0] == (
        f"qube-reproduce: warning: {logs_with_an_empty_one / 'b_empty.mcap'}: empty file, "
        "not an MCAP episode log; skipped"
    ), err
    assert status == 0 and (tmp_path / "o" / "qube.json").exists(), err  # the study ran on the other 29


@pytest.mark.parametrize("flag", ["-q", None, "-v"])
def test_qube_identify_counts_the_episodes_as_an_info_line(flag, tmp_path, capsys):
    from qube_koopman.identify.cli.identify import main

    for name in ("train_a", "train_b", "test_a"):
        write_episode(tmp_path / f"{name}.mcap", make_episode(300, seed=len(name)))
    train, test = [str(tmp_path / "train_a.mcap"), str(tmp_path / "train_b.mcap")], [str(tmp_path / "test_a.mcap")]
    # --estimate-window longer than the episodes: refused right after the count, before any fit
    argv = [
        "--train",
        *train,
        "--test",
        *test,
        "--skip",
        "0",
        "--offsets",
        "alpha",
        "--estimate-window",
        "5",
        "--out",
        str(tmp_path / "o"),
        *([flag] if flag else []),
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    counted = "qube-identify: info: 2 training and 1 test episodes, 0 samples dropped from each\n"
    assert (counted in err) == (flag == "-v"), err
    assert "training and" not in err.replace(counted, ""), "never a bare line"
    assert err.endswith("leaves nothing to score in the shortest test episode\n"), err
