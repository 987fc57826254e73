"""A stateful pendulum for a real-time loop: one call per 500 Hz tick.

Plain Python floats throughout: at this size numpy's per-call overhead
would cost more than the arithmetic.
"""

from __future__ import annotations

import math

import numpy as np

from qube_koopman.sim.pendulum.physics import (
    DEFAULT_SUBSTEPS,
    SAMPLE_PERIOD,
    Coefficients,
    PendulumParameters,
    advance,
    check_timing,
    hold_pattern,
    scalar_rk4,
)
from qube_koopman.sim.pendulum.load import LoadStream, RandomLoad
from qube_koopman.sim.pendulum.relaxation import CableRelaxation
from qube_koopman.sim.pendulum.sensor import SensorModel, encoder_angles

__all__ = ["PendulumSimulator"]

_NOISE_BLOCK = 4096


class PendulumSimulator:
    """The pendulum plus its encoders, advanced one sample at a time.

    ``y = sim.reset(x0)`` then, each tick, ``y = sim.step(u)``: the voltage
    is held over one sample period (as the amplifier holds the last command;
    after ``params.delay`` seconds, the commands before it are held until then)
    and the measurement of the state at the end of it is returned.

    Parameters
    ----------
    params : PendulumParameters
    sensor : SensorModel
    dt : float
        Sample period (s).
    n_substeps : int
        RK4 steps per sample.
    max_voltage : float or None
        Amplifier saturation (V); the QUBE-Servo 2's amplifier stops at 15 V.
        None for no limit.
    seed : int, optional
        Seed of the measurement noise.
    load : RandomLoad, optional
        A random torque on the arm (:mod:`~qube_koopman.sim.pendulum.load`); None: none, the
        arithmetic exactly as without one. Its samples restart from ``load_seed`` at each
        :meth:`reset`.
    load_seed : int
        The load's seed (:meth:`reset` takes a new one for each episode).
    relaxation : CableRelaxation, optional
        The cables' torque that the arm's own motion drives
        (:mod:`~qube_koopman.sim.pendulum.relaxation`), its element relaxed at each :meth:`reset`;
        settable between episodes (the attribute). None: none, the arithmetic exactly as without it.
    """

    def __init__(
        self,
        params: PendulumParameters = PendulumParameters(),
        sensor: SensorModel = SensorModel(),
        dt: float = SAMPLE_PERIOD,
        n_substeps: int = DEFAULT_SUBSTEPS,
        max_voltage: float | None = 15.0,
        seed: int | None = None,
        load: RandomLoad | None = None,
        load_seed: int = 0,
        relaxation: CableRelaxation | None = None,
    ) -> None:
        check_timing(dt, n_substeps)
        if max_voltage is not None and not (math.isfinite(max_voltage) and max_voltage > 0):
            raise ValueError(f"max_voltage must be positive or None, got {max_voltage!r}")
        self._params = params
        self._sensor = sensor
        self.dt = float(dt)
        self.n_substeps = int(n_substeps)
        self.max_voltage = math.inf if max_voltage is None else float(max_voltage)
        self._k = Coefficients.of(params)
        self._rk4 = scalar_rk4(self._k)
        self._h = self.dt / self.n_substeps
        self._whole, self._weights = hold_pattern(params.delay, self.dt, self.n_substeps)
        self._commands = [0.0] * (self._whole + 1)  # the last commands, oldest first (transport delay)
        self._rng = np.random.default_rng(seed)
        self._noise: list[float] = []
        self._noise_at = 0
        self._x = (0.0, 0.0, 0.0, 0.0)
        self._steps = 0
        self._load = load
        self._load_stream = None if load is None else LoadStream(load, self.dt, load_seed)
        self.relaxation = relaxation
        self._remembered = 0.0  # the relaxing element's memory of the arm's angle (relaxed at each reset)
        self._y = self._measure()

    @property
    def load(self) -> RandomLoad | None:
        """The random load on the arm (None: none); settable between episodes, from the next
        :meth:`reset` on (its ``load_seed``, else the current seed)."""
        return self._load

    @load.setter
    def load(self, load: RandomLoad | None) -> None:
        seed = 0 if self._load_stream is None else self._load_stream.seed
        self._load = load
        self._load_stream = None if load is None else LoadStream(load, self.dt, seed)

    @property
    def load_seed(self) -> int | None:
        """The seed of the current episode's load (None without a load)."""
        return None if self._load_stream is None else self._load_stream.seed

    def reset(self, state=(0.0, 0.0, 0.0, 0.0), load_seed: int | None = None) -> tuple[float, float]:
        """Set the state (theta, alpha, theta_dot, alpha_dot) and time zero; return its measurement.

        ``load_seed``: the new episode's load seed (a load restarts from it; None keeps the current
        seed and restarts its samples).
        """
        if self._load is not None:
            if load_seed is None:
                load_seed = 0 if self._load_stream is None else self._load_stream.seed
            self._load_stream = LoadStream(self._load, self.dt, load_seed)
        values = tuple(float(v) for v in np.asarray(state, dtype=float).reshape(-1))
        if len(values) != 4 or not all(math.isfinite(v) for v in values):
            raise ValueError(f"state must be 4 finite numbers (theta, alpha, theta_dot, alpha_dot), got {state!r}")
        self._x = values
        self._remembered = values[0]
        self._steps = 0
        self._commands = [0.0] * (self._whole + 1)
        self._y = self._measure()
        return self._y

    def step(self, voltage: float) -> tuple[float, float]:
        """Hold ``voltage`` for one sample period; return the measured (theta, alpha) after it."""
        v = float(voltage)
        if not math.isfinite(v):
            raise ValueError(f"voltage must be finite, got {voltage!r}")
        v = min(max(v, -self.max_voltage), self.max_voltage)
        commands = self._commands
        commands.append(v)
        torque = None if self._load_stream is None else self._load_stream.value
        relaxation = self.relaxation
        if relaxation is not None:  # the cables' relaxing torque, the arm's angle held over the step
            theta = self._x[0]
            extra = relaxation.torque(theta, self._remembered)
            torque = extra if torque is None else torque + extra
            self._remembered = relaxation.then(self._remembered, theta, self.dt)
        self._x = advance(
            self._x,
            commands[-self._whole - 2],
            commands[-self._whole - 1],
            self._weights,
            self._h,
            self._k,
            math.sin,
            math.cos,
            self._rk4,
            torque,
        )
        if self._load_stream is not None:
            self._load_stream.advance()
        del commands[0]
        self._steps += 1
        self._y = self._measure()
        return self._y

    def set_period(self, dt: float) -> None:
        """Change the sample period from the next step on, keeping the state and the last commands.

        For a plant stepped at the pace of something else's clock (the emulated
        bridge's ticks, a few cycles apart): the transport delay keeps its
        commands in flight, where a new simulator would start them from 0 V.
        """
        check_timing(dt, self.n_substeps)
        self.dt = float(dt)
        self._h = self.dt / self.n_substeps
        self._whole, self._weights = hold_pattern(self._params.delay, self.dt, self.n_substeps)
        if self._load_stream is not None:
            self._load_stream.set_period(self.dt)
        kept = self._commands[-(self._whole + 1) :]
        self._commands = [kept[0]] * (self._whole + 1 - len(kept)) + kept

    @property
    def params(self) -> PendulumParameters:
        """The model's parameters; settable between episodes (a replayed log's day's cables, say):
        the integrator's coefficients follow, the commands in flight start again from 0 V."""
        return self._params

    @params.setter
    def params(self, params: PendulumParameters) -> None:
        self._params = params
        self._k = Coefficients.of(params)
        self._rk4 = scalar_rk4(self._k)
        self._whole, self._weights = hold_pattern(params.delay, self.dt, self.n_substeps)
        self._commands = [0.0] * (self._whole + 1)

    @property
    def sensor(self) -> SensorModel:
        """The encoder model; settable between episodes (a new zero offset, say)."""
        return self._sensor

    @sensor.setter
    def sensor(self, sensor: SensorModel) -> None:
        if not isinstance(sensor, SensorModel):
            raise TypeError(f"sensor must be a SensorModel, got {type(sensor).__name__}")
        self._sensor = sensor

    @property
    def state(self) -> np.ndarray:
        """True state (theta, alpha, theta_dot, alpha_dot); alpha is not wrapped."""
        return np.array(self._x)

    @property
    def measurement(self) -> tuple[float, float]:
        """The last measurement returned."""
        return self._y

    @property
    def time(self) -> float:
        """Seconds since the last reset."""
        return self._steps * self.dt

    def _measure(self) -> tuple[float, float]:
        theta, alpha = self._x[0], self._x[1] + self._sensor.alpha_offset
        if self._sensor.noise_std > 0:
            theta += self._next_noise()
            alpha += self._next_noise()
        return encoder_angles(theta, alpha, self._sensor.counts_per_rev, math.floor)

    def _next_noise(self) -> float:
        # Drawn in blocks: one Generator call per sample would cost microseconds.
        if self._noise_at == len(self._noise):
            self._noise = self._rng.normal(0.0, self._sensor.noise_std, _NOISE_BLOCK).tolist()
            self._noise_at = 0
        self._noise_at += 1
        return self._noise[self._noise_at - 1]
