"""Argument fuzzing (issue 30): no argument vector gives any command a traceback.

For every console script in pyproject.toml, hypothesis draws argument vectors from the command's
own parser (its options, introspected: flags, nargs, choices) with values that are negative, zero,
NaN, infinite, huge (1e308, 10**30), empty, of the wrong type ("abc", "1.5" for a whole number),
and paths that are missing, empty files, binary junk, folders, or real episode logs. Each vector
runs in-process (``main(argv)``, stderr captured) in a fresh folder. Asserted, the README's exit
table: no traceback, exit 0, 1 or 2, and an exit 2 whose error names an option of the vector
(its flag), a file or folder it names, or the argument it lacks.

The vectors are the same every run (hypothesis derandomized), so the suite is deterministic;
``QUBE_FUZZ_EXPLORE=1`` (and ``QUBE_FUZZ_EXAMPLES=N``) draws fresh ones to look for more bugs.

Long work is never started: where the arguments pass, the step that would run for seconds or
forever (the emulator's pseudo-terminal, the calibration's fit, the Duffing experiment, the
lifting search, a qube-run longer than 2 s of simulated time or paced, streamed or at real-time
priority) is replaced by a stub that ends the command (``Reached``, counted as a pass; the
stubs and the folder each example starts from are tests/_command_stubs.py's). The Duffing stub
first checks what the library itself requires of its arguments, so a value the command let
through and the library refuses still fails here. No serial device is opened: the only ports
drawn are files and folders under the example's temporary folder.
"""

from __future__ import annotations

import argparse
from collections import Counter
import importlib
import os
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from _command_stubs import commands, run_in_process

pytestmark = pytest.mark.slow

#: Values drawn for any option that takes one: out of range, non-finite, huge, empty, wrong type, and a few valid.
NUMBERS = [
    "-1",
    "0",
    "nan",
    "inf",
    "-inf",
    "1e308",
    str(10**30),
    f"-{10**30}",
    "",
    "abc",
    "1.5",
    "-0.5",
    "1",
    "2",
    "3",
    "0.5",
]
#: Paths, relative to the example's folder (the working directory while the command runs).
PATHS = [
    "missing",
    "missing/deeper/x.mcap",
    "empty.txt",
    "junk.bin",
    "folder",
    "logs",
    "logs/a.mcap",
    "logs/b.mcap",
    "csv",
    "csv/" + "qube_20230828T150615_434_696_394.csv",
    "",
]
PATH_WORDS = ("FILE", "DIR", "LOG", "SRC", "DEV", "URL", "ADDRESS", ".toml", ".rrd", ".csv", ".json")

#: A valid invocation per command (and subcommand) that half the vectors start from, so that the drawn
#: options also reach the checks behind the parsing (the logs loaded, the fit's own); the drawn options
#: follow it (the last of an option counts).
BASE = {
    "qube-identify": ["--train", "logs/a.mcap", "--test", "logs/b.mcap", "--skip", "0"],
    "qube-run": ["--episodes", "1", "--duration", "1"],
    "qube-import": ["csv", "--out", "out"],
    "qube-export": ["logs", "--format", "csv", "--out", "out"],
    "qube-calibrate": ["logs/a.mcap", "--out", "p.toml"],
    "qube": ["--data", "logs"],
}

#: Examples drawn per command; the count is checked by the last test.
EXAMPLES = int(os.environ.get("QUBE_FUZZ_EXAMPLES", "60"))
# The same vectors every run (derandomized): a suite that failed on a fresh draw one run in a few
# would block everyone's work for a bug nobody's change made. QUBE_FUZZ_EXPLORE=1 draws new ones
# (with QUBE_FUZZ_EXAMPLES=1000, say) to look for more, as a developer's run.
EXPLORE = os.environ.get("QUBE_FUZZ_EXPLORE") == "1"
DRAWN: dict[str, Counter] = {}  # command -> exit statuses ("reached": the long work's stub)


def _parser_of(module) -> argparse.ArgumentParser:
    builder = getattr(module, "build_parser", None) or module._parser
    return builder()


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _variants() -> list[tuple[str, list[str]]]:
    """(command, leading words): one per command, one per subcommand."""
    found = []
    for name, target in sorted(commands().items()):
        module = importlib.import_module(target.split(":")[0])
        subs = _subcommands(_parser_of(module))
        found += [(name, [sub]) for sub in sorted(subs)] or [(name, [])]
    return found


VARIANTS = _variants()


