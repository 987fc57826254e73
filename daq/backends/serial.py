"""The bridge firmware over a serial port (pyserial), behind the backend contract.

The bridge owns the 500 Hz clock (it samples, streams telemetry, applies the latest
command at its next tick and zeroes the motor if commands stop): :meth:`SerialBackend.read`
blocks until its next TELEMETRY frame and :meth:`SerialBackend.write` answers
with a COMMAND, which the bridge applies at its next tick. The protocol is
``firmware_protocol`` (PROTOCOL.md); angles come from the encoder counts
through :func:`sim.pendulum.sensor.counts_to_angles`, the rig's conversion.

Each episode opens a fresh session (HELLO, version check, CONFIG), so the
bridge's tick counter, watchdog and faults start clean. The backend aborts
the episode, by raising :class:`~daq.backends.contract.BackendFault` with the
reason, on:

- link loss: no telemetry for ``link_timeout`` (25 ms by default, 12 ticks),
  or the port failing (a USB device unplugged);
- a device fault: amplifier fault, motor stall error, QUBE absent (bad SPI
  module id), the bridge's watchdog tripped (the host fell behind by five
  ticks: the motor was off, the data no longer shows the controller's
  loop), or a bridge that lost the session.

A watchdog trip while the host has commanded nothing but 0 V in this session
is not a fault: that is the start gate holding the motor still (the loop's
pause between the gate opening and its first tick, opening the log, can
exceed five ticks). The backend then re-arms the watchdog with one
amplifier-off command before its first real one. Skipped ticks and late
commands are counted from the first non-zero command on.

Lost frames are counted, not fatal: a gap in the telemetry's tick counter
(``ticks_missed``) or in the frame sequence (``frames_lost``), frames the
decoder rejected, commands that missed their tick (``late_commands``), and
the bridge's own reports (receive errors, tick overruns). A host that falls
behind reads the newest telemetry and counts the ones it passed over
(``ticks_skipped``): acting on queued, stale samples would add a tick of
delay for the rest of the episode. :meth:`SerialBackend.statistics`
hands them to the loop, which records them with the episode's final status.
"""

from __future__ import annotations

import math
import os
import select
import time
from collections import deque
from typing import Any, Callable

from qube_koopman.daq.backends.contract import Backend, BackendFault, Pacing
from qube_koopman.firmware_protocol import (
    PROTOCOL_VERSION,
    Capability,
    Command,
    CommandFlags,
    Config,
    ConfigAck,
    ConfigResult,
    Fault,
    FaultCode,
    Hello,
    HelloReply,
    Status,
    StreamDecoder,
    Telemetry,
    encode_frame,
)
from qube_koopman.firmware_protocol.messages import FIRMWARE_VERSION, MAX_MILLIVOLTS
from qube_koopman.sim.pendulum.sensor import counts_to_angles

__all__ = ["SerialBackend", "DEFAULT_BAUD", "DEFAULT_LINK_TIMEOUT"]

#: The bridge sketch's UART rate (PROTOCOL.md section 2; USB CDC ignores it).
DEFAULT_BAUD = 500_000

#: No telemetry for this long (s) means the link is lost.
DEFAULT_LINK_TIMEOUT = 0.025

_U32 = 0xFFFFFFFF
_REQUIRED = Capability.TELEMETRY | Capability.WATCHDOG
_DEVICE_FAULT_STATUS = Status.AMP_FAULT | Status.STALL_ERROR | Status.BAD_MODULE_ID | Status.WATCHDOG_TRIPPED
_AGE_NONE = 0xFFFF
# LED colour while the host is in control (the bridge shows blue before, red after a trip).
_LED_RUNNING = (0, 999, 0)
# Resend a HELLO this often (s) while waiting for its reply: a first frame can be lost.
_HELLO_RETRY = 0.2


def _fault_text(code: int, value: int) -> str:
    if code == FaultCode.WATCHDOG_TRIPPED:
        return (
            f"bridge watchdog tripped: no command for {value} ticks, the motor was switched off "
            "(the host fell behind or commands were lost)"
        )
    if code == FaultCode.AMP_FAULT:
        return f"amplifier fault reported by the QUBE (status 0x{value:02x})"
    if code == FaultCode.STALL_ERROR:
        return f"motor stall error reported by the QUBE (status 0x{value:02x})"
    if code == FaultCode.BAD_MODULE_ID:
        return f"no QUBE-Servo 2 on the bridge's SPI bus (module id {value}, expected 777)"
    if code == FaultCode.NOT_CONNECTED:
        return "the bridge lost the session (it was reset or another host opened one)"
    return f"bridge fault {code} ({value})"


