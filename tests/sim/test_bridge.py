"""The emulated bridge (sim.bridge) and ``qube-emulate``: the firmware core driving the simulated QUBE on a pty.

Checked here: the rig's encoder conversion; the emulated QUBE's SPI side
(motor word, presets, faults, current); sessions, telemetry and device time
over a real pseudo-terminal; the watchdog zeroing the motor five ticks (10 ms
of device time) after the last command, with a scripted host and with a real
``qube-run`` killed by SIGKILL; fault injection; the command-line tool.
"""

from __future__ import annotations

import json
import math
import os
import random
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import serial
from bridge_helpers import REPO, HostWait, await_emulator_ticks, start_emulator, stop_process

from qube_koopman.firmware_protocol import (
    Capability,
    Command,
    CommandFlags,
    Fault,
    FaultCode,
    Hello,
    HelloReply,
    StreamDecoder,
    Telemetry,
    encode_frame,
)
from qube_koopman.firmware_protocol.qube_spi import (
    MASK_ENCODER1,
    MASK_NORMAL,
    SpiCommand,
    current_amps,
    motor_word_pwm,
    pack_spi_command,
    unpack_spi_response,
)
from qube_koopman.sim.bridge import BridgeEmulator, DelayLine, EmulatedQube, Faults, FaultyLink
from qube_koopman.sim.pendulum import SensorModel, measure
from qube_koopman.sim.pendulum.sensor import angles_to_counts, counts_to_angles

STEP = 2 * math.pi / 2048


# --- the rig's encoder conversion ---------------------------------------------------------------


def test_counts_convert_as_the_rig_did():
    # The rig's C program: theta = enc0 * 2 pi / 2048, alpha = wrap(enc1 * 2 pi / 2048 - pi), zero hanging down.
    assert counts_to_angles(0, 1024) == (0.0, 0.0)  # upright
    assert counts_to_angles(0, 0)[1] == -math.pi  # hanging down: the counter's zero
    assert counts_to_angles(0, 2048)[1] == -math.pi  # one turn later, still hanging
    assert counts_to_angles(512, 1024 + 256) == (math.pi / 2, math.pi / 4)
    assert counts_to_angles(-1, 1023) == (-STEP, -STEP)
    assert counts_to_angles(0, 1024 + 3 * 2048) == (0.0, 0.0)  # alpha wraps, theta does not
    assert angles_to_counts(0.0, 0.0) == (0, 1024)
    assert angles_to_counts(2 * math.pi, -math.pi) == (2048, 0)


def test_emulated_counts_read_back_as_the_simulator_measures():
    rng = np.random.default_rng(3)
    states = rng.uniform(-20, 20, size=(2000, 2))
    expected = measure(states, SensorModel())
    got = np.array([counts_to_angles(*angles_to_counts(th, al)) for th, al in states])
    np.testing.assert_array_equal(got, expected)


# --- the emulated QUBE's SPI side ---------------------------------------------------------------


def _transfer(qube: EmulatedQube, motor: int, mask: int = MASK_NORMAL, preset1: int = 0):
    return unpack_spi_response(
        qube.transfer(pack_spi_command(SpiCommand(write_mask=mask, motor=motor, encoder1_preset=preset1)))
    )


def test_the_emulated_qubes_random_load_moves_the_arm_and_each_seed_draws_its_own():
    from qube_koopman.sim.pendulum.load import RandomLoad

    def arm(load, seed):
        qube = EmulatedQube(load=load)
        qube.place((0.0, math.pi, 0.0, 0.0), load_seed=seed)  # hanging, the motor off
        for _ in range(500):
            qube.advance()
        return qube.state[0]

    load = RandomLoad(0.5, 1.0)
    assert arm(None, 1) == arm(None, 2) and abs(arm(None, 1)) < 1e-12  # no load: hanging at rest stays at rest
    assert arm(load, 1) == arm(load, 1) != arm(load, 2)  # a seed's draw, and another's
    assert abs(arm(load, 1)) > 1e-3


