"""The simulated QUBE-Servo as a backend: the ``sim.pendulum`` model behind the backend contract.

Each episode starts upright with a small seeded perturbation of the
pendulum angle, so the start gate (``|alpha| < 5 deg``) passes at once: a
simulated pendulum cannot be raised by hand. With ``start="hanging"`` it
starts hanging instead (the same perturbation about the bottom), for an
episode that swings it up (``qube-run --swing-up``). Measurements follow the
dataset's conventions (alpha = 0 upright, 2048-count encoders), with the
pendulum encoder's zero drawn a little off the true upright each episode as
on the rig (:class:`~sim.pendulum.ZeroOffsetDistribution`); the episode's
offset is recorded in the log's metadata (``extra.backend.sensor.alpha_offset``).

Time: each :meth:`SimBackend.write` holds the command for one sample period
and advances the model by it, so the next :meth:`SimBackend.read` returns
the encoders one period later, as on the rig (read, compute, write, wait).
Free-running, this runs as fast as the CPU allows; with ``realtime=True``
the backend asks the loop to pace ticks by wall-clock deadlines.
"""

from __future__ import annotations

import math
from dataclasses import asdict, replace

import numpy as np

from qube_koopman.daq.backends.contract import Backend, BackendFault, Pacing
from qube_koopman.sim.pendulum import (
    SAMPLE_PERIOD,
    CableRelaxation,
    PendulumParameters,
    PendulumSimulator,
    RandomLoad,
    SensorModel,
    ZeroOffsetDistribution,
)

__all__ = ["SimBackend", "DEFAULT_PERTURBATION", "STARTS"]

#: Largest initial ``|alpha|`` (rad) by default: well inside the 5 deg start gate.
DEFAULT_PERTURBATION = math.radians(2.0)

#: Where an episode's pendulum starts: upright (raised, as by hand) or hanging at rest (to be swung up).
STARTS = ("upright", "hanging")


