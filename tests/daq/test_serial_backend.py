"""The serial backend (daq.backends.serial) through the acquisition loop, against the emulated bridge.

Episodes run over a real pseudo-terminal with the bridge firmware's own core
behind it. Checked here: a full episode logged to MCAP passes the sim
backend's checks, with contiguous device ticks whose angles are exactly the
emulated QUBE's counts and whose commands were applied at the next tick;
garbage and corrupted frames are survived and counted; a vanished or silent
device aborts the episode within 50 ms with the log intact; device faults
and a host that falls behind abort with the reason; sequence gaps are counted
exactly; handshake failures are one clear line; ``qube-run --backend serial``
end to end in real time.

Most episodes use the emulator's lockstep mode (the device ticks as soon as
the host answers), so they do not depend on scheduling noise; the real-time
path runs in ``test_qube_run_in_real_time`` and in test_bridge.py. Their
lockstep timeout runs on the time the host spent waiting on the port with
nothing to read, and the host's link timeout on the bridge's device clock
(bridge_helpers.HostWait, device_clock): neither moves while a loaded machine
holds the host or the bridge up, so no wall-clock stall can make the bridge
tick ahead of its host or the host give up on a bridge that is talking
(``test_a_host_held_up_for_300_ms_loses_nothing`` holds it up on purpose).
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from _episodes import assert_follows_controller, nan_controller
from bridge_helpers import (
    FakeDevice,
    HostWait,
    device_clock,
    lockstep_backend,
    run_in_real_time,
)

from qube_koopman.daq.backends.contract import BackendFault
from qube_koopman.daq.backends.serial import SerialBackend
from qube_koopman.daq.cli.run import main
from qube_koopman.daq.excitation import generate_excitation
from qube_koopman.daq.log import read_episode
from qube_koopman.daq.loop import run_episode
from qube_koopman.daq.session import excitation_settings, plan_episodes, run_seeds
from qube_koopman.core.controller_file import load_controller
from qube_koopman.daq.sinks import McapSink
from qube_koopman.firmware_protocol import (
    Command,
    Config,
    ConfigAck,
    Fault,
    FaultCode,
    Hello,
    HelloReply,
    Status,
    StreamDecoder,
    Telemetry,
    encode_frame,
    encode_raw_frame,
)
from qube_koopman.firmware_protocol.qube_spi import motor_word_pwm
from qube_koopman.sim.bridge import BridgeEmulator, Faults
from qube_koopman.sim.pendulum import PendulumSimulator, SensorModel
from qube_koopman.sim.pendulum.sensor import angles_to_counts, counts_to_angles

CONTROLLER = load_controller()


def _plan(seconds: float = 4.0, seed: int = 1, controller=CONTROLLER):
    seeds, _ = run_seeds(seed, 1)
    return plan_episodes(controller, seeds, excitation_settings(seconds), source="test")[0]


class TimedBackend(SerialBackend):
    """Notes when a read or write first raises, on the clock its timeouts run on (the device's in _run)."""

    fault_at: float | None = None
    emu: BridgeEmulator | None = None  # set by _run

    def _timed(self, call, *args):
        try:
            return call(*args)
        except BackendFault:
            if self.fault_at is None:
                self.fault_at = self.emu.device_time
            raise

    def read(self):
        return self._timed(super().read)

    def write(self, volts):
        return self._timed(super().write, volts)


def _run(
    core,
    tmp_path,
    faults=Faults(),
    seconds=4.0,
    lockstep_timeout=0.02,
    link_timeout=0.2,
    backend_cls=SerialBackend,
    wait=None,
    controller=CONTROLLER,
    load=None,
):
    """One episode in lockstep into an MCAP log: (result, episode read back, emulator, backend).

    The lockstep timeout runs on the host's waiting (``wait``), the link timeout on the device clock.
    """
    wait = wait if wait is not None else HostWait()
    emu = BridgeEmulator(
        seed=9,
        core=core,
        lockstep=True,
        lockstep_timeout=lockstep_timeout,
        lockstep_clock=wait,
        faults=faults,
        record_ticks=200_000,
        load=load,
    )
    emu.start()
    backend = lockstep_backend(emu, wait, backend_cls, link_timeout=link_timeout)
    backend.emu = emu
    sink = McapSink(tmp_path)
    try:
        result = run_episode(backend, _plan(seconds, controller=controller), [sink])
    finally:
        backend.close()
        _until_applied(emu, backend.last_command_seq)  # the amplifier-off command reaches the device's record
        emu.stop()
    episode = read_episode(sink.paths[0]) if sink.paths else None
    return result, episode, emu, backend


def _until_applied(emu, seq, limit=30.0):
    """Wait until a tick of the bridge applied command ``seq`` (its record says so), or its device is gone.

    Watched on the bridge's record, not guessed in wall time; ``limit`` only guards against a hang.
    """
    deadline = time.monotonic() + limit
    while emu.running and emu.error is None and time.monotonic() < deadline:
        if emu.record()["command_seq"][-1:].tolist() == [seq]:
            return
        time.sleep(0.002)


# --- a clean episode ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def clean(core, tmp_path_factory):
    return _run(core, tmp_path_factory.mktemp("clean"))


def test_the_emulated_rig_carries_a_plant_files_random_load(core, clean, tmp_path):
    # The same seed, excitation and lockstep as the clean episode, with a strong random torque on the
    # arm: the device's arm goes elsewhere, the loop still balances, and the emulator says which load.
    from qube_koopman.sim.pendulum.load import RandomLoad

    load = RandomLoad(0.5, 1.0)
    result, ep, emu, _ = _run(core, tmp_path, load=load)
    assert result.complete and emu.stats()["load"] == load.to_dict() and clean[2].stats()["load"] is None
    assert np.abs(ep.alpha).max() < math.radians(20)
    same = clean[1]  # the same excitation and start, without the load
    assert np.array_equal(ep.target_theta, same.target_theta) and ep.alpha[0] == same.alpha[0]
    assert np.abs(ep.theta - same.theta).max() > 0.02  # rad: well beyond the encoder's count


def test_full_episode_passes_the_sim_backends_checks(clean):
    result, ep, _, _ = clean
    assert result.complete and len(ep) == 2000
    meta = ep.metadata
    assert meta.status == "complete" and not meta.salvaged and meta.backend == "serial"
    assert_follows_controller(ep)
    info = meta.extra["backend"]
    assert info["emulated"] is True and info["firmware"] == "1.0.0" and info["protocol_version"] == 1
    assert info["pacing"] == "device" and info["max_millivolts"] == 10_000
    seeds = meta.excitation["seeds"]
    ex = generate_excitation(
        tuple(seeds[k] for k in ("target_theta", "target_alpha", "feedforward")), excitation_settings(4.0)
    )
    assert np.array_equal(ep.target_theta, ex.target_theta) and np.array_equal(ep.feedforward, ex.feedforward)
    assert meta.timing["n_ticks"] == 2000 and meta.timing["paced"] is True
    link = meta.backend_stats
    assert link["ticks_missed"] == 0 and link["frames_lost"] == 0 and link["host_rejects"] == 0
    assert link["telemetry"] >= 2000 and link["device_rx_errors"] == 0
    assert np.abs(ep.alpha).max() < math.radians(20), "balanced"


def _session_ticks(emu):
    """The emulator's record from the first session's first tick, and the angles a replay gives there."""
    rec = emu.record()
    p = np.flatnonzero(rec["session"] == 1)[0]
    sim = PendulumSimulator(sensor=SensorModel(counts_per_rev=None))
    sim.reset(emu.initial_states[0])
    angles = []
    for volts in rec["volts"][p:]:
        theta, alpha = sim.state[:2]
        angles.append(counts_to_angles(*angles_to_counts(theta, alpha)))
        sim.step(volts)
    return {k: v[p:] for k, v in rec.items()}, np.array(angles)


def test_logged_angles_are_the_emulated_counts_of_contiguous_ticks(clean):
    # An independent replay of the pendulum under the voltages the emulated QUBE applied gives the
    # counts of every device tick; the log must hold a contiguous run of them, converted as the rig did.
    _, ep, emu, _ = clean
    _, angles = _session_ticks(emu)
    starts = [g for g in range(len(angles) - len(ep)) if np.array_equal(angles[g : g + len(ep)], ep.states)]
    assert len(starts) == 1, "the episode is one contiguous run of device ticks"


def test_each_command_is_applied_at_the_next_tick_in_integer_millivolts(clean):
    _, ep, emu, _ = clean
    rec, angles = _session_ticks(emu)
    g = next(g for g in range(len(angles)) if np.array_equal(angles[g : g + len(ep)], ep.states))
    # The last one may be overtaken by the 0 V the loop sends as the episode ends: only the newest
    # command is applied at a tick.
    after = g + 1 + np.arange(len(ep) - 1)
    mv = np.round(ep.plant_input[:-1] * 1000).astype(int)
    np.testing.assert_array_equal(rec["command_mv"][after], mv)
    np.testing.assert_allclose(rec["volts"][after], [motor_word_pwm(v) * 0.024 for v in mv], rtol=0, atol=1e-12)
    assert rec["amp_enabled"][after].all()
    assert not rec["amp_enabled"][-1] and rec["command_mv"][-1] == 0, "stop(): 0 V, amplifier off"
    # Lockstep: every tick of the episode was answered (before the next tick: NaN otherwise), and the
    # next tick came upon the answer. How fast the host answered is the machine's luck: not asserted.
    answer = rec["answer"][after - 1]
    assert np.all(answer > 0)
    assert np.all(np.diff(rec["wall"])[after[:-1] - 1] >= answer[:-1])


def test_a_host_held_up_for_300_ms_loses_nothing(core, tmp_path):
    # A loaded machine, on purpose: 300 ms into the episode the host thread sleeps 300 ms between a
    # read and its answer, and later the whole process (host and bridge threads) is stopped for 300 ms
    # (SIGSTOP, SIGCONT from a child), both past the 200 ms link timeout. Neither clock moves meanwhile,
    # so the episode is complete: no link loss, no tick skipped or missed, the watchdog never tripped.
    import os
    import subprocess

    stopper = []

    class HeldUp(SerialBackend):
        writes = 0

        def write(self, volts):
            self.writes += 1
            if self.writes == 150:
                time.sleep(0.3)
            if self.writes == 600:
                stopper.append(
                    subprocess.Popen(["sh", "-c", f"kill -STOP {os.getpid()}; sleep 0.3; kill -CONT {os.getpid()}"])
                )
            super().write(volts)

    result, ep, _, _ = _run(core, tmp_path, seconds=2.0, backend_cls=HeldUp)
    assert stopper and stopper[0].wait(10) == 0
    assert result.complete and ep.metadata.status == "complete", result.reason
    link = ep.metadata.backend_stats
    assert link["ticks_missed"] == 0 and link["ticks_skipped"] == 0 and link["late_commands"] == 0, link
    assert np.all(np.diff(ep.device_time) == pytest.approx(0.002))


# --- a bad link -------------------------------------------------------------------------------------


def test_garbage_and_corrupted_frames_are_survived_and_counted(core, tmp_path):
    faults = Faults(drop_rate=0.01, corrupt_rate=2e-4, garbage_rate=0.02)
    # A lost telemetry frame goes unanswered: the bridge ticks again after 20 ms of the host waiting
    # for it. The link timeout, 200 ms of device time, would take 100 lost frames in a row.
    result, ep, emu, _ = _run(core, tmp_path, faults, lockstep_timeout=0.02, link_timeout=0.2)
    assert result.complete and len(ep) == 2000 and ep.metadata.status == "complete"
    assert_follows_controller(ep)
    injected = emu.stats()
    assert injected["frames_dropped"] > 0 and injected["bytes_corrupted"] > 0 and injected["garbage_bursts"] > 0
    link = ep.metadata.backend_stats
    assert link["ticks_missed"] > 0 and link["frames_lost"] > 0, "dropped and rejected telemetry is counted"
    assert link["host_rejects"] > 0 and link["decoder"]["bad_crc"] > 0
    assert ep.metadata.timing["device_stalls"] == 0, "a frame lost now and then is no stall"
    assert link["device_rx_errors"] > 0, "corrupted commands, rejected by the bridge, are reported by it"
    # Every frame lost shows as a gap: frames dropped on purpose are a lower bound.
    assert link["frames_lost"] >= 1


# --- link loss --------------------------------------------------------------------------------------


def test_vanished_device_aborts_at_once_with_the_log_intact(core, tmp_path):
    # The host must see the device go at once (the port failing), not by a timeout. Timed on the
    # device clock, which stops when the device vanishes: the abort comes at the device time of the
    # vanishing, with no tick between, and its reason is the port's error, not "no telemetry" (on the
    # wall clock the same is 0.1-1 ms, but a loaded machine may hold the host up for any time).
    result, ep, emu, backend = _run(
        core, tmp_path, Faults(vanish_at=1.0), lockstep_timeout=0.02, link_timeout=0.2, backend_cls=TimedBackend
    )
    assert result.status == "aborted" and result.cause == "fault" and "link lost" in result.reason
    assert "no telemetry" not in result.reason, result.reason
    vanished_us = next(d for d, _, e in emu.events if e == "vanish")
    assert backend.fault_at == vanished_us * 1e-6, "no tick of the bridge between vanishing and abort"
    meta = ep.metadata
    assert meta.status == "aborted" and "link lost" in meta.status_reason and not meta.salvaged
    assert 300 < len(ep) < 600 and np.array_equal(ep.t, np.arange(len(ep)) / 500)
    assert meta.backend_stats["telemetry"] >= len(ep)


def test_silent_device_aborts_25_ms_of_device_time_after_its_last_telemetry(core, tmp_path):
    # The default 25 ms link timeout on purpose: it is what bounds the detection. Timed on the device
    # clock, as the backend's timeouts are here: the silent bridge ticks on (after 10 ms of the host
    # waiting each), device time advances 2 ms a tick, and the host gives up at the first tick that
    # moves the clock to 25 ms or more after its read began. The last telemetry went out at the tick
    # before the silence (S - 2 ms); the host's read takes its deadline at one of three device times:
    # S - 2 ms (before the bridge finished that tick), S (after), or S + 2 ms (the bridge already took
    # the host's answer and ran the first silent tick before the read looked at the clock). So the
    # abort comes 24, 26 or 28 ms after the silence: the timeout plus at most one period either way.
    # Which one is the machine's luck; a loaded machine holding either side up moves neither clock,
    # so it cannot move the abort out of that window.
    result, ep, emu, backend = _run(
        core, tmp_path, Faults(silence_at=1.0), lockstep_timeout=0.01, link_timeout=0.025, backend_cls=TimedBackend
    )
    silences = [d for d, _, e in emu.events if e == "silence"]
    assert silences, f"the device never went silent: {result.reason}"
    assert result.cause == "fault" and "no telemetry" in result.reason and "25 ms" in result.reason
    detected = backend.fault_at - silences[0] * 1e-6
    assert 0.024 - 1e-9 <= detected <= 0.028 + 1e-9, f"abort {detected * 1e3:.1f} ms after the silence"
    assert ep.metadata.status == "aborted" and not ep.metadata.salvaged and len(ep) > 300


# --- device faults ----------------------------------------------------------------------------------


@pytest.mark.parametrize("fault, text", [("stall_at", "motor stall error"), ("amp_fault_at", "amplifier fault")])
def test_device_fault_aborts_with_the_reason_and_the_motor_off(core, tmp_path, fault, text):
    result, ep, emu, _ = _run(core, tmp_path, Faults(**{fault: 1.0}))
    assert result.cause == "fault" and text in result.reason and text in ep.metadata.status_reason
    rec, _ = _session_ticks(emu)
    at = next(d for d, _, e in emu.events if e in ("stall", "amplifier fault"))
    after = rec["device_us"] >= at
    assert np.all(rec["volts"][after] == 0.0), "the QUBE drives nothing once faulted"
    assert rec["amp_enabled"][~after][-50:].all() and not rec["amp_enabled"][-1]


def test_firmware_held_for_periods_shows_the_gap_in_the_logged_device_time(core, tmp_path):
    # The firmware is held 7 periods at 1 s of device time (as by a QUBE holding the SPI bus): it
    # reports the lost periods, and the log's device time says where they went.
    result, ep, emu, backend = _run(core, tmp_path, Faults(hold_at=1.0, hold_periods=7), seconds=2.0)
    assert result.complete and ep.metadata.status == "complete", result.reason
    assert any(e == "hold" for _, _, e in emu.events)
    assert np.isfinite(ep.device_time).all()
    steps = np.round(np.diff(ep.device_time) * ep.metadata.sample_rate_hz).astype(int)
    gaps = np.flatnonzero(steps != 1)
    assert gaps.size == 1 and steps[gaps[0]] == 8, f"steps {np.unique(steps, return_counts=True)}"
    assert ep.metadata.backend_stats["device_overruns"] == 7
    # The tick counter skipped the lost periods with the clock; no frame was lost on the link.
    assert ep.metadata.backend_stats["ticks_missed"] == 7 and ep.metadata.backend_stats["frames_lost"] == 0


def test_a_62_ms_bridge_hold_is_a_stall_in_the_timing_with_a_warning(core, tmp_path):
    # No telemetry for 62 ms, well inside the 200 ms link timeout: the episode goes on, but its log
    # misses 31 ticks. Not only counted as missed ticks: a device stall in the episode's timing (its
    # duration on the bridge's clock, where the host's lateness cannot see it), and a warning.
    # The warning is caught by a handler on the package's logger itself: a command run earlier in this
    # worker may have stopped that logger propagating to the root (it owns stderr) or raised its level.
    import logging

    said: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if "stalled" in record.getMessage():
                said.append(record.getMessage())

    logger, handler = logging.getLogger("qube_koopman"), Keep(logging.WARNING)
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.WARNING)
    try:
        result, ep, _, _ = _run(core, tmp_path, Faults(hold_at=1.0, hold_periods=31), seconds=2.0)
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
    assert result.complete, result.reason
    timing = ep.metadata.timing
    assert timing["device_stalls"] == 1 and ep.metadata.backend_stats["ticks_missed"] == 31
    assert timing["device_stall_max"] == pytest.approx(0.062, abs=1e-9) == timing["device_stall_time"]
    k = int(np.flatnonzero(np.diff(ep.device_time) > 0.003)[0]) + 1  # the sample after the hold
    assert timing["device_stall_first"] == pytest.approx(k / 500)
    assert said == [
        f"episode 0: the serial backend's device stalled 1 time(s), 62 ms at most (the first before "
        f"t = {k / 500:.3f} s): the ticks it held back are missing from the log"
    ]


