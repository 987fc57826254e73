"""The declared version floors are the tested ones: a fresh venv with the lowest allowed versions runs.

Needs PyPI (skipped with a message when it cannot be reached); pip's cache makes later runs
quick (the first downloads the dependencies' wheels). The pins are in .ci/lowest-versions.txt.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PINS = ROOT / ".ci" / "lowest-versions.txt"
# One seed of the SDP cross-check (cvxpy + clarabel: clarabel 0.6.0 failed it at closed_loop-5.0).
SDP = "tests/identify/test_sdp_cross_check.py::test_closed_form_equals_sdp"
SMOKE_TESTS = [
    "tests/daq/test_log.py",
    "tests/daq/test_export.py",
    "tests/identify/test_analytic.py",
    "tests/identify/test_appendix_lstsq.py",
    "tests/daq/test_viz_recording.py",
    f"{SDP}[closed_loop-0.0-2]",
    f"{SDP}[closed_loop-5.0-2]",
    f"{SDP}[plant-5.0-2]",
]

#: The 48 files' CSV round trip reaches no dependency the other export tests do not (numpy's text
#: output): half the subset's time, and the main suite runs it.
SMOKE_DESELECTED = "tests/daq/test_export.py::test_csv_round_trips_the_48_dataset_files_bit_for_bit"

#: What the smoke subset needs beside the package (its tests' imports and pyproject's addopts).
SMOKE_RUNNER = ["pytest", "hypothesis", "pytest-xdist"]


def _pins() -> dict[str, str]:
    lines = (line.split("#")[0].strip() for line in PINS.read_text().splitlines())
    return dict(line.split("==") for line in lines if line)


def _floors() -> dict[str, str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    requirements = project["dependencies"] + project["optional-dependencies"]["viz"]
    floors = {}
    for requirement in requirements:
        match = re.fullmatch(r"([A-Za-z0-9_.-]+)>=([0-9.]+)(,<[0-9.]+)?", requirement.replace(" ", ""))
        assert match, f"pyproject.toml: {requirement!r} has no plain >= floor"
        floors[match[1]] = match[2]
    return floors


def _same_version(a: str, b: str) -> bool:
    pad = lambda v: [int(x) for x in v.split(".")] + [0] * (3 - len(v.split(".")))  # noqa: E731
    return pad(a) == pad(b)


def test_every_floor_is_pinned_in_the_lowest_versions_file():
    pins, floors = _pins(), _floors()
    assert set(pins) == set(floors)
    for name, floor in floors.items():
        assert _same_version(pins[name], floor), f"{name}: floor {floor} in pyproject.toml, {pins[name]} tested"


#: The venv's commands write their bytecode (the suite may run with PYTHONDONTWRITEBYTECODE): the
#: install compiles nothing, so the first command compiles what it imports and the others reuse it.
VENV_ENV = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def _run(args: list, cwd: Path, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(a) for a in args], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=VENV_ENV
    )


def _unreachable(done: subprocess.CompletedProcess) -> bool:
    return done.returncode != 0 and bool(
        re.search(r"(?i)connection|network is unreachable|temporary failure", done.stdout + done.stderr)
    )


@pytest.fixture(scope="module")
def built_wheel(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """The wheel built from this checkout by pip (verbose, for the build's warnings), once for the
    module: the venv below installs this file rather than building it a second time."""
    tmp_path = tmp_path_factory.mktemp("wheel")
    built = _run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--disable-pip-version-check", "-v", "-w", tmp_path, ROOT],
        tmp_path,
    )
    if _unreachable(built):
        pytest.skip("PyPI not reachable (the build backend comes from it)")
    assert built.returncode == 0, built.stderr[-3000:]
    (wheel,) = tmp_path.glob("qube_koopman-*.whl")
    return wheel, built


@pytest.fixture(scope="module")
def lowest_venv(tmp_path_factory, built_wheel) -> Path:
    """A fresh venv with the wheel built from this checkout, the lowest allowed versions, and
    PyPI's own `identify` (pre-commit's dependency, whose import name the project must not take)."""
    tmp_path = tmp_path_factory.mktemp("lowest")
    env_dir = tmp_path / "venv"
    # No pip of its own: this interpreter's pip installs into it (`pip --python`), 3 s less than
    # bootstrapping one with ensurepip.
    venv.create(env_dir, with_pip=False)
    python = env_dir / "bin" / "python"
    # The runtime and viewer dependencies at their floors, and only what the smoke subset runs with
    # (pytest, hypothesis, pytest-xdist for the addopts): the test extra's documentation, notebook,
    # linter and cluster tools have no floor here, and installing them took most of this test's time.
    # --no-compile: byte-compiling every installed module (scipy's and cvxpy's tests among them)
    # took half the install; the smoke commands compile what they import, once (VENV_ENV).
    install = _run(
        [
            *_pip(python),
            "install",
            "--no-compile",
            "--only-binary",
            ":all:",
            "-c",
            PINS,
            f"{built_wheel[0]}[viz]",
            *SMOKE_RUNNER,
            "identify",
        ],
        tmp_path,
        timeout=900,
    )
    if _unreachable(install):
        pytest.skip(f"PyPI not reachable: {install.stderr.strip().splitlines()[-1]}")
    assert install.returncode == 0, install.stdout[-3000:] + install.stderr[-3000:]
    return env_dir


def _pip(python: Path) -> list:
    """This interpreter's pip, acting on the venv of ``python``."""
    return [sys.executable, "-m", "pip", "--python", python, "--disable-pip-version-check"]