def _fuzzable(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    skip = (argparse._HelpAction, argparse._VersionAction, argparse._SubParsersAction)
    return [a for a in parser._actions if not isinstance(a, skip)]


def _is_path(action: argparse.Action) -> bool:
    if action.type is Path:
        return True
    metavar = action.metavar if isinstance(action.metavar, str) else ""
    return any(word in metavar for word in PATH_WORDS) or action.dest in ("logs", "sources", "port", "out", "data")


def _values(action: argparse.Action) -> st.SearchStrategy[list[str]]:
    """Values for one action, as many as its nargs takes (now and then one too few)."""
    if action.nargs == 0:
        return st.just([])
    if action.choices:
        one = st.sampled_from(list(action.choices) + ["", "abc"])
    elif _is_path(action):
        one = st.sampled_from(PATHS + ["abc", "-1"])
    else:
        one = st.sampled_from(NUMBERS + ["junk.bin"])
    if action.nargs is None:
        return st.lists(one, min_size=1, max_size=1)
    if action.nargs == "?":
        return st.lists(one, min_size=0, max_size=1)
    if action.nargs == "+":
        return st.lists(one, min_size=1, max_size=3)
    if action.nargs == "*":
        return st.lists(one, min_size=0, max_size=3)
    n = int(action.nargs)
    return st.lists(one, min_size=n - 1, max_size=n)


@st.composite
def _argv(draw, parser: argparse.ArgumentParser, base: list[str]) -> list[str]:
    actions = _fuzzable(parser)
    positionals = [a for a in actions if not a.option_strings]
    options = [a for a in actions if a.option_strings]
    argv: list[str] = list(base) if base and draw(st.booleans()) else []
    for action in positionals if not argv else []:
        if draw(st.integers(0, 9)) > 0:  # now and then left out
            argv += draw(_values(action))
    chosen = draw(st.lists(st.sampled_from(options), max_size=6, unique_by=lambda a: a.dest))
    for action in chosen:
        argv += [draw(st.sampled_from(action.option_strings))] + draw(_values(action))
    if draw(st.integers(0, 19)) == 0:
        argv.append("--no-such-option")
    return argv


def _names_the_problem(stderr: str, argv: list[str], parser: argparse.ArgumentParser) -> bool:
    """An error (or a warning it follows) names a flag, a path or a value of ``argv``, or what is missing."""
    lines = [line for line in stderr.splitlines() if ": error: " in line or ": warning: " in line]
    words = {w for w in argv if w.startswith("-") and len(w) > 1}
    words |= {w for w in argv if w in PATHS or w == "abc"}  # a path drawn (abc: a missing one, for a path option)
    words |= {str(a.metavar) for a in _fuzzable(parser) if not a.option_strings and a.metavar}
    words |= {name for a in _fuzzable(parser) if not a.option_strings for name in (a.dest, a.dest.upper())}
    words |= {"--" + a.dest.replace("_", "-") for a in _fuzzable(parser) if a.option_strings}
    return any(w in line for line in lines for w in words if w)


@pytest.mark.parametrize("command, words", VARIANTS, ids=[" ".join([c, *w]) for c, w in VARIANTS])
def test_no_argument_vector_gives_a_traceback(command, words, template, stubs):
    module = importlib.import_module(commands()[command].split(":")[0])
    parser = _parser_of(module)
    if words:
        parser = _subcommands(parser)[words[0]]

    @settings(
        max_examples=EXAMPLES,
        deadline=None,
        database=None,
        derandomize=not EXPLORE,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )
    @given(argv=_argv(parser, BASE.get(words[0] if words else command, [])))
    def check(argv):
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp) / "run"
            shutil.copytree(template, folder)
            status, stderr = run_in_process(command, [*words, *argv], folder)
        DRAWN.setdefault(" ".join([command, *words]), Counter())[status] += 1
        shown = f"{command} {' '.join(map(repr, [*words, *argv]))}\n{stderr}"
        assert status != "traceback" and "Traceback (most recent call last)" not in stderr, shown
        assert status in (0, 1, 2, "reached"), shown
        if status == 2:
            assert _names_the_problem(stderr, argv, parser), shown

    check()