def test_host_falling_behind_trips_the_watchdog_and_aborts(core, tmp_path):
    wait = HostWait()

    class Stalling(SerialBackend):
        writes = 0

        def write(self, volts):
            self.writes += 1
            if self.writes == 800:
                wait.hold(self.emu, 8)  # the bridge ticks on eight times without commands
            super().write(volts)

    result, ep, emu, _ = _run(core, tmp_path, lockstep_timeout=0.01, link_timeout=0.2, backend_cls=Stalling, wait=wait)
    assert result.cause == "fault" and "watchdog tripped" in result.reason
    assert "no command for 5 ticks" in ep.metadata.status_reason
    rec, _ = _session_ticks(emu)
    assert not rec["amp_enabled"][-1]


def test_a_pause_after_holding_zero_volts_is_not_a_fault(core):
    # The start gate holds 0 V; opening the log before tick 0 can take longer than the watchdog's
    # five ticks (the first McapSink.open takes ~30 ms). The motor was at 0 V: no fault, re-armed.
    # The bridge ticks unanswered only while the host waits (HostWait), so a loaded machine pausing
    # the host cannot make it tick ahead (a skipped tick); the pause below is eight ticks, on purpose.
    wait = HostWait()
    emu = BridgeEmulator(
        seed=3, core=core, lockstep=True, lockstep_timeout=0.01, lockstep_clock=wait, record_ticks=10_000
    )
    emu.start()
    backend = lockstep_backend(emu, wait, link_timeout=0.2)
    try:
        backend.start()
        for _ in range(20):
            backend.read()
            backend.write(0.0)
        backend.read()
        wait.hold(emu, 8)  # eight ticks without a command
        for _ in range(50):
            backend.read()
            backend.write(1.0)
        stats = backend.statistics()
    finally:
        backend.close()
        _until_applied(emu, backend.last_command_seq)
        emu.stop()
    rec, _ = _session_ticks(emu)
    assert not rec["amp_enabled"][25:35].all(), "the watchdog did trip during the pause"
    driven = rec["command_mv"] == 1000
    assert driven.sum() >= 45 and rec["amp_enabled"][driven].all()
    assert np.all(rec["volts"][driven] == pytest.approx(motor_word_pwm(1000) * 0.024))
    assert stats["ticks_skipped"] == 0 and stats["late_commands"] <= 1