COMMANDS = [
    "qube-run",
    "qube-identify",
    "qube-reproduce",
    "qube-import",
    "qube-export",
    "qube-emulate",
    "qube-calibrate",
]


@pytest.mark.slow
@pytest.mark.network
def test_the_wheel_installs_beside_pypi_identify(lowest_venv, tmp_path):
    python = lowest_venv / "bin" / "python"
    code = (
        "import identify, identify.identify, qube_koopman.identify, qube_koopman.daq, qube_koopman.sim, "
        "qube_koopman.firmware_protocol; from qube_koopman.identify import ClEdmd; "
        "print(identify.__file__); print(qube_koopman.identify.__file__); "
        "print(identify.identify.tags_from_filename('x.py'))"
    )
    done = _run([python, "-c", code], tmp_path)  # outside the checkout: only installed code is seen
    assert done.returncode == 0, done.stderr[-3000:]
    theirs, ours, tags = done.stdout.split("\n")[:3]
    assert "site-packages/identify/" in theirs and "site-packages/qube_koopman/identify/" in ours
    assert "python" in tags
    # every command of the project runs from the wheel (and none is PyPI identify's `identify-cli`)
    for command in COMMANDS:
        for flag in ("--version", "--help"):
            ran = _run([lowest_venv / "bin" / command, flag], tmp_path, timeout=120)
            assert ran.returncode == 0 and ran.stdout.strip(), f"{command} {flag}: {ran.stderr[-2000:]}"


@pytest.mark.slow
@pytest.mark.network
def test_lowest_allowed_versions_install_and_pass_a_smoke_subset(lowest_venv, tmp_path):
    bin_dir = lowest_venv / "bin"
    python = bin_dir / "python"
    listed = _run([*_pip(python), "list", "--format", "freeze"], tmp_path).stdout
    installed = dict(line.split("==") for line in listed.split() if "==" in line)
    for name, version in _pins().items():
        assert installed.get(name) == version, (name, installed.get(name))

    # The commands, from the installed wheel: acquire, record, identify, export.
    logs, held_out = tmp_path / "logs", tmp_path / "held_out"
    steps = [
        [
            bin_dir / "qube-run",
            "--episodes",
            "4",
            "--duration",
            "2",
            "--seed",
            "1",
            "--out",
            logs,
            "--rerun-save",
            tmp_path / "run.rrd",
            "-q",
        ],
        [bin_dir / "qube-run", "--episodes", "1", "--duration", "2", "--seed", "2", "--out", held_out, "-q"],
        [bin_dir / "rerun", "rrd", "verify", tmp_path / "run.rrd"],
        # training and test logs apart: qube-identify refuses a log given as both
        [
            bin_dir / "qube-identify",
            "--train",
            logs,
            "--test",
            held_out,
            "--delays",
            "2",
            "--out",
            tmp_path / "model",
            "--rerun-save",
            tmp_path / "id.rrd",
        ],
        [bin_dir / "qube-export", logs, "--format", "parquet", "--out", tmp_path / "pq", "-q"],
        [bin_dir / "qube-export", logs, "--format", "mat", "--out", tmp_path / "mat", "-q"],
    ]
    for step in steps:
        done = _run(step, tmp_path)
        assert done.returncode == 0, f"{Path(step[0]).name}: {done.stdout[-2000:]}{done.stderr[-2000:]}"
    file, name = SMOKE_DESELECTED.split("::")
    assert f"def {name}(" in (ROOT / file).read_text()  # a renamed test would be deselected silently
    # A subset of the tests that reaches every dependency (run from the sources), in this process: the
    # suite's other worker keeps the second core busy, and two workers of its own each imported it all.
    tests = _run(
        [
            python,
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:cacheprovider",
            "-n",
            "0",
            *SMOKE_TESTS,
            "--deselect",
            SMOKE_DESELECTED,
        ],
        ROOT,
    )
    assert tests.returncode == 0, tests.stdout[-4000:] + tests.stderr[-2000:]


@pytest.mark.slow
@pytest.mark.network
def test_the_wheel_builds_without_deprecation_warnings_and_carries_the_licence(built_wheel):
    wheel, built = built_wheel
    assert "deprecat" not in (built.stdout + built.stderr).lower()
    import zipfile

    with zipfile.ZipFile(wheel) as archive:
        metadata = archive.read(next(n for n in archive.namelist() if n.endswith(".dist-info/METADATA"))).decode()
        licence = [n for n in archive.namelist() if n.endswith("licenses/LICENSE")]
        assert licence and archive.read(licence[0]).decode().startswith("MIT License")
    assert "License-Expression: MIT" in metadata.splitlines()
