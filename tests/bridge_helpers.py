"""Shared by the emulated-bridge and serial-backend tests: the firmware core, subprocesses, a fake device."""

from __future__ import annotations

import os
import re
import shutil
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
    return dict(
        os.environ,
        PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
        XDG_CACHE_HOME=str(cache_home),
    )


#: SCHED_FIFO priority of the real-time tests' emulator and loop thread, where the machine grants
#: it (root or CAP_SYS_NICE, as in CI): what a user does on a busy machine (``qube-run
#: --rt-priority``), so two CPU burners beside the suite do not take its real time away.
RT_PRIORITY = 20


def fifo_granted() -> bool:
    """Whether this process may run SCHED_FIFO (tried on this thread and undone)."""
    try:
        saved = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except (AttributeError, OSError):
        return False
    os.sched_setscheduler(0, *saved)
    return True


def granted_rt_priority() -> int | None:
    """:data:`RT_PRIORITY` where SCHED_FIFO is granted and ``chrt`` is on the path, else None."""
    return RT_PRIORITY if fifo_granted() and shutil.which("chrt") else None


def fifo_command(command: list, rt_priority: int | None) -> list:
    """``command`` under ``chrt --fifo rt_priority`` (every thread inherits it), or as it is with None."""
    return command if rt_priority is None else ["chrt", "--fifo", str(rt_priority), *command]


def start_emulator(env: dict, *args: str, rt_priority: int | None = None) -> tuple[subprocess.Popen, str]:
    """``qube-emulate ARGS`` in a subprocess; returns it and the device path it printed first.

    With ``rt_priority`` it runs SCHED_FIFO at that priority (through ``chrt``, so every thread of
    it inherits the policy from its start).
    """
    command = fifo_command([sys.executable, "-m", "qube_koopman.sim.cli.emulate", *args], rt_priority)
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
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


def _emulator_behind_ms(emulator_err: str) -> float:
    """How far the emulated bridge fell behind the wall clock by its own clock, as ``qube-emulate`` reports it
    when it stops: ``--target avr`` its chip's worst lag, the emulated core its ticks' worst lateness
    against their deadlines (a process held up past the watchdog shows there, not in the host's log)."""
    found = re.search(r"at most ([0-9.]+) ms behind the wall clock|max lateness ([0-9.]+) ms", emulator_err)
    return float(found.group(1) or found.group(2)) if found else 0.0


def _lost_to_stalls(folder: Path, emulator_err: str, run_out: str = "") -> list[str]:
    """What was measured of each episode in ``folder`` lost to a scheduler stall, and of one lost before its
    start (``run_out``, qube-run's output: an episode lost during its swing-up leaves no log).

    A host stalled past the bridge's watchdog (10 ms) loses its episode to the watchdog; a
    stalled emulator process, to link loss or, once the emulated chip catches up on the time
    it lost, to the watchdog. Either counts as a stall only when it was measured: ticks more
    than 2 ms late in the host's own log (``timing.stalls``), a tick whose work the host's log
    measured at more than 2 ms (``timing.compute_max``; a tick's work takes about 0.2 ms at its
    99th percentile: the process was held up inside it, which leaves the next tick on time but
    the bridge without a command for as long), the emulated bridge (the chip, or the emulated
    core's ticks) more than half the watchdog (5 ms) behind the wall clock by its own report (a
    quiet machine: under 4 ms), or, the host on time by its own log, commands the bridge itself
    reports arriving after the tick they were sent for (``late_commands``: each command carries the
    tick it answers, so the bridge measures this; held up between the two processes, in the
    pseudo-terminal or the emulator's reading thread, as a loaded suite once saw: 6 late commands
    and a tripped watchdog with the host's worst tick 1.6 ms late); the worst lateness or work is given.
    An episode lost before its start has no log, nor the host's timing: the emulated bridge behind, or
    the late commands the bridge reported in the run's summary (``serial link: ... N commands late``),
    count as measured there.
    """
    from qube_koopman.daq.log import read_episode

    behind = _emulator_behind_ms(emulator_err)
    lost = []
    for f in sorted(folder.glob("*.mcap")):
        meta = read_episode(f).metadata
        reason = meta.status_reason
        if meta.status == "complete" or not ("watchdog" in reason or "link lost: no telemetry" in reason):
            continue
        cause = reason.split(":")[1].strip()
        if (meta.timing.get("stalls") or 0) > 0:
            lost.append(
                f"{meta.timing['stalls']} late ticks, worst {meta.timing['lateness_max'] * 1e3:.1f} ms ({cause})"
            )
        elif (meta.timing.get("compute_max") or 0.0) > 2e-3:
            lost.append(f"a tick's work held up {meta.timing['compute_max'] * 1e3:.1f} ms ({cause})")
        elif behind > 5.0:
            lost.append(f"the emulated bridge up to {behind:.1f} ms behind the wall clock ({cause})")
        elif (meta.backend_stats or {}).get("late_commands", 0) > 0:
            late = meta.backend_stats["late_commands"]
            lost.append(f"{late} commands reached the bridge after their tick, the host on time ({cause})")
    before = re.search(r"backend fault before the start: (bridge watchdog tripped|link lost: no telemetry)", run_out)
    late_commands = re.search(r"(\d+) commands late", run_out)
    if before is not None:
        if behind > 5.0:
            lost.append(
                f"the emulated bridge up to {behind:.1f} ms behind the wall clock ({before[1]}, before the start)"
            )
        elif late_commands is not None and int(late_commands[1]) > 0:
            lost.append(
                f"{late_commands[1]} commands reached the bridge after their tick ({before[1]}, before the start)"
            )
    return lost