def test_rig_start_gate_then_a_slow_log_open_still_runs_the_episode(core, tmp_path):
    # As on the rig: the pendulum is raised by hand over a second while the start gate holds 0 V,
    # then the log is slow to open: the bridge ticks eight times unanswered (the watchdog trips at
    # the fifth). Counted on the emulator's ticks, not wall time: the bridge ticks unanswered only
    # while the host waits on the port (HostWait) or, here, while the log opens, so a scheduler
    # stall on a loaded machine cannot make the bridge tick ahead of the host (the ticks_skipped
    # check would see it).
    wait = HostWait()

    class SlowDisk(McapSink):
        def open(self, metadata):
            wait.hold(emu, 8)
            super().open(metadata)

    emu = BridgeEmulator(
        seed=5,
        core=core,
        lockstep=True,
        lockstep_timeout=0.01,
        lockstep_clock=wait,
        raise_time=1.0,
        record_ticks=20_000,
    )
    emu.start()
    backend = lockstep_backend(emu, wait, link_timeout=0.2)
    sink = SlowDisk(tmp_path)
    try:
        result = run_episode(backend, _plan(1.0), [sink])
    finally:
        backend.close()
        emu.stop()
    assert result.complete, result.reason
    ep = read_episode(sink.paths[0])
    assert ep.metadata.status == "complete" and len(ep) == 500
    assert_follows_controller(ep)
    rec = emu.record()
    held = rec["session"] == 1
    gate = held & (rec["command_mv"] == 0) & rec["amp_enabled"]
    assert gate.sum() > 400, "the start gate held 0 V, amplifier on, while the pendulum was raised"
    tripped = held & ~rec["amp_enabled"] & (rec["command_seq"] > 0)
    assert tripped.any(), "the watchdog tripped while the log opened"
    assert ep.metadata.backend_stats["ticks_skipped"] == 0


