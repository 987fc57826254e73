"""Legacy CSV import (daq.legacy_csv, qube-import): round trip, controller check, refused files."""

from __future__ import annotations

import csv
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from _legacy_csv import GAINS_TOML, GOOD, write_synthetic_csv
from qube_koopman.daq.cli.import_csv import main
from qube_koopman.daq.legacy_csv import (
    LEGACY_COLUMNS,
    LegacyCsvError,
    legacy_episode,
    load_legacy_controller,
    parse_legacy_name,
)
from qube_koopman.daq.log import read_episode
from qube_koopman.daq.log.names import log_path


def parse_csv_independently(path: Path) -> dict[str, np.ndarray]:
    """The CSV through the standard library's csv module and float(), not numpy's parser."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f, skipinitialspace=True))
    names = [n.strip() for n in rows[0]]
    values = np.array([[float(v) for v in row] for row in rows[1:]])
    return {name: values[:, i] for i, name in enumerate(names)}


def assert_matches_csv(episode, csv_path: Path) -> None:
    columns = parse_csv_independently(csv_path)
    for name in LEGACY_COLUMNS:
        np.testing.assert_array_equal(getattr(episode, name), columns[name], err_msg=f"{csv_path.name}: {name}")


def assert_controller_state_consistent(episode) -> None:
    """The stored state obeys the logged controller and reproduces control_output."""
    c = episode.controller
    e = episode.tracking_error
    x = episode.controller_state
    np.testing.assert_array_equal(x[0], 0.0)
    np.testing.assert_allclose(x[1:], x[:-1] @ c.A.T + e[:-1] @ c.B.T, rtol=0, atol=1e-12)
    after = episode.t >= 1.0
    output = (x @ c.C.T + e @ c.D.T)[:, 0]
    assert np.abs(output - episode.control_output)[after].max() <= 1e-9


@pytest.fixture
def synthetic_dir(tmp_path) -> Path:
    src = tmp_path / "src"
    src.mkdir()
    (src / "controller.toml").write_text(GAINS_TOML)
    write_synthetic_csv(src / f"{GOOD}.csv")
    return src


def _stderr_lines(captured) -> list[str]:
    return [line for line in captured.err.splitlines() if "refused" in line or "error" in line]


# --- the file name ---------------------------------------------------------------


def test_start_time_and_seeds_come_from_the_file_name():
    start, seeds = parse_legacy_name(Path("/x") / f"{GOOD}.csv")
    assert start == "2023-08-28T15:06:15"
    assert seeds == {"target_theta": 434, "target_alpha": 696, "feedforward": 394}
    with pytest.raises(LegacyCsvError, match=r"run1\.csv: file name does not follow"):
        parse_legacy_name("run1.csv")


# --- synthetic files: no dataset needed -----------------------------------------


def test_synthetic_import_round_trip(synthetic_dir, tmp_path, capsys):
    out = tmp_path / "out"
    assert main([str(synthetic_dir), "--out", str(out)]) == 0
    assert "imported 1 of 1 file into" in capsys.readouterr().out
    episode = read_episode(log_path(out, GOOD))
    assert_matches_csv(episode, synthetic_dir / f"{GOOD}.csv")
    assert_controller_state_consistent(episode)
    meta = episode.metadata
    assert meta.backend == "legacy-rig" and meta.status == "complete" and meta.sample_rate_hz == 500.0
    assert meta.controller.method == "backward-euler" and meta.controller.gains["kd_alpha"] == 2.5
    assert meta.excitation["seeds"] == {"target_theta": 434, "target_alpha": 696, "feedforward": 394}
    assert np.isnan(episode.lateness).all() and np.isnan(episode.compute_time).all()


def test_an_imported_log_is_chunked_at_most_one_second_of_samples_a_chunk(tmp_path, capsys):
    # One bad byte costs its chunk: imported logs hold the live writer's 0.5 s chunks (they held the
    # whole episode in one or two 1 MiB chunks, 15 s of samples, before).
    from mcap.reader import make_reader

    src = tmp_path / "src"
    src.mkdir()
    (src / "controller.toml").write_text(GAINS_TOML)
    write_synthetic_csv(src / f"{GOOD}.csv", n=3000)  # 6 s
    out = tmp_path / "out"
    assert main([str(src), "--out", str(out), "-q"]) == 0
    with open(log_path(out, GOOD), "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    # consecutive samples 2 ms apart: a chunk's time span gives its count
    per_chunk = [round((c.message_end_time - c.message_start_time) / 2_000_000) + 1 for c in chunks]
    assert max(per_chunk) <= 500 and sum(per_chunk) == 3000, per_chunk
    assert per_chunk == [250] * 12


def _edit_lines(path: Path, edit) -> None:
    lines = path.read_text().splitlines()
    path.write_text("\n".join(edit(lines)) + "\n")


def _drop_column(lines, name="feedforward"):
    index = [c.strip() for c in lines[0].split(",")].index(name)
    return [", ".join(f for i, f in enumerate(line.split(",")) if i != index) for line in lines]


def _short_row(lines):
    lines[100] = ",".join(lines[100].split(",")[:7])  # line 101 of the file
    return lines


def _non_finite(lines):
    fields = lines[50].split(",")
    fields[4] = " nan"  # alpha, line 51 of the file
    lines[50] = ",".join(fields)
    return lines


BAD_FILES = {
    "qube_20230828T150700_1_2_3": (_drop_column, "missing column feedforward"),
    "qube_20230828T150800_1_2_3": (_short_row, "line 101: short row: 7 fields, the header has 9"),
    "qube_20230828T150900_1_2_3": (_non_finite, "line 51: column alpha: non-finite value nan"),
}


def test_bad_files_are_refused_by_name_and_the_good_one_still_imports(synthetic_dir, tmp_path, capsys):
    for stem, (edit, _) in BAD_FILES.items():
        shutil.copy(synthetic_dir / f"{GOOD}.csv", synthetic_dir / f"{stem}.csv")
        _edit_lines(synthetic_dir / f"{stem}.csv", edit)
    # A file run by another controller: same data, a controller.toml with another gain.
    other = tmp_path / "other"
    other.mkdir()
    (other / "controller.toml").write_text(GAINS_TOML.replace("kd_alpha = 2.5", "kd_alpha = 2.6"))
    mismatched = other / "qube_20230828T151000_1_2_3.csv"
    shutil.copy(synthetic_dir / f"{GOOD}.csv", mismatched)

    out = tmp_path / "out"
    status = main([str(synthetic_dir), str(mismatched), "--out", str(out), "--quiet"])
    captured = capsys.readouterr()
    assert status == 1
    errors = _stderr_lines(captured)
    assert len(errors) == 4, captured.err
    for stem, (_, problem) in BAD_FILES.items():
        [line] = [e for e in errors if f"{stem}.csv" in e]
        assert problem in line
    [line] = [e for e in errors if mismatched.name in e]
    assert str(mismatched) in line and "does not reproduce control_output" in line
    assert sorted(p.name for p in out.iterdir()) == [f"{GOOD}.mcap"]
    assert "imported 1 of 5 files" in captured.out and "4 refused" in captured.out
    assert "Traceback" not in captured.err


def test_controller_check_refuses_the_papers_zoh_discretization(synthetic_dir):
    # The paper's text says ZOH; the rig ran backward Euler (it reproduces the logged output to 1e-14 V).
    zoh = load_legacy_controller(synthetic_dir / "controller.toml", method="zoh")
    with pytest.raises(LegacyCsvError, match=rf"{GOOD}\.csv: the zoh pd controller .* off by"):
        legacy_episode(synthetic_dir / f"{GOOD}.csv", zoh)


def test_controller_check_ignores_the_first_second_only(synthetic_dir):
    controller = load_legacy_controller(synthetic_dir / "controller.toml")
    path = synthetic_dir / f"{GOOD}.csv"

    def shift_output(row: int) -> None:
        _edit_lines(
            path,
            lambda lines: (
                lines[: row + 1]
                + [", ".join(f"{float(v) + 1e-6 * (i == 5):.17e}" for i, v in enumerate(lines[row + 1].split(",")))]
                + lines[row + 2 :]
            ),
        )

    shift_output(499)  # t = 0.998 s: the hand-raising transient is not checked
    assert len(legacy_episode(path, controller)) == 1000
    shift_output(500)  # t = 1.000 s: checked
    with pytest.raises(LegacyCsvError, match=r"off by 1e-06 V at t = 1\.000 s"):
        legacy_episode(path, controller)


def test_existing_output_is_refused_unless_forced(synthetic_dir, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    target = out / f"{GOOD}.mcap"
    target.write_bytes(b"keep me")
    assert main([str(synthetic_dir), "--out", str(out)]) == 1
    assert "exists (use --force to overwrite)" in capsys.readouterr().err
    assert target.read_bytes() == b"keep me"
    assert main([str(synthetic_dir), "--out", str(out), "--force"]) == 0
    assert len(read_episode(target)) == 1000


def test_usage_problems_give_one_line_each_and_no_traceback(synthetic_dir, tmp_path, capsys):
    lonely = tmp_path / "lonely"
    lonely.mkdir()
    shutil.copy(synthetic_dir / f"{GOOD}.csv", lonely / "qube_20230828T160000_1_2_3.csv")
    misnamed = synthetic_dir / "run7.csv"
    shutil.copy(synthetic_dir / f"{GOOD}.csv", misnamed)
    status = main([str(tmp_path / "nowhere.csv"), str(lonely), str(misnamed), "--out", str(tmp_path / "o")])
    captured = capsys.readouterr()
    assert status == 2  # a SRC that does not exist is a usage error, as in every command (issue 30)
    errors = _stderr_lines(captured)
    assert len(errors) == 3, captured.err
    assert any("nowhere.csv: no such file or folder" in e for e in errors)
    assert any("qube_20230828T160000_1_2_3.csv: no controller file" in e and "--controller" in e for e in errors)
    assert any("run7.csv: file name does not follow" in e for e in errors)
    assert "Traceback" not in captured.err


def test_explicit_controller_file_and_a_bad_one(synthetic_dir, tmp_path, capsys):
    gains = tmp_path / "gains.toml"
    gains.write_text(GAINS_TOML)
    (synthetic_dir / "controller.toml").unlink()
    assert main([str(synthetic_dir / f"{GOOD}.csv"), "--out", str(tmp_path / "o"), "--controller", str(gains)]) == 0
    gains.write_text("kp_theta = 6.0\n")
    assert main([str(synthetic_dir), "--out", str(tmp_path / "o2"), "--controller", str(gains)]) == 2
    err = capsys.readouterr().err
    assert "gains.toml: missing gains kd_theta" in err and "Traceback" not in err


def test_a_file_named_twice_is_imported_once(synthetic_dir, tmp_path, capsys):
    assert main([str(synthetic_dir), str(synthetic_dir / f"{GOOD}.csv"), "--out", str(tmp_path / "o")]) == 0
    assert "imported 1 of 1 file" in capsys.readouterr().out


def test_help_and_usage_errors(capsys):
    assert main(["--help"]) == 0
    text = capsys.readouterr().out
    assert "--force" in text and "controller.toml" in text and "1e-9 V" in text
    assert main(["some.csv"]) == 2  # --out is required
    assert "--out" in capsys.readouterr().err


def test_progress_bar_on_a_terminal_and_silence_elsewhere(synthetic_dir, tmp_path, capsys, monkeypatch):
    shutil.copy(synthetic_dir / f"{GOOD}.csv", synthetic_dir / "qube_20230828T170000_1_2_3.csv")
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert main([str(synthetic_dir), "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    assert "2/2" in err and "qube_20230828T170000_1_2_3.csv" in err
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False)  # piped or logged: no bar
    assert main([str(synthetic_dir), "--out", str(tmp_path / "p")]) == 0
    assert capsys.readouterr().err == ""


# --- the paper's dataset -----------------------------------------------------------


@pytest.mark.dataset
def test_dataset_subset_round_trip(qube_csv_files, tmp_path, capsys):
    subset = [qube_csv_files[0], qube_csv_files[-1]]
    assert main([*map(str, subset), "--out", str(tmp_path), "--quiet"]) == 0
    for path in subset:
        episode = read_episode(log_path(tmp_path, path.stem))
        assert len(episode) == 10_000
        assert_matches_csv(episode, path)
        assert_controller_state_consistent(episode)


@pytest.mark.slow
@pytest.mark.dataset
def test_dataset_all_episodes_round_trip_within_the_size_budget(qube_dataset, qube_csv_files, tmp_path, capsys):
    assert len(qube_csv_files) == 48
    assert main([str(qube_dataset), "--out", str(tmp_path), "--quiet"]) == 0
    csv_bytes = mcap_bytes = 0
    for path in qube_csv_files:
        out = tmp_path / f"{path.stem}.mcap"
        episode = read_episode(out)
        assert_matches_csv(episode, path)
        assert_controller_state_consistent(episode)
        csv_bytes += path.stat().st_size
        mcap_bytes += out.stat().st_size
    assert mcap_bytes <= 0.40 * csv_bytes


@pytest.mark.parametrize("cut_from_end", [5, 40])  # inside the last number (9 fields still), or inside the row
def test_a_file_cut_mid_line_is_imported_without_that_line_as_incomplete(cut_from_end, legacy_folder, tmp_path, capsys):
    csv_path = legacy_folder / f"{GOOD}.csv"
    whole = parse_csv_independently(csv_path)
    raw = csv_path.read_bytes()
    cut_at = raw.index(b"\n", len(raw) * 3 // 4) - cut_from_end  # past the first second, inside a row
    csv_path.write_bytes(raw[:cut_at])
    rows_before = raw[:cut_at].count(b"\n") - 1  # whole data rows before the cut one
    status = main([str(legacy_folder), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert status == 0, err
    line = raw[:cut_at].count(b"\n") + 1
    assert err == (
        f"qube-import: warning: {csv_path}: cut short: its last line (line {line}) ends without a "
        f"newline and was dropped; imported as an incomplete episode of {rows_before} samples\n"
    )
    episode = read_episode(tmp_path / "o" / f"{GOOD}.mcap", warn=False)
    assert len(episode) == rows_before and not episode.is_complete
    assert episode.metadata.status == "aborted" and "legacy CSV cut short" in episode.metadata.status_reason
    np.testing.assert_array_equal(episode.theta, whole["theta"][:rows_before])


def _gap(lines):
    return lines[:300] + lines[550:]  # 250 samples missing, as an export of a log with a lost chunk


def _half_saturated(lines):
    fields = lines[20].split(",")
    fields[-1] = " 0.5"
    lines[20] = ",".join(fields)
    return lines


@pytest.mark.parametrize(
    "edit, problem",
    [
        (_gap, "t is not evenly spaced at 500 Hz from 0 (line 301: t = 1.098, expected 0.598)"),
        (_half_saturated, "line 21: saturation 0.5 is not -1, 0 or +1"),
    ],
    ids=["time gap", "saturation"],
)
def test_refusals_quote_numbers_as_plain_numbers(synthetic_dir, edit, problem):
    from qube_koopman.daq.legacy_csv import LegacyCsvError, legacy_episode, load_legacy_controller

    path = synthetic_dir / f"{GOOD}.csv"
    _edit_lines(path, edit)
    with pytest.raises(LegacyCsvError) as info:
        legacy_episode(path, load_legacy_controller(synthetic_dir / "controller.toml"))
    assert problem in str(info.value) and "np.float64" not in str(info.value)


def test_a_failed_import_leaves_no_folder_it_made(synthetic_dir, tmp_path, monkeypatch, capsys):
    import qube_koopman.daq.log as log_module

    def full_disk(path, episode, overwrite=False):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(log_module, "write_episode", full_disk)
    out = tmp_path / "new" / "out"
    assert main([str(synthetic_dir / f"{GOOD}.csv"), "--out", str(out)]) == 1
    assert "No space left on device" in capsys.readouterr().err
    assert not (tmp_path / "new").exists(), "the folders it made are gone"
