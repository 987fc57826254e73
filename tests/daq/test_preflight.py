"""``qube-run --backend serial --check``: the rig's pre-flight, against ``qube-emulate`` (host target)."""

from __future__ import annotations

import re
import subprocess
import sys

from bridge_helpers import fifo_command, granted_rt_priority, start_emulator, stop_process

from qube_koopman.daq.cli.run import main


def _check(env, path: str, rt_priority: int | None = None) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "qube_koopman.daq.cli.run", "--backend", "serial", "--port", path, "--check"]
    return subprocess.run(fifo_command(command, rt_priority), capture_output=True, text=True, env=env, timeout=60)


def test_check_passes_on_the_emulated_rig_and_reports_the_round_trip(env, tmp_path):
    # The round trip runs against the emulator in real time: both SCHED_FIFO where the machine
    # grants it, as on a busy lab PC (a loaded run with the suite on both cores and two burners
    # saw only 98 of 100 commands applied without it).
    rt = granted_rt_priority()
    proc, path = start_emulator(env, "-q", "--hanging", rt_priority=rt)  # as a check finds the rig: hanging
    try:
        run = _check(env, path, rt)
    finally:
        stop_process(proc)
    assert run.returncode == 0, run.stderr
    out = run.stdout
    for name in (
        "module id: 777",
        "encoders: read",
        "amplifier: enabled at 0 V",
        "round trip: p50",
        "motor sign: 1 V",
        "watchdog: bridge watchdog tripped: no command for 5 ticks",
    ):
        assert f"ok   {name}" in out, out
    # The push turns the emulated arm the way theta grows, by about what the motor's physics gives (0.1 rad).
    turned = float(re.search(r"turned the arm \+([\d.]+) rad", out).group(1))
    assert 0.03 < turned < 0.3, out
    p50, worst = map(float, re.search(r"p50 ([\d.]+) ms, max ([\d.]+) ms over 100 commands", out).groups())
    # A command is applied at the bridge's next tick: its telemetry comes within about a period.
    assert 0.0 < p50 <= worst and p50 < 20.0, out
    assert not list(tmp_path.iterdir()), "no episode is run"


def test_check_fails_naming_the_amplifier_on_a_fault(env):
    proc, path = start_emulator(env, "-q", "--amp-fault-at", "0.1")  # mid-check (it lasts 0.2 s)
    try:
        run = _check(env, path)
    finally:
        stop_process(proc)
    assert run.returncode == 1
    assert "amplifier" in run.stderr and "Traceback" not in run.stderr, run.stderr


def test_check_is_for_the_serial_backend(capsys):
    assert main(["--check"]) == 2
    assert "--check is for --backend serial" in capsys.readouterr().err


def test_the_motor_is_not_pushed_unless_the_pendulum_hangs(env):
    proc, path = start_emulator(env, "-q")  # raised at once, as for an episode
    try:
        run = _check(env, path)
    finally:
        stop_process(proc)
    assert run.returncode == 1 and "check failed: motor sign" in run.stderr, run.stderr
    assert "FAIL motor sign: not tried: the pendulum is at" in run.stdout and "not hanging" in run.stdout
