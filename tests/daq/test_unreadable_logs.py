"""Unreadable files among episode logs: skipped with one warning each naming them, or refused (strict)."""

from __future__ import annotations

import shutil
import warnings

import pytest
from _episodes import make_episode

from qube_koopman.daq.log import write_episode
from qube_koopman.identify.data.logs import IncompleteLogSkipped, UnreadableLogSkipped, load_logs


@pytest.fixture
def folder(tmp_path):
    write_episode(tmp_path / "a_good.mcap", make_episode(400, seed=1))
    (tmp_path / "b_empty.mcap").write_bytes(b"")
    (tmp_path / "c_text.mcap").write_text("not a log\n")
    good = (tmp_path / "a_good.mcap").read_bytes()
    (tmp_path / "d_header_only.mcap").write_bytes(good[:20])
    return tmp_path


def test_unreadable_logs_are_skipped_with_one_warning_each(folder):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        logs = load_logs(sorted(folder.glob("*.mcap")))
    assert [log.path.name for log in logs] == ["a_good.mcap"]
    messages = [str(w.message) for w in caught]
    assert all(issubclass(w.category, UnreadableLogSkipped) for w in caught) and len(messages) == 3
    assert messages[0] == f"{folder / 'b_empty.mcap'}: empty file, not an MCAP episode log; skipped"
    assert messages[1] == f"{folder / 'c_text.mcap'}: not an MCAP file (bad magic bytes); skipped"
    assert messages[2].startswith(f"{folder / 'd_header_only.mcap'}: unreadable episode log")
    assert issubclass(UnreadableLogSkipped, IncompleteLogSkipped)  # one filter for both


def test_strict_refuses_the_first_unreadable_log(folder):
    with pytest.raises(
        ValueError, match="b_empty.mcap: empty file, not an MCAP episode log; refused because of --strict"
    ):
        load_logs(sorted(folder.glob("*.mcap")), strict=True)


@pytest.mark.dataset
def test_qube_identify_skips_unreadable_logs_in_a_folder(qube_logs, tmp_path, capsys):
    from qube_koopman.identify.cli.identify import main

    logs = sorted(qube_logs.glob("*.mcap"))
    train = tmp_path / "train"
    train.mkdir()
    for path in logs[:6]:
        shutil.copy(path, train / path.name)
    (train / "zz_empty.mcap").write_bytes(b"")
    (train / "zz_cut_header.mcap").write_bytes(logs[0].read_bytes()[:30])
    test = tmp_path / "test"
    test.mkdir()
    for path in logs[28:30]:
        shutil.copy(path, test / path.name)
    code = main(["--train", str(train), "--test", str(test), "--out", str(tmp_path / "o"), "-v"])
    err = capsys.readouterr().err
    assert code == 0, err
    warned = [line for line in err.splitlines() if "warning:" in line]
    assert (
        len(warned) == 2 and "zz_cut_header.mcap: unreadable" in warned[0] and "zz_empty.mcap: empty file" in warned[1]
    )
    assert "qube-identify: info: 6 training and 2 test episodes" in err
    code = main(["--train", str(train), "--test", str(test), "--out", str(tmp_path / "o"), "--strict", "--force"])
    assert code == 2 and "zz_cut_header.mcap" in capsys.readouterr().err


def test_commands_print_one_warning_line_per_skipped_log(folder, capsys):
    # qube-reproduce and qube-identify run through run_command: one line per skipped file.
    from qube_koopman.core.command import run_command
    from qube_koopman.identify.command_warnings import ONE_LINE_WARNINGS

    assert (
        run_command(
            "qube-reproduce",
            lambda a: len(load_logs(sorted(folder.glob("*.mcap")))),
            None,
            one_line_warnings=ONE_LINE_WARNINGS,
        )
        == 1
    )
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 3 and all(
        line.startswith("qube-reproduce: warning: ") and line.endswith("; skipped") for line in err
    )
    assert "b_empty.mcap" in err[0] and "c_text.mcap" in err[1] and "d_header_only.mcap" in err[2]


def test_qube_calibrate_refuses_an_unreadable_log_without_naming_an_option_it_lacks(folder, tmp_path, capsys):
    # qube-calibrate always refuses such a log; it has no --strict to blame.
    from qube_koopman.identify.cli.calibrate import main

    assert main([str(folder / "b_empty.mcap"), "--out", str(tmp_path / "p.toml"), "-q"]) == 2
    assert capsys.readouterr().err == (
        f"qube-calibrate: error: {folder / 'b_empty.mcap'}: empty file, not an MCAP "
        "episode log; refused: qube-calibrate fits complete, readable logs only\n"
    )
    assert not (tmp_path / "p.toml").exists()


def _deeply_nested_log(path, depth: int = 100_000) -> None:
    """A log whose metadata value ``extra`` nests ``depth`` lists deep (written as a string of the same length)."""
    placeholder = "A" * (2 * depth - 2)
    write_episode(path, make_episode(400, seed=2, extra={"x": placeholder}))
    raw = path.read_bytes()
    assert raw.count(f'"{placeholder}"'.encode()) == 1
    path.write_bytes(raw.replace(f'"{placeholder}"'.encode(), b"[" * depth + b"]" * depth))


def test_a_log_with_crafted_metadata_is_skipped_with_a_warning(folder):
    # Deeply nested metadata, or a controller of a kind the loop never runs: unreadable, not a traceback.
    import numpy as np

    from qube_koopman.core.controller_file import ControllerInfo
    from qube_koopman.core.lti import DiscreteStateSpace

    _deeply_nested_log(folder / "e_deep.mcap")
    neural = ControllerInfo(
        DiscreteStateSpace(np.eye(2), np.ones((2, 2)), np.ones((1, 2)), np.zeros((1, 2)), 0.002), "given", kind="neural"
    )
    write_episode(folder / "f_neural.mcap", make_episode(400, seed=3, controller=neural))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        logs = load_logs([folder / "a_good.mcap", folder / "e_deep.mcap", folder / "f_neural.mcap"])
    assert [log.path.name for log in logs] == ["a_good.mcap"]
    messages = [str(w.message) for w in caught]
    assert len(messages) == 2, messages
    assert messages[0] == (
        f"{folder / 'e_deep.mcap'}: malformed episode metadata: a metadata value: lists and "
        "tables nested more than 64 levels deep; skipped"
    )
    assert messages[1] == (
        f"{folder / 'f_neural.mcap'}: malformed episode metadata: unknown controller kind "
        "'neural' (a log records one of 'pd', 'state-space', 'mpc'); skipped"
    )