def test_qube_applies_the_motor_word():
    qube = EmulatedQube()
    qube.place((0.0, 0.0, 0.0, 0.0))
    resp = _transfer(qube, 0x81A1)  # PROTOCOL.md section 8: 10 V
    assert (resp.module_id, resp.encoder0, resp.encoder1, resp.status) == (777, 0, 1024, 0)
    assert resp.current_raw == 8190, "no current before the voltage is applied"
    assert qube.volts == pytest.approx(417 * 0.024) and qube.enabled
    assert _transfer(qube, 0xFE5F) is not None and qube.volts == pytest.approx(-417 * 0.024)
    assert _transfer(qube, 0x017F).status == 0 and qube.volts == 0.0 and not qube.enabled, (
        "bit 15 clear: amplifier off whatever the PWM bits"
    )
    qube.place((0.0, 0.0, 0.0, 0.0))
    _transfer(qube, 0x8000 | 208)  # +5 V from rest
    resp = _transfer(qube, 0x8000 | 208)
    # At rest the current is V / Rm (no back-EMF yet); one period later, a little less.
    assert 0 < current_amps(resp.current_raw) <= 5 / 8.4 + 1e-3
    for _ in range(50):
        qube.advance()
    assert qube.state[0] > 0, "a positive voltage turns the arm the positive way"


def test_qube_faults_hold_the_motor_at_zero_until_the_amplifier_is_off():
    qube = EmulatedQube()
    qube.place((0.0, 0.0, 0.0, 0.0))
    qube.stall_error = True
    resp = _transfer(qube, 0x81A1)
    assert resp.status == 0x04 and qube.volts == 0.0
    assert _transfer(qube, 0x81A1).status == 0x04 and qube.volts == 0.0, "latched while enabled"
    _transfer(qube, 0x0000)
    assert _transfer(qube, 0x81A1).status == 0 and qube.volts > 9, "cleared by one word with bit 15 clear"
    qube.amp_fault = True
    assert _transfer(qube, 0x81A1).status == 0x01 and qube.volts == 0.0


def test_qube_encoder_preset_applies_after_the_transfer():
    qube = EmulatedQube()
    qube.place((0.0, 0.3, 0.0, 0.0))
    counts = angles_to_counts(0.0, 0.3)[1]
    assert _transfer(qube, 0, MASK_NORMAL | MASK_ENCODER1, preset1=5).encoder1 == counts
    assert _transfer(qube, 0).encoder1 == 5


# --- fault injection pieces ---------------------------------------------------------------------


def _telemetry_stream(n: int) -> bytes:
    return b"".join(encode_frame(Telemetry(tick=k, encoder1=1024), k, 2000 * k) for k in range(n))


def test_link_faults_are_seeded_and_counted():
    stream = _telemetry_stream(2000)
    faults = Faults(drop_rate=0.1, corrupt_rate=1e-3, garbage_rate=0.05)
    outs = []
    for _ in range(2):
        link = FaultyLink(faults, random.Random(7))
        outs.append(b"".join(link.outgoing(stream[i * 46 : (i + 1) * 46]) for i in range(2000)))
    assert outs[0] == outs[1], "same seed, same faults"
    assert 150 < link.frames_dropped < 250 and 60 < link.bytes_corrupted < 130 and 60 < link.garbage_bursts < 140
    decoder = StreamDecoder()
    frames = decoder.feed(outs[0])
    # Every frame neither dropped nor corrupted gets through; none that was damaged does.
    assert 1500 < len(frames) < 2000 - link.frames_dropped
    assert all(isinstance(f.message, Telemetry) and f.message.encoder1 == 1024 for f in frames)
    assert decoder.stats.rejected > 0
    assert FaultyLink(Faults(), random.Random(1)).outgoing(stream) == stream


