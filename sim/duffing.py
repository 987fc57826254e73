"""The paper's simulated example: a Duffing oscillator under PI control.

Reproduces the experiment of paper section 4 as the reference code ran it:
forward Euler at 100 Hz, a ZOH-discretized PI controller
acting on the (noisy) measured position, a PRBS position reference with
random dwell, coloured measurement noise on the training episodes only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import signal

from qube_koopman.core.lti import DiscreteStateSpace

__all__ = [
    "DuffingParameters",
    "DuffingEpisode",
    "DuffingExperiment",
    "duffing_pi_controller",
    "random_dwell_prbs",
    "coloured_noise",
    "simulate_duffing_episode",
    "duffing_experiment",
]


@dataclass(frozen=True)
class DuffingParameters:
    """Duffing oscillator ``m x'' + b x' + k1 x + k2 x^3 = u`` (SI units).

    Parameters
    ----------
    mass : float
        ``m`` (kg).
    damping : float
        ``b`` (N s/m).
    stiffness : float
        ``k1`` (N/m).
    hardening : float
        ``k2`` (N/m^3).
    """

    mass: float = 0.01
    damping: float = 0.1
    stiffness: float = 0.02
    hardening: float = 0.4

    def acceleration(self, position, velocity, force):
        """Acceleration for the given state and force."""
        return (force - self.damping * velocity - self.stiffness * position - self.hardening * position**3) / self.mass


def duffing_pi_controller(dt: float = 0.01) -> DiscreteStateSpace:
    """The paper's PI controller ``K(s) = 1 + 1/s``, ZOH-discretized.

    The realization is the reference code's (A 1, B 1, C dt, D 1): the
    integrator state accumulates the error and C scales it by the period.
    """
    return DiscreteStateSpace(np.array([[1.0]]), np.array([[1.0]]), np.array([[dt]]), np.array([[1.0]]), dt)


def random_dwell_prbs(
    n_samples: int, rng: np.random.Generator, amplitude: float = 1.0, min_dwell: int = 29, max_dwell: int = 199
) -> np.ndarray:
    """Binary sequence of +-amplitude whose levels last a random number of samples.

    Each dwell is drawn uniformly from ``[min_dwell, max_dwell)`` samples and
    the starting level is random, as in the reference code (0.3 s .. 2 s at
    100 Hz).
    """
    if not 0 < min_dwell < max_dwell:
        raise ValueError(f"need 0 < min_dwell < max_dwell, got {min_dwell}, {max_dwell}")
    dwells = rng.integers(min_dwell, max_dwell, n_samples // min_dwell + 1)
    start_high = bool(rng.choice([True, False]))
    levels = np.where((np.arange(dwells.size) % 2 == 0) == start_high, amplitude, -amplitude)
    return np.repeat(levels, dwells)[:n_samples]


def coloured_noise(
    n_samples: int,
    rng: np.random.Generator,
    variance: float = 0.02,
    order: int = 12,
    cutoff_hz: float = 5.0,
    fs_hz: float = 100.0,
) -> np.ndarray:
    """White Gaussian noise of the given variance through a causal Butterworth low-pass."""
    white = rng.normal(0.0, np.sqrt(variance), n_samples)
    sos = signal.butter(order, cutoff_hz, btype="low", fs=fs_hz, output="sos")
    return signal.sosfilt(sos, white)


@dataclass(frozen=True, eq=False)
class DuffingEpisode:
    """One closed-loop episode; every array has one row per sample.

    ``measured`` is what the controller saw (position plus noise); identification
    uses it as the measured plant state.
    """

    t: np.ndarray
    reference: np.ndarray
    measured: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    force: np.ndarray
    controller_state: np.ndarray
    noisy: bool


def simulate_duffing_episode(
    reference: np.ndarray,
    controller: DiscreteStateSpace,
    noise: np.ndarray | None = None,
    params: DuffingParameters = DuffingParameters(),
) -> DuffingEpisode:
    """Simulate one episode from rest with forward Euler at the controller's period.

    At sample k the controller sees ``y_k = x_k + n_k``, outputs
    ``u_k = C xc_k + D (r_k - y_k)``, and both the controller and the plant
    advance one step with that error and force.
    """
    r = np.asarray(reference, dtype=float).reshape(-1)
    n = r.size
    noise = np.zeros(n) if noise is None else np.asarray(noise, dtype=float).reshape(-1)
    if noise.size != n:
        raise ValueError(f"noise has {noise.size} samples, reference has {n}")
    if controller.n_inputs != 1 or controller.n_outputs != 1:
        raise ValueError("the Duffing experiment needs a single-input single-output controller")
    dt = controller.dt
    Ac, Bc, Cc, Dc = controller.A, controller.B[:, 0], controller.C[0], controller.D[0, 0]
    pos = np.zeros(n)
    vel = np.zeros(n)
    force = np.zeros(n)
    xc = np.zeros((n, controller.n_states))
    state_c = np.zeros(controller.n_states)
    p = v = 0.0
    for k in range(n):
        pos[k], vel[k], xc[k] = p, v, state_c
        e = r[k] - (p + noise[k])
        u = float(Cc @ state_c) + Dc * e
        force[k] = u
        state_c = Ac @ state_c + Bc * e
        p, v = p + dt * v, v + dt * params.acceleration(p, v, u)
    return DuffingEpisode(
        t=np.arange(n) * dt,
        reference=r,
        measured=pos + noise,
        position=pos,
        velocity=vel,
        force=force,
        controller_state=xc,
        noisy=bool(np.any(noise)),
    )


@dataclass(frozen=True, eq=False)
class DuffingExperiment:
    """The paper's data set: noisy training episodes and a noise-free test episode.

    Parameters
    ----------
    train, test : list of DuffingEpisode
        The episodes.
    controller : DiscreteStateSpace
        The PI controller they ran under.
    params : DuffingParameters
        The oscillator.
    seed : int
        The seed everything was drawn from.
    """

    train: list[DuffingEpisode]
    test: list[DuffingEpisode]
    controller: DiscreteStateSpace
    params: DuffingParameters = field(default_factory=DuffingParameters)
    seed: int = 0


def duffing_experiment(
    seed: int = 1234,
    n_train: int = 10,
    n_test: int = 1,
    duration_s: float = 10.0,
    dt: float = 0.01,
    noise_variance: float = 0.02,
    params: DuffingParameters = DuffingParameters(),
) -> DuffingExperiment:
    """Generate the paper's Duffing data set (all randomness from ``seed``).

    Training episodes carry coloured measurement noise (the controller sees
    it); test episodes are noise-free.

    Parameters
    ----------
    seed : int
        The seed of every random draw.
    n_train, n_test : int
        Training and test episodes.
    duration_s : float
        Length of each episode (s).
    dt : float
        Sample period (s).
    noise_variance : float
        Variance of the training episodes' measurement noise.
    params : DuffingParameters
        The oscillator.

    Returns
    -------
    DuffingExperiment
    """
    if n_train < 1 or n_test < 0:
        raise ValueError(f"need at least one training episode, got n_train={n_train}, n_test={n_test}")
    rng = np.random.default_rng(seed)
    controller = duffing_pi_controller(dt)
    n = int(round(duration_s / dt))
    fs = 1.0 / dt
    episodes = []
    for i in range(n_train + n_test):
        reference = random_dwell_prbs(n, rng)
        noise = coloured_noise(n, rng, noise_variance, fs_hz=fs) if i < n_train else None
        episodes.append(simulate_duffing_episode(reference, controller, noise, params))
    return DuffingExperiment(
        train=episodes[:n_train], test=episodes[n_train:], controller=controller, params=params, seed=seed
    )
