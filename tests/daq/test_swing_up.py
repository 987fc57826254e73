"""The swing-up (daq.swing_up): the energy controller, the supervisor's swing-up limits, the phase."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from bridge_helpers import await_emulator_ticks, run_in_real_time

from qube_koopman.core.controller_file import load_controller
from qube_koopman.daq.backends import SimBackend
from qube_koopman.daq.backends.contract import Backend
from qube_koopman.daq.excitation import ExcitationSettings, generate_excitation
from qube_koopman.daq.loop import EpisodePlan, run_episode
from qube_koopman.daq.safety import SafetyLimits, StopRequest, SwingUpLimits
from qube_koopman.daq.session import FATAL_CAUSES
from qube_koopman.daq.sinks import MemorySink
from qube_koopman.daq.swing_up import EnergyController, SwingUp, run_swing_up
from qube_koopman.sim.pendulum import PendulumParameters, dynamics, total_energy

PARAMS = PendulumParameters()
CONTROLLER = load_controller(None, "backward-euler", 1.0 / 500.0)  # the rig's PD


def test_energy_is_the_models_pendulum_energy():
    """Upright at rest E0 = mp Lp g / 2, hanging at rest -E0; and at any (alpha, alpha_dot) with the arm
    at rest at its zero, the model's total energy (kinetic with the full inertia matrix, the spring
    unstretched)."""
    ctrl = EnergyController(PARAMS)
    e0 = PARAMS.mp * PARAMS.Lp * PARAMS.g / 2.0
    assert ctrl.reference_energy == pytest.approx(e0, rel=1e-15)
    assert ctrl.energy(0.0, 0.0) == pytest.approx(e0, rel=1e-15)
    assert ctrl.energy(math.pi, 0.0) == pytest.approx(-e0, rel=1e-15)
    # The workbook's pendulum: 0.024 kg, 0.129 m -> 0.0151850 J (worked by hand: 0.024 * 0.129 * 9.81 / 2).
    assert EnergyController(PendulumParameters.workbook()).reference_energy == pytest.approx(0.01518588, rel=1e-6)
    rng = np.random.default_rng(0)
    for alpha, alpha_dot in zip(rng.uniform(-math.pi, math.pi, 50), rng.uniform(-20, 20, 50)):
        state = [PARAMS.theta_rest, alpha, 0.0, alpha_dot]
        assert ctrl.energy(alpha, alpha_dot) == pytest.approx(float(total_energy(state, PARAMS)), rel=1e-12, abs=1e-15)


def _pendulum_energy_rate(state, volts, params=PARAMS) -> float:
    """dE/dt of the pendulum's energy along the model's own equations under ``volts``."""
    _, alpha, _, alpha_dot = state
    alpha_ddot = dynamics(state, volts, params)[3]
    inertia = params.Jp + params.mp * params.Lp**2 / 4.0
    return inertia * alpha_dot * alpha_ddot - params.mp * params.Lp * params.g / 2.0 * math.sin(alpha) * alpha_dot


def test_the_energy_controllers_voltage_gives_the_arm_its_acceleration_through_every_friction():
    """The voltage the controller asks for, applied to the model, gives the arm the acceleration it
    wanted with the arm moving (its Coulomb and static friction, its cables and dead zone all acting)."""
    params = replace(PARAMS, Cs=2 * PARAMS.Cr, stribeck_speed=0.1)
    ctrl = EnergyController(params, energy_margin=0.0)
    rng = np.random.default_rng(2)
    checked = 0
    for theta, alpha, theta_dot, alpha_dot in rng.uniform(
        [-0.5, -math.pi, -0.3, -15], [0.5, math.pi, 0.3, 15], (200, 4)
    ):
        volts = ctrl.voltage(theta, alpha, theta_dot, alpha_dot)
        if abs(volts) < 10.0:  # inside the clamp: the acceleration is the one asked for
            wanted = ctrl.acceleration(theta, alpha, theta_dot, alpha_dot)
            got = dynamics([theta, alpha, theta_dot, alpha_dot], volts, params)[2]
            assert got == pytest.approx(wanted, rel=1e-9, abs=1e-9)
            checked += 1
    assert checked > 100


@pytest.mark.parametrize("params", [PARAMS, PendulumParameters.workbook()], ids=["twin", "workbook"])
def test_energy_controller_pumps_energy_towards_the_upright(params):
    """With the arm at rest at its zero (the centering term then asks nothing), the voltage the
    controller gives makes the model's pendulum energy rise while it is below E0 and fall above,
    at the rate the acceleration it asks for predicts: -(mp Lp Lr / 2) a alpha_dot cos(alpha), less
    what the pendulum's own friction takes (Dp alpha_dot^2: none in the twin)."""
    ctrl = EnergyController(params, energy_margin=0.0)
    rng = np.random.default_rng(1)
    below = above = 0
    for alpha, alpha_dot in zip(rng.uniform(-math.pi, math.pi, 400), rng.uniform(-15, 15, 400)):
        state = np.array([params.theta_rest, alpha, 0.0, alpha_dot])
        volts = ctrl.voltage(*state)
        assert abs(volts) <= 10.0  # inside the clamp at this saturation: the rate is the one asked for
        rate = _pendulum_energy_rate(state, volts, params)
        a = ctrl.acceleration(*state)
        friction = params.Dp * alpha_dot**2
        pumped = -(params.mp * params.Lp * params.Lr / 2.0) * a * alpha_dot * math.cos(alpha)
        assert rate == pytest.approx(pumped - friction, rel=1e-6, abs=1e-12)
        if ctrl.energy(alpha, alpha_dot) < ctrl.reference_energy:
            below += 1
            assert rate + friction >= 0.0
        else:
            above += 1
            assert rate + friction <= 0.0
    assert below > 100 and above > 50