def test_trip_bits_sent_before_the_rearm_arrived_are_ignored_but_not_later_ones():
    import os

    with _scripted_bridge() as dev:
        backend = SerialBackend(dev.path, link_timeout=0.5)
        backend.start()
        os.write(dev.master, _tm(12, 0))
        backend.read()
        backend.write(0.0)  # seq 3: the gate's 0 V
        tripped = Status.WATCHDOG_TRIPPED
        os.write(
            dev.master,
            encode_frame(Fault(FaultCode.WATCHDOG_TRIPPED, 6, 5), 13, 0)
            + _tm(14, 6, status=tripped, last_command_seq=3),
        )
        backend.read()  # not driving: re-arm
        writes, send = [], backend._send
        backend._send = lambda data: (writes.append(data), send(data))[1]
        backend.write(2.0)  # seq 4 amp off, seq 5 2 V
        # One write: a bridge (or the lockstep emulator) must not take the re-arm for a whole answer.
        assert [[f.seq for f in StreamDecoder().feed(w)] for w in writes] == [[4, 5]]
        os.write(dev.master, _tm(15, 7, status=tripped, last_command_seq=3))  # made before seq 4 arrived
        backend.read()
        os.write(dev.master, _tm(16, 8, last_command_seq=5))
        backend.read()
        backend.write(2.0)
        os.write(dev.master, _tm(17, 9, status=tripped, last_command_seq=6))  # a real trip now
        with pytest.raises(BackendFault, match="watchdog tripped"):
            backend.read()
        backend.close()
        received = dev.wait_for(lambda got: sum(isinstance(f.message, Command) for f in got) == 5)
    commands = [(f.seq, f.message.millivolts, f.message.flags) for f in received if isinstance(f.message, Command)]
    assert commands == [(3, 0, 1), (4, 0, 0), (5, 2000, 1), (6, 2000, 1), (7, 0, 0)]