class SimBackend(Backend):
    """The pendulum simulator behind the backend contract.

    Parameters
    ----------
    params : PendulumParameters
        Physical model.
    sensor : SensorModel
        Encoders (and optional noise).
    zero_offsets : ZeroOffsetDistribution or None
        Each episode's pendulum encoder zero offset is drawn from it (the
        rig's, by default); None keeps ``sensor.alpha_offset`` for every episode.
    perturbation : float
        Each episode starts at rest with alpha drawn uniformly from
        ``[-perturbation, perturbation]`` (rad) and theta = 0.
    seed : int, optional
        Seeds the perturbations and the sensor noise.
    realtime : bool
        Pace ticks like hardware (the loop's deadlines) instead of running
        as fast as possible.
    dt : float
        Sample period (s).
    start : {"upright", "hanging"}
        Where each episode's pendulum starts: upright (alpha = the perturbation), or hanging
        (alpha = pi + the perturbation) for an episode that swings it up.
    load : RandomLoad, optional
        A random torque on the arm (a plant file's ``[load]``); each episode's load has its own
        seed, drawn after the episode's other draws (so without a load every draw is as before),
        and the log records it (``extra.backend.load``). None: no load.
    spin : bool
        With ``realtime``, spin through each tick to its deadline instead of sleeping until shortly
        before it (:attr:`Backend.spin`).
    relaxation : CableRelaxation, optional
        The cables' torque that the arm's motion drives (a plant file's ``[relaxation]``); the log
        records it (``extra.backend.relaxation``). None: none.
    """

    name = "sim"
    # Set by the instance from ``realtime``.
    pacing = Pacing.NONE

    def __init__(
        self,
        params: PendulumParameters = PendulumParameters(),
        sensor: SensorModel = SensorModel(),
        zero_offsets: ZeroOffsetDistribution | None = ZeroOffsetDistribution(),
        perturbation: float = DEFAULT_PERTURBATION,
        seed: int | None = None,
        realtime: bool = False,
        dt: float = SAMPLE_PERIOD,
        start: str = "upright",
        load: RandomLoad | None = None,
        spin: bool = False,
        relaxation: CableRelaxation | None = None,
    ) -> None:
        if start not in STARTS:
            raise ValueError(f"start must be one of {', '.join(STARTS)}, got {start!r}")
        if not (math.isfinite(perturbation) and perturbation >= 0):
            raise ValueError(f"perturbation must be a non-negative angle in rad, got {perturbation!r}")
        self.params = params
        self.sensor = sensor
        self.zero_offsets = zero_offsets
        self.perturbation = float(perturbation)
        self.seed = seed
        self.realtime = bool(realtime)
        self.pacing = Pacing.LOOP if realtime else Pacing.NONE
        self.spin = bool(spin)
        self.sample_period = float(dt)
        self.start_at = start
        self._rng = np.random.default_rng(seed)
        noise_seed = int(self._rng.integers(2**63))
        self.load = load
        self._sim = PendulumSimulator(params, sensor, dt=dt, seed=noise_seed, load=load, relaxation=relaxation)
        self._y = self._sim.measurement
        self._initial_state = (0.0, 0.0, 0.0, 0.0)
        self._running = False

    def use_plant(self, params: PendulumParameters) -> None:
        """Simulate ``params`` from the next :meth:`start` on (a replayed log's own twin: its day's cables)."""
        self.params = params
        self._sim.params = params

    def use_load(self, load: RandomLoad | None) -> None:
        """Run with ``load`` on the arm from the next :meth:`start` on (a replayed log's day's load); None: none."""
        self.load = load
        self._sim.load = load

    @property
    def relaxation(self) -> CableRelaxation | None:
        """The cables' relaxation the twin runs with (None: none)."""
        return self._sim.relaxation

    def use_relaxation(self, relaxation: CableRelaxation | None) -> None:
        """Run with the cables' ``relaxation`` from the next :meth:`start` on (a replayed log's day's); None: none."""
        self._sim.relaxation = relaxation

    def start(self) -> None:
        """Reset the pendulum at rest, upright or hanging, with a fresh random perturbation and encoder zero."""
        alpha0, offset, load_seed = self._start_draws()
        if self.start_at == "hanging":
            alpha0 += math.pi
        self._initial_state = (0.0, alpha0, 0.0, 0.0)
        if offset is not None:
            self._sim.sensor = replace(self.sensor, alpha_offset=offset)
        self._y = self._sim.reset(self._initial_state, load_seed=load_seed)
        self._running = True

    def _start_draws(self) -> tuple[float, float | None, int | None]:
        """An episode's random start: its initial alpha, pendulum encoder zero (None: the sensor's) and
        load seed (None without a load: no draw, so a run without a load draws as before loads existed)."""
        alpha0 = float(self._rng.uniform(-self.perturbation, self.perturbation))
        offset = None if self.zero_offsets is None else self.zero_offsets.draw(self._rng)
        load_seed = None if self.load is None else int(self._rng.integers(2**63))
        return alpha0, offset, load_seed

    def skip_episode(self) -> None:
        """Make one episode's random draws without running it: the next :meth:`start` is the next episode's.

        A copy of the backend skipped past ``k`` episodes starts episode ``k`` exactly as the
        original does after running them (the same perturbation and encoder zero): how a worker
        process runs episode ``k`` of a run (:mod:`daq.parallel`).

        Raises
        ------
        ValueError
            For a noisy sensor (``sensor.noise_std > 0``): its noise stream runs on from one
            episode into the next, by as many ticks as each ran, so an episode's noise depends on
            how long the ones before it lasted.
        """
        if self.sensor.noise_std > 0:
            raise ValueError(
                "a noisy sensor's noise runs on from episode to episode (by as many ticks as "
                "each ran): its episodes can only run one after the other"
            )
        self._start_draws()

    def read(self) -> tuple[float, float]:
        """The encoders' (theta, alpha) at the current simulated time."""
        if not self._running:
            raise BackendFault("simulator read before start() or after stop()")
        return self._y

    def write(self, volts: float) -> None:
        """Hold ``volts`` for one sample period (advances the simulation)."""
        if not self._running:
            raise BackendFault("simulator written before start() or after stop()")
        try:
            self._y = self._sim.step(volts)
        except (ValueError, OverflowError) as exc:
            raise BackendFault(f"simulator step failed: {exc}") from exc

    def stop(self) -> None:
        """End the episode (the simulated motor simply stops being driven)."""
        self._running = False

    @property
    def state(self) -> np.ndarray:
        """The true simulated state (theta, alpha, theta_dot, alpha_dot)."""
        return self._sim.state

    def describe(self) -> dict:
        """Model, encoders (with this episode's zero offset), perturbation and initial state."""
        offsets = None if self.zero_offsets is None else asdict(self.zero_offsets)
        return {
            **super().describe(),
            "realtime": self.realtime,
            "seed": self.seed,
            "perturbation": self.perturbation,
            "start": self.start_at,
            "initial_state": list(self._initial_state),
            "params": asdict(self.params),
            "sensor": asdict(self._sim.sensor),
            "zero_offsets": offsets,
            "load": None if self.load is None else {**self.load.to_dict(), "seed": self._sim.load_seed},
            **({} if self.relaxation is None else {"relaxation": asdict(self.relaxation)}),
            "sample_period": self.sample_period,
        }
