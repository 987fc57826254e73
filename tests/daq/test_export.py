"""qube-export and daq.export: legacy CSV round trip, Parquet and MATLAB contents, refused input."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from _episodes import make_episode
from qube_koopman.daq.cli.export import main
from qube_koopman.daq.cli.import_csv import main as import_main
from qube_koopman.daq.export import episode_columns, export_episode, write_mat
from qube_koopman.daq.log import read_episode, write_episode
from qube_koopman.daq.log.metadata import metadata_from_records
from qube_koopman.daq.log.names import log_path


@pytest.fixture
def log(tmp_path):
    path = tmp_path / "qube_20260101T000000_1_2_3.mcap"
    episode = make_episode(n=700, seed=3, status="aborted", status_reason="|alpha| > 45 deg")
    write_episode(path, episode)
    return path, episode


@pytest.mark.dataset
def test_csv_round_trips_the_48_dataset_files_bit_for_bit(qube_csv_files, qube_logs, tmp_path):
    assert len(qube_csv_files) == 48
    assert main([str(qube_logs), "--format", "csv", "--out", str(tmp_path / "csv"), "-q"]) == 0
    for original in qube_csv_files:
        assert (tmp_path / "csv" / original.name).read_bytes() == original.read_bytes(), original.name
    # ...and qube-import reads the exported files back into the same episodes.
    (tmp_path / "csv" / "controller.toml").write_bytes((qube_csv_files[0].parent / "controller.toml").read_bytes())
    assert import_main([str(tmp_path / "csv"), "--out", str(tmp_path / "again"), "-q"]) == 0
    for original in qube_csv_files[:5]:
        first, again = (
            read_episode(log_path(qube_logs, original.stem)),
            read_episode(log_path(tmp_path / "again", original.stem)),
        )
        for name, value in first.arrays().items():
            np.testing.assert_array_equal(getattr(again, name), value, err_msg=f"{original.name}: {name}")


def test_csv_of_a_simulated_episode_has_the_legacy_header_and_exact_values(log, tmp_path):
    path, episode = log
    out = export_episode(path, "csv", tmp_path / "out")
    lines = out.read_text().splitlines()
    assert out.name == "qube_20260101T000000_1_2_3.csv"
    assert (
        lines[0] == "t, target_theta, target_alpha, theta, alpha, control_output, feedforward, plant_input, saturation"
    )
    assert len(lines) == 1 + len(episode)
    values = np.array([[float(v) for v in line.split(", ")] for line in lines[1:]])
    np.testing.assert_array_equal(values[:, 3], episode.theta)
    np.testing.assert_array_equal(values[:, 8], episode.saturation)


def test_parquet_holds_every_signal_and_the_metadata(log, tmp_path):
    pq = pytest.importorskip("pyarrow.parquet")
    path, episode = log
    table = pq.read_table(export_episode(path, "parquet", tmp_path))
    for name, value in episode_columns(episode).items():
        np.testing.assert_array_equal(table.column(name).to_numpy(), value, err_msg=name)
    assert table.schema.field("theta").metadata[b"unit"] == b"rad"
    records = {k.decode(): json.loads(v) for k, v in table.schema.metadata.items() if k.startswith(b"qube.")}
    meta = metadata_from_records(records, "parquet")
    assert meta.status == "aborted" and meta.status_reason == "|alpha| > 45 deg"
    np.testing.assert_array_equal(meta.controller.system.C, episode.controller.C)
    assert meta.excitation == episode.metadata.excitation


def test_mat_holds_column_vectors_and_a_metadata_struct(log, tmp_path):
    from scipy.io import loadmat

    path, episode = log
    data = loadmat(export_episode(path, "mat", tmp_path), simplify_cells=True)
    np.testing.assert_array_equal(data["alpha"], episode.alpha)
    np.testing.assert_array_equal(data["controller_state"], episode.controller_state)
    assert data["metadata"]["status"]["status"] == "aborted"
    assert json.loads(data["metadata"]["controller"]["D"]) == episode.controller.D.tolist()


def test_refused_logs_are_named_and_the_others_exported(log, tmp_path, capsys):
    path, _ = log
    bad = tmp_path / "not_a_log.mcap"
    bad.write_text("hello")
    status = main(
        [str(path), str(bad), str(tmp_path / "missing.mcap"), "--format", "mat", "--out", str(tmp_path / "o")]
    )
    err = capsys.readouterr().err
    assert status == 2  # a LOG that does not exist is a usage error, as in every command (issue 30)
    assert f"qube-export: error: {bad}: not an MCAP file" in err
    assert "missing.mcap: no such file or folder" in err
    assert (tmp_path / "o" / f"{path.stem}.mat").is_file()
    # An existing output is left alone unless --force.
    assert main([str(path), "--format", "mat", "--out", str(tmp_path / "o"), "-q"]) == 1
    assert "exists (use --force" in capsys.readouterr().err
    assert main([str(path), "--format", "mat", "--out", str(tmp_path / "o"), "-q", "--force"]) == 0
    assert main([str(path), "--format", "xlsx", "--out", str(tmp_path / "o")]) == 2
    assert main([str(path), "--format", "csv", "--out", str(path)]) == 2


def test_parquet_without_pyarrow_says_how_to_get_it(log, tmp_path, monkeypatch, capsys):
    path, _ = log
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    assert main([str(path), str(path.with_name("x.mcap")), "--format", "parquet", "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "needs pyarrow (pip install pyarrow" in err and err.count("needs pyarrow") == 1
    assert not (tmp_path / "o").exists()


def test_episode_frame_when_pandas_is_there(log):
    pytest.importorskip("pandas")
    from qube_koopman.daq.export import episode_frame

    _, episode = log
    frame = episode_frame(episode)
    np.testing.assert_array_equal(frame["plant_input"].to_numpy(), episode.plant_input)
    assert frame.attrs["metadata"]["qube.status"]["status"] == "aborted"


def test_episode_frame_without_pandas_says_it_is_optional(log, monkeypatch):
    from qube_koopman.daq.export import episode_frame

    monkeypatch.setitem(sys.modules, "pandas", None)
    with pytest.raises(ImportError, match="pandas, which is optional"):
        episode_frame(log[1])


def test_episode_frame_without_pandas_names_the_extra_that_installs_it(log, monkeypatch):
    import tomllib
    from pathlib import Path

    from qube_koopman.daq.export import episode_frame

    extras = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    assert any(r.startswith("pandas>=") for r in extras["pandas"]) and any(
        r.startswith("pandas") for r in extras["test"]
    )
    monkeypatch.setitem(sys.modules, "pandas", None)
    with pytest.raises(ImportError) as caught:
        episode_frame(log[1])
    assert 'pip install "qube-koopman[pandas]"' in str(caught.value) and "\n" not in str(caught.value)


def test_write_mat_of_an_empty_episode(tmp_path):
    from scipy.io import loadmat

    write_mat(make_episode(n=0), tmp_path / "e.mat")
    assert loadmat(tmp_path / "e.mat")["t"].size == 0


def test_csv_of_an_episode_that_did_not_complete_carries_its_status_beside_it(legacy_folder, tmp_path, capsys):
    import dataclasses

    from _legacy_csv import GOOD

    assert import_main([str(legacy_folder), "--out", str(tmp_path / "logs"), "-q"]) == 0
    complete = read_episode(tmp_path / "logs" / f"{GOOD}.mcap")
    stopped = dataclasses.replace(
        complete,
        metadata=dataclasses.replace(complete.metadata, status="aborted", status_reason="safety: |alpha| > 45 deg"),
    )
    write_episode(tmp_path / "logs" / f"{GOOD}.mcap", stopped, overwrite=True)
    out = tmp_path / "csv"
    assert main([str(tmp_path / "logs"), "--format", "csv", "--out", str(out)]) == 0
    sidecar = out / f"{GOOD}.status.json"
    assert (
        f"qube-export: warning: {tmp_path / 'logs' / f'{GOOD}.mcap'}: not a complete episode; its status is in "
        f"{sidecar}" in capsys.readouterr().err
    )
    assert json.loads(sidecar.read_text()) == {
        "status": "aborted",
        "reason": "safety: |alpha| > 45 deg",
        "salvaged": False,
        "salvage_note": "",
        "samples": len(complete),
    }
    # qube-import gives the status back: the CSV never reads as a complete episode
    (out / "controller.toml").write_bytes((legacy_folder / "controller.toml").read_bytes())
    capsys.readouterr()
    assert import_main([str(out), "--out", str(tmp_path / "again")]) == 0
    assert capsys.readouterr().err == (
        f"qube-import: warning: {out / f'{GOOD}.csv'}: safety: |alpha| > 45 deg; "
        f"imported as an aborted episode of {len(complete)} samples\n"
    )
    again = read_episode(tmp_path / "again" / f"{GOOD}.mcap")
    assert not again.is_complete and again.metadata.status_reason == "safety: |alpha| > 45 deg"
    # exporting the complete episode over it removes the stale status file
    write_episode(tmp_path / "logs" / f"{GOOD}.mcap", complete, overwrite=True)
    assert main([str(tmp_path / "logs"), "--format", "csv", "--out", str(out), "--force", "-q"]) == 0
    assert not sidecar.exists() and (out / f"{GOOD}.csv").read_bytes() == (legacy_folder / f"{GOOD}.csv").read_bytes()


def test_csv_of_a_log_that_lost_samples_says_qube_import_will_refuse_it(tmp_path, capsys):
    # A damaged chunk skipped on reading leaves a jump in t; the CSV layout is evenly spaced in time,
    # so the round trip cannot hold: the export says so (and which formats keep the episode whole).
    from test_log import _chunks

    from qube_koopman.daq.log import EpisodeWriter

    episode = make_episode(500)
    logs = tmp_path / "logs"
    logs.mkdir()
    path = logs / "qube_20260101T000000_1_2_3.mcap"
    with EpisodeWriter(path, episode.metadata, flush_interval_s=0.2) as writer:  # 100 samples a chunk
        writer.write_samples(episode)
    data = bytearray(path.read_bytes())
    data[_chunks(path)[2][1] - 50] ^= 0xFF  # samples 200 to 299 lost
    path.write_bytes(bytes(data))
    assert main([str(logs), "--format", "csv", "--out", str(tmp_path / "csv")]) == 0
    csv = tmp_path / "csv" / f"{path.stem}.csv"
    t_before = float(episode.t[199])
    assert (
        f"qube-export: warning: {csv}: 100 samples missing after t = {t_before:.3f} s (lost when the log was "
        "read); the CSV layout is evenly spaced, so qube-import will refuse this file: --format parquet or mat "
        "keep the episode as it is"
    ) in capsys.readouterr().err
    (tmp_path / "csv" / "controller.toml").write_text(
        "kp_theta = 6\nkd_theta = 1.8\nkp_alpha = 30\nkd_alpha = 2.5\ntau = 50\n"
    )
    assert import_main([str(tmp_path / "csv"), "--out", str(tmp_path / "back")]) == 1
    assert "t is not evenly spaced" in capsys.readouterr().err
    # mat keeps the episode as it is: no warning
    assert main([str(logs), "--format", "mat", "--out", str(tmp_path / "mat")]) == 0
    assert "samples missing" not in capsys.readouterr().err


def test_a_failed_export_leaves_no_folder_it_made(log, tmp_path, monkeypatch, capsys):
    import qube_koopman.daq.export as export_module

    def full_disk(episode, out):
        raise OSError(28, "No space left on device")

    monkeypatch.setitem(export_module._WRITERS, "csv", full_disk)
    path, _ = log
    out = tmp_path / "new" / "out"
    assert main([str(path), "--format", "csv", "--out", str(out)]) == 1
    assert "No space left on device" in capsys.readouterr().err
    assert not (tmp_path / "new").exists(), "the folders it made are gone"
