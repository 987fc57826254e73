"""Pre-flight check of the rig through the serial bridge (``qube-run --backend serial --check``).

Before the first episode on a real QUBE-Servo 2: the bridge answers, the
module on its SPI bus is a QUBE-Servo 2 (module id 777), both encoders are
read (and counting, if someone turns the arm or the pendulum meanwhile), the
amplifier enables on a zero-volt command without a fault, the round trip
of a command (sent until the telemetry of the tick that applied it arrives)
is measured, and the motor's sign is tried: with the pendulum hanging at rest,
:data:`MOTOR_CHECK_VOLTS` for :data:`MOTOR_CHECK_PUSH` ticks must turn the arm
the way theta grows (a few degrees, then 0 V). That push is the only voltage
other than 0 V ever commanded, and it is not commanded unless the pendulum hangs.
Last, the host stops commanding: the bridge's watchdog must switch the motor off
and report it within :data:`WATCHDOG_WAIT` ticks.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from qube_koopman.daq.backends.contract import BackendFault
from qube_koopman.firmware_protocol import Status
from qube_koopman.firmware_protocol.messages import MODULE_ID_QUBE_SERVO_2

__all__ = ["CheckResult", "MOTOR_CHECK_VOLTS", "PreflightReport", "preflight"]

#: The motor check's push (V) and its length and the coast after it (ticks of 2 ms): on the QUBE-Servo 2 the
#: arm turns about 0.1 rad (30 counts) this way, against a tenth of that for the check to tell the sign.
MOTOR_CHECK_VOLTS, MOTOR_CHECK_PUSH, MOTOR_CHECK_COAST = 1.0, 20, 50
#: Arm counts the push must move it by, either way, to tell the motor's sign (a count is 3.1 mrad).
MOTOR_CHECK_COUNTS = 3
#: The pendulum hangs when it is within this of straight down (rad): the motor check's condition.
HANGING_WITHIN = 0.5
#: Ticks the host reads without commanding for the watchdog check (the bridge's timeout is 1-1000, 5 by default).
WATCHDOG_WAIT = 50


@dataclass(frozen=True)
class CheckResult:
    """One check: its name, whether it passed, and what was seen."""

    name: str
    ok: bool
    detail: str


@dataclass
class PreflightReport:
    """The checks in order, and the round trips measured (s)."""

    checks: list[CheckResult] = field(default_factory=list)
    round_trips: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def ok(self) -> bool:
        """True when every check passed."""
        return bool(self.checks) and all(c.ok for c in self.checks)

    @property
    def failed(self) -> list[str]:
        """Names of the failed checks."""
        return [c.name for c in self.checks if not c.ok]

    def text(self) -> str:
        """The report, one line per check."""
        return "\n".join(f"{'ok  ' if c.ok else 'FAIL'} {c.name}: {c.detail}" for c in self.checks)


def _module_id(backend) -> CheckResult:
    found = backend.hello.module_id if backend.hello is not None else None
    ok = found == MODULE_ID_QUBE_SERVO_2
    detail = (
        f"{found} (QUBE-Servo 2)"
        if ok
        else f"{found}, expected {MODULE_ID_QUBE_SERVO_2}: is the QUBE powered and wired to the bridge?"
    )
    return CheckResult("module id", ok, detail)


def _exchange(backend, n_commands: int):
    """Command 0 V with the amplifier on every tick; (telemetry seen, round trips in s, fault text)."""
    sent: dict[int, float] = {}
    trips, seen = [], []
    fault = ""
    try:
        for _ in range(n_commands + 20):  # the last commands' telemetry arrives a tick or two later
            backend.read()
            arrived = time.perf_counter()
            tm = backend.last_telemetry
            seen.append(tm)
            if tm.last_command_seq in sent:
                trips.append(arrived - sent.pop(tm.last_command_seq))
            if len(trips) >= n_commands:
                break
            backend.write(0.0)
            sent[backend.last_command_seq] = time.perf_counter()
    except BackendFault as exc:
        fault = str(exc)
    return seen, np.array(trips), fault


def preflight(backend, n_commands: int = 100) -> PreflightReport:
    """Run the checks on an opened :class:`~daq.backends.serial.SerialBackend`.

    Parameters
    ----------
    backend : SerialBackend
        Connected (``open()`` done); a session is started and stopped here.
    n_commands : int
        Zero-volt commands whose round trip is measured.

    Returns
    -------
    PreflightReport
    """
    report = PreflightReport()
    report.checks.append(_module_id(backend))
    backend.start()
    motor = watchdog = None
    try:
        seen, trips, fault = _exchange(backend, n_commands)
        if not fault and seen:
            motor = _motor_sign(backend)
            watchdog = _watchdog(backend)
    finally:
        backend.stop()
    report.round_trips = trips
    if seen:
        first, last = seen[0], seen[-1]
        moved = [
            name
            for name, a, b in (("arm", first.encoder0, last.encoder0), ("pendulum", first.encoder1, last.encoder1))
            if a != b
        ]
        counting = (
            f"counting ({', '.join(moved)} moved)"
            if moved
            else "no motion seen (turn the arm and the pendulum by hand during the check to see them count)"
        )
        report.checks.append(
            CheckResult(
                "encoders",
                True,
                f"read: arm {first.encoder0} -> {last.encoder0}, pendulum {first.encoder1} -> "
                f"{last.encoder1} counts; {counting}",
            )
        )
    else:
        report.checks.append(CheckResult("encoders", False, f"no telemetry: {fault or 'none arrived'}"))
    enabled = any(tm.status & Status.AMP_ENABLED for tm in seen)
    if fault:
        report.checks.append(CheckResult("amplifier", False, fault))
    else:
        report.checks.append(
            CheckResult(
                "amplifier", enabled, "enabled at 0 V without a fault" if enabled else "never reported enabled at 0 V"
            )
        )
    if len(trips) >= n_commands:
        report.checks.append(
            CheckResult(
                "round trip",
                True,
                f"p50 {np.median(trips) * 1e3:.2f} ms, max {trips.max() * 1e3:.2f} ms over "
                f"{len(trips)} commands (sent until the telemetry of the tick that applied it)",
            )
        )
    else:
        report.checks.append(
            CheckResult("round trip", False, f"only {len(trips)} of {n_commands} commands were seen applied")
        )
    report.checks += [check for check in (motor, watchdog) if check is not None]
    return report


def _watchdog(backend) -> CheckResult:
    """Stop commanding (the amplifier on, 0 V): the bridge's watchdog must trip and say so."""
    try:
        for _ in range(WATCHDOG_WAIT):
            backend.read()
    except BackendFault as exc:
        ok = "watchdog tripped" in str(exc)
        return CheckResult("watchdog", ok, str(exc) if ok else f"another fault came first: {exc}")
    timeout = backend.watchdog_ticks
    return CheckResult("watchdog", False, f"no trip in {WATCHDOG_WAIT} ticks without a command (timeout {timeout})")


