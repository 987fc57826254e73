"""The acquisition loop (daq.loop) with scripted backends and the simulator: safety, faults, logging."""

from __future__ import annotations

import gc
import math
import signal
import threading
import time

import numpy as np
import pytest
from _episodes import QUBE_PD, assert_follows_controller, nan_controller

from qube_koopman.daq.backends import Backend, BackendFault, Pacing, SimBackend
from qube_koopman.core.controller_file import ControllerInfo
from qube_koopman.daq.excitation import Excitation, ExcitationSettings, generate_excitation
from qube_koopman.daq.loop import EpisodePlan, run_episode
from qube_koopman.daq.safety import SafetyLimits, StopRequest
from qube_koopman.daq.sinks import MemorySink
from qube_koopman.sim.pendulum import SensorModel, simulate_closed_loop

RIG_GAINS = {"kp_theta": 6.0, "kd_theta": 1.8, "kp_alpha": 30.0, "kd_alpha": 2.5, "tau": 50.0}
CONTROLLER = ControllerInfo(QUBE_PD, "backward-euler", RIG_GAINS)


class ScriptedBackend(Backend):
    """Plays back a list of (theta, alpha) readings, one per read; records every command.

    ``on_read[i]`` (optional) is called at the i-th read: raise a fault, set a stop...
    """

    name = "scripted"

    def __init__(self, readings, pacing: Pacing = Pacing.NONE, on_read=None) -> None:
        self.readings = list(readings)
        self.pacing = pacing
        self.on_read = dict(on_read or {})
        self.reads = 0
        self.writes: list[float] = []
        self.started = 0
        self.stopped = 0

    def start(self) -> None:
        self.started += 1

    def read(self):
        i = self.reads
        self.reads += 1
        if i in self.on_read:
            self.on_read[i]()
        return self.readings[min(i, len(self.readings) - 1)]

    def write(self, volts: float) -> None:
        self.writes.append(volts)

    def stop(self) -> None:
        self.stopped += 1


def _plan(n: int, target_theta=0.0, target_alpha=0.0, feedforward=0.0) -> EpisodePlan:
    ex = Excitation(np.full(n, float(target_theta)), np.full(n, float(target_alpha)), np.full(n, float(feedforward)))
    return EpisodePlan(CONTROLLER, ex, {"seeds": {"target_theta": 1, "target_alpha": 2, "feedforward": 3}})


def _fault(message="link lost"):
    def raise_fault():
        raise BackendFault(message)

    return raise_fault


# --- safety ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "bad, limit_text",
    [
        ((1.6, 0.0), "|theta|"),
        ((-1.6, 0.0), "|theta|"),
        ((0.0, 0.8), "|alpha|"),
        ((0.0, -0.8), "|alpha|"),
        ((0.0, math.nan), "|alpha|"),
    ],
)
def test_limit_aborts_with_zero_volts_in_the_same_tick(bad, limit_text):
    readings = [(0.0, 0.01)] * 6 + [bad] + [(0.0, 0.01)] * 10
    backend = ScriptedBackend(readings)
    sink = MemorySink()
    result = run_episode(backend, _plan(100), [sink])
    assert result.status == "aborted" and result.cause == "safety" and limit_text in result.reason
    # Read 0 is the start gate; ticks 0..5 ran normally, tick 6 saw the bad reading.
    assert result.n_samples == 6
    episode = sink.episodes[0].episode()
    assert len(episode) == 6 and episode.metadata.status == "aborted"
    assert episode.plant_input[-1] == 0.0
    assert backend.writes[5] == 0.0, "0 V must be written in the tick that saw the violation"
    assert all(v != 0.0 for v in backend.writes[:5])
    assert backend.stopped == 1


def test_limits_are_configurable():
    readings = [(0.0, 0.01)] * 3 + [(0.0, 0.2)] * 5
    result = run_episode(
        ScriptedBackend(readings), _plan(50), [MemorySink()], limits=SafetyLimits(alpha_limit=0.15, start_alpha=0.05)
    )
    assert result.cause == "safety" and "0.150 rad" in result.reason
    assert run_episode(ScriptedBackend(readings), _plan(50), [MemorySink()]).complete


