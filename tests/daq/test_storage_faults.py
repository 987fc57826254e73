"""Storage faults while logging: a file-size limit (RLIMIT_FSIZE) and a full disk at a chosen byte.

A write error stops the episode with 0 V at once, ends the run with a non-zero exit and one
message naming the file and the error; what was flushed before stays readable, marked
incomplete, never complete; no empty or headerless file is left behind.
"""

from __future__ import annotations

import errno
import io
import os
import resource
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import qube_koopman.daq.log.writer as writer_module
from qube_koopman.daq.backends import SimBackend
from qube_koopman.daq.cli.run import main
from qube_koopman.daq.log import IncompleteEpisodeWarning, read_episode
from qube_koopman.daq.sinks import McapSink, MemorySink

REPO = Path(__file__).resolve().parents[2]


def _logs(folder: Path) -> list[Path]:
    return sorted(folder.glob("*.mcap"))


def _assert_salvaged(path: Path) -> None:
    """Readable up to its last flushed chunk, and not complete."""
    assert path.stat().st_size > 0
    with pytest.warns(IncompleteEpisodeWarning, match="status incomplete"):
        ep = read_episode(path)
    assert ep.metadata.status == "incomplete" and len(ep) > 0
    assert np.all(np.diff(ep.t) > 0)


def test_file_size_limit_stops_the_run_with_the_file_named(tmp_path):
    # The kernel refuses writes past 100 kB (EFBIG; Python ignores SIGXFSZ, and so does the child).
    limit = 100_000

    def limited():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    code = "import sys; from daq.cli.run import main; sys.exit(main(sys.argv[1:]))"
    proc = subprocess.run(
        [
            sys.executable,
            "-c",
            code,
            "--episodes",
            "3",
            "--duration",
            "60",
            "--seed",
            "1",
            "--out",
            str(tmp_path),
            "-q",
        ],
        capture_output=True,
        text=True,
        env=env,
        preexec_fn=limited,
        timeout=120,
    )
    logs = _logs(tmp_path)
    assert proc.returncode == 1, proc.stderr
    assert len(logs) == 1, "the run stopped at the first episode"
    err = proc.stderr.strip().splitlines()
    assert err == [
        f"qube-run: error: {logs[0]}: File too large (EFBIG): the episode was stopped with the motor "
        f"at 0 V; the samples flushed before stay readable, marked incomplete"
    ], proc.stderr
    assert "0 complete, 1 aborted" in proc.stdout
    assert logs[0].stat().st_size <= limit
    _assert_salvaged(logs[0])


def _full_disk_at(monkeypatch, limit: int) -> None:
    """Episode log files refuse bytes past ``limit`` with ENOSPC (writing what fits first)."""

    class FullDisk(io.FileIO):
        def write(self, b):
            room = limit - self.tell()
            data = bytes(b)
            if len(data) > room:
                if room > 0:
                    super().write(data[:room])
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return super().write(data)

    monkeypatch.setattr(
        writer_module, "open", lambda path, mode: io.BufferedWriter(FullDisk(path, mode[0])), raising=False
    )


def test_full_disk_mid_episode_stops_the_run_and_is_never_complete(monkeypatch, tmp_path, capsys):
    _full_disk_at(monkeypatch, 50_000)
    status = main(["--episodes", "3", "--duration", "60", "--seed", "2", "--out", str(tmp_path), "-q"])
    out, err = capsys.readouterr()
    logs = _logs(tmp_path)
    assert status == 1 and "0 complete, 1 aborted" in out
    assert len(logs) == 1 and logs[0].stat().st_size == 50_000  # every byte that fitted
    assert err == (
        f"qube-run: error: {logs[0]}: No space left on device (ENOSPC): the episode was stopped "
        f"with the motor at 0 V; the samples flushed before stay readable, marked incomplete\n"
    )
    _assert_salvaged(logs[0])


def test_full_disk_in_the_loop_commands_zero_volts_in_the_detecting_tick(monkeypatch, tmp_path):
    from qube_koopman.daq.loop import run_episode
    from qube_koopman.daq.session import excitation_settings, plan_episodes
    from qube_koopman.core.controller_file import load_controller

    _full_disk_at(monkeypatch, 50_000)
    plan = plan_episodes(load_controller(), [(1, 2, 3)], excitation_settings(60.0))[0]
    memory = MemorySink()
    result = run_episode(SimBackend(seed=1), plan, [McapSink(tmp_path), memory], handle_signals=False)
    assert result.status == "aborted" and result.cause == "log"
    assert "ENOSPC" in result.reason and str(_logs(tmp_path)[0]) in result.reason
    volts = memory.episodes[0].episode().plant_input
    assert len(volts) < plan.n_samples
    # Driven up to the tick that saw the error, 0 V in that very tick.
    assert volts[-1] == 0.0 and np.count_nonzero(volts[-50:-1]) > 40
    _assert_salvaged(_logs(tmp_path)[0])


