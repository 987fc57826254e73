"""The emulated bridge: the firmware core on a pseudo-terminal, driving the simulated QUBE.

:class:`BridgeEmulator` owns the master side of a pseudo-terminal; its slave
side (``emulator.path``, e.g. ``/dev/pts/3``) is the "device" a host opens
with pyserial as it would open the bridge's USB serial port. Inside, the
bridge firmware's own core (``firmware_protocol/c/src``, compiled and loaded
through ``firmware_protocol.ccore``) runs as on the microcontroller: host
bytes go in, and at every tick it does one SPI transfer, here with an
:class:`~sim.bridge.emulated_qube.EmulatedQube`, and queues telemetry for the host.

Time. Device time advances one period per tick (2 ms at 500 Hz) and is what
the firmware core and the pendulum see; frames carry it as their timestamp.
Ticks are paced in one of two ways:

- real time (default): absolute wall-clock deadlines, reached by sleeping
  in ``select`` on the pty (so host bytes are taken as they arrive) and
  spinning the last ``spin`` seconds. Ticks that fall up to three periods
  behind (the emulator's process was not scheduled) are caught up back to
  back, as by a bridge whose clock was right but whose output was held up:
  device time stays with the wall clock (``stats()["late_ticks"]``). A
  longer stall restarts the schedule instead, as the firmware sketch does,
  so that a burst cannot trip the watchdog by itself; device time then
  pauses for the lost periods (``stats()["slips"]``).
- lockstep: once a session is open, the next tick comes as soon as the host
  has answered the last telemetry (any valid frame; normally its command),
  or after ``lockstep_timeout`` of wall time without an answer: a host does
  not answer every tick (an acquisition loop sends nothing on the tick its
  start gate opens), so the timeout must stay below the host's link timeout.
  As long as the host answers within it, the run does not depend on
  scheduling noise, and it goes faster than real time; for tests.
  ``lockstep_clock`` measures that timeout on another clock than the wall's:
  a test host in the same process passes the time it has spent waiting on
  the port with nothing to read, so that the bridge ticks unanswered only
  while the host waits for it (a lost frame), never because a loaded
  machine held the host up between its read and its answer.

Each HELLO (a host opening a session) puts the pendulum back upright at
rest with a seeded perturbation of alpha, as a person raises the real one by
hand, so that ``qube-run`` passes its start gate: at once, or carried up from
hanging over ``raise_time`` seconds of device time (the host's start gate
then holds the motor at 0 V meanwhile, as on the rig). Faults are injected as
:class:`~sim.bridge.faults.Faults` asks.
"""

from __future__ import annotations

import errno
import dataclasses
import math
import os
import random
import select
import threading
import time
import tty
from collections import deque
from typing import TYPE_CHECKING, Callable

import numpy as np

from qube_koopman.firmware_protocol import Capability, Command, Hello, StreamDecoder
from qube_koopman.sim.bridge.faults import DelayLine, Faults, FaultyLink
from qube_koopman.sim.bridge.emulated_qube import EmulatedQube
from qube_koopman.sim.pendulum import PendulumParameters

if TYPE_CHECKING:
    from qube_koopman.firmware_protocol.ccore import CDevice
    from qube_koopman.sim.pendulum.load import RandomLoad
    from qube_koopman.sim.pendulum.relaxation import CableRelaxation

__all__ = ["BridgeEmulator", "DEFAULT_PERTURBATION", "DEFAULT_SPIN", "RECORD_FIELDS"]

#: Largest initial ``|alpha|`` (rad) at each session start: well inside the 5 deg start gate.
DEFAULT_PERTURBATION = math.radians(2.0)

#: Spin this long before each tick deadline (s): covers the usual sleep overshoot.
DEFAULT_SPIN = 300e-6

#: Per-tick record kept when ``record_ticks > 0`` (see :meth:`BridgeEmulator.record`).
RECORD_FIELDS = (
    "device_us",
    "wall",
    "lateness",
    "volts",
    "amp_enabled",
    "command_seq",
    "command_mv",
    "session",
    "answer",
)

# Output waiting for a host that does not read is dropped beyond this (bytes),
# as a real USB serial link drops what nobody collects.
_MAX_PENDING = 4096
# Longest select() timeout (s), so a stop request is seen promptly.
_POLL = 0.05
# Periods a late emulator catches up back to back; beyond, it restarts its schedule.
# Below the default watchdog (5): a burst alone must not trip it.
_MAX_BURST = 3
# Lockstep on a clock of the caller's: how often (s) it is looked at while no host bytes come.
_LOCKSTEP_SLICE = 0.001


