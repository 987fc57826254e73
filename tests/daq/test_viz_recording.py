"""The acquisition recording (qube-run --rerun-save) stays batched: chunk count and size of a 20 s episode."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from qube_koopman.daq.cli.run import main


@pytest.mark.slow
def test_a_20_s_episode_records_in_few_chunks_and_little_space(tmp_path):
    chunk_module = pytest.importorskip("rerun.chunk")
    rrd = tmp_path / "run.rrd"
    assert (
        main(
            [
                "--episodes",
                "1",
                "--duration",
                "20",
                "--seed",
                "3",
                "--out",
                str(tmp_path / "ep"),
                "--rerun-save",
                str(rrd),
                "-q",
            ]
        )
        == 0
    )
    chunks: dict[str, int] = {}
    rows: dict[str, int] = {}
    for chunk in chunk_module.RrdReader(str(rrd)).stream():
        if not chunk.is_static:
            chunks[chunk.entity_path] = chunks.get(chunk.entity_path, 0) + 1
            rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    for path in ("/theta", "/alpha", "/voltage", "/timing"):
        assert rows[path] == 10_000, path  # every tick is there...
        assert chunks[path] <= 81, (path, chunks[path])  # ...in 0.25 s batches (80 of them), not per tick
    # The issue measured about 30 MB for this episode before batching; 0.1 s batches gave 2.0 MB.
    assert rrd.stat().st_size < 1_800_000, rrd.stat().st_size


def test_qube_run_without_rerun_says_how_to_get_it(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "rerun", None)  # as if rerun-sdk (the [viz] extra) were not installed
    status = main(
        [
            "--episodes",
            "1",
            "--duration",
            "0.5",
            "--out",
            str(tmp_path / "ep"),
            "--rerun-save",
            str(tmp_path / "run.rrd"),
            "-q",
        ]
    )
    err = capsys.readouterr().err
    assert status == 1
    assert 'rerun-sdk is not installed (the viewer is optional): pip install "qube-koopman[viz]"' in err
    assert "Traceback" not in err and not (tmp_path / "run.rrd").exists()


def test_qube_identify_without_rerun_says_how_to_get_it_before_any_work(tmp_path, monkeypatch, capsys):
    from qube_koopman.identify.cli.identify import main as identify_main

    monkeypatch.setitem(sys.modules, "rerun", None)
    status = identify_main(
        [
            "--train",
            str(tmp_path / "nothing"),
            "--test",
            str(tmp_path / "nothing"),
            "--out",
            str(tmp_path / "out"),
            "--rerun-save",
            str(tmp_path / "id.rrd"),
        ]
    )
    assert status == 1  # an optional package missing: as qube-run --rerun and qube-export --format parquet
    assert '--rerun-save needs rerun-sdk, which is optional: pip install "qube-koopman[viz]"' in capsys.readouterr().err


def test_the_packages_import_and_run_without_rerun(tmp_path):
    code = (
        "import sys; sys.modules['rerun'] = None\n"
        "from daq.cli.run import main\n"
        f"assert main(['--episodes', '1', '--duration', '0.5', '--out', {str(tmp_path)!r}, '-q']) == 0\n"
        "import identify, daq.export"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert len(list(tmp_path.glob("*.mcap"))) == 1


def test_a_run_killed_mid_episode_leaves_no_recording_under_its_name(tmp_path):
    # SIGKILL runs no cleanup: whatever is under the final name then is what a viewer would open.
    pytest.importorskip("rerun", reason="the viewer is the optional viz extra")
    rrd, out = tmp_path / "run.rrd", tmp_path / "ep"
    code = "import sys; from qube_koopman.daq.cli.run import main; sys.exit(main(sys.argv[1:]))"
    run = subprocess.Popen(
        [
            sys.executable,
            "-c",
            code,
            "--episodes",
            "1",
            "--duration",
            "60",
            "--realtime",
            "--out",
            str(out),
            "--rerun-save",
            str(rrd),
            "-q",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 60
        while not (out.is_dir() and any(out.iterdir())):  # the episode is being logged: the recording is open
            assert run.poll() is None and time.monotonic() < deadline, "the run did not start its episode"
            time.sleep(0.05)
    finally:
        run.kill()
        run.wait(timeout=30)
    assert run.returncode == -9
    assert not rrd.exists(), "a recording under its final name would be one without its end"
