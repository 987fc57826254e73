"""Files the commands write: modes from the umask like open()'s; no temporary file left for good."""

from __future__ import annotations

import os
import stat
import time

import pytest
from _episodes import make_episode
from _legacy_csv import GOOD

from qube_koopman.daq.log import write_episode


@pytest.fixture
def umask():
    """Set the process umask for a test; the old one back after."""
    old = os.umask(0o022)
    os.umask(old)
    yield os.umask
    os.umask(old)


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.parametrize("mask", [0o022, 0o027, 0o002], ids=["022", "027", "002"])
def test_every_command_writes_files_as_open_would_under_the_umask(mask, umask, legacy_folder, tmp_path):
    from qube_koopman.daq.cli.export import main as export
    from qube_koopman.daq.cli.import_csv import main as import_csv
    from qube_koopman.daq.cli.run import main as run

    umask(mask)
    assert import_csv([str(legacy_folder), "--out", str(tmp_path / "imported"), "-q"]) == 0
    assert run(["--episodes", "1", "--duration", "0.2", "--out", str(tmp_path / "ran"), "-q"]) == 0
    assert export([str(tmp_path / "ran"), "--format", "csv", "--out", str(tmp_path / "exported"), "-q"]) == 0
    written = [*tmp_path.glob("imported/*"), *tmp_path.glob("ran/*"), *tmp_path.glob("exported/*")]
    assert len(written) == 3
    assert {p.name: oct(mode(p)) for p in written} == {p.name: oct(0o666 & ~mask) for p in written}


def test_write_episode_honours_a_strict_umask(umask, tmp_path):
    umask(0o077)
    assert mode(write_episode(tmp_path / "a.mcap", make_episode(50))) == 0o600


def _stale(folder, name: str, age_s: float):
    path = folder / name
    path.write_bytes(b"\x89MCAP0\r\n partial")
    then = time.time() - age_s
    os.utime(path, (then, then))
    return path


def test_the_next_import_removes_the_temporary_files_an_interrupted_one_left(legacy_folder, tmp_path, capsys):
    from qube_koopman.daq.cli.import_csv import main

    out = tmp_path / "o"
    out.mkdir()
    left = _stale(out, f".{GOOD}.mcap.1a2b3c4d.tmp", 3600)  # an import killed an hour ago
    just = _stale(out, f".{GOOD}.mcap.99999999.tmp", 0)  # ... or killed a moment ago: no writer holds it
    other = _stale(out, ".notes.txt.1a2b3c4d.tmp", 3600)  # not a log's temporary file
    assert main([str(legacy_folder), "--out", str(out), "-v"]) == 0
    assert not left.exists() and not just.exists() and other.exists()
    err = capsys.readouterr().err
    for path in (left, just):
        assert f"qube-import: info: {path}: removed, a temporary file an interrupted import left" in err
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [f"{GOOD}.mcap"]


def test_a_temporary_file_being_written_is_never_removed(tmp_path):
    from qube_koopman.daq.log.writer import _temp_file, remove_stale_temp_files

    fd, name = _temp_file(tmp_path / "a.mcap")  # what write_episode holds while it writes
    try:
        assert remove_stale_temp_files(tmp_path) == [] and os.path.exists(name)
    finally:
        os.close(fd)
    assert remove_stale_temp_files(tmp_path) == [tmp_path / os.path.basename(name)]  # its writer gone
    assert list(tmp_path.iterdir()) == []


def test_a_temporary_file_taken_before_its_lock_is_given_up_for_another(tmp_path, monkeypatch):
    # A cleaner that removed the new file between its creation and its lock: the writer sees the
    # name no longer leads to its file, and takes another name.
    import qube_koopman.daq.log.writer as writer
    from qube_koopman.daq.log.writer import _temp_file

    real_open, calls = os.open, []

    def open_then_lose_it(path, flags, *mode):
        fd = real_open(path, flags, *mode)
        calls.append(path)
        if len(calls) == 1:
            os.unlink(path)  # the cleaner's doing
        return fd

    monkeypatch.setattr(writer.os, "open", open_then_lose_it)
    fd, name = _temp_file(tmp_path / "a.mcap")
    os.close(fd)
    assert len(calls) == 2 and name == str(calls[1]) and os.path.exists(name)