def open_raw_pty() -> tuple[int, int, str]:
    """A pseudo-terminal for an emulated device: (master fd, slave fd, device path)."""
    master, slave = os.openpty()
    # Raw on both ends: no echo, no newline translation, every byte as sent.
    tty.setraw(master)
    tty.setraw(slave)
    os.set_blocking(master, False)
    # The slave stays open here too: with no slave open the master reads
    # EIO, and a host closing the port must not look like one.
    return master, slave, os.ttyname(slave)


def close_fds(fds) -> None:
    """Close file descriptors in order, skipping -1 and ignoring errors (the other end may be gone)."""
    for fd in fds:
        if fd >= 0:
            try:
                os.close(fd)
            except OSError:
                pass


class BridgeEmulator:
    """The bridge firmware and a simulated QUBE-Servo 2 behind a pseudo-terminal.

    Parameters
    ----------
    seed : int, optional
        Seeds the start perturbations and every injected fault; None draws
        one (``seed`` then holds it, so the run can be repeated).
    lockstep : bool
        Tick when the host has answered instead of by the wall clock (see
        the module docstring).
    lockstep_timeout : float
        In lockstep, tick anyway after this many seconds without an answer
        (keep it below the host's link timeout, 25 ms for the serial backend).
    lockstep_clock : callable, optional
        The clock ``lockstep_timeout`` is measured on (s, any origin); by
        default the wall clock. Tests pass the time their host has spent
        waiting for telemetry (see the module docstring).
    perturbation : float
        Each session starts at rest with alpha uniform in
        ``[-perturbation, perturbation]`` (rad); with ``start_upright`` False
        the first session starts at rest that far from hanging straight down.
    start_upright : bool
        Raise the pendulum at each HELLO; False leaves it hanging, as after
        power-up (the host's start gate then waits in vain): at the first
        HELLO at rest within ``perturbation`` of straight down (the counters
        still zero straight down), later ones wherever the pendulum is (as
        on the rig after an episode: falling, or swinging).
    raise_time : float
        Seconds of device time the raising takes (0: at once). Meanwhile
        the pendulum follows the hand, whatever the motor does.
    faults : Faults
        What to break.
    params : PendulumParameters
        Physical model of the pendulum.
    load : RandomLoad, optional
        A random torque on the arm (a plant file's ``[load]``), a new draw at each session's
        start (seeded from ``seed``); None: none, every draw as without one.
    relaxation : CableRelaxation, optional
        The cables' torque that the arm's motion drives (a plant file's ``[relaxation]``); None: none.
    spin : float
        Real time: spin this long before each deadline (s); 0 sleeps only
        (less CPU, more jitter).
    record_ticks : int
        Keep a record of the last this many ticks (0: none).
    core : firmware_protocol.ccore.CCore, optional
        A loaded firmware core; by default it is built (or reused) in the
        cache by ``firmware_protocol.ccore.cached_library`` when opened.
    """

    def __init__(
        self,
        *,
        seed: int | None = None,
        lockstep: bool = False,
        lockstep_timeout: float = 0.01,
        lockstep_clock: Callable[[], float] | None = None,
        perturbation: float = DEFAULT_PERTURBATION,
        start_upright: bool = True,
        raise_time: float = 0.0,
        faults: Faults = Faults(),
        params: PendulumParameters = PendulumParameters(),
        load: RandomLoad | None = None,
        relaxation: CableRelaxation | None = None,
        spin: float = DEFAULT_SPIN,
        record_ticks: int = 0,
        core=None,
    ) -> None:
        if not (math.isfinite(perturbation) and 0 <= perturbation < math.pi / 2):
            raise ValueError(f"perturbation must be an angle in [0, pi/2) rad, got {perturbation!r}")
        if not (math.isfinite(lockstep_timeout) and lockstep_timeout > 0):
            raise ValueError(f"lockstep_timeout must be a positive number of s, got {lockstep_timeout!r}")
        if not (math.isfinite(raise_time) and 0 <= raise_time <= 60):
            raise ValueError(f"raise_time must be in [0, 60] s, got {raise_time!r}")
        if not (math.isfinite(spin) and 0 <= spin < 0.002):
            raise ValueError(f"spin must be in [0, 2 ms), got {spin!r}")
        if not isinstance(faults, Faults):
            raise TypeError(f"faults must be a Faults, got {type(faults).__name__}")
        sequence = np.random.SeedSequence(seed)
        if seed is None:
            assert isinstance(sequence.entropy, int)  # drawn from the OS: one int
            seed = sequence.entropy
        self.seed = seed
        pose_seq, link_seq, load_seq = sequence.spawn(3)  # (the first two as when there were two)
        self._pose_rng = np.random.default_rng(pose_seq)
        self._load_rng = np.random.default_rng(load_seq)
        self._link = FaultyLink(faults, random.Random(int(link_seq.generate_state(1)[0])))
        self.lockstep = bool(lockstep)
        self.lockstep_timeout = float(lockstep_timeout)
        self.lockstep_clock = lockstep_clock
        self.perturbation = float(perturbation)
        self.start_upright = bool(start_upright)
        self.raise_time = float(raise_time)
        self._raising: tuple[int, int, float] | None = None  # ticks done, ticks in all, final alpha
        self.faults = faults
        self.params = params
        self.load = load
        self.relaxation = relaxation
        self.spin = float(spin)
        self._core = core
        self._record: deque | None = deque(maxlen=int(record_ticks)) if record_ticks > 0 else None
        self._in_delay = DelayLine(faults.latency) if faults.latency > 0 else None
        self._out_delay = DelayLine(faults.latency) if faults.latency > 0 else None
        self._mirror = StreamDecoder()
        self._inject: deque[bytes] = deque()
        self._pending = bytearray()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master = self._slave = -1
        self._dev: CDevice | None = None  # both made by open()
        self._qube: EmulatedQube | None = None
        self.path = ""
        self.error: BaseException | None = None
        self.events: list[tuple[int, float, str]] = []
        self.vanished_at: float | None = None
        # Device state seen from outside the core.
        self._device_us = 0
        self._last_tick_us = 0
        self._session = False
        self._awaiting = False
        self._raise_pending = False
        self._release_pending = False  # start_upright False: the first session's tilt about the bottom
        self._first_hello_us: int | None = None
        self._fired: set[str] = set()
        self._timed_faults = any(
            t is not None
            for t in (faults.stall_at, faults.amp_fault_at, faults.silence_at, faults.vanish_at, faults.hold_at)
        )
        self._silent = False
        self._command_seq = 0
        self._command_mv = 0
        self._last_row: list | None = None
        self.initial_states: list[tuple[float, float, float, float]] = []
        self._counts = dict(
            ticks=0,
            sessions=0,
            commands=0,
            late_ticks=0,
            slips=0,
            missed_periods=0,
            bytes_in=0,
            bytes_out=0,
            bytes_discarded=0,
            bytes_silenced=0,
        )
        self._max_lateness = 0.0

    # --- lifecycle -------------------------------------------------------------------------

    def open(self) -> str:
        """Build or load the firmware core, create the pseudo-terminal; returns the device path.

        Raises
        ------
        firmware_protocol.ccore.CompilerNotFound
            No C compiler to build the firmware core with.
        """
        if self._master >= 0:
            return self.path
        from qube_koopman.firmware_protocol import ccore

        core = self._core if self._core is not None else ccore.CCore(ccore.cached_library())
        self._dev = dev = ccore.CDevice(core, Capability.EMULATED)
        self._qube = qube = EmulatedQube(
            self.params, dt=dev.period_us * 1e-6, load=self.load, relaxation=self.relaxation
        )
        # Power-up: the pendulum hangs at rest, the counters read zero.
        qube.place((0.0, math.pi, 0.0, 0.0))
        self._master, self._slave, self.path = open_raw_pty()
        self._send(dev.take_output(), time.perf_counter())
        return self.path

    def start(self) -> str:
        """Open and run in a background thread; returns the device path."""
        path = self.open()
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run_caught, name="bridge-emulator", daemon=True)
            self._thread.start()
        return path

    def _run_caught(self) -> None:
        try:
            self.run()
        except BaseException as exc:  # noqa: BLE001 - kept for the owner of the thread, see stop()
            self.error = exc

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the thread started by :meth:`start` and close the device.

        Raises
        ------
        RuntimeError
            If the emulator's thread had failed (the cause is chained).
        """
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        self.close()
        if self.error is not None:
            raise RuntimeError(f"the bridge emulator failed: {self.error}") from self.error

    def request_stop(self) -> None:
        """Ask :meth:`run` to return (safe from a signal handler or another thread)."""
        self._stop.set()

    def close(self) -> None:
        """Close the pseudo-terminal (the device disappears)."""
        # Not running before the host can tell: closing the master is what it sees (EIO, and the
        # device node goes), so our own slave end goes first and the fds are forgotten before.
        fds = (self._slave, self._master)
        self._master = self._slave = -1
        close_fds(fds)

    def __enter__(self) -> "BridgeEmulator":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        """True while the device exists (not stopped, not vanished)."""
        return self._master >= 0 and not self._stop.is_set()

    def inject(self, data: bytes) -> None:
        """Send raw bytes to the host at the next tick, past the fault injection (tests)."""
        self._inject.append(bytes(data))

    # --- the loop --------------------------------------------------------------------------

    def run(self, stop: threading.Event | None = None) -> None:
        """Tick until stopped (or vanished), in the calling thread.

        Parameters
        ----------
        stop : threading.Event, optional
            Set it to return; :meth:`request_stop` sets the emulator's own.
        """
        self.open()
        assert self._dev is not None  # open() made it
        stop = stop if stop is not None else self._stop
        clock = time.perf_counter
        pace = self.lockstep_clock or clock
        deadline = clock()
        last_tick = pace()
        while not stop.is_set() and self._master >= 0:
            period = self._dev.period_us * 1e-6
            if self.lockstep and self._session:
                now, lateness = self._wait_answer(last_tick, stop), math.nan
            else:
                now, lateness = self._wait_deadline(deadline, stop)
            if stop.is_set():
                break
            self._tick(now, lateness)
            last_tick = pace()
            deadline += period
            if self.lockstep:
                deadline = now + period
            elif now >= deadline:
                behind = int(lateness / period)
                if behind <= _MAX_BURST:
                    self._counts["late_ticks"] += 1  # the next ones follow at once
                else:
                    self._counts["slips"] += 1
                    self._counts["missed_periods"] += behind
                    deadline = now + period

    def _wait_deadline(self, deadline: float, stop: threading.Event) -> tuple[float, float]:
        """Sleep in select, then spin to the deadline; host bytes are taken as they come."""
        clock = time.perf_counter
        master = self._master
        while not stop.is_set():
            now = clock()
            remaining = deadline - now
            if remaining <= 0:
                return now, now - deadline
            if remaining > self.spin:
                timeout = min(remaining - self.spin, self._next_release() - now, _POLL)
                ready, _, _ = select.select([master], [], [], max(timeout, 0.0))
                self._service(clock(), bool(ready))
            else:
                # Spin, still taking host bytes as they come (a poll is about a microsecond).
                while clock() < deadline:
                    if select.select([master], [], [], 0.0)[0]:
                        self._read_host(clock())
        return clock(), math.nan

    def _wait_answer(self, last_tick: float, stop: threading.Event) -> float:
        """Lockstep: wait until the host has answered the last telemetry, or the lockstep timeout.

        ``last_tick`` is the lockstep clock's reading at the last tick; the timeout is read anew
        each time (a test may change it while the emulator runs).
        """
        clock = time.perf_counter
        pace = self.lockstep_clock
        while self._awaiting and not stop.is_set():
            now = clock()
            if (pace() if pace is not None else now) >= last_tick + self.lockstep_timeout:
                break
            # On another clock than the wall's, its time cannot be slept to: look again soon.
            slice_ = _LOCKSTEP_SLICE if pace is not None else last_tick + self.lockstep_timeout - now
            timeout = min(slice_, self._next_release() - now, _POLL)
            ready, _, _ = select.select([self._master], [], [], max(timeout, 0.0))
            self._service(clock(), bool(ready))
        return clock()

    def _next_release(self) -> float:
        lines = [d.next_release for d in (self._in_delay, self._out_delay) if d is not None]
        return min(lines, default=math.inf)

    def _service(self, now: float, readable: bool) -> None:
        """Take the host's bytes, release delayed ones, push output."""
        if readable:
            self._read_host(now)
        if self._in_delay is not None:
            self._deliver(self._in_delay.take(now), now)
        if self._out_delay is not None:
            self._write(self._out_delay.take(now))
        self._flush()

    def _read_host(self, now: float) -> None:
        while True:
            try:
                data = os.read(self._master, 4096)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                if exc.errno == errno.EIO:  # no slave open: nothing to read
                    return
                raise
            if not data:
                return
            # Stamped when read: a caller's ``now`` may be a tick's start, before these bytes came.
            now = max(now, time.perf_counter())
            self._counts["bytes_in"] += len(data)
            data = self._link.incoming(data)
            if self._in_delay is not None:
                self._in_delay.put(now, data)
            else:
                self._deliver(data, now)

    def _deliver(self, data: bytes, now: float) -> None:
        """Host bytes reach the firmware core (and are watched on the way)."""
        if not data:
            return
        for frame in self._mirror.feed(data):
            message = frame.message
            # In lockstep any valid frame answers: the handshake's CONFIG too.
            self._awaiting = False
            if isinstance(message, Hello):
                self._session = True
                self._raise_pending = self.start_upright
                self._release_pending = not self.start_upright and self._counts["sessions"] == 0
                self._counts["sessions"] += 1
                if self._first_hello_us is None:
                    self._first_hello_us = self._device_us
                self.events.append((self._device_us, now, f"HELLO nonce {message.nonce}"))
            elif isinstance(message, Command) and self._session:
                self._command_seq, self._command_mv = frame.seq, message.millivolts
                self._counts["commands"] += 1
                row = self._last_row
                if row is not None and row[-1] != row[-1]:
                    row[-1] = now - row[1]  # the first answer to that tick
        # Frames answered between ticks carry the last tick's time.
        assert self._dev is not None  # bytes come only once open() made it
        self._dev.receive(data, self._last_tick_us)
        self._send(self._dev.take_output(), now)

    def _send(self, data: bytes, now: float) -> None:
        if not data:
            return
        if self._silent:
            self._counts["bytes_silenced"] += len(data)
            return
        data = self._link.outgoing(data)
        if self._out_delay is not None:
            self._out_delay.put(now, data)
        else:
            self._write(data)

    def _write(self, data: bytes) -> None:
        if data:
            self._pending += data
            self._counts["bytes_out"] += len(data)

    def _flush(self) -> None:
        pending = self._pending
        if not pending:
            return
        try:
            del pending[: os.write(self._master, pending)]
        except (BlockingIOError, InterruptedError):
            pass
        if len(pending) > _MAX_PENDING:
            self._counts["bytes_discarded"] += len(pending)
            pending.clear()

    def _tick(self, now: float, lateness: float) -> None:
        """One firmware tick: faults due, SPI transfer with the QUBE, telemetry out."""
        self._service(now, True)
        if self._timed_faults and self._first_hello_us is not None and self._fire_faults(now):
            return
        dev, qube = self._dev, self._qube
        assert dev is not None and qube is not None  # ticks run only after open() made them
        period_us = dev.period_us
        qube.set_period(period_us * 1e-6)
        if self._raise_pending:
            self._raise_pending = False
            alpha0 = float(self._pose_rng.uniform(-self.perturbation, self.perturbation))
            self._raising = (0, round(self.raise_time * 1e6 / period_us), alpha0)
        if self._release_pending:
            # Left hanging: at the first session it hangs at rest tilted by up to the perturbation
            # about the bottom (its counters still zero hanging straight down); later sessions find
            # it wherever the last one left it.
            self._release_pending = False
            tilt = float(self._pose_rng.uniform(-self.perturbation, self.perturbation))
            state = (0.0, math.pi + tilt, 0.0, 0.0)
            qube.place(state, load_seed=self._session_load_seed())
            self.initial_states.append(state)
        held = self._hand(qube)
        spi_rx = qube.transfer(dev.tick_begin(self._device_us))
        dev.tick_end(spi_rx)
        if not held:
            qube.advance()
        while self._inject:
            self._write(self._inject.popleft())
        self._send(dev.take_output(), now)
        self._service(now, False)
        if self._session:
            self._awaiting = True
        if lateness > self._max_lateness:
            self._max_lateness = lateness
        if self._record is not None:
            self._last_row = [
                self._device_us,
                now,
                lateness,
                qube.volts,
                qube.enabled,
                self._command_seq,
                self._command_mv,
                self._counts["sessions"],
                math.nan,
            ]
            self._record.append(self._last_row)
        self._counts["ticks"] += 1
        self._last_tick_us = self._device_us
        self._device_us += period_us

    def _session_load_seed(self) -> int | None:
        """A new session's load seed (None without a load: no draw)."""
        return None if self.load is None else int(self._load_rng.integers(2**63))

    def _hand(self, qube: EmulatedQube) -> bool:
        """Carry the pendulum from hanging to its start tilt; True while it is held."""
        if self._raising is None:
            return False
        done, total, alpha0 = self._raising
        if done >= total:
            self._raising = None
            state = (0.0, alpha0, 0.0, 0.0)
            qube.place(state, load_seed=self._session_load_seed())
            self.initial_states.append(state)
            return False
        s = done / total
        s = s * s * (3.0 - 2.0 * s)  # eased, as a hand moves
        qube.place((0.0, math.pi + (alpha0 - math.pi) * s, 0.0, 0.0))
        self._raising = (done + 1, total, alpha0)
        return True

    def _fire_faults(self, now: float) -> bool:
        """Raise the faults whose time has come; True when the device vanished."""
        assert self._first_hello_us is not None  # fired only after the first HELLO (_tick)
        elapsed = (self._device_us - self._first_hello_us) * 1e-6
        f = self.faults
        actions: tuple[tuple[str, float | None, Callable[[], None]], ...] = (
            ("stall", f.stall_at, lambda: setattr(self._qube, "stall_error", True)),
            ("amplifier fault", f.amp_fault_at, lambda: setattr(self._qube, "amp_fault", True)),
            ("silence", f.silence_at, lambda: setattr(self, "_silent", True)),
            ("vanish", f.vanish_at, self._vanish),
            ("hold", f.hold_at, self._hold),
        )
        for name, at, action in actions:
            if at is not None and elapsed >= at - 1e-9 and name not in self._fired:
                self._fired.add(name)
                self.events.append((self._device_us, now, name))
                action()
        return self._master < 0

    def _hold(self) -> None:
        """The firmware misses ``hold_periods`` ticks; its clock and the pendulum go on."""
        assert self._dev is not None and self._qube is not None  # a fault of a tick: after open()
        for _ in range(self.faults.hold_periods):
            self._qube.advance()
        self._device_us += self.faults.hold_periods * self._dev.period_us

    def _vanish(self) -> None:
        self.vanished_at = time.perf_counter()
        self.close()

    # --- what happened ---------------------------------------------------------------------

    @property
    def device_time(self) -> float:
        """Device time of the next tick (s since the emulator opened)."""
        return self._device_us * 1e-6

    def stats(self) -> dict:
        """Counters so far: ticks, sessions, late ticks caught up, schedule slips, bytes, faults injected."""
        return {
            **self._counts,
            "max_lateness": self._max_lateness,
            "device_time": self.device_time,
            "seed": self.seed,
            "lockstep": self.lockstep,
            "load": None if self.load is None else self.load.to_dict(),
            **({} if self.relaxation is None else {"relaxation": dataclasses.asdict(self.relaxation)}),
            **self._link.counters(),
            "host_frames": self._mirror.stats.frames,
            "host_rejects": self._mirror.stats.rejected,
            "faults_fired": sorted(self._fired),
        }

    def record(self) -> dict[str, np.ndarray]:
        """The per-tick record (fields :data:`RECORD_FIELDS`), oldest first.

        ``device_us``: device time of the tick; ``wall``: ``time.perf_counter()``
        when it started; ``lateness``: against its wall-clock deadline (NaN in
        lockstep); ``volts``: what the motor got over the following period;
        ``amp_enabled``: the amplifier-enable bit of the tick's motor word;
        ``command_seq``, ``command_mv``: the newest command received from the
        host before the tick (0 before any); ``session``: HELLOs received
        before the tick (the pendulum is raised at the first tick of each
        session, to ``initial_states[session - 1]``); ``answer``: seconds from
        the tick to the first command received after it, NaN when none came
        before the next tick (the round trip the host's loop achieves).

        Raises
        ------
        RuntimeError
            If the emulator was made with ``record_ticks=0``.
        """
        if self._record is None:
            raise RuntimeError("no record kept: make the emulator with record_ticks > 0")
        rows = list(self._record)
        columns = list(zip(*rows)) if rows else [()] * len(RECORD_FIELDS)
        dtypes = (np.int64, float, float, float, bool, np.int64, np.int64, np.int64, float)
        return {name: np.array(col, dtype=dt) for name, col, dt in zip(RECORD_FIELDS, columns, dtypes)}