def test_command_is_clamped_to_ten_volts_and_flagged():
    # alpha = +0.05 rad: the PD asks for +7.2 V decaying to +3.9 V; the feedforward pushes past +10 V.
    backend = ScriptedBackend([(0.0, 0.05)] * 20)
    sink = MemorySink()
    assert run_episode(backend, _plan(10, feedforward=8.0), [sink]).complete
    ep = sink.episodes[0].episode()
    assert np.all(ep.control_output + ep.feedforward > 10.0)
    assert np.all(ep.plant_input == 10.0) and np.all(ep.saturation == 1)
    assert backend.writes[:10] == [10.0] * 10
    backend = ScriptedBackend([(0.0, -0.05)] * 20)
    sink = MemorySink()
    run_episode(backend, _plan(10, feedforward=-8.0), [sink])
    assert np.all(sink.episodes[0].episode().saturation == -1) and min(backend.writes) == -10.0


def test_start_gate_holds_zero_volts_until_upright():
    tilted, upright = (0.0, math.radians(10)), (0.0, math.radians(3))
    readings = [tilted] * 4 + [upright] + [(0.0, 0.001)] * 20
    backend = ScriptedBackend(readings)
    sink = MemorySink()
    result = run_episode(backend, _plan(5), [sink])
    assert result.complete
    assert backend.writes[:4] == [0.0] * 4, "no control while |alpha| >= 5 deg"
    # The gate took reads 0..4; the episode's first sample is read 5.
    assert sink.episodes[0].episode().alpha[0] == 0.001


def test_start_gate_times_out_without_opening_the_log():
    backend = ScriptedBackend([(0.0, math.radians(10))] * 10_000)
    sink = MemorySink()
    result = run_episode(backend, _plan(5), [sink], limits=SafetyLimits(start_timeout=1.0))
    assert result.status == "aborted" and result.cause == "start" and not result.started
    assert sink.episodes == []
    assert set(backend.writes) == {0.0} and backend.reads == 500
    assert backend.stopped == 1


# --- faults and stops --------------------------------------------------------------------------


def test_backend_fault_on_read_closes_the_log_aborted():
    backend = ScriptedBackend([(0.0, 0.01)] * 50, on_read={8: _fault("link lost")})
    sink = MemorySink()
    result = run_episode(backend, _plan(40), [sink])
    assert result.cause == "fault" and "link lost" in result.reason
    ep = sink.episodes[0].episode()
    assert len(ep) == 7 and ep.metadata.status == "aborted" and "link lost" in ep.metadata.status_reason
    assert np.array_equal(ep.t, np.arange(7) / 500)
    assert backend.writes[-1] == 0.0 and backend.stopped == 1


def test_backend_fault_on_write_stops_the_motor():
    class FailingWrite(ScriptedBackend):
        def write(self, volts):
            super().write(volts)
            if len(self.writes) == 4 and volts != 0.0:
                raise BackendFault("amplifier fault")

    backend = FailingWrite([(0.0, 0.01)] * 50)
    result = run_episode(backend, _plan(40), [MemorySink()])
    assert result.cause == "fault" and "amplifier fault" in result.reason and result.n_samples == 3
    assert backend.writes[-1] == 0.0 and backend.stopped == 1


def test_stop_request_puts_zero_volts_in_the_tick_that_sees_it():
    stop = StopRequest()
    backend = ScriptedBackend([(0.0, 0.02)] * 50, on_read={6: lambda: stop.request("operator")})
    sink = MemorySink()
    result = run_episode(backend, _plan(40), [sink], stop=stop)
    assert result.cause == "stop" and result.reason == "operator" and result.n_samples == 6
    assert backend.writes[5] == 0.0 and sink.episodes[0].episode().plant_input[-1] == 0.0