def test_full_disk_at_the_header_leaves_no_file(monkeypatch, tmp_path, capsys):
    _full_disk_at(monkeypatch, 100)
    assert main(["--episodes", "2", "--duration", "1", "--out", str(tmp_path), "-q"]) == 1
    err = capsys.readouterr().err
    assert _logs(tmp_path) == [] and list(tmp_path.iterdir()) == []
    assert (
        err.startswith("qube-run: error: ")
        and "No space left on device (ENOSPC): the episode was not started" in err
        and err.count("\n") == 1
    ), err


def test_too_little_free_space_refuses_to_start(monkeypatch, tmp_path, capsys):
    import shutil

    import qube_koopman.daq.sinks as sinks_module

    monkeypatch.setattr(
        sinks_module.shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(10**9, 10**9 - 10**6, 10**6)
    )
    assert main(["--episodes", "2", "--duration", "20", "--out", str(tmp_path), "-q"]) == 1
    captured = capsys.readouterr()
    err = captured.err
    assert list(tmp_path.iterdir()) == []
    assert "1.0 MB free, the episode needs about 5.0 MB (ENOSPC): the episode was not started" in err
    assert err.count("\n") == 1 and "Traceback" not in err
    # The summary counts the logs that are there (none), and the episode's reason names no internals.
    assert "0 complete, 1 aborted; 0 episode logs in" in captured.out, captured.out
    assert "McapSink" not in captured.out and "LogWriteError" not in captured.out, captured.out


def test_flipped_bytes_read_as_a_corrupted_chunk_at_its_offset(tmp_path):
    from _episodes import make_episode

    from qube_koopman.daq.log import EpisodeWriter

    episode = make_episode(4000, seed=2)
    path = tmp_path / "flipped.mcap"
    with EpisodeWriter(path, episode.metadata, flush_interval_s=0.5) as writer:
        writer.write_samples(episode)
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle] ^= 0xFF
    data[middle + 1] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.warns(IncompleteEpisodeWarning, match="is unusable"):
        ep = read_episode(path)
    reason = ep.metadata.status_reason
    assert ep.metadata.status == "incomplete" and 0 < len(ep) < 4000
    assert reason.startswith("corrupted: Chunk record at byte ") and "CRC" in reason, reason
    assert "writer stopped" not in reason


def test_qube_import_of_a_binary_file_is_one_short_line(tmp_path, capsys):
    from qube_koopman.daq.cli.import_csv import main as import_main

    src = tmp_path / "qube_20230828T120000_1_2_3.csv"
    src.write_bytes(b"\x7fELF\x02\x01\x01" + bytes(3000))
    controller = Path(__file__).resolve().parents[2] / "core" / "rig_controller.toml"
    assert import_main([str(src), "--controller", str(controller), "--out", str(tmp_path / "o"), "-q"]) == 1
    err = capsys.readouterr().err
    assert err == f"qube-import: error: {src}: not a CSV file (binary content: NUL bytes near its start)\n"


def test_a_log_failing_on_its_last_sample_is_never_recorded_complete(tmp_path):
    # Free-running, the loop is done long before the writer thread reaches the last sample:
    # the failure then shows only while the queue drains, and must still abort the episode.
    from qube_koopman.daq.loop import run_episode
    from qube_koopman.daq.session import excitation_settings, plan_episodes
    from qube_koopman.core.controller_file import load_controller

    plan = plan_episodes(load_controller(), [(1, 2, 3)], excitation_settings(1.0))[0]

    class FailsAtTheEnd(MemorySink):
        def write(self, sample):
            if sample.k == plan.n_samples - 1:
                raise OSError(errno.EIO, os.strerror(errno.EIO))
            super().write(sample)

        def close(self, outcome):
            self.outcome = outcome
            super().close(outcome)

    failing, mcap = FailsAtTheEnd(), McapSink(tmp_path)
    result = run_episode(SimBackend(seed=1), plan, [failing, mcap], handle_signals=False)
    assert result.status == "aborted" and result.cause == "log" and "Input/output error" in result.reason
    assert failing.outcome.status == "aborted" and result.metadata.status == "aborted"
    assert read_episode(_logs(tmp_path)[0]).metadata.status == "aborted"  # the log says so too


def test_the_summary_counts_the_samples_the_failed_log_still_holds(monkeypatch, tmp_path, capsys):
    _full_disk_at(monkeypatch, 50_000)
    assert main(["--episodes", "1", "--duration", "60", "--seed", "2", "--out", str(tmp_path), "-q"]) == 1
    out = capsys.readouterr().out
    log = _logs(tmp_path)[0]
    readable = len(read_episode(log, warn=False))
    row = next(line.split() for line in out.splitlines() if log.name in line)
    assert row[2] == "aborted" and int(row[3]) == readable, out  # not the ticks the loop ran
    ran = int(next(line for line in out.splitlines() if line.startswith("episode 0: ")).split(" of the ")[1].split()[0])
    assert readable < ran
    assert f"the log holds the first {readable} of the {ran} samples run, marked incomplete" in out
