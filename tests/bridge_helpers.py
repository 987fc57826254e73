"""Shared by the emulated-bridge and serial-backend tests: the firmware core, subprocesses, a fake device."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import tty
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