def test_delay_line_holds_bytes_for_its_delay():
    line = DelayLine(0.005)
    line.put(1.0, b"ab")
    line.put(1.002, b"cd")
    assert line.take(1.0049) == b"" and line.next_release == pytest.approx(1.005)
    assert line.take(1.005) == b"ab" and line.take(1.01) == b"cd" and line.next_release == math.inf


@pytest.mark.parametrize(
    "bad", [dict(drop_rate=1.5), dict(corrupt_rate=-0.1), dict(latency=-1.0), dict(vanish_at=float("nan"))]
)
def test_faults_refuse_nonsense(bad):
    with pytest.raises(ValueError):
        Faults(**bad)


# --- the emulator over a pty, with a scripted host -----------------------------------------------


class Host:
    """The minimum of a host: HELLO, then frames in, commands out."""

    def __init__(self, path: str, wait: HostWait | None = None, emu: BridgeEmulator | None = None) -> None:
        self.port = serial.Serial(path, 500000, timeout=0.005)
        if wait is not None:
            wait.watch(self.port, emu)  # the lockstep emulator's clock: this host's waiting
        self.port.reset_input_buffer()
        self.decoder = StreamDecoder()
        self.seq = 0

    def send(self, message) -> None:
        self.seq += 1
        self.port.write(encode_frame(message, self.seq, 0))

    def frames(self, until, timeout: float = 2.0) -> list:
        """Frames until ``until(frames)`` holds (or the timeout: a failure)."""
        got: list = []
        deadline = time.monotonic() + timeout
        while not until(got):
            assert time.monotonic() < deadline, f"timed out with {len(got)} frames"
            try:
                got += self.decoder.feed(self.port.read(max(1, self.port.in_waiting)))
            except OSError as exc:
                # A vanished pty surfaces as EIO from pyserial's in_waiting ioctl or as a
                # SerialException from read, by timing; the serial backend treats both as a
                # lost link, and so does this host.
                raise serial.SerialException(f"device lost: {exc}") from exc
        return got

    def close(self) -> None:
        self.port.close()


def _count(kind, n):
    return lambda frames: sum(isinstance(f.message, kind) for f in frames) >= n


def test_session_telemetry_carries_device_time(core):
    with BridgeEmulator(seed=11, core=core, spin=0) as emu:
        host = Host(emu.path)
        host.port.write(b"\0")
        host.send(Hello(nonce=99))
        frames = host.frames(_count(Telemetry, 40))
        host.close()
    reply = frames[0].message
    assert isinstance(reply, HelloReply) and reply.nonce == 99 and reply.protocol_version == 1
    assert reply.capabilities & Capability.EMULATED and (reply.firmware_major, reply.firmware_minor) == (1, 0)
    tms = [f for f in frames if isinstance(f.message, Telemetry)]
    assert [f.message.tick for f in tms] == list(range(len(tms)))
    # Device time: one period per tick, whatever the wall clock did.
    assert np.all(np.diff([f.timestamp_us for f in tms]) == 2000)
    first = tms[0].message
    # Raised upright at the HELLO, tilted by at most 2 deg (11.4 counts), at rest, no command yet.
    assert first.encoder0 == 0 and abs(first.encoder1 - 1024) <= 12
    assert first.command_age == 0xFFFF and first.applied_millivolts == 0 and first.motor_word == 0
    assert emu.initial_states[0][1] == pytest.approx((first.encoder1 - 1024) * STEP, abs=STEP / 2)