def test_a_non_finite_controller_output_is_a_fault_with_zero_volts_applied(core, tmp_path):
    # As on the simulator (test_loop.py): a fault naming the output, 0 V applied and logged, the
    # amplifier off; not a silent amplifier-off command the episode carries on past.
    result, ep, emu, _ = _run(core, tmp_path, controller=nan_controller())
    assert result.cause == "fault"
    assert result.reason == "controller fault: its output is nan, not a voltage; 0 V applied"
    assert ep.metadata.status == "aborted" and ep.metadata.status_reason == result.reason and len(ep) < 20
    assert ep.plant_input[-1] == 0.0 and np.isfinite(ep.plant_input).all(), "the log holds what was applied"
    rec, _ = _session_ticks(emu)
    driven = rec["amp_enabled"] & (rec["command_seq"] > 0)
    assert driven.any() and not rec["amp_enabled"][-1] and rec["volts"][-1] == 0.0
    assert np.all(rec["command_mv"][np.flatnonzero(driven)[-1] + 1 :] == 0), "0 V from the fault on"


def test_a_non_finite_command_is_refused_with_the_amplifier_off():
    import os

    with _scripted_bridge() as dev:
        backend = SerialBackend(dev.path, link_timeout=0.5)
        backend.start()
        os.write(dev.master, _tm(12, 0))
        backend.read()
        with pytest.raises(BackendFault, match=r"the command is not a voltage \(nan\)"):
            backend.write(math.nan)
        backend.close()
        received = dev.wait_for(lambda got: sum(isinstance(f.message, Command) for f in got) == 2)
    commands = [(f.message.millivolts, f.message.flags) for f in received if isinstance(f.message, Command)]
    assert commands == [(0, 0), (0, 0)], "amplifier off, then stop()'s"