def _motor_sign(backend) -> CheckResult:
    """Push the arm with :data:`MOTOR_CHECK_VOLTS`, then 0 V: theta must grow (the pendulum hanging at rest)."""
    import math

    from qube_koopman.sim.pendulum.sensor import COUNTS_PER_REV

    _, alpha = backend.read()
    if abs(abs(alpha) - math.pi) > HANGING_WITHIN:
        return CheckResult(
            "motor sign",
            False,
            f"not tried: the pendulum is at {math.degrees(alpha):.0f} deg, not hanging (let it hang at rest, "
            "then check again)",
        )
    start = backend.last_telemetry.encoder0
    try:
        for tick in range(MOTOR_CHECK_PUSH + MOTOR_CHECK_COAST):
            backend.write(MOTOR_CHECK_VOLTS if tick < MOTOR_CHECK_PUSH else 0.0)
            backend.read()
        backend.write(0.0)
    except BackendFault as exc:
        return CheckResult("motor sign", False, f"the push failed: {exc}")
    moved = backend.last_telemetry.encoder0 - start
    radians = moved * 2 * math.pi / COUNTS_PER_REV
    if moved >= MOTOR_CHECK_COUNTS:
        return CheckResult(
            "motor sign",
            True,
            f"{MOTOR_CHECK_VOLTS:g} V turned the arm {radians:+.3f} rad ({moved:+d} counts): theta grows",
        )
    if moved <= -MOTOR_CHECK_COUNTS:
        return CheckResult(
            "motor sign",
            False,
            f"{MOTOR_CHECK_VOLTS:g} V turned the arm {radians:+.3f} rad ({moved:+d} counts), the wrong way: the "
            "motor's leads or the arm encoder's direction are reversed (theta must grow with a positive voltage)",
        )
    return CheckResult(
        "motor sign",
        False,
        f"{MOTOR_CHECK_VOLTS:g} V moved the arm {moved:+d} counts: is the amplifier powered and the arm free?",
    )
