"""Running a console script in-process with its long work stubbed, in a folder of inputs: shared by
the argument fuzzing (tests/core/test_argument_fuzzing.py) and the output rule
(tests/core/test_output_rule.py). The fixtures ``template`` and ``stubs`` are registered for the
suite in tests/conftest.py."""

from __future__ import annotations

import contextlib
import importlib
import io
import os
import tomllib
import traceback
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


class Reached(BaseException):
    """The command got past its arguments to long work, which the harness does not run."""


def commands() -> dict[str, str]:
    """Every console script: name -> "module:function"."""
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> Path:
    """Files every example starts from: junk, folders, two real 2 s episode logs, a legacy CSV."""
    from _legacy_csv import GAINS_TOML, GOOD, write_synthetic_csv

    from qube_koopman.daq.backends import SimBackend
    from qube_koopman.daq.session import excitation_settings, plan_episodes, run_episodes, run_seeds
    from qube_koopman.core.controller_file import load_controller
    from qube_koopman.daq.sinks import McapSink

    root = tmp_path_factory.mktemp("fuzz_template")
    (root / "empty.txt").touch()
    (root / "junk.bin").write_bytes(b"\x7fELF\x02\x01\x01\x00\xff\xfe" + bytes(range(256)) * 4)
    (root / "folder").mkdir()
    (root / "csv").mkdir()
    (root / "csv" / "controller.toml").write_text(GAINS_TOML)
    write_synthetic_csv(root / "csv" / f"{GOOD}.csv")
    (root / "logs").mkdir()
    rate = 500.0
    seeds, backend_seed = run_seeds(1, 2)
    plans = plan_episodes(
        load_controller(None, "backward-euler", 1 / rate), seeds, excitation_settings(2.0, rate), source="fuzz"
    )
    sink = McapSink(root / "logs")
    run_episodes(SimBackend(seed=backend_seed, dt=1 / rate), plans, [sink])
    for path, name in zip(sink.paths, ("a", "b")):
        path.rename(root / "logs" / f"{name}.mcap")
    return root


@pytest.fixture(scope="module")
def stubs():
    """Replace each command's long work by :class:`Reached` (see tests/core/test_argument_fuzzing.py's docstring)."""
    import math

    from qube_koopman.daq.cli import run
    from qube_koopman.identify import calibrate
    from qube_koopman.identify.model_selection import distributed, search, transfer
    from qube_koopman.identify._checks import check_alpha
    from qube_koopman.reproduce import duffing_study
    from qube_koopman.sim.bridge import BridgeEmulator, avr_pty

    def reached(*args, **kwargs):
        raise Reached

    real_collect = run._collect

    def collect(args, backend, plans, settings, *rest):
        short = args.episodes * args.duration <= 2 and not args.realtime and args.rerun is None
        if short and args.rt_cpu is None and args.rt_priority is None:
            return real_collect(args, backend, plans, settings, *rest)
        raise Reached

    def reproduce_duffing(seed, alpha):
        import numpy as np

        check_alpha(alpha)  # what the library requires of the command's values
        np.random.default_rng(seed)
        assert math.isfinite(alpha)
        raise Reached

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(run, "_collect", collect)
        mp.setattr(BridgeEmulator, "open", reached)
        mp.setattr(avr_pty.AvrPtyBridge, "open", reached)
        mp.setattr(calibrate.PlantCalibration, "fit", reached)
        mp.setattr(duffing_study, "reproduce_duffing", reproduce_duffing)
        mp.setattr(transfer, "twin_probes", lambda *a, **k: None)
        mp.setattr(search, "search_liftings", reached)
        mp.setattr(distributed, "connect", reached)  # --scheduler: no waiting for a scheduler's answer
        yield


def run_in_process(command: str, argv: list[str], folder: Path) -> tuple[int | str, str]:
    """``command``'s ``main(argv)`` in ``folder``: (exit status, or "reached"; stderr)."""
    target = commands()[command]
    module_name, function = target.split(":")
    main = getattr(importlib.import_module(module_name), function)
    err, out = io.StringIO(), io.StringIO()
    cwd = os.getcwd()
    os.chdir(folder)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            try:
                status = main(argv)
            except SystemExit as exc:
                status = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
            except Reached:
                status = "reached"
            except Exception:  # the failure this test is for
                traceback.print_exc(file=err)
                status = "traceback"
    finally:
        os.chdir(cwd)
    return status, err.getvalue()