_STATUS_TEXT = (
    (
        Status.WATCHDOG_TRIPPED,
        "bridge watchdog tripped: the motor was switched off (the host fell behind or commands were lost)",
    ),
    (Status.AMP_FAULT, "amplifier fault reported by the QUBE"),
    (Status.STALL_ERROR, "motor stall error reported by the QUBE"),
    (Status.BAD_MODULE_ID, "no QUBE-Servo 2 on the bridge's SPI bus (bad module id)"),
)


def _status_text(status: int) -> str:
    # The FAULT frame says more, but it may have been lost: the status bits are the backstop.
    return next(text for bit, text in _STATUS_TEXT if status & bit)


class SerialBackend(Backend):
    """The QUBE-Servo through the bridge firmware on a serial port.

    Parameters
    ----------
    port : str
        Serial device (``/dev/ttyACM0``, the path ``qube-emulate`` prints) or
        a pyserial URL (``spy:///dev/ttyACM0?file=link.txt`` hex-dumps traffic).
    baud : int
        Baud rate (a UART bridge must match the sketch's, 500000; USB CDC
        and pseudo-terminals ignore it).
    rate_hz : int
        Tick rate asked of the bridge.
    watchdog_ticks : int
        Ticks without a command after which the bridge switches the motor off.
    max_voltage : float
        The bridge clamps commands to +-this (V): a second line of defence
        behind the loop's own clamp.
    link_timeout : float
        Seconds without telemetry that count as a lost link.
    handshake_timeout : float
        Seconds to wait for the bridge's replies to HELLO and CONFIG.
    clock : callable
        The clock both timeouts are measured on (s, any origin); the wall
        clock by default. A test whose emulated bridge runs in its process
        passes the bridge's device clock: device time advances only as the
        bridge ticks, and every tick sends telemetry, so a host held up by a
        loaded machine (the bridge's ticks then wait in the port) is never
        taken for a lost link.
    spin : bool
        Wait for each telemetry busy, the port polled without blocking, rather than asleep in the
        port's read (:attr:`Backend.spin`).
    """

    name = "serial"
    pacing = Pacing.DEVICE
    _last_frame_seq: int | None  # of the last frame received (None: none this episode); see _reset_counts

    def __init__(
        self,
        port: str,
        baud: int = DEFAULT_BAUD,
        *,
        rate_hz: int = 500,
        watchdog_ticks: int = 5,
        max_voltage: float = 10.0,
        link_timeout: float = DEFAULT_LINK_TIMEOUT,
        handshake_timeout: float = 1.0,
        clock: Callable[[], float] = time.perf_counter,
        spin: bool = False,
    ) -> None:
        if isinstance(baud, bool) or not isinstance(baud, int) or baud <= 0:
            raise ValueError(f"baud must be a positive whole number, got {baud!r}")
        Config(rate_hz=rate_hz, watchdog_ticks=watchdog_ticks).pack()  # ValueError naming a bad one
        if not (math.isfinite(max_voltage) and 0 < max_voltage <= MAX_MILLIVOLTS / 1000):
            raise ValueError(f"max_voltage must be in (0, {MAX_MILLIVOLTS / 1000:g}] V, got {max_voltage!r}")
        for name, value in (("link_timeout", link_timeout), ("handshake_timeout", handshake_timeout)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number of s, got {value!r}")
        self.port = str(port)
        self.baud = baud
        self.rate_hz = int(rate_hz)
        self.watchdog_ticks = int(watchdog_ticks)
        self.max_millivolts = int(round(max_voltage * 1000))
        self.link_timeout = float(link_timeout)
        self.handshake_timeout = float(handshake_timeout)
        self._clock = clock
        self.spin = bool(spin)
        self.sample_period = 1.0 / self.rate_hz
        self._serial: Any | None = None  # the pyserial port (untyped): open() opens it, close() drops it
        self._low_latency = "not tried"
        self._fd: int | None = None  # the port's own descriptor, when writes may go to it (see _send)
        self._decoder = StreamDecoder()
        self._frames: deque = deque()
        self.hello: HelloReply | None = None
        self._command_seq = 0
        self._running = False
        self._faulted = False
        self._driving = self._rearm = False
        self._rearm_seq: int | None = None
        self._reset_counts()

    # --- link ------------------------------------------------------------------------------

    def open(self) -> None:
        """Open the port (if not yet open) and hold a session with the bridge.

        Raises
        ------
        BackendFault
            The port cannot be opened, the bridge does not answer, or it
            speaks another protocol or firmware major version.
        """
        if self._serial is None:
            self._serial = self._open_port()
            self._fd = _plain_fd(self._serial)
        self._handshake()

    def _open_port(self):
        import serial

        try:
            # A short read timeout: read() polls in slices of it until its own deadline (none with
            # spin: each read returns at once, and read() spins to its deadline). Exclusive
            # (an advisory lock every pyserial program takes): a second qube-run on the same port
            # must fail, not take the rig over in the middle of an episode.
            port = serial.serial_for_url(
                self.port,
                baudrate=self.baud,
                timeout=0 if self.spin else min(0.005, self.link_timeout),
                write_timeout=self.link_timeout,
                exclusive=True,
            )
        except serial.SerialException as exc:
            if "exclusively lock" in str(exc):
                raise BackendFault(
                    f"cannot open {self.port}: another program is using it (a qube-run, or a serial terminal)"
                ) from None
            raise BackendFault(f"cannot open {self.port}: {_plain(exc).removesuffix(f': {self.port!r}')}") from None
        except (ValueError, OSError) as exc:
            # pyserial's text ends with the path (an OSError's filename): named once, first
            raise BackendFault(f"cannot open {self.port}: {_plain(exc).removesuffix(f': {self.port!r}')}") from None
        try:
            port.set_low_latency_mode(True)
            self._low_latency = "on"
        except (AttributeError, NotImplementedError, ValueError, OSError) as exc:
            # Only FTDI-like USB serial drivers have the flag; pseudo-terminals and CDC do not need it.
            self._low_latency = f"not supported ({_plain(exc)})"
        return port

    def _send(self, frame: bytes) -> None:
        import serial

        assert self._serial is not None, "open() first"
        try:
            if self._fd is None:
                self._serial.write(frame)
            else:
                self._write_fd(self._fd, frame)
        except (serial.SerialException, OSError) as exc:
            self._faulted = True
            raise BackendFault(f"link lost: cannot write to {self.port}: {_plain(exc)}") from None

    def _write_fd(self, fd: int, frame: bytes) -> None:
        """Write all of ``frame`` to the port's non-blocking descriptor within ``link_timeout``.

        pyserial's own write timeout also fires after every byte went out when the process was
        held up (a loaded machine) inside the call for longer than the timeout. Here the time is
        looked at only after a write that left bytes behind: a device that stops taking them
        fails, a host merely held up does not.
        """
        view = memoryview(frame)
        deadline = None
        while view:
            try:
                view = view[os.write(fd, view) :]
            except BlockingIOError:
                pass
            if not view:
                return
            now = self._clock()
            deadline = now + self.link_timeout if deadline is None else deadline
            if now >= deadline:
                raise OSError(f"the device took no bytes for {self.link_timeout * 1e3:.0f} ms")
            select.select([], [fd], [], 0.001)

    def _receive(self, deadline: float) -> bool:
        """Decode what arrives until a frame is queued or ``deadline``; False on timeout."""
        import serial

        port = self._serial
        assert port is not None, "open() first"
        while True:
            try:
                data = port.read(max(1, port.in_waiting))
            except (serial.SerialException, OSError) as exc:
                self._faulted = True
                raise BackendFault(f"link lost: {self.port}: {_plain(exc)}") from None
            if data:
                frames = self._decoder.feed(data)
                if frames:
                    self._frames.extend(frames)
                    return True
            if self._clock() >= deadline:
                return False

    def _drain(self) -> None:
        """Decode whatever has already arrived, without waiting."""
        import serial

        port = self._serial
        assert port is not None, "open() first"
        try:
            waiting = port.in_waiting
            if waiting:
                self._frames.extend(self._decoder.feed(port.read(waiting)))
        except (serial.SerialException, OSError) as exc:
            self._faulted = True
            raise BackendFault(f"link lost: {self.port}: {_plain(exc)}") from None

    def _next_frame(self, deadline: float):
        if not self._frames and not self._receive(deadline):
            return None
        return self._frames.popleft()

    def _handshake(self) -> None:
        port = self._serial
        assert port is not None  # open() opened it
        try:
            port.reset_input_buffer()  # telemetry of an older session, or of nobody's
        except Exception:  # noqa: BLE001 - not every URL handler can; stale frames are skipped anyway
            pass
        self._decoder.reset()
        self._frames.clear()
        start = self._clock()
        deadline = start + self.handshake_timeout
        reply = None
        next_hello = start
        while reply is None:
            now = self._clock()
            if now >= deadline:
                raise BackendFault(self._no_answer())
            if now >= next_hello:
                # A fresh nonce per attempt: only the reply to the last HELLO counts, so no
                # late HELLO can restart the session after this one. The leading delimiter
                # ends whatever partial frame the bridge holds.
                nonce = int.from_bytes(os.urandom(4), "little")
                self._send(b"\0" + encode_frame(Hello(nonce), self._next_seq(), self._host_us()))
                next_hello = now + _HELLO_RETRY
            frame = self._next_frame(min(deadline, next_hello))
            if frame is not None and isinstance(frame.message, HelloReply) and frame.message.nonce == nonce:
                reply = frame
        hello = reply.message
        if hello.protocol_version != PROTOCOL_VERSION:
            raise BackendFault(
                f"the bridge on {self.port} speaks protocol version {hello.protocol_version}; "
                f"this host speaks version {PROTOCOL_VERSION}"
            )
        if hello.firmware_major != FIRMWARE_VERSION[0]:
            raise BackendFault(
                f"bridge firmware {_firmware(hello)} is not supported: this host needs {FIRMWARE_VERSION[0]}.x"
            )
        if (hello.capabilities & _REQUIRED) != _REQUIRED:
            raise BackendFault(
                f"bridge firmware {_firmware(hello)} lacks telemetry or the watchdog "
                f"(capabilities 0x{hello.capabilities:x})"
            )
        self.hello = hello
        self._last_frame_seq = reply.seq
        config = Config(self.rate_hz, self.watchdog_ticks, self.max_millivolts)
        self._send(encode_frame(config, self._next_seq(), self._host_us()))
        while True:
            frame = self._next_frame(deadline)
            if frame is None:
                raise BackendFault(
                    f"the bridge on {self.port} answered HELLO but not CONFIG within {self.handshake_timeout:g} s"
                )
            self._track(frame)
            if isinstance(frame.message, ConfigAck):
                break
        ack = frame.message
        if ack.result != ConfigResult.OK:
            raise BackendFault(f"the bridge refused the configuration {config}: {_result_name(ack.result)}")

    def _no_answer(self) -> str:
        stats = self._decoder.stats
        where = f"the bridge on {self.port}"
        if stats.bad_version:
            return (
                f"{where} speaks protocol version {stats.last_bad_version}; this host speaks version "
                f"{PROTOCOL_VERSION}: update the firmware or this software"
            )
        if stats.rejected:
            return (
                f"{where} sends bytes this host cannot decode ({stats.rejected} bad frames): is the baud "
                f"rate right? (--baud, now {self.baud}; the bridge sketch uses {DEFAULT_BAUD})"
            )
        return (
            f"no answer from {where} within {self.handshake_timeout:g} s: is the bridge firmware running on that port?"
        )

    def _next_seq(self) -> int:
        # Command sequence numbers start at 1: telemetry's last_command_seq 0 means "none yet".
        self._command_seq = self._command_seq % _U32 + 1
        return self._command_seq

    @staticmethod
    def _host_us() -> int:
        return int(time.monotonic() * 1e6) & _U32

    # --- per frame -------------------------------------------------------------------------

    def _reset_counts(self) -> None:
        self._counts = dict(
            telemetry=0,
            ticks_missed=0,
            ticks_skipped=0,
            frames_lost=0,
            late_commands=0,
            tx_overflows=0,
            device_overruns=0,
            device_rx_errors=0,
        )
        self._expected_tick: int | None = None
        self._last_frame_seq = None
        self._rejected_at_start = self._decoder.stats.rejected
        self._stamp: int | None = None
        self._device_us = 0
        self.last_telemetry: Telemetry | None = None

    def _track(self, frame) -> None:
        """Sequence gaps, and the bridge's fault reports; raises on device faults."""
        if self._last_frame_seq is not None:
            gap = (frame.seq - self._last_frame_seq - 1) & _U32
            self._counts["frames_lost"] += gap
        self._last_frame_seq = frame.seq
        message = frame.message
        if isinstance(message, Fault):
            code = message.code
            if code == FaultCode.TICK_OVERRUN:
                self._counts["device_overruns"] += message.value
            elif code == FaultCode.RX_ERRORS:
                self._counts["device_rx_errors"] = message.value
            elif code == FaultCode.WATCHDOG_TRIPPED and not self._driving:
                self._rearm = True
            elif code in (
                FaultCode.WATCHDOG_TRIPPED,
                FaultCode.AMP_FAULT,
                FaultCode.STALL_ERROR,
                FaultCode.BAD_MODULE_ID,
                FaultCode.NOT_CONNECTED,
            ):
                self._faulted = True
                raise BackendFault(_fault_text(code, message.value))

    def _telemetry(self, frame) -> Telemetry:
        tm = frame.message
        counts = self._counts
        counts["telemetry"] += 1
        # The bridge's clock, unwrapped (32-bit microseconds wrap every 71.6 min).
        if self._stamp is not None:
            self._device_us += (frame.timestamp_us - self._stamp) & _U32
        self._stamp = frame.timestamp_us
        if self._expected_tick is not None and tm.tick != self._expected_tick:
            gap = (tm.tick - self._expected_tick) & _U32
            if gap >= 1 << 31:
                self._faulted = True
                raise BackendFault(f"the bridge restarted its session (tick {tm.tick} after {self._expected_tick - 1})")
            counts["ticks_missed"] += gap
        self._expected_tick = (tm.tick + 1) & _U32
        status = tm.status
        if status & Status.WATCHDOG_TRIPPED:
            if not self._driving:
                self._rearm = True
                status &= ~Status.WATCHDOG_TRIPPED
            elif self._rearm_seq is not None and (tm.last_command_seq - self._rearm_seq) & _U32 >= 1 << 31:
                status &= ~Status.WATCHDOG_TRIPPED  # sent before the re-arming command arrived
        if self._rearm_seq is not None and (tm.last_command_seq - self._rearm_seq) & _U32 < 1 << 31:
            self._rearm_seq = None
        if status & _DEVICE_FAULT_STATUS:
            self._faulted = True
            raise BackendFault(_status_text(status))
        self.last_telemetry = tm
        if self._driving and tm.command_age != _AGE_NONE and tm.command_age > 0:
            counts["late_commands"] += 1
        if tm.status & Status.TX_OVERFLOW:
            counts["tx_overflows"] += 1
        return tm

    # --- the backend contract --------------------------------------------------------------

    def start(self) -> None:
        """Open a fresh session with the bridge (opening the port the first time).

        Raises
        ------
        BackendFault
            As :meth:`open`.
        """
        self._faulted = False
        self._driving = self._rearm = False
        self._rearm_seq = None
        self._reset_counts()
        self.open()
        # Rejects while resynchronizing on an older session's stream are not this episode's.
        self._rejected_at_start = self._decoder.stats.rejected
        self._running = True

    def read(self) -> tuple[float, float]:
        """Block until the bridge's next telemetry; its (theta, alpha) in rad, alpha = 0 upright.

        Raises
        ------
        BackendFault
            Link lost (no telemetry for ``link_timeout``) or a device fault.
        """
        if not self._running:
            raise BackendFault("serial backend read before start() or after stop()")
        deadline = self._clock() + self.link_timeout
        latest = None
        while True:
            # Everything already here is processed (faults, gaps) and the newest
            # telemetry wins: a host that fell behind catches up instead of
            # acting on stale samples, one tick late, for the rest of the episode.
            self._drain()
            frames = self._frames
            while frames:
                frame = frames.popleft()
                self._track(frame)
                if isinstance(frame.message, Telemetry):
                    if latest is not None and self._driving:
                        self._counts["ticks_skipped"] += 1
                    latest = self._telemetry(frame)
            if latest is not None:
                return counts_to_angles(latest.encoder0, latest.encoder1)
            if not self._receive(deadline):
                self._faulted = True
                raise BackendFault(f"link lost: no telemetry from {self.port} for {self.link_timeout * 1e3:.0f} ms")

    def write(self, volts: float) -> None:
        """Send the command for the bridge's next tick (integer millivolts, amplifier on).

        After a fault the amplifier is commanded off whatever ``volts`` says.

        Raises
        ------
        BackendFault
            When the command cannot be sent, or is not finite (the amplifier is then
            commanded off first).
        """
        if not self._running:
            raise BackendFault("serial backend written before start() or after stop()")
        if self._faulted:
            self._command(0, 0)
            return
        if not math.isfinite(volts):
            # As the simulator: a fault, not a silent amplifier-off command the episode carries on past.
            self._faulted = True
            self._command(0, 0)
            raise BackendFault(f"the command is not a voltage ({volts!r}): the amplifier was switched off")
        mv = max(-self.max_millivolts, min(self.max_millivolts, int(round(volts * 1000.0))))
        rearm = b""
        if self._rearm:
            # The trip is latched until the amplifier is commanded off (PROTOCOL.md 7.4); the
            # device clears it on receipt, so both commands go in one write: one USB transfer,
            # and a bridge never sees the re-arm as an answer of its own.
            rearm = self._command_frame(0, 0)
            self._rearm, self._rearm_seq = False, self._command_seq
        self._driving = self._driving or mv != 0
        self._send(rearm + self._command_frame(mv, CommandFlags.AMP_ENABLE))

    def _command(self, millivolts: int, flags: int) -> None:
        self._send(self._command_frame(millivolts, flags))

    def _command_frame(self, millivolts: int, flags: int) -> bytes:
        red, green, blue = _LED_RUNNING if flags else (0, 0, 0)
        return encode_frame(Command(millivolts, int(flags), red, green, blue), self._next_seq(), self._host_us())

    def stop(self) -> None:
        """Command 0 V with the amplifier off (best effort: the link may be gone); safe to call twice."""
        self._running = False
        if self._serial is None:
            return
        try:
            self._command(0, 0)
        except BackendFault:
            pass

    def close(self) -> None:
        """Stop and release the port."""
        self.stop()
        port, self._serial, self._fd = self._serial, None, None
        if port is not None:
            try:
                port.close()
            except Exception:  # noqa: BLE001 - closing a vanished device may fail; it is gone either way
                pass

    @property
    def last_command_seq(self) -> int:
        """Sequence number of the last frame sent (telemetry's ``last_command_seq`` once applied)."""
        return self._command_seq

    def device_time(self) -> float | None:
        """The bridge's clock at the last telemetry read (s since the session's first), or None before."""
        return None if self._stamp is None else self._device_us * 1e-6

    def describe(self) -> dict:
        """Port, link settings and what the bridge said of itself at the handshake."""
        info = {
            **super().describe(),
            "port": self.port,
            "baud": self.baud,
            "rate_hz": self.rate_hz,
            "watchdog_ticks": self.watchdog_ticks,
            "max_millivolts": self.max_millivolts,
            "link_timeout": self.link_timeout,
            "low_latency": self._low_latency,
            "sample_period": self.sample_period,
        }
        if self.hello is not None:
            h = self.hello
            info.update(
                protocol_version=h.protocol_version,
                firmware=_firmware(h),
                capabilities=[c.name.lower() for c in Capability if h.capabilities & c and c.name is not None],
                emulated=bool(h.capabilities & Capability.EMULATED),
                module_id=h.module_id,
            )
        return info

    def statistics(self) -> dict:
        """Link counters of the current (or last) episode.

        ``telemetry``: frames received; ``ticks_missed``: gaps in the
        bridge's tick counter (telemetry lost or rejected on the way);
        ``ticks_skipped``: telemetry received but passed over for a newer
        one, the host having fallen behind; ``frames_lost``: gaps in its frame sequence
        (any type); ``late_commands``: ticks at which the bridge had no new
        command (``command_age`` > 0); ``tx_overflows``: telemetry flagged
        with dropped output; ``device_overruns``: periods the bridge reported
        missing; ``device_rx_errors``: frames from the host the bridge
        rejected (its running count); ``host_rejects``: frames from the
        bridge this host rejected during the episode, by reason in ``decoder``.
        """
        stats = self._decoder.stats
        return {**self._counts, "host_rejects": stats.rejected - self._rejected_at_start, "decoder": stats.as_dict()}


def _plain_fd(port) -> int | None:
    """The descriptor of a plain POSIX pyserial port (None for URL handlers that add to its writes)."""
    import serial

    posix = getattr(serial, "serialposix", None)
    if posix is None or type(port).write is not posix.Serial.write:
        return None
    try:
        return port.fileno()
    except (AttributeError, OSError, serial.SerialException):
        return None


def _firmware(hello: HelloReply) -> str:
    return f"{hello.firmware_major}.{hello.firmware_minor}.{hello.firmware_patch}"


def _result_name(result: int) -> str:
    try:
        return ConfigResult(result).name.lower().replace("_", " ")
    except ValueError:
        return f"result {result}"


def _plain(exc: BaseException) -> str:
    """An OS or pyserial error as one short line."""
    text = str(exc)
    if isinstance(exc, OSError) and exc.strerror:
        text = exc.strerror
    # pyserial repeats the errno ("[Errno 2] could not open port X: [Errno 2] No such file...").
    return text.split(": [Errno")[-1].split("] ", 1)[-1] if "[Errno" in text else text
