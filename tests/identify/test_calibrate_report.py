"""qube-calibrate --report: band-power table of the replay's spectra, the calibration.rrd recording."""

from __future__ import annotations

import logging
import re

import numpy as np
import pytest

from _calibration_replay import DT, NAMES, SCALE, synthetic_replay
from qube_koopman.identify.calibrate.validate import ReplayResult
from qube_koopman.identify.calibrate.report import write_report
from qube_koopman.identify.calibrate.replay_spectra import (
    BANDS,
    CHANNELS,
    band_power_ratios,
    band_powers,
    replay_spectra,
    spectra_text,
)


def table_ratios(text: str) -> dict[str, list[float]]:
    """The twin/real column of each channel's table in ``text``."""
    out = {}
    for channel in CHANNELS:
        section = text.split(f"### {channel}\n", 1)[1].split("###", 1)[0]
        out[channel] = [float(row.split("|")[-2]) for row in section.splitlines() if re.match(r"\| [\d.]+-", row)]
    return out


def test_band_power_ratios_are_the_scale_squared_and_one_against_itself():
    text = spectra_text(synthetic_replay(), DT)
    ratios = table_ratios(text)
    for channel, scale in zip(CHANNELS, SCALE):
        assert ratios[channel] == pytest.approx([scale**2] * len(BANDS), abs=1e-3), channel
    same = table_ratios(spectra_text(synthetic_replay(scale=np.ones(3)), DT))
    assert all(r == [1.0] * len(BANDS) for r in same.values())
    assert "| 1-3 |" in text and "| 30-100 |" in text and "(2 episodes)" in text
    np.testing.assert_allclose(
        band_power_ratios(replay_spectra(synthetic_replay(), DT)), np.tile(SCALE**2, (len(BANDS), 1)), rtol=1e-12
    )


def test_band_power_integrates_the_psd_to_the_sinusoid_power():
    spectra = replay_spectra(synthetic_replay(), DT)
    assert spectra.nperseg == 1024 and spectra.frequency[-1] == pytest.approx(0.5 / DT)
    real, _ = spectra.mean()
    power = band_powers(spectra.frequency, real)  # (bands, channels)
    # A sinusoid of amplitude A carries A^2 / 2, all of it in its band (2, 5 and 20 Hz: bands 1, 2, 3).
    for j, (band, amplitude) in enumerate(((1, 0.1), (2, 0.02), (3, 3.0))):
        assert power[band, j] == pytest.approx(amplitude**2 / 2, rel=0.03)
    assert np.isnan(band_powers(spectra.frequency, real, [(300.0, 400.0)])).all()  # above Nyquist


def test_report_writes_the_table_and_a_recording_with_the_expected_entities(tmp_path):
    pytest.importorskip("rerun", reason="the viewer is the optional viz extra")
    from rerun.chunk import RrdReader

    replay = synthetic_replay()
    written = write_report(tmp_path, "tables\n", (replay, np.zeros((2, 2)), NAMES), DT)
    assert written == [tmp_path / "report.md", tmp_path / "calibration.rrd"]
    report = (tmp_path / "report.md").read_text()
    assert report.startswith("# qube-calibrate report\n\ntables\n") and "## Power spectra" in report
    schema = RrdReader(tmp_path / "calibration.rrd").store().schema()
    paths = set(schema.entity_paths())
    expected = {
        f"/validation/{stem}/{channel}/{kind}"
        for stem in ("val_a", "val_b")
        for channel in CHANNELS
        for kind in ("real", "twin")
    }
    expected |= {f"/spectra/{channel}/{kind}" for channel in CHANNELS for kind in ("real", "twin")}
    assert expected | {"/spectra/frequency_hz"} == paths
    timelines = {str(c) for c in schema.index_columns()}
    assert all(any(name in t for t in timelines) for name in ("time", "frequency_bin", "frequency_millihertz"))


def test_blueprint_has_an_episode_grid_and_a_spectra_tab():
    pytest.importorskip("rerun", reason="the viewer is the optional viz extra")
    from qube_koopman.identify.calibrate.validation_recording import blueprint, episode_paths

    parts = episode_paths(["a.mcap", "dir/a.mcap", "b c.mcap"])
    assert parts[0] == "a" and parts[1] != "a" and len(set(parts)) == 3
    episodes, spectra = blueprint(parts).root_container.contents
    assert len(episodes.contents) == 3 and "validation" in str(episodes.name)
    assert [str(v.origin) for v in episodes.contents[0].contents] == [f"validation/a/{c}" for c in CHANNELS]
    assert [str(v.origin) for v in spectra.contents[:3]] == [f"spectra/{c}" for c in CHANNELS]


