"""Settings that run but are probably not what the user meant get one warning line each: the paper's split
given other than the paper's 48 logs, a sweep whose best alpha is the edge of its grid."""

import argparse
import shutil
import warnings

import pytest

from qube_koopman.core.command import run_command
from qube_koopman.daq.log.names import find_logs
from qube_koopman.identify.cli.identify import main as identify_main
from qube_koopman.identify.command_warnings import ONE_LINE_WARNINGS
from qube_koopman.identify.model_selection.split import paper_split


def _names(n):
    return [f"qube_{i:03d}.mcap" for i in range(n)]


def test_the_paper_split_of_other_than_48_logs_says_what_it_did(capsys):
    def command(args):
        train, test = paper_split(_names(54)[::-1])
        assert [p.name for p in train] == _names(28) and len(test) == 26
        return 0

    assert run_command("qube-identify", command, argparse.Namespace(), one_line_warnings=ONE_LINE_WARNINGS) == 0
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "qube-identify: warning: the paper's split is for its 48 logs, got 54: the first 28 names sorted train, "
        "the other 26 test"
    ]


def test_the_paper_split_of_48_logs_is_silent():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        train, test = paper_split(_names(48))
    assert len(train) == 28 and len(test) == 20


@pytest.mark.dataset
def test_a_sweep_whose_best_alpha_is_its_grids_edge_says_to_widen_it(qube_logs, tmp_path, capsys):
    logs = find_logs(qube_logs)
    for name, chosen in (("train", logs[:6]), ("test", logs[28:29])):
        (tmp_path / name).mkdir()
        for path in chosen:
            shutil.copy(path, tmp_path / name / path.name)
    code = identify_main(
        [
            "--train",
            str(tmp_path / "train"),
            "--test",
            str(tmp_path / "test"),
            "--out",
            str(tmp_path / "out"),
            "--alpha-sweep",
            "10",
            "100",
            "2",
            "--cv-splits",
            "2",
            "--quiet",
        ]
    )  # two alphas, both too large: the smaller is the best, and the score still rises there
    err = capsys.readouterr().err
    assert code == 0, err
    lines = [line for line in err.splitlines() if "the sweep's best alpha" in line]
    assert lines == [
        "qube-identify: warning: the sweep's best alpha 10 is the smallest of its grid (10 to 100) and its score "
        "still rises there: the best may lie beyond it; widen the sweep (--alpha-sweep MIN MAX N)"
    ]


def test_an_edge_where_the_score_is_flat_is_no_reason_to_warn():
    from qube_koopman.identify.model_selection.sweep import FLAT_R2, AlphaAtGridEdge, warn_at_grid_edge

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_at_grid_edge([1e-5, 1e-3, 1e-1], 1e-5, [0.98066, 0.98066 - FLAT_R2 / 2, 0.977])
        warn_at_grid_edge([1e-5, 1e-3, 1e-1], 1e-3, [0.97, 0.98, 0.977])
    with pytest.warns(AlphaAtGridEdge, match="largest of its grid"):
        warn_at_grid_edge([1e-1, 1e-3, 1e-5], 1e-1, [0.99, 0.98, 0.97])