def await_bridge_ticks(path: str, frames: int = 2, timeout: float = 10.0) -> int:
    """Wait until the bridge behind ``path`` has sent ``frames`` frames since this call; returns how many came.

    After ``qube-run`` has left the port, a test that stops the emulator at once may stop it
    before it ticks on what the host last sent (its 0 V), on a loaded machine: the record then
    ends at the tick before. The bridge keeps ticking (in lockstep, one tick per lockstep
    timeout with no host); what was buffered before this call is flushed, and the second fresh
    frame comes from a tick that started after the first was written, so after the host left.
    Returns early (fewer frames) where the port cannot be opened or nothing comes in time: the
    caller's own assertions decide then.
    """
    import select
    import termios
    import time

    try:
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError:
        return 0
    try:
        tty.setraw(fd)
        termios.tcflush(fd, termios.TCIFLUSH)
        decoder, seen = StreamDecoder(), 0
        deadline = time.monotonic() + timeout
        while seen < frames and (left := deadline - time.monotonic()) > 0:
            if select.select([fd], [], [], left)[0]:
                try:
                    seen += len(decoder.feed(os.read(fd, 4096)))
                except BlockingIOError:
                    continue
        return seen
    finally:
        os.close(fd)


def await_emulator_ticks(emu, ticks: int, limit: float = 30.0, poll: float = 0.002) -> None:
    """Wait until the in-process ``emu`` has ticked ``ticks`` more times than now, or stopped running.

    Watched on the bridge's own count, not guessed in wall time; ``limit`` (s) only guards against a
    hang, and the caller's assertions decide then.
    """
    import time

    target, deadline = emu.stats()["ticks"] + ticks, time.monotonic() + limit
    while emu.stats()["ticks"] < target and emu.running and time.monotonic() < deadline:
        time.sleep(poll)


def run_in_real_time(
    env: dict, emulator_args: list[str], run_args: list[str], tmp_path: Path, capsys
) -> tuple[int, str, str, Path, str]:
    """``qube-run --backend serial RUN_ARGS`` against ``qube-emulate EMULATOR_ARGS``, in real time.

    Real time on a shared machine: where SCHED_FIFO is granted, the emulator and qube-run's loop
    run at ``RT_PRIORITY`` (``--rt-priority``). Elsewhere a host the scheduler stalls past the
    bridge's watchdog loses its episode. Such a run (the stall measured in its own log) is tried
    again, at most twice, and reported; three lost to measured stalls skip (the machine gave no
    real time to test); any other failure is returned at once for the test to fail on. A 200 ms
    link timeout: an emulator process held up pauses device time (then catches up; nothing is
    lost), which the default 25 ms would take for a lost link. Returns the exit status,
    qube-run's stdout, the emulator's stderr, the log folder and the device path.
    """
    from qube_koopman.daq.cli.run import main

    rt = granted_rt_priority()
    rt_args = ["--rt-priority", str(rt)] if rt is not None else []
    measured = []
    for attempt in range(3):
        out_dir = tmp_path / f"attempt{attempt}"
        proc, path = start_emulator(env, *emulator_args, rt_priority=rt)
        try:
            status = main(
                [
                    "--backend",
                    "serial",
                    "--port",
                    path,
                    *run_args,
                    "--out",
                    str(out_dir),
                    "--link-timeout",
                    "200",
                    "-q",
                    *rt_args,
                ]
            )
            await_bridge_ticks(path)  # the bridge has ticked on what qube-run sent last
        finally:
            _, emulator_err = stop_process(proc)
        out = capsys.readouterr().out
        stalls = _lost_to_stalls(out_dir, emulator_err, out) if status != 0 else []
        if not stalls:
            break
        measured += stalls
    report = "; ".join(measured)
    how = f"SCHED_FIFO {rt}" if rt is not None else "normal priority, SCHED_FIFO not granted"
    if stalls:  # the last attempt was lost to a stall too
        pytest.skip(f"three runs lost to measured scheduler stalls ({how}): {report}")
    if measured:
        warnings.warn(f"runs lost to measured scheduler stalls ({how}), tried again: {report}", stacklevel=2)
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


# --- lockstep that a loaded machine cannot break ------------------------------------------------