# --- sequence tracking, exactly -----------------------------------------------------------------


def _scripted_bridge():
    def respond(frame):
        m = frame.message
        if isinstance(m, Hello):
            return encode_frame(HelloReply(nonce=m.nonce, capabilities=0x7F, module_id=777), 10, 0)
        if isinstance(m, Config):
            return encode_frame(ConfigAck(), 11, 0)
        return b""

    return FakeDevice(respond)


def _tm(seq, tick, **fields):
    return encode_frame(Telemetry(tick=tick, encoder0=tick, encoder1=1024, **fields), seq, 2000 * tick)


def test_sequence_gaps_are_counted_exactly():
    import os

    with _scripted_bridge() as dev:
        backend = SerialBackend(dev.path, link_timeout=0.5)
        backend.start()
        script = [
            _tm(12, 0),
            _tm(13, 1),
            _tm(15, 3),  # tick 2 (seq 14) lost
            encode_frame(Fault(FaultCode.RX_ERRORS, 3, 7), 16, 0) + _tm(17, 4),
            _tm(19, 5),  # seq 18 lost
            _tm(20, 6, command_age=2),  # our command came late
            _tm(21, 7, status=Status.TX_OVERFLOW),
            _tm(22, 8) + _tm(23, 9),  # fell behind: the newest wins
        ]
        angles = []
        for chunk in script:
            os.write(dev.master, chunk)
            angles.append(backend.read())
            backend.write(0.5)
        stats = backend.statistics()
        backend.close()
        commands = [
            f
            for f in dev.wait_for(lambda got: sum(isinstance(f.message, Command) for f in got) == 9)
            if isinstance(f.message, Command)
        ]
    assert stats["telemetry"] == 9 and stats["ticks_missed"] == 1 and stats["frames_lost"] == 2
    assert stats["ticks_skipped"] == 1 and stats["late_commands"] == 1 and stats["tx_overflows"] == 1
    assert stats["device_rx_errors"] == 7 and stats["host_rejects"] == 0
    assert [a[0] for a in angles] == [k * 2 * math.pi / 2048 for k in (0, 1, 3, 4, 5, 6, 7, 9)]
    assert all(a[1] == 0.0 for a in angles)
    assert [c.message.millivolts for c in commands[:-1]] == [500] * 8 and commands[-1].message.flags == 0
    # Command sequence numbers: after HELLO (1) and CONFIG (2), one per command without gaps.
    assert [c.seq for c in commands] == list(range(3, 3 + len(commands)))