def test_watchdog_zeroes_the_motor_ten_ms_of_device_time_after_the_last_command(core):
    # Lockstep: after the host goes quiet the device ticks every 10 ms of the host waiting on the
    # port (HostWait), and device time advances 2 ms per tick, so the check is exact whatever the
    # scheduling: a host held up between a telemetry frame and its command (a loaded machine) does
    # not wait on the port meanwhile, so the device does not tick on without the command.
    wait = HostWait()
    emu = BridgeEmulator(seed=2, core=core, lockstep=True, lockstep_clock=wait, record_ticks=10_000)
    emu.start()
    host = Host(emu.path, wait, emu)
    host.send(Hello(nonce=1))
    n_commands = 0
    frames: list = []
    while n_commands < 30:
        new = host.frames(_count(Telemetry, 1))
        frames += new
        host.send(Command(millivolts=2000, flags=CommandFlags.AMP_ENABLE))
        n_commands += 1
    last_seq = host.seq
    frames += host.frames(lambda f: any(isinstance(x.message, Fault) for x in f), timeout=3)
    host.close()
    emu.stop()
    record = emu.record()
    applied = np.flatnonzero(record["command_seq"] == last_seq)
    j = applied[0]
    off = np.flatnonzero(~record["amp_enabled"][j:])
    z = j + off[0]
    assert z - j == 5, "a command is applied for five ticks, the sixth without one is off"
    assert record["device_us"][z] - record["device_us"][j] == 10_000
    assert np.all(record["volts"][j:z] == pytest.approx(motor_word_pwm(2000) * 0.024))
    assert np.all(record["volts"][z:] == 0.0) and not record["amp_enabled"][z:].any()
    fault = next(f.message for f in frames if isinstance(f.message, Fault))
    assert fault.code == FaultCode.WATCHDOG_TRIPPED and fault.value == 5


def test_latency_is_added_each_way(core):
    with BridgeEmulator(seed=1, core=core, spin=0, faults=Faults(latency=0.005)) as emu:
        host = Host(emu.path)
        t0 = time.perf_counter()
        host.send(Hello(nonce=5))
        host.frames(_count(HelloReply, 1))
        round_trip = time.perf_counter() - t0
        host.close()
    # 5 ms each way at least. Only lower bounds on the wall clock: a loaded machine can hold either
    # side up for any time, which only adds. That each line holds its bytes for exactly its delay,
    # on its own clock, test_delay_line_holds_bytes_for_its_delay checks.
    assert round_trip >= 0.010
    hello_at = next(w for _, w, e in emu.events if e.startswith("HELLO"))
    assert hello_at - t0 >= 0.005, "the HELLO reached the firmware core after the inbound delay"


def test_vanish_closes_the_device_at_its_time(core):
    emu = BridgeEmulator(seed=1, core=core, spin=0, faults=Faults(vanish_at=0.1))
    emu.start()
    host = Host(emu.path)
    host.send(Hello(nonce=5))
    with pytest.raises(serial.SerialException):
        host.frames(lambda f: False, timeout=5)
    host.close()
    assert not os.path.exists(emu.path) and not emu.running and emu.vanished_at is not None
    hello_us = next(d for d, _, e in emu.events if e.startswith("HELLO"))
    vanish_us = next(d for d, _, e in emu.events if e == "vanish")
    assert vanish_us - hello_us == 100_000
    emu.stop()


def test_same_seed_same_start(core):
    starts = []
    for _ in range(2):
        with BridgeEmulator(seed=21, core=core, spin=0) as emu:
            for nonce in (1, 2):
                host = Host(emu.path)
                host.send(Hello(nonce=nonce))
                host.frames(_count(Telemetry, 2))
                host.close()
        starts.append(emu.initial_states)
    assert starts[0] == starts[1] and len(starts[0]) == 2 and starts[0][0] != starts[0][1]
    assert all(0 < abs(s[1]) <= math.radians(2) for s in starts[0])


def test_left_hanging_the_first_session_finds_it_tilted_about_the_bottom_and_later_ones_as_left(core):
    """``start_upright=False`` (``qube-emulate --hanging``): the first session's pendulum hangs at rest within
    the perturbation of straight down, seeded (another seed, another tilt), the counters still zero straight
    down; a later session is not placed (it finds the pendulum as the last one left it)."""
    tilts = []
    for seed in (21, 22):
        with BridgeEmulator(seed=seed, core=core, spin=0, start_upright=False) as emu:
            for nonce in (1, 2):
                host = Host(emu.path)
                host.send(Hello(nonce=nonce))
                frames = host.frames(_count(Telemetry, 2))
                host.close()
                if nonce == 1:
                    first = next(f.message for f in frames if isinstance(f.message, Telemetry))
        (state,) = emu.initial_states  # the second session placed nothing
        assert state[0] == state[2] == state[3] == 0.0 and 0 < abs(state[1] - math.pi) <= math.radians(2)
        counts = (first.encoder1 + 1024) % 2048 - 1024  # a turn is 2048 counts, zero straight down
        assert counts == pytest.approx((state[1] - math.pi) / STEP, abs=1) and counts != 0
        tilts.append(state[1])
    assert tilts[0] != tilts[1]