class HostWait:
    """The time a test host has spent waiting on the bridge's port with nothing to read, nor coming.

    The clock a lockstep :class:`~sim.bridge.BridgeEmulator` measures its ``lockstep_timeout`` on in
    these tests (``lockstep_clock=wait``). A read of the port that came back empty adds the port's
    read timeout, however long the machine held the host, and only when the host has read every
    byte the bridge sent and the bridge has read every byte the host sent (a pseudo-terminal hands
    bytes on a moment later, longer on a loaded machine: an empty read then is not a lost frame). So
    the clock does not move while the host
    is held up (between a read and its answer, or in the middle of a read), nor while the bridge's
    bytes are on their way; only while the host runs and waits for a frame that will not come.
    The bridge then ticks unanswered only for a lost frame (or a host that does not answer that
    tick, as at its start gate), never ahead of a host the machine was slow to run; and the host's
    link timeout, measured on the bridge's device clock (:func:`device_clock`), runs out only after
    that many ticks' telemetry never arrived.
    """

    def __init__(self) -> None:
        self.waited = 0.0
        self.port = None
        self.written = 0  # bytes the host wrote to the port (see wrote)

    def wrote(self, n: int) -> None:
        """The host wrote ``n`` bytes (counted by :meth:`watch` for ``port.write``)."""
        self.written += n

    def __call__(self) -> float:
        return self.waited

    def watch(self, port, emu) -> None:
        """Count ``port``'s empty reads (a pyserial port with a read timeout) against ``emu``'s output."""
        read, reset, write = port.read, port.reset_input_buffer, port.write
        self.port = port
        got = [0, 0]  # bytes the host read, bytes the bridge had sent before them (since the last reset)
        taken = emu.stats()["bytes_in"] - self.written  # the bridge's count when this host had written 0

        def sent() -> int:
            stats = emu.stats()
            return stats["bytes_out"] - stats["bytes_discarded"]

        def counted(size: int = 1) -> bytes:
            data = read(size)
            got[0] += len(data)
            if not data and got[0] >= sent() - got[1] and emu.stats()["bytes_in"] - taken >= self.written:
                self.waited += port.timeout
            return data

        def writes(data) -> int | None:
            self.wrote(len(data))
            return write(data)

        def resets() -> None:
            reset()
            got[:] = [0, sent()]  # what the bridge sent until now was dropped, or is read on top: never owed

        port.read, port.reset_input_buffer, port.write = counted, resets, writes
        got[1] = sent() - port.in_waiting

    def hold(self, emu, ticks: int, limit: float = 60.0) -> None:
        """The host is held while the bridge ticks ``ticks`` times on its own (a slow log open, a stall).

        Each tick is let through by one lockstep timeout of waiting. Then, until every byte the bridge
        sent meanwhile can be read from the host's port (a pseudo-terminal hands them on a moment
        later): the host, released, must find the newest telemetry there, as after a real pause,
        not answer an older one. ``limit`` seconds of wall time is only a guard against a bridge
        that stopped (a failure), never reached by a working one.
        """
        import time

        deadline = time.monotonic() + limit

        def until(done, what):
            while not done():
                assert emu.running and time.monotonic() < deadline, what
                time.sleep(0.001)

        queued, sent = self.port.in_waiting if self.port is not None else 0, emu.stats()["bytes_out"]
        for _ in range(ticks):
            ticked = emu.stats()["ticks"]
            self.waited += emu.lockstep_timeout
            until(lambda ticked=ticked: emu.stats()["ticks"] > ticked, "the bridge stopped ticking")
        if self.port is not None:
            arrived = queued + emu.stats()["bytes_out"] - sent
            until(lambda: self.port.in_waiting >= arrived, "the bridge's bytes never reached the host")


def device_clock(emu):
    """The emulator's device clock (s) for a host's timeouts; infinite once its device is gone or it failed.

    Device time advances only as the bridge ticks and each tick sends telemetry, so a timeout on it
    runs out only when that many ticks' telemetry never reached the host, however slowly the machine
    ran either of them. A bridge that stopped ticking would freeze it: infinity then ends the wait.
    """
    import math

    return lambda: emu.device_time if emu.running and emu.error is None else math.inf


def lockstep_backend(emu, wait: HostWait, backend_cls=None, **kwargs):
    """A serial backend on ``emu``'s port whose timeouts run on the device clock and whose waits move ``wait``."""
    from qube_koopman.daq.backends.serial import SerialBackend

    backend = (backend_cls or SerialBackend)(emu.path, clock=device_clock(emu), **kwargs)
    open_port = backend._open_port

    def watched():
        port = open_port()
        wait.watch(port, emu)
        return port

    backend._open_port = watched
    write_fd = backend._write_fd  # the backend's writes that do not go through port.write

    def counted(fd, frame):
        wait.wrote(len(frame))
        return write_fd(fd, frame)

    backend._write_fd = counted
    return backend