@pytest.mark.parametrize(
    "status, fault_frame, text",
    [
        (Status.WATCHDOG_TRIPPED, None, "watchdog tripped"),
        (0, Fault(FaultCode.NOT_CONNECTED, 0, 3), "lost the session"),
        (0, Fault(FaultCode.BAD_MODULE_ID, 0, 0), "module id 0"),
    ],
)
def test_fault_reports_and_status_bits_raise(status, fault_frame, text):
    import os

    with _scripted_bridge() as dev:
        backend = SerialBackend(dev.path, link_timeout=0.5)
        backend.start()
        os.write(dev.master, _tm(12, 0))
        backend.read()
        backend.write(1.0)  # driving: from now on a watchdog trip is a fault
        os.write(
            dev.master,
            (encode_frame(fault_frame, 13, 0) if fault_frame else b"")
            + _tm(14 if fault_frame else 13, 1, status=status),
        )
        with pytest.raises(BackendFault, match=text):
            backend.read()
        backend.write(3.0)
        backend.close()
        received = dev.wait_for(lambda got: sum(isinstance(f.message, Command) for f in got) == 3)
        last = [f.message for f in received if isinstance(f.message, Command)][-2:]
    assert all(c.flags == 0 and c.millivolts == 0 for c in last), "after a fault: amplifier off"


# --- handshake failures -------------------------------------------------------------------------


def _hello_reply(**fields):
    def respond(frame):
        if isinstance(frame.message, Hello):
            return encode_frame(HelloReply(nonce=frame.message.nonce, **fields), 1, 0)
        if isinstance(frame.message, Config):
            return encode_frame(ConfigAck(result=1), 2, 0)
        return b""

    return respond


@pytest.mark.parametrize(
    "respond, text",
    [
        (lambda f: b"", "no answer from the bridge"),
        (
            lambda f: encode_raw_frame(0x81, 0, 0, bytes(20), version=2),
            "speaks protocol version 2; this host speaks version 1",
        ),
        (lambda f: bytes(range(1, 200)) + b"\0" + bytes(range(50, 120)) + b"\0", "is the baud rate right"),
        (_hello_reply(firmware_major=2, capabilities=0x7F), "firmware 2.0.0 is not supported"),
        (_hello_reply(capabilities=0x01), "lacks telemetry or the watchdog"),
        (_hello_reply(capabilities=0x7F), "refused the configuration"),
    ],
)
def test_handshake_failures_say_why(respond, text):
    with FakeDevice(respond) as dev:
        backend = SerialBackend(dev.path, handshake_timeout=0.3)
        with pytest.raises(BackendFault, match=text):
            backend.start()
        backend.close()


def test_unknown_port_is_a_clear_fault():
    with pytest.raises(BackendFault, match="cannot open /nonexistent/tty: No such file"):
        SerialBackend("/nonexistent/tty").open()
    with pytest.raises(BackendFault) as caught:
        SerialBackend("/nonexistent/tty").open()
    assert str(caught.value) == "cannot open /nonexistent/tty: No such file or directory"  # the path once


def test_a_port_in_use_is_refused_in_one_line_naming_it(tmp_path, capsys):
    # The first holder keeps the rig: a second qube-run on the same port fails at once, whatever it asks.
    with _scripted_bridge() as dev:
        first = SerialBackend(dev.path)
        first.open()
        try:
            with pytest.raises(BackendFault) as caught:
                SerialBackend(dev.path).open()
            said = f"cannot open {dev.path}: another program is using it (a qube-run, or a serial terminal)"
            assert str(caught.value) == said
            status = main(["--backend", "serial", "--port", dev.path, "--out", str(tmp_path / "out"), "-q"])
            err = capsys.readouterr().err
            assert status == 1 and err == f"qube-run: error: {said}\n"
        finally:
            first.close()
        again = SerialBackend(dev.path)
        again.open()  # free again once the first let it go
        again.close()
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("bad", [dict(baud=0), dict(rate_hz=333), dict(max_voltage=20.0), dict(link_timeout=0.0)])
def test_settings_are_checked(bad):
    with pytest.raises(ValueError):
        SerialBackend("/dev/null", **bad)


# --- qube-run --backend serial ------------------------------------------------------------------