class _Records(logging.Handler):
    """Keeps every record it is handed: attached to the project's logger itself, it sees each record once
    whatever a CLI run left on that logger (``propagate = False``) and whatever pytest attaches (pytest 9.2
    also hangs caplog's handler on non-propagating loggers, so caplog saw a propagated record twice)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def test_without_rerun_the_report_is_written_and_one_warning_names_the_skip(tmp_path, monkeypatch, caplog):
    monkeypatch.setitem(__import__("sys").modules, "rerun", None)  # as if the viz extra were not installed
    logger, seen = logging.getLogger("qube_koopman"), _Records()
    logger.addHandler(seen)
    try:  # at_level: a `-q` CLI run earlier in the process may have left the logger at ERROR
        with caplog.at_level(logging.WARNING, logger="qube_koopman"):
            written = write_report(tmp_path, "tables\n", (synthetic_replay(), np.zeros((2, 2)), NAMES), DT)
    finally:
        logger.removeHandler(seen)
    assert written == [tmp_path / "report.md"] and not (tmp_path / "calibration.rrd").exists()
    assert "## Power spectra" in (tmp_path / "report.md").read_text()
    [record] = seen.records
    assert "calibration.rrd not written" in record.getMessage() and 'pip install -e ".[viz]"' in record.getMessage()


def test_report_without_validation_is_the_tables_only(tmp_path):
    assert write_report(tmp_path, "tables\n", None) == [tmp_path / "report.md"]
    assert (tmp_path / "report.md").read_text() == "# qube-calibrate report\n\ntables\n"
    with pytest.raises(ValueError, match="dt"):
        write_report(tmp_path, "tables\n", (synthetic_replay(), np.zeros((2, 2)), NAMES))


def test_cli_report_folder_gets_the_spectra_and_the_recording(tmp_path, capsys):
    from qube_koopman.daq.cli.run import main as run_main
    from qube_koopman.identify.cli.calibrate import main

    assert run_main(["--episodes", "3", "--duration", "3", "--seed", "5", "--out", str(tmp_path / "logs"), "-q"]) == 0
    logs = sorted(map(str, (tmp_path / "logs").glob("*.mcap")))
    capsys.readouterr()
    assert (
        main(
            [
                *logs[:2],
                "--validate",
                logs[2],
                "--out",
                str(tmp_path / "plant.toml"),
                "--max-nfev",
                "4",
                "--report",
                str(tmp_path / "report"),
            ]
        )
        == 0
    )
    err = capsys.readouterr().err
    report = (tmp_path / "report" / "report.md").read_text()
    assert "## Validation on 1 episodes not fitted" in report and "### voltage" in report
    try:
        import rerun  # noqa: F401
    except ImportError:
        assert "calibration.rrd not written" in err
    else:
        # No warning but the fit's own (stopped by --max-nfev 4, on purpose: a quick test).
        warnings = [line for line in err.splitlines() if "warning" in line and "did not converge" not in line]
        assert (tmp_path / "report" / "calibration.rrd").stat().st_size > 0 and not warnings, err


def test_validation_logs_that_were_fitted_are_not_called_held_out(tmp_path, capsys):
    from qube_koopman.daq.cli.run import main as run_main
    from qube_koopman.identify.cli.calibrate import main
    from qube_koopman.sim.pendulum.params_file import load_plant

    assert run_main(["--episodes", "2", "--duration", "3", "--seed", "5", "--out", str(tmp_path / "logs"), "-q"]) == 0
    logs = sorted(map(str, (tmp_path / "logs").glob("*.mcap")))
    capsys.readouterr()
    # The first log fitted and validated (named through another path), the second only validated.
    again = str(tmp_path / "logs" / ".." / "logs" / logs[0].rsplit("/", 1)[1])
    assert (
        main(
            [
                logs[0],
                "--validate",
                again,
                logs[1],
                "--out",
                str(tmp_path / "plant.toml"),
                "--max-nfev",
                "2",
                "--report",
                str(tmp_path / "report"),
            ]
        )
        == 0
    )
    err = capsys.readouterr().err
    assert "1 of the 2 validation logs are fitted too" in err and "not a held-out check" in err
    report = (tmp_path / "report" / "report.md").read_text()
    assert "## Validation on 2 episodes (1 of them fitted too: not held out)" in report
    assert "not fitted" not in report
    assert load_plant(tmp_path / "plant.toml").provenance["validated_also_fitted"] == 1


def test_the_per_controller_fit_table_names_the_segments_length(tmp_path, capsys):
    from qube_koopman.daq.cli.run import main as run_main
    from qube_koopman.identify.cli.calibrate import main

    for name, extra in (("rig", []), ("soft", ["--controller", "soft-theta"])):
        assert (
            run_main(["--episodes", "1", "--duration", "3", "--seed", "5", "--out", str(tmp_path / name), "-q", *extra])
            == 0
        )
    logs = sorted(map(str, tmp_path.glob("*/*.mcap")))
    capsys.readouterr()
    assert main([*logs, "--horizon", "0.1", "--out", str(tmp_path / "plant.toml"), "--max-nfev", "2"]) == 0
    out = capsys.readouterr().out
    assert "Fit per controller (0.1 s segments of the logged voltage, open loop):" in out


def test_band_and_slow_std_ratios_are_the_scale_in_every_band():
    # twin = real * SCALE: every band's and the slow signals' std ratio is SCALE, whatever the spectrum.
    from qube_koopman.identify.calibrate.replay_spectra import STD_BANDS, band_std_ratios, slow_std_ratio

    replay = synthetic_replay(n_steps=9000)
    ratios = band_std_ratios(replay, DT)
    assert ratios.shape == (len(STD_BANDS), 3)
    np.testing.assert_allclose(ratios, np.tile(SCALE, (len(STD_BANDS), 1)), rtol=1e-9)
    np.testing.assert_allclose(slow_std_ratio(replay, DT), SCALE, rtol=1e-9)
    # A twin that only misses the slow motion: below 0.3 Hz low, the other bands 1.
    t = np.arange(9000) * DT
    slow = 0.3 * np.sin(2 * np.pi * 0.15 * t)[:, None, None] * np.array([1.0, 0.0, 0.0])
    real = synthetic_replay(scale=np.ones(3), n_steps=9000)
    missing = ReplayResult(real.std_ratio, real.balanced, real.nrmse, real.offsets, real.twin, real.real + slow)
    ratios = band_std_ratios(missing, DT)
    assert ratios[0, 0] < 0.2 and np.allclose(ratios[2:, 0], 1.0, atol=0.02)


def test_the_per_controller_summary_has_a_row_per_controller_and_the_issue_bands():
    from qube_koopman.identify.calibrate.report import controller_summary_text

    text = controller_summary_text(
        [("kp_theta 6", synthetic_replay(n_steps=9000)), ("kp_theta 2", synthetic_replay(np.ones(3), n_steps=9000))], DT
    )
    rows = [line for line in text.splitlines() if line.startswith("| kp_theta")]
    assert len(rows) == 2
    header = next(line for line in text.splitlines() if line.startswith("| controller"))
    for band in ("0-0.3 Hz", "0.3-1 Hz", "1-3 Hz", "above 3 Hz", "slow (< 0.5 Hz)"):
        assert band in header
    assert "0.500 / 2.000 / 1.500" in rows[0] and "1.000 / 1.000 / 1.000" in rows[1]


def test_controller_groups_follow_the_logged_controller(tmp_path):
    from qube_koopman.daq.cli.run import main as run_main
    from qube_koopman.daq.log import read_episode
    from qube_koopman.identify.calibrate.validate import controller_groups

    assert run_main(["--episodes", "2", "--duration", "1", "--seed", "3", "--out", str(tmp_path / "a"), "-q"]) == 0
    assert (
        run_main(
            [
                "--episodes",
                "1",
                "--duration",
                "1",
                "--seed",
                "4",
                "--controller",
                "soft-theta",
                "--out",
                str(tmp_path / "b"),
                "-q",
            ]
        )
        == 0
    )
    paths = sorted((tmp_path / "a").glob("*.mcap")) + sorted((tmp_path / "b").glob("*.mcap"))
    episodes = [read_episode(p) for p in [paths[0], paths[2], paths[1]]]
    groups = controller_groups(episodes)
    assert [members for _, members in groups] == [[0, 2], [1]]
    assert groups[0][0].startswith("kp_theta 6") and groups[1][0].startswith("kp_theta 2")
