"""tools/same_reports.py: two runs' JSON outputs compared apart from their timings."""

import importlib.util
import json
from pathlib import Path

TOOL = Path(__file__).resolve().parents[2] / "tools" / "same_reports.py"


def _tool():
    spec = importlib.util.spec_from_file_location("same_reports", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(tmp_path, before: dict, after: dict, capsys) -> tuple[int, str]:
    for name, report in (("before", before), ("after", after)):
        (tmp_path / name).mkdir(exist_ok=True)
        (tmp_path / name / "report.json").write_text(json.dumps(report))
    code = _tool().main([str(tmp_path / "before"), str(tmp_path / "after")])
    return code, capsys.readouterr().out


def test_timings_and_nan_are_the_same_a_changed_figure_is_not(tmp_path, capsys):
    report = {"test": {"r2_mean": 0.9, "seconds": 1.0}, "fit_elapsed": 2.0, "ll": float("nan"), "logs": ["a", "b"]}
    timed = {**report, "test": {"r2_mean": 0.9, "seconds": 7.5}, "fit_elapsed": 3.0}
    assert _run(tmp_path, report, timed, capsys) == (0, "1 file(s) compared, 0 difference(s)\n")
    code, out = _run(tmp_path, report, {**timed, "logs": ["a", "c"]}, capsys)
    assert code == 1 and "report.json/logs/1: 'b' != 'c'" in out
    code, out = _run(tmp_path, report, {"test": report["test"]}, capsys)
    assert code == 1 and "report.json/: keys" in out
    (tmp_path / "before" / "model.json").write_text("{}")
    code, out = _run(tmp_path, report, report, capsys)
    assert code == 1 and "model.json: missing" in out