# --- the host killed mid-episode: the real path, in real time ------------------------------------


@pytest.mark.slow
def test_killed_host_gets_the_motor_zeroed_within_ten_ms_of_device_time(core, env, tmp_path):
    # Everything is asserted on the device's clock. In lockstep the device ticks once the host
    # answered, or after 2 s without an answer while the host lives (its start gate leaves a tick
    # unanswered): the watchdog could trip before the kill only if the machine held the host up
    # five times that. The link timeout (30 s) plays no part in what is tested, and is that long
    # so that a host held up while the emulator (in this process) is too is not taken for link
    # loss. After the kill the device ticks every 50 ms unanswered, as a bridge whose host died.
    emu = BridgeEmulator(seed=4, core=core, lockstep=True, lockstep_timeout=2.0, record_ticks=100_000)
    path = emu.start()
    code = "import sys; from daq.cli.run import main; sys.exit(main(sys.argv[1:]))"
    host = subprocess.Popen(
        [
            sys.executable,
            "-c",
            code,
            "--backend",
            "serial",
            "--port",
            path,
            "--episodes",
            "1",
            "--duration",
            "20",
            "--seed",
            "3",
            "--out",
            str(tmp_path),
            "--link-timeout",
            "30000",
            "-q",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        deadline = time.monotonic() + 120
        while emu.stats()["commands"] < 1000:  # two seconds of control, in device time
            assert host.poll() is None, (host.communicate(), emu.stats())
            assert time.monotonic() < deadline, ("qube-run sent no commands", emu.stats())
            time.sleep(0.05)
        t_kill = time.perf_counter()
        host.kill()
        host.wait(10)
        emu.lockstep_timeout = 0.05
        await_emulator_ticks(emu, 20, limit=max(0.0, deadline - time.monotonic()), poll=0.05)  # one per 50 ms
    finally:
        if host.poll() is None:
            host.kill()
            host.wait(10)
        emu.stop()
    rec = emu.record()
    stalls = {key: emu.stats()[key] for key in ("late_ticks", "slips", "missed_periods")}
    k_kill = np.flatnonzero(rec["wall"] >= t_kill)[0]
    last_seq = rec["command_seq"][-1]
    j = np.flatnonzero(rec["command_seq"] == last_seq)[0]
    z = j + np.flatnonzero(~rec["amp_enabled"][j:])[0]
    assert rec["amp_enabled"][j - 200 : z].all(), ("the host was not driving the motor until it died", stalls)
    assert z - j == 5 and rec["device_us"][z] - rec["device_us"][j] == 10_000, stalls
    # Bytes written before the kill are read by the first tick after it, so that command came no later.
    assert j <= k_kill
    assert rec["device_us"][z] - rec["device_us"][k_kill] <= 10_000
    assert len(rec["volts"]) - z >= 10, "too few ticks recorded after the trip"
    assert not rec["amp_enabled"][z:].any() and np.all(rec["volts"][z:] == 0.0)


# --- qube-emulate ---------------------------------------------------------------------------------


def test_cli_prints_the_path_first_and_stops_cleanly_on_sigterm(env, tmp_path):
    stats_file = tmp_path / "stats.json"
    proc, path = start_emulator(env, "--seed", "3", "--stats", str(stats_file))
    host = Host(path)
    host.send(Hello(nonce=3))
    frames = host.frames(_count(Telemetry, 10))
    host.close()
    assert frames[0].message.capabilities & Capability.EMULATED
    out, err = stop_process(proc)
    assert proc.returncode == 0 and out == "", err
    assert "Traceback" not in err and "stopped after" in err and "seed 3" in err
    stats = json.loads(stats_file.read_text())
    assert stats["stats"]["sessions"] == 1 and stats["stats"]["ticks"] >= 10
    assert not os.path.exists(path)


def test_cli_runs_a_named_plants_random_load_and_leaves_it_out_on_request(env, tmp_path):
    from qube_koopman.sim.pendulum.params_file import plant_file

    central = plant_file("calibrated-with-load").load.to_dict()
    for extra, load in (([], central), (["--no-load"], None)):
        stats_file = tmp_path / f"stats{len(extra)}.json"
        proc, _ = start_emulator(env, "--plant", "calibrated-with-load", *extra, "--stats", str(stats_file))
        out, err = stop_process(proc)
        assert proc.returncode == 0 and ("the plant's random load on the arm" in err) == (load is not None), err
        assert json.loads(stats_file.read_text())["stats"]["load"] == load


def test_cli_runs_a_plant_files_cable_relaxation_and_records_it(env, tmp_path):
    from qube_koopman.sim.pendulum import CableRelaxation, PendulumParameters
    from qube_koopman.sim.pendulum.params_file import PlantFile, save_plant

    save_plant(tmp_path / "plant.toml", PlantFile(PendulumParameters(), relaxation=CableRelaxation(0.26, 0.38, 1.0)))
    stats_file = tmp_path / "stats.json"
    proc, _ = start_emulator(env, "--plant", str(tmp_path / "plant.toml"), "--stats", str(stats_file))
    out, err = stop_process(proc)
    assert proc.returncode == 0 and "the cables' relaxation" in err, err
    assert json.loads(stats_file.read_text())["stats"]["relaxation"] == {
        "fast": 0.26,
        "relaxing": 0.38,
        "time_constant": 1.0,
    }


def test_cli_vanishes_on_request_and_exits(env):
    proc, path = start_emulator(env, "--vanish-at", "0.2", "-q")
    host = Host(path)
    host.send(Hello(nonce=3))
    with pytest.raises(serial.SerialException):
        host.frames(lambda f: False, timeout=5)
    host.close()
    out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0 and out == "" and err == ""


def test_cli_help_and_usage_errors(env):
    run = [sys.executable, "-m", "qube_koopman.sim.cli.emulate"]
    help_text = subprocess.run(run + ["--help"], capture_output=True, text=True, env=env)
    assert help_text.returncode == 0
    for option in (
        "--lockstep",
        "--drop-rate",
        "--corrupt-rate",
        "--latency",
        "--stall-at",
        "--amp-fault-at",
        "--vanish-at",
        "--seed",
        "qube-run --backend serial --port",
        "exit status",
    ):
        assert option in help_text.stdout
    bad = subprocess.run(run + ["--drop-rate", "2"], capture_output=True, text=True, env=env)
    assert bad.returncode == 2 and bad.stdout == "" and bad.stderr.count("\n") == 1
    assert bad.stderr.startswith("qube-emulate: error:") and "a rate must be in [0, 1]" in bad.stderr


def test_cli_without_a_compiler_says_so_in_one_line(env, tmp_path):
    bare = dict(env, PATH=str(tmp_path), XDG_CACHE_HOME=str(tmp_path / "empty_cache"))
    bare.pop("CC", None)
    proc = subprocess.run(
        [sys.executable, "-m", "qube_koopman.sim.cli.emulate"], capture_output=True, text=True, env=bare, cwd=REPO
    )
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.count("\n") == 1 and "no C compiler found" in proc.stderr and "Traceback" not in proc.stderr


def test_cli_stops_on_sigint_too(env):
    proc, _ = start_emulator(env, "-q")
    time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0 and err == ""