def test_signal_handlers_only_during_the_episode():
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    seen = {}

    def peek():
        seen["handlers"] = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
        seen["gc"] = gc.isenabled()
        # A real signal in the middle of the episode, delivered to this (main) thread.
        signal.raise_signal(signal.SIGTERM)

    backend = ScriptedBackend([(0.0, 0.01)] * 50, on_read={10: peek})
    sink = MemorySink()
    result = run_episode(backend, _plan(40), [sink])
    assert result.cause == "stop" and result.signal == signal.SIGTERM and "SIGTERM" in result.reason
    assert result.n_samples == 10 and sink.episodes[0].outcome.status == "aborted"
    assert all(h not in before for h in seen["handlers"])
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
    assert seen["gc"] is False and gc.isenabled()


class _BrokenSink:
    def __init__(self, required: bool, fail_at: int = 3) -> None:
        self.required = required
        self.fail_at = fail_at
        self.closed = None

    def open(self, metadata):
        pass

    def write(self, sample):
        if sample.k == self.fail_at:
            raise OSError("disk full")

    def close(self, outcome):
        self.closed = outcome


def test_failing_log_aborts_the_episode_but_an_optional_view_does_not():
    broken = _BrokenSink(required=True)
    # Paced, so the writer thread (polling every 10 ms) sees the failure long before the end.
    backend = ScriptedBackend([(0.0, 0.01)] * 10, pacing=Pacing.LOOP)
    result = run_episode(backend, _plan(500), [broken])
    assert result.cause == "log" and "disk full" in result.reason
    assert result.n_samples < 500 and backend.writes[result.n_samples - 1] == 0.0
    assert broken.closed.status == "aborted", "a failed log is still closed with the abort"

    view, memory = _BrokenSink(required=False), MemorySink()
    result = run_episode(ScriptedBackend([(0.0, 0.01)] * 100), _plan(50), [view, memory])
    assert result.complete and len(memory.episodes[0].samples) == 50
    assert any("disk full" in e for e in result.sink_errors)


def test_sink_that_cannot_open_means_no_episode():
    class Unopenable(MemorySink):
        def open(self, metadata):
            raise PermissionError("read-only folder")

    backend = ScriptedBackend([(0.0, 0.01)] * 100)
    result = run_episode(backend, _plan(50), [Unopenable()])
    assert result.cause == "log" and "read-only" in result.reason and result.n_samples == 0
    assert backend.writes[-1] == 0.0 and backend.stopped == 1


# --- what is logged ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sim_episode():
    ex = generate_excitation((434, 696, 394), ExcitationSettings(n_samples=3000, window_start=500, window_stop=2500))
    backend = SimBackend(seed=5)
    sink = MemorySink()
    result = run_episode(backend, EpisodePlan(CONTROLLER, ex), [sink])
    return result, sink.episodes[0].episode(), backend


def test_controller_state_and_output_follow_the_controller(sim_episode):
    result, ep, _ = sim_episode
    assert result.complete and len(ep) == 3000
    assert_follows_controller(ep)


def test_loop_on_the_simulator_matches_the_batched_closed_loop():
    # Exact angles: with encoders, float rounding differences between the per-tick and the
    # batched integrator eventually flip one count and the runs part by a count or two.
    ex = generate_excitation((434, 696, 394), ExcitationSettings(n_samples=3000, window_start=500, window_stop=2500))
    sensor = SensorModel(counts_per_rev=None)
    backend = SimBackend(sensor=sensor, seed=7)
    sink = MemorySink()
    assert run_episode(backend, EpisodePlan(CONTROLLER, ex), [sink]).complete
    ep = sink.episodes[0].episode()
    described = backend.describe()
    # The episode's encoder zero offset was drawn at its start; the batched run uses the same sensor.
    episode_sensor = SensorModel(**described["sensor"])
    assert episode_sensor.alpha_offset != 0.0
    run = simulate_closed_loop(
        described["initial_state"], QUBE_PD, ep.references, ep.feedforward, sensor=episode_sensor
    )
    np.testing.assert_allclose(ep.states, run.measurements, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ep.controller_state, run.controller_states, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ep.plant_input, run.plant_input, rtol=0, atol=1e-9)


