"""Shared by the emulated-bridge and serial-backend tests: the firmware core, subprocesses, a fake device."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import tty
import warnings
from pathlib import Path

import pytest

from qube_koopman.firmware_protocol import StreamDecoder, ccore

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def cache_home(tmp_path_factory) -> Path:
    """An XDG cache folder holding the built firmware core, so subprocesses do not rebuild it."""
    if ccore.find_c_compiler() is None:
        pytest.skip("no C compiler found (set $CC or install gcc/clang): the emulated bridge cannot run")
    home = tmp_path_factory.mktemp("xdg_cache")
    ccore.cached_library(home / "qube-koopman")
    return home


@pytest.fixture(scope="session")
def core(cache_home) -> ccore.CCore:
    """The firmware core, loaded once per session."""
    return ccore.CCore(ccore.cached_library(cache_home / "qube-koopman"))


@pytest.fixture(scope="session")
def env(cache_home) -> dict:
    """Environment for subprocesses: this checkout first on the path, the session's core cache."""
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
                XDG_CACHE_HOME=str(cache_home))


def start_emulator(env: dict, *args: str) -> tuple[subprocess.Popen, str]:
    """``qube-emulate ARGS`` in a subprocess; returns it and the device path it printed first."""
    proc = subprocess.Popen([sys.executable, "-m", "qube_koopman.sim.cli.emulate", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    path = proc.stdout.readline().strip()
    if not path.startswith("/dev/"):
        proc.kill()
        raise AssertionError(f"qube-emulate printed {path!r}: {proc.communicate()[1]}")
    return proc, path


def stop_process(proc: subprocess.Popen, timeout: float = 10.0) -> tuple[str, str]:
    """SIGTERM (this test's own child, by its pid) and collect its output."""
    if proc.poll() is None:
        proc.terminate()
    try:
        return proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.communicate()


def _lost_to_stalls(folder: Path) -> list[str]:
    """What the logs in ``folder`` measured of each episode lost to a scheduler stall.

    A host stalled past the bridge's watchdog (10 ms) loses its episode to the watchdog; a
    stalled emulator process, to link loss. Either counts as a stall only when the host's own
    log measured ticks more than 2 ms late (``timing.stalls``); then its worst lateness is given.
    """
    from qube_koopman.daq.log import read_episode

    lost = []
    for f in sorted(folder.glob("*.mcap")):
        meta = read_episode(f).metadata
        reason = meta.status_reason
        if meta.status != "complete" and ("watchdog" in reason or "link lost: no telemetry" in reason) \
                and (meta.timing.get("stalls") or 0) > 0:
            lost.append(f"{meta.timing['stalls']} late ticks, worst {meta.timing['lateness_max'] * 1e3:.1f} ms "
                        f"({reason.split(':')[1].strip()})")
    return lost


def run_in_real_time(env: dict, emulator_args: list[str], run_args: list[str], tmp_path: Path,
                     capsys) -> tuple[int, str, str, Path, str]:
    """``qube-run --backend serial RUN_ARGS`` against ``qube-emulate EMULATOR_ARGS``, in real time.

    Real time on a shared machine: a host the scheduler stalls past the bridge's watchdog loses
    its episode. Such a run (the stall measured in its own log) is tried again, at most twice,
    and reported; three lost to measured stalls skip (the machine gave no real time to test);
    any other failure is returned at once for the test to fail on. A 200 ms link timeout: an
    emulator process held up pauses device time (then catches up; nothing is lost), which the
    default 25 ms would take for a lost link. Returns the exit status, qube-run's stdout, the
    emulator's stderr, the log folder and the device path.
    """
    from qube_koopman.daq.cli.run import main

    measured = []
    for attempt in range(3):
        out_dir = tmp_path / f"attempt{attempt}"
        proc, path = start_emulator(env, *emulator_args)
        try:
            status = main(["--backend", "serial", "--port", path, *run_args, "--out", str(out_dir),
                           "--link-timeout", "200", "-q"])
        finally:
            _, emulator_err = stop_process(proc)
        out = capsys.readouterr().out
        stalls = _lost_to_stalls(out_dir) if status != 0 else []
        if not stalls:
            break
        measured += stalls
    report = "; ".join(measured)
    if stalls:  # the last attempt was lost to a stall too
        pytest.skip(f"three runs lost to measured scheduler stalls: {report}")
    if measured:
        warnings.warn(f"runs lost to measured scheduler stalls, tried again: {report}")
    return status, out, emulator_err, out_dir, path


class FakeDevice:
    """A pseudo-terminal answering each frame the host sends with ``respond(frame)`` bytes.

    For bridges that misbehave in ways the real firmware core cannot be made to.
    """

    def __init__(self, respond) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self._respond = respond
        self._stop = threading.Event()
        self.received: list = []
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import select

        decoder = StreamDecoder()
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.02)
            if not ready:
                continue
            try:
                data = os.read(self.master, 4096)
            except OSError:
                return
            for frame in decoder.feed(data):
                self.received.append(frame)
                out = self._respond(frame)
                if out:
                    os.write(self.master, out)

    def wait_for(self, predicate, timeout: float = 2.0) -> list:
        """The frames received, once ``predicate(frames)`` holds (a failure after ``timeout``)."""
        import time

        deadline = time.monotonic() + timeout
        while not predicate(list(self.received)):
            assert time.monotonic() < deadline, f"the fake device got only {self.received}"
            time.sleep(0.005)
        return list(self.received)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        os.close(self.master)
        os.close(self.slave)

    def __enter__(self) -> "FakeDevice":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