def test_energy_controller_centers_the_arm_and_kicks_a_pendulum_at_rest():
    """Hanging at rest (sign(0) taken as +1) it pushes; with the pendulum upright at rest it only
    centres the arm: the acceleration is -kp theta - kd theta_dot."""
    ctrl = EnergyController(PARAMS)
    assert ctrl.acceleration(0.0, math.pi, 0.0, 0.0) != 0.0
    still = replace(ctrl, energy_margin=0.0)
    assert still.acceleration(0.3, 0.0, -0.5, 0.0) == pytest.approx(
        -still.centering_kp * 0.3 + still.centering_kd * 0.5
    )


# --- the supervisor's swing-up limits, through the loop -------------------------------------------


class _Recording(SimBackend):
    """The simulator hanging at rest, recording each tick's reading and command."""

    def __init__(self, **kwargs) -> None:
        super().__init__(start="hanging", seed=3, **kwargs)
        self.reads: list[tuple[float, float]] = []
        self.writes: list[float] = []

    def read(self):
        y = super().read()
        self.reads.append(y)
        return y

    def write(self, volts: float) -> None:
        super().write(volts)
        self.writes.append(volts)  # a command the stopped simulator refuses is not recorded


@dataclass(frozen=True)
class _Push(EnergyController):
    """A faulty swing-up controller: a constant voltage, whatever the state."""

    volts: float = 8.0

    def voltage(self, theta, alpha, theta_dot, alpha_dot):
        return self.volts