def test_sim_starts_upright_with_a_seeded_perturbation(sim_episode):
    _, ep, backend = sim_episode
    meta = ep.metadata
    assert meta.backend == "sim" and meta.extra["backend"]["seed"] == 5
    alpha0 = meta.extra["backend"]["initial_state"][1]
    assert 0 < abs(alpha0) <= math.radians(2.0)
    # Encoder grid: 2048 counts per revolution.
    step = 2 * math.pi / 2048
    np.testing.assert_allclose(np.round(ep.alpha / step) * step, ep.alpha, atol=1e-12)
    again = SimBackend(seed=5)
    again.start()
    assert again.describe()["initial_state"][1] == alpha0


def test_metadata_says_what_ran(sim_episode):
    result, ep, _ = sim_episode
    meta = ep.metadata
    assert meta.controller.gains == RIG_GAINS and meta.sample_rate_hz == 500.0
    assert meta.extra["safety"]["max_voltage"] == 10.0 and meta.extra["n_planned"] == 3000
    assert meta.timing["n_ticks"] == 3000 and meta.timing["paced"] is False
    assert meta.timing["lateness_p99"] is None and meta.timing["compute_p99"] > 0
    assert np.all(np.isnan(ep.lateness)) and np.all(ep.compute_time > 0)
    assert result.metadata.status == "complete"


# --- pacing ------------------------------------------------------------------------------------


class SimClock:
    """A simulated clock for the loop's timing: ``sleep`` oversleeps as an OS does, stalls on request.

    Every reading advances it by ``step`` (so spin loops end); ``sleep(dt)`` advances it by
    ``dt + oversleep``, and by ``stall`` more on the sleep numbers listed in ``stall_at``.
    Timing properties are then asserted exactly, whatever the host machine's load.
    """

    def __init__(self, oversleep: float = 0.0, stall: float = 0.0, stall_at=(), step: float = 1e-6) -> None:
        self.now = 1000.0
        self.oversleep, self.stall, self.stall_at, self.step = oversleep, stall, set(stall_at), step
        self.sleeps = 0

    def perf_counter(self) -> float:
        self.now += self.step
        return self.now

    def sleep(self, dt: float) -> None:
        self.now += max(dt, 0.0) + self.oversleep + (self.stall if self.sleeps in self.stall_at else 0.0)
        self.sleeps += 1


def _use_clock(monkeypatch, clock: SimClock) -> None:
    """Run daq.loop (its tick clock and its deadline pacer) on ``clock``."""
    import types

    from qube_koopman.daq import loop, timing

    monkeypatch.setattr(loop, "time", types.SimpleNamespace(perf_counter=clock.perf_counter))
    monkeypatch.setattr(
        loop,
        "DeadlinePacer",
        lambda period, spin: timing.DeadlinePacer(period, spin, clock=clock.perf_counter, sleep=clock.sleep),
    )


def test_free_running_never_waits(monkeypatch):
    # Free-running means no pacer and no sleep in the loop's thread (counted, not timed).
    from qube_koopman.daq import loop

    pacers, sleeps, me = [], [], threading.get_ident()
    real_sleep = time.sleep
    monkeypatch.setattr(loop, "DeadlinePacer", lambda *a, **k: pacers.append(a))
    monkeypatch.setattr(
        time, "sleep", lambda dt: (sleeps.append(dt) if threading.get_ident() == me else None, real_sleep(dt))
    )
    backend = ScriptedBackend([(0.0, 0.01)] * 10)
    assert run_episode(backend, _plan(1000), [MemorySink()]).complete
    assert pacers == [] and sleeps == [] and len(backend.writes) == 1000 + 1  # and the final 0 V


