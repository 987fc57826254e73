"""A plain qube-identify shows its progress: the fit's training episodes and the test episodes' scoring."""

import shutil

import pytest

from qube_koopman.daq.log.names import find_logs
from qube_koopman.identify.cli import identify

pytestmark = pytest.mark.dataset


@pytest.mark.parametrize(
    "extra", [[], ["--interval", "0"], ["--method", "cl-arx"]], ids=["default", "no-interval", "arx"]
)
def test_the_fit_and_the_test_scoring_report_their_episodes(qube_logs, tmp_path, capsys, monkeypatch, extra):
    logs = find_logs(qube_logs)
    for name, chosen in (("train", logs[:5]), ("test", logs[28:31])):
        (tmp_path / name).mkdir()
        for path in chosen:
            shutil.copy(path, tmp_path / name / path.name)
    calls = []
    monkeypatch.setattr(identify, "progress", lambda label, done, total: calls.append((label, done, total)))
    code = identify.main(
        ["--train", str(tmp_path / "train"), "--test", str(tmp_path / "test"), "--out", str(tmp_path / "out"), *extra]
    )
    assert code == 0, capsys.readouterr().err
    tested = [c for c in calls if c[0] == "test episodes"]
    assert tested[0] == ("test episodes", 0, 3) and tested[-1] == ("test episodes", 3, 3)
    assert [done for _, done, _ in tested] == sorted(done for _, done, _ in tested)
    if "cl-arx" not in extra:  # ARX fits from every episode at once
        fitted = [c for c in calls if c[0] == "fit: training episodes"]
        assert fitted[0] == ("fit: training episodes", 0, 5) and fitted[-1] == ("fit: training episodes", 5, 5)