# What the fuzzing (and probing past it with real logs) found, each as it now reads. Before: a traceback
# (reproduce --alpha inf, identify --estimate-window inf), a count that never ends (--poly 10**30), the
# library's words without the option (radians for --alpha-limit; "Maximum allowed size exceeded"), or an
# empty path read as the current folder (".: cannot read plant file (Is a directory)").
FOUND = [
    (
        "qube-reproduce",
        ["duffing", "--alpha", "inf"],
        "qube-reproduce: error: --alpha must be a finite number >= 0, got inf",
    ),
    (
        "qube-run",
        ["--alpha-limit", "1.5"],
        "qube-run: error: --alpha-limit 1.5 deg: inside the start gate (start_alpha",
    ),
    (
        "qube-emulate",
        ["--plant", ""],
        "qube-emulate: error: argument --plant: an empty path (an unset shell variable?)",
    ),
    (
        "qube-import",
        ["csv", "--out", "out", "--controller", ""],
        "qube-import: error: argument --controller: an empty path",
    ),
    ("qube-run", ["--out", "", "--episodes", "1", "--duration", "1"], "qube-run: error: argument --out: an empty path"),
    (
        "qube-identify",
        [*BASE["qube-identify"], "--estimate-window", "inf", "--protocol", "window"],
        "qube-identify: error: --estimate-window must be at most 86400 s (the longest episode), got inf",
    ),
    (
        "qube-identify",
        [*BASE["qube-identify"], "--estimate-window", "1e308", "--offsets", "alpha"],
        "qube-identify: error: --estimate-window must be at most 86400 s (the longest episode), got 1e+308",
    ),
    (
        "qube-identify",
        [*BASE["qube-identify"], "--alpha", "inf"],
        "qube-identify: error: --alpha must be a finite number >= 0, got inf",
    ),
    (
        "qube-identify",
        [*BASE["qube-identify"], "--max-radius", "inf"],
        "qube-identify: error: --max-radius must be a finite positive number, got inf",
    ),
    (
        "qube-identify",
        [*BASE["qube-identify"], "--max-radius", "1", "--pole-center", "nan"],
        "qube-identify: error: --pole-center must be a finite number, got nan",
    ),
    (
        "qube-identify",
        [*BASE["qube-identify"], "--rbf", "thin-plate", "--rbf-shape", "nan"],
        "qube-identify: error: --rbf-shape must be positive, got nan",
    ),
    (
        "qube-identify",
        [*BASE["qube-identify"], "--rbf", "thin-plate", "--rbf-offset", "-1"],
        "qube-identify: error: --rbf-offset must be positive, got -1.0",
    ),
    (
        "qube-identify",
        [*BASE["qube-identify"], "--rbf", "thin-plate", "--rbf-centers", str(10**30)],
        f"qube-identify: error: argument --rbf-centers: must be a whole number in [1, 1000], got {10**30}",
    ),
    (
        "qube-identify",
        [*BASE["qube-identify"], "--alpha-sweep", "1", "2", str(10**30)],
        f"qube-identify: error: --alpha-sweep needs a finite MAX and N <= 1000, got 1 2 {10**30}",
    ),
    (
        "qube-identify",
        [*BASE["qube-identify"], "--alpha-sweep", "1", "inf", "3"],
        "qube-identify: error: --alpha-sweep needs a finite MAX and N <= 1000, got 1 inf 3",
    ),
    (
        "qube-identify",
        [*BASE["qube-identify"], "--poly", str(10**30)],
        f"qube-identify: error: --poly must be at most 10, got {10**30}",
    ),
    ("qube-design", ["junk.bin", "--out", "c.toml"], "qube-design: error: junk.bin: not a readable model file ("),
    (
        "qube-identify",
        [*BASE["qube-identify"], "--delays", str(10**30)],
        f"qube-identify: error: --delays {10**30} needs episodes of at least {10**30 + 2} samples; ",
    ),
    (
        "qube-identify",
        [*BASE["qube-identify"], "--search"],
        "qube-identify: error: --search cross-validates by "
        "holding out whole training episodes: it needs at least 2 training logs, got 1",
    ),
    (
        "qube-identify",
        [*BASE["qube-identify"], "--alpha-sweep", "1e-3", "1", "3"],
        "qube-identify: error: "
        "--alpha-sweep cross-validates by holding out whole training episodes: "
        "it needs at least 2 training logs, got 1",
    ),
]


@pytest.mark.parametrize("command, argv, message", FOUND, ids=[" ".join(c[1][-2:]) for c in FOUND])
def test_what_the_fuzzing_found_is_a_usage_error_naming_the_option(command, argv, message, template, tmp_path):
    folder = tmp_path / "run"
    shutil.copytree(template, folder)
    status, stderr = run_in_process(command, argv, folder)
    assert status == 2 and message in stderr and "Traceback" not in stderr, stderr
    assert not (folder / "o").exists() and not (folder / "identified").exists()  # before any work


def test_zz_every_command_drew_its_argument_vectors(capsys):
    """Last in the file: how many vectors were drawn (hypothesis may stop early when it has seen them all)."""
    if not DRAWN:
        pytest.skip("the fuzzing tests did not run in this process")
    assert {name.split()[0] for name in DRAWN} == set(commands()), DRAWN
    total = sum(sum(c.values()) for c in DRAWN.values())
    with capsys.disabled():
        print(f"\nargument fuzzing: {total} argument vectors; exit statuses by command:")
        for name, statuses in sorted(DRAWN.items()):
            print(f"  {name}: {dict(sorted(statuses.items(), key=str))}")