class ClockedBackend(ScriptedBackend):
    """Notes the (simulated) time of every read."""

    def __init__(self, clock: SimClock, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.clock, self.read_at = clock, []

    def read(self):
        self.read_at.append(self.clock.now)
        return super().read()


def test_loop_paced_backend_keeps_absolute_deadlines(monkeypatch):
    # Every sleep overshoots by 0.5 ms (more than the spin covers) and one stalls 30 ms, on a
    # simulated clock: a relative schedule would end 250 x 0.5 ms + 30 ms = 155 ms late.
    clock = SimClock(oversleep=0.0005, stall=0.030, stall_at={100})
    _use_clock(monkeypatch, clock)
    backend = ClockedBackend(clock, [(0.0, 0.01)] * 10, pacing=Pacing.LOOP)
    sink = MemorySink()
    result = run_episode(backend, _plan(250), [sink])
    ep = sink.episodes[0].episode()
    ticks = np.asarray(backend.read_at[1:])  # read 0 is the start gate
    t0 = ticks[0] - ep.lateness[0]
    late = ticks - (t0 + 0.002 * np.arange(250))
    np.testing.assert_allclose(ep.lateness, late, atol=2e-5)  # the recorded lateness is the real one
    assert np.all(ep.lateness >= 0) and result.timing.paced and result.timing.n_ticks == 250
    # The stall makes a few ticks late; they follow back to back until the schedule is caught up.
    stalled = np.flatnonzero(ep.lateness > 0.001)
    assert 1 <= len(stalled) <= 16 and stalled[-1] - stalled[0] == len(stalled) - 1
    assert ep.lateness[-1] < 0.0006 and np.median(ep.lateness) < 0.0006, "the schedule drifted"


def test_a_spinning_paced_backend_never_sleeps_and_keeps_its_deadlines(monkeypatch):
    # A backend that asks to spin (qube-run --spin): the loop busy-waits every tick to its deadline
    # on the simulated clock, never asleep. Sleeps that overshoot by 0.5 ms make the sleeping loop's
    # ticks 0.2 ms late (past its 0.3 ms of spin); the spinning loop's are on time.
    for spin, slept, worst in ((True, False, (0.0, 5e-5)), (False, True, (1.5e-4, 2.5e-4))):
        clock = SimClock(oversleep=0.0005)
        _use_clock(monkeypatch, clock)
        backend = ClockedBackend(clock, [(0.0, 0.01)] * 10, pacing=Pacing.LOOP)
        backend.spin = spin
        sink = MemorySink()
        assert run_episode(backend, _plan(100), [sink]).complete
        late = sink.episodes[0].episode().lateness
        assert (clock.sleeps > 0) is slept and np.all(late >= 0), spin
        assert worst[0] <= late[1:].max() < worst[1], (spin, late.max())
        assert backend.describe()["spin"] is spin


def test_device_paced_backend_is_not_paced_by_the_loop(monkeypatch):
    clock = SimClock()
    _use_clock(monkeypatch, clock)

    class Device(ScriptedBackend):
        def read(self):
            clock.now += 0.001  # the device's clock: a sample every 1 ms
            return super().read()

    backend = Device([(0.0, 0.01)] * 10, pacing=Pacing.DEVICE)
    sink = MemorySink()
    result = run_episode(backend, _plan(100), [sink])
    ep = sink.episodes[0].episode()
    assert result.complete and np.all(np.isfinite(ep.lateness)) and clock.sleeps == 0
    # Samples came every 1 ms, faster than the nominal 2 ms, and the loop did not hold them back.
    np.testing.assert_allclose(ep.lateness[-1], -99 * 0.001, atol=5e-4)  # clock readings cost 1 us each


def test_device_clock_lateness_survives_a_late_start_and_a_passed_over_sample(monkeypatch):
    clock = SimClock()
    _use_clock(monkeypatch, clock)

    class Device(ScriptedBackend):
        """Ticks every 2 ms on its own clock; tick 0 is read 1 ms late, tick 40 is never read."""

        def __init__(self):
            super().__init__([(0.0, 0.01)] * 10, pacing=Pacing.DEVICE)
            self.t0 = None
            self.tick = -1

        def read(self):
            self.tick += 1 if self.tick != 39 else 2
            if self.t0 is None:
                self.t0 = clock.now
            clock.now = max(clock.now, self.t0 + self.tick * 0.002 + (0.001 if self.tick <= 1 else 0.0))
            return super().read()

        def device_time(self):
            return self.tick * 0.002

    backend = Device()
    sink = MemorySink()
    assert run_episode(backend, _plan(100), [sink]).complete
    late = sink.episodes[0].episode().lateness
    # Against k periods from the first read, ticks before the gap would read -1 ms and after it
    # +1 ms; against the device's clock, anchored on its earliest arrival, both are near zero.
    assert np.all(late >= 0)
    assert np.all(late[2:] < 1e-4), late


def test_stop_from_another_thread_ends_a_paced_episode():
    stop = StopRequest()
    timer = threading.Timer(0.1, stop.request, args=("operator pressed stop",))
    # Started at tick 0 (read 1; read 0 is the start gate), so about 50 ticks run.
    backend = ScriptedBackend([(0.0, 0.01)] * 10, pacing=Pacing.LOOP, on_read={1: timer.start})
    result = run_episode(backend, _plan(5000), [MemorySink()], stop=stop, handle_signals=False)
    timer.join()
    assert result.cause == "stop" and 10 < result.n_samples < 1000
    assert backend.writes[-1] == 0.0


def test_controller_must_match_the_backend():
    wrong = ControllerInfo(
        QUBE_PD.__class__(QUBE_PD.A, QUBE_PD.B, QUBE_PD.C, QUBE_PD.D, 0.01), "backward-euler", RIG_GAINS
    )
    with pytest.raises(ValueError, match="sample period"):
        run_episode(ScriptedBackend([(0.0, 0.0)]), EpisodePlan(wrong, _plan(5).excitation), [])


# --- a controller whose output is not a voltage --------------------------------------------------


def test_a_non_finite_controller_output_is_a_fault_with_zero_volts_applied_and_logged():
    # On every backend alike (the serial one: test_serial_backend.py), not left to the backend to refuse.
    backend = ScriptedBackend([(0.0, 0.01)] * 50)
    sink = MemorySink()
    plan = _plan(40)
    result = run_episode(backend, EpisodePlan(nan_controller(), plan.excitation, plan.excitation_info), [sink])
    assert result.status == "aborted" and result.cause == "fault"
    assert result.reason == "controller fault: its output is nan, not a voltage; 0 V applied"
    ep = sink.episodes[0].episode()
    assert ep.metadata.status_reason == result.reason and math.isnan(ep.control_output[-1])
    assert ep.plant_input[-1] == 0.0 and np.isfinite(ep.plant_input).all(), "the log holds what was applied"
    assert backend.writes[-1] == 0.0 and all(math.isfinite(v) for v in backend.writes) and backend.stopped == 1
    assert len(ep) == len(backend.writes) - 1 < 10  # the episode's commands, then stop()'s 0 V


def test_qube_run_on_the_simulator_fails_on_a_non_finite_controller_output(tmp_path, capsys):
    from qube_koopman.core.controller_file import write_controller_file
    from qube_koopman.daq.cli.run import main
    from qube_koopman.daq.log import read_episode

    path = write_controller_file(tmp_path / "F.toml", nan_controller().system)
    status = main(
        ["--controller", str(path), "--out", str(tmp_path / "out"), "--episodes", "1", "--duration", "1", "-q"]
    )
    err = capsys.readouterr().err
    assert status == 1 and "controller fault: its output is nan" in err and "Traceback" not in err
    ep = read_episode(next((tmp_path / "out").glob("*.mcap")))
    assert ep.plant_input[-1] == 0.0 and np.isfinite(ep.plant_input).all()