def test_a_spinning_host_polls_the_port_and_follows_the_bridge(core, tmp_path):
    """``SerialBackend(spin=True)`` (``qube-run --spin``): its port's reads return at once and read() spins to
    the next telemetry; the episode is an episode like any other, and its log says the host spun. Lockstep on
    the wall clock (the host's empty reads take no time to count on a clock of their own), the link
    timeout on the device's."""
    emu = BridgeEmulator(seed=9, core=core, lockstep=True, lockstep_timeout=0.05, record_ticks=10_000)
    emu.start()
    backend = SerialBackend(emu.path, clock=device_clock(emu), link_timeout=0.2, spin=True)
    sink = McapSink(tmp_path)
    try:
        result = run_episode(backend, _plan(1.0), [sink])
        read_timeout = backend._serial.timeout
    finally:
        backend.close()
        _until_applied(emu, backend.last_command_seq)
        emu.stop()
    assert result.complete, result.reason
    ep = read_episode(sink.paths[0])
    assert read_timeout == 0 and ep.metadata.extra["backend"]["spin"] is True
    assert ep.metadata.backend_stats["ticks_missed"] == 0
    assert_follows_controller(ep)


def test_qube_run_with_a_bad_port_is_one_line(tmp_path, capsys):
    status = main(["--backend", "serial", "--port", "/nonexistent/tty", "--out", str(tmp_path), "-q"])
    err = capsys.readouterr().err
    assert status == 1 and err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith("qube-run: error: cannot open /nonexistent/tty")
    assert not list(tmp_path.glob("*.mcap"))


@pytest.mark.slow
def test_qube_run_in_real_time(env, tmp_path, capsys):
    status, out, emulator_err, tmp_path, path = run_in_real_time(
        env, ["--seed", "5"], ["--episodes", "2", "--duration", "2", "--seed", "7"], tmp_path, capsys
    )
    assert status == 0, out
    assert f"on the emulated bridge on {path} (firmware 1.0.0)" in out and "serial link: " in out
    assert "2 complete, 0 aborted" in out
    files = sorted(tmp_path.glob("*.mcap"))
    assert len(files) == 2
    for f in files:
        ep = read_episode(f)
        assert ep.metadata.status == "complete" and len(ep) == 1000 and ep.metadata.backend == "serial"
        assert_follows_controller(ep)
        link = ep.metadata.backend_stats
        assert link["ticks_missed"] == 0 and link["frames_lost"] == 0 and link["host_rejects"] == 0
        assert ep.metadata.timing["paced"] is True
    assert "3 session(s)" in emulator_err, "one to connect, one per episode"


def test_a_real_time_run_counts_the_emulators_own_lateness_as_a_measured_stall():
    """Both emulators' stop reports are read for how far they fell behind the wall clock by their own clock
    (an emulator process held up past the bridge's watchdog loses the host's episode while the host's log
    shows it on time), and nothing is read from a report that says neither."""
    from bridge_helpers import _emulator_behind_ms

    core_report = (
        "qube-emulate: stopped after 1000 ticks (2.0 s of device time), 1 session(s), 990 commands, "
        "3 ticks caught up late, 0 schedule restarts (max lateness 12.5 ms)"
    )
    avr_report = "qube-emulate: stopped after 1000 ticks (...), at most 0.8 ms behind the wall clock"
    assert _emulator_behind_ms(core_report) == 12.5
    assert _emulator_behind_ms(avr_report) == 0.8
    assert _emulator_behind_ms("qube-emulate: error: no such port") == 0.0


def test_an_episode_lost_before_its_start_counts_as_a_stall_only_when_measured(tmp_path):
    """An episode lost to the watchdog during its swing-up leaves no log: qube-run's summary is read instead,
    a stall only when the bridge reported late commands there (or the emulator fell behind), and any other
    failure before the start is left for the test to fail on."""
    from bridge_helpers import _lost_to_stalls

    fault = "episode 0: backend fault before the start: bridge watchdog tripped: no command for 5 ticks\n"
    summary = "serial link: 57 telemetry frames, 0 ticks missed, 6 skipped, 0 frames lost, 0 rejected, {} commands late"
    (lost,) = _lost_to_stalls(tmp_path, "", fault + summary.format(7))
    assert lost.startswith("7 commands reached the bridge after their tick") and "before the start" in lost
    assert _lost_to_stalls(tmp_path, "", fault + summary.format(0)) == []
    assert _lost_to_stalls(tmp_path, "", "episode 0: swing-up gave up\n" + summary.format(7)) == []
    behind = "qube-emulate: stopped after 1000 ticks, 3 ticks caught up late (max lateness 12.5 ms)"
    assert "12.5 ms behind" in _lost_to_stalls(tmp_path, behind, fault + summary.format(0))[0]