def _plan(swing: SwingUp, n: int = 500) -> EpisodePlan:
    settings = ExcitationSettings(n_samples=n, window_start=n // 5, window_stop=4 * n // 5)
    return EpisodePlan(CONTROLLER, generate_excitation((1, 2, 3), settings), swing_up=swing)


def test_supervisor_stops_a_swing_up_that_pushes_the_arm_past_its_limit():
    """The arm's swing-up limit: 0 V in the tick whose reading is past it, the reason in the log,
    which holds no samples; the run goes on (the cause is not fatal)."""
    backend = _Recording()
    sink = MemorySink()
    limit = math.radians(60.0)
    swing = SwingUp(energy=_Push(), limits=SwingUpLimits(arm_limit=limit, time_limit=5.0))
    result = run_episode(backend, _plan(swing), [sink])
    assert result.status == "aborted" and result.cause == "swing-up"
    assert result.cause not in FATAL_CAUSES
    assert "|theta|" in result.reason and "swing-up" in result.reason
    past = [i for i, (theta, _) in enumerate(backend.reads) if abs(theta) > limit]
    assert past and past[0] == len(backend.reads) - 1  # stopped at the first reading past the limit
    assert set(backend.writes[past[0] :]) == {0.0}  # ... with 0 V in that tick
    assert all(v == 8.0 for v in backend.writes[: past[0]])  # the voltage asked for until then
    (episode,) = sink.episodes
    assert episode.samples == [] and episode.outcome.status == "aborted"
    assert episode.outcome.reason == result.reason
    swung = episode.metadata.extra["swing_up"]
    assert swung["outcome"] == "failed" and swung["reason"] == result.reason
    assert swung["max_abs_theta"] <= limit  # the readings before the stop


def test_supervisor_clamps_the_swing_up_voltage():
    backend = _Recording()
    swing = SwingUp(energy=_Push(volts=50.0), limits=SwingUpLimits(max_voltage=3.0, time_limit=0.5))
    run_episode(backend, _plan(swing), [MemorySink()])
    assert max(abs(v) for v in backend.writes) == 3.0


def test_supervisor_gives_up_a_swing_up_after_its_time_limit():
    """A controller that never swings the pendulum up: after the time limit (counted in ticks) 0 V, and the
    log says the swing-up gave up."""
    backend = _Recording()
    sink = MemorySink()
    swing = SwingUp(energy=_Push(volts=0.0), limits=SwingUpLimits(time_limit=0.5))
    result = run_episode(backend, _plan(swing), [sink])
    assert result.cause == "swing-up" and "gave up" in result.reason and "0.5 s" in result.reason
    assert len(backend.reads) == 251  # ticks 0..249 ran the controller, tick 250 put 0 V
    assert backend.writes[250:] and set(backend.writes[250:]) == {0.0}  # (the loop's stop writes 0 V again)
    assert sink.episodes[0].metadata.extra["swing_up"]["duration"] == pytest.approx(0.5)


def test_stop_during_a_swing_up_puts_0_v_in_the_tick_that_sees_it():
    stop = StopRequest()

    class Stopping(_Recording):
        def read(self):
            if len(self.reads) == 100:
                stop.request("interrupted by SIGINT", 2)
            return super().read()

    backend = Stopping()
    sink = MemorySink()
    result = run_episode(backend, _plan(SwingUp(energy=_Push(volts=1.0))), [sink], stop=stop)
    assert result.cause == "stop" and "swing-up" in result.reason
    assert len(backend.reads) == 101 and backend.writes[:100] == [1.0] * 100
    assert set(backend.writes[100:]) == {0.0}
    assert sink.episodes == []  # stopped before the episode: no log, as at the start gate


class _Scripted(Backend):
    """Readings from a script (the last one repeated), each tick's command recorded."""

    def __init__(self, readings) -> None:
        self.readings = list(readings)
        self.writes: list[float] = []

    def start(self) -> None:
        pass

    def read(self):
        return self.readings[min(len(self.writes), len(self.readings) - 1)]

    def write(self, volts: float) -> None:
        self.writes.append(volts)

    def stop(self) -> None:
        pass


def test_the_catch_takes_over_without_a_derivative_kick():
    """A pendulum already within the catch angle with the arm off its zero (the previous episode's, still
    balanced, over the serial link): the controller takes over with the state the held errors give it, so
    its first command is the PD's proportional part (6 V/rad of the arm, 30 of the pendulum) and the
    commands do not step while the readings hold; from zero state its derivative takes the arm's error for
    a step and the first command saturates."""
    reading = (0.18, 0.01)
    swing = SwingUp(limits=SwingUpLimits(time_limit=0.2))
    run_swing_up(held := _Scripted([reading]), CONTROLLER.system, swing, SafetyLimits(), StopRequest())
    proportional = 6.0 * 0.18 + 30.0 * 0.01
    assert held.writes[0] == pytest.approx(proportional, abs=0.15)  # the filter 99 % settled after 0.1 s
    assert max(held.writes[:-1]) - min(held.writes[:-1]) < 0.15 and held.writes[-1] == 0.0  # gave up: 0 V
    kicked = _Scripted([reading])
    run_swing_up(kicked, CONTROLLER.system, replace(swing, catch_hold=0.0), SafetyLimits(), StopRequest())
    assert kicked.writes[0] == 10.0  # (6 + 81.8) V/rad x 0.18 rad and more: the clamp


def test_prepare_is_called_once_settled_and_the_controller_balances_until_it_is_ready():
    """``prepare`` (the log opening, over the serial link): called once with the settled report; the balance
    controller goes on commanding every tick until its poll says ready, and the phase returns that report; a
    pendulum that falls meanwhile fails the phase with 0 V."""
    upright = (0.0, 0.01)
    swing = SwingUp(settle_time=0.1)
    given, polls = [], []

    def prepare(report):
        given.append(report)
        return lambda: polls.append(len(backend.writes)) or len(polls) > 20

    backend = _Scripted([upright])
    report = run_swing_up(backend, CONTROLLER.system, swing, SafetyLimits(), StopRequest(), prepare=prepare)
    assert given == [report] and report.outcome == "settled" and report.duration == pytest.approx(0.1)
    assert len(backend.writes) == 50 + 20  # the settling's ticks, then one per poll until ready
    assert all(abs(v - backend.writes[0]) < 0.2 and v != 0.0 for v in backend.writes)  # still balancing
    falls = _Scripted([upright] * 60 + [(0.0, 1.0)])
    report = run_swing_up(
        falls, CONTROLLER.system, swing, SafetyLimits(), StopRequest(), prepare=lambda r: lambda: False
    )
    assert report.outcome == "failed" and "fell after it settled" in report.reason and falls.writes[-1] == 0.0


def test_an_arm_left_past_its_limit_is_waited_for_at_0_v():
    """The previous episode's fall left the arm past its limit: 0 V until it is back within, then the pump;
    past the limit again after that, the supervisor gives up with 0 V in that tick."""
    hanging = math.pi - 0.01
    script = [(2.0, hanging)] * 5 + [(1.2, hanging)] * 5 + [(1.7, hanging)]
    backend = _Scripted(script)
    report = run_swing_up(backend, CONTROLLER.system, SwingUp(), SafetyLimits(), StopRequest())
    assert backend.writes[:5] == [0.0] * 5 and all(v != 0.0 for v in backend.writes[5:10])
    assert backend.writes[10:] == [0.0] and report.outcome == "failed" and "|theta| = 1.700" in report.reason
    assert report.max_abs_theta == 1.2  # what the swing-up drove, not what it waited out
    waited = _Scripted([(2.0, hanging)])
    report = run_swing_up(
        waited, CONTROLLER.system, SwingUp(limits=SwingUpLimits(time_limit=0.1)), SafetyLimits(), StopRequest()
    )
    assert set(waited.writes) == {0.0} and len(waited.writes) == 51 and "gave up" in report.reason
    nan = _Scripted([(math.nan, hanging)])
    report = run_swing_up(nan, CONTROLLER.system, SwingUp(), SafetyLimits(), StopRequest())
    assert nan.writes == [0.0] and report.outcome == "failed"  # a reading that is not a number: at once


# --- qube-run --swing-up on the simulator ----------------------------------------------------------


def test_qube_run_swing_up_records_complete_episodes_after_the_catch(tmp_path, capsys):
    """Three seeds from hanging at rest: each swung up, caught and settled within the limits, then the
    recorded episode complete, its samples inside the clamp and the arm's limit, started as an
    upright episode starts (controller state zero, the pendulum near upright) and driven by the same
    excitation as a run without the swing-up."""
    from qube_koopman.daq.cli.run import main
    from qube_koopman.daq.log import read_episode

    common = ["--episodes", "3", "--seed", "4", "--duration", "2", "--n-jobs", "1", "-q"]
    assert main([*common, "--swing-up", "--out", str(tmp_path / "up")]) == 0
    assert "3 complete, 0 aborted" in capsys.readouterr().out
    assert main([*common, "--out", str(tmp_path / "upright")]) == 0
    swung = [read_episode(p) for p in sorted((tmp_path / "up").glob("*.mcap"))]
    upright = [read_episode(p) for p in sorted((tmp_path / "upright").glob("*.mcap"))]
    assert len(swung) == len(upright) == 3
    for episode, plain in zip(swung, upright):
        meta = episode.metadata
        report = meta.extra["swing_up"]
        assert meta.status == "complete" and len(episode.t) == 1000
        assert meta.extra["backend"]["start"] == "hanging"
        assert report["outcome"] == "settled" and report["n_catches"] >= 1
        assert report["duration"] <= 10.0
        assert report["max_abs_theta"] < math.pi / 2 and report["max_abs_voltage"] <= 10.0
        assert np.max(np.abs(episode.plant_input)) <= 10.0
        assert np.max(np.abs(episode.theta)) < math.pi / 2
        assert abs(episode.alpha[0]) < math.radians(5.0) and abs(episode.theta[0]) < 0.1
        assert np.all(episode.controller_state[0] == 0.0)
        for signal in ("target_theta", "target_alpha", "feedforward"):
            np.testing.assert_array_equal(getattr(episode, signal), getattr(plain, signal))


def test_qube_run_swing_up_options_need_swing_up(tmp_path, capsys):
    from qube_koopman.daq.cli.run import main

    assert main(["--catch-angle", "10", "--out", str(tmp_path)]) == 2
    assert "--catch-angle is for --swing-up" in capsys.readouterr().err


def test_qube_run_failed_swing_up_writes_a_log_that_says_why(tmp_path, capsys):
    """A swing-up that runs out of time: 0 V, a log without samples, closed aborted with the reason (exit 0:
    the supervisor's recorded outcome, as a safety stop); the next episode swings up again."""
    from qube_koopman.daq.cli.run import main
    from qube_koopman.daq.log import read_episode

    args = ["--swing-up", "--swing-up-time", "1", "--episodes", "2", "--seed", "1", "--duration", "2", "-q"]
    assert main([*args, "--n-jobs", "1", "--out", str(tmp_path)]) == 0
    assert "0 complete, 2 aborted" in capsys.readouterr().out
    logs = [read_episode(p) for p in sorted(tmp_path.glob("*.mcap"))]
    assert len(logs) == 2
    for episode in logs:
        assert len(episode.t) == 0 and episode.metadata.status == "aborted"
        assert episode.metadata.status_reason == "swing-up gave up: not caught and settled within 1 s"
        report = episode.metadata.extra["swing_up"]
        assert report["outcome"] == "failed" and report["duration"] == pytest.approx(1.0)


# --- over the serial link: the emulated bridge ------------------------------------------------------


def test_swing_up_over_the_serial_link(core, tmp_path):
    """The same phase over --backend serial, paced by the bridge's telemetry (lockstep): the emulated
    pendulum left hanging at the session's start is swung up, caught and settled within the limits,
    then the episode is recorded complete. The link's timeout runs on the bridge's device clock and
    the bridge's lockstep on the host's waiting (``HostWait``): a machine that holds either process up
    for a while loses no tick (on the wall clock a loaded run once lost the link before the start)."""

    from bridge_helpers import HostWait, lockstep_backend

    from qube_koopman.daq.log import read_episode
    from qube_koopman.daq.sinks import McapSink
    from qube_koopman.sim.bridge import BridgeEmulator

    wait = HostWait()
    emu = BridgeEmulator(
        seed=9, core=core, lockstep=True, lockstep_timeout=0.1, lockstep_clock=wait, start_upright=False
    )
    emu.start()
    backend = lockstep_backend(emu, wait, link_timeout=0.2)
    sink = McapSink(tmp_path)
    result = _swing_up_episode_on(emu, backend, sink, 2.0)
    assert result.complete, result.reason
    episode = read_episode(sink.paths[0])
    report = episode.metadata.extra["swing_up"]
    assert report["outcome"] == "settled" and report["catch_time"] > 1.0  # it started far from upright
    assert report["duration"] <= 10.0
    assert report["max_abs_theta"] < math.pi / 2 and report["max_abs_voltage"] <= 10.0
    assert len(episode.t) == 1000 and np.max(np.abs(episode.plant_input)) <= 10.0
    assert abs(episode.alpha[0]) < math.radians(5.0)


def test_over_the_serial_link_the_log_opens_while_the_settled_pendulum_stays_balanced(core, tmp_path):
    """The bridge's watchdog switches the motor off after five ticks without a command: a log slow to open
    between the swing-up and the episode would trip it with the pendulum balanced on the motor. The log
    opens while the balance controller keeps commanding every tick (here a log that takes 8 of the bridge's
    ticks), and the episode then starts: complete, the watchdog never tripped."""
    import time

    from bridge_helpers import HostWait, lockstep_backend

    from qube_koopman.daq.log import read_episode
    from qube_koopman.daq.sinks import McapSink
    from qube_koopman.sim.bridge import BridgeEmulator

    wait = HostWait()
    ticked: list[int] = []

    class SlowDisk(McapSink):
        def open(self, metadata):
            first = emu.stats()["ticks"]
            deadline = time.monotonic() + 10.0  # ticks only while the loop answers the bridge (lockstep)
            while emu.stats()["ticks"] < first + 8 and time.monotonic() < deadline:
                time.sleep(0.001)
            ticked.append(emu.stats()["ticks"] - first)
            super().open(metadata)

    emu = BridgeEmulator(
        seed=9,
        core=core,
        lockstep=True,
        lockstep_timeout=0.01,
        lockstep_clock=wait,
        start_upright=False,
        record_ticks=20_000,
    )
    emu.start()
    backend = lockstep_backend(emu, wait, link_timeout=0.2)
    sink = SlowDisk(tmp_path)
    result = _swing_up_episode_on(emu, backend, sink, 1.0)
    assert result.complete, result.reason
    assert ticked and ticked[0] >= 8  # the bridge ticked on, answered, while the log opened
    episode = read_episode(sink.paths[0])
    report = episode.metadata.extra["swing_up"]
    assert episode.device_time[0] >= report["duration"] + 8 * 0.002
    rec = emu.record()
    mine = rec["session"] == 1
    driven = np.flatnonzero(rec["command_mv"][mine] != 0)  # the swing-up's first command to the episode's last
    assert np.all(rec["amp_enabled"][mine][driven[0] : driven[-1] + 1]), "the watchdog never tripped"
    assert episode.metadata.backend_stats["ticks_skipped"] == 0


def test_qube_run_swing_up_over_serial_against_qube_emulate(env, tmp_path, capsys):
    """``qube-run --backend serial --swing-up`` against ``qube-emulate --hanging`` (in lockstep, its own
    process): two episodes, the first swung up from hanging at rest, the second from where the first left
    the pendulum (still balanced, the arm off its zero). Each is caught and settled within 10 s of the
    bridge's clock, never past the arm's limit nor the clamp, and its recorded samples start after the catch,
    on the bridge's clock, as on the twin: controller state zero, near upright, the twin's excitation."""
    from qube_koopman.daq.cli.run import main
    from qube_koopman.daq.log import read_episode

    run = ["--swing-up", "--episodes", "2", "--duration", "2", "--seed", "7"]
    status, out, _, folder, _ = run_in_real_time(env, ["--hanging", "--lockstep", "--seed", "3"], run, tmp_path, capsys)
    assert status == 0 and "2 complete, 0 aborted" in out, out
    assert main([*run, "--n-jobs", "1", "-q", "--out", str(tmp_path / "twin")]) == 0
    twin = [read_episode(p) for p in sorted((tmp_path / "twin").glob("*.mcap"))]
    logs = [read_episode(p) for p in sorted(folder.glob("*.mcap"))]
    assert len(logs) == len(twin) == 2
    for episode, on_twin in zip(logs, twin):
        meta = episode.metadata
        report = meta.extra["swing_up"]
        assert meta.status == "complete" and meta.backend == "serial" and len(episode.t) == 1000
        assert report.keys() == on_twin.metadata.extra["swing_up"].keys()
        assert report["outcome"] == "settled" and report["n_catches"] >= 1
        assert report["max_abs_theta"] < math.pi / 2 and report["max_abs_voltage"] <= 10.0
        # The bridge's clock since the session's first telemetry: the swing-up's ticks (then those that
        # kept the pendulum balanced while the log opened), then the samples.
        assert report["catch_time"] < report["duration"] <= episode.device_time[0] <= 10.0
        assert np.max(np.abs(episode.theta)) < math.pi / 2 and np.max(np.abs(episode.plant_input)) <= 10.0
        assert abs(episode.alpha[0]) < math.radians(5.0) and abs(episode.theta[0]) < 0.1
        assert np.all(episode.controller_state[0] == 0.0)
        for signal in ("target_theta", "target_alpha", "feedforward"):
            np.testing.assert_array_equal(getattr(episode, signal), getattr(on_twin, signal))
    assert logs[0].metadata.extra["swing_up"]["catch_time"] > 1.0  # from hanging: pumped first


def _swing_up_episode_on(emulator, backend, sink, duration: float):
    """One swung-up episode of ``duration`` s of the rig's controller (the run's first seeds) through ``backend``
    to the started ``emulator``, which is stopped after it."""
    import time

    from qube_koopman.daq.session import excitation_settings, plan_episodes, run_seeds

    seeds, _ = run_seeds(1, 1)
    swing = SwingUp()
    (plan,) = plan_episodes(CONTROLLER, seeds, excitation_settings(duration), source="test", swing_up=swing)
    try:
        return run_episode(backend, plan, [sink])
    finally:
        backend.close()
        time.sleep(0.05)  # the link's last bytes reach the emulator before it stops
        emulator.stop()


def _session_ticks(record: Path, session: int) -> dict[str, np.ndarray]:
    """The emulated bridge's per-tick record (``qube-emulate --record``) of one session (HELLOs counted)."""
    rows = np.genfromtxt(record, delimiter=",", names=True)
    rows = rows[rows["session"] == session]
    return {name: rows[name] for name in rows.dtype.names}


def test_a_swing_up_giving_up_over_serial_puts_0_v_through_the_bridge(env, tmp_path, capsys):
    """The time limit over the serial link: the bridge applies the swing-up's commands within its clamp (1 V)
    until the limit's tick on its own clock, then 0 V to the end of the session; the log says why (exit 0)."""
    from qube_koopman.daq.log import read_episode

    record = tmp_path / "ticks.csv"
    emulator = ["--hanging", "--lockstep", "--seed", "3", "--record", str(record), "--force"]
    run = ["--swing-up", "--swing-up-time", "1", "--swing-up-voltage", "1", "--episodes", "1", "--duration", "2"]
    status, out, _, folder, _ = run_in_real_time(env, emulator, run, tmp_path, capsys)
    assert status == 0 and "0 complete, 1 aborted" in out, out
    (log,) = folder.glob("*.mcap")
    meta = read_episode(log).metadata
    assert meta.status_reason == "swing-up gave up: not caught and settled within 1 s"
    ticks = _session_ticks(record, 2)  # the first session connects, the second is the episode's
    driven = np.flatnonzero(ticks["volts"] != 0.0)
    assert driven.size > 400 and np.max(np.abs(ticks["volts"])) <= 1.012  # the QUBE's 24 mV PWM steps
    seconds = (ticks["device_us"][driven[-1]] - ticks["device_us"][0]) * 1e-6
    assert 0.95 < seconds <= 1.02  # the last tick driven is the limit's, on the bridge's clock
    assert np.all(ticks["volts"][driven[-1] + 1 :] == 0.0) and ticks["command_mv"][-1] == 0
    assert driven[-1] + 1 < len(ticks["volts"])  # ... and the bridge ticked on at 0 V


@pytest.mark.parametrize("signame, status", [("SIGINT", 130), ("SIGTERM", 143)])
def test_a_signal_during_a_swing_up_over_serial_puts_0_v_through_the_bridge(signame, status, core, env, tmp_path):
    """Ctrl-C or SIGTERM to ``qube-run --backend serial --swing-up`` while it pumps (a 1 V clamp: slow to
    swing up): exit 130 or 143, no log (the episode never started), and the bridge's last command 0 V,
    applied from the tick after it came to the end of the session."""
    import signal
    import subprocess
    import sys
    import time

    from qube_koopman.sim.bridge import BridgeEmulator

    # In this process, to watch it: the bridge ticks once the host has answered (or after 0.1 s).
    emu = BridgeEmulator(
        seed=3, core=core, lockstep=True, lockstep_timeout=0.1, start_upright=False, record_ticks=10_000
    )
    path = emu.start()
    out = tmp_path / "runs"
    command = [sys.executable, "-m", "qube_koopman.daq.cli.run", "--backend", "serial", "--port", path, "-q"]
    command += ["--swing-up", "--swing-up-voltage", "1", "--out", str(out), "--link-timeout", "1000"]
    run = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.monotonic() + 60.0
        while emu.stats()["sessions"] < 2 or emu.stats()["commands"] < 100:  # pumping for 0.2 s
            assert run.poll() is None, run.communicate()
            assert time.monotonic() < deadline, "qube-run did not start its swing-up in 60 s"
            time.sleep(0.01)
        run.send_signal(getattr(signal, signame))
        _, err = run.communicate(timeout=30)
    finally:
        if run.poll() is None:
            run.kill()
            run.communicate()
        await_emulator_ticks(emu, 2)  # the second began after qube-run's last bytes
        emu.stop()
    assert run.returncode == status, err
    assert f"interrupted by {signame}" in err and not list(out.glob("*.mcap"))
    ticks = emu.record()
    mine = ticks["session"] == 2
    volts, commands = ticks["volts"][mine], ticks["command_mv"][mine]
    driven = np.flatnonzero(volts != 0.0)
    assert driven.size >= 100 and np.max(np.abs(volts)) <= 1.012  # the QUBE's 24 mV PWM steps
    assert commands[-1] == 0 and np.all(volts[driven[-1] + 1 :] == 0.0) and driven[-1] + 1 < volts.size
